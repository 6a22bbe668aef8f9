"""Bad body-sensor columns: exit code 2 and one line naming the file, line and column; kinds without bodies refuse them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.cli import main
from bayescal.io.recording import Recording, write_recording

from .chain import JOINTS, machine_text, poses, transforms


@pytest.fixture()
def files(tmp_path):
    m = tmp_path / "column.toml"
    m.write_text(machine_text(JOINTS))
    q = poses(12, 7)
    frames, tool = transforms(JOINTS, q)
    Rb = np.array([f[1][:3, :3] for f in frames])
    rng = np.random.default_rng(8)
    u = np.einsum("ji,nkj,k->ni", Rotation.from_rotvec([0.01, 0.0, 0.0]).as_matrix(), Rb, [0.0, 0.0, 1.0])
    u, tool = u + rng.normal(size=u.shape) * 2e-5, tool + rng.normal(size=tool.shape) * 0.005
    aux = {f"accel.joint2.{a}": u[:, i] for i, a in enumerate("xyz")}
    rec = tmp_path / "rec.csv"
    write_recording(rec, Recording(q=q, position=tool, aux=aux))
    return m, rec


def _edit(rec, tmp_path, fn):
    lines = rec.read_text().splitlines()
    header = lines[0].split(",")
    rows = [ln.split(",") for ln in lines[1:]]
    header, rows = fn(header, rows)
    out = tmp_path / "bad.csv"
    out.write_text("\n".join(",".join(r) for r in [header] + rows) + "\n")
    return out


def _renamed(header, rows):
    return [h.replace("accel.joint2", "accel.column") for h in header], rows


def _no_z(header, rows):
    k = header.index("accel.joint2.z")
    return header[:k] + header[k + 1:], [r[:k] + r[k + 1:] for r in rows]


def _zero(header, rows):
    for a in "xyz":
        rows[3][header.index(f"accel.joint2.{a}")] = "0"
    return header, rows


def _nan(header, rows):
    rows[5][header.index("accel.joint2.y")] = "nan"
    return header, rows


def _upper_axis(header, rows):
    return [h.replace("accel.joint2.x", "accel.joint2.X") for h in header], rows


def _upper_all(header, rows):
    return [h.replace("accel.joint2.y", "ACCEL.JOINT2.Y") for h in header], rows


@pytest.mark.parametrize("fn, expected", [
    (_upper_axis, "line 1, column 'accel.joint2.X': a body sensor's column in the wrong case; expected 'accel.joint2.x'"),
    (_upper_all, "line 1, column 'ACCEL.JOINT2.Y': a body sensor's column in the wrong case; expected 'accel.joint2.y'"),
    (_renamed, "column 'accel.column.x': no body 'column' on this machine; expected accel.<body>.x/y/z with <body> one "
               "of base, joint1, joint2, joint3"),
    (_no_z, "column(s) accel.joint2.z missing"),
    (_zero, "line 5, column 'accel.joint2.x': the sensor on 'joint2' reads [0.0, 0.0, 0.0]"),
    (_nan, "line 7, column 'accel.joint2.y': expected a finite number"),
])
def test_bad_sensor_columns_exit_2_naming_the_place(files, tmp_path, capsys, fn, expected):
    machine, rec = files
    bad = _edit(rec, tmp_path, fn)
    assert main(["identify", str(bad), "--machine", str(machine), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert expected in err and str(bad) in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_good_sensor_columns_identify_and_predict(files, tmp_path, capsys):
    machine, rec = files
    cal = tmp_path / "cal.toml"
    assert main(["identify", str(rec), "--machine", str(machine), "--method", "ls", "--write-machine", str(cal),
                 "--quiet"]) == 0
    assert "sensor." not in cal.read_text()  # the mountings are the session's, not the machine's
    assert main(["predict", str(rec), "--machine", str(cal), "--quiet"]) == 0
    assert main(["diagnose", str(rec), "--machine", str(machine), "--quiet"]) == 0


def test_a_kind_without_bodies_refuses_a_body_sensor(tmp_path, capsys):
    """A linear delta exposes no body but its base: a sensor elsewhere is an error naming the column."""
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "delta"
    rec = example / "recording.csv"
    lines = rec.read_text().splitlines()
    out = tmp_path / "delta.csv"
    out.write_text("\n".join([lines[0] + ",accel.platform.x,accel.platform.y,accel.platform.z"]
                             + [ln + ",0.0,0.0,1.0" for ln in lines[1:]]) + "\n")
    assert main(["identify", str(out), "--machine", str(example / "machine.toml"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "column 'accel.platform.x': no body 'platform' on this machine (this machine kind exposes no body but the " \
           "base)" in err


def test_measurement_keys_are_read_written_and_checked(tmp_path):
    from bayescal.errors import MachineFileError
    from bayescal.machines.files import load_machine

    p = tmp_path / "m.toml"
    p.write_text(machine_text(JOINTS, sigma_tilt=3e-5, extra="base_level = 5.0e-5"))
    m = load_machine(p)
    assert (m.noise.sigma_tilt, m.noise.base_level, m.noise.sensor_mount) == (3e-5, 5e-5, 1e-3)
    again = tmp_path / "again.toml"
    again.write_text(m.to_toml())
    m2 = load_machine(again)
    assert (m2.noise.sigma_tilt, m2.noise.base_level) == (3e-5, 5e-5)
    for extra, key in (("sensor_mount = 2.0", "sensor_mount"), ("sensor_turn = -1.0", "sensor_turn")):
        p.write_text(machine_text(JOINTS, extra=extra))
        with pytest.raises(MachineFileError, match=key):
            load_machine(p)


def test_fitted_frames_per_station_with_sensors(files, tmp_path, capsys):
    """Stations in their own frames: the frames, the geometry and the mountings in one fit; the check rows scored."""
    machine, rec = files
    lines = rec.read_text().splitlines()
    out = tmp_path / "stations.csv"
    out.write_text("\n".join([lines[0] + ",station,role"] + [
        ln + f",{'a' if i % 2 else 'b'},{'check' if i % 6 == 0 else 'fit'}" for i, ln in enumerate(lines[1:])]) + "\n")
    answer = tmp_path / "answer.json"
    assert main(["identify", str(out), "--machine", str(machine), "--frame", "fit", "--json", str(answer),
                 "--quiet"]) == 0
    import json

    d = json.loads(answer.read_text())
    names = [p["name"] for p in d["parameters"]]
    assert names[0].startswith("frame.") and names[-2:] == ["gravity.tilt.rx", "gravity.tilt.ry"]
    assert d["dof"] == 3 and d["tilt_rows_per_pose"] == 2 and d["rms_after"]["tilt"] < 1e-4
    assert d["check"]["summary"]["n"] == 2


def test_a_base_sensor_in_upper_case_is_refused_not_read_as_a_channel(tmp_path, capsys):
    """docs/formats.md section 8 names sensors accel.<body>.x/y/z; 'accel.base.X' was an ordinary channel, silently."""
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "prs3"
    lines = (example / "recording.csv").read_text().splitlines()
    out = tmp_path / "upper.csv"
    out.write_text("\n".join([lines[0] + ",accel.base.X,accel.base.y,accel.base.z"]
                             + [ln + ",0.0,0.0,1.0" for ln in lines[1:]]) + "\n")
    assert main(["identify", str(out), "--machine", str(example / "machine.toml"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{out}: line 1, column 'accel.base.X'" in err and "expected 'accel.base.x'" in err
    assert len(err.strip().splitlines()) == 1
    # a channel that only looks alike (no axis x, y or z) stays a channel
    out.write_text("\n".join([lines[0] + ",Accel.base.w"] + [ln + ",1.0" for ln in lines[1:]]) + "\n")
    assert main(["identify", str(out), "--machine", str(example / "machine.toml"), "--quiet"]) == 0
