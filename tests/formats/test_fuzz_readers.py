"""Fuzzing every reader: any input is read or refused with a BayescalError, never another exception (issue 30, item 4).

Property-based (hypothesis, derandomised so that CI sees the same cases every
run): recordings (CSV text and raw bytes), machine files (mutated TOML), pose
files, MCMC checkpoints (valid archives with damaged arrays, and raw bytes),
a comparison's saved state and ``--methods`` specs.  The time limit is
hypothesis' per-example deadline, not a wall-clock assertion.
"""

from __future__ import annotations

import json
import math
import re
import tempfile
from datetime import timedelta
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayescal.errors import BayescalError
from tests.conftest import ROOT

FUZZ = settings(max_examples=40, deadline=timedelta(seconds=5), derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# ------------------------------------------------------------------ recording CSV
COLUMNS = ["q1", "q2", "q3", "x", "y", "z", "rx", "ry", "rz", "nx", "ny", "nz", "sigma_position", "sigma_angle",
           "temp_C", "x_um", "y_m", "q1_deg", "rx_deg", "sigma_position_um", "Q1", "", "q4", "measure", "x_deg"]
CELLS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(400, 600).map(repr),
    st.floats(-50, 50).map(repr),
    st.sampled_from(["", " ", "nan", "inf", "-inf", "1e308", "-1e308", "1e-320", "abc", "1_0", "\u0661", "0x10", "1e",
                     "\"5\"", "# c", "1,5", "5;6", "\t"]),
)


@st.composite
def recording_text(draw):
    header = draw(st.lists(st.sampled_from(COLUMNS), min_size=1, max_size=12))
    # most cases a well-formed 3-PRS header, so that the values (not only the header) are exercised
    if draw(st.booleans()):
        header = ["q1", "q2", "q3", "x", "y", "z"] + draw(st.lists(st.sampled_from(COLUMNS[6:]), max_size=3))
    n = len(header)
    rows = draw(st.lists(st.lists(CELLS, min_size=max(0, n - 1), max_size=n + 1), max_size=6))
    sep = draw(st.sampled_from([",", ",", ";", "\t"]))
    end = draw(st.sampled_from(["\n", "\r\n", "\r", ""]))
    return end.join(sep.join(r) for r in [header, *rows]) + draw(st.sampled_from(["", "\n", "\n\n"]))


def _read_and_model(path: str, text: str | None = None) -> None:
    from bayescal.instrument import prepare_model
    from bayescal.io import read_recording
    from bayescal.machines.files import load_machine

    try:
        rec = read_recording(path, text=text)
        prepare_model(load_machine(ROOT / "examples" / "prs3" / "machine.toml"), rec)
    except BayescalError:
        pass


@FUZZ
@given(recording_text())
def test_recordings_are_read_or_refused(text):
    _read_and_model("fuzz.csv", text)


@FUZZ
@given(st.binary(max_size=300))
def test_recording_bytes_are_read_or_refused(data):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "fuzz.csv"
        p.write_bytes(b"q1,q2,q3,x,y,z\n" + data)
        _read_and_model(str(p))


# ------------------------------------------------------------------ machine files (TOML)
MACHINES = [ROOT / "examples" / k / "machine.toml" for k in ("prs3", "delta", "raspm", "rupus_prs", "arm6")]
_ASSIGN = re.compile(r"^(\s*[A-Za-z_][\w.]*\s*=\s*)(.+)$")


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + "}"
    return str(v)


NUMBERS = st.one_of(st.integers(-10**30, 10**30), st.floats(), st.sampled_from([0, 0.0, -0.0, 1e-300, 1e300]))
VALUES = st.recursive(
    st.one_of(NUMBERS, st.booleans(), st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.from_regex(r"[a-z]{1,6}", fullmatch=True),
                                                                         inner, max_size=3)),
    max_leaves=8,
)


@st.composite
def machine_text(draw):
    lines = draw(st.sampled_from(MACHINES)).read_text().splitlines()
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(lines) - 1))
        how = draw(st.sampled_from(["value", "value", "vector", "drop", "dup", "garbage"]))
        m = _ASSIGN.match(lines[i])
        if how == "value" and m:
            lines[i] = m.group(1) + _toml(draw(VALUES))
        elif how == "vector" and m:
            lines[i] = m.group(1) + _toml(draw(st.lists(NUMBERS, min_size=0, max_size=5)))
        elif how == "drop":
            del lines[i]
        elif how == "dup":
            lines.insert(i, lines[i])
        elif how == "garbage":
            lines.insert(i, draw(st.sampled_from(["[[chain]]", "[tool]", "[effect.backlash]", "kind = \"hybrid\"",
                                                  "[[module]]\nfile = \"machine.toml\"\nrole = \"tool\"", "= 1", "[x"])))
    return "\n".join(lines) + "\n"


@FUZZ
@given(machine_text())
def test_machine_files_are_read_or_refused(text):
    from bayescal.machines.files import machine_from_text

    try:
        m = machine_from_text(text, "fuzz.toml")
    except BayescalError:
        return
    q = m.home_q()[None, :]
    try:
        m.forward(q)
    except BayescalError:
        pass


@FUZZ
@given(st.binary(max_size=200))
def test_machine_file_bytes_are_read_or_refused(data):
    from bayescal.machines.files import load_machine

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "m.toml"
        p.write_bytes(b'kind = "3-PRS"\n' + data)
        try:
            load_machine(p)
        except BayescalError:
            pass


# ------------------------------------------------------------------ pose files
@FUZZ
@given(recording_text())
def test_pose_files_are_read_or_refused(text):
    from bayescal.simulated import read_poses_file

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "poses.csv"
        p.write_text(text)
        try:
            q = read_poses_file(str(p), 3)
        except BayescalError:
            return
        assert q.shape[1] == 3 and np.isfinite(q).all()


# ------------------------------------------------------------------ MCMC checkpoints
FP = {"seed": 0, "n_walkers": 4, "names": ["a", "b"], "surrogate": "none", "data_sha256": "x", "proposal": "p"}
KEYS = ["chain", "log_prob", "accepted", "iteration", "rs_keys", "rs_meta", "rs_cached", "rs_name", "fingerprint", "blobs"]
ARRAYS = st.one_of(
    st.builds(lambda shape, v: np.full(shape, v), st.lists(st.integers(0, 5), max_size=3).map(tuple),
              st.one_of(st.floats(), st.integers(-2**40, 2**40), st.booleans(), st.text(max_size=5))),
    st.sampled_from([np.array("MT19937"), np.array(json.dumps(FP)), np.array("{}"), np.zeros(624, np.uint32),
                     np.array([1 + 2j]), np.array(3), np.array(-3)]),
)


def _good_checkpoint(path: Path) -> dict:
    import emcee

    from bayescal.bayes.checkpoint import save_checkpoint

    backend = emcee.backends.Backend()
    backend.reset(4, 2)
    backend.grow(3, None)
    backend.chain[:] = 1.0
    backend.log_prob[:] = -1.0
    backend.iteration = 3
    backend.random_state = np.random.RandomState(0).get_state()
    save_checkpoint(path, backend, FP)
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


@FUZZ
@given(st.dictionaries(st.sampled_from(KEYS), ARRAYS, min_size=1, max_size=3), st.sets(st.sampled_from(KEYS), max_size=2))
def test_checkpoints_with_damaged_arrays_are_refused(changes, drop):
    from bayescal.bayes.checkpoint import load_checkpoint

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.npz"
        data = {**_good_checkpoint(p), **changes}
        np.savez(p, **{k: v for k, v in data.items() if k not in drop})
        try:
            backend = load_checkpoint(p, FP)
        except BayescalError:
            return
        assert backend.chain.shape == (backend.iteration, 4, 2) and np.isfinite(backend.chain).all()


@FUZZ
@given(st.binary(max_size=400), st.integers(0, 2000))
def test_checkpoint_bytes_are_refused(data, cut):
    from bayescal.bayes.checkpoint import load_checkpoint

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.npz"
        _good_checkpoint(p)
        raw = p.read_bytes()
        p.write_bytes(raw[:cut] + data + raw[cut + len(data):])
        try:
            load_checkpoint(p, FP)
        except BayescalError:
            pass


# ------------------------------------------------------------------ a comparison's saved state
GOOD = {"trial": 0, "nominal": {"rms_position": 0.1}, "n_free": 3,
        "methods": {"ls": {"success": True, "message": "", "seconds": 0.1, "rms_position": 0.01}}}
JSON = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20), st.floats(allow_nan=False),
                              st.text(max_size=5)),
                    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                    max_leaves=8)


@st.composite
def trial_line(draw):
    rec = json.loads(json.dumps(GOOD))
    how = draw(st.sampled_from(["good", "key", "value", "any", "cut"]))
    if how == "key":
        rec.pop(draw(st.sampled_from(sorted(rec))))
    elif how == "value":
        path = draw(st.sampled_from([("trial",), ("nominal",), ("methods",), ("methods", "ls"), ("methods", "ls", "success"),
                                     ("methods", "ls", "rms_position"), ("nominal", "rms_position")]))
        target = rec
        for k in path[:-1]:
            target = target[k]
        target[path[-1]] = draw(JSON)
    elif how == "any":
        return json.dumps(draw(JSON))
    text = json.dumps(rec)
    return text[: draw(st.integers(0, len(text)))] if how == "cut" else text


@FUZZ
@given(st.lists(trial_line(), max_size=4), st.one_of(st.none(), JSON), st.binary(max_size=20))
def test_saved_comparison_states_are_read_or_refused(lines, config, tail):
    from bayescal.compare.result import comparison_from_records
    from bayescal.compare.runner import CONFIG_FILE, TRIALS_FILE, load_trials
    from bayescal.compare.trial import CompareConfig

    cfg = CompareConfig(machine_text="", methods="ls", trials=2)
    with tempfile.TemporaryDirectory() as d:
        if config is not None:
            (Path(d) / CONFIG_FILE).write_text(json.dumps(config))
        (Path(d) / TRIALS_FILE).write_bytes("\n".join(lines).encode() + b"\n" + tail)
        try:
            done = load_trials(d, cfg)
        except BayescalError:
            return
        if len(done) == cfg.trials:  # what a resumed comparison then computes from them
            comparison_from_records([done[t] for t in range(cfg.trials)], cfg, n_resamples=50)


# ------------------------------------------------------------------ --methods
SPEC = st.builds(
    lambda name, opts: name + (":" + ";".join(opts) if opts else ""),
    st.sampled_from(["ls", "ridge", "tsvd", "map", "kalman", "mcmc", "foo", ""]),
    st.lists(st.builds(lambda k, v: f"{k}={v}", st.sampled_from(["lam", "k", "rule", "variant", "steps", "seed",
                                                                 "surrogate", "foo", ""]),
                       st.sampled_from(["1", "0", "-1", "abc", "auto", "snr", "gcv", "nope", "ukf", "linear", "1e400",
                                        "nan", "2.5", "20", "4294967296", ""])), max_size=2),
)


@FUZZ
@given(st.lists(SPEC, max_size=4).map(",".join))
def test_method_specs_are_parsed_or_refused(text):
    from bayescal.compare.methods import METHODS, parse_methods

    try:
        specs = parse_methods(text)
    except BayescalError:
        return
    for s in specs:  # what parsed is what the method takes
        m = METHODS[s.name]
        if m.check is not None:
            m.check({**m.defaults, **dict(s.options)}, s.label)
