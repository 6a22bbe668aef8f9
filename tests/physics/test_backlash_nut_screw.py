"""backlash against a stepwise nut-and-screw simulation (tests/physics/nut_screw.py)."""

import numpy as np
import pytest

from bayescal.diagnose import diagnose
from bayescal.effects.backlash import play_operator
from bayescal.machines.files import machine_from_text
from bayescal.simulate import draw_poses, measure
from tests.physics.nut_screw import LostMotion, NutScrew
from tests.physics.statics_3prs import random_prs3_text


def test_nut_lags_the_screw_by_hand():
    drive = NutScrew([40.0])  # 40 um clearance, nut centred
    path = np.array([[0.0], [1.0], [0.99], [0.97], [0.5], [0.5], [0.51], [2.0]])
    y = drive.run(path, np.ones(len(path), bool))[:, 0]
    expected = [
        0.0,            # start: centred in the clearance
        1.0 - 0.02,     # moved up: dragged by the lower flank, 20 um behind
        0.98,           # 10 um back: inside the clearance, the nut stays
        0.98,           # 30 um back in all: still inside the 40 um clearance
        0.5 + 0.02,     # down: the other flank has it, 20 um above the screw (behind)
        0.52,           # no move: nothing changes
        0.52,           # 10 um up: inside the clearance again
        2.0 - 0.02,     # up: behind by 20 um below
    ]
    np.testing.assert_allclose(y, expected, atol=1e-12)


def test_play_operator_equals_the_stepwise_nut(rng):
    # small and large moves, reversals shorter than the band, pauses: the effect's operator is exact
    b = np.array([25.0, 60.0, 5.0])
    steps = rng.choice([-1.0, 1.0], (300, 3)) * np.exp(rng.uniform(np.log(1e-3), np.log(0.5), (300, 3)))
    steps[rng.random((300, 3)) < 0.05] = 0.0
    x = 500.0 + np.cumsum(steps, axis=0)
    y = NutScrew(b).run(x, np.ones(len(x), bool))
    dq, der = play_operator(x, 0.5e-3 * b)
    np.testing.assert_allclose(dq, y - x, atol=1e-12)
    # its derivative by the half band: finite differences
    h = 1e-7
    fd = (play_operator(x, 0.5e-3 * b + h)[0] - play_operator(x, 0.5e-3 * b - h)[0]) / (2 * h)
    np.testing.assert_allclose(der, fd, atol=1e-6)


def test_unknown_first_gap_matters_only_until_the_band_is_crossed(rng):
    b = np.array([40.0, 40.0, 40.0])
    x = 500.0 + np.cumsum(rng.uniform(-5, 5, (50, 3)), axis=0)  # moves of mm, far beyond the band
    y = NutScrew(b, initial_gap_um=[20.0, -20.0, 7.0]).run(x, np.ones(50, bool))
    dq, _ = play_operator(x, 0.5e-3 * b)
    np.testing.assert_allclose((y - x)[1:], dq[1:], atol=1e-12)
    np.testing.assert_allclose((y - x)[0], [-0.02, 0.02, -0.007], atol=1e-12)  # the history the model cannot know
    assert np.all(dq[0] == 0.0)


def _recording(seed, n=80, via=None):
    rng = np.random.default_rng(seed)
    m = machine_from_text(random_prs3_text(rng), f"random-{seed}.toml")
    theta = rng.normal(size=m.n_params) * m.tolerance
    q = draw_poses(m, n, rng, theta)
    b = rng.uniform(15.0, 60.0, 3)
    rec = measure(m, q, theta, int(rng.choice([6, 3])), rng, effects=[LostMotion(b, rng, via=via)])
    return m, rec, b


@pytest.mark.parametrize("seed", [4, 9])
def test_nut_screw_recordings_are_fitted_with_positive_dead_bands(seed):
    m, rec, b = _recording(seed)
    d = diagnose(m, rec, seed=1, n_perm=19)
    assert d.verdict == "backlash" and d.selected[0] == "backlash"
    trial = next(e for e in d.effects if e.name == "backlash")
    for p, truth in zip(trial.parameters, b):
        assert p.value > 0
        assert abs(p.value - truth) < 4 * p.std, (p, truth)
    assert d.p_final > 1e-3


def test_unidirectional_approach_is_a_constant_offset_not_backlash():
    # every pose approached from above (a retract above the stroke between poses): the nut always sits
    # b/2 above the screw, a constant the actuator zero absorbs; the recording cannot show the band
    def via(a, b):
        return [np.maximum(a, b) + 2.0]

    m, rec, _ = _recording(4, via=via)
    d = diagnose(m, rec, seed=1, n_perm=19)
    assert "backlash" not in d.selected
    assert d.verdict == "none"


def test_a_negative_band_is_the_odd_extension_with_a_consistent_derivative(rng):
    # a fit's iterate can go below zero (the bound is not enforced, docs/diagnose.md "Physical signs"): clamped at
    # zero, the value stopped moving while the derivative said -1/+1 (finite differences about 0 against -4.68 in
    # a stalled backlash fit), so Gauss-Newton's step was no descent direction there
    x = 500.0 + np.cumsum(rng.uniform(-0.05, 0.05, (80, 3)), axis=0)  # short moves: reversals inside the band too
    h_pos = np.array([0.02, 0.01, 0.005])
    for half in (-h_pos, np.array([-0.02, 0.01, -1e-9])):
        dq, der = play_operator(x, half)
        np.testing.assert_allclose(dq, -play_operator(x, np.abs(half))[0] * (half < 0) + dq * (half >= 0), atol=1e-15)
        step = 1e-7
        fd = (play_operator(x, half + step)[0] - play_operator(x, half - step)[0]) / (2 * step)
        away = np.abs(half) > 10 * step  # not across zero, where the odd extension has a kink after short moves
        np.testing.assert_allclose(der[:, away], fd[:, away], atol=1e-6)
