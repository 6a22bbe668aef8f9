"""Benchmark: what the ``targets`` rule for k costs per recording, against the ``success`` rule it replaced.

The ``targets`` rule first calibrates its Lagrange weights on the
recording's design (:func:`bayescal.identify.target_rule.calibrate_target_rule`:
300 simulated data sets per truth scale, each valued under four posteriors,
one linear programme), then applies them (:meth:`TargetRule.choose`).  The
baseline is one call of the ``success`` rule on the same problem
(``choose_linear(..., rule="success")``, 2,000 posterior draws, which also
computes every other rule): the default for k before.  Reported per size:
CPU time of the calibration, of applying the calibrated rule to one data
set, and of the baseline; their ratios; and the growth exponent of each
time with the number of parameters ``p``.

Designs: random ``A`` with ``N = 3 p`` rows and singular values spread over
three decades (like a calibration Jacobian after tolerance scaling), an
output map of ``3 p`` rows, TSVD candidates ``k = 1..p``; seed 1.  The
3-PRS of ``studies/choice_rules.py`` has ``p = 33``.  CPU time
(``time.process_time``) with one BLAS thread.

    python benchmarks/target_rule.py [--quick] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bayescal.identify.choose import choose_linear  # noqa: E402
from bayescal.identify.target_rule import calibrate_target_rule, rule_design  # noqa: E402
from bayescal.io import write_json_atomic  # noqa: E402


def design(p: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``A`` (3p x p, singular values over three decades), an output map and one data set."""
    U, _ = np.linalg.qr(rng.normal(size=(3 * p, p)))
    V, _ = np.linalg.qr(rng.normal(size=(p, p)))
    A = U @ np.diag(np.logspace(1.5, -1.5, p)) @ V.T
    z = A @ rng.normal(size=p) + rng.normal(size=3 * p)
    return A, rng.normal(size=(3 * p, p)), z


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="p = 8 and 16 only")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out"))
    args = ap.parse_args(argv)
    sizes = (8, 16) if args.quick else (8, 16, 32, 64)
    rng = np.random.default_rng(1)
    rows = []
    for p in sizes:
        A, G, z = design(p, rng)
        grid = np.arange(1, p + 1)
        t = time.process_time()
        choose_linear(A, z, "tsvd", rule="success", output_map=G)
        t_success = time.process_time() - t
        t = time.process_time()
        rule = calibrate_target_rule(A, "tsvd", grid, output_map=G)
        t_cal = time.process_time() - t
        d = rule_design(A, "tsvd", grid, G)
        t = time.process_time()
        rule.choose(d, d.U.T @ z)
        t_apply = time.process_time() - t
        rows.append({"p": p, "success_cpu_s": t_success, "calibrate_cpu_s": t_cal, "apply_cpu_s": t_apply,
                     "calibrate_over_success": t_cal / t_success, "apply_over_success": t_apply / t_success})
        print(f"p={p:3d}: success rule {t_success:7.3f} s; targets calibration {t_cal:7.2f} s "
              f"({t_cal / t_success:6.1f} x), applying it {t_apply:6.3f} s ({t_apply / t_success:5.2f} x)", flush=True)
    logp = np.log([r["p"] for r in rows])
    growth = {k: float(np.polyfit(logp, np.log([r[k] for r in rows]), 1)[0])
              for k in ("success_cpu_s", "calibrate_cpu_s", "apply_cpu_s")}
    print("growth exponent with p: " + ", ".join(f"{k.removesuffix('_cpu_s')} {v:.2f}" for k, v in growth.items()))
    write_json_atomic(Path(args.out) / "target_rule.json", {"rows": rows, "growth_exponent": growth})
    return 0


if __name__ == "__main__":
    sys.exit(main())
