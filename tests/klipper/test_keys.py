"""Klipper's keys written for a calibrated delta: read back by the reader into bayescal's linear delta, they
predict the calibrated nozzle positions; gauges (a shift and a turn of the whole printer, the nozzle's
horizontal offset) are re-expressed so that stepper_c keeps its angle; what Klipper cannot hold is noted."""

from __future__ import annotations

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.klipper.cfg import AUTOSAVE_HEADER, read_klipper_config
from bayescal.klipper import klipper_machine, klipper_recording, read_klipper_delta
from bayescal.klipper.keys import klipper_keys, klipper_text, klipper_values
from bayescal.machines.files import load_machine
from tests import klipper_configs as synth
from tests.conftest import ROOT


@pytest.fixture(scope="module")
def printer(tmp_path_factory):
    """The synthetic printer: its config path, nominal machine and the poses of its saved measurements."""
    path = synth.write_config(tmp_path_factory.mktemp("printer"))
    cfg = read_klipper_config(path)
    rec = klipper_recording(cfg, read_klipper_delta(cfg))
    q = np.vstack([rec.qa, rec.qb[np.isfinite(rec.qb).all(axis=1)]])
    return path, klipper_machine(read_klipper_delta(cfg), q_span=q), q


def _pasted(path, block: str):
    """The config with ``block`` pasted just above its SAVE_CONFIG block, as the block's comments say, read back."""
    text = path.read_text()
    at = text.index("\n" + AUTOSAVE_HEADER)
    pasted = path.with_name("pasted.cfg")
    pasted.write_text(text[:at] + "\n" + block + text[at:])
    cfg = read_klipper_config(pasted)
    assert cfg.saved and cfg.autosave_note is None  # Klipper still reads its block below the paste
    return cfg


def _rot(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def test_written_keys_read_back_predict_the_calibrated_nozzle_positions(printer):
    path, m, q = printer
    # a calibrated printer built here from Klipper values with 6 decimals, then moved by a known shift and
    # turn of the whole printer and given a nozzle offset (gauges no height or distance sees)
    R, ang = 100.5, np.array([210.25, 329.9, 90.0])
    arms, pe = np.array([215.2, 215.4, 214.9]), np.array([250.1, 250.4, 249.8])
    shift, turn, tool = np.array([0.8, -0.5]), 0.3, np.array([0.2, -0.1, 0.35])
    feet = shift + (R * np.column_stack([np.cos(np.radians(ang)), np.sin(np.radians(ang))])) @ _rot(turn).T - tool[:2]
    theta = np.zeros(m.n_params)
    names = m.layout.names
    for i in range(3):
        a = np.arctan2(feet[i, 1], feet[i, 0])
        theta[names.index(f"tower{i + 1}.angle")] = (a - m.angle[i] + np.pi) % (2 * np.pi) - np.pi
        theta[names.index(f"tower{i + 1}.radius")] = np.hypot(*feet[i]) - m.radius[i]
        # E_i = position_endstop_i + sqrt(L_i^2 - R^2) is the nozzle's height at the endstop: zero_i + t_z
        theta[names.index(f"tower{i + 1}.zero")] = pe[i] + np.sqrt(arms[i] ** 2 - R**2) - tool[2] - m.zero[i]
        theta[names.index(f"tower{i + 1}.arm_length")] = arms[i] - m.arm_length[i]
    for k, x in enumerate("xyz"):
        theta[names.index(f"tool.point.{x}")] = tool[k]
    text = klipper_text(m, theta)
    expected = ["[printer]", "delta_radius: 100.500000"]
    for k, ab in enumerate("abc"):
        expected += [f"[stepper_{ab}]", f"angle: {ang[k]:.6f}", f"arm_length: {arms[k]:.6f}", f"position_endstop: {pe[k]:.6f}"]
    assert [ln for ln in text.splitlines() if ln and not ln.startswith("#")] == expected
    assert not any(ln.startswith("#*#") for ln in text.splitlines())  # Klipper would take it for a broken block
    # read back from the config it was pasted into: the printer Klipper will run
    m2 = klipper_machine(read_klipper_delta(_pasted(path, text)), q_span=q)
    x_cal = m.forward(q, theta).position
    x_klipper = m2.forward(q).position
    # Klipper's frame: the calibrated one moved back by the known shift and turn
    np.testing.assert_allclose(x_klipper[:, :2], (x_cal[:, :2] - shift) @ _rot(turn), atol=1e-6)
    np.testing.assert_allclose(x_klipper[:, 2], x_cal[:, 2], atol=1e-6)
    k = klipper_keys(m, theta)
    np.testing.assert_allclose(k.centre, shift, atol=1e-9)
    assert k.turn_deg == pytest.approx(turn, abs=1e-9)
    assert any("0.300000 deg" in n for n in k.notes) and any("(0.8000, -0.5000) mm" in n for n in k.notes)


def _rigid_2d(a: np.ndarray, b: np.ndarray):
    """Least-squares rotation and shift with b ~ a @ Rot.T + t (Kabsch in the plane)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    rot = (u @ vt).T
    return rot, cb - ca @ rot.T


def test_random_calibrations_round_trip_up_to_a_planar_motion(printer, rng):
    path, m, q = printer
    names = m.layout.names
    for _ in range(5):
        theta = rng.normal(size=m.n_params) * m.tolerance * 0.5
        theta[[i for i, n in enumerate(names) if "tilt" in n]] = 0.0
        text = klipper_text(m, theta)
        assert "angle: 90.000000" in text.split("[stepper_c]")[1]  # stepper_c keeps its configured angle
        m2 = klipper_machine(read_klipper_delta(_pasted(path, text)), q_span=q)
        x_cal, x_klipper = m.forward(q, theta).position, m2.forward(q).position
        rot, t = _rigid_2d(x_cal[:, :2], x_klipper[:, :2])
        # values written with Klipper's 6 decimals: nozzle positions agree to a few 1e-6 mm
        assert np.abs(x_cal[:, :2] @ rot.T + t - x_klipper[:, :2]).max() < 5e-6
        assert np.abs(x_cal[:, 2] - x_klipper[:, 2]).max() < 5e-6
        assert np.linalg.det(rot) > 0


def test_what_klipper_cannot_hold_is_noted_and_an_impossible_printer_refused(printer):
    path, m, q = printer
    names = m.layout.names
    theta = np.zeros(m.n_params)
    values, notes = klipper_values(m, theta)
    assert notes == [] and values["stepper_b"]["angle"] == pytest.approx(329.8, abs=1e-9)
    theta[names.index("tower1.direction.tilt_x")] = 1e-3
    assert any("tower tilts of 0.0573" in n for n in klipper_values(m, theta)[1])
    # a tilted tower is written vertical where its carriage works (nozzle at the bed centre), not at its foot
    # (z = 0, some 300 mm lower): the printer Klipper gets probes the bed as the tilted one within 0.01 mm
    # here (0.06 mm through the feet)
    m2 = klipper_machine(read_klipper_delta(_pasted(path, klipper_text(m, theta))), q_span=q)
    assert np.abs(m2.forward(q[:8]).position[:, 2] - m.forward(q[:8], theta).position[:, 2]).max() < 0.01
    theta[:] = 0.0
    theta[names.index("tower2.arm_length")] = -120.0  # shorter than delta_radius
    with pytest.raises(InputError, match=r"\[stepper_b\] arm_length .* not longer than delta_radius"):
        klipper_text(m, theta)
    with pytest.raises(InputError, match="three-tower linear delta"):
        klipper_text(load_machine(ROOT / "examples" / "prs3" / "machine.toml"))


def test_keys_of_a_printer_in_an_instrument_frame_are_its_geometrys(printer):
    """A calibration measured in an instrument frame (fitted or known) writes the delta's keys, not the frame's."""
    from bayescal.machines.framed import Frame, InstrumentFrame

    _, m, _ = printer
    theta = np.zeros(m.n_params)
    theta[m.layout.names.index("tower1.arm_length")] = 0.3
    frame = Frame.from_rotation_vector([10.0, -5.0, 2.0], [0.0, 0.0, 0.4])
    fitted = InstrumentFrame(m, frame, fit=True)
    assert klipper_text(fitted, np.r_[[1.0, 2.0, 3.0, 0.01, 0.02, 0.03], theta]) == klipper_text(m, theta)
    assert klipper_text(InstrumentFrame(m, frame, fit=False), theta) == klipper_text(m, theta)
