"""`bayescal klipper` and `identify --write-klipper` on a synthetic printer.cfg, end to end: the written block,
pasted where its comments say, is what the config then holds (Klipper's precedence), and the refusals exit 2."""

from __future__ import annotations

import json

import numpy as np

from bayescal.cli import main
from bayescal.klipper.cfg import AUTOSAVE_HEADER, read_klipper_config
from bayescal.klipper import read_klipper_delta
from tests import klipper_configs as synth


def test_from_printer_cfg_to_a_pasted_block(tmp_path, capsys):
    cfg_path = synth.write_config(tmp_path / "printer")
    out = tmp_path / "calib"
    assert main(["klipper", str(cfg_path), "--out", str(out), "--json", str(tmp_path / "k.json")]) == 0
    said = capsys.readouterr().out
    assert "(8 heights, 6 distances)" in said and "note:" not in said
    summary = json.loads((tmp_path / "k.json").read_text())
    assert len(summary["files_read"]) == 5 and summary["notes"] == []
    block = tmp_path / "klipper.cfg"
    assert main(["identify", str(out / "recording.csv"), "--machine", str(out / "machine.toml"), "--method", "map",
                 "--free", "all", "--write-klipper", str(block), "--json", str(tmp_path / "a.json")]) == 0
    assert f"wrote {block} (Klipper keys)" in capsys.readouterr().err
    text = block.read_text()
    assert "above" in text and "SAVE_CONFIG" in text and "[stepper_c]\nangle: 90.000000" in text
    # paste it as told: just above the SAVE_CONFIG block; Klipper then uses its values over the block's
    printer = cfg_path.read_text()
    at = printer.index("\n" + AUTOSAVE_HEADER)
    cfg_path.write_text(printer[:at] + "\n" + text + printer[at:])
    cfg = read_klipper_config(cfg_path)
    kd = read_klipper_delta(cfg)
    written = {ln.split(": ")[0]: float(ln.split(": ")[1]) for ln in text.splitlines() if ": " in ln and not ln.startswith("#")}
    assert kd.delta_radius == written["delta_radius"] and kd.angle_deg[2] == 90.0
    assert float(cfg.saved["printer"]["delta_radius"]) == synth.R  # the block itself is left as it was
    # the data were exact for the configured printer: the calibration stays at it, to a micrometre
    np.testing.assert_allclose(kd.arm_length, synth.ARMS, atol=2e-3)
    np.testing.assert_allclose(kd.position_endstop, synth.ENDSTOPS, atol=2e-3)


def test_a_multi_line_bed_mesh_used_to_be_refused(tmp_path, capsys):
    # the block a real printer leaves after BED_MESH_CALIBRATE and SAVE_CONFIG, with nothing else changed
    path = synth.write_config(tmp_path)
    assert main(["klipper", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_missing_include_is_a_note_or_with_the_option_an_error(tmp_path, capsys):
    main_text = synth.MAIN.replace("[include steppers.cfg]", "[include steppers.cfg]\n[include fluidd.cfg]")
    path = synth.write_config(tmp_path, main=main_text)
    assert main(["klipper", str(path), "--out", str(tmp_path / "o"), "--missing-includes", "error"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{path} line 5: [include fluidd.cfg]: {tmp_path / 'fluidd.cfg'} does not exist" in err
    assert not (tmp_path / "o").exists()
    assert main(["klipper", str(path), "--out", str(tmp_path / "o")]) == 0  # the default: skipped with a note
    out = capsys.readouterr().out
    assert f"note: [include] at {path} line 5: {tmp_path / 'fluidd.cfg'} not found; skipped" in out
