"""sigma_position and sigma_angle tested apart (bayescal/identify/group_noise.py).

With sigma_position stated 100 times too large and sigma_angle right, the whole test's reduced chi-square was
0.40 ("the stated noise fits") and MAP left 0.11 mm where the right sigma reaches 0.0073 mm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bayescal.identify.calibrate import calibrate
from bayescal.identify.group_noise import group_scales
from bayescal.identify.noise import check_noise
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
from bayescal.measurement import MeasurementModel

EX = Path(__file__).resolve().parents[2] / "examples" / "prs3"


@pytest.fixture(scope="module")
def model():
    return MeasurementModel.from_recording(load_machine(EX / "machine.toml"), read_recording(EX / "recording.csv"))


def _scaled(model, position: float, angle: float):
    sigma = np.array(model.row_sigma, dtype=float)
    sigma[:, :3] *= position
    sigma[:, 3:] *= angle
    return model.with_pose_sigma(sigma)


def _pos(cal):
    return cal.result.rms_after["position"]


def test_a_position_sigma_100_times_too_large_is_found_and_rescaled_alone(model):
    right = calibrate(model, method="map", prior_scale="tolerance", robust="off")
    wrong = calibrate(_scaled(model, 100.0, 1.0), method="map", prior_scale="tolerance", robust="off")
    stated = calibrate(_scaled(model, 100.0, 1.0), method="map", prior_scale="tolerance", robust="off", noise="stated")
    block = wrong.result.extras["tool_noise"]
    assert block["position"]["verdict"] == "overstated" and block["angle"]["verdict"] == "consistent"
    assert set(block["scale_used"]) == {"position"}
    # the whole test alone called it consistent: the position rows carry almost nothing of its chi-square
    assert stated.noise.verdict == "consistent" and _pos(stated) > 10 * _pos(right)
    # rescaled, the fit reaches what the right sigma reaches, and the sigma used is about the right one
    assert _pos(wrong) == pytest.approx(_pos(right), rel=0.02)
    assert 100.0 * block["scale_used"]["position"] == pytest.approx(1.0, rel=0.25)
    assert "sigma_position used" in wrong.report()


def test_both_sigmas_off_by_one_factor_keep_the_one_scale(model):
    wrong = calibrate(_scaled(model, 100.0, 100.0), method="map", prior_scale="tolerance", robust="off")
    assert wrong.result.extras["tool_noise"]["scale_used"] == {}
    assert wrong.noise.verdict == "overstated" and wrong.noise_scale == pytest.approx(0.01, rel=0.2)


def test_a_stated_noise_that_fits_changes_nothing(model):
    cal = calibrate(model, method="map", prior_scale="tolerance", robust="off")
    block = cal.result.extras["tool_noise"]
    assert block["scale_used"] == {} and {block["position"]["verdict"], block["angle"]["verdict"]} == {"consistent"}
    assert "position noise" not in cal.report()


def test_the_rule_rescales_groups_apart_only_where_they_disagree():
    fits, low, lower = check_noise(100.0, 100.0), check_noise(1.0, 100.0), check_noise(0.5, 100.0)
    high = check_noise(10_000.0, 100.0)
    assert group_scales({"position": fits, "angle": fits}) == {}
    assert group_scales({"position": low, "angle": fits}) == {"position": low.scale}
    assert group_scales({"position": low, "angle": lower}) == {}  # both 0.1 and 0.07: one scale serves
    assert group_scales({"position": low, "angle": high}) == {"position": low.scale, "angle": high.scale}
    assert group_scales(None) == {}
    # the bundled positioner: 0.22 ("overstated") against 0.35 ("consistent") is one noise, not two
    pos, ang = check_noise(0.222 * 608, 608), check_noise(0.355 * 608, 608)
    assert pos.verdict == "overstated" and ang.verdict == "consistent"
    assert group_scales({"position": pos, "angle": ang}) == {}
