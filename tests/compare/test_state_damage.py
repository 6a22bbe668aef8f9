"""A damaged comparison state (--out DIR) is refused naming the file and line, never a traceback (issue 30)."""

from __future__ import annotations

import json

import pytest

from bayescal.cli import main
from bayescal.compare.runner import CONFIG_FILE, TRIALS_FILE, load_trials
from bayescal.compare.trial import CompareConfig
from bayescal.errors import InputError
from tests.conftest import PRS3_FILE

CFG = CompareConfig(machine_text=PRS3_FILE.read_text(), methods="ls,ridge", trials=3)
GOOD = {"trial": 0, "nominal": {"rms_position": 0.1}, "n_free": 3,
        "methods": {"ls": {"success": True, "message": "", "seconds": 0.1, "rms_position": 0.01},
                    "ridge": {"success": False, "message": "no", "seconds": 0.1}}}


def _state(tmp_path, trials: bytes, config=None):
    (tmp_path / CONFIG_FILE).write_text(json.dumps(CFG.to_dict() if config is None else config))
    (tmp_path / TRIALS_FILE).write_bytes(trials)
    return tmp_path


def test_good_state_and_a_torn_last_line_load(tmp_path):
    line = json.dumps(GOOD).encode()
    done = load_trials(_state(tmp_path, line + b"\n" + line[:20]), CFG)
    assert list(done) == [0]
    assert (tmp_path / TRIALS_FILE).read_bytes() == line + b"\n"  # the torn line dropped


@pytest.mark.parametrize("trials, match", [
    (json.dumps(GOOD)[:30].encode() + b"\n" + json.dumps(GOOD).encode() + b"\n", "line 1: not a JSON trial record"),
    (json.dumps({k: v for k, v in GOOD.items() if k != "trial"}).encode() + b"\n", 'line 1: expected "trial"'),
    (json.dumps({**GOOD, "trial": "0"}).encode() + b"\n", 'line 1: expected "trial"'),
    (b"\x00\xff\xfe binary\n", "not a UTF-8 text file"),
    (b"[1, 2]\n", "line 1: expected a JSON object"),
    (json.dumps({**GOOD, "methods": {"ls": GOOD["methods"]["ls"]}}).encode() + b"\n", "no result of method 'ridge'"),
    (json.dumps({**GOOD, "nominal": {"rms_position": "x"}}).encode() + b"\n", "nominal"),
    (b"\n" + json.dumps({**GOOD, "methods": {**GOOD["methods"], "ls": {"success": "yes"}}}).encode() + b"\n",
     "line 2: no result of method 'ls'"),
    (b"[" * 100000 + b"\n", "line 1: not a JSON trial record"),
])
def test_damaged_trials_are_refused_naming_the_line(tmp_path, trials, match):
    with pytest.raises(InputError, match=f"{TRIALS_FILE}: .*{match}" if "line" in match else match):
        load_trials(_state(tmp_path, trials), CFG)


@pytest.mark.parametrize("config, match", [([1, 2], "expected a JSON object"), ("text", "expected a JSON object")])
def test_a_config_that_is_not_an_object_is_refused(tmp_path, config, match):
    with pytest.raises(InputError, match=f"{CONFIG_FILE}: {match}"):
        load_trials(_state(tmp_path, b"", config), CFG)


def test_binary_config_and_a_linked_state_are_refused(tmp_path):
    (tmp_path / CONFIG_FILE).write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputError, match="not a UTF-8 text file"):
        load_trials(tmp_path, CFG)
    (tmp_path / CONFIG_FILE).unlink()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (tmp_path / TRIALS_FILE).symlink_to(victim)  # appends would go through the link
    with pytest.raises(InputError, match="is a symbolic link"):
        load_trials(tmp_path, CFG)


def test_the_command_refuses_a_damaged_state_in_one_line(tmp_path, capsys):
    out = tmp_path / "cmp"
    out.mkdir()
    (out / CONFIG_FILE).write_text("[]")
    rc = main(["compare", "--machine", str(PRS3_FILE), "--methods", "ls", "--trials", "1", "--poses", "12",
               "--eval-poses", "5", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "config.json: expected a JSON object" in err[0]
