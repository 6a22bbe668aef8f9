import numpy as np
import pytest

from bayescal.errors import RecordingError
from bayescal.machines.files import load_machine
from bayescal.redundant import PoseModel, TrueModule, applicable_error_model, geometric_error_model, solve_restrained
from bayescal.redundant.relative_io import read_relative_recording, relative_to_csv
from bayescal.redundant.steps import INSTRUMENTS, design_rm1, identify_step, measure_relative
from tests.conftest import ROOT

K = np.array([2.0e4, 3.0e4, 5.0e4, 4.0e4])


@pytest.fixture(scope="module")
def raspm():
    return load_machine(ROOT / "examples" / "raspm" / "machine.toml")


def test_restrained_solver_equilibrium_and_compatibility(raspm):
    rng = np.random.default_rng(3)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance * 5
    x = raspm.sample_planar(15, rng)
    q = raspm.inverse_planar(x)
    st = solve_restrained(raspm, q, th, K)
    assert st.success.all() and np.abs(st.deformation).max() > 1e-3  # the actuators do fight
    _, Ja = raspm.ik_jacobian(st.x, th)
    eq = np.einsum("nki,nk->ni", Ja, st.force)
    assert np.abs(eq).max() <= 1e-9 * np.abs(st.force).max() * np.abs(Ja).max()
    # compatibility with the deformed joints, in the constraint form |A - C| = l
    g = raspm._geometry(np.tile(th, (15, 1)))
    A, _, _ = raspm._joint_vectors(st.x, g)
    d = A - g.B - (q + st.deformation)[..., None] * g.u
    assert np.abs(np.linalg.norm(d, axis=2) - g.l).max() < 1e-9


def test_pose_independent_of_uniform_stiffness_scale(raspm):
    rng = np.random.default_rng(4)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance * 5
    q = raspm.inverse_planar(raspm.sample_planar(6, rng))
    a, b = solve_restrained(raspm, q, th, K), solve_restrained(raspm, q, th, 10 * K)
    assert np.allclose(a.x, b.x, atol=1e-10, rtol=0)
    assert np.allclose(b.force, 10 * a.force * 1.0, rtol=1e-6, atol=1e-6)


def test_linear_models_agree_with_the_physics(raspm):
    rng = np.random.default_rng(5)
    x = raspm.sample_planar(5, rng)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance * 1e-3  # tiny: the linearisation is exact to 1e-6
    G = raspm.ik_parameter_jacobian(x)
    _, Ja = raspm.ik_jacobian(x)
    e = -np.einsum("nkp,p->nk", G, th)
    q = raspm.inverse_planar(x)
    st = solve_restrained(raspm, q, th, K)
    dx, delta, lam = geometric_error_model(Ja, e, 1 / K)
    assert np.allclose(dx, st.x - x, atol=1e-6 * np.abs(st.x - x).max() + 1e-12)
    # projected model with the true compliance ratios reproduces it exactly, at any common scale
    dxp, P = applicable_error_model(Ja, e, weights=K)
    dxp10, _ = applicable_error_model(Ja, e, weights=10 * K)
    assert np.allclose(dxp, dx, atol=1e-12) and np.allclose(dxp10, dx, atol=1e-12)
    assert np.allclose(np.einsum("nij,nj->ni", P, delta), 0, atol=1e-12)


def test_noise_free_identification_recovers_parameters_and_ignores_stiffness_scale(raspm):
    rng = np.random.default_rng(6)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance
    truth = TrueModule(raspm, th, stiffness=np.full(4, 3e4))
    from bayescal.redundant.procedure import calibrate_zero

    zp = calibrate_zero(truth, raspm._home_x(), None)
    ctrl = PoseModel(raspm, zero=zp)
    xf, xt, _ = design_rm1(raspm.pose_range, 5, 4)
    xf2 = np.vstack([xf, np.tile([0, 0, 0.0], (5, 1))])
    xt2 = np.vstack([xt, np.column_stack([np.zeros(5), np.zeros(5), np.linspace(-0.4, 0.4, 5)])])
    results = []
    for scale in (1.0, 10.0):
        rec = measure_relative(truth.with_stiffness(truth.stiffness * scale), ctrl, np.zeros(raspm.n_params), xf2, xt2,
                               ("dx", "dz", "dry"), INSTRUMENTS["dial_gauge"], None)
        results.append(identify_step(ctrl, rec, np.zeros(raspm.n_params), step="SI", sigma=[1e-3, 1e-3, 5e-6], eta_min=1e-3))
    a, b = results
    assert a.identified == b.identified and np.allclose(a.theta_after, b.theta_after, atol=1e-9)
    # the identifiable combinations are recovered: the identified model predicts fresh relative measurements
    assert a.rms_after < 1e-4
    xf3 = np.tile([0.0, 0.0, 0.0], (6, 1))
    xt3 = np.column_stack([rng.uniform(-250, 250, 6), rng.uniform(-150, 150, 6), np.zeros(6)])
    fresh = measure_relative(truth, ctrl, np.zeros(raspm.n_params), xf3, xt3, ("dx", "dz"), INSTRUMENTS["dial_gauge"], None)
    y = ctrl.tool(np.vstack([fresh.q_from, fresh.q_to]), a.theta_after)
    pred = (y[6:] - y[:6])[:, :2]
    y0 = ctrl.tool(np.vstack([fresh.q_from, fresh.q_to]), np.zeros(raspm.n_params))
    assert np.abs(pred - fresh.values).max() < 1e-3 * np.abs((y0[6:] - y0[:6])[:, :2] - fresh.values).max() + 1e-6


def test_compatibility_zero_only_for_exact_geometry(raspm):
    rng = np.random.default_rng(9)
    x = raspm.sample_planar(4, rng)
    q = raspm.inverse_planar(x)
    assert np.abs(raspm.compatibility(q)).max() < 1e-9
    th = rng.normal(size=raspm.n_params) * raspm.tolerance
    c = raspm.compatibility(q, th)
    assert np.abs(c[:, list(raspm.nonredundant)]).max() < 1e-9 and np.abs(c[:, 1]).max() > 1e-3


def test_relative_recording_round_trip_and_errors(tmp_path):
    rec_text = "q1_from,q2_from,q1_to,q2_to,dx,line\n1,2,3,4,0.5,1\n"
    rec = read_relative_recording("r.csv", text=rec_text)
    assert rec.components == ("dx",) and rec.aux["line"].tolist() == [1.0]
    again = read_relative_recording("r.csv", text=relative_to_csv(rec))
    assert np.array_equal(again.values, rec.values)
    bad = {
        "q1_from,q1_to,dx\n1,2,\n": ("line 2", "dx", "empty"),
        "q1_from,q1_to,dx\n1,2,abc\n": ("line 2", "dx", "number"),
        "q1_from,q2_from,q1_to,dx\n1,2,3,4\n": ("line 1", "q2_to", "missing"),
        "q1_from,q1_to,line\n1,2,3\n": ("line 1", "", "measured"),
        "q1_from,q1_to,dx,dx\n1,2,3,4\n": ("line 1", "dx", "duplicate"),
        "q1_from,q1_to,dx\n1,2\n": ("line 2", "", "cells"),
    }
    for text, (line, col, word) in bad.items():
        with pytest.raises(RecordingError) as ei:
            read_relative_recording("bad.csv", text=text)
        msg = str(ei.value)
        assert "bad.csv" in msg and line in msg and col in msg and word in msg, msg


def test_anti_disturbance_closed_form_and_instrument_rounding():
    from bayescal.redundant.steps import Instrument, anti_disturbance

    rng = np.random.default_rng(12)
    A = rng.normal(size=(30, 5))
    eta, smin = anti_disturbance(A)
    assert np.allclose(eta, 1 / np.sqrt(np.diag(np.linalg.inv(A.T @ A))), rtol=1e-10)
    assert np.isclose(smin, np.linalg.svd(A, compute_uv=False)[-1])
    inst = Instrument("gauge", 1e-3, "mm")
    r = inst.read(np.full(2000, 0.01234), rng)
    assert np.allclose(r / 1e-3, np.round(r / 1e-3))  # whole resolution steps
    assert abs(r.mean() - 0.01234) < 3 * inst.sigma / np.sqrt(2000) + 1e-4
    assert inst.read(np.array([0.01234]), None)[0] == 0.01234


def test_practical_model_matches_the_zero_calibrated_physics(raspm):
    """Pitch-free truth with stiffnesses in the model's ratios, commanded through the zero-calibrated nominal model."""
    from bayescal.redundant.models import ZeroPosition, practical_error_model

    rng = np.random.default_rng(13)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance * 1e-3  # tiny: first order exact to ~1e-3 relative
    truth = TrueModule(raspm, th, stiffness=np.full(4, 3e4))
    x0 = raspm._home_x()
    zp = ZeroPosition(x0=x0, q0=truth.command_for(x0[None])[0])
    ctrl = PoseModel(raspm, zero=zp)
    x = raspm.sample_planar(6, rng)
    st = truth.settle(raspm.inverse_planar(x, ctrl.complete(np.zeros(raspm.n_params))))
    _, Ja = raspm.ik_jacobian(x)
    G = raspm.ik_parameter_jacobian(x)
    G0 = raspm.ik_parameter_jacobian(x0[None])[0]
    off = raspm.offset_index()
    H = practical_error_model(Ja, -G, -G0, off)
    rest = np.setdiff1d(np.arange(raspm.n_params), off)
    pred = np.einsum("nij,j->ni", H, th[rest])
    actual = st.x - x
    assert np.abs(actual).max() > 1e-6
    assert np.allclose(pred, actual, atol=2e-3 * np.abs(actual).max())


def test_relative_recording_limits_name_line_and_column():
    import numpy as np
    import pytest

    from bayescal.errors import RecordingError
    from bayescal.redundant.relative_io import RelativeRecording

    rec = RelativeRecording(
        q_from=np.array([[1.0, 2.0], [1.0, 2.0]]), q_to=np.array([[1.0, 2.0], [1.0, 9.0]]),
        components=("dx",), values=np.zeros((2, 1)), path="rel.csv",
    )
    limits = np.array([[0.0, 5.0], [0.0, 5.0]])
    with pytest.raises(RecordingError, match="outside q_limits") as err:
        rec.check_machine(2, limits)
    assert (err.value.row, err.value.column, err.value.path) == (3, "q2_to", "rel.csv")
