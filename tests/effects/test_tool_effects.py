"""Effects that move the tool, not a joint (gravity_deflection): one mechanism, every consumer.

The stored application in predictions (MeasurementModel.from_recording, also
through an instrument frame: the base-frame perturbation rotated into the
measurement frame), constraint recordings, the joint fit's Jacobian, the
identify --fit-effects model, the simulator and the compensation grid.
Expected values are built by hand from the machine's forward kinematics and
the effect's dx, or by finite differences.
"""

from pathlib import Path

import numpy as np

from bayescal.effects import get_effect
from bayescal.effects.joint_model import effect_model
from bayescal.effects.model import effect_columns, _slices
from bayescal.effects.stored import StoredEffect, StoredEffectsTransform, machine_file_text, predict_poses
from bayescal.geometry import so3_exp, so3_log
from bayescal.io.recording import Recording
from bayescal.machines.files import machine_from_text
from bayescal.measurement import MeasurementModel
from bayescal.simulate import measure

ROOT = Path(__file__).resolve().parents[2]
TELESCOPE = (ROOT / "examples" / "telescope" / "machine.toml").read_text()
MASSES = {"link_mass_kg": [30.0, 20.0, 25.0, 6.0], "link_com_mm": [[0.0, 0, 30], [40.0, 0, 10], [100.0, 0, 0], [25.0, 0, 5]]}
VALUES = (("bending.joint1", 8.0), ("bending.link3", 12.0), ("gravity.tilt_1", 0.01), ("gravity.tilt_2", -0.02))
INSTRUMENT = '\n[instrument]\norigin = [1500.0, -800.0, 200.0]\nrotation_vector = [0.1, -0.2, 2.5]\n'


def _table():
    return StoredEffect("gravity_deflection", VALUES, settings=tuple((k, v) for k, v in MASSES.items()))


def _dx(machine, q, aux=None):
    eff = get_effect("gravity_deflection", **MASSES)
    f = eff.features(machine, q, np.zeros(machine.n_params), aux or {}, None, None)
    return eff.delta_x(f, np.array([v for _, v in VALUES]))


def test_stored_table_moves_the_tool_in_every_prediction(rng):
    base = machine_from_text(TELESCOPE, "t.toml")
    m = base.with_effects((_table(),))
    q = base.sample_q(8, rng)
    dx = _dx(base, q)
    assert np.abs(dx[:, :3]).max() > 0.05  # tenths of a mm
    # by hand: the rigid tool moved by dx and turned by exp([w]x)
    rigid = base.forward(q)
    got = predict_poses(m, q)
    np.testing.assert_allclose(got.position, rigid.position + dx[:, :3], atol=1e-12)
    np.testing.assert_allclose(so3_log(got.rotation @ np.swapaxes(rigid.rotation, 1, 2)), dx[:, 3:], atol=1e-12)
    # a noise-free recording of the machine with the table is predicted exactly from the file (the loads at the file's
    # geometry: at a geometry off it by the tolerances they differ by a few 1e-4 relative)
    theta = np.zeros(base.n_params)
    rec = measure(base, q, theta, 6, None, effects=[StoredEffectsTransform(base, (_table(),))])
    model = MeasurementModel.from_recording(m, rec)
    assert model.pose_offset is not None
    np.testing.assert_allclose(model.residual(model.predict(theta)), 0.0, atol=1e-9)
    # the file as written reads back with its table and predicts the same
    again = machine_from_text(machine_file_text(m), "again.toml")
    np.testing.assert_allclose(predict_poses(again, q).position, got.position, atol=1e-9)


def test_through_an_instrument_frame_the_offset_is_rotated_into_the_measurement_frame(rng):
    framed = machine_from_text(TELESCOPE + INSTRUMENT, "f.toml").with_effects((_table(),))
    base = machine_from_text(TELESCOPE, "t.toml")
    q = base.sample_q(6, rng)
    dx = _dx(base, q)
    # by hand, docs/formats.md section 4: p_base = R p_instrument + origin
    R = so3_exp(np.array([0.1, -0.2, 2.5]))
    origin = np.array([1500.0, -800.0, 200.0])
    p_base = base.forward(q).position + dx[:, :3]
    R_base = so3_exp(dx[:, 3:]) @ base.forward(q).rotation
    want_p = (p_base - origin) @ R
    want_R = R.T @ R_base
    rec = Recording(q=q, position=want_p, rotvec=so3_log(want_R), axis=None, aux={})
    model = MeasurementModel.from_recording(framed, rec)
    np.testing.assert_allclose(model.residual(model.predict(None)), 0.0, atol=1e-9)


def test_joint_fit_columns_of_a_tool_effect_by_finite_differences(rng):
    # a fitted instrument frame: the effect's columns go through each pose's measurement rotation
    framed = machine_from_text(TELESCOPE + INSTRUMENT, "f.toml").with_effects((_table(),))
    theta = np.zeros(framed.n_params)
    q = framed.sample_q(5, rng)
    rec = measure(framed.with_effects(()), q, theta, 6, rng)
    em = effect_model(framed, rec)
    th = em.theta_start + 1e-3 * rng.normal(size=em.n_params) * em.machine.tolerance
    pred = em.predict(th)
    J = em.jacobian(th, pred)
    P = em.machine.n_base
    for k in range(P, em.n_params):
        e = np.zeros(em.n_params)
        e[k] = 1e-4 * em.machine.tolerance[k]
        fd = (em.predict(th + e).y - em.predict(th - e).y) / (2 * e[k])
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max() + 1e-12)
    # stacked parameter sets (one block per walker) predict each block with its own effect values
    two = np.vstack([np.tile(th, (5, 1)), np.tile(th + np.r_[np.zeros(P), 1.0, 0, 0, 0], (5, 1))])
    y = em.predict(two).y
    np.testing.assert_allclose(y[:5], pred.y, atol=1e-12)
    np.testing.assert_allclose(y[5:], em.predict(th + np.r_[np.zeros(P), 1.0, 0, 0, 0]).y, atol=1e-12)


def test_effect_columns_of_a_pose_model_equal_finite_differences(rng):
    base = machine_from_text(TELESCOPE, "t.toml")
    q = base.sample_q(6, rng)
    rec = measure(base, q, np.zeros(base.n_params), 5, rng)  # 5-DOF rows: the axis sees the rotation
    model = MeasurementModel.from_recording(base, rec)
    eff = get_effect("gravity_deflection")  # unknown masses: bilinear
    f = eff.features(base, q, np.zeros(base.n_params), {}, None, None)
    eta = np.array([p.start_value for p in eff.params(base, f)]) + 0.3
    from bayescal.effects.model import _predict, _dx, _dq

    def rows(e):
        sl = _slices([(eff, f)], model)
        return _predict(model, model.pose_q + _dq([(eff, f)], sl, e, q.shape), np.zeros(base.n_params), None,
                        dx=_dx([(eff, f)], sl, e, 6))

    sub, pred = rows(eta)
    cols, _ = effect_columns(sub, np.zeros(base.n_params), pred, [(eff, f)], _slices([(eff, f)], model), eta)
    for k in range(len(eta)):
        e = np.zeros(len(eta))
        e[k] = 1e-5 * max(abs(eta[k]), 1.0)
        fd = (rows(eta + e)[1].y - rows(eta - e)[1].y) / (2 * e[k])
        np.testing.assert_allclose(cols[0][:, :, k], fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max() + 1e-12)


def test_constraint_recordings_see_the_tool_moved(rng):
    from bayescal.constraints.model import ConstraintModel
    from bayescal.io.constraints import ConstraintRecording

    base = machine_from_text(TELESCOPE, "t.toml")
    m = base.with_effects((_table(),))
    qa, qb = base.sample_q(4, rng), base.sample_q(4, rng)
    pa = base.forward(qa).position + _dx(base, qa)[:, :3]
    pb = base.forward(qb).position + _dx(base, qb)[:, :3]
    measure_ = ("distance", "height", "distance", "height")
    value = np.array([np.linalg.norm(pa[i] - pb[i]) if measure_[i] == "distance" else pa[i, 2] for i in range(4)])
    qb_rows = np.where(np.array([x == "distance" for x in measure_])[:, None], qb, np.nan)
    rec = ConstraintRecording(measure=measure_, qa=qa, qb=qb_rows, pivot=("",) * 4, value=value, aux={}, path="c.csv")
    model = ConstraintModel.from_recording(m, rec)
    np.testing.assert_allclose(model.residual(model.predict(None)), 0.0, atol=1e-9)


def test_compensation_grid_nodes_include_the_tool_offset():
    from bayescal.bayes.grid import compensation_grid

    base = machine_from_text(TELESCOPE, "t.toml")
    m = base.with_effects((_table(),))
    g0 = compensation_grid(base, np.zeros(base.n_params), covariance=1e-12 * np.eye(base.n_params), free=np.ones(base.n_params, bool), n=3)
    g1 = compensation_grid(m, np.zeros(base.n_params), covariance=1e-12 * np.eye(base.n_params), free=np.ones(base.n_params, bool), n=3)
    q = np.array([[a, b] for a in g0.axes[0] for b in g0.axes[1]])
    np.testing.assert_allclose((g0.correction - g1.correction).reshape(-1, 3), _dx(base, q)[:, :3], atol=1e-9)
