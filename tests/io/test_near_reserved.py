"""A channel named like a reserved column (``sigma_postion``) is said, not silently read as a channel (issue 31)."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest

import bayescal
from bayescal.cli import main
from bayescal.errors import BayescalWarning
from bayescal.io.recording import near_reserved_columns, read_recording

EX = Path(__file__).resolve().parents[2] / "examples"


def _with_column(tmp_path, name: str) -> Path:
    lines = (EX / "prs3" / "recording.csv").read_text().splitlines()
    path = tmp_path / "rec.csv"
    path.write_text("\n".join([lines[0] + f",{name}"] + [ln + ",0.005" for ln in lines[1:]]) + "\n")
    return path


@pytest.mark.parametrize("name, reserved", [("sigma_postion", "sigma_position"), ("sigma_angel", "sigma_angle"),
                                            ("payload_kgs", "payload_kg")])
def test_a_near_miss_is_named_with_the_reserved_column(tmp_path, capsys, name, reserved):
    path = _with_column(tmp_path, name)
    (message,) = near_reserved_columns(read_recording(path))
    assert f"column {name!r} is read as an auxiliary channel; did you mean the reserved column {reserved!r}" in message
    with pytest.warns(BayescalWarning, match=name):
        bayescal.load(EX / "prs3" / "machine.toml", path)
    assert main(["identify", str(path), "--machine", str(EX / "prs3" / "machine.toml")]) == 0
    assert f"warning: {path}: column {name!r}" in capsys.readouterr().err


def test_the_bundled_recordings_channels_are_no_near_misses():
    names = [p for p in sorted(EX.glob("*/*.csv")) if read_recording(p).aux]
    assert names  # accel.*, time_s, source_key
    for path in names:
        assert near_reserved_columns(read_recording(path)) == [], path
    with warnings.catch_warnings():
        warnings.simplefilter("error", BayescalWarning)
        bayescal.load(EX / "prs3" / "machine.toml", EX / "prs3" / "recording.csv")
