"""The instrument-frame wrapper: Jacobian, file round trip, and frames recovered on simulated recordings."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.bayes.priors import map_estimate
from bayescal.errors import MachineFileError
from bayescal.geometry import so3_log
from bayescal.instrument import align_frame, prepare_model
from bayescal.machines.check import check_machine
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.machines.framed import FRAME_NAMES, Frame, InstrumentFrame
from bayescal.simulate import simulate_recording
from tests.instrument.frames import random_frame, to_instrument

ROOT = Path(__file__).resolve().parents[2]
KINDS = ("prs3", "rupus_prs", "raspm")


@pytest.fixture(scope="module")
def machines():
    return {k: load_machine(ROOT / "examples" / k / "machine.toml") for k in KINDS}


def _framed(machine, rng):
    o, R = random_frame(rng)
    return InstrumentFrame(machine, Frame(o, R), fit=True)


@pytest.mark.parametrize("kind", KINDS)
def test_jacobian_matches_central_differences(machines, kind):
    rng = np.random.default_rng(1)
    m = _framed(machines[kind], rng)
    q = m.sample_q(4, rng)
    theta = rng.normal(size=m.n_params) * np.concatenate([[5.0] * 3, [0.3] * 3, m.machine.tolerance])
    poses = m.forward(q, theta)
    assert poses.success.all()
    J = m.tool_jacobian(q, theta, poses)
    cols = list(range(6)) + list(rng.choice(np.arange(6, m.n_params), 6, replace=False))
    for j in cols:
        # steps well above round-off of tool points metres from the base (|p| ~ 3e3 mm)
        h = 1e-3 if m.layout.units[j] == "mm" else 1e-6
        d = np.zeros(m.n_params)
        d[j] = h
        p, mn = m.forward(q, theta + d, guess=poses), m.forward(q, theta - d, guess=poses)
        fd_p = (p.position - mn.position) / (2 * h)
        fd_r = so3_log(p.rotation @ np.swapaxes(mn.rotation, 1, 2)) / (2 * h)
        scale = max(np.abs(J[:, :, j]).max(), 1e-9)
        assert np.abs(J[:, :3, j] - fd_p).max() < 1e-5 * scale + 2e-6, m.layout.names[j]
        assert np.abs(J[:, 3:, j] - fd_r).max() < 1e-5 * scale + 2e-6, m.layout.names[j]


def test_forward_is_the_rigid_transform_of_the_base_machine(machines):
    rng = np.random.default_rng(2)
    base = machines["prs3"]
    o, R = random_frame(rng)
    m = InstrumentFrame(base, Frame(o, R), fit=False)
    assert m.layout == base.layout and m.kind == base.kind
    q = base.sample_q(5, rng)
    theta = rng.normal(size=base.n_params) * base.tolerance
    pb, pi = base.forward(q, theta), m.forward(q, theta)
    assert np.allclose(pi.position @ R.T + o, pb.position, atol=1e-9)
    assert np.allclose(R @ pi.rotation, pb.rotation, atol=1e-12)


def test_layout_puts_the_frame_first(machines):
    m = InstrumentFrame(machines["prs3"], Frame.identity())
    assert m.layout.names[:6] == FRAME_NAMES
    assert m.layout.names[6:] == machines["prs3"].layout.names
    assert m.n_params == machines["prs3"].n_params + 6


def test_passes_the_machine_conformance_check(machines):
    # the check draws theta from the tolerances; guess_from_measurement starts from frame0, so the
    # drawn frame corrections must be of the size a closed-form start leaves (mm, mrad), not 1 m
    o, R = random_frame(np.random.default_rng(3))
    m = InstrumentFrame(machines["prs3"], Frame(o, R), frame_tolerance={"frame_origin": 1.0, "frame_rotation": 1e-3})
    assert check_machine(m) == []
    assert check_machine(InstrumentFrame(machines["rupus_prs"], Frame(o, R), fit=False)) == []


def test_to_toml_carries_the_instrument_table_and_reads_back(machines):
    rng = np.random.default_rng(4)
    m = _framed(machines["prs3"], rng)
    theta = rng.normal(size=m.n_params) * np.concatenate([[3.0] * 3, [0.1] * 3, m.machine.tolerance])
    text = m.to_toml(theta)
    assert "[instrument]" in text
    back = machine_from_text(text)
    assert isinstance(back, InstrumentFrame) and not back.fit
    assert back.n_params == m.machine.n_params
    q = m.sample_q(6, rng)
    a, b = m.forward(q, theta), back.forward(q)
    assert np.abs(a.position - b.position).max() < 1e-8
    f = m.frame_at(theta)
    assert np.allclose(back.frame0.origin, f.origin) and np.allclose(back.frame0.rotation, f.rotation, atol=1e-12)
    # the geometry stays in the base frame: the inner machine equals the base machine at theta
    assert np.abs(back.machine.forward(q).position - m.machine.forward(q, theta[6:]).position).max() < 1e-8


def test_instrument_table_is_read_strictly():
    text = (ROOT / "examples" / "prs3" / "machine.toml").read_text() + "\n[instrument]\norigin = [1.0, 2.0]\n"
    with pytest.raises(MachineFileError, match="instrument.origin"):
        machine_from_text(text)
    text2 = (ROOT / "examples" / "prs3" / "machine.toml").read_text() + "\n[instrument]\norigin = [1.0, 2.0, 3.0]\nrot = 1\n"
    with pytest.raises(MachineFileError, match="instrument.rot"):
        machine_from_text(text2)


@pytest.mark.parametrize("max_angle", [np.pi, np.radians(179.5)])
def test_alignment_recovers_large_rotations_and_translations(max_angle):
    rng = np.random.default_rng(5)
    p = rng.normal(size=(30, 3)) * 200
    for _ in range(20):
        o, R = random_frame(rng, max_angle=max_angle, max_offset=5000)
        pin = (p - o) @ R
        f = align_frame(pin, p)
        assert np.abs(f.rotation - R).max() < 1e-10 and np.abs(f.origin - o).max() < 1e-8


def _fit(machine, rec, dof, frame):
    m, model, _ = prepare_model(machine, rec, dof=dof, frame=frame)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = map_estimate(model, free="auto")
    assert res.success, res.message
    return m, res


def _rms(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("dof", [6, 5, 3])
def test_frame_fit_equals_base_frame_calibration(machines, kind, dof):
    """In a random frame (up to 180 deg, metres away), --frame fit calibrates the machine as the base frame does."""
    machine = machines[kind]
    seed = {"prs3": 10, "rupus_prs": 20, "raspm": 30}[kind] + dof
    rng = np.random.default_rng(seed)
    n = 40 if kind != "rupus_prs" else 60
    sim = simulate_recording(machine, n, seed=seed, dof=dof)
    o, R = random_frame(rng)
    rec_i = to_instrument(sim.recording, o, R)
    mb, rb = _fit(machine, sim.recording, dof, "base")
    mf, rf = _fit(machine, rec_i, dof, "fit")
    # the gauge shared by the frame and the machine's base parameters is reported by name (MAP with
    # free="auto" estimates both and reports it as decided by the prior)
    assert any("frame." in c for c in rf.decided_by_prior)
    q = machine.sample_q(60, np.random.default_rng(99))
    truth = machine.forward(q, sim.theta_true)
    # what the instrument reads at fresh poses: predicted with the fitted frame, gauge-free
    pred_i = mf.forward(q, rf.theta)
    true_i = (truth.position - o) @ R
    base_err = _rms(machine.forward(q, rb.theta).position, truth.position)
    sp = machine.noise.sigma_position
    assert _rms(pred_i.position, true_i) < 1.5 * base_err + 2 * sp
    # the calibrated geometry in the base frame equals the base-frame calibration up to the gauge (a rigid motion)
    pf = mf.machine.forward(q, rf.theta[6:]).position
    pb = machine.forward(q, rb.theta).position
    f = align_frame(pf, pb)
    assert _rms(f.to_base(pf), pb) < 1.0 * base_err + 2 * sp
    # and the fitted frame is the true one up to that same rigid motion
    fit = mf.frame_at(rf.theta)
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(fit.rotation.T @ R).as_rotvec())) < 0.5
    assert np.linalg.norm(fit.origin - o) < 20.0


def test_answer_does_not_depend_on_the_frame_width(machines):
    machine = machines["prs3"]
    sim = simulate_recording(machine, 36, seed=41, dof=6)
    o, R = random_frame(np.random.default_rng(41))
    rec_i = to_instrument(sim.recording, o, R)
    m, model, _ = prepare_model(machine, rec_i, frame="fit")
    # 10 times wider (1 m, 1 rad)
    wide = InstrumentFrame(m.machine, m.frame0, fit=True, frame_tolerance={"frame_origin": 1e3, "frame_rotation": 1.0})
    from bayescal.measurement import MeasurementModel

    model_w = MeasurementModel.from_recording(wide, rec_i)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = map_estimate(model, free="all")
        b = map_estimate(model_w, free="all")
    assert a.success and b.success
    std = a.std
    assert np.all(np.abs(a.theta - b.theta) < 1e-3 * np.maximum(std, 1e-12) + 1e-9)
    assert np.allclose(a.std, b.std, rtol=1e-3)


@pytest.mark.parametrize("method,kw", [("ls", {}), ("ridge", {"lam": 1.0}), ("tsvd", {"k": 16}), ("ridge", {"lam": "auto"})])
def test_every_deterministic_method_fits_the_frame(machines, method, kw):
    from bayescal.identify import identify
    from bayescal.identify.choose import choose_regularisation

    machine = machines["raspm"]
    sim = simulate_recording(machine, 40, seed=51, dof=6)
    o, R = random_frame(np.random.default_rng(51))
    m, model, _ = prepare_model(machine, to_instrument(sim.recording, o, R), frame="fit")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kw.get("lam") == "auto":
            _, res = choose_regularisation(model, "ridge")
        else:
            res = identify(model, method=method, **kw)
    assert res.success, res.message
    q = machine.sample_q(40, np.random.default_rng(7))
    true_i = (machine.forward(q, sim.theta_true).position - o) @ R
    # what the instrument reads at fresh poses, predicted through the fitted frame
    assert _rms(m.forward(q, res.theta).position, true_i) < 5 * machine.noise.sigma_position


def _two_machines():
    serial = load_machine(ROOT / "examples" / "positioner" / "machine.toml")
    return serial, load_machine(ROOT / "examples" / "prs3" / "machine.toml")


def test_columns_of_the_framed_jacobian_are_the_whole_jacobians_bit_for_bit():
    """tool_jacobian_columns through a fitted frame (issue 32: a fit asks only for its free columns): the whole
    Jacobian's columns bit for bit (the whole one is checked against central differences above), one station or
    two, over a serial chain (which computes only its blocks asked for) and a parallel kind (which slices); any
    subset, the frame's columns alone, the machine's alone, and one machine column (whose rotation would be a
    matrix-vector product, other round-off)."""
    rng = np.random.default_rng(21)
    for inner in _two_machines():
        q = inner.sample_q(6, rng)
        o, R = random_frame(rng)
        for m in (InstrumentFrame(inner, Frame(o, R), fit=True),
                  InstrumentFrame(inner, stations=("a", "b"), frames0=(Frame(o, R), Frame.identity()),
                                  pose_station=np.array([0, 1, 1, 0, 1, 0]))):
            P, k = m.n_params, m.n_frame
            theta = rng.normal(size=P) * np.concatenate([[5.0, 5.0, 5.0, 0.3, 0.3, 0.3] * m.n_stations,
                                                          inner.tolerance])
            poses = m.forward(q, theta)
            whole = m.tool_jacobian(q, theta, poses)
            picks = [np.arange(P), np.arange(k), np.arange(k, P), np.array([k + 2]), np.r_[np.arange(k), k + 1],
                     np.r_[1, 4, k + 3], np.array([0, 5])]
            picks += [np.sort(rng.choice(P, size=rng.integers(2, P), replace=False)) for _ in range(8)]
            for cols in picks:
                got = m.tool_jacobian_columns(q, theta, poses, cols)
                assert got.shape == (6, 6, cols.size) and np.array_equal(got, whole[:, :, cols]), (inner.kind, cols)


def test_the_remembered_frame_follows_the_parameters():
    """The frame of the last parameters is remembered (issue 32: a step asks for it three times at one point):
    other parameters get their own frame, the same ones the same frame as a fresh wrapper's, read-only."""
    serial, _ = _two_machines()
    rng = np.random.default_rng(22)
    o, R = random_frame(rng)
    m, fresh = InstrumentFrame(serial, Frame(o, R), fit=True), InstrumentFrame(serial, Frame(o, R), fit=True)
    q = serial.sample_q(4, rng)
    t1, t2 = (np.concatenate([rng.normal(size=6) * [5, 5, 5, 0.3, 0.3, 0.3], np.zeros(serial.n_params)])
              for _ in range(2))
    a, b = m.forward(q, t1), m.forward(q, t2)
    Jb = m.tool_jacobian(q, t2, b)  # at the remembered frame
    again = m.forward(q, t1)
    assert not np.allclose(a.position, b.position)
    assert np.array_equal(again.position, a.position) and np.array_equal(again.rotation, a.rotation)
    assert np.array_equal(b.position, fresh.forward(q, t2).position)
    assert np.array_equal(Jb, fresh.tool_jacobian(q, t2, b))
    _, R2 = m._frame_arrays(t2[:6], 4)
    assert not R2.flags.writeable
