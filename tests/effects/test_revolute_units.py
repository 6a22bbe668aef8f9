"""Effect units and pitch bands follow the actuator kind (mm / um on sliders, rad / urad on revolute joints)."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.diagnose import diagnose
from bayescal.effects import get_effect
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.machines.base import ACTUATOR_UNITS
from bayescal.simulate import draw_errors, draw_poses, measure

ROOT = Path(__file__).resolve().parents[2]


def _positioner():
    """The two-axis positioner example (two revolute joints) with a better instrument and the default tolerances."""
    text = (ROOT / "examples" / "positioner" / "machine.toml").read_text()
    head = text.split("[measurement]")[0]
    return machine_from_text(
        head + "[measurement]\nsigma_position = 0.01\nsigma_angle = 2.0e-5\n\n"
        "[workspace]\nq_limits = [[-0.6, 0.6], [-3.1, 3.1]]\n",
        "positioner-test.toml",
    )


def _units(machine, name, aux):
    eff = get_effect(name)
    q = draw_poses(machine, 30, np.random.default_rng(0))
    f = eff.features(machine, q, np.zeros(machine.n_params), aux, None, machine.forward(q))
    return {p.name: p.unit for p in eff.params(machine, f)}


def test_units_follow_the_actuator_unit():
    pos = _positioner()
    assert pos.actuator_units == ("rad", "rad")
    assert [u.small for u in pos.actuator_unit_info] == ["urad", "urad"]
    assert _units(pos, "backlash", {}) == {"backlash.q1": "urad", "backlash.q2": "urad"}
    spe = _units(pos, "screw_periodic_error", {})
    assert spe["pitch"] == "rad" and spe["sin.q1"] == "urad" and spe["cos.q2"] == "urad"
    t = np.arange(30.0) * 30
    th = _units(pos, "thermal_expansion", {"temp_C": 20 + t / 300})
    assert th["drift.q1"] == "urad/K" and th["alpha.q2"] == "urad/rad/K"
    tt = _units(pos, "thermal_expansion", {"time_s": t})
    assert tt["shift.q1"] == "urad" and tt["strain.q2"] == "urad/rad" and tt["tau"] == "s"
    # a prismatic machine keeps its units
    prs = load_machine(ROOT / "examples" / "prs3" / "machine.toml")
    assert set(_units(prs, "backlash", {}).values()) == {"um"}
    spe = _units(prs, "screw_periodic_error", {})
    assert spe["pitch"] == "mm" and spe["sin.q1"] == "um"


def test_a_dead_band_in_urad_moves_the_joint_by_microradians():
    # the effect's dq is in rad: 400 urad of dead band is +-200e-6 rad after a move
    pos = _positioner()
    eff = get_effect("backlash")
    q = np.array([[0.0, 0.0], [0.1, 0.2], [0.05, 0.3]])
    f = eff.features(pos, q, np.zeros(pos.n_params), {}, None, None)
    dq = eff.delta_q(f, np.array([400.0, 400.0]))
    np.testing.assert_allclose(dq, [[0.0, 0.0], [-2e-4, -2e-4], [2e-4, -2e-4]], atol=1e-15)
    assert ACTUATOR_UNITS["rad"].small_to_q == 1e-6 and ACTUATOR_UNITS["mm"].small_to_q == 1e-3


class _GearError:
    """Independent of the effect's code: each joint's angle errs by a_i sin(2 pi q_i / p + phi_i) (rad)."""

    def __init__(self, amp_urad, pitch_rad, phase):
        self.a, self.p, self.phi = 1e-6 * np.asarray(amp_urad), pitch_rad, np.asarray(phase)

    def transform(self, q, theta, aux, order):
        return q + self.a * np.sin(2 * np.pi * q / self.p + self.phi), theta


class _TiltError:
    """Outside the library: the tilt joint's angle errs smoothly with the tilt, ``c f(q1)`` (rad)."""

    def __init__(self, c_rad, shape):
        self.c, self.f = c_rad, shape

    def transform(self, q, theta, aux, order):
        out = np.array(q, float, copy=True)
        out[:, 0] += self.c * self.f(out[:, 0])
        return out, theta


def _recording(machine, effect, seed=3, n=160):
    rng = np.random.default_rng(seed)
    theta = draw_errors(machine, rng)
    q = draw_poses(machine, n, rng, theta)
    return measure(machine, q, theta, 6, rng, effects=[effect])


def test_gear_periodic_error_on_revolute_joints_is_named_in_rad_and_urad():
    pos = _positioner()
    pitch = 2 * np.pi / 40  # a 40-tooth mesh: 0.157 rad
    amp = np.array([150.0, 250.0])  # urad
    rec = _recording(pos, _GearError(amp, pitch, [0.4, 2.0]))
    d = diagnose(pos, rec, seed=1)
    assert d.verdict == "screw_periodic_error"
    got = {p.name: p for p in next(e for e in d.effects if e.name == "screw_periodic_error").parameters}
    assert got["pitch"].unit == "rad" and got["sin.q1"].unit == "urad"
    assert abs(got["pitch"].value - pitch) < 4 * got["pitch"].std
    for i in (1, 2):
        a = np.hypot(got[f"sin.q{i}"].value, got[f"cos.q{i}"].value)
        sd = max(got[f"sin.q{i}"].std, got[f"cos.q{i}"].std)
        assert abs(a - amp[i - 1]) < 4 * sd, (i, a, amp[i - 1], sd)


@pytest.mark.parametrize("shape", [lambda q1: np.sin(2 * q1), lambda q1: q1**2], ids=["sin2q1", "q1sq"])
def test_smooth_tilt_dependent_error_is_not_a_periodic_gear_error(shape):
    # 300 urad smooth in the tilt (+-0.6 rad): with the screws' band of 1-50 (mm, read as rad) and the turntable's
    # 6.2 rad stroke admitting pitches up to 3.1, both were named screw_periodic_error with a "pitch" of 2.5-3 "mm";
    # on revolute joints the band is now gear teeth, 0.01-0.5 rad
    pos = _positioner()
    d = diagnose(pos, _recording(pos, _TiltError(3e-4, shape)), seed=1)
    assert d.verdict != "screw_periodic_error"
    for spe in (e for e in d.effects if e.name == "screw_periodic_error"):  # fitted unless skipped (its reason in d.skipped)
        assert spe.parameters[0].unit == "rad" and spe.parameters[0].value <= 0.5 * 1.001
    periodic = [ch for ch in d.location.channels if ch.kind == "periodic"]
    assert len(periodic) == 2 and all(ch.detail.endswith(" rad") for ch in periodic)


def test_mixed_drives_get_their_own_units_and_no_shared_pitch():
    # a 3-PRS head over a turntable: three sliders and one revolute joint
    m = load_machine(ROOT / "examples" / "hybrid_table" / "machine.toml")
    assert m.actuator_units == ("mm", "mm", "mm", "rad")
    assert list(_units(m, "backlash", {}).values()) == ["um", "um", "um", "urad"]
    why = get_effect("screw_periodic_error").not_applicable(m, {})
    assert why is not None and "both prismatic (mm) and revolute (rad)" in why
