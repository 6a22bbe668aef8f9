"""Held-out coverage and error on the real recordings, with and without the model discrepancy.

The two real recordings of ``docs/real-recordings.md``: the two-axis
positioner (``examples/positioner``, 205 poses, 6-DOF, Apache-2.0) and the
TIAGo arm (``examples/tiago``, 34 poses, position only, Apache-2.0; its chain
written from the kinematic parameters of the URDF, whose file is CC BY-NC-ND
and not used).  Each is cut into folds; every
fold is held out as ``role = check`` rows of the same recording and
calibrated exactly as ``bayescal identify --method map --frame fit
[--discrepancy auto]`` calibrates it (bayescal.load and bayescal.calibrate,
which score the check rows as identify's answer does).  Reported per
recording: held-out mean and p95 position error, the share of held-out
poses inside their 90 % region, how often the discrepancy was kept, and the
noise scale the residuals supported.

    python studies/real_discrepancy.py                 # positioner 10 folds, TIAGo leave-one-out
    python studies/real_discrepancy.py --quick         # 3 folds each (the test suite)
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import bayescal
from bayescal.io import read_recording, write_json_atomic
from bayescal.machines.files import load_machine

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import real_common as rc  # noqa: E402

ROOT = HERE.parent
OUT = HERE / "data" / "real_discrepancy.json"


def folds_of(n: int, k: int, seed: int = 0) -> list[np.ndarray]:
    return rc.kfold(n, k, seed)


def run(name: str, machine, rec, k: int, modes=("off", "auto")) -> dict:
    """Cross-validate one recording: each fold held out as check rows, calibrated as identify calibrates."""
    n = rec.n_poses
    out = {m: {"err": np.full(n, np.nan), "inside": np.zeros(n, bool), "kept": 0, "scale": []} for m in modes}
    t0 = time.perf_counter()
    for test in folds_of(n, k):
        role = np.array(["fit"] * n, dtype=object)
        role[test] = "check"
        session = bayescal.load(machine, replace(rec, role=tuple(role)), frame="fit")
        for mode in modes:
            cal = bayescal.calibrate(session, method="map", discrepancy=mode)
            rows = cal.result.extras["check"]["rows"]
            for i, r in zip(test, rows):
                if "error" not in r:
                    out[mode]["err"][i] = r["error_position_mm"]
                    out[mode]["inside"][i] = r["inside_90"]
            out[mode]["kept"] += int(cal.discrepancy is not None)
            out[mode]["scale"].append(cal.noise_scale * np.sqrt(cal.variance_factor))
    res = {"n_poses": n, "folds": k, "seconds": time.perf_counter() - t0}
    for mode, o in out.items():
        e = o["err"][np.isfinite(o["err"])]
        p = o["inside"][np.isfinite(o["err"])].astype(float)
        res[mode] = {"mean_error_mm": float(e.mean()), "rms_error_mm": float(np.sqrt(np.mean(e**2))),
                     "p95_error_mm": float(np.percentile(e, 95)),
                     "coverage_90": float(p.mean()), "coverage_se": float(np.sqrt(p.mean() * (1 - p.mean()) / p.size)),
                     "discrepancy_kept_folds": o["kept"], "sigma_factor_median": float(np.median(o["scale"]))}
    print(f"{name}: " + "; ".join(f"{m}: mean {res[m]['mean_error_mm']:.3f} mm, p95 {res[m]['p95_error_mm']:.3f}, "
                                  f"coverage {res[m]['coverage_90']:.2f} ± {res[m]['coverage_se']:.2f}, "
                                  f"kept {res[m]['discrepancy_kept_folds']}/{k}" for m in modes), flush=True)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 folds each, not written to studies/data")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--only", choices=("positioner", "tiago"), help="run one of the two (the other's results kept)")
    args = ap.parse_args(argv)
    import json

    results = json.loads(Path(args.out).read_text()) if args.only and Path(args.out).is_file() else {}
    pos_m = load_machine(ROOT / "examples" / "positioner" / "machine.toml")
    pos_r = read_recording(ROOT / "examples" / "positioner" / "recording.csv")
    if args.only in (None, "positioner"):
        results["positioner"] = run("positioner", pos_m, pos_r, 3 if args.quick else 10)
    if args.only in (None, "tiago"):
        tiago = ROOT / "examples" / "tiago"  # bundled (studies/convert_tiago.py); the CC BY-NC-ND URDF is not used
        m, r = load_machine(tiago / "machine.toml"), read_recording(tiago / "recording.csv")
        results["tiago"] = run("tiago", m, r, 3 if args.quick else r.n_poses)
    if not args.quick:
        write_json_atomic(args.out, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
