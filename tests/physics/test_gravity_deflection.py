"""gravity_deflection against an independent multi-body statics simulation (tests/physics/beam_statics.py).

The simulator composes docs/formats.md section 5's transforms itself (mimic joints
included), cuts every member into 400 elements and turns everything beyond
each element by the moment of the loads beyond it in the already deflected
configuration; it never calls the effect, the machine's kinematics or any
closed-form beam formula.  Random chains (telescopic columns with a mimic
stage, a turning boom and wrist; the 6R arm), random masses and centres of
mass, payloads and gravity tilted up to 20 degrees.
"""

import numpy as np
import pytest

from bayescal.effects import check_effect, get_effect
from bayescal.effects.gravity_deflection import FLEX_PER_BENDING, member_response
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.simulate import draw_errors
from tests.physics.beam_statics import Member, MimicChain, deflected_tool, generalized_gravity, rotvec

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ARM6 = ROOT / "examples" / "arm6" / "machine.toml"
TELESCOPE = ROOT / "examples" / "telescope" / "machine.toml"


def _tilted(rng, max_deg):
    axis = rng.normal(size=3)
    axis[2] = 0.0
    axis /= np.linalg.norm(axis)
    a = np.radians(rng.uniform(0.3, 1.0) * max_deg)
    return np.cos(a) * np.array([0.0, 0.0, -1.0]) + np.sin(a) * axis


def _column_text(rng) -> str:
    """A telescopic column (a mimic upper stage), a bracket, a turning boom and a belt-coupled wrist, at random."""
    f = lambda v: "[" + ", ".join(repr(float(x)) for x in v) + "]"  # noqa: E731
    tilt = rng.normal(0, 0.05, 3)
    return f"""
kind = "serial"
[[joint]]
type = "prismatic"
origin = {f(rng.uniform(-100, 100, 3))}
rpy = {f(tilt)}
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "prismatic"
origin = [0.0, 0.0, {rng.uniform(20, 80)!r}]
axis = [0.0, 0.0, 1.0]
mimic = 1
multiplier = {rng.uniform(0.6, 1.4)!r}
offset = {rng.uniform(0, 40)!r}
[[joint]]
type = "revolute"
origin = {f([rng.uniform(50, 120), 0.0, rng.uniform(0, 40)])}
rpy = {f(rng.normal(0, 0.05, 3))}
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "revolute"
origin = {f([rng.uniform(300, 700), rng.uniform(-50, 50), rng.uniform(-30, 30)])}
rpy = [1.5707963267948966, 0.0, 0.0]
axis = [0.0, 0.0, 1.0]
mimic = 3
multiplier = {rng.uniform(-1.0, 1.0)!r}
offset = {rng.uniform(-0.5, 0.5)!r}
[tool]
point = {f([rng.uniform(50, 200), rng.uniform(-30, 30), rng.uniform(-30, 30)])}
[workspace]
q_limits = [[50.0, 1200.0], [-3.0, 3.0]]
"""


def _compare(m, theta, q, members_sim, bending, mass, com, down, payload, n_elements=100):
    """The effect's dx against the simulator's deflected tool, pose by pose; returns (effect dx, simulated dx)."""
    eff = get_effect("gravity_deflection", link_mass_kg=mass, link_com_mm=com, gravity=down)
    aux = {"payload_kg": payload}
    f = eff.features(m, q, theta, aux, None, None)
    names = [p.name for p in eff.params(m, f)]
    eta = np.array([bending.get(nm, 0.0) for nm in names])
    got = eff.delta_x(f, eta)
    chain = MimicChain.from_text(m.to_toml(theta))
    sim = np.zeros_like(got)
    for i in range(q.shape[0]):
        p0, R0, p1, R1 = deflected_tool(chain, q[i], members_sim, mass, com, down, payload[i], n_elements)
        sim[i, :3] = p1 - p0
        sim[i, 3:] = rotvec(R1 @ R0.T)
    return got, sim, names


def _column_case(seed: int, n: int):
    """A random column (:func:`_column_text`), geometry, ``n`` poses, masses, tilted gravity, payloads, and its
    bending compliances (um/N at 1 m) with the simulator's members of the same stiffness."""
    rng = np.random.default_rng(seed)
    m = machine_from_text(_column_text(rng), f"column{seed}.toml")
    theta = draw_errors(m, rng)
    q = m.sample_q(n, rng)
    mass = rng.uniform(2.0, 60.0, 4)
    com = rng.uniform(-150.0, 150.0, (4, 3))
    down = _tilted(rng, 20.0)
    payload = rng.uniform(0.0, 30.0, n)
    b_col, b_boom = rng.uniform(0.05, 0.3), rng.uniform(0.2, 1.0)
    EI_col, EI_boom = 1e12 / (3 * b_col), 1e12 / (3 * b_boom)
    members = [Member("stage", 0, EI_col), Member("stage", 1, EI_col), Member("link", 2, EI_boom)]
    return m, theta, q, mass, com, down, payload, {"bending.joint1": b_col, "bending.link3": b_boom}, members


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_column_boom_and_wrist_bend_as_the_element_by_element_statics(seed):
    m, theta, q, mass, com, down, payload, bending, members = _column_case(seed, 6)
    got, sim, names = _compare(m, theta, q, members, bending, mass, com, down, payload)
    assert names == ["bending.joint1", "bending.link3", "gravity.tilt_1", "gravity.tilt_2"]
    # 0.1-1 mm at the tool; the linear model within 0.3 % of the largest (discretisation and second order: at 10 mm
    # on these 1.5 m structures the simulator's geometric nonlinearity alone is 0.7 %)
    assert np.abs(sim[:, :3]).max() > 0.1
    np.testing.assert_allclose(got[:, :3], sim[:, :3], atol=3e-3 * np.abs(sim[:, :3]).max())
    np.testing.assert_allclose(got[:, 3:], sim[:, 3:], atol=3e-3 * np.abs(sim[:, 3:]).max())


@pytest.mark.parametrize("seed", [3, 4])
def test_sensor_bodies_turn_as_the_element_by_element_statics(seed):
    # tilt sensors on the column's stages, the bracket and the wrist: each body's turn under the bending
    # (what its sensor reads) against the simulator's frames, followed element by element
    m, theta, q, mass, com, down, payload, bending, members = _column_case(seed, 5)
    eff = get_effect("gravity_deflection", link_mass_kg=mass, link_com_mm=com, gravity=down)
    bodies = ("joint1", "joint2", "joint3", "joint4")
    aux = {"payload_kg": payload} | {f"accel.{b}.{a}": np.ones(5) for b in bodies for a in "xyz"}
    f = eff.features(m, q, theta, aux, None, None)
    names = [p.name for p in eff.params(m, f)]
    eta = np.array([bending.get(nm, 0.0) for nm in names])
    got = eff.body_rotation(f, eta)
    assert tuple(got) == bodies
    chain = MimicChain.from_text(m.to_toml(theta))
    sim = np.array([deflected_tool(chain, q[i], members, mass, com, down, payload[i], 100, bodies=(0, 1, 2, 3))[4]
                    for i in range(q.shape[0])])  # (n, 4, 3)
    for s_, b in enumerate(bodies):
        np.testing.assert_allclose(got[b], sim[:, s_], atol=3e-3 * np.abs(sim).max())
    # the column's lower stage turns its own frame (at its tip) and every body above it; the boom's bending
    # turns the wrist, not the boom's own frame (at its root)
    assert np.abs(sim[:, 0]).max() > 1e-4 and np.abs(sim[:, 3] - sim[:, 2]).max() > 1e-4
    # the tool turns as the wrist's body does (nothing bends beyond the wrist)
    np.testing.assert_allclose(eff.delta_x(f, eta)[:, 3:], got["joint4"], atol=1e-12)


def test_arm_links_bend_as_the_element_by_element_statics():
    rng = np.random.default_rng(7)
    m = load_machine(ARM6)
    theta = draw_errors(m, rng)
    q = m.sample_q(5, rng)
    mass = rng.uniform(0.5, 9.0, 6)
    com = rng.uniform(-150.0, 150.0, (6, 3))
    down = _tilted(rng, 15.0)
    payload = rng.uniform(0.0, 10.0, 5)
    b = {"bending.link2": 12.0, "bending.link3": 20.0}
    members = [Member("link", 1, 1e12 / (3 * 12.0)), Member("link", 2, 1e12 / (3 * 20.0))]
    got, sim, names = _compare(m, theta, q, members, b, mass, com, down, payload)
    assert names[:2] == ["bending.link2", "bending.link3"]
    assert np.abs(sim[:, :3]).max() > 0.01
    np.testing.assert_allclose(got[:, :3], sim[:, :3], atol=3e-3 * np.abs(sim[:, :3]).max())
    np.testing.assert_allclose(got[:, 3:], sim[:, 3:], atol=3e-3 * np.abs(sim[:, 3:]).max())


def test_cantilever_closed_forms():
    # a horizontal cantilever along +x, 1 m, flexibility 1/(E I) = 1: end load, end moment, a load half-way on it
    r, a, L = np.zeros((1, 3)), np.array([[1.0, 0, 0]]), np.array([1000.0])
    down = np.array([0.0, 0.0, -1.0])
    tip = np.array([[[1000.0, 0, 0]]])
    R = member_response(r, a, L, tip, np.array([False]), np.array([[1000.0, 0, 0]]))[0, 0]
    np.testing.assert_allclose(R @ down, [0, 0, -1000.0**3 / 3, 0, 1000.0**2 / 2, 0])  # F L^3/3EI down, F L^2/2EI about +y
    # a load 200 mm beyond the tip along x: end load plus the end moment 200 F: M L^2/2 more at the tip, M L more turn
    R = member_response(r, a, L, np.array([[[1200.0, 0, 0]]]), np.array([False]), np.array([[1000.0, 0, 0]]))[0, 0]
    np.testing.assert_allclose(R @ down, [0, 0, -(1000.0**3 / 3 + 200 * 1000.0**2 / 2), 0, 1000.0**2 / 2 + 200 * 1000.0, 0])
    # the member's own body at mid-length: P a^2 (3L - a) / 6 at the tip, P a^2 / 2 turn (a = L / 2)
    R = member_response(r, a, L, np.array([[[500.0, 0, 30.0]]]), np.array([True]), np.array([[1000.0, 0, 0]]))[0, 0]
    np.testing.assert_allclose((R @ down)[[2, 4]], [-(500.0**2) * (3000 - 500) / 6, 500.0**2 / 2])
    # a load along the member bends nothing
    R = member_response(r, a, L, tip, np.array([False]), np.array([[1000.0, 0, 0]]))[0, 0]
    np.testing.assert_allclose(R @ np.array([1.0, 0, 0]), 0.0, atol=1e-9)


def test_units_of_the_bending_compliance():
    # b um/N: a lateral end load of 1 N on a 1 m member deflects its tip by b um
    assert FLEX_PER_BENDING * 1000.0**3 / 3 == pytest.approx(1e-3)


@pytest.mark.parametrize("path", [TELESCOPE, ARM6])
def test_the_effect_passes_the_interface_check(path):
    m = load_machine(path)
    check_effect(get_effect("gravity_deflection"), m)
    check_effect(get_effect("gravity_deflection"), m, aux={"payload_kg": np.linspace(0, 20, 12)})
    # with tilt sensors on bodies (their turns and the Jacobian of the turns)
    sensors = {f"accel.{b}.{a}": np.ones(12) for b in m.sensor_bodies[1:] for a in "xyz"}
    check_effect(get_effect("gravity_deflection"), m, aux={"payload_kg": np.linspace(0, 20, 12)} | sensors)
    n = m.n_joints
    check_effect(get_effect("gravity_deflection", link_mass_kg=np.full(n, 5.0)), m)


def test_joint_compliance_weighs_every_body_of_a_mimic_column():
    # the telescope's two stages (one mimicking the other), boom and wrist, with payload and a tilt: the loads on
    # the two actuators are the potential energy's derivative by the actuators (the mimic joints moving with them)
    rng = np.random.default_rng(4)
    m = load_machine(TELESCOPE)
    theta = draw_errors(m, rng)
    q = m.sample_q(6, rng)
    mass = rng.uniform(2.0, 40.0, 4)
    com = rng.uniform(-150.0, 150.0, (4, 3))
    down = _tilted(rng, 15.0)
    payload = rng.uniform(0.0, 20.0, 6)
    eff = get_effect("joint_compliance", link_mass_kg=mass, link_com_mm=com.ravel(), gravity=down)
    f = eff.features(m, q, theta, {"payload_kg": payload}, None, m.forward(q, theta))
    c = np.array([0.7, 30.0])  # um/N on the column drive, urad/(N m) on the boom
    got = eff.delta_q(f, np.r_[c, 0.0, 0.0])
    chain = MimicChain.from_text(m.to_toml(theta))
    tau = np.array([generalized_gravity(chain, qq, mass, com, down, p) for qq, p in zip(q, payload)])
    expected = np.column_stack([1e-3 * c[0] * tau[:, 0], 1e-9 * c[1] * tau[:, 1]])
    for i in range(2):
        np.testing.assert_allclose(got[:, i], expected[:, i], rtol=1e-6, atol=1e-6 * np.abs(expected[:, i]).max())
    # every body counts: the lower stage lifts itself, the upper stage (mimic, multiplier 1) lifts the rest twice as fast
    np.testing.assert_allclose(-tau[:, 0] / 9.80665, (mass[0] + 2 * (mass[1:].sum() + payload)) * (-down[2]), rtol=1e-5)
