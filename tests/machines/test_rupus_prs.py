"""RU-PUS-PRS (solar tracker): kinematics, Jacobian, machine file, measurement, identification."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bayescal.errors import MachineFileError
from bayescal.geometry import rotation_from_tilt_torsion, so3_exp, so3_log, tilt_torsion_angles
from bayescal.identifiability import analyse_identifiability
from bayescal.identify import identify
from bayescal.machines import KINDS
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.machines.rupus_prs import RupusPrs, rotate_about
from bayescal.measurement import MeasurementModel
from bayescal.simulate import measure, simulate_recording

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rupus_prs" / "machine.toml"
TEXT = EXAMPLE.read_text()
# parameters whose first-order effect vanishes at the nominal (coaxial post) geometry
SECOND_ORDER = ("base_axis", "link_direction", "universal_axis")


@pytest.fixture(scope="module")
def tracker():
    return load_machine(EXAMPLE)


def _second_order(machine):
    return [i for i, n in enumerate(machine.layout.names) if any(s in n for s in SECOND_ORDER)]


def _rx(a):
    return so3_exp(np.array([a, 0.0, 0.0]))


def _ry(a):
    return so3_exp(np.array([0.0, a, 0.0]))


def test_kind_is_registered_and_example_loads(tracker):
    assert KINDS["RU-PUS-PRS"] is RupusPrs
    assert isinstance(tracker, RupusPrs)
    assert tracker.n_actuators == 2 and tracker.n_params == 38
    assert tracker.layout.names[:3] == ("chain1.sphere_center.x", "chain1.sphere_center.y", "chain1.sphere_center.z")
    assert "chain2.revolute_axis.tilt_y" in tracker.layout.names
    assert "chain3.universal_axis_platform.tilt_z" in tracker.layout.names


def test_closed_form_tilts_on_nominal_machine(tracker):
    """Nominal tracker: R = Rx(g1) Ry(g2) about the fixed U centre N = (0, 0, 800).

    Chain 2 (plane x = 0) fixes g1 alone: A2 = N + 400 (0, cos g1, sin g1);
    chain 1 then fixes g2.  q from these closed forms, then FK must return them.
    """
    g1 = np.radians([0.0, 20.0, -15.0, 10.0, 25.0])
    g2 = np.radians([0.0, 0.0, 12.0, -20.0, 25.0])
    N = np.array([0.0, 0.0, 800.0])
    A2z = 800.0 + 400.0 * np.sin(g1)
    q2 = A2z - np.sqrt(400.0**2 - (500.0 - 400.0 * np.cos(g1)) ** 2)
    A1 = np.stack([-400 * np.cos(g2), -400 * np.sin(g2) * np.sin(g1), 800 + 400 * np.sin(g2) * np.cos(g1)], axis=1)
    q1 = A1[:, 2] - np.sqrt(400.0**2 - (A1[:, 0] + 500.0) ** 2 - A1[:, 1] ** 2)
    poses = tracker.forward(np.stack([q1, q2], axis=1))
    assert poses.success.all()
    R = np.array([_rx(a) @ _ry(b) for a, b in zip(g1, g2)])
    assert np.allclose(poses.rotation, R, atol=1e-12)
    assert np.allclose(poses.position, N + R[:, :, 2] * 50.0, atol=1e-10)
    assert np.allclose(poses.state.beta, 0.0, atol=1e-12)  # the R joint at O only frees the over-constraint
    assert np.allclose(tracker.inverse(R), np.stack([q1, q2], axis=1), atol=1e-10)
    # home: level platform, tool 50 mm above N
    assert np.allclose(poses.position[0], [0.0, 0.0, 850.0], atol=1e-10)


def test_constraints_hold_at_solution(tracker):
    rng = np.random.default_rng(4)
    q = tracker.sample_q(25, rng)
    theta = rng.normal(size=tracker.n_params) * tracker.tolerance * 5
    poses = tracker.forward(q, theta)
    assert poses.success.all()
    g = tracker.geometry_arrays(theta)
    R, p, beta = poses.rotation, poses.state.p, poses.state.beta
    A = p[:, None, :] + np.einsum("nij,kj->nki", R, g["sphere_center"])
    C = g["rail_origin"][None] + q[:, :, None] * g["rail_direction"][None]
    d = A - C
    assert np.allclose(np.linalg.norm(d, axis=2), g["link_length"][None], atol=1e-9)
    assert np.allclose(d[:, 1] @ g["revolute_axis"], 0.0, atol=1e-9)
    n = len(q)
    w = np.broadcast_to(g["base_axis"], (n, 3))
    N = g["base_point"] + g["center_link_length"] * rotate_about(w, beta, np.broadcast_to(g["link_direction"], (n, 3)))
    assert np.allclose(p + R @ g["universal_center"], N, atol=1e-9)
    k1 = rotate_about(w, beta, np.broadcast_to(g["universal_axis_link"], (n, 3)))
    assert np.allclose(np.einsum("ni,ni->n", k1, R @ g["universal_axis_platform"]), 0.0, atol=1e-12)
    assert np.allclose(poses.position, p + R @ g["tool_point"], atol=1e-12)


def test_tool_jacobian_against_central_differences(tracker):
    rng = np.random.default_rng(7)
    q = tracker.sample_q(8, rng)
    theta = rng.normal(size=tracker.n_params) * tracker.tolerance * 10
    poses = tracker.forward(q, theta)
    J = tracker.tool_jacobian(q, theta, poses)
    scale = np.abs(J).max()
    second = set(_second_order(tracker))
    for k, unit in enumerate(tracker.layout.units):
        h = 1e-5 if unit == "mm" else 1e-7
        e = np.zeros(tracker.n_params)
        e[k] = h
        pp, pm = tracker.forward(q, theta + e, guess=poses), tracker.forward(q, theta - e, guess=poses)
        fd_pos = (pp.position - pm.position) / (2 * h)
        fd_rot = so3_log(pp.rotation @ np.swapaxes(pm.rotation, 1, 2)) / (2 * h)
        assert np.allclose(J[:, :3, k], fd_pos, atol=1e-7 * scale), tracker.layout.names[k]
        assert np.allclose(J[:, 3:, k], fd_rot, atol=1e-7 * scale), tracker.layout.names[k]
        if k in second:  # small columns (second-order at nominal): checked against their own size too
            own = np.abs(J[:, :, k]).max()
            assert own > 0.1 and np.abs(J[:, :3, k] - fd_pos).max() < 1e-5 * own, tracker.layout.names[k]
            assert np.abs(J[:, 3:, k] - fd_rot).max() < 1e-5 * own, tracker.layout.names[k]


@given(st.floats(270.0, 640.0), st.floats(270.0, 640.0), st.integers(0, 2**16))
@settings(max_examples=40, deadline=None)
def test_forward_robust_across_workspace(tracker, q1, q2, seed):
    q = np.array([[q1, q2]])
    theta = np.random.default_rng(seed).normal(size=tracker.n_params) * tracker.tolerance * 5
    poses = tracker.forward(q, theta)
    assert poses.success.all(), poses.message
    assert np.allclose(tracker.inverse(poses.rotation, theta), q, atol=1e-8)
    # on the tracker's branch: platform facing up, sliders below the spheres
    assert poses.rotation[0, 2, 2] > 0.7


def test_unreachable_pose_is_reported_not_raised(tracker):
    poses = tracker.forward(np.array([[450.0, 450.0], [0.0, 2000.0]]))
    assert poses.success.tolist() == [True, False]
    assert poses.message[1]


def test_tilt_torsion_convention():
    """The seed's T&T angles: normal tilted by theta towards azimuth phi, torsion psi about the normal."""
    rng = np.random.default_rng(1)
    phi, th, psi = rng.uniform(-np.pi, np.pi, 20), rng.uniform(0.05, 1.2, 20), rng.uniform(-np.pi, np.pi, 20)
    R = rotation_from_tilt_torsion(phi, th, psi)
    normal = np.stack([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)], axis=1)
    assert np.allclose(R[:, :, 2], normal, atol=1e-12)
    # torsion turns the platform about its own normal
    d = 0.3
    rz = so3_exp(np.array([0.0, 0.0, d]))
    assert np.allclose(rotation_from_tilt_torsion(phi, th, psi + d), R @ rz, atol=1e-12)
    back = tilt_torsion_angles(R)
    assert np.allclose(back[:, 0], phi, atol=1e-10) and np.allclose(back[:, 1], th, atol=1e-10)
    assert np.allclose(np.angle(np.exp(1j * (back[:, 2] - psi))), 0.0, atol=1e-10)


def test_machine_tilt_torsion_output(tracker):
    q = tracker.sample_q(10, np.random.default_rng(3))
    tt = tracker.tilt_torsion(q)
    R = tracker.forward(q).rotation
    assert np.allclose(np.cos(tt[:, 1]), R[:, 2, 2], atol=1e-12)  # tilt = angle of the normal from z
    assert np.allclose(rotation_from_tilt_torsion(tt[:, 0], tt[:, 1], tt[:, 2]), R, atol=1e-10)
    assert np.isnan(tracker.tilt_torsion(np.array([[0.0, 2000.0]]))).all()


def test_written_machine_reproduces_the_model(tracker):
    rng = np.random.default_rng(8)
    theta = rng.normal(size=tracker.n_params) * tracker.tolerance * 3
    again = machine_from_text(tracker.to_toml(theta))
    q = tracker.sample_q(15, rng)
    a, b = tracker.forward(q, theta), again.forward(q)
    assert np.allclose(a.position, b.position, atol=1e-10)
    assert np.allclose(a.rotation, b.rotation, atol=1e-12)
    assert again.q_limits.tolist() == tracker.q_limits.tolist()
    assert again.noise == tracker.noise and again.name == tracker.name
    # and the nominal file round-trips to the same text
    assert machine_from_text(tracker.to_toml()).to_toml() == tracker.to_toml()


def test_against_rail_assembly_round_trip(tracker):
    """Sliders above the sphere centres (links hanging down, against the rail direction)."""
    text = TEXT.replace('name = "solar tracker A"', 'name = "hanging"\nassembly = "against_rail"')
    text = text.replace("q_limits = [[270.0, 640.0], [270.0, 640.0]]", "q_limits = [[1000.0, 1300.0], [1000.0, 1300.0]]")
    m = machine_from_text(text)
    assert not m.links_along_rail
    up = 800.0 + np.sqrt(400.0**2 - 100.0**2)
    poses = m.forward(np.array([[up, up], [up + 30.0, up - 20.0]]))
    assert poses.success.all()
    assert np.allclose(poses.rotation[0], np.eye(3), atol=1e-12)
    A = poses.state.p[1] + m.sphere_center @ poses.rotation[1].T  # sphere centres of pose 2, base frame
    assert (A[:, 2] < [up + 30.0, up - 20.0]).all()  # below their sliders
    assert np.allclose(m.inverse(poses.rotation), [[up, up], [up + 30.0, up - 20.0]], atol=1e-9)
    assert 'assembly = "against_rail"' in m.to_toml()
    assert machine_from_text(m.to_toml()).to_toml() == m.to_toml()


@pytest.mark.parametrize(
    "old, new, key",
    [
        ("link_length    = 400.0\nsphere_center  = [-400.0", "link_lenght    = 400.0\nsphere_center  = [-400.0", "chain[1].link_lenght"),
        ("revolute_axis  = [1.0, 0.0, 0.0]", "revolute_axis  = [1.0, 0.1, 0.0]", "chain[2].revolute_axis"),
        ("universal_axis_link     = [1.0, 0.0, 0.0]", "universal_axis_link     = [0.0, 0.0, 1.0]", "chain[3].universal_axis_link"),
        ('joints                  = "RU"', 'joints                  = "RS"', "chain[3].joints"),
        ("universal_center        = [0.0, 0.0, 0.0]", "universal_center        = [0.0, 0.0]", "chain[3].universal_center"),
        ("link_length             = 800.0", "link_length             = -800.0", "chain[3].link_length"),
        ("base_point              = [0.0, 0.0, 0.0]\n", "", "chain[3].base_point"),
        ("q_limits = [[270.0, 640.0], [270.0, 640.0]]", "q_limits = [[270.0, 640.0]]", "workspace.q_limits"),
        ('name = "solar tracker A"', 'name = "solar tracker A"\nassembly = "upside_down"', "assembly"),
        ("[tool]\npoint", "[tool]\npiont", "tool.piont"),
    ],
)
def test_malformed_machine_file_names_the_key(old, new, key):
    assert old in TEXT
    with pytest.raises(MachineFileError, match=key.replace("[", r"\[").replace("]", r"\]")):
        machine_from_text(TEXT.replace(old, new), "bad.toml")


def test_wrong_number_of_chains_is_rejected():
    third = TEXT.index("[[chain]]                          # chain 3")
    with pytest.raises(MachineFileError, match="expected 3"):
        machine_from_text(TEXT[:third] + TEXT[TEXT.index("[tool]"):], "bad.toml")


@pytest.mark.parametrize("dof", [6, 5, 3])
def test_measurement_model_works_unchanged(tracker, dof):
    """From a recording: the truth reproduces it; the analytic model Jacobian matches differences."""
    sim = simulate_recording(tracker, 12, seed=3, dof=dof)
    model = MeasurementModel.from_recording(tracker, sim.recording)
    pred = model.predict(sim.theta_true)
    assert pred.success.all()
    assert np.abs(model.residual(pred)[:, :3]).max() < 6 * tracker.noise.sigma_position
    theta = sim.theta_true
    J = model.jacobian(theta, pred)
    for k in range(tracker.n_params):
        h = 1e-5 if tracker.layout.units[k] == "mm" else 1e-7
        e = np.zeros(tracker.n_params)
        e[k] = h
        fd = (model.predict(theta + e, guess=pred.poses).y - model.predict(theta - e, guess=pred.poses).y) / (2 * h)
        assert np.allclose(J[:, :, k], fd, atol=1e-6 * np.abs(J).max()), tracker.layout.names[k]
    # stacked parameter vectors (samplers) and pose subsets work on this state
    stacked = model.predict(np.vstack([np.broadcast_to(theta, (12, tracker.n_params))] * 2))
    assert np.allclose(stacked.y[:12], pred.y) and np.allclose(stacked.y[12:], pred.y)
    assert np.allclose(model.subset([1, 4]).predict(theta).y, pred.y[[1, 4]])


def test_identifiability_counts_and_gauges(tracker):
    """6-DOF: 26 identifiable; 5-DOF: 25 (torsion gauge); 3-DOF: 23.  Gauge directions from geometry."""
    q = tracker.sample_q(40, np.random.default_rng(5))
    names = tracker.layout.names
    idx = {n: i for i, n in enumerate(names)}

    def vec(pairs):
        v = np.zeros(tracker.n_params)
        for n, x in pairs:
            v[idx[n]] = x
        return v

    # shifting the platform frame: every platform-frame point moves by the same vector
    shift_x = vec([(f"{p}.x", 1.0) for p in ("chain1.sphere_center", "chain2.sphere_center", "chain3.universal_center", "tool.point")])
    # turning the platform frame about its normal (platform z): a -> a + alpha e_z x a; U axis (0,1,0) tilts about z
    a1, a2 = tracker.sphere_center
    turn = vec([("chain1.sphere_center.x", -a1[1]), ("chain1.sphere_center.y", a1[0]),
                ("chain2.sphere_center.x", -a2[1]), ("chain2.sphere_center.y", a2[0]),
                ("chain3.universal_axis_platform.tilt_z", 1.0)])
    expected = {6: 26, 5: 25, 3: 23}
    for dof in (6, 5, 3):
        model = MeasurementModel(tracker, q, dof)
        pred = model.predict()
        J = (model.jacobian(None, pred) / model.sigma[None, :, None]).reshape(-1, tracker.n_params)
        ida = analyse_identifiability(J, tracker.layout)
        assert ida.rank == len(ida.kept) == expected[dof], dof
        assert np.abs(J @ shift_x).max() < 1e-9 * np.abs(J).max()
        seen = np.abs(J @ turn).max() / np.abs(J).max()
        assert (seen < 1e-9) == (dof != 6), dof  # only a 6-DOF measurement sees the torsion
        # second-order parameters: no first-order effect at the coaxial nominal geometry
        zero = [names[i] for i in _second_order(tracker) if np.abs(J[:, i]).max() < 1e-9 * np.abs(J).max()]
        assert {n for n in zero} >= {"chain3.base_axis.tilt_x", "chain3.universal_axis_link.tilt_y",
                                     "chain3.universal_axis_platform.tilt_x"}
        assert set(zero) <= set(ida.fixed)


@pytest.mark.parametrize("dof", [6, 5, 3])
def test_noise_free_identification_reproduces_predictions(tracker, dof):
    """LS on noise-free data of a coaxial-post truth: predictions agree to 1e-9 mm on fresh poses."""
    rng = np.random.default_rng(2)
    theta = rng.normal(size=tracker.n_params) * tracker.tolerance
    theta[_second_order(tracker)] = 0.0
    q = tracker.sample_q(40, rng)
    model = MeasurementModel.from_recording(tracker, measure(tracker, q, theta, dof, None))
    res = identify(model, method="ls")
    assert res.success, res.message
    assert res.rms_after["position"] < 1e-9
    fresh = MeasurementModel(tracker, tracker.sample_q(50, np.random.default_rng(9)), dof)
    assert np.abs(fresh.predict(res.theta).y - fresh.predict(theta).y).max() < 1e-9


def test_second_order_errors_leave_a_tiny_residual(tracker):
    """With an eccentric post and tilted U axes the fit is limited by their second-order effect only."""
    rng = np.random.default_rng(2)
    theta = rng.normal(size=tracker.n_params) * tracker.tolerance
    q = tracker.sample_q(40, rng)
    model = MeasurementModel.from_recording(tracker, measure(tracker, q, theta, 6, None))
    res = identify(model, method="ls")
    assert res.success
    # far below the instrument noise, far above round-off: r * tilt * beta ~ 800 mm * 2e-4 * 2e-4
    assert 1e-7 < res.rms_after["position"] < 0.05 * tracker.noise.sigma_position


def test_5dof_ls_on_the_6dof_parameter_set_is_ill_posed(tracker):
    """The seed's finding: LS fails with 5-DOF on a set that 6-DOF identifies (the torsion gauge)."""
    rng = np.random.default_rng(2)
    theta = rng.normal(size=tracker.n_params) * tracker.tolerance
    q = tracker.sample_q(40, rng)
    six = identify(MeasurementModel.from_recording(tracker, measure(tracker, q, theta, 6, None)), method="ls")
    kept6 = [n for n, f in zip(tracker.layout.names, six.free) if f]
    model5 = MeasurementModel.from_recording(tracker, measure(tracker, q, theta, 5, None))
    from bayescal.errors import ConvergenceWarning

    with pytest.warns(ConvergenceWarning, match="ill-posed"):
        res = identify(model5, method="ls", free=kept6)
    assert not res.success and "ill-posed" in res.message
    assert identify(model5, method="ls").success  # the automatic 5-DOF set drops the gauge


def test_cli_simulate_identify_write_machine(tmp_path, capsys):
    """End to end through the CLI with 5-DOF data: the calibrated file alone predicts the true tracker."""
    from bayescal.cli import main

    rec, cal = tmp_path / "rec.csv", tmp_path / "cal.toml"
    assert main(["simulate", "--machine", str(EXAMPLE), "--poses", "30", "--seed", "4", "--dof", "5", "--out", str(rec)]) == 0
    assert main(["identify", str(rec), "--machine", str(EXAMPLE), "--method", "tsvd", "--k", "20",
                 "--write-machine", str(cal)]) == 0
    assert "RU-PUS-PRS" in capsys.readouterr().out
    nominal, calibrated, true = load_machine(EXAMPLE), load_machine(cal), load_machine(tmp_path / "rec.truth.toml")
    q = nominal.sample_q(100, np.random.default_rng(0))
    axis_err = lambda m: np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", m.forward(q).axis, true.forward(q).axis), -1, 1)))  # noqa: E731
    pos_err = lambda m: np.sqrt(np.mean(np.sum((m.forward(q).position - true.forward(q).position) ** 2, axis=1)))  # noqa: E731
    assert pos_err(calibrated) < 0.25 * pos_err(nominal)
    assert np.sqrt(np.mean(axis_err(calibrated) ** 2)) < 0.5 * np.sqrt(np.mean(axis_err(nominal) ** 2))


def test_inverse_tilt_round_trip(tracker):
    """q -> T&T angles of the normal -> q, with errors; the torsion comes back too."""
    rng = np.random.default_rng(12)
    theta = rng.normal(size=tracker.n_params) * tracker.tolerance * 5
    q = tracker.sample_q(30, rng)
    tt = tracker.tilt_torsion(q, theta)
    q_back, psi, ok = tracker.inverse_tilt(tt[:, 0], tt[:, 1], theta)
    assert ok.all()
    assert np.allclose(q_back, q, atol=1e-9)
    assert np.allclose(np.angle(np.exp(1j * (psi - tt[:, 2]))), 0.0, atol=1e-12)
    # a normal 80 degrees off the vertical is out of reach: reported, not invented
    q_far, _, ok_far = tracker.inverse_tilt([0.3], [np.radians(80.0)])
    assert not ok_far[0] and np.isnan(q_far).all()
