"""gravity_backlash against a stepwise simulation of masses on joints with play (not the effect's own formula).

The simulation moves each drive from pose to pose in steps of a twentieth
of the half band; after every step the joint is pushed by the flanks of its
dead band and, where its gravity load (computed here in closed form from the
pendulum or the inclined slider, at the joint's own position) exceeds what
friction holds, slides to the flank on the side gravity pushes.  The load
can change sign in the middle of a move; the effect only looks at the
commanded poses.
"""

import numpy as np
import pytest

from bayescal.effects import check_effect, get_effect
from bayescal.effects.gravity_backlash import gravity_play
from bayescal.machines.files import load_machine, machine_from_text
from pathlib import Path

G = 9.80665
ROOT = Path(__file__).resolve().parents[2]

PENDULUM = """
kind = "serial"
[[joint]]
type = "revolute"
origin = [0.0, 0.0, 500.0]
axis = [0.0, 1.0, 0.0]
[tool]
point = [400.0, 0.0, 0.0]
[workspace]
q_limits = [[-3.0, 3.0]]
"""

BOOM = """
kind = "serial"
[[joint]]
type = "revolute"
origin = [0.0, 0.0, 800.0]
axis = [0.0, 1.0, 0.0]
[[joint]]
type = "prismatic"
origin = [100.0, 0.0, 0.0]
axis = [1.0, 0.0, 0.0]
[tool]
point = [50.0, 0.0, 0.0]
[workspace]
q_limits = [[-1.2, 1.2], [0.0, 600.0]]
"""


def stepwise(x: np.ndarray, h: np.ndarray, hold: np.ndarray, load, coarse: np.ndarray) -> np.ndarray:
    """Joint minus drive position after each commanded pose, by quasi-static steps along straight moves.

    Steps are ``coarse`` per drive (small enough not to jump across the
    band between 1 and 1.5 times the holding load), and a fifth of the half
    band of every drive whose load is below 1.5 times what friction holds
    (where the gravity side can change); plain floats, for speed.
    """
    x = np.asarray(x, float)
    m = x.shape[1]
    h, hold, coarse = [list(map(float, v)) for v in (h, hold, coarse)]
    y = list(map(float, x[0]))
    tau = load(y)
    y = [x[0][j] + h[j] * np.sign(tau[j]) if abs(tau[j]) > hold[j] else y[j] for j in range(m)]
    out = [[y[j] - x[0][j] for j in range(m)]]
    for a, b in zip(x[:-1], x[1:]):
        a, b = list(map(float, a)), list(map(float, b))
        span = [abs(b[j] - a[j]) for j in range(m)]
        s = 0.0
        while s < 1.0:
            near = [abs(t) < 1.5 * hj for t, hj in zip(load(y), hold)]
            ds = min([coarse[j] / span[j] for j in range(m) if span[j] > 0]
                     + [0.2 * h[j] / span[j] for j in range(m) if span[j] > 0 and near[j]] + [1.0])
            s = min(1.0, s + ds)
            xd = [a[j] + s * (b[j] - a[j]) for j in range(m)]
            y = [min(max(y[j], xd[j] - h[j]), xd[j] + h[j]) for j in range(m)]  # the flanks push
            tau = load(y)  # at the joints' own positions
            y = [xd[j] + h[j] * np.sign(tau[j]) if abs(tau[j]) > hold[j] else y[j] for j in range(m)]  # gravity beats friction
        out.append([y[j] - b[j] for j in range(m)])
    return np.array(out)


def _session(rng, lo, hi, h, n):
    """Random poses, with short reversals (under the band) and repeated poses mixed in."""
    x = [rng.uniform(lo, hi)]
    for _ in range(n - 1):
        r = rng.random()
        if r < 0.2:
            x.append(x[-1] + rng.choice([-1, 1]) * rng.uniform(0.2, 1.5) * 2 * h)
        elif r < 0.25:
            x.append(x[-1].copy())
        else:
            x.append(rng.uniform(lo, hi))
        x[-1] = np.clip(x[-1], lo, hi)
    return np.array(x)


def test_a_pendulum_with_play_takes_it_up_on_the_gravity_side():
    m = machine_from_text(PENDULUM, "pendulum.toml")
    rng = np.random.default_rng(5)
    mass, r = 12.0, 0.25  # kg, m: centre of mass 250 mm out along the link
    h = np.array([1.5e-3])  # rad: a 3 mrad dead band
    hold = np.array([1.0])  # N m
    q = _session(rng, np.array([-3.0]), np.array([3.0]), h, 80)
    # closed form: rotation about +y turns the link from +x towards -z; V = -m g r sin(y), tau = -dV/dy
    sim = stepwise(q, h, hold, lambda y: [mass * G * r * np.cos(y[0])], coarse=[0.01])
    eff = get_effect("gravity_backlash", link_mass_kg=[mass], link_com_mm=[[1000 * r, 0.0, 0.0]], holding_load=hold)
    f = eff.features(m, q, np.zeros(m.n_params), {}, None, None)
    got = eff.delta_q(f, [2e6 * h[0]])  # backlash.q1 = full band, urad
    # both sides occur, and both the gravity side and the approach side are exercised
    assert np.any(sim > 0) and np.any(sim < 0) and np.any(f.per_pose["side"] == 0)
    np.testing.assert_allclose(got, sim, atol=1e-9)
    # the approach alone (backlash) would be wrong on about half the poses
    plain = get_effect("backlash")
    wrong = np.abs(plain.delta_q(plain.features(m, q, np.zeros(m.n_params), {}, None, None), [2e6 * h[0]]) - sim) > 1e-6
    assert wrong.mean() > 0.2


def test_a_slider_on_a_tilting_boom_and_the_boom_joint():
    m = machine_from_text(BOOM, "boom.toml")
    rng = np.random.default_rng(8)
    m1, c1 = 30.0, 0.3  # kg, m: boom housing centre of mass 300 mm out
    m2, c2 = 15.0, 0.05  # kg, m: the slider's, 50 mm beyond its frame
    h = np.array([1.0e-3, 0.05])  # rad, mm
    hold = np.array([2.0, 5.0])  # N m, N
    q = _session(rng, np.array([-1.2, 0.0]), np.array([1.2, 300.0]), h, 60)

    def load(y):
        # boom angle y0 about +y (from +x towards -z), slider at 100 + y1 mm along the boom
        arm2 = (100.0 + y[1]) / 1000 + c2
        tau0 = G * np.cos(y[0]) * (m1 * c1 + m2 * arm2)  # N m
        f1 = m2 * G * np.sin(y[0])  # N along the boom
        return [tau0, f1]

    sim = stepwise(q, h, hold, load, coarse=[0.005, 2.0])
    eff = get_effect("gravity_backlash", link_mass_kg=[m1, m2], link_com_mm=[[1000 * c1, 0, 0], [1000 * c2 - 0.0, 0, 0]],
                     holding_load=hold)
    # link 2's frame is the slider's after the motion (origin at 100 + q2 along the boom): its centre 50 mm beyond
    f = eff.features(m, q, np.zeros(m.n_params), {}, None, None)
    got = eff.delta_q(f, [2e6 * h[0], 2e3 * h[1]])
    side = f.per_pose["side"]
    assert np.any(side[:, 1] > 0) and np.any(side[:, 1] < 0) and np.any(side[:, 1] == 0)
    np.testing.assert_allclose(got, sim, atol=1e-9)


def test_operator_pieces():
    # gravity side wins over the approach; held poses keep the last move's lag; the first pose is centred
    x = np.array([[0.0], [1.0], [0.9995], [2.0], [1.0]])
    side = np.array([[0], [0], [0], [1], [0]], float)
    y, d = gravity_play(x, side, np.array([0.01]))
    np.testing.assert_allclose(y[:, 0], [0.0, -0.01, -0.0095, 0.01, 0.01])
    np.testing.assert_allclose(d[:, 0], [0.0, -1.0, -1.0, 1.0, 1.0])


@pytest.mark.parametrize("path", ["telescope", "arm6"])
def test_interface(path):
    m = load_machine(ROOT / "examples" / path / "machine.toml")
    check_effect(get_effect("gravity_backlash"), m)


def test_a_negative_band_is_the_odd_extension_with_a_consistent_derivative():
    # as the approach-direction play operator (tests/physics/test_backlash_nut_screw.py): a fit's iterate below
    # zero must see a derivative that is the value's
    rng = np.random.default_rng(4)
    x = 100.0 + np.cumsum(rng.uniform(-0.05, 0.05, (60, 2)), axis=0)
    side = rng.choice([-1.0, 0.0, 1.0], size=(60, 2))
    half = np.array([-0.02, 0.01])
    out, der = gravity_play(x, side, half)
    np.testing.assert_allclose(out[:, 0], -gravity_play(x, side, np.abs(half))[0][:, 0], atol=1e-15)
    step = 1e-7
    fd = (gravity_play(x, side, half + step)[0] - gravity_play(x, side, half - step)[0]) / (2 * step)
    np.testing.assert_allclose(der, fd, atol=1e-6)
