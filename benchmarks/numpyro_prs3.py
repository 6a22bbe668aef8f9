"""The 3-PRS problem of ``peers_numpyro.py``: its export (bayescal side) and its model in ``jax.numpy`` (NumPyro side).

The posterior is what ``bayescal identify --method mcmc`` samples on the
bundled ``examples/prs3`` recording (36 poses, 6-DOF, base frame, ``free =
auto``: all 36 parameters; the command's noise check keeps the stated
sigmas and its robust pass flags no pose, so it runs
``sample_posterior(model, free="auto")``).

The JAX model repeats :class:`bayescal.machines.prs3.Prs3` from the arrays
exported here: the geometry from ``theta`` as ``Prs3._geometry`` maps it
(sphere centres and rail origins plus their errors, rail and revolute
directions tilted by :func:`bayescal.geometry.tilted_direction`, link lengths,
tool point), the six constraints ``F1_i = (|d_i|^2 - l_i^2) / 2``,
``F2_i = d_i . r_i`` with ``d_i = p + R a_i - B_i - q_i u_i`` and their
derivative in ``(dp, dw)`` (``R <- exp([dw]x) R``) as ``Prs3._constraints``
writes them, and Newton from the measured pose (``Prs3.guess_from_measurement``,
what ``MeasurementModel.predict`` starts from) with ``Prs3._solve``'s step cap,
tolerance and final polishing step, under ``jax.lax.while_loop``.  The
solver's derivative is the implicit-function theorem's (a
``jax.custom_jvp``: ``dx = -F_x^{-1} F_theta dtheta``), so gradients never
differentiate through the Newton loop.  A pose whose Newton does not reach
the tolerance makes the log density ``-inf``, as bayescal's does.
"""

from __future__ import annotations

#: bayescal side: the model's arrays, the MAP and its covariance, and test points with bayescal's rows.
EXPORT = r'''
import json, sys, time, numpy as np
a = json.loads(sys.argv[1])
sys.path.insert(0, a["root"])
from bayescal.bayes.priors import map_estimate, prior_from_machine
from bayescal.instrument import prepare_model
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
ex = a["root"] + "/examples/prs3/"
t0 = time.perf_counter()
m, model, _ = prepare_model(load_machine(ex + "machine.toml"), read_recording(ex + "recording.csv"), frame="base")
assert type(m).__name__ == "Prs3" and model.pose_offset is None and model.sensors is None and model.dof == 6
res = map_estimate(model, free="auto")
map_seconds = time.perf_counter() - t0
idx = np.flatnonzero(res.free)
prior = prior_from_machine(m)
rng = np.random.default_rng(0)
tests = res.theta[None].repeat(11, 0)
tests[1:6, idx] += rng.multivariate_normal(np.zeros(idx.size), res.covariance, 5) * 3.0   # 3 Laplace sds out
tests[6:] = prior.sample(5, rng)                                                          # draws from the prior
preds = [model.predict(t) for t in tests]
assert all(p.success.all() for p in preds), "bayescal cannot solve a test point"
ys = np.stack([p.y for p in preds])
E = np.eye(3)
tilt_basis = lambda dirs, axes: np.array([np.stack([np.cross(E[ax[0]], v), np.cross(E[ax[1]], v)], -1)
                                          for v, ax in zip(dirs, axes)])   # (chain, 3, 2): e_a x u0, e_b x u0
st = model.guess.state
np.savez(a["out"], q=model.q, y=model.y_measured, sig=model.row_sigma, R_ref=model.R_ref, p0=st.p, R0=st.R,
         sphere_center=m.sphere_center, rail_origin=m.rail_origin, rail_direction=m.rail_direction,
         revolute_axis=m.revolute_axis, link_length=m.link_length, tool_point=m.tool_point,
         Gu=tilt_basis(m.rail_direction, m._axes_u), Gr=tilt_basis(m.revolute_axis, m._axes_r),
         idx=idx, theta_map=res.theta, cov=res.covariance,
         prior_mean=prior.mean, prior_std=prior.std, tests=tests, ys=ys,
         jac=model.jacobian(tests[1], model.predict(tests[1])))   # bayescal's analytic Jacobian, 3 sds out
print("RESULT " + json.dumps({"n_free": int(idx.size), "n_params": int(res.theta.size), "map_seconds": map_seconds}))
'''

#: NumPyro side: ``predict(theta) -> (rows (n, 6), ok)``, run after the shared header (jnp, d, skew, so3_exp, so3_log).
MODEL = r'''
q, y, sig, R_ref = (jnp.asarray(d[k]) for k in ("q", "y", "sig", "R_ref"))
p_start, R_start = jnp.asarray(d["p0"]), jnp.asarray(d["R0"])   # bayescal's start: the measured poses
sc, ro, rd, ra = (jnp.asarray(d[k]) for k in ("sphere_center", "rail_origin", "rail_direction", "revolute_axis"))
ll, tp, Gu, Gr = (jnp.asarray(d[k]) for k in ("link_length", "tool_point", "Gu", "Gr"))
NEWTON_TOL, NEWTON_MAXIT = 1e-9, 60   # bayescal.machines.prs3's

def geometry(theta):
    """Prs3._geometry: theta (36,) -> sphere centres a, rail origins B, rail dirs u, revolute axes r, lengths l, tool t."""
    th = theta[:33].reshape(3, 11)
    nu = rd + jnp.einsum("kij,kj->ki", Gu, th[:, 6:8])
    nr = ra + jnp.einsum("kij,kj->ki", Gr, th[:, 8:10])
    return (sc + th[:, 0:3], ro + th[:, 3:6], nu / jnp.linalg.norm(nu, axis=1, keepdims=True),
            nr / jnp.linalg.norm(nr, axis=1, keepdims=True), ll + th[:, 10], tp + theta[33:])

def constraints(p, R, g):
    """Prs3._constraints: F (n, 6) (rows F1_1, F2_1, F1_2, ...) and F_x (n, 6, 6) in (dp, dw)."""
    a, B, u, r, l, _ = g
    Ra = jnp.einsum("nij,kj->nki", R, a)
    dd = p[:, None, :] + Ra - B[None] - q[:, :, None] * u[None]
    F = jnp.stack([0.5 * (jnp.sum(dd * dd, -1) - l**2), jnp.sum(dd * r[None], -1)], -1).reshape(-1, 6)
    rr = jnp.broadcast_to(r[None], dd.shape)
    Fx = jnp.stack([jnp.concatenate([dd, jnp.cross(Ra, dd)], -1),
                    jnp.concatenate([rr, jnp.cross(Ra, rr)], -1)], 2).reshape(-1, 6, 6)
    return F, Fx

def newton_error(F, l):
    return jnp.max(jnp.maximum(jnp.abs(F[:, 0::2]) / jnp.maximum(l, 1.0), jnp.abs(F[:, 1::2])), axis=1)

@jax.custom_jvp
def platform(theta):
    """Platform poses (p (n, 3), R (n, 3, 3)) and the largest constraint error after the polishing step."""
    g = geometry(theta)
    scale = jnp.maximum(g[4], 1.0)

    def step(c):
        p, R, F, Fx, it = c
        dx = -jnp.linalg.solve(Fx, F[..., None])[..., 0]
        s = jnp.linalg.norm(dx[:, :3], axis=1) / jnp.mean(scale) + jnp.linalg.norm(dx[:, 3:], axis=1)
        dx = dx * jnp.minimum(1.0, 0.2 / jnp.maximum(s, 1e-300))[:, None]   # bayescal's step cap
        p, R = p + dx[:, :3], so3_exp(dx[:, 3:]) @ R
        return (p, R, *constraints(p, R, g), it + 1)

    def cond(c):
        return (c[4] < NEWTON_MAXIT) & (jnp.max(newton_error(c[2], g[4])) >= NEWTON_TOL)

    c = jax.lax.while_loop(cond, step, (p_start, R_start, *constraints(p_start, R_start, g), 0))
    p, R, F, _, _ = step(c)   # one more step below the tolerance polishes to round-off, as bayescal does
    return p, R, jnp.max(newton_error(F, g[4]))

@platform.defjvp
def platform_jvp(primals, tangents):
    """Implicit-function theorem: F(x(theta), theta) = 0 gives dx = -F_x^{-1} F_theta dtheta, x = (p, w)."""
    (theta,), (dtheta,) = primals, tangents
    p, R, err = platform(theta)
    _, Fx = constraints(p, R, geometry(theta))
    Ft = jax.jvp(lambda th: constraints(p, R, geometry(th))[0], (theta,), (dtheta,))[1]
    dx = -jnp.linalg.solve(Fx, Ft[..., None])[..., 0]
    return (p, R, err), (dx[:, :3], skew(dx[:, 3:]) @ R, jnp.zeros_like(err))

def predict(theta):
    """MeasurementModel.predict's rows (tool point mm, log(R R_ref^T) rad) and whether every pose solved."""
    p, R, err = platform(theta)
    t = geometry(theta)[5]
    rows = jnp.concatenate([p + R @ t, so3_log(R @ jnp.swapaxes(R_ref, -1, -2))], axis=1)
    return rows, err < NEWTON_TOL
'''
