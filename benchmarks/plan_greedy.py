"""Benchmark: greedy pose selection with rank-k updates against naive recomputation; comparison scaling.

Part 1 (3-PRS, 6-DOF, 20,000 candidates, 40 poses, D criterion):

* rank-k: :func:`bayescal.design.greedy_select` (determinant lemma, one
  product with ``M^-1`` per candidate, vectorised over candidates), with
  lazy evaluation (default: stale gains are upper bounds because log det is
  submodular) and re-evaluating every candidate at every step;
* naive SVD: the criterion recomputed from the singular values of the
  stacked Jacobian of the selected poses plus the candidate, per
  candidate (what the definition says);
* naive factorisation: a fresh ``slogdet`` of ``M + B^T B`` per candidate
  (:func:`bayescal.design.brute_force_greedy`'s inner step);
* batched factorisation: the same fresh ``slogdet``, vectorised over all
  candidates with numpy (the strongest baseline).

The baselines are too slow to run in full (800,000 evaluations); they are
timed at five selection sizes (per-candidate ones on a subset of the
candidates, the batched one on all) and extrapolated to 20,000 candidates x
40 steps (stated in the output).

Part 1 measures CPU time (``time.process_time``) with one BLAS thread, so
that other users of a shared machine do not distort the ratios.

Part 2: wall time of a small ``compare_methods`` run against the number of
trials and the backend/workers, checking that every backend gives the same
table.  The machine this runs on is shared: read ratios, not absolute times.

    python benchmarks/plan_greedy.py [--quick] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bayescal.compare import compare_methods  # noqa: E402
from bayescal.design import draw_candidates, greedy_select, utility  # noqa: E402
from bayescal.design.plan import DELTA_REL  # noqa: E402
from bayescal.io import write_json_atomic  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402


def per_candidate_seconds(fn, n_cand: int, repeat: int = 1) -> float:
    t0 = time.process_time()
    for _ in range(repeat):
        for i in range(n_cand):
            fn(i)
    return (time.process_time() - t0) / (repeat * n_cand)


def part1(machine, n_cand: int, n_poses: int, subset: int) -> dict:
    rng = np.random.default_rng(0)
    t0 = time.process_time()
    cands = draw_candidates(machine, n_cand, dof=6, rng=rng)
    t_cands = time.process_time() - t0
    B = cands.blocks
    L = B.shape[2]
    M0 = DELTA_REL * float(np.mean(np.sum(B**2, axis=(1, 2)))) / L * np.eye(L)

    t0 = time.process_time()
    idx, _ = greedy_select(B, n_poses, "D", M0=M0, lazy=True)
    t_lazy = time.process_time() - t0
    t0 = time.process_time()
    idx_plain, _ = greedy_select(B, n_poses, "D", M0=M0, lazy=False)
    t_rank = time.process_time() - t0
    same = bool(np.array_equal(idx_plain, idx))

    # per-candidate baselines, timed at several selection sizes on a subset and extrapolated
    steps = sorted({0, n_poses // 4, n_poses // 2, 3 * n_poses // 4, n_poses - 1})
    svd_s, fac_s, bat_s = [], [], []
    for s in steps:
        A_sel = B[idx[:s]].reshape(-1, L)
        Ms = M0 + A_sel.T @ A_sel
        svd_s.append(per_candidate_seconds(
            lambda i: np.linalg.svd(np.vstack([A_sel, B[i]]), compute_uv=False), subset))
        fac_s.append(per_candidate_seconds(lambda i: np.linalg.slogdet(Ms + B[i].T @ B[i]), subset))
        t0 = time.process_time()
        utility("D", Ms[None] + np.swapaxes(B, 1, 2) @ B)  # fresh factorisation, vectorised over all candidates
        bat_s.append((time.process_time() - t0) / n_cand)
    # integrate the per-candidate cost over all steps (linear interpolation between timed steps)
    all_steps = np.arange(n_poses)
    t_svd = float(np.sum(np.interp(all_steps, steps, svd_s)) * n_cand)
    t_fac = float(np.sum(np.interp(all_steps, steps, fac_s)) * n_cand)
    t_batched = float(np.sum(np.interp(all_steps, steps, bat_s)) * n_cand)
    return {
        "candidates": cands.n, "poses": n_poses, "parameters": L, "dof": 6,
        "seconds_candidates_and_jacobians": t_cands,
        "seconds_rank_k_lazy": t_lazy,
        "seconds_rank_k_every_candidate": t_rank,
        "seconds_batched_fresh_slogdet_extrapolated": t_batched,
        "seconds_naive_svd_extrapolated": t_svd,
        "seconds_naive_slogdet_extrapolated": t_fac,
        "naive_timed_on": f"{subset} candidates (batched: all) at steps {steps}, extrapolated to {n_cand} x {n_poses}",
        "speedup_lazy_vs_naive_svd": t_svd / t_lazy,
        "speedup_lazy_vs_naive_slogdet": t_fac / t_lazy,
        "speedup_lazy_vs_batched_slogdet": t_batched / t_lazy,
        "speedup_every_candidate_vs_naive_svd": t_svd / t_rank,
        "speedup_every_candidate_vs_naive_slogdet": t_fac / t_rank,
        "speedup_every_candidate_vs_batched_slogdet": t_batched / t_rank,
        "lazy_and_every_candidate_select_same_poses": same,
    }


def part2(machine, trials_list, quick: bool) -> list[dict]:
    rows = []
    ref = None
    kw = dict(methods="ls,ridge,tsvd", dof=6, n_poses=18, n_eval=30, seed=0, progress=False)
    T = max(trials_list)
    backends = [("in-process", {}), ("processes", {"workers": 2}), ("dask", {"dask_workers": 2})]
    for t in trials_list:
        t0 = time.perf_counter()
        c = compare_methods(machine, trials=t, **kw)
        rows.append({"backend": "in-process", "workers": 1, "trials": t, "seconds": time.perf_counter() - t0})
        if t == T:
            ref = json.dumps(c.table(), default=str)
    for name, opts in backends[1:]:
        t0 = time.perf_counter()
        c = compare_methods(machine, trials=T, **kw, **opts)
        rows.append({"backend": name, "workers": 2, "trials": T, "seconds": time.perf_counter() - t0,
                     "same_table_as_in_process": json.dumps(c.table(), default=str) == ref})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out"))
    args = ap.parse_args(argv)
    machine = load_machine(ROOT / "examples" / "prs3" / "machine.toml")
    from threadpoolctl import threadpool_limits

    # part 1 counts CPU time of one BLAS thread: on a shared machine wall time measures the neighbours
    with threadpool_limits(limits=1, user_api="blas"):
        p1 = part1(machine, 2000, 20, 100) if args.quick else part1(machine, 20000, 40, 400)
    if args.quick:
        p2 = part2(machine, [2, 4], True)
    else:
        p2 = part2(machine, [4, 8, 16], False)
    print("greedy selection, D criterion, 3-PRS 6-DOF (CPU seconds, one BLAS thread):")
    for k, v in p1.items():
        print(f"  {k:<40} {v:.4g}" if isinstance(v, float) else f"  {k:<40} {v}")
    print("\ncomparison wall time (ls,ridge,tsvd; 18 poses; 2-core shared machine):")
    for r in p2:
        same = f"  same table: {r['same_table_as_in_process']}" if "same_table_as_in_process" in r else ""
        print(f"  {r['backend']:<12} workers {r['workers']}  trials {r['trials']:>3}  {r['seconds']:7.2f} s "
              f"({r['seconds'] / r['trials']:.3f} s/trial){same}")
    write_json_atomic(Path(args.out) / ("plan_greedy_quick.json" if args.quick else "plan_greedy.json"),
                      {"greedy": p1, "compare": p2})
    return 0


if __name__ == "__main__":
    sys.exit(main())
