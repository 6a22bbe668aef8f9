"""Conformance check for effects (the ``check_machine`` of effects)."""

from __future__ import annotations

import re

import numpy as np

from ..errors import BayescalError
from ..machines.base import Machine
from .base import Effect, Features

__all__ = ["check_effect", "EffectCheckError"]

_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_PARAM = re.compile(r"^[a-z][a-z0-9_]*(\.[a-z][a-z0-9_]*)?$")


class EffectCheckError(BayescalError, AssertionError):
    """An effect does not satisfy the effect interface."""


def check_effect(effect: Effect, machine: Machine, *, aux: dict | None = None, n_poses: int = 12, seed: int = 0, rtol: float = 1e-5) -> None:
    """Check that an effect satisfies the interface; raise :class:`EffectCheckError` if not.

    Checks: a stable snake_case name, a docstring stating the physics, named
    parameters with units and positive prior widths, ``delta_q`` of the right
    shape and zero at zero parameters (where the prior mean is zero),
    ``delta_q_jacobian`` against central finite differences (and, for a
    geometry-dependent effect, ``delta_q_at`` and its two Jacobians), the
    :class:`~bayescal.simulate.PoseTransform` behaviour of the bound effect
    (``theta`` unchanged, ``q`` moved by ``delta_q``, the tool by
    ``delta_x`` for an effect that moves it), and feature subsetting.

    Parameters
    ----------
    effect : Effect
    machine : Machine
        With ``q_limits``.
    aux : dict, optional
        Channels the effect needs (e.g. ``temp_C``), one value per pose.
    n_poses : int
    seed : int
    rtol : float
        Tolerance of the Jacobian check, relative to the largest entry.
    """
    def fail(msg):
        raise EffectCheckError(f"effect {effect.name or type(effect).__name__}: {msg}")

    _check_declaration(effect, fail)
    rng = np.random.default_rng(seed)
    aux = {} if aux is None else aux
    why = effect.not_applicable(machine, aux)
    if why:
        fail(f"not applicable to the machine and channels given: {why}")
    q = machine.sample_q(n_poses, rng)
    theta = np.zeros(machine.n_params)
    poses = machine.forward(q, theta) if effect.needs_poses else None
    feats = effect.features(machine, q, theta, aux, np.arange(n_poses), poses)
    if not isinstance(feats, Features):
        fail("features() must return a Features")
    params = effect.params(machine, feats)
    _check_params(params, fail)
    K = len(params)
    mean = np.array([p.prior_mean for p in params])
    sd = np.array([p.prior_sd for p in params])
    zero = np.where(mean == 0, 0.0, mean)
    dq0 = effect.delta_q(feats, zero)
    if dq0.shape != q.shape:
        fail(f"delta_q: expected shape {q.shape}, got {dq0.shape}")
    lin = mean == 0
    if lin.all() and np.max(np.abs(dq0)) > 0:
        fail("delta_q must vanish when every parameter is zero")
    eta = mean + sd * rng.uniform(0.2, 1.0, K)
    _check_delta_q_jacobian(effect, feats, eta, sd, q.shape, rtol, fail)
    if effect.geometry_dependent:
        _check_geometry_dependence(effect, machine, feats, eta, theta, rng, rtol, fail)
    if effect.moves_tool:
        _check_tool_motion(effect, feats, zero, lin.all(), eta, sd, rtol, fail)
    if effect.bends_bodies:
        _check_body_turns(effect, feats, eta, sd, rtol, fail)
    idx = np.arange(0, n_poses, 2)
    sub = feats.subset(idx)
    if not np.allclose(effect.delta_q(sub, eta), effect.delta_q(feats, eta)[idx]):
        fail("Features.subset does not give the subset's delta_q")
    _check_binding(effect, machine, feats, eta, q, theta, aux, idx, fail)


def _check_declaration(effect: Effect, fail) -> None:
    """A stable snake_case name, a class docstring stating the physics, a magnitude unit."""
    if not _NAME.match(effect.name or ""):
        fail("name: expected a snake_case stable name")
    if not (type(effect).__doc__ or "").strip() or "Physics" not in type(effect).__doc__:
        fail("the class docstring must state the physics ('Physics: ...') and its usual magnitude")
    if not effect.magnitude_unit:
        fail("magnitude_unit is empty")


def _check_params(params, fail) -> None:
    """At least one parameter; distinct dotted snake_case names, each with a unit and a positive finite prior width."""
    if not params:
        fail("no parameters")
    names = [p.name for p in params]
    if len(set(names)) != len(names):
        fail(f"duplicate parameter names {names}")
    for p in params:
        if not _PARAM.match(p.name) or not p.unit or not (p.prior_sd > 0 and np.isfinite(p.prior_sd)):
            fail(f"parameter {p.name!r}: expected a dotted snake_case name, a unit and a positive prior_sd")


def _check_delta_q_jacobian(effect: Effect, feats: Features, eta, sd, q_shape, rtol: float, fail) -> None:
    """``delta_q_jacobian`` of shape ``q_shape + (K,)`` and within ``rtol`` of central differences of ``delta_q``."""
    K = eta.size
    J = effect.delta_q_jacobian(feats, eta)
    if J.shape != q_shape + (K,):
        fail(f"delta_q_jacobian: expected shape {q_shape + (K,)}, got {J.shape}")
    Jfd = np.empty_like(J)
    for k in range(K):
        h = 1e-4 * sd[k]
        e = np.zeros(K)
        e[k] = h
        Jfd[..., k] = (effect.delta_q(feats, eta + e) - effect.delta_q(feats, eta - e)) / (2 * h)
    scale = max(np.max(np.abs(Jfd)), 1e-300)
    if np.max(np.abs(J - Jfd)) > rtol * scale:
        fail(f"delta_q_jacobian differs from finite differences by {np.max(np.abs(J - Jfd)) / scale:.1e} (relative)")


def _check_binding(effect: Effect, machine: Machine, feats: Features, eta, q, theta, aux, idx, fail) -> None:
    """The bound effect as a PoseTransform: ``q`` moved by ``delta_q``, ``theta`` kept, the tool by ``delta_x``."""
    n_poses = q.shape[0]
    bound = effect.bind(machine, eta)
    q2, th2 = bound.transform(q, np.broadcast_to(theta, (n_poses, machine.n_params)).copy(), aux, np.arange(n_poses))
    if not np.allclose(q2, q + effect.delta_q(feats, eta), rtol=0, atol=1e-12):
        fail("the bound effect's transform does not move q by delta_q")
    if not np.array_equal(th2, np.broadcast_to(theta, th2.shape)):
        fail("the bound effect's transform changed theta")
    if effect.moves_tool:
        if not np.allclose(effect.delta_x(feats.subset(idx), eta), effect.delta_x(feats, eta)[idx]):
            fail("Features.subset does not give the subset's delta_x")
        off = bound.pose_offset(q, np.broadcast_to(theta, (n_poses, machine.n_params)).copy(), aux, np.arange(n_poses))
        if off is None or not np.allclose(off, effect.delta_x(feats, eta), rtol=0, atol=1e-12):
            fail("the bound effect's pose_offset is not delta_x")


def _check_tool_motion(effect: Effect, feats: Features, zero, linear: bool, eta, sd, rtol: float, fail) -> None:
    """An effect that moves the tool: ``delta_x`` of shape (n, 6), zero at zero parameters, its Jacobian against central differences."""
    n = next(iter(feats.per_pose.values())).shape[0]
    dx0 = effect.delta_x(feats, zero)
    if dx0.shape != (n, 6):
        fail(f"delta_x: expected shape {(n, 6)}, got {dx0.shape}")
    if linear and np.max(np.abs(dx0)) > 0:
        fail("delta_x must vanish when every parameter is zero")
    J = effect.delta_x_jacobian(feats, eta)
    K = len(sd)
    if J.shape != (n, 6, K):
        fail(f"delta_x_jacobian: expected shape {(n, 6, K)}, got {J.shape}")
    Jfd = np.empty_like(J)
    for k in range(K):
        e = np.zeros(K)
        e[k] = 1e-4 * sd[k]
        Jfd[..., k] = (effect.delta_x(feats, eta + e) - effect.delta_x(feats, eta - e)) / (2 * e[k])
    scale = max(np.max(np.abs(Jfd)), 1e-300)
    if np.max(np.abs(J - Jfd)) > rtol * scale:
        fail(f"delta_x_jacobian differs from finite differences by {np.max(np.abs(J - Jfd)) / scale:.1e} (relative)")


def _check_body_turns(effect: Effect, feats: Features, eta, sd, rtol: float, fail) -> None:
    """An effect that turns sensor-carrying bodies: one (n, 3) turn per body, its Jacobian against central differences."""
    n = next(iter(feats.per_pose.values())).shape[0]
    turns, jac = effect.body_rotation(feats, eta), effect.body_rotation_jacobian(feats, eta)
    if set(turns) != set(jac):
        fail(f"body_rotation and its Jacobian name different bodies: {sorted(turns)} and {sorted(jac)}")
    K = len(sd)
    for body, w in turns.items():
        if w.shape != (n, 3) or jac[body].shape != (n, 3, K):
            fail(f"body_rotation {body}: expected shapes {(n, 3)} and {(n, 3, K)}, got {w.shape} and {jac[body].shape}")
        fd = np.empty((n, 3, K))
        for k in range(K):
            e = np.zeros(K)
            e[k] = 1e-4 * sd[k]
            fd[..., k] = (effect.body_rotation(feats, eta + e)[body] - effect.body_rotation(feats, eta - e)[body]) / (2 * e[k])
        scale = max(np.max(np.abs(fd)), 1e-300)
        if np.max(np.abs(jac[body] - fd)) > rtol * scale:
            fail(f"body_rotation_jacobian {body} differs from finite differences by {np.max(np.abs(jac[body] - fd)) / scale:.1e} (relative)")


def _check_geometry_dependence(effect: Effect, machine: Machine, feats: Features, eta, theta, rng, rtol: float, fail) -> None:
    """An effect whose ``dq`` depends on the geometry: ``delta_q_at`` at the features' geometry is ``delta_q``,
    and ``delta_q_jacobian_at`` and ``delta_q_theta_jacobian`` agree with central finite differences."""
    if not np.allclose(effect.delta_q_at(feats, eta, theta), effect.delta_q(feats, eta), rtol=0, atol=1e-12):
        fail("delta_q_at at the features' geometry differs from delta_q")
    P = machine.n_params
    th = theta + machine.tolerance * rng.uniform(-1.0, 1.0, P)
    Jt = effect.delta_q_theta_jacobian(feats, eta, th)
    n, m = effect.delta_q(feats, eta).shape
    if Jt is None or Jt.shape != (n, m, P):
        fail(f"delta_q_theta_jacobian: expected shape {(n, m, P)} for a geometry-dependent effect, got {None if Jt is None else Jt.shape}")
    Jfd = np.empty_like(Jt)
    for j in range(P):
        e = np.zeros(P)
        e[j] = 1e-3 * machine.tolerance[j]
        Jfd[..., j] = (effect.delta_q_at(feats, eta, th + e) - effect.delta_q_at(feats, eta, th - e)) / (2 * e[j])
    scale = max(np.max(np.abs(Jfd)), 1e-300)
    if np.max(np.abs(Jt - Jfd)) > rtol * scale:
        fail(f"delta_q_theta_jacobian differs from finite differences by {np.max(np.abs(Jt - Jfd)) / scale:.1e} (relative)")
    J = effect.delta_q_jacobian_at(feats, eta, th)
    sd = np.array([p.prior_sd for p in effect.params(machine, feats)])
    Jfd = np.empty_like(J)
    for k in range(len(sd)):
        e = np.zeros(len(sd))
        e[k] = 1e-4 * sd[k]
        Jfd[..., k] = (effect.delta_q_at(feats, eta + e, th) - effect.delta_q_at(feats, eta - e, th)) / (2 * e[k])
    scale = max(np.max(np.abs(Jfd)), 1e-300)
    if np.max(np.abs(J - Jfd)) > rtol * scale:
        fail(f"delta_q_jacobian_at differs from finite differences by {np.max(np.abs(J - Jfd)) / scale:.1e} (relative)")
