"""Unit suffixes and recordings whose numbers look like another unit."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bayescal.errors import RecordingError
from bayescal.instrument import check_recording_units, prepare_model
from bayescal.io import read_recording
from bayescal.io.recording import recording_to_csv
from bayescal.machines.files import load_machine
from bayescal.simulate import measure, simulate_recording
from tests.instrument.frames import random_frame, to_instrument

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def rec6(prs3):
    return simulate_recording(prs3, 24, seed=5, dof=6).recording


def test_plain_recordings_pass(prs3, rec6):
    check_recording_units(prs3, rec6)
    # in a tracker frame metres away and rotated: spreads and relative angles do not change
    o, R = random_frame(np.random.default_rng(0))
    check_recording_units(prs3, to_instrument(rec6, o, R))


def test_positions_in_metres_are_refused_with_the_suffix_to_use(prs3, rec6):
    metres = replace(rec6, position=rec6.position / 1000.0)
    with pytest.raises(RecordingError, match=r"look like metres.*x_m, y_m, z_m"):
        check_recording_units(prs3, metres)
    with pytest.raises(RecordingError, match=r"look like micrometres.*x_um"):
        check_recording_units(prs3, replace(rec6, position=rec6.position * 1000.0))


def test_metres_with_the_suffix_are_read_as_millimetres(prs3, rec6, tmp_path):
    text = recording_to_csv(replace(rec6, position=rec6.position / 1000.0))
    text = text.replace("x,y,z", "x_m,y_m,z_m", 1)
    p = tmp_path / "m.csv"
    p.write_text(text)
    back = read_recording(p)
    assert np.allclose(back.position, rec6.position, rtol=1e-12, atol=1e-9)
    assert back.declared_units["x"] == "m"
    check_recording_units(prs3, back)


def test_small_workspace_recording_is_not_mistaken_for_metres(prs3):
    # poses within 0.2 mm of stroke: tool points a fraction of a millimetre apart, legitimately
    rng = np.random.default_rng(1)
    q = 500.0 + rng.uniform(-0.1, 0.1, size=(20, 3))
    theta = rng.normal(size=prs3.n_params) * prs3.tolerance
    rec = measure(prs3, q, theta, 6, rng)
    assert np.ptp(rec.position, axis=0).max() < 1.0
    check_recording_units(prs3, rec)
    prepare_model(prs3, rec)


def test_degrees_are_refused_both_ways(prs3, rec6):
    # large angles: a rotation vector beyond pi
    with pytest.raises(RecordingError, match=r"above pi.*degrees.*rx_deg"):
        check_recording_units(prs3, replace(rec6, rotvec=np.degrees(rec6.rotvec)))
    # small angles (all below pi in degrees): judged by the relative angles between poses
    rng = np.random.default_rng(2)
    q = 500.0 + rng.uniform(-2.0, 2.0, size=(20, 3))
    rec = measure(prs3, q, np.zeros(prs3.n_params), 6, rng)
    deg = np.degrees(rec.rotvec)
    assert np.linalg.norm(deg, axis=1).max() < np.pi
    check_recording_units(prs3, rec)
    with pytest.raises(RecordingError, match=r"turn by .*degrees.*rx_deg"):
        check_recording_units(prs3, replace(rec, rotvec=deg))


@pytest.mark.parametrize("suffix,factor", [("deg", np.pi / 180), ("mrad", 1e-3), ("rad", 1.0)])
def test_angle_suffixes(rec6, tmp_path, suffix, factor):
    text = recording_to_csv(replace(rec6, rotvec=rec6.rotvec / factor)).replace("rx,ry,rz", f"rx_{suffix},ry_{suffix},rz_{suffix}", 1)
    p = tmp_path / "a.csv"
    p.write_text(text)
    assert np.allclose(read_recording(p).rotvec, rec6.rotvec, rtol=1e-12, atol=1e-15)


def test_actuator_suffix_in_metres(rec6, tmp_path):
    text = recording_to_csv(replace(rec6, q=rec6.q / 1000.0)).replace("q1,q2,q3", "q1_m,q2_m,q3_m", 1)
    p = tmp_path / "q.csv"
    p.write_text(text)
    back = read_recording(p)
    assert np.allclose(back.q, rec6.q) and back.q_units == ("mm",) * 3


def test_wrong_kind_of_suffix_is_named(tmp_path):
    p = tmp_path / "w.csv"
    p.write_text("q1,q2,q3,x_deg,y,z\n500,500,500,1,2,3\n")
    with pytest.raises(RecordingError, match=r"x_deg.*x_m"):
        read_recording(p)
    p.write_text("q1,q2,q3,x,y,z,sigma_angle_mm\n500,500,500,1,2,3,1\n")
    with pytest.raises(RecordingError, match=r"sigma_angle is an angle"):
        read_recording(p)


def test_known_instrument_frame_machine_file_passes(rec6, tmp_path):
    text = (ROOT / "examples" / "prs3" / "machine.toml").read_text() + "\n[instrument]\norigin = [2000.0, 0.0, 0.0]\nrotation_vector = [0.0, 0.0, 2.5]\n"
    p = tmp_path / "m.toml"
    p.write_text(text)
    m = load_machine(p)
    check_recording_units(m, rec6)


def test_a_machine_that_hardly_turns_is_not_taken_for_degrees(prs3):
    # poses that nominally turn the platform by microradians; the real errors add far more
    rng = np.random.default_rng(3)
    q = 500.0 + rng.uniform(-1e-3, 1e-3, size=(12, 3))
    theta = rng.normal(size=prs3.n_params) * prs3.tolerance
    rec = measure(prs3, q, theta, 6, rng)
    check_recording_units(prs3, rec)
