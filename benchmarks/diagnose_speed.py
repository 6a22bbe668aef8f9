"""Benchmark: diagnosis time and peak memory against the number of poses, with the growth exponent.

Targets (issue 32, 2 cores): 10,000 poses in under 30 s of CPU, 100,000
poses in under 10 minutes, time exponent at most 1.0 from 1,000 poses on
(issue 12's earlier targets: 5,000 poses in under 60 s and under 1 GB;
50,000 poses in under 10 minutes).  The script prints each against its
target.

The problem: the bundled 3-PRS (``examples/prs3/machine.toml``), a 6-DOF
recording with a concealed 20 um backlash and the time, temperature and
payload channels (``simulate_with_effects``, seed 1), at each size.  Each
recording is written once to ``benchmarks/out/diagnose_speed/`` and every
contestant diagnoses that same file in its own subprocess, so the peak
memory (``ru_maxrss`` of the process: interpreter, numpy and scipy
included) belongs to one diagnosis of one size.

Contestants:

* ``current``: ``bayescal.diagnose.diagnose`` of this checkout.
* ``baseline``: the same function at ``--baseline-ref`` (default: commit
  ``c50f909``, the implementation before the block distance-covariance
  test, whose location tests permute full ``n x n`` distance matrices),
  exported with ``git archive`` into ``benchmarks/out/``.  It runs only up
  to ``--baseline-max`` poses (default 1,000; it needs 11 minutes at 5,000);
  larger sizes are *extrapolated* from its two largest measured points with
  ``t = a n + b n^2`` (model fits are linear, the permutation tests
  quadratic) and marked as such.

Times are CPU seconds of the diagnosis (``time.process_time``; the
target's "2 cores" is the machine, the diagnosis itself runs on one) and,
for information, wall seconds with the load average at the start: on a
shared machine the wall time mostly measures the other jobs.  Also
reported for the current code: the CPU time of one ridge identification
(``identify(model, method="ridge", lam=1)``) of the same recording.

Run (from the repository root; the 100,000-pose point takes several minutes)::

    nice python benchmarks/diagnose_speed.py                              # 160, 1000, 5000
    nice python benchmarks/diagnose_speed.py --sizes 1000,10000,100000 --no-baseline   # issue 32's targets
    nice python benchmarks/diagnose_speed.py --sizes 1000,10000 --baseline-ref ec5df6d --baseline-max 10000
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small matrices: threads only spin on a shared machine
ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out" / "diagnose_speed"
BASELINE_REF = "c50f9095035fde413bd5c7fa2771c00e2b23f280"
#: Issue 32: (poses, CPU seconds at most).
TARGETS = ((10_000, 30.0), (100_000, 600.0))


def _child(args) -> int:
    """Diagnose one recording in this process and print one JSON line."""
    import resource

    sys.path.insert(0, args.src)
    from bayescal.diagnose import diagnose
    from bayescal.io.recording import read_recording
    from bayescal.machines.files import load_machine

    machine = load_machine(ROOT / "examples" / "prs3" / "machine.toml")
    rec = read_recording(args.recording)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    times, cpus = [], []
    for _ in range(args.repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        d = diagnose(machine, rec, seed=1)
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    out = {"seconds": min(times), "cpu_seconds": min(cpus), "load": os.getloadavg()[0],
           "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "before_mb": rss0, "verdict": d.verdict, "located": d.located.channel if d.located else "",
           "located_significant": bool(d.located and d.located.significant)}
    if args.identify:
        from bayescal.identify import identify
        from bayescal.measurement import MeasurementModel

        model = MeasurementModel.from_recording(machine, rec)
        c0 = time.process_time()
        identify(model, method="ridge", lam=1.0, free="all")
        out["identify_cpu_seconds"] = time.process_time() - c0
    print("RESULT " + json.dumps(out))
    return 0


def _run_child(src: Path, recording: Path, repeat: int, identify: bool) -> dict:
    cmd = [sys.executable, __file__, "--child", "--src", str(src), "--recording", str(recording), "--repeat", str(repeat)]
    if identify:
        cmd.append("--identify")
    res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(src)})
    for line in res.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"child failed ({res.returncode}):\n{res.stderr[-3000:]}")


def _export_baseline(ref: str) -> Path:
    dest = OUT / f"baseline-{ref[:7]}"
    if not (dest / "bayescal" / "diagnose" / "locate.py").exists():
        dest.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "bayescal"], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
    return dest


def _recording(n: int) -> Path:
    path = OUT / f"prs3_backlash20_n{n}.csv"
    if not path.exists():
        sys.path.insert(0, str(ROOT))
        from bayescal.effects.simulate import simulate_with_effects
        from bayescal.io import write_recording
        from bayescal.machines.files import load_machine

        machine = load_machine(ROOT / "examples" / "prs3" / "machine.toml")
        sim = simulate_with_effects(machine, n, seed=1, dof=6, effects=[("backlash", 20.0)],
                                    record=("time_s", "temp_C", "payload_kg"))
        write_recording(path, sim.recording)
    return path


def _slope(n0, t0, n1, t1) -> float:
    return math.log(t1 / t0) / math.log(n1 / n0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="160,1000,5000", help="comma-separated pose counts (default 160,1000,5000)")
    ap.add_argument("--baseline-max", type=int, default=1000, help="largest size the baseline runs at (default 1000)")
    ap.add_argument("--baseline-ref", default=BASELINE_REF, help="git commit of the baseline implementation")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--repeat", type=int, default=1, help="timing repeats up to 1,000 poses (best taken; 1 above)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--src", help=argparse.SUPPRESS)
    ap.add_argument("--recording", help=argparse.SUPPRESS)
    ap.add_argument("--identify", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return _child(args)

    sizes = sorted(int(s) for s in args.sizes.split(","))
    OUT.mkdir(parents=True, exist_ok=True)
    base_src = None if args.no_baseline else _export_baseline(args.baseline_ref)
    rows = []
    for n in sizes:
        rec = _recording(n)
        rep = args.repeat if n <= 1000 else 1
        cur = _run_child(ROOT, rec, rep, identify=True)
        base = _run_child(base_src, rec, rep, identify=False) if base_src is not None and n <= args.baseline_max else None
        rows.append({"n": n, "current": cur, "baseline": base})
        print(f"n={n}: current {cur['cpu_seconds']:.1f} s CPU ({cur['seconds']:.1f} s wall), {cur['peak_mb']:.0f} MB, {cur['verdict']}"
              + (f"; baseline {base['cpu_seconds']:.1f} s CPU ({base['seconds']:.1f} s wall), {base['peak_mb']:.0f} MB, {base['verdict']}"
                 if base else ""), flush=True)

    # baseline beyond what it ran: t = a n + b n^2 through its two largest measured points
    measured = [(r["n"], r["baseline"]["cpu_seconds"]) for r in rows if r["baseline"]]
    extrap = None
    if len(measured) >= 2:
        (n0, t0), (n1, t1) = measured[-2:]
        b = (t1 / n1 - t0 / n0) / (n1 - n0)
        a = t0 / n0 - b * n0
        if b > 0 and a > 0:
            extrap = (a, b)

    lines = [
        f"diagnosis of the 3-PRS with 20 um backlash, 6-DOF, aux time_s/temp_C/payload_kg; OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}",
        f"baseline: commit {args.baseline_ref[:7]}"
        + (" (full-matrix permutation tests)" if args.baseline_ref == BASELINE_REF else "")
        + f", measured up to {args.baseline_max} poses"
        + (f"; above: extrapolated t = {extrap[0]:.3g} n + {extrap[1]:.3g} n^2 s (marked ~)" if extrap else ""),
        "",
        "| poses | current CPU [s] | slope | wall [s] (load) | peak [MB] | identify CPU [s] | verdict | baseline CPU [s] | slope | baseline wall [s] | baseline peak [MB] | baseline verdict | speed-up (CPU) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    prev = None
    for r in rows:
        n, c, b = r["n"], r["current"], r["baseline"]
        slope = f"{_slope(prev['n'], prev['current']['cpu_seconds'], n, c['cpu_seconds']):.2f}" if prev else "-"
        bwall = "-"
        if b:
            bt, bpk, bv = b["cpu_seconds"], f"{b['peak_mb']:.0f}", b["verdict"]
            bts, bwall = f"{bt:.1f}", f"{b['seconds']:.1f} ({b['load']:.1f})"
        elif extrap:
            bt, bpk, bv = extrap[0] * n + extrap[1] * n * n, "-", "-"
            bts = f"~{bt:.0f}"
        else:
            bt, bpk, bv, bts = None, "-", "-", "-"
        bslope = "-"
        if prev and bt is not None and prev.get("_bt") is not None:
            bslope = f"{_slope(prev['n'], prev['_bt'], n, bt):.2f}" + ("" if b else "~")
        speed = f"{bt / c['cpu_seconds']:.1f}x" + ("" if b else "~") if bt is not None else "-"
        lines.append(f"| {n} | {c['cpu_seconds']:.1f} | {slope} | {c['seconds']:.1f} ({c['load']:.1f}) | {c['peak_mb']:.0f} | "
                     f"{c.get('identify_cpu_seconds', float('nan')):.2f} | {c['verdict']} | {bts} | {bslope} | {bwall} | {bpk} | {bv} | {speed} |")
        prev = {**r, "_bt": bt}
    big = [r for r in rows if r["n"] >= 1000]
    if len(big) >= 2:
        slope = _slope(big[0]['n'], big[0]['current']['cpu_seconds'], big[-1]['n'], big[-1]['current']['cpu_seconds'])
        lines.append("")
        lines.append(f"growth exponent of the current diagnosis from {big[0]['n']} to {big[-1]['n']} poses: "
                     f"{slope:.2f} (CPU time; 1 = linear; target <= 1.0: {'met' if slope <= 1.0 else 'missed'})")
    for n_target, limit in TARGETS:
        hit = [r for r in rows if r["n"] == n_target]
        if hit:
            c = hit[0]["current"]["cpu_seconds"]
            lines.append(f"{n_target} poses: {c:.1f} s CPU, target < {limit:.0f} s: {'met' if c < limit else 'missed'}")
    try:
        load = os.getloadavg()
        lines.append(f"load average at the end: {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} (2 cores, shared)")
    except OSError:
        pass
    text = "\n".join(lines)
    print()
    print(text)
    (OUT / "table.md").write_text(text + "\n")
    (OUT / "results.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
