"""joint_compliance and redundancy_preload on revolute drives: joint torques, urad/(N m), priors from the actuator unit."""

import copy
from pathlib import Path

import numpy as np
import pytest

from bayescal.effects import check_effect, get_effect
from bayescal.effects.joint_compliance import GRAVITY
from bayescal.machines.files import load_machine
from bayescal.simulate import draw_poses

ROOT = Path(__file__).resolve().parents[2]
G = 9.80665  # standard gravity, m/s^2, stated here rather than read from the effect


@pytest.fixture(scope="module")
def positioner():
    return load_machine(ROOT / "examples" / "positioner" / "machine.toml")


@pytest.fixture(scope="module")
def arm6():
    return load_machine(ROOT / "examples" / "arm6" / "machine.toml")


def _params(machine, aux, n=20, **settings):
    eff = get_effect("joint_compliance", **settings)
    q = draw_poses(machine, n, np.random.default_rng(0))
    f = eff.features(machine, q, np.zeros(machine.n_params), aux, None, machine.forward(q))
    return eff, q, f, {p.name: p for p in eff.params(machine, f)}


@pytest.mark.parametrize("name", ["positioner", "arm6"])
def test_revolute_compliance_is_angular_with_a_torsional_prior(name, request):
    m = request.getfixturevalue(name)
    assert set(m.actuator_units) == {"rad"}
    _, _, _, p = _params(m, {"payload_kg": np.linspace(0, 20, 20)})
    for i in range(1, m.n_actuators + 1):
        c = p[f"compliance.q{i}"]
        # 100 urad/(N m): a torsional stiffness of 1e4 N m/rad, the joint that lets a point 100 mm from its axis
        # give way 1 um/N (the slider's prior); robot and positioner joints are 1-100 urad/(N m)
        assert c.unit == "urad/(N m)" and c.prior_sd == pytest.approx(100.0) and c.lower == 0.0
    assert p["platform_mass"].unit == "kg" and p["com.x"].unit == "mm" and p["gravity.tilt_1"].unit == "rad"
    _, _, _, p = _params(m, {})
    w = p["weight_deflection.q1"]
    assert w.unit == "urad/m" and w.prior_sd == pytest.approx(30000.0)  # 3 mrad at 100 mm of lever arm
    assert w.start_value == pytest.approx(0.5 * 100.0 * 30.0 * G)


def test_prismatic_and_mixed_drives_keep_their_units():
    prs = load_machine(ROOT / "examples" / "prs3" / "machine.toml")
    _, _, _, p = _params(prs, {"payload_kg": np.linspace(0, 20, 20)})
    assert (p["compliance.q1"].unit, p["compliance.q1"].prior_sd) == ("um/N", 1.0)
    _, _, _, p = _params(prs, {})
    w = p["weight_deflection.q2"]
    assert (w.unit, w.prior_sd) == ("um", 300.0) and w.start_value == pytest.approx(0.5 * 30.0 * G)
    hyb = load_machine(ROOT / "examples" / "hybrid_table" / "machine.toml")
    _, _, _, p = _params(hyb, {"payload_kg": np.linspace(0, 20, 20)})
    assert [p[f"compliance.q{i}"].unit for i in (1, 2, 3, 4)] == ["um/N"] * 3 + ["urad/(N m)"]


def _point(machine, q, offset):
    """A point fixed to the last body, ``offset`` mm in its frame from the tool point (base frame, mm)."""
    poses = machine.forward(q)
    return poses.position + np.einsum("nij,j->ni", poses.rotation, offset)


@pytest.mark.parametrize("name", ["positioner", "arm6"])
def test_joint_deflection_is_compliance_times_the_gravity_torque_by_finite_differences(name, request):
    # first principles, not the effect's Jacobian: the gravity torque on joint i is dV/dq_i with
    # V = -m g d . x(q) the potential's negative (N mm per rad, from finite differences of the forward
    # kinematics), and the joint gives way c_i tau_i with c_i in urad/(N m): dq_i = 1e-6 c_i 1e-3 tau_i rad
    m = request.getfixturevalue(name)
    rng = np.random.default_rng(5)
    payload = rng.uniform(0.0, 25.0, 12)
    off = np.array([10.0, -20.0, 60.0])
    eff, q, f, p = _params(m, {"payload_kg": payload}, n=12, payload_offset=off)
    names = list(p)
    c = rng.uniform(5.0, 80.0, m.n_actuators)  # urad/(N m)
    mp, com = 40.0, np.array([30.0, -50.0, 120.0])
    eta = np.zeros(len(names))
    eta[: m.n_actuators] = c
    eta[names.index("platform_mass")] = mp
    eta[[names.index(f"com.{x}") for x in "xyz"]] = com
    down = np.array([0.0, 0.0, -1.0])
    h = 1e-6
    tau = np.zeros((len(q), m.n_actuators))
    for i in range(m.n_actuators):
        e = np.zeros(m.n_actuators)
        e[i] = h
        for point, mass in ((com, np.full(len(q), mp)), (off, payload)):
            dx = (_point(m, q + e, point) - _point(m, q - e, point)) / (2 * h)  # mm/rad
            tau[:, i] += mass * G * (dx @ down)  # N mm
    expected = 1e-9 * c[None, :] * tau  # rad
    got = eff.delta_q(f, eta)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
    # sizes: tens to thousands of urad for joints of 5-80 urad/(N m) under 40 kg at 0.1-1 m, not radians
    assert 1e-6 < np.abs(got).max() < 0.05
    assert GRAVITY == G


def test_conformance_on_revolute_joints(positioner):
    check_effect(get_effect("joint_compliance"), positioner, aux={"payload_kg": np.linspace(0.0, 20.0, 12)})
    check_effect(get_effect("joint_compliance"), positioner)


def test_redundancy_preload_not_applicable_on_serial_revolute_chains(positioner, arm6):
    eff = get_effect("redundancy_preload")
    for m in (positioner, arm6):
        why = eff.not_applicable(m, {})
        assert why and why.startswith("not applicable") and "no redundant actuation" in why


def _with_units(machine, units):
    """The RASPM declaring other actuator units (only the units change: this tests what the effect reads)."""
    cls = type("Relabelled", (type(machine),), {"actuator_units": property(lambda self: tuple(units))})
    out = copy.copy(machine)
    object.__setattr__(out, "__class__", cls)  # a frozen dataclass
    return out


def test_redundancy_preload_units_follow_the_drives():
    raspm = load_machine(ROOT / "examples" / "raspm" / "machine.toml")
    eff = get_effect("redundancy_preload")
    q = raspm.sample_q(3, np.random.default_rng(0))
    f = eff.features(raspm, q, np.zeros(raspm.n_params), {}, None, None)
    p = {x.name: x for x in eff.params(raspm, f)}
    assert (p["offset.q2"].unit, p["offset.q2"].prior_sd) == ("mm", 1.0)  # the slider machine's numbers
    rev = _with_units(raspm, ["rad"] * 4)
    assert eff.not_applicable(rev, {}) is None
    p = {x.name: x for x in eff.params(rev, f)}
    assert (p["offset.q2"].unit, p["offset.q2"].prior_sd) == ("rad", pytest.approx(0.01))
    assert p["compliance_ratio.q1"].unit == "1"
    vals = eff.simulated_values(rev, f, 100.0, np.random.default_rng(1))
    assert abs(vals[list(p).index("offset.q2")]) == pytest.approx(1e-4)  # 100 urad
    mixed = _with_units(raspm, ["mm", "rad", "mm", "mm"])
    why = eff.not_applicable(mixed, {})
    assert why and why.startswith("not applicable") and "not dimensionless" in why


class _JointTorqueSag:
    """Outside the library: each joint turns by ``c_i tau_i``, the torque from finite differences of the
    potential of a platform weight (at ``com`` from the tool point, last-body frame) and the recorded payload."""

    def __init__(self, machine, c_urad_per_nm, mass_kg, com_mm):
        self.m, self.c, self.mass, self.com = machine, np.asarray(c_urad_per_nm), mass_kg, np.asarray(com_mm)

    def transform(self, q, theta, aux, order):
        n, k = q.shape
        tau = np.zeros((n, k))  # N mm
        for i in range(k):
            e = np.zeros(k)
            e[i] = 1e-6
            for point, mass in ((self.com, np.full(n, self.mass)), (np.zeros(3), np.asarray(aux["payload_kg"]))):
                up = self.m.forward(q + e, theta)
                dn = self.m.forward(q - e, theta)
                zu = up.position[:, 2] + np.einsum("nj,j->n", up.rotation[:, 2], point)
                zd = dn.position[:, 2] + np.einsum("nj,j->n", dn.rotation[:, 2], point)
                tau[:, i] -= mass * G * (zu - zd) / 2e-6  # gravity along -z
        return q + 1e-9 * self.c[None, :] * tau, theta


def sagging_positioner(c=(30.0, 18.0)):
    """The positioner of test_revolute_units (better instrument) sagging by ``c`` urad/(N m) at its joints under
    payloads of 0-25 kg (recorded), 160 poses: ``(machine, recording)``."""
    from bayescal.simulate import draw_errors, measure
    from tests.effects.test_revolute_units import _positioner

    pos = _positioner()
    rng = np.random.default_rng(4)
    theta = draw_errors(pos, rng)
    q = draw_poses(pos, 160, rng, theta)
    aux = {"payload_kg": rng.uniform(0.0, 25.0, 160)}
    return pos, measure(pos, q, theta, 6, rng, aux=aux, effects=[_JointTorqueSag(pos, np.asarray(c), 30.0, [0.0] * 3)])


def test_diagnose_names_a_joint_torque_sag_in_urad_per_newton_metre():
    from bayescal.diagnose import diagnose

    c = np.array([30.0, 18.0])  # urad/(N m)
    pos, rec = sagging_positioner(c)
    d = diagnose(pos, rec, seed=1)
    assert d.verdict == "joint_compliance"
    got = {p.name: p for p in next(e for e in d.effects if e.name == "joint_compliance").parameters}
    for i in (1, 2):
        p = got[f"compliance.q{i}"]
        assert p.unit == "urad/(N m)" and abs(p.value - c[i - 1]) < 4 * p.std, (i, p.value, p.std)
