"""Study: calibration of the redundantly actuated 2T1R module (the seed's Figures 8 to 12).

    PYTHONPATH=. python studies/seed1_redundant_module.py [--quick] [--out DIR]

Regenerates from scratch, on a simulated module whose physics includes the
restrained deformation at the actuated joints: the procedure (pitch
compensation, zero position, RM1/SI1, BIC, RM2/SI2, RM3/SI3) and the
comparison with the previous (non-redundant) method; writes results.json,
the BIC grid, the relative recordings and PNG figures; checks the seed's
targets and prints which are met (exit status 1 if any is missed).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bayescal.compensation import write_grid  # noqa: E402
from bayescal.io import write_json_atomic  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402
from bayescal.redundant.physics import TrueModule  # noqa: E402
from bayescal.redundant.grid_std import predicted_grid  # noqa: E402
from bayescal.redundant.procedure import compare_methods, run_procedure  # noqa: E402
from bayescal.redundant.relative_io import write_relative_recording  # noqa: E402

#: One-sigma geometric errors of the simulated module (mm, rad): of the seed's size.
TRUE_TOLERANCE = {"platform_joint": 0.6, "rail_origin": 0.08, "rail_direction": 1.0e-4, "link_length": 0.6, "tool_point": 0.1}
#: A systematic error on top (mm): the platform joints of chains 1 and 2 sit this much lower than drawn.
#: It leaves the translation alone and makes the rotation-range orientation error of the seed's size.
PLATFORM_JOINT_DROP = 6.0
TARGETS = {"position_after_si1_mm": 0.075, "position_after_bic_mm": 0.014, "orientation_after_si2_deg": 0.005, "orientation_after_si3_deg": 0.007}


def make_truth(machine, seed: int) -> TrueModule:
    rng = np.random.default_rng(seed)
    tol = np.array([TRUE_TOLERANCE[s.group] for s in machine.layout])
    theta = rng.normal(size=machine.n_params) * tol
    theta[machine.layout.indices(["chain1.platform_joint.z", "chain2.platform_joint.z"])] += PLATFORM_JOINT_DROP
    return TrueModule(
        machine, theta,
        stiffness=np.array([2.0e4, 3.0e4, 5.0e4, 4.0e4]),  # N/mm, unequal: never given to the identification
        lead_error=rng.normal(size=4) * 2e-5, periodic_error=np.full(4, 0.003), straightness=rng.normal(size=4) * 0.02,
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer comparison steps (for the test suite)")
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "seed1_redundant_module"), help="output folder")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    machine = load_machine(ROOT / "examples" / "raspm" / "machine.toml")
    truth = make_truth(machine, args.seed)
    res = run_procedure(truth, np.random.default_rng(args.seed + 1))
    comp = compare_methods(truth, args.seed + 2, n_steps=3 if args.quick else 5)
    print(res.report())
    print(comp.report())
    p = {k: getattr(res, k).peaks for k in ("before", "after_si1", "after_bic", "after_si2", "after_si3")}
    got = {
        "position_after_si1_mm": p["after_si1"]["position_mm"],
        "position_after_bic_mm": p["after_bic"]["position_mm"],
        "orientation_after_si2_deg": p["after_si2"]["orientation_translation_deg"],
        "orientation_after_si3_deg": p["after_si3"]["orientation_rotation_deg"],
    }
    met = {k: got[k] <= TARGETS[k] for k in TARGETS}
    cp, cv = comp.steps_to_converge["proposed"], comp.steps_to_converge["previous"]
    met["proposed_converges_in_fewer_steps"] = (cp["position"] + cp["orientation"]) < (cv["position"] + cv["orientation"])
    for k, ok in met.items():
        print(f"target {k}: {'met' if ok else 'MISSED'}" + (f" ({got[k]:.4f} <= {TARGETS[k]})" if k in got else ""))
    write_json_atomic(out / "results.json", {"procedure": res.to_dict(), "comparison": comp.to_dict(), "targets": TARGETS, "achieved": got, "met": met})
    write_grid(out / "bic_grid.csv", res.grid)
    # the grid SI1's model predicts for the nominal controller, with each node's std (docs/redundant.md section 5)
    s1 = res.steps[0]
    pgrid = predicted_grid(res.controller, s1.theta_after, s1.covariance, theta_cmd=s1.theta_before)
    write_grid(out / "bic_grid_predicted.csv", pgrid)
    print(pgrid.report() + f"; node std max {np.nanmax(pgrid.std) * 1e3:.2f} um")
    for name, rec in res.recordings.items():
        write_relative_recording(out / f"{name.lower()}.csv", rec)
    from bayescal.plots.redundant import plot_comparison, plot_grid_std, plot_procedure

    plot_grid_std(pgrid, out / "bic_grid_std.png", title="BIC grid predicted from SI1: node std (linearised covariance)")

    plot_procedure(res, out)
    plot_comparison(comp, out)
    return 0 if all(met.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
