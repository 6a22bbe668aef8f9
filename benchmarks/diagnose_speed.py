"""Benchmark: diagnosis of one 160-pose recording (target: under a minute on 2 cores).

Baseline in the same run: one geometric identification (ridge, lam = 1) of
the same recording; the ratio says what the diagnosis costs in
identifications (it runs about 30 joint fits for cross-validation).

Run: python benchmarks/diagnose_speed.py [--dof 6] [--repeat 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small matrices: threads only spin on a shared machine
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    from bayescal.diagnose import diagnose
    from bayescal.effects.simulate import simulate_with_effects
    from bayescal.identify import identify
    from bayescal.machines import load_machine
    from bayescal.measurement import MeasurementModel

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--dof", type=int, default=6, choices=(6, 5, 3))
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    machine = load_machine(Path(__file__).resolve().parents[1] / "examples" / "prs3" / "machine.toml")
    sim = simulate_with_effects(machine, 160, seed=1, dof=args.dof, effects=[("backlash", 20.0)],
                                record=("time_s", "temp_C", "payload_kg"))
    model = MeasurementModel.from_recording(machine, sim.recording)
    t_id, t_dg = [], []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        identify(model, method="ridge", lam=1.0, free="all")
        t_id.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        d = diagnose(machine, sim.recording)
        t_dg.append(time.perf_counter() - t0)
    best_id, best_dg = min(t_id), min(t_dg)
    print(f"160 poses, {args.dof}-DOF, aux time_s/temp_C/payload_kg, verdict {d.verdict}")
    print(f"identify (ridge, baseline): {best_id:.2f} s")
    print(f"diagnose:                   {best_dg:.2f} s  ({best_dg / best_id:.0f} x the baseline; target < 60 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
