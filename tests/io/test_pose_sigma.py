"""Per-pose noise columns sigma_position / sigma_angle (docs/formats.md section 4): read strictly, weight each pose."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from bayescal.bayes.priors import map_estimate
from bayescal.errors import RecordingError
from bayescal.io import read_recording
from bayescal.io.recording import recording_to_csv
from bayescal.measurement import MeasurementModel
from bayescal.simulate import simulate_recording


@pytest.fixture(scope="module")
def rec(prs3):
    return simulate_recording(prs3, 30, seed=8, dof=6).recording


def _write(tmp_path, text, name="r.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_columns_are_read_with_units_and_round_trip(rec, tmp_path):
    n = rec.n_poses
    sp, sa = np.linspace(1, 3, n), np.linspace(10, 20, n)
    text = recording_to_csv(replace(rec, sigma_position=sp * 1e-3, sigma_angle=sa * 1e-6))
    back = read_recording(_write(tmp_path, text))
    assert np.allclose(back.sigma_position, sp * 1e-3) and np.allclose(back.sigma_angle, sa * 1e-6)
    assert "sigma_position" not in back.aux
    text_u = text.replace("sigma_position,sigma_angle", "sigma_position_um,sigma_angle_mrad", 1)
    text_u = "\n".join([text_u.splitlines()[0]] + [
        ",".join(c[:-2] + [repr(float(c[-2]) * 1e3), repr(float(c[-1]) * 1e3)])
        for c in (line.split(",") for line in text_u.splitlines()[1:])
    ]) + "\n"
    back_u = read_recording(_write(tmp_path, text_u, "u.csv"))
    assert np.allclose(back_u.sigma_position, sp * 1e-3) and np.allclose(back_u.sigma_angle, sa * 1e-6)


@pytest.mark.parametrize("bad", ["0", "-0.01"])
def test_non_positive_sigma_is_refused_with_line_and_column(rec, tmp_path, bad):
    text = recording_to_csv(replace(rec, sigma_position=np.full(rec.n_poses, 0.005)))
    lines = text.splitlines()
    cells = lines[3].split(",")
    cells[-1] = bad
    lines[3] = ",".join(cells)
    with pytest.raises(RecordingError, match=r"line 4.*sigma_position.*positive"):
        read_recording(_write(tmp_path, "\n".join(lines) + "\n"))


def test_model_takes_the_columns_and_falls_back_to_the_machine(prs3, rec):
    n = rec.n_poses
    sp = np.linspace(0.001, 0.01, n)
    m6 = MeasurementModel.from_recording(prs3, replace(rec, sigma_position=sp))
    assert np.allclose(m6.row_sigma[:, :3], sp[:, None]) and np.allclose(m6.row_sigma[:, 3:], prs3.noise.sigma_angle)
    sa = np.linspace(1e-5, 1e-4, n)
    m5 = MeasurementModel.from_recording(prs3, replace(rec, sigma_angle=sa), dof=5)
    assert np.allclose(m5.row_sigma[:, :3], prs3.noise.sigma_position) and np.allclose(m5.row_sigma[:, 3:], sa[:, None])
    # position-only ignores sigma_angle
    m3 = MeasurementModel.from_recording(prs3, replace(rec, sigma_angle=sa), dof=3)
    assert m3.pose_sigma is None
    assert MeasurementModel.from_recording(prs3, rec).pose_sigma is None


def test_weighting_works_end_to_end(prs3, rec):
    """Poses given a huge sigma drop out: the MAP answer equals the one without them."""
    bad = np.array([2, 9, 17])
    corrupt = rec.position.copy()
    corrupt[bad] += np.array([0.3, -0.2, 0.25])  # gross errors on three poses
    rec_bad = replace(rec, position=corrupt)
    keep = np.setdiff1d(np.arange(rec.n_poses), bad)
    sp = np.full(rec.n_poses, prs3.noise.sigma_position)
    sa = np.full(rec.n_poses, prs3.noise.sigma_angle)
    sp[bad], sa[bad] = 1e4, 1e4
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        weighted = map_estimate(MeasurementModel.from_recording(prs3, replace(rec_bad, sigma_position=sp, sigma_angle=sa)), free="all")
        without = map_estimate(MeasurementModel.from_recording(prs3, rec.subset(keep)), free="all")
        naive = map_estimate(MeasurementModel.from_recording(prs3, rec_bad), free="all")
    std = without.std
    assert np.max(np.abs(weighted.theta - without.theta) / std) < 1e-3
    assert np.max(np.abs(naive.theta - without.theta) / std) > 1.0
