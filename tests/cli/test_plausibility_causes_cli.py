"""The plausibility report names the right likely cause (docs/real-instruments.md, "Plausibility").

Each bad recording is built here from a simulated one: a tool 20 mm longer than
the machine file says, the x and y columns exchanged, and a recording in an
instrument's frame identified without --frame fit.  The cause must be the true
one, with the numbers that locate it, and not one of the others (a tool-length
error used to be blamed on "wrong units", and on a 3-PRS refused as a frame).
"""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.cli import main
from bayescal.io import read_recording, write_recording
from tests.instrument.frames import to_instrument

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _run(args: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(args)
        except SystemExit as exc:  # argparse
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def _simulate(tmp_path: Path, machine: Path, n: int, seed: int) -> Path:
    rec = tmp_path / "rec.csv"
    assert _run(["simulate", "--machine", str(machine), "--poses", str(n), "--seed", str(seed), "--out", str(rec),
                 "--quiet"])[0] == 0
    return rec


def _identify(rec: Path, machine: Path, tmp_path: Path, *extra: str) -> tuple[int, str, str, dict]:
    answer = tmp_path / "answer.json"
    code, out, err = _run(["identify", str(rec), "--machine", str(machine), "--json", str(answer), *extra])
    return code, out, err, json.loads(answer.read_text())


def _causes(answer: dict) -> list[str]:
    return answer["plausibility"]["causes"]


@pytest.mark.parametrize("example, old, new", [
    # a 3-PRS spindle head (the platform barely turns: the check used to take the tool for a frame and refuse)
    ("prs3", "point = [0.0, 0.0, -100.0]", "point = [0.0, 0.0, -80.0]"),
    # a solar tracker (the platform turns far: the tool points' spread changed, which was blamed on units)
    ("rupus_prs", "point = [0.0, 0.0, 50.0]", "point = [0.0, 0.0, 70.0]"),
])
def test_a_wrong_tool_length_is_named(tmp_path, example, old, new):
    nominal = EXAMPLES / example / "machine.toml"
    rec = _simulate(tmp_path, nominal, 40, 3)
    text = nominal.read_text()
    assert old in text
    short = tmp_path / "short_tool.toml"  # the machine file's tool is 20 mm shorter than the one measured
    short.write_text(text.replace(old, new))
    code, out, err, answer = _identify(rec, short, tmp_path, "--robust", "off")  # (the outlier refits: seconds)
    assert code == 1 and not answer["plausible"]
    causes = _causes(answer)
    tool = [c for c in causes if c.startswith("wrong tool point")]
    assert tool and not any(c.startswith(("wrong units", "wrong frame", "missing --frame fit")) for c in causes)
    # the offset found is the 20 mm the file is short, along the tool axis (z of the platform frame), within
    # what the drawn tolerances (0.05 mm) and the noise allow
    assert np.allclose(answer["frame_check"]["tool_offset"], [0.0, 0.0, -20.0], atol=0.5)
    assert answer["frame_check"]["explanation"] == "tool" and not answer["frame_check"]["fires"]
    assert "likely causes:" in out and "wrong tool point" in out
    assert "warning: wrong tool point" in err  # said before the identification too


def test_swapped_columns_are_named(tmp_path):
    nominal = EXAMPLES / "arm6" / "machine.toml"
    rec = read_recording(_simulate(tmp_path, nominal, 30, 4))
    p = rec.position.copy()
    p[:, [0, 1]] = p[:, [1, 0]]
    swapped = tmp_path / "swapped.csv"
    write_recording(swapped, replace(rec, position=p))
    # --robust off: the outlier screen's refits of a recording no geometry explains take half a minute, and the
    # cause does not depend on them
    code, out, err, answer = _identify(swapped, nominal, tmp_path, "--robust", "off")
    assert code == 1 and not answer["plausible"]
    causes = _causes(answer)
    assert any(c.startswith("swapped columns: with columns x and y exchanged") for c in causes)
    assert not any(c.startswith(("wrong units", "wrong frame", "missing --frame fit", "wrong tool")) for c in causes)
    chk = answer["frame_check"]
    assert chk["swapped"] == "x, y" and chk["explanation"] == "swap"
    # exchanged back, the recording is as close to the nominal machine as the drawn errors (tolerances) put it;
    # no rigid transform comes near (a reflection)
    assert chk["rms_swapped"] < 2.0 < 50.0 < chk["rms_rigid"]
    assert "warning: swapped columns" in err


def test_a_missing_frame_fit_is_named(tmp_path):
    """A recording in a motion-capture frame, of an arm whose marker position is unknown (a tool-point tolerance of
    1 m, as on the real positioner and TIAGo recordings): the tolerances explain metres, so the frame check stays
    silent, the base absorbs the frame and nothing used to say why; now the cause is the missing --frame fit."""
    nominal = EXAMPLES / "arm6" / "machine.toml"
    rec = read_recording(_simulate(tmp_path, nominal, 30, 5))
    unknown_tool = tmp_path / "marker_unknown.toml"
    unknown_tool.write_text(nominal.read_text() + "\n[tolerance]\ntool_point = 1000.0\n")
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    R, o = Rotation.from_rotvec(np.radians(20.0) * axis).as_matrix(), np.array([300.0, -150.0, 90.0])
    framed = tmp_path / "mocap.csv"
    write_recording(framed, to_instrument(rec, o, R))
    code, out, err, answer = _identify(framed, unknown_tool, tmp_path)
    assert code == 1 and not answer["plausible"]
    causes = _causes(answer)
    frame = [c for c in causes if c.startswith("missing --frame fit")]
    assert frame and "identify with --frame fit" in frame[0]
    assert not any(c.startswith(("wrong units", "wrong tool", "swapped")) for c in causes)
    chk = answer["frame_check"]
    assert chk["explanation"] == "frame" and not chk["fires"]  # the tolerances hid it from the check
    assert chk["translation"] == pytest.approx(np.linalg.norm(o), rel=0.02)
    assert chk["rotation_deg"] == pytest.approx(20.0, abs=0.2)
    # the advice is right: with --frame fit the frame is found where it is, and the cause is gone
    code, out, err, fitted = _identify(framed, unknown_tool, tmp_path, "--frame", "fit")
    assert np.allclose(fitted["frame"]["origin"], o, atol=1.0)
    assert np.allclose(Rotation.from_rotvec(fitted["frame"]["rotation_vector"]).as_matrix(), R, atol=1e-3)
    assert not any(c.startswith("missing --frame fit") for c in _causes(fitted))
