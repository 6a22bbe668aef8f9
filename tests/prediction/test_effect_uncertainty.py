"""The [effect.*] tables' parameters carry their uncertainty into predict (their block of [calibration]).

Checked against Monte Carlo, not the engine's own formula: with every geometric parameter at zero variance and
the effect parameters given a covariance in the record, the predicted variance of each measured component
exceeds the noise's by the variance of the rows over draws of the effect parameters from that covariance, each
draw's tables applied by rebuilding the model (1,500 draws: the variance ratios' standard error is about 4 %).
And the diagnosis writes the selected effects' parameters into the record it writes.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from bayescal.io.recording import read_recording
from bayescal.machines.files import machine_from_text
from bayescal.measurement import MeasurementModel
from bayescal.prediction.record import CalibrationRecord, calibration_toml, effect_parameter_names
from bayescal.prediction.recording import _moved_tables, predict_recording
from tests.conftest import ROOT
from tests.identify.test_gauss_newton import TELESCOPE_DEFLECTION

FOLDER = ROOT / "examples" / "telescope"
#: one-sigma uncertainty given to each table parameter (um/N, um/N, kg, kg, kg, rad, rad)
EFFECT_STD = np.array([1.0, 0.5, 2.0, 3.0, 2.0, 1e-4, 2e-4])


def _recording():
    """session b's poses and base inclinometer (tool rows only, no stations), every row a check row."""
    rec = read_recording(FOLDER / "session_b.csv")
    keep = np.arange(0, rec.n_poses, 3)
    rec = rec.subset(keep)
    aux = {k: v for k, v in rec.aux.items() if k.startswith("accel.base")}
    # every row held out: the measured values (station frames, not the base frame) take no part, and no fit row
    # tests the predictive regions (predict widens those its fit rows contradict)
    return replace(rec, aux=aux, station=None, role=("check",) * rec.n_poses)


def _machine(names, cov, geometry_names):
    text = (FOLDER / "machine.toml").read_text() + TELESCOPE_DEFLECTION
    plain = machine_from_text(text, str(FOLDER / "machine.toml"))
    all_names = tuple(geometry_names) + tuple(names)
    C = np.zeros((len(all_names),) * 2)
    C[len(geometry_names):, len(geometry_names):] = cov
    rec = CalibrationRecord(all_names, C, 1.0, "map", 1.0)
    return machine_from_text(text + "\n" + calibration_toml(rec), str(FOLDER / "machine.toml")), plain


def test_effect_parameters_uncertainty_reaches_the_rows_as_monte_carlo_says():
    rng = np.random.default_rng(7)
    plain = machine_from_text((FOLDER / "machine.toml").read_text() + TELESCOPE_DEFLECTION,
                              str(FOLDER / "machine.toml"))
    names = effect_parameter_names(plain.effects)
    assert len(names) == EFFECT_STD.size
    A = rng.normal(size=(len(names),) * 2) * 0.3 + np.eye(len(names))
    corr = A @ A.T
    corr /= np.sqrt(np.outer(np.diag(corr), np.diag(corr)))
    cov = corr * np.outer(EFFECT_STD, EFFECT_STD)
    machine, _ = _machine(names, cov, plain.layout.names)
    rec = _recording()
    res = predict_recording(machine, rec, frame="base")
    std = np.array([r["std"] for r in res.rows])
    noise = machine.noise.sigma_position
    assert not any("not this machine's" in n for n in res.notes)
    # Monte Carlo: the rows' spread over draws of the table parameters (model rebuilt with each draw's tables)
    draws = rng.multivariate_normal(np.zeros(len(names)), cov, size=1500)
    ys = []
    for d in draws:
        tables = plain.effects
        for name, step in zip(names, d):
            tables = _moved_tables(tables, name, float(step))
        model = MeasurementModel.from_recording(plain.with_effects(tables), rec)
        ys.append(model.predict(np.zeros(plain.n_params)).y)
    mc_var = np.var(np.array(ys), axis=0, ddof=1)
    pred_var = std**2 - noise**2
    big = mc_var > 4 * noise**2  # components the effects move well beyond the noise
    assert big.sum() > 0.5 * big.size
    ratio = pred_var[big] / mc_var[big]
    assert np.all((ratio > 0.88) & (ratio < 1.12))  # 3 standard errors


def test_without_the_effect_block_the_rows_carry_the_noise_only():
    plain = machine_from_text((FOLDER / "machine.toml").read_text() + TELESCOPE_DEFLECTION,
                              str(FOLDER / "machine.toml"))
    machine, _ = _machine((), np.zeros((0, 0)), plain.layout.names)
    std = np.array([r["std"] for r in predict_recording(machine, _recording(), frame="base").rows])
    np.testing.assert_allclose(std, machine.noise.sigma_position, rtol=1e-9)
