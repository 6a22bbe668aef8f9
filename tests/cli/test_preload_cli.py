"""End to end on a restrained RASPM recording: diagnose --json --write-machine, then identify and grid with the written machine."""

import json

import numpy as np

from bayescal.cli import main
from bayescal.io import read_recording
from bayescal.io.recording import write_recording
from bayescal.machines.files import load_machine
from bayescal.redundant.restrained_recording import restrained_recording
from tests.conftest import ROOT

RASPM = ROOT / "examples" / "raspm" / "machine.toml"


def test_restrained_recording_diagnosed_and_its_machine_applied(tmp_path, capsys):
    m = load_machine(RASPM)
    rec, fresh, cal = tmp_path / "rec.csv", tmp_path / "fresh.csv", tmp_path / "cal.toml"
    write_recording(rec, restrained_recording(m, 50, 21, offset_mm=0.2).recording)
    # the same module (same seed: same geometry and stiffnesses), other poses: the first 50 of 70 are the recording's
    write_recording(fresh, restrained_recording(m, 70, 21, offset_mm=0.2).recording)
    code = main(["diagnose", str(rec), "--machine", str(RASPM), "--json", str(tmp_path / "d.json"), "--write-machine", str(cal),
                 "--effects", "redundancy_preload"])
    out = capsys.readouterr().out
    assert code == 0, out
    answer = json.loads((tmp_path / "d.json").read_text())
    assert answer["verdict"] == "redundancy_preload"
    params = {p["name"]: p for e in answer["effects"] if e["name"] == "redundancy_preload" for p in e["parameters"]}
    assert params["compliance_ratio.q1"]["unit"] == "1" and params["offset.q2"]["unit"] == "mm"
    assert params["redundant.chain2_slider1_rail_direction_tilt"]["unit"] == "rad"
    text = cal.read_text()
    assert "[effect.redundancy_preload]" in text and '"offset.q2"' in text
    written = load_machine(cal)
    assert dict(written.effects[0].values) == {k: v["value"] for k, v in params.items()}

    # identify with the written machine on the fresh poses: the preload is applied, the geometry left with the noise
    assert main(["identify", str(fresh), "--machine", str(cal), "--method", "map", "--json", str(tmp_path / "id.json"), "--quiet"]) in (0, 1)
    ident = json.loads((tmp_path / "id.json").read_text())
    noise = m.noise.sigma_position * np.sqrt(3)
    assert ident["rms_before"]["position"] < 2.0 * noise
    # a geometry-only calibration of the same poses is left with more than the noise
    assert main(["identify", str(fresh), "--machine", str(RASPM), "--method", "map", "--json", str(tmp_path / "id0.json"), "--quiet"]) in (0, 1)
    geo = json.loads((tmp_path / "id0.json").read_text())["rms_after"]["position"]
    assert geo > 1.5 * noise and geo > 1.5 * ident["rms_after"]["position"]

    # grid nodes (each a session of its own) get the preload of their commanded positions
    from bayescal.effects.stored import static_effect_delta_q

    q = read_recording(fresh).q[:5]
    dq = static_effect_delta_q(written, written.effects, q)
    assert np.abs(dq[:, list(m.nonredundant)]).max() > 1e-3 and np.all(dq[:, 1] == 0.0)
