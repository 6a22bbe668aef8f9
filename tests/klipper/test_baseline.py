"""Klipper's own objective re-implemented: it reproduces the calibration Klipper stored for the
FLSUN Q5 (GPL-3.0 data read from ../shared, never copied)."""

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bayescal.klipper.cfg import AUTOSAVE_HEADER, parse_klipper_text
from bayescal.klipper.cfg import read_klipper_config
from bayescal.klipper import klipper_machine, klipper_recording, read_klipper_delta
from bayescal.klipper.baseline import fit_klipper, klipper_objective
from tests import klipper_configs as synth

SHARED = Path(os.environ.get("BAYESCAL_SHARED", Path(__file__).resolve().parents[2] / ".." / "shared"))
DATA = SHARED / "data" / "real" / "delta_flsun_q5"
q5 = pytest.mark.skipif(not (DATA / "printer-post-calibration.cfg").exists(), reason="../shared data not present")


@pytest.fixture(scope="module")
def nominal():
    # the geometry in force while probing (the pre-calibration cfg, delta_radius 105) with the saved measurements
    post = (DATA / "printer-post-calibration.cfg").read_text()
    block = "\n" + AUTOSAVE_HEADER + post[post.index("#*# [delta_calibrate]"):]
    pre = (DATA / "printer-pre-calibration.cfg").read_text().replace("#delta_radius: 105", "delta_radius: 105")
    cfg = parse_klipper_text(pre + "\n" + block, "pre+block.cfg")
    kd = read_klipper_delta(cfg)
    return kd, klipper_recording(cfg, kd)


@q5
def test_objective_at_nominal_and_at_klippers_result(nominal):
    kd, rec = nominal
    assert abs(klipper_objective(kd, rec) - 139.79) < 0.01
    stored = replace(
        kd, delta_radius=101.288849, angle_deg=np.array([210.481232, 330.925002, 90.0]),
        arm_length=np.array([217.425939, 216.095900, 215.670200]), position_endstop=np.array([218.724820, 219.438345, 218.763895]),
    )
    assert abs(klipper_objective(stored, rec) - 0.616029) < 1e-6


@q5
def test_fit_reproduces_klippers_stored_calibration(nominal):
    kd, rec = nominal
    fit = fit_klipper(kd, rec)
    assert fit.success and fit.names[-3:] == ("arm_a", "arm_b", "arm_c")
    d = fit.delta
    assert abs(fit.objective - 0.616029) < 1e-6
    assert abs(d.delta_radius - 101.2889) < 1e-3
    np.testing.assert_allclose(d.angle_deg, [210.4812, 330.9250, 90.0], atol=1e-3)
    np.testing.assert_allclose(d.position_endstop, [218.7248, 219.4383, 218.7639], atol=1e-3)
    np.testing.assert_allclose(d.arm_length, [217.4260, 216.0960, 215.6702], atol=1e-3)


def test_manual_heights_do_not_count_in_klippers_height_weight(tmp_path):
    # Klipper weighs heights by n_distances / (0.5 n_probed): the one manual height of the synthetic config
    # is a height row but not a probed one (7 probed, 6 distances: w = 12/7)
    cfg = read_klipper_config(synth.write_config(tmp_path))
    kd = read_klipper_delta(cfg)
    rec = klipper_recording(cfg, kd)
    off = replace(kd, delta_radius=kd.delta_radius + 0.3, arm_length=kd.arm_length + [0.2, -0.1, 0.0])
    m = klipper_machine(off, q_span=np.vstack([rec.qa, rec.qb[8:]]))
    z = m.forward(rec.qa[:8]).position[:, 2] - rec.value[:8]
    d = np.linalg.norm(m.forward(rec.qa[8:]).position - m.forward(rec.qb[8:]).position, axis=1) - rec.value[8:]
    assert klipper_objective(off, rec) == pytest.approx(6 / (0.5 * 7) * np.sum(z**2) + np.sum(d**2), rel=1e-9)
