"""Benchmark: bayescal's MCMC against NumPyro's NUTS on the same posterior (the real positioner, the 3-PRS example).

Two problems (``--problems``, one after the other):

* ``positioner``: what ``bayescal identify --method mcmc --frame fit``
  samples on ``examples/positioner`` (205 real poses, 6-DOF, the instrument
  frame fitted, ``free = auto``: 30 parameters, 16 of them decided by the
  prior);
* ``prs3``: what ``bayescal identify --method mcmc`` samples on the bundled
  3-PRS recording ``examples/prs3`` (36 poses, 6-DOF, base frame, ``free =
  auto``: all 36 parameters); its forward kinematics is implicit (Newton on
  six constraints), see :mod:`numpyro_prs3`.

Each posterior is the exact-kinematics likelihood with the instrument's
sigmas, under the machine file's tolerance prior, the other parameters held
at the MAP.

NumPyro needs the model in ``jax.numpy``.  Positioner: the serial chain
(URDF joint semantics, tilted axes, zero offsets, rpy, tool), the fitted
frame and the 6-DOF rows (tool point, ``log(R R_ref^T)``) are written out
below from the arrays bayescal exports.  3-PRS: the geometry as
``Prs3._geometry`` maps theta, Newton on the constraints under
``jax.lax.while_loop`` and the implicit-function theorem as its derivative
(a ``jax.custom_jvp``), in ``numpyro_prs3.py``.  Both are checked against
bayescal's ``MeasurementModel.predict`` at the MAP and at random draws
(3-PRS: also draws from the prior): the largest row difference must be
below 1e-9 (mm, rad), and JAX's reverse-mode Jacobian of the rows must agree
with bayescal's analytic ``MeasurementModel.jacobian`` to 1e-6 of each
column's largest entry, or the script stops.

Contestants (``--repeats`` rounds, interleaved, each in its own process,
end to end: set-up, JIT compilation, warm-up and sampling all counted;
imports not):

* bayescal ``sample_posterior`` with its defaults (the command's sampler),
  or with ``--bayescal-ess N`` until its bulk and tail ESS reach N
  (``identify --ess N``), for comparisons at equal effective sample size;
* NumPyro NUTS with its defaults (diagonal mass matrix adapted in warm-up,
  ``--default-warmup`` / ``--default-samples`` per chain, ``--nuts-chains``
  chains one after the other, started at the MAP);
* NumPyro NUTS whitened by bayescal's Laplace covariance: sampled in
  ``z`` with ``theta = MAP + L z`` (``L L^T`` the MAP's covariance), step
  size adapted, no mass-matrix adaptation (``--nuts-warmup`` /
  ``--nuts-samples``); with ``--long-samples N`` also a longer run of it
  (``nuts-whitened-long``: N draws kept per chain), which spreads its fixed
  cost (compilation, warm-up) over more draws.

Figures: the smallest bulk ESS over the parameters (arviz, chains or
walkers as chains), ESS per second, R-hat, peak memory; the posterior
means and standard deviations compared with bayescal's (difference in
units of the Monte Carlo error).  The bayescal process runs in this
project's environment; NumPyro runs in ``--bench-python`` (the ``bench``
extra: ``pip install numpyro jax``).

Run::

    python benchmarks/peers_numpyro.py --repeats 3
    python benchmarks/peers_numpyro.py --problems prs3 --repeats 3 --long-samples 2500
    python benchmarks/peers_numpyro.py --problems prs3 --repeats 2 --bayescal-ess 4000 --nuts-samples 1200 --skip-default
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out" / "peers_numpyro"
sys.path.insert(0, str(Path(__file__).resolve().parent))
from peer_child import run_child

# the positioner's arrays, MAP, covariance and test points with bayescal's rows
POSITIONER_EXPORT = r'''
import json, sys, time, numpy as np
a = json.loads(sys.argv[1])
sys.path.insert(0, a["root"])
from bayescal.bayes.priors import map_estimate, prior_from_machine
from bayescal.instrument import prepare_model
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
ex = a["root"] + "/examples/positioner/"
t0 = time.perf_counter()
m2, model, _ = prepare_model(load_machine(ex + "machine.toml"), read_recording(ex + "recording.csv"), frame="fit")
res = map_estimate(model, free="auto")
map_seconds = time.perf_counter() - t0
idx = np.flatnonzero(res.free)
s = m2.machine
prior = prior_from_machine(m2)
rng = np.random.default_rng(0)
tests = res.theta[None].repeat(6, 0)
tests[1:, idx] += rng.multivariate_normal(np.zeros(idx.size), res.covariance, 5) * 3.0
ys = np.stack([model.predict(t).y for t in tests])
np.savez(a["out"], q=model.q, y=model.y_measured, sig=model.row_sigma, R_ref=model.R_ref,
         o0=m2._o0[0], R0=m2._R0[0], origin=s.origin, rpy=s.rpy, axis=s.axis, tilt=np.array(s._tilt),
         q_map=s._q_map, q_shift=s._q_shift, revolute=np.array([t == "revolute" for t in s.joint_type]),
         tool_point=s.tool_point, tool_rpy=s.tool_rpy, idx=idx, theta_map=res.theta, cov=res.covariance,
         prior_mean=prior.mean, prior_std=prior.std, tests=tests, ys=ys,
         jac=model.jacobian(tests[1], model.predict(tests[1])))   # bayescal's analytic Jacobian, 3 sds out
print("RESULT " + json.dumps({"n_free": int(idx.size), "n_params": int(res.theta.size), "map_seconds": map_seconds}))
'''

BAYESCAL = r'''
import json, sys, time, resource, numpy as np
a = json.loads(sys.argv[1])
sys.path.insert(0, a["root"])
t0 = time.perf_counter()
from bayescal.bayes.mcmc import sample_posterior
from bayescal.instrument import prepare_model
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
ex = a["root"] + "/examples/" + a["example"] + "/"
t1 = time.perf_counter()
m2, model, _ = prepare_model(load_machine(ex + "machine.toml"), read_recording(ex + "recording.csv"), frame=a["frame"])
r = sample_posterior(model, free="auto", seed=a["seed"], ess=a["ess"])
t = time.perf_counter() - t1
chain = r.tree["posterior"]["theta"].values  # (walkers, draws, n)
np.save(a["draws"], chain)
print("RESULT " + json.dumps({"seconds": t, "import_seconds": t1 - t0, "success": bool(r.success),
      "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
'''

# NumPyro's process: header (imports, data, SO(3) helpers), then a problem's MODEL (predict), then NUMPYRO_TAIL
NUMPYRO_HEAD = r'''
import json, sys, time, resource
a = json.loads(sys.argv[1])
t0 = time.perf_counter()
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpyro
from numpyro.infer import MCMC, NUTS
t1 = time.perf_counter()
d = dict(np.load(a["data"]))
idx, theta_map = d["idx"], jnp.asarray(d["theta_map"])

def skew(w):
    z = jnp.zeros_like(w[..., 0])
    return jnp.stack([jnp.stack([z, -w[..., 2], w[..., 1]], -1), jnp.stack([w[..., 2], z, -w[..., 0]], -1),
                      jnp.stack([-w[..., 1], w[..., 0], z], -1)], -2)

def so3_exp(w):
    th = jnp.linalg.norm(w, axis=-1)[..., None, None]
    small = th < 1e-8
    ts = jnp.where(small, 1.0, th)
    A = jnp.where(small, 1.0 - th**2 / 6.0, jnp.sin(ts) / ts)
    B = jnp.where(small, 0.5 - th**2 / 24.0, (1.0 - jnp.cos(ts)) / ts**2)
    K = skew(w)
    return jnp.eye(3) + A * K + B * (K @ K)

def so3_log(R):  # small rotations only (the rows are relative to the measured orientation)
    tr = jnp.clip((jnp.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    th = jnp.arccos(tr)
    v = jnp.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    small = th < 1e-6
    ts = jnp.where(small, 1.0, th)
    return jnp.where(small, 0.5 + th**2 / 12.0, ts / (2.0 * jnp.sin(ts)))[..., None] * v

'''

# the positioner's serial chain, the fitted frame and the 6-DOF rows
POSITIONER_MODEL = r'''
q, y, sig, R_ref = (jnp.asarray(d[k]) for k in ("q", "y", "sig", "R_ref"))
m = d["origin"].shape[0]
E = np.eye(3)
G = [np.stack([np.cross(E[d["tilt"][k][0]], d["axis"][k]), np.cross(E[d["tilt"][k][1]], d["axis"][k])], -1) for k in range(m)]

def rpy_matrix(rpy):
    cr, sr = jnp.cos(rpy[..., 0]), jnp.sin(rpy[..., 0])
    cp, sp = jnp.cos(rpy[..., 1]), jnp.sin(rpy[..., 1])
    cy, sy = jnp.cos(rpy[..., 2]), jnp.sin(rpy[..., 2])
    return jnp.stack([jnp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
                      jnp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
                      jnp.stack([-sp, cp * sr, cp * cr], -1)], -2)

def predict(theta):
    """bayescal's InstrumentFrame(Serial) rows, theta (P,): frame (6), 9 per joint, tool (6)."""
    tf, th = theta[:6], theta[6:]
    qe = q @ jnp.asarray(d["q_map"]).T + jnp.asarray(d["q_shift"])
    R = jnp.broadcast_to(jnp.eye(3), (q.shape[0], 3, 3))
    p = jnp.zeros((q.shape[0], 3))
    for k in range(m):
        t = th[9 * k: 9 * k + 9]
        n = jnp.asarray(d["axis"][k]) + jnp.asarray(G[k]) @ t[1:3]
        ax = n / jnp.linalg.norm(n)
        p = p + R @ (jnp.asarray(d["origin"][k]) + t[3:6])
        R = R @ rpy_matrix(jnp.asarray(d["rpy"][k]) + t[6:9])
        if d["revolute"][k]:
            R = R @ so3_exp(ax[None, :] * (qe[:, k] + t[0])[:, None])
        else:
            p = p + jnp.einsum("nij,nj->ni", R, ax[None, :] * (qe[:, k] + t[0])[:, None])
    tt = th[9 * m:]
    p_tool = p + jnp.einsum("nij,j->ni", R, jnp.asarray(d["tool_point"]) + tt[:3])
    R_tool = R @ rpy_matrix(jnp.asarray(d["tool_rpy"]) + tt[3:])
    o = jnp.asarray(d["o0"]) + tf[:3]
    Rf = so3_exp(tf[3:]) @ jnp.asarray(d["R0"])
    p_inst = (p_tool - o) @ Rf        # R^T (p - o), row-wise
    R_inst = Rf.T @ R_tool
    rows = jnp.concatenate([p_inst, so3_log(R_inst @ jnp.swapaxes(R_ref, -1, -2))], axis=1)
    return rows, jnp.bool_(True)
'''

# shared by the problems: the log posterior, the check against bayescal's rows, the sampling
NUMPYRO_TAIL = r'''
pm, ps = jnp.asarray(d["prior_mean"][idx]), jnp.asarray(d["prior_std"][idx])
def log_post(x):
    theta = theta_map.at[idx].set(x)
    rows, ok = predict(theta)
    r = (rows - y) / sig
    lp = -0.5 * jnp.sum(r**2) - 0.5 * jnp.sum(((x - pm) / ps) ** 2)
    return jnp.where(ok, lp, -jnp.inf)   # a pose that does not solve: zero density, as in bayescal

pred = jax.jit(predict)
outs = [pred(jnp.asarray(t)) for t in d["tests"]]
check = max(float(jnp.max(jnp.abs(o[0] - yb))) if bool(o[1]) else float("inf") for o, yb in zip(outs, d["ys"]))
if a["mode"] == "check":
    # the gradient NUTS follows: JAX's reverse-mode Jacobian of the rows against bayescal's analytic one
    J = np.asarray(jax.jit(jax.jacrev(lambda th: predict(th)[0]))(jnp.asarray(d["tests"][1])))
    jac = float(np.max(np.abs(J - d["jac"]) / np.abs(d["jac"]).max(axis=(0, 1), keepdims=True)))
    print("RESULT " + json.dumps({"max_row_difference": check, "max_jacobian_difference": jac}))
    sys.exit(0)
if not check < 1e-9:
    raise SystemExit(f"the jax model differs from bayescal's predict by {check:.3g}")
x_map = jnp.asarray(d["theta_map"][idx])
t2 = time.perf_counter()
if a["mode"] == "whitened":
    L = jnp.asarray(np.linalg.cholesky(d["cov"]))
    kernel = NUTS(potential_fn=lambda z: -log_post(x_map + L @ z), adapt_mass_matrix=False)
    init = jnp.zeros(len(idx))
else:
    kernel = NUTS(potential_fn=lambda x: -log_post(x))
    init = x_map
mc = MCMC(kernel, num_warmup=a["warmup"], num_samples=a["samples"], num_chains=a["chains"],
          chain_method="sequential", progress_bar=False)
mc.run(jax.random.PRNGKey(a["seed"]), init_params=jnp.tile(init, (a["chains"], 1)) if a["chains"] > 1 else init,
       extra_fields=("num_steps",))
z = np.asarray(mc.get_samples(group_by_chain=True))  # (chains, draws, n)
x = np.asarray(x_map) + z @ np.asarray(L).T if a["mode"] == "whitened" else z
t = time.perf_counter() - t2
extra = mc.get_extra_fields(group_by_chain=True)
depth = float(np.mean(np.asarray(extra["num_steps"]) >= 2**10 - 1)) if "num_steps" in extra else float("nan")
np.save(a["draws"], x)
print("RESULT " + json.dumps({"seconds": t, "import_seconds": t1 - t0, "max_row_difference": check,
      "tree_depth_saturated": depth, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
'''


def _child(python: str, code: str, args: dict) -> dict:
    return run_child(python, code, args, {"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false", "PYTHONPATH": str(ROOT)})


def _ess(draws):
    """Smallest bulk ESS over the parameters and largest R-hat (arviz; chains or walkers as chains)."""
    import arviz as az
    import numpy as np

    ds = az.convert_to_dataset({"x": np.asarray(draws)})
    ess = az.ess(ds, method="bulk")["x"].values
    rhat = az.rhat(ds)["x"].values
    return float(np.min(ess)), float(np.max(rhat))


def _problems() -> dict:
    """Per problem: export code, JAX model code, the example directory, the frame, a title."""
    import numpyro_prs3

    return {
        "positioner": {"export": POSITIONER_EXPORT, "model": POSITIONER_MODEL, "example": "positioner", "frame": "fit",
                       "title": "the real positioner"},
        "prs3": {"export": numpyro_prs3.EXPORT, "model": numpyro_prs3.MODEL, "example": "prs3", "frame": "base",
                 "title": "the 3-PRS example recording (examples/prs3, 36 poses, 6-DOF)"},
    }


def _contestant(who: str, r: int, prob: dict, data: Path, args) -> dict:
    """One end-to-end run of ``who`` in round ``r``: its result with ESS, R-hat, means and standard deviations."""
    import numpy as np

    draws = args.out / f"{prob['name']}_{who}_{r}.npy"
    if who == "bayescal":
        res = _child(sys.executable, BAYESCAL, {"root": str(ROOT), "seed": r, "draws": str(draws),
                                                "example": prob["example"], "frame": prob["frame"],
                                                "ess": args.bayescal_ess})
    else:
        whitened = who.startswith("nuts-whitened")
        samples = {"nuts": args.default_samples, "nuts-whitened": args.nuts_samples,
                   "nuts-whitened-long": args.long_samples}[who]
        res = _child(args.bench_python, NUMPYRO_HEAD + prob["model"] + NUMPYRO_TAIL, {
            "data": str(data), "mode": "whitened" if whitened else "default", "seed": r,
            "draws": str(draws), "chains": args.nuts_chains,
            "warmup": args.nuts_warmup if whitened else args.default_warmup, "samples": samples})
    x = np.load(draws)
    res["ess"], res["rhat"] = _ess(x)
    x = x.reshape(-1, x.shape[-1])
    res["mean"], res["std"] = x.mean(0).tolist(), x.std(0).tolist()
    return res


def _table(prob: dict, info: dict, chk: dict, runs: dict, load0: float, args) -> str:
    """The markdown table of one problem: medians and ranges over the rounds, the posteriors against bayescal's."""
    import numpy as np

    def rng(v, f):
        return f"{statistics.median(v):{f}} ({min(v):{f}}-{max(v):{f}})"

    long = f" (long: {args.nuts_warmup} + {args.long_samples})" if args.long_samples > 0 else ""
    head = (f"MCMC on {prob['title']} ({info['n_free']} parameters), {args.repeats} interleaved rounds, load "
            f"{load0:.2f} at start, {os.getloadavg()[0]:.2f} at end; end to end (set-up, compilation, warm-up, sampling)")
    mine = ("bayescal: its default 1,000 steps" if args.bayescal_ess is None else
            f"bayescal: until bulk and tail ESS >= {args.bayescal_ess:g} (`--ess`)")
    nuts = (f"{mine}; NUTS: {args.nuts_chains} chains one after the other; default {args.default_warmup} warm-up + "
            f"{args.default_samples} draws per chain, whitened {args.nuts_warmup} + {args.nuts_samples}{long}; jax model "
            f"against bayescal's predict: largest row difference {chk['max_row_difference']:.1e}, Jacobian "
            f"{chk['max_jacobian_difference']:.1e}; bayescal's MAP and Laplace covariance (given to whitened NUTS, "
            f"not in its time) took {info['map_seconds']:.2f} s")
    columns = ("| sampler | seconds median (range) | min bulk ESS median (range) | ESS/s median (range) | max R-hat "
               "(worst run) | peak [MB] | means vs bayescal [MC sd] | stds ratio to bayescal | tree depth saturated | "
               "ratio (bayescal ESS/s over this) |")
    lines = [head, nuts, "", columns, "|---|---|---|---|---|---|---|---|---|---|"]
    eps_b = statistics.median(x["ess"] / x["seconds"] for x in runs["bayescal"])
    ref = runs["bayescal"][-1]
    for who, rs in runs.items():
        eps = [x["ess"] / x["seconds"] for x in rs]
        # the last round against bayescal's last round; Monte Carlo error of the difference from both ESS
        last = rs[-1]
        m1, s1 = np.asarray(last["mean"]), np.asarray(last["std"])
        m0, s0 = np.asarray(ref["mean"]), np.asarray(ref["std"])
        z = float(np.max(np.abs(m1 - m0) / np.sqrt(s0**2 / ref["ess"] + s1**2 / max(last["ess"], 1.0))))
        depth = (f"{100 * max(x['tree_depth_saturated'] for x in rs):.0f}% of draws"
                 if "tree_depth_saturated" in last else "-")
        lines.append(f"| {who} | {rng([x['seconds'] for x in rs], '.1f')} | {rng([x['ess'] for x in rs], '.0f')} | "
                     f"{rng(eps, '.1f')} | {max(x['rhat'] for x in rs):.3f} | {max(x['peak_mb'] for x in rs):.0f} | "
                     f"{z:.1f} | {float(np.median(s1 / s0)):.3f} | {depth} | "
                     f"{eps_b / max(statistics.median(eps), 1e-300):.1f}x |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bench-python", default=str(ROOT / ".venv-bench" / "bin" / "python"),
                    help="the python of the environment with numpyro and jax (default .venv-bench/bin/python)")
    ap.add_argument("--problems", default="positioner,prs3",
                    help="comma-separated: positioner, prs3 (default both, one after the other)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--nuts-chains", type=int, default=2, help="NUTS chains, run one after the other (default 2)")
    ap.add_argument("--nuts-warmup", type=int, default=500, help="whitened NUTS: warm-up draws per chain (default 500)")
    ap.add_argument("--nuts-samples", type=int, default=500, help="whitened NUTS: draws kept per chain (default 500)")
    ap.add_argument("--default-warmup", type=int, default=150,
                    help="default NUTS: warm-up draws per chain (default 150: it saturates its tree depth, 1,023 "
                         "gradient evaluations per draw, so longer runs cost minutes and do not converge either)")
    ap.add_argument("--default-samples", type=int, default=150, help="default NUTS: draws kept per chain (default 150)")
    ap.add_argument("--long-samples", type=int, default=0,
                    help="also run whitened NUTS keeping this many draws per chain (contestant nuts-whitened-long: "
                         "its compilation and warm-up spread over more draws; default 0, not run)")
    ap.add_argument("--bayescal-ess", type=float, default=None, metavar="N",
                    help="bayescal stops at bulk and tail ESS N (sample_posterior(ess=N), `identify --ess N`); "
                         "default: its 1,000 steps")
    ap.add_argument("--skip-default", action="store_true",
                    help="do not run NUTS with its defaults (it saturates its tree depth: minutes for no posterior)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    problems = _problems()
    names = [n.strip() for n in args.problems.split(",") if n.strip()]
    unknown = [n for n in names if n not in problems]
    if unknown or not names:
        ap.error(f"--problems: expected names among {', '.join(problems)}, got {args.problems!r}")
    args.out.mkdir(parents=True, exist_ok=True)
    tables = []
    for name in names:
        prob = {**problems[name], "name": name}
        data = args.out / f"{name}.npz"
        info = _child(sys.executable, prob["export"], {"root": str(ROOT), "out": str(data)})
        chk = _child(args.bench_python, NUMPYRO_HEAD + prob["model"] + NUMPYRO_TAIL, {"data": str(data), "mode": "check"})
        print(f"{name} posterior: {info['n_free']} parameters sampled; jax model against bayescal's predict: "
              f"largest row difference {chk['max_row_difference']:.2e} (must be < 1e-9), Jacobian "
              f"{chk['max_jacobian_difference']:.2e} of each column's largest entry (must be < 1e-6)", flush=True)
        if not (chk["max_row_difference"] < 1e-9 and chk["max_jacobian_difference"] < 1e-6):
            raise SystemExit(f"{name}: the jax model differs from bayescal's predict by {chk['max_row_difference']:.3g} "
                             f"(rows) and {chk['max_jacobian_difference']:.3g} (Jacobian)")
        todo = (["bayescal"] + ([] if args.skip_default else ["nuts"]) + ["nuts-whitened"]
                + (["nuts-whitened-long"] if args.long_samples > 0 else []))
        runs = {k: [] for k in todo}
        load0 = os.getloadavg()[0]
        for r in range(args.repeats):
            k = r % len(todo)
            for who in todo[k:] + todo[:k]:
                runs[who].append(_contestant(who, r, prob, data, args))
                print(f"  round {r + 1}, {who}: {runs[who][-1]['seconds']:.1f} s, min bulk ESS "
                      f"{runs[who][-1]['ess']:.0f}", flush=True)
        tables.append(_table(prob, info, chk, runs, load0, args))
        print(tables[-1], flush=True)
        (args.out / f"table_{name}.md").write_text(tables[-1] + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
