"""The exact-design search of studies/exact_design_gap.py: exchanges checked by brute force, gradients by differences."""

import json
import sys

import numpy as np
import pytest

from tests.studies.conftest import load_study


def _load():
    return load_study("exact_design_gap")


def test_full_exchange_is_a_local_optimum_by_brute_force():
    mod = _load()
    rng = np.random.default_rng(3)
    N, k, L = 40, 3, 7
    B = rng.normal(size=(N, k, L)) * rng.uniform(0.2, 2.0, size=(N, 1, 1))
    G = rng.normal(size=(L, L))
    Q = G @ G.T
    BB = np.einsum("nki,nkj->nij", B, B)
    start = rng.choice(N, 5, replace=True)
    S, f, _ = mod.full_exchange(B, BB, Q, start)
    # the value it reports is the design's, and no better than the start's
    assert np.isclose(f, mod.mse_of(BB, Q, S), rtol=1e-12)
    assert f <= mod.mse_of(BB, Q, start)
    # no single exchange (repeats allowed) lowers it: every (remove, add) pair computed directly
    for a in set(S.tolist()):
        for j in range(N):
            T = list(S)
            T[T.index(a)] = j
            assert mod.mse_of(BB, Q, T) >= f * (1 - 1e-10)


def test_continuous_gradient_matches_differences_of_the_objective():
    mod = _load()
    pp = sys.modules.get("pose_planning") or __import__("pose_planning")
    s = pp.build("prs3-6dof", dict(pp.QUICK, candidates={"prs3": 200, "arm6": 50}), 1)
    blk = mod.Blocks(s)
    # the blocks at candidate poses are the candidate set's
    assert np.allclose(blk(s.cands.q[:5]), s.B[:5], rtol=1e-9, atol=1e-12)
    lo, hi = blk.lim[:, 0], blk.lim[:, 1]
    q = lo + (hi - lo) * np.random.default_rng(0).uniform(0.2, 0.8, size=(4, lo.size))
    h = 1e-6 * (hi - lo)
    L = s.Q.shape[0]

    def f(qq):
        Jq = blk(qq)
        return float(np.trace(np.linalg.solve(np.eye(L) + np.einsum("nki,nkj->ij", Jq, Jq), s.Q)))

    f0, g = mod.mse_and_gradient(blk, s.Q, q, h)
    assert np.isclose(f0, f(q), rtol=1e-12)
    step = 1e-4 * (hi - lo)
    for i, a in [(0, 0), (2, 1), (3, 2)]:
        e = np.zeros_like(q)
        e[i, a] = step[a]
        fd = (f(q + e) - f(q - e)) / (2 * step[a])
        assert np.isclose(g[i, a], fd, rtol=1e-3, atol=1e-4 * abs(f(q)) / (hi - lo)[a]), (i, a, g[i, a], fd)


def test_decide_only_writes_its_answer_and_refuses_bad_specs(tmp_path, capsys):
    study = load_study("exact_design_gap")
    assert study.main(["--quick", "--decide", "prs3-6dof:8", "--nodes", "1", "--out", str(tmp_path)]) == 0
    (row,) = json.loads((tmp_path / "decide.json").read_text())["rows"]
    # one relaxation cannot close the question at 8 poses (the plan is 1.7 % above the relaxed bound)
    assert row["decision"]["below"] is None and row["decision"]["nodes"] == 1
    assert row["plan_ratio"] > 1.01
    assert "no answer after 1 relaxations" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="SETTING:N"):
        study.main(["--quick", "--decide", "prs3-6dof", "--out", str(tmp_path)])
