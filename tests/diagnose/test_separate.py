"""What to measure next, checked against the second session itself, simulated by independent full statics.

A compliant 3-PRS (tests/physics/statics_3prs.py: the links' axial loads by
statics of platform, payload and gravity, not the effect's formula) recorded
with a base tilt sensor and a varying payload: its written geometry is
confounded with the platform's unknown mass and centre of mass.  The
diagnosis forecasts what a second session would do; the session is then
simulated by the statics at the forecast's conditions, appended, and
diagnosed again: its reported uncertainty must be the forecast's, and the
written geometry's error against the true one within that.
"""

import numpy as np
import pytest

from bayescal.diagnose import diagnose
from bayescal.effects.conditions import second_payload, temperature_step, tilted_mounting
from bayescal.effects.gravity_field import BASE_SENSOR, tilt_basis
from bayescal.io.recording import Recording
from bayescal.machines.files import machine_from_text
from bayescal.simulate import draw_poses, measure
from tests.physics.statics_3prs import CompliantDrives, GravityLoad, random_prs3_text, tilted_down


def _session(m, theta, q, down, load, c, mass, rng):
    aux = {"payload_kg": mass, **{k: np.full(len(q), down[i]) for i, k in enumerate(BASE_SENSOR)}}
    return measure(m, q, theta, 6, rng, aux=aux,
                   effects=[CompliantDrives(m, c, GravityLoad(load["mp"], load["com"], down), mass)])


def _appended(a: Recording, b: Recording) -> Recording:
    return Recording(q=np.vstack([a.q, b.q]), position=np.vstack([a.position, b.position]),
                     rotvec=np.vstack([a.rotvec, b.rotvec]), axis=None,
                     aux={k: np.concatenate([a.aux[k], b.aux[k]]) for k in a.aux})


def _error_um(m, theta_true, theta, seed):
    q = draw_poses(m, 200, np.random.default_rng(1000 + seed), theta_true)
    return 1e3 * float(np.sqrt(np.mean(np.sum((m.forward(q, theta).position - m.forward(q, theta_true).position) ** 2, axis=1))))


@pytest.mark.slow
def test_the_forecast_second_session_does_what_it_says_under_independent_statics():
    seed = 13
    rng = np.random.default_rng(seed)
    m = machine_from_text(random_prs3_text(rng), f"random-{seed}.toml")
    theta = rng.normal(size=m.n_params) * m.tolerance
    q = draw_poses(m, 90, rng, theta)
    down = tilted_down(rng, 15.0)
    load = {"com": np.array([*rng.uniform(-80, 80, 2), rng.uniform(-150, 50)]), "mp": rng.uniform(20, 100)}
    c, mass = rng.uniform(0.2, 1.0, 3), rng.choice(np.arange(0.0, 26.0, 5.0), 90)
    first = _session(m, theta, q, down, load, c, mass, rng)

    d = diagnose(m, first, effects=["joint_compliance"], seed=1, n_folds=2)
    conf = d.confound
    assert d.verdict == "joint_compliance" and conf.confounded
    nxt = conf.next_sessions
    assert nxt, "a confounded written geometry must come with what to measure next"
    # the forecast's 'before' is the confound's own figure, computed from the information afresh
    for x in nxt:
        assert x.tool_std_before_um == pytest.approx(conf.tool_std_um, rel=1e-6)
    assert [x.tool_std_after_um for x in nxt] == sorted(x.tool_std_after_um for x in nxt)
    best = nxt[0]
    # gravity turned against the machine is what tells the platform's weight from a zero offset
    assert best.key.startswith("tilt_") and best.ratio < 0.6
    assert best.n_poses == 90 and "accel.base" in best.advice
    assert "next:" in conf.report() and d.to_dict()["written_geometry"]["next_measurement"][0]["condition"] == best.key

    # the second session, as the statics says it comes out: gravity tilted by the forecast's 10 degrees
    # (turned towards the base axis the advice names, in the plane of that axis and the first session's gravity)
    e = tilt_basis(np.array([0.0, 0.0, -1.0]))[int(best.key[-1]) - 1]
    k = int(np.argmax(np.abs(e)))
    assert f"towards base {'+' if e[k] > 0 else '-'}{'xyz'[k]}" in best.advice
    e = e - (e @ down) * down
    a = np.deg2rad(10.0)
    down2 = np.cos(a) * down + np.sin(a) * e / np.linalg.norm(e)
    second = _session(m, theta, q, down2, load, c, mass, rng)
    d2 = diagnose(m, _appended(first, second), effects=["joint_compliance"], seed=1, n_folds=2)
    got = d2.confound.tool_std_um
    print(f"forecast {best.tool_std_before_um:.1f} -> {best.tool_std_after_um:.1f} um, got {got:.1f} um")
    assert got == pytest.approx(best.tool_std_after_um, rel=0.15)
    err1, err2 = _error_um(m, theta, d.theta_final, seed), _error_um(m, theta, d2.theta_final, seed)
    print(f"written geometry's error: {err1:.1f} um after the first session, {err2:.1f} um after both")
    assert err2 < 3 * got

    # planned: 20 of the poses, chosen one at a time; the statics' session at those poses does what the plan says
    plan = best.plan(20)
    rows = best.design.rows[plan.order]
    assert len(set(rows.tolist())) == 20 and np.array_equal(plan.q, first.q[rows])
    np.testing.assert_array_equal(plan.channels["payload_kg"], mass[rows])
    assert np.all(np.diff(plan.std_um) <= 1e-9) and plan.std_um[-1] < best.tool_std_before_um
    third = _session(m, theta, plan.q, down2, load, c, plan.channels["payload_kg"], rng)
    d3 = diagnose(m, _appended(first, third), effects=["joint_compliance"], seed=1, n_folds=2)
    print(f"20 planned poses: forecast {plan.std_um[-1]:.1f} um, got {d3.confound.tool_std_um:.1f} um")
    assert d3.confound.tool_std_um == pytest.approx(plan.std_um[-1], rel=0.15)
    # the pose file: q columns, pose_id and the channels to set, one row per planned pose
    head, *lines = plan.to_csv().splitlines()
    assert head.split(",") == ["q1", "q2", "q3", "pose_id", "payload_kg", *BASE_SENSOR] and len(lines) == 20


def test_conditions_are_the_stated_changes():
    n = 4
    aux = {"payload_kg": np.array([0.0, 5.0, 5.0, 12.0]), "temp_C": np.array([20.0, 21.0, 22.0, 21.0])}
    pay = second_payload(aux)
    assert np.array_equal(pay.session(aux, n)["payload_kg"], np.full(n, 24.0))  # twice the heaviest
    np.testing.assert_array_equal(pay.baseline(aux, n)["payload_kg"], aux["payload_kg"])
    # no payload channel: the recorded session had none, the second carries a test mass
    none = second_payload({})
    assert np.array_equal(none.baseline({}, n)["payload_kg"], np.zeros(n)) and none.session({}, n)["payload_kg"][0] > 0
    assert np.array_equal(temperature_step(10.0).session(aux, n)["temp_C"], np.full(n, 31.0))
    # the tilt: the sensor reads gravity turned by exactly 10 degrees from the mounting's direction
    down = np.array([0.1, -0.2, -1.0]) / np.linalg.norm([0.1, -0.2, -1.0])
    for axis in (0, 1):
        s = tilted_mounting(down, axis, 10.0).session({}, n)
        v = np.column_stack([s[k] for k in BASE_SENSOR])
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(np.degrees(np.arccos(v @ down)), 10.0, atol=1e-9)
    # a recorded base sensor is turned pose by pose, read in its own units and sign (specific force, m/s^2)
    tilt = {k: np.full(2, -9.81 * down[i]) for i, k in enumerate(BASE_SENSOR)}
    s = tilted_mounting(np.array([0.0, 0.0, -1.0]), 0, 5.0).session(tilt, 2)
    v = np.column_stack([s[k] for k in BASE_SENSOR])
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 9.81, rtol=1e-12)
    np.testing.assert_allclose(np.degrees(np.arccos(-v @ down / 9.81)), 5.0, atol=1e-9)


def test_greedy_steps_are_the_best_single_additions_and_all_poses_give_the_whole_session():
    rng = np.random.default_rng(0)
    N, P, m, d = 7, 4, 12, 3
    A0 = rng.normal(size=(20, N))
    G = rng.normal(size=(9, P))
    GS = np.zeros((9, N))
    GS[:, :P] = G
    from bayescal.diagnose.separate import SessionDesign

    blocks = rng.normal(size=(m, d, N))
    design = SessionDesign(A0.T @ A0 + np.eye(N), blocks, GS.T @ GS, 3, 1.0, np.arange(m), rng.normal(size=(m, 2)), {})
    order, std = design.greedy(m)
    # each step: the candidate whose block, added by a full inverse, leaves the smallest tool variance
    H = design.H0.copy()
    for k in order[:4]:
        trial = [design.std_um(np.linalg.inv(H + b.T @ b)) if j not in order[: list(order).index(k)] else np.inf
                 for j, b in enumerate(blocks)]
        assert int(np.argmin(trial)) == k
        H = H + blocks[k].T @ blocks[k]
    full = design.H0 + np.einsum("mdi,mdj->ij", blocks, blocks)
    assert std[-1] == pytest.approx(design.std_um(np.linalg.inv(full)), rel=1e-10)
    assert sorted(order.tolist()) == list(range(m))


@pytest.mark.slow
def test_a_temperature_step_separates_thermal_growth_recorded_at_a_near_constant_temperature():
    """Growth over 2 K is mostly a constant (a zero offset); 10 K more, simulated by independent part growth, fixes it."""
    from tests.physics.thermal_growth import PartGrowth

    rng = np.random.default_rng(3)
    m = machine_from_text(random_prs3_text(rng), "random-3.toml")
    theta = rng.normal(size=m.n_params) * m.tolerance
    q = draw_poses(m, 120, rng, theta)
    temp = 26 + np.linspace(0, 2.0, 120) + rng.normal(0, 0.02, 120)
    a_s, a_l = rng.uniform(8, 25, 3), rng.uniform(10, 25, 3)
    bearing = np.where(rng.random(3) < 0.5, 0.0, m.q_limits[:, 1] + 50.0)

    def session(t):
        return measure(m, q, theta, 6, rng, aux={"temp_C": t},
                       effects=[PartGrowth(m, t, alpha_screw=a_s, bearing_mm=bearing, alpha_link=a_l)])

    first = session(temp)
    d = diagnose(m, first, effects=["thermal_expansion"], seed=1, n_folds=2)
    assert d.verdict == "thermal_expansion" and d.confound.confounded
    best = d.confound.next_sessions[0]
    assert best.key == "temperature" and best.ratio < 0.5
    warm = session(np.full(120, temp.mean() + 10.0))
    d2 = diagnose(m, _appended(first, warm), effects=["thermal_expansion"], seed=1, n_folds=2)
    print(f"forecast {best.tool_std_before_um:.2f} -> {best.tool_std_after_um:.2f} um, got {d2.confound.tool_std_um:.2f}")
    assert d2.confound.tool_std_um == pytest.approx(best.tool_std_after_um, rel=0.15)


@pytest.mark.slow
def test_a_second_payload_separates_a_bending_telescope_from_its_geometry():
    """Element-by-element beam statics (tests/physics/beam_statics.py), no payload recorded: the forecast for a
    10 kg second session against that session simulated and diagnosed (the forecast, linearised at the first
    session's fit and scaled by its noise estimate, came out 24 % above the diagnosed figure: on the safe side)."""
    from bayescal.machines.files import load_machine
    from bayescal.simulate import draw_errors
    from tests.physics.beam_statics import Member
    from tests.physics.test_deflection_diagnosis import TELESCOPE, BendingStructure

    class Loaded(BendingStructure):
        def __init__(self, *args, payload_kg):
            super().__init__(*args)
            self.payload_kg = payload_kg

        def pose_offset(self, q, theta, aux, order):
            from bayescal.geometry import so3_log
            from tests.physics.beam_statics import deflected_tool

            out = np.zeros((q.shape[0], 6))
            for i, qq in enumerate(q):
                p0, R0, p1, R1 = deflected_tool(self.chain, qq, self.members, self.mass, self.com, self.down,
                                                self.payload_kg, n_elements=30)
                out[i, :3], out[i, 3:] = p1 - p0, so3_log(R1 @ R0.T)
            return out

    m = load_machine(TELESCOPE)
    rng = np.random.default_rng(21)
    theta = draw_errors(m, rng)
    mass = np.array([40.0, 25.0, 30.0, 8.0])
    com = np.array([[0.0, 0, 40], [60.0, 0, 10], [110.0, 5, 0], [20.0, 0, 10]])
    a = np.radians(1.5)
    down = np.array([np.sin(a), 0.0, -np.cos(a)])
    members = [Member("stage", 0, 1e12 / 9.0), Member("stage", 1, 1e12 / 9.0), Member("link", 2, 1e12 / 18.0)]
    q = draw_poses(m, 60, rng, theta)

    def session(payload):
        structure = Loaded(m.to_toml(theta), members, mass, com, down, payload_kg=payload)
        return measure(m, q, theta, 6, rng, aux={"payload_kg": np.full(60, payload)}, effects=[structure])

    first = session(0.0)
    d = diagnose(m, first, effects=["gravity_deflection"], seed=1, n_folds=2)
    assert d.verdict == "gravity_deflection" and d.confound.confounded
    pay = next(x for x in d.confound.next_sessions if x.key == "payload")
    assert "10 kg" in pay.advice and pay.ratio < 0.3
    d2 = diagnose(m, _appended(first, session(10.0)), effects=["gravity_deflection"], seed=1, n_folds=2)
    got = d2.confound.tool_std_um
    print(f"forecast {pay.tool_std_before_um:.1f} -> {pay.tool_std_after_um:.1f} um, got {got:.1f} um")
    assert 0.65 * pay.tool_std_after_um < got < 1.1 * pay.tool_std_after_um
