"""The model contract (bayescal.contract): every kind, measurement type, wrapper and effect passes check_model.

check_model compares each model with central differences of its own
prediction and with itself (a subset predicts its rows of the whole, a noise
scale scales the row sigma), so it is not the model's code checking itself
term by term; the planted defects at the end show that it can fail.
"""

from __future__ import annotations

import dataclasses
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bayescal.bayes.linear import linearise
from bayescal.constraints.model import ConstraintModel
from bayescal.constraints.simulate import simulate_ballbar, simulate_distances
from bayescal.contract import Model, ModelCheckError, check_model
from bayescal.effects.joint_model import effect_model
from bayescal.effects.stored import StoredEffect, StoredEffectsTransform
from bayescal.geometry import so3_exp, so3_log
from bayescal.instrument.prepare import prepare_model
from bayescal.machines.files import load_machine
from bayescal.machines.framed import Frame
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording

EX = Path(__file__).resolve().parents[1] / "examples"
N = 8  # poses: enough for a subset of every other one, few enough that every parameter's differences are cheap


def _pose_model(example: str, dof: int = 6, seed: int = 1):
    m = load_machine(EX / example / "machine.toml")
    rec = simulate_recording(m, N, seed=seed, dof=dof).recording
    return MeasurementModel.from_recording(m, rec, dof=dof)


def _stations():
    m = load_machine(EX / "prs3" / "machine.toml")
    rec = simulate_recording(m, N, seed=3, dof=6).recording
    labels = np.array(["east", "west"] * (N // 2))
    frames = {"east": Frame.from_rotation_vector([1500.0, -200.0, 300.0], [0.3, -1.2, 0.4]),
              "west": Frame.from_rotation_vector([-900.0, 2500.0, -100.0], [2.0, 0.1, -0.5])}
    pos, rv = rec.position.copy(), rec.rotvec.copy()
    for k, f in frames.items():
        s = labels == k
        pos[s] = f.to_instrument(rec.position[s])
        rv[s] = so3_log(f.rotation.T @ so3_exp(rec.rotvec[s]))
    stationed = replace(rec, position=pos, rotvec=rv, station=tuple(labels.tolist()))
    return prepare_model(m, stationed, frame="fit")[1]


def _fitted_frame():
    m = load_machine(EX / "prs3" / "machine.toml")
    rec = simulate_recording(m, N, seed=4, dof=6).recording
    return prepare_model(m, rec, frame="fit")[1]


def sensor_column():
    """The sensor test column (tests/sensors/chain.py) and a recording with tilt sensors on joints 2 and 3."""
    from tests.sensors.chain import JOINTS, machine_text, poses, transforms

    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "column.toml"
        p.write_text(machine_text(JOINTS, sigma_tilt=1e-4, sigma_position=0.05))
        m = load_machine(p)
    q = poses(N, 2)
    frames, tool = transforms(JOINTS, q)
    aux = {}
    for k in (1, 2):
        Rb = np.array([f[k][:3, :3] for f in frames])
        u = np.einsum("nkj,k->nj", Rb, [0.0, 0.0, 1.0])
        aux.update({f"accel.joint{k + 1}.{a}": 9.81 * u[:, i] for i, a in enumerate("xyz")})
    from bayescal.io.recording import Recording

    return m, Recording(q=q, position=tool, aux=aux)


def _sensors(effect: StoredEffect | None = None):
    m, rec = sensor_column()
    if effect is not None:  # the sensors' rows move with the effect's dq too (joint2 and joint3 turn with q1, q3)
        model = effect_model(m.with_effects((effect,)), rec)
        assert model.geo.sensors is not None
        return model
    model = MeasurementModel.from_recording(m, rec)
    assert model.sensors is not None and model.dof > model.tool_dof
    return model


def _constraints(kind: str):
    if kind == "distances":
        m = load_machine(EX / "delta" / "machine.toml")
        rec = simulate_distances(m, N, seed=5).recording
    else:
        m = load_machine(EX / "prs3" / "machine.toml")
        rec = simulate_ballbar(m, 25.0, seed=6, n_points=N).recording
    return ConstraintModel.from_recording(m, rec)


BACKLASH = StoredEffect("backlash", (("backlash.q1", 20.0), ("backlash.q2", 30.0), ("backlash.q3", 25.0)))
COMPLIANCE = StoredEffect("joint_compliance", (("compliance.q1", 0.4), ("compliance.q2", 0.6), ("compliance.q3", 0.5),
                                               ("platform_mass", 30.0), ("com.x", 5.0), ("com.y", -3.0), ("com.z", 10.0),
                                               ("gravity.tilt_1", 0.01), ("gravity.tilt_2", -0.02)))


# the column's stage and the arm bend; the sensors on joint2 (the stage's tip) and joint3 turn with them
DEFLECTION = StoredEffect("gravity_deflection", (("bending.joint2", 40.0), ("bending.link1", 10.0), ("bending.link3", 60.0),
                                                 ("gravity.tilt_1", 0.01), ("gravity.tilt_2", -0.02)),
                          settings=(("link_mass_kg", [20.0, 15.0, 8.0]),))
SERIAL_BACKLASH = StoredEffect("backlash", (("backlash.q1", 0.002), ("backlash.q2", 30.0), ("backlash.q3", 0.003)))


def _effects(stored: StoredEffect, aux_name: str | None):
    m = load_machine(EX / "prs3" / "machine.toml").with_effects((stored,))
    aux = None if aux_name is None else {aux_name: np.random.default_rng(5).uniform(0.0, 25.0, N)}
    rec = simulate_recording(m, N, seed=12, effects=[StoredEffectsTransform(m, m.effects)], aux=aux).recording
    return effect_model(m, rec)


CASES = {
    "prs3-6dof": lambda: _pose_model("prs3"),
    "prs3-5dof": lambda: _pose_model("prs3", dof=5),
    "prs3-3dof": lambda: _pose_model("prs3", dof=3),
    "rupus_prs": lambda: _pose_model("rupus_prs"),
    "raspm": lambda: _pose_model("raspm", dof=3),
    "serial-arm6": lambda: _pose_model("arm6"),
    "serial-urdf-telescope": lambda: _pose_model("telescope", dof=3),
    "hybrid-table": lambda: _pose_model("hybrid_table"),
    "linear-delta": lambda: _pose_model("delta", dof=3),
    "instrument-frame-fitted": _fitted_frame,
    "two-stations": _stations,
    "body-sensors": _sensors,
    "constraints-heights-distances": lambda: _constraints("distances"),
    "constraints-ballbar-pivots": lambda: _constraints("ballbar"),
    "effect-backlash": lambda: _effects(BACKLASH, None),
    "effect-compliance": lambda: _effects(COMPLIANCE, "payload_kg"),
    "effect-backlash-body-sensors": lambda: _sensors(SERIAL_BACKLASH),
    "effect-deflection-body-sensors": lambda: _sensors(DEFLECTION),
    "linearised-prs3": lambda: linearise(_pose_model("prs3")),
    "linearised-ballbar-pivots": lambda: linearise(_constraints("ballbar")),
    "linearised-body-sensors": lambda: linearise(_sensors()),
}


@pytest.mark.parametrize("case", list(CASES))
def test_every_model_keeps_the_contract(case):
    model = CASES[case]()
    assert isinstance(model, Model)
    assert check_model(model) == []


# ------------------------------------------------------------------ the check can fail


@pytest.fixture(scope="module")
def model():
    return _pose_model("prs3")


class _Wrapped:
    """A model with one behaviour changed; everything else forwarded."""

    def __init__(self, inner, **changed):
        self._inner, self._changed = inner, changed

    def __getattr__(self, name):
        if name in self._changed:
            return self._changed[name]
        return getattr(self._inner, name)


def test_a_wrong_jacobian_column_is_named(model):
    def jacobian(theta, prediction):
        J = model.jacobian(theta, prediction).copy()
        J[:, :, 4] *= 1.01
        return J

    problems = check_model(_Wrapped(model, jacobian=jacobian))
    assert len(problems) == 1 and f"column 4 ({model.machine.layout.names[4]})" in problems[0]


def test_a_subset_that_predicts_other_rows_is_caught(model):
    problems = check_model(_Wrapped(model, subset=lambda idx: model.subset(np.asarray(idx)[::-1])))
    assert len(problems) == 1 and problems[0].startswith("subset")


def test_a_pose_sigma_that_does_not_scale_is_caught(model):
    problems = check_model(_Wrapped(model, with_pose_sigma=lambda s: model))
    assert problems == ["with_pose_sigma(2 row_sigma).row_sigma is not 2 row_sigma"]


def test_a_missing_member_is_named_and_strict_raises(model):
    class Partial:
        def __getattr__(self, name):
            if name == "theta_start":
                raise AttributeError(name)
            return getattr(model, name)

    assert check_model(Partial()) == ["missing member(s) of the model contract: theta_start"]
    with pytest.raises(ModelCheckError, match="theta_start"):
        check_model(Partial(), strict=True)


def test_a_residual_of_the_wrong_sign_is_caught(model):
    problems = check_model(_Wrapped(model, residual=lambda p: p.y - model.y_measured))
    assert problems == ["residual is not y_measured - predict(theta).y"]


def test_the_wrapper_classes_keep_the_contract_by_construction():
    """Frozen dataclasses with replace: a model's with_* returns a model of the same contract."""
    m = _pose_model("prs3")
    for other in (m.with_pose_sigma(2 * m.row_sigma), m.subset([0, 2]), m.without_sensors()):
        assert isinstance(other, Model) and dataclasses.is_dataclass(other)


def test_a_linearised_model_without_its_sensors_keeps_the_tool_rows():
    lin = linearise(_sensors())
    tool = lin.without_sensors()
    assert tool.dof == lin.tool_dof and tool.sensors is None
    assert check_model(tool) == []
    theta = 0.1 * np.asarray(lin.machine.tolerance)
    np.testing.assert_array_equal(tool.predict(theta).y, lin.predict(theta).y[:, : lin.tool_dof])


def test_a_linearised_model_refuses_to_move_its_poses():
    from bayescal.errors import InputError

    lin = linearise(_pose_model("prs3"))
    assert lin.with_pose_offset(None) is lin
    with pytest.raises(InputError, match="linearise"):
        lin.with_pose_q(lin.q + 1.0)
    with pytest.raises(InputError, match="linearise"):
        lin.with_pose_offset(np.zeros((lin.n_poses, 6)))


# ------------------------------------------------------------------ the result contract


@pytest.fixture(scope="module")
def recorded():
    """The bundled 3-PRS recording as a model (every method answers it)."""
    from bayescal.io.recording import read_recording

    m = load_machine(EX / "prs3" / "machine.toml")
    return MeasurementModel.from_recording(m, read_recording(EX / "prs3" / "recording.csv"))


def _registry_result(model, name):
    from bayescal.compare.methods import METHODS, MethodSpec

    options = {"ridge": (("lam", 0.5),), "mcmc": (("steps", 40),)}.get(name, ())
    assert name in METHODS
    return MethodSpec(label=name, name=name, options=options).run(model, free="auto")


@pytest.mark.parametrize("name", ["ls", "ridge", "tsvd", "map", "kalman", "mcmc"])
def test_every_methods_result_keeps_the_contract(recorded, name):
    import warnings

    from bayescal.contract import Result, check_result

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a 40-step chain warns that it is short; its answer must still conform
        res = _registry_result(recorded, name)
    assert isinstance(res, Result) and res.method == name
    assert check_result(res, recorded) == []
    # the prior's effective parameters: none for least squares, a hat-matrix trace below the free count otherwise
    pe = res.prior_effective_params
    assert (pe is None) if name == "ls" else (name == "mcmc" and not res.success) or 0 < pe < res.free.sum()


def test_the_front_door_answers_keep_the_result_contract():
    import bayescal
    from bayescal.contract import check_result

    session = bayescal.load(EX / "prs3" / "machine.toml", EX / "prs3" / "recording.csv")
    for method in ("ls", "kalman"):
        answer = bayescal.calibrate(session, method=method)
        assert check_result(answer.result, answer.model) == []


def test_a_result_with_a_wrong_covariance_or_a_missing_member_is_caught(recorded):
    from bayescal.contract import check_result
    from bayescal.identify import identify

    res = identify(recorded, method="ridge", lam=1.0)
    n = int(res.free.sum())
    assert check_result(replace(res, covariance=np.eye(n + 1)), recorded) == [
        f"covariance: shape ({n + 1}, {n + 1}), expected ({n}, {n})"]

    class Partial:
        def __getattr__(self, name):
            if name == "prior_effective_params":
                raise AttributeError(name)
            return getattr(res, name)

    assert check_result(Partial()) == ["missing member(s) of the result contract: prior_effective_params"]


def test_whiten_into_the_values_themselves_gives_the_same_values(prs3, rng):
    """``whiten(model, J, out=J)`` (the joint fit's system, in place) is ``whiten(model, J)`` bit for bit."""
    from bayescal.contract import whiten
    from bayescal.effects.simulate import simulate_with_effects
    from bayescal.measurement import MeasurementModel

    sim = simulate_with_effects(prs3, 9, seed=2, dof=6, effects=[("thermal_expansion", 25.0)], record=("temp_C",))
    model = MeasurementModel.from_recording(prs3, sim.recording)
    for shape in ((9, 6), (9, 6, 4)):
        v = rng.normal(size=shape)
        want = whiten(model, v)
        got = whiten(model, v.copy(), out=(w := v.copy()))
        assert got is w and np.array_equal(got, want)
