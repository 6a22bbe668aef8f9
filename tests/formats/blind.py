"""Running the CLI as an outside program would, and reading its answers as docs/formats.md (the contract) states them.

Nothing here imports bayescal's readers or writers: the command line is run through
``bayescal.cli.main`` (the same entry point as ``python -m bayescal``) and its files are
read with ``json`` and ``tomllib``.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np

from bayescal.cli import main

from .handwritten import Chain, Joint, Prs3, Serial


def run(capsys, *argv) -> tuple[int, str, str]:
    """Exit code, stdout and stderr of one command."""
    capsys.readouterr()
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def answer(path: Path) -> dict:
    return json.loads(Path(path).read_text(encoding="utf-8"))


def check_parameters(params: list) -> None:
    """Section 3: name, value, std (number or null), unit for every parameter."""
    assert isinstance(params, list) and params
    for p in params:
        assert isinstance(p["name"], str) and p["name"]
        assert isinstance(p["value"], float | int) and np.isfinite(p["value"])
        assert p["std"] is None or (isinstance(p["std"], float | int) and p["std"] >= 0)
        assert isinstance(p["unit"], str) and p["unit"]


def check_outliers(a: dict) -> list[int]:
    """Section 4: a list of {line, statistic, p_value}; what the fit did with them is stated."""
    assert isinstance(a["outliers"], list)
    for o in a["outliers"]:
        assert isinstance(o["line"], int) and o["line"] >= 2
        assert isinstance(o["statistic"], float | int)
        assert 0.0 <= o["p_value"] <= 1.0
    return [o["line"] for o in a["outliers"]]


def check_identify_answer(a: dict, *, angle: bool = True) -> None:
    """Section 3 and 4 keys of an identify answer with their types."""
    assert isinstance(a["machine"], str)
    assert isinstance(a["method"], str)
    check_parameters(a["parameters"])
    for key in ("rms_before", "rms_after"):
        assert isinstance(a[key]["position"], float) and a[key]["position"] >= 0
        if angle:
            assert isinstance(a[key]["angle"], float) and a[key]["angle"] >= 0
    check_outliers(a)


def check_diagnose_answer(a: dict) -> None:
    """Section 3 and 4 keys of a diagnose answer with their types."""
    assert isinstance(a["verdict"], str) and a["verdict"]
    assert isinstance(a["effects"], list)
    ev = [e["evidence"] for e in a["effects"]]
    assert ev == sorted(ev, reverse=True), "effects are listed most evident first"
    for e in a["effects"]:
        assert isinstance(e["name"], str) and isinstance(e["detected"], bool)
        assert isinstance(e["evidence"], float | int)
        for p in e["parameters"]:
            assert isinstance(p["name"], str) and isinstance(p["unit"], str)
            assert isinstance(p["value"], float | int)
        for key in ("rms_before", "rms_after"):
            assert isinstance(e[key], float | int) and e[key] >= 0
    loc = a["located"]
    assert isinstance(loc, dict) and "channel" in loc and "strength" in loc
    check_outliers(a)


def read_prs3(path: Path) -> tuple[Prs3, dict]:
    """A 3-PRS machine file read with tomllib only (the calibrated-machine contract)."""
    d = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    assert d["kind"] == "3-PRS"
    chains = tuple(
        Chain(tuple(c["rail_origin"]), tuple(c["rail_direction"]), tuple(c["revolute_axis"]),
              float(c["link_length"]), tuple(c["sphere_center"]))
        for c in d["chain"]
    )
    return Prs3(chains, tuple(d["tool"]["point"]), name=d.get("name", "")), d


def read_serial(path: Path) -> tuple[Serial, dict]:
    d = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    assert d["kind"] == "serial"
    joints = tuple(
        Joint(j["type"], tuple(j.get("origin", (0, 0, 0))), tuple(j.get("rpy", (0, 0, 0))), tuple(j["axis"]))
        for j in d["joint"]
    )
    tool = d.get("tool", {})
    return Serial(joints, tuple(tool.get("point", (0, 0, 0))), tuple(tool["rpy"]) if "rpy" in tool else None), d


def identify_map(capsys, recording, machine, json_path, *extra, ok=(0,)) -> dict:
    """Run ``identify --method map --json json_path --quiet`` (plus ``extra`` options) and read its answer.

    ``ok`` holds the exit codes the caller accepts (1 = computed but not plausible).
    """
    rc, _, err = run(capsys, "identify", recording, "--machine", machine, "--method", "map", *extra,
                     "--json", json_path, "--quiet")
    assert rc in ok, err
    return answer(json_path)


def diagnose_checked(capsys, recording, machine, json_path, *extra) -> dict:
    """Run ``diagnose --json json_path --quiet`` (plus ``extra`` options), expect exit 0, check the answer's keys."""
    rc, _, err = run(capsys, "diagnose", recording, "--machine", machine, *extra, "--json", json_path, "--quiet")
    assert rc == 0, err
    a = answer(json_path)
    check_diagnose_answer(a)
    return a
