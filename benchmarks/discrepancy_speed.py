"""Cost of the model discrepancy against the geometry-only MAP calibration, and its growth with the poses.

Baseline (same run, same recording): ``calibrate(model, method="map")``, what
``bayescal identify --method map`` runs.  Contestant: the same with
``discrepancy="on"`` (hyperparameters by marginal likelihood on at most
1,200 poses, the joint posterior on all).  Recordings: the bundled 6R arm,
position only, with the sag of ``studies/discrepancy_coverage.py``.  Reported:
wall time (median of ``--repeat``, single-threaded BLAS), the ratio to the
baseline, the time exponent between sizes, peak memory (tracemalloc).
Target (issue #28 / #32): 5,000 poses under one minute on 2 cores.

    python benchmarks/discrepancy_speed.py                  # 200, 1000, 2000, 5000 poses
    python benchmarks/discrepancy_speed.py --sizes 200,1000 --repeat 1
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import tracemalloc
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "studies"))

from bayescal.identify.calibrate import calibrate  # noqa: E402
from bayescal.instrument.prepare import prepare_session  # noqa: E402
from bayescal.io.recording import Recording  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402
from bayescal.simulate import draw_errors, draw_poses  # noqa: E402

import discrepancy_coverage as dc  # noqa: E402


def recording(n: int, seed: int = 0) -> Recording:
    machine = load_machine(dc.MACHINE)
    rng = np.random.default_rng([2026, 32, n, seed])
    theta = draw_errors(machine, rng)
    q = draw_poses(machine, n, rng, theta)
    p, aux = dc._mismatch("bending", machine, theta, q, rng)
    p = p + rng.normal(scale=machine.noise.sigma_position, size=p.shape)
    return Recording(q=q, position=p, aux=aux, path=f"<bending {n}>")


def timed(fn):
    """Wall time of ``fn()`` (untraced: tracemalloc slows Python-heavy code by a factor of about two)."""
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def peak_memory(fn) -> float:
    """Peak Python-allocated memory of ``fn()``, MiB, in a separate traced run."""
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="200,1000,2000,5000")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    machine = load_machine(dc.MACHINE)
    rows = []
    for n in [int(s) for s in args.sizes.split(",")]:
        model = prepare_session(machine, recording(n)).fit_model
        base, disc = [], []
        for _ in range(args.repeat):  # contestants interleaved: a load change hits both
            _, t0 = timed(lambda: calibrate(model, method="map"))
            cal, t1 = timed(lambda: calibrate(model, method="map", discrepancy="on"))
            base.append(t0)
            disc.append(t1)
        b, d = float(np.median(base)), float(np.median(disc))
        m0 = peak_memory(lambda: calibrate(model, method="map"))
        m1 = peak_memory(lambda: calibrate(model, method="map", discrepancy="on"))
        rows.append((n, b, d, m0, m1, cal.discrepancy.discrepancy.log_evidence_gain))
        print(f"{n:6d} poses: map {b:7.2f} s [{min(base):.2f}-{max(base):.2f}], with discrepancy {d:7.2f} s "
              f"[{min(disc):.2f}-{max(disc):.2f}] ({d / b:.1f}x), peak memory {m0:.0f} / {m1:.0f} MiB", flush=True)
    print("\n| poses | map (s) | map + discrepancy (s) | ratio | peak memory, map / with (MiB) | exponent |")
    print("|---|---|---|---|---|---|")
    for i, (n, b, d, m0, m1, _) in enumerate(rows):
        exp = "" if i == 0 else f"{math.log(d / rows[i - 1][2]) / math.log(n / rows[i - 1][0]):.2f}"
        print(f"| {n} | {b:.2f} | {d:.2f} | {d / b:.1f} | {m0:.0f} / {m1:.0f} | {exp} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
