"""A [calibration] record that lacks parameters: their tolerance is their uncertainty, not zero (issue 30).

Closed form: with every parameter the record holds at zero variance and one
parameter ``p`` missing, the predicted variance of each measured component
exceeds that of the complete (all-zero) record by exactly
``J_p^2 tolerance_p^2``, ``J_p`` the component's derivative by ``p``, taken
here by central finite differences of the model (not the engine's Jacobian).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import bayescal
from bayescal.errors import MachineFileError
from bayescal.io.recording import read_recording
from bayescal.machines.files import load_machine
from bayescal.prediction.record import CalibrationRecord, calibration_toml, covariance_with_prior
from bayescal.prediction.recording import predict_recording
from tests.conftest import PRS3_FILE, ROOT


def _machine_with(tmp_path, names, tag):
    rec = CalibrationRecord(tuple(names), np.zeros((len(names), len(names))), 1.0, "map", 1.0)
    path = tmp_path / f"m_{tag}.toml"
    path.write_text(PRS3_FILE.read_text() + "\n" + calibration_toml(rec))
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("prior")
    lines = (ROOT / "examples" / "prs3" / "recording.csv").read_text().splitlines()
    (d / "r.csv").write_text("\n".join(lines[:5]) + "\n")
    names = load_machine(PRS3_FILE).layout.names
    return d, names


@pytest.mark.parametrize("k", [0, 7, 30])
def test_a_missing_parameter_carries_its_tolerance(setup, k):
    d, names = setup
    p = names[k]
    full = load_machine(_machine_with(d, names, "full"))
    lacking = load_machine(_machine_with(d, [n for n in names if n != p], f"no{k}"))
    # check rows: the propagation alone (fit rows would test the regions against the uncalibrated residuals)
    rec = replace(read_recording(d / "r.csv"), role=("check",) * 4)
    std_full = np.array([r["std"] for r in predict_recording(full, rec).rows])
    res = predict_recording(lacking, rec)
    std_lack = np.array([r["std"] for r in res.rows])
    assert any(p in n and "tolerances" in n for n in res.notes)
    # the derivative of every measured component by p, by central differences of the model
    model = bayescal.load(PRS3_FILE, d / "r.csv").fit_model
    j = model.machine.layout.names.index(p)
    tol = float(model.machine.tolerance[j])
    h = 1e-3 * tol
    th = np.zeros(model.machine.n_params)
    th[j] = h
    up = model.predict(th).y
    th[j] = -h
    down = model.predict(th).y
    J = (up - down) / (2 * h)
    np.testing.assert_allclose(std_lack**2 - std_full**2, (J * tol) ** 2, rtol=1e-4, atol=1e-12)
    assert np.max((J * tol) ** 2) > 1e-6  # p matters at these poses: the test could fail


def test_no_tolerance_for_a_missing_parameter_is_refused():
    rec = CalibrationRecord(("a",), np.eye(1), 1.0, "map", 1.0)
    C, missing = covariance_with_prior(rec, ["a", "b"], [1.0, 0.5], "m.toml")
    np.testing.assert_allclose(C, np.diag([1.0, 0.25]))
    assert missing == ("b",)
    with pytest.raises(MachineFileError, match=r"m.toml: key 'calibration.parameters': .*\(b\)"):
        covariance_with_prior(rec, ["a", "b"], [1.0, 0.0], "m.toml")


def test_least_squares_records_its_gauge_fixed_parameters_as_exact(tmp_path):
    """The parameters least squares fixed (the gauge: the free ones absorbed them) are in its record at zero
    variance, so predict does not give them their tolerance and count their effect twice."""
    cal = tmp_path / "ls.toml"
    from bayescal.cli import main

    # (least squares on the example is judged not plausible, exit 1; --force writes it all the same)
    main(["identify", str(ROOT / "examples" / "prs3" / "recording.csv"), "--machine", str(PRS3_FILE),
          "--method", "ls", "--write-machine", str(cal), "--quiet", "--force"])
    m = load_machine(cal)
    assert set(m.calibration.names) == set(m.layout.names)
    res = predict_recording(m, read_recording(ROOT / "examples" / "prs3" / "recording.csv"))
    assert not any("tolerances" in n for n in res.notes)
