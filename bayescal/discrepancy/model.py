"""A fitted model discrepancy: a smooth function of the inputs added to the tool pose, and its rows.

The measurement model with a discrepancy (Kennedy and O'Hagan, "Bayesian
calibration of computer models", JRSS B 63, 2001) is

    y = h(q, theta) + M(q) delta(x) + noise,

``delta`` a vector field over chosen inputs ``x`` (actuator positions,
auxiliary channels of the recording such as temperature, payload or a tilt
reading), with values a small displacement of the tool point (mm, base
frame) and, for measurements that see orientation, a small rotation of the
platform (rad, base frame); ``M`` maps a tool-pose perturbation into the
measured rows of each pose (its instrument frame, its measurement type),
the same map every geometric parameter goes through.

Component ``o`` of ``delta`` is ``s_o phi(x)^T v_o`` with the inducing-point
basis of :mod:`bayescal.discrepancy.kernel`; the weights ``v`` (``n_out m``
of them, prior ``N(0, I)``) are fitted jointly with the geometry, the split
between the two decided by their priors (:mod:`bayescal.discrepancy.fit`).
The uncertainty of the weights, jointly with the parameters', is carried by
the machine file's ``[calibration]`` table.  (:attr:`Discrepancy.shift`, a
mean correction ``- J c`` on named parameters, is kept for tables that state
one; the joint fit writes none.)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from .kernel import nystrom_features

__all__ = ["Discrepancy", "DiscrepancyTransform", "OUTPUT_NAMES", "weight_names"]

#: The components ``delta`` may have: tool point (mm) and small rotation (rad), base frame.
OUTPUT_NAMES = ("x", "y", "z", "rx", "ry", "rz")
_UNITS = {"x": "mm", "y": "mm", "z": "mm", "rx": "rad", "ry": "rad", "rz": "rad"}


def weight_names(n: int) -> tuple[str, ...]:
    """Parameter names of the discrepancy's weights in a joint covariance."""
    return tuple(f"discrepancy.w{k}" for k in range(n))


@dataclass(frozen=True, eq=False)
class Discrepancy:
    """A fitted discrepancy (module docstring).

    Attributes
    ----------
    inputs : tuple of str
        ``q<i>`` (actuator ``i``) or a recording's auxiliary channel.
    center, scale : ndarray, shape (d,)
        Standardisation of the inputs, in their units: ``z = (x - center) / scale``.
    length_scales : ndarray, shape (d,)
        Per input, in standardised units (large: the input does not matter).
    outputs : tuple of str
        Components of ``delta`` (a subset of :data:`OUTPUT_NAMES`).
    output_scales : ndarray, shape (n_out,)
        Prior standard deviation of each component, mm or rad.
    inducing : ndarray, shape (m, d)
        Inducing inputs, standardised.
    weights : ndarray, shape (n_out * m,)
        Posterior mean of ``v`` (dimensionless).
    shift_names : tuple of str
        Parameters of the projection's mean correction ``- J c``.
    shift : ndarray
        ``c``, in those parameters' units.
    log_evidence_gain : float
        Log marginal likelihood of the residual with the discrepancy over
        without it (a log Bayes factor, at the fitted hyperparameters).
    explained : float
        Share of the whitened residual sum of squares the discrepancy's mean carries, 0-1.
    """

    inputs: tuple[str, ...]
    center: NDArray
    scale: NDArray
    length_scales: NDArray
    outputs: tuple[str, ...]
    output_scales: NDArray
    inducing: NDArray
    weights: NDArray
    shift_names: tuple[str, ...] = ()
    shift: NDArray = field(default_factory=lambda: np.zeros(0))
    log_evidence_gain: float = float("nan")
    explained: float = float("nan")

    def __post_init__(self) -> None:
        d, m = len(self.inputs), np.asarray(self.inducing).shape[0]
        for name, arr, shape in (("center", self.center, (d,)), ("scale", self.scale, (d,)),
                                 ("length_scales", self.length_scales, (d,)),
                                 ("output_scales", self.output_scales, (len(self.outputs),)),
                                 ("inducing", self.inducing, (m, d)), ("weights", self.weights, (len(self.outputs) * m,)),
                                 ("shift", self.shift, (len(self.shift_names),))):
            a = np.asarray(arr, dtype=float)
            if a.shape != shape:
                raise InputError(f"discrepancy {name}: expected shape {shape}, got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise InputError(f"discrepancy {name}: expected finite values")
            object.__setattr__(self, name, a)
        if any(o not in OUTPUT_NAMES for o in self.outputs) or len(set(self.outputs)) != len(self.outputs):
            raise InputError(f"discrepancy outputs: expected distinct names among {', '.join(OUTPUT_NAMES)}")
        if np.any(self.scale <= 0) or np.any(self.length_scales <= 0) or np.any(self.output_scales < 0):
            raise InputError("discrepancy: scales and length scales must be positive")
        object.__setattr__(self, "_chol", nystrom_features(self.inducing[:1], self.inducing, self.length_scales)[1])

    # ------------------------------------------------------------- sizes
    @property
    def n_inducing(self) -> int:
        return self.inducing.shape[0]

    @property
    def n_features(self) -> int:
        return len(self.outputs) * self.n_inducing

    @property
    def output_units(self) -> tuple[str, ...]:
        return tuple(_UNITS[o] for o in self.outputs)

    def relevance(self) -> dict[str, float]:
        """Per input, ``1 / length scale`` (standardised units): how fast the discrepancy changes with it."""
        return {n: float(1.0 / ls) for n, ls in zip(self.inputs, self.length_scales)}

    # ------------------------------------------------------------- inputs
    def raw_inputs(self, model) -> NDArray:
        """The inputs at every pose ``model`` solves, shape (n_solved, d), in their own units."""
        return discrepancy_inputs(model, self.inputs)

    def features(self, X_raw: NDArray) -> NDArray:
        """``phi`` at raw inputs, shape (n, m)."""
        z = (np.asarray(X_raw, dtype=float) - self.center) / self.scale
        return nystrom_features(z, self.inducing, self.length_scales, chol=self._chol)[0]

    def tool_offset(self, q: NDArray, aux: dict | None = None) -> NDArray:
        """The discrepancy's mean at commanded ``q`` (n, N) and channels ``aux``: base-frame tool offset (n, 6).

        Rows 0-2 the tool point (mm), 3-5 the small rotation (rad); components
        the discrepancy does not model are zero.  InputError naming an input
        the channels lack.
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        n = q.shape[0]
        cols = []
        for name in self.inputs:
            if name.startswith("q") and name[1:].isdigit() and int(name[1:]) <= q.shape[1]:
                cols.append(q[:, int(name[1:]) - 1])
            elif aux is not None and name in aux:
                cols.append(np.broadcast_to(np.asarray(aux[name], dtype=float), (n,)))
            elif name.startswith("q") and name[1:].isdigit():
                raise InputError(f"discrepancy input {name!r}: the machine has actuators q1..q{q.shape[1]}")
            else:
                # "(give the channel)" did not say how: a grid takes a channel's value with --aux
                raise InputError(f"discrepancy input {name!r}: the machine file's [discrepancy] depends on this channel; "
                                 f"expected its value (for a grid: --aux {name}=VALUE)")
        phi = self.features(np.column_stack(cols))
        m = self.n_inducing
        out = np.zeros((n, 6))
        for k, o in enumerate(self.outputs):
            out[:, OUTPUT_NAMES.index(o)] = self.output_scales[k] * (phi @ self.weights[k * m:(k + 1) * m])
        return out

    # ------------------------------------------------------------- rows
    def tool_map(self, model, theta, prediction) -> NDArray:
        """``(n_solved, dof, n_out)``: each pose's measured rows per unit of each component of ``delta``."""
        return output_rows_map(model, theta, prediction, self.outputs)

    def rows(self, model, theta, prediction, J: NDArray | None = None) -> tuple[NDArray, NDArray, NDArray]:
        """The discrepancy's mean, feature matrix and residual variance in ``model``'s rows.

        Parameters
        ----------
        model : MeasurementModel
        theta : ndarray, shape (P,)
        prediction : Prediction
            ``model.predict(theta)``.
        J : ndarray, shape (n, dof, P), optional
            ``model.jacobian(theta, prediction)`` if already computed (for the mean correction).

        Returns
        -------
        mean : ndarray, shape (n, dof)
            ``F v_mean - J c`` (mm, rad).
        F : ndarray, shape (n, dof, n_out m)
            Rows per unit of each weight.
        var : ndarray, shape (n, dof, dof)
            The prior's part the inducing points do not carry, mapped into the rows.
        """
        G = self.tool_map(model, theta, prediction)  # (n, dof, n_out)
        phi = self.features(self.raw_inputs(model))  # (n_solved, m)
        if G.shape[0] != phi.shape[0]:
            raise InputError("discrepancy: takes recordings of measured poses (one pose per row)")
        s = self.output_scales
        F = np.einsum("nao,o,nj->naoj", G, s, phi).reshape(G.shape[0], G.shape[1], -1)
        mean = F @ self.weights
        if self.shift_names:
            names = model.machine.layout.names
            pos = {n: i for i, n in enumerate(names)}
            have = [k for k, n in enumerate(self.shift_names) if n in pos]
            if have:
                if J is None:
                    J = model.jacobian(theta, prediction)
                cols = [pos[self.shift_names[k]] for k in have]
                mean = mean - J[:, :, cols] @ self.shift[have]
        rest = np.clip(1.0 - np.sum(phi**2, axis=1), 0.0, 1.0)  # (n,)
        var = np.einsum("nao,o,n,nbo->nab", G, s**2, rest, G)
        return mean, F, var


def discrepancy_inputs(model, names) -> NDArray:
    """Values of the inputs ``names`` at every pose ``model`` solves, shape (n_solved, d).

    ``q<i>`` is actuator ``i`` (as commanded, effects applied); any other
    name is an auxiliary channel of the recording.  InputError naming the
    input when the recording does not have it.
    """
    q = np.asarray(model.pose_q, dtype=float)
    rows = np.asarray(model.pose_row)
    aux = model.aux or {}
    cols = []
    for name in names:
        if name.startswith("q") and name[1:].isdigit():
            i = int(name[1:]) - 1
            if not 0 <= i < q.shape[1]:
                raise InputError(f"discrepancy input {name!r}: the machine has actuators q1..q{q.shape[1]}")
            cols.append(q[:, i])
        elif name in aux:
            cols.append(np.asarray(aux[name], dtype=float)[rows])
        else:
            have = ", ".join(sorted(aux)) or "none"
            raise InputError(f"discrepancy input {name!r}: the recording has no such column (auxiliary channels: {have})")
    return np.column_stack(cols) if cols else np.zeros((q.shape[0], 0))


def output_rows_map(model, theta, prediction, outputs) -> NDArray:
    """``(n_solved, dof, n_out)``: measured rows per unit base-frame tool displacement / rotation component."""
    n = np.asarray(model.pose_q).shape[0]
    R = model.machine.measurement_rotation(model.pose_q, theta)  # base -> measurement frame, (n, 3, 3)
    unit = np.zeros((n, 6, 6))
    unit[:, :3, :3] = R
    unit[:, 3:, 3:] = R
    rows = model.rows_jacobian(unit, prediction)  # (n_rows, dof, 6)
    idx = [OUTPUT_NAMES.index(o) for o in outputs]
    return rows[:, :, idx]


@dataclass(frozen=True, eq=False)
class DiscrepancyTransform:
    """A discrepancy as a :class:`bayescal.simulate.PoseTransform`: simulating a machine that carries one."""

    discrepancy: Discrepancy

    def transform(self, q: NDArray, theta: NDArray, aux: dict, order: NDArray) -> tuple[NDArray, NDArray]:
        return q, theta

    def pose_offset(self, q: NDArray, theta: NDArray, aux: dict, order: NDArray) -> NDArray:
        return self.discrepancy.tool_offset(q, aux)
