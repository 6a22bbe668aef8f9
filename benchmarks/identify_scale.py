"""Benchmark: ``bayescal identify`` on a 444-pose, 7-joint serial recording with a fitted instrument frame.

Issue 32: on a real serial recording of 444 poses (7 joints from a URDF,
total-station frame fitted) ``identify --method map`` took 4.6 times the
bundled 36-pose 3-PRS example.  Targets, in one run on 2 cores: map under
2 s wall on a quiet machine and at most 2 times the 3-PRS example; the
automatic lambda and k rules (``--method ridge --lam auto``, ``--method
tsvd --k auto``) under 3 times map.

The problem.  The issue's recording is not public, so one of the same
shape is simulated:

* the machine: the 7-R arm of the PAL Robotics TIAGo, from ``torso_lift_link``
  to ``wrist_ft_tool_link`` (the joint table of
  ``../shared/data/real/tiago/README.md``, typed in below in mm and rad; the
  fixed joints after ``arm_7_joint`` are folded into the tool), with a
  measured point (59, 1, 72) mm in ``wrist_ft_tool_link`` (about where the
  upstream calibration put its marker).  With ``--urdf PATH`` the chain is
  read from the TIAGo URDF itself (``tiago.urdf``, CC BY-NC-ND: read where it
  lies, never copied), as the issue's machine was;
* the instrument: position-only (3-DOF), sigma 0.2 mm, a total station 3.8 m
  from the arm's base, turned by 122 degrees (``[instrument] origin =
  [3200, -1500, 800]`` mm, ``rotation_vector = [0.3, -0.2, 2.1]`` rad) in the
  file that simulates; the file that identifies has no ``[instrument]``
  table and the frame is fitted (``--frame fit``);
* 444 poses drawn in the URDF's joint limits, errors drawn from the default
  tolerances (``bayescal simulate --dof 3 --seed 1``).

Three recordings exercise the paths a real one takes:

* ``clean``: the noise as stated;
* ``noise``: the machine file states half the simulated sigma, so the noise
  check of ``bayescal.identify.calibrate`` rejects it and refits with the
  estimated scale;
* ``outliers``: four poses moved by 3 mm, so the outlier test flags them
  and the robust (Student-t IRLS) refit runs.

Contestants: each command in its own process (start-up included, as a
user pays it), interleaved (one of each per round, the order rotated),
``--repeats`` rounds; median and range of the wall time, median CPU time
(user + system of the process) and peak memory (``ru_maxrss``).  BLAS is
single-threaded for everyone.  ``--stages`` also times the stages inside
one process (imports excluded): reading, the model, ``calibrate``.

``--answers DIR`` keeps every command's JSON answer; ``--compare DIR``
compares them with an earlier run's (numbers to 1e-9 relative, texts
exactly), so a speed change can be shown not to change the answers.

Run (from the repository root)::

    python benchmarks/identify_scale.py                         # about 3 minutes on a shared machine
    python benchmarks/identify_scale.py --urdf ../shared/data/real/tiago/tiago.urdf --repeats 5
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out" / "identify_scale"
PI = math.pi

#: TIAGo arm_1 ... arm_7 (README table, tiago.urdf): origin xyz (m), rpy (rad); every axis local z.
TIAGO_ARM = [
    ((0.15505, 0.014, -0.151), (0.0, 0.0, -PI / 2)),
    ((0.125, 0.0165, -0.031), (PI / 2, 0.0, 0.0)),
    ((0.0895, 0.0, 0.0015), (-PI / 2, 0.0, PI / 2)),
    ((-0.02, -0.027, -0.222), (-PI / 2, -PI / 2, 0.0)),
    ((-0.162, 0.02, 0.027), (0.0, -PI / 2, 0.0)),
    ((0.0, 0.0, 0.15), (0.0, -PI / 2, -PI / 2)),
    ((0.0, 0.0, 0.0), (PI / 2, 0.0, PI / 2)),
]
#: Fixed joints arm_tool_joint, wrist_ft_joint, wrist_tool_joint (m, rad) and the URDF joint limits (rad).
TIAGO_TAIL = [((0.0, 0.0, 0.046), (PI / 2, -PI / 2, PI)), ((0.00785, 0.0, 0.0), (PI / 2, 0.0, PI / 2)),
              ((0.0, 0.0, 0.012725), (-PI / 2, -PI / 2, 0.0))]
TIAGO_LIMITS = [(0.0, 2.7489), (-PI / 2, 1.0908), (-3.5343, PI / 2), (-0.3927, 2.3562), (-2.0944, 2.0944),
                (-1.4137, 1.4137), (-2.0944, 2.0944)]
MARKER_MM = (59.0, 1.0, 72.0)
INSTRUMENT = "[instrument]\norigin = [3200.0, -1500.0, 800.0]\nrotation_vector = [0.3, -0.2, 2.1]\n"
SIGMA = 0.2
N_POSES = 444
METHODS = {"map": ["--method", "map"], "ridge-auto": ["--method", "ridge", "--lam", "auto"],
           "tsvd-auto": ["--method", "tsvd", "--k", "auto"]}


def _f(v) -> str:
    return "[" + ", ".join(repr(float(x)) for x in v) + "]"


def arm7_toml(*, sigma: float = SIGMA, instrument: bool = False, urdf: Path | None = None) -> str:
    """The TIAGo 7-R arm as a serial machine file (mm, rad), from the joint table or a URDF."""
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from bayescal.machines.serial import rpy_from_matrix, rpy_matrix

    head = ['kind = "serial"', 'name = "TIAGo arm, 7 R (benchmark)"', ""]
    if urdf is not None:
        head += [f"urdf = {json.dumps(str(Path(urdf).resolve()))}", 'base_link = "torso_lift_link"',
                 'tip_link = "wrist_ft_tool_link"', "", "[tool]", f"point = {_f(MARKER_MM)}", ""]
    else:
        for xyz, rpy in TIAGO_ARM:
            head += ["[[joint]]", 'type = "revolute"', f"origin = {_f(np.round(1000 * np.array(xyz), 9))}", f"rpy = {_f(rpy)}",
                     "axis = [0.0, 0.0, 1.0]", ""]
        R, p = np.eye(3), np.zeros(3)
        for xyz, rpy in TIAGO_TAIL:
            p, R = p + R @ (1000 * np.array(xyz)), R @ rpy_matrix(rpy)
        head += ["[tool]", f"point = {_f(p + R @ np.array(MARKER_MM))}", f"rpy = {_f(rpy_from_matrix(R))}", ""]
        head += ["[workspace]", "q_limits = [" + ", ".join(_f(x) for x in TIAGO_LIMITS) + "]", ""]
    head += ["[measurement]", f"sigma_position = {sigma!r}", ""]
    return "\n".join(head) + (INSTRUMENT if instrument else "")


def _bayescal(*args, capture=True):
    return subprocess.run([sys.executable, "-m", "bayescal", *map(str, args)], capture_output=capture, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True)


def prepare(out: Path, urdf: Path | None) -> dict:
    """Machine files and the three recordings; returns {name: (recording, machine)}."""
    out.mkdir(parents=True, exist_ok=True)
    cases = {"prs3": (ROOT / "examples/prs3/recording.csv", ROOT / "examples/prs3/machine.toml")}
    for tag, u in (("arm7", None), ("arm7-urdf", urdf)):
        if tag == "arm7-urdf" and u is None:
            continue
        sim, fit, half = out / f"{tag}_sim.toml", out / f"{tag}.toml", out / f"{tag}_half_sigma.toml"
        sim.write_text(arm7_toml(instrument=True, urdf=u))
        fit.write_text(arm7_toml(urdf=u))
        half.write_text(arm7_toml(urdf=u, sigma=SIGMA / 2))
        rec = out / f"{tag}_{N_POSES}.csv"
        if not rec.exists():
            _bayescal("simulate", "--machine", sim, "--poses", N_POSES, "--seed", 1, "--dof", 3, "--out", rec, "--quiet")
        cases[tag] = (rec, fit)
        if tag == "arm7":
            cases["arm7-noise"] = (rec, half)
            bad = out / f"{tag}_{N_POSES}_outliers.csv"
            lines = rec.read_text().splitlines()
            for i in (17, 111, 250, 401):  # data rows: x moved by 3 mm
                cells = lines[i].split(",")
                cells[7] = repr(float(cells[7]) + 3.0)
                lines[i] = ",".join(cells)
            bad.write_text("\n".join(lines) + "\n")
            cases["arm7-outliers"] = (bad, fit)
    return cases


def contestants(cases: dict, methods: list[str]) -> list[tuple[str, list]]:
    out = []
    for case, (rec, machine) in cases.items():
        frame = [] if case == "prs3" else ["--frame", "fit"]
        for m in methods:
            if case in ("arm7-noise", "arm7-outliers", "arm7-urdf") and m != "map":
                continue
            out.append((f"{case} {m}", ["identify", rec, "--machine", machine, *METHODS[m], *frame]))
    return out


def run_one(args: list, json_path: Path | None) -> dict:
    """One command in its own process: wall, CPU (user + system) and peak memory."""
    cmd = [sys.executable, "-m", "bayescal", *map(str, args), "--quiet"]
    if json_path is not None:
        cmd += ["--json", str(json_path)]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    err = p.stderr.read().decode()
    p.stderr.close()
    if p.returncode not in (0, 1):
        raise RuntimeError(f"{' '.join(cmd)} exited {p.returncode}: {err[-2000:]}")
    return {"wall": wall, "cpu": ru.ru_utime + ru.ru_stime, "peak_mb": ru.ru_maxrss / 1024, "exit": p.returncode}


def stages(rec: Path, machine: Path, method: list, frame: str, repeat: int = 1) -> dict:
    """Seconds of each stage in one process (best of ``repeat``; 1: the first, cold run), imports excluded."""
    code = f"""
import json, time, sys
sys.path.insert(0, {str(ROOT)!r})
from bayescal.machines.files import load_machine
from bayescal.io import read_recording
from bayescal.instrument import prepare_model
from bayescal.identify.calibrate import calibrate
kw = {json.dumps(dict(zip(method[0::2], method[1::2])))}
kw = {{k.lstrip('-'): (v if v == 'auto' or k == '--method' else float(v)) for k, v in kw.items()}}
best = {{}}
for _ in range({repeat}):
    t = {{}}
    t0 = time.perf_counter(); m = load_machine({str(machine)!r}); rec = read_recording({str(rec)!r}); t['read'] = time.perf_counter() - t0
    t0 = time.perf_counter(); m2, model, _ = prepare_model(m, rec, frame={frame!r}); t['model'] = time.perf_counter() - t0
    t0 = time.perf_counter(); calibrate(model, **kw); t['calibrate'] = time.perf_counter() - t0
    best = {{k: min(v, best.get(k, v)) for k, v in t.items()}}
print(json.dumps(best))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    return json.loads(res.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- answers
def compare_json(a, b, path="", rtol=1e-9, atol=1e-12) -> list[str]:
    """Differences between two JSON answers: numbers beyond ``rtol`` (relative) + ``atol``, texts not equal."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}: keys differ {sorted(set(a) ^ set(b))}"] if set(a) != set(b) else []
        for k in sorted(set(a) & set(b)):
            out += compare_json(a[k], b[k], f"{path}.{k}", rtol, atol)
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: lengths {len(a)} and {len(b)}"]
        out = []
        for i, (x, y) in enumerate(zip(a, b)):
            out += compare_json(x, y, f"{path}[{i}]", rtol, atol)
        return out
    num = (int, float)
    if isinstance(a, num) and isinstance(b, num) and not isinstance(a, bool) and not isinstance(b, bool):
        if math.isnan(a) and math.isnan(b):
            return []
        return [] if abs(a - b) <= rtol * max(abs(a), abs(b)) + atol or a == b else [f"{path}: {a!r} != {b!r}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="interleaved rounds (default 3)")
    ap.add_argument("--methods", default="map,ridge-auto,tsvd-auto")
    ap.add_argument("--urdf", type=Path, help="tiago.urdf (read in place): also run the chain read from the URDF")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--answers", type=Path, help="write every command's JSON answer into this folder")
    ap.add_argument("--compare", type=Path, help="compare the answers with those of an earlier --answers folder")
    ap.add_argument("--stages", action="store_true", help="also time the stages inside one process")
    args = ap.parse_args(argv)
    methods = args.methods.split(",")
    cases = prepare(args.out, args.urdf)
    todo = contestants(cases, methods)
    if args.answers:
        args.answers.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()[0]
    runs = {name: [] for name, _ in todo}
    for r in range(args.repeats):
        order = todo[r % len(todo):] + todo[: r % len(todo)]
        for name, cmd in order:
            jp = args.answers / (name.replace(" ", "_") + ".json") if args.answers and r == 0 else None
            runs[name].append(run_one(cmd, jp))
    print(f"identify, {N_POSES}-pose 7-R arm (3-DOF, frame fitted) against the 36-pose 3-PRS example; "
          f"{args.repeats} interleaved rounds, load {load0:.2f} at start, {os.getloadavg()[0]:.2f} at end")
    print(f"  {'command':<24} {'wall median [s]':>15} {'range':>15} {'cpu [s]':>8} {'peak [MB]':>9}")
    med = {}
    for name, rs in runs.items():
        w = [x["wall"] for x in rs]
        med[name] = statistics.median(w)
        print(f"  {name:<24} {med[name]:15.2f} {min(w):7.2f}-{max(w):<7.2f} {statistics.median(x['cpu'] for x in rs):8.2f} "
              f"{max(x['peak_mb'] for x in rs):9.0f}")
    base = med.get("prs3 map")
    if base and "arm7 map" in med:
        m = med["arm7 map"]
        print(f"\n  arm7 map: {m:.2f} s (target < 2 s on a quiet machine), {m / base:.2f}x the 3-PRS map (target <= 2)")
        for k in ("ridge-auto", "tsvd-auto"):
            if f"arm7 {k}" in med:
                print(f"  arm7 {k}: {med[f'arm7 {k}'] / m:.2f}x arm7 map (target < 3)")
    if args.stages:
        print("\n  stages in one process, imports excluded (one cold run) [s]:")
        for name, cmd in todo:
            rec, machine = cmd[1], cmd[3]
            method = cmd[4:cmd.index("--frame")] if "--frame" in cmd else cmd[4:]
            frame = "fit" if "--frame" in cmd else "base"
            s = stages(rec, machine, method, frame)
            print(f"  {name:<24} " + "  ".join(f"{k} {v:.3f}" for k, v in s.items()))
    if args.compare and args.answers:
        bad = 0
        for f in sorted(args.answers.glob("*.json")):
            g = args.compare / f.name
            if not g.exists():
                print(f"  {f.name}: no earlier answer")
                continue
            diffs = compare_json(json.loads(g.read_text()), json.loads(f.read_text()))
            bad += bool(diffs)
            print(f"  {f.name}: " + ("same answer (1e-9)" if not diffs else f"{len(diffs)} differences, e.g. {diffs[:3]}"))
        return 1 if bad else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
