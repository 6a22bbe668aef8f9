"""Identifiability: SVD of the column-scaled Jacobian, and an identifiable parameter set.

Columns are scaled to unit norm (the usual scaling for identifiability,
independent of the units of each parameter), so singular values compare
directions in parameter space fairly.  A parameter whose scaled column lies
(numerically) in the span of columns already kept is fixed at its nominal
value; its column's expression in the kept columns names the combination
the measurement sees.

That reduction is what least squares needs (it has nothing else to decide
a direction the data do not see).  An estimator with a prior (MAP, ridge
with ``lam > 0``, TSVD in the tolerance-scaled metric) does not: the prior
decides such a direction, keeping it near nominal in proportion to the
tolerances, which is the posterior mean.  Fixing a parameter at nominal
instead is a hard constraint the true machine violates by about its
tolerance, and the data then move the parameters confounded with it by
that amount times the combination's coefficients, which can be large.  On
the example delta with a two-plane ballbar recording (docs/delta.md),
fixing the ballbar pivot at its start and three tower parameters for the
rotation gauge left MAP at a median output error of 1.60 mm against
0.71 mm uncalibrated (``compare --recording``, 200 trials, true pivots
1 mm about the start); the prior deciding the same directions gave 0.50 mm.
:meth:`Identifiability.with_prior` is the set for such estimators: only
the parameters the measurement does not see at all are fixed (the prior
would leave them at nominal anyway), and the combinations are reported as
decided by the prior.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from .params import ParamLayout

__all__ = ["Identifiability", "analyse_identifiability", "priority_order", "UNKNOWN_RATIO"]

#: Relative singular value below which a direction counts as structurally unidentifiable.
STRUCTURAL_RTOL = 1e-8


@dataclass(frozen=True)
class Identifiability:
    """What the poses can identify.

    Attributes
    ----------
    singular_values : ndarray, shape (P,)
        Of the whitened, column-normalised Jacobian of all parameters, descending.
    rank : int
        Numerical rank (singular values above ``STRUCTURAL_RTOL`` times the largest).
    kept : tuple of str
        Identifiable parameter set chosen (in the priority order given).
    fixed : tuple of str
        Parameters fixed at nominal.
    combinations : tuple of str
        For each fixed parameter, the kept parameters it cannot be told apart
        from, in words.
    condition_number : float
        Of the column-normalised Jacobian of the kept set.
    kept_index, fixed_index : ndarray of int
        The same sets as indices.
    no_effect_index : ndarray of int
        Parameters whose column is zero (the measurement does not see them).
    relations : tuple of str
        For each parameter confounded with others (fixed, or left to the
        prior by :meth:`with_prior`), what it looks the same as, in words.
    decided_by_prior : tuple of str
        After :meth:`with_prior`: the combinations the data do not separate
        and the prior decides (these parameters are estimated, not fixed).
    """

    singular_values: NDArray
    rank: int
    kept: tuple[str, ...]
    fixed: tuple[str, ...]
    combinations: tuple[str, ...]
    condition_number: float
    kept_index: NDArray
    fixed_index: NDArray
    no_effect_index: NDArray = field(default_factory=lambda: np.zeros(0, dtype=int))
    relations: tuple[str, ...] = ()
    decided_by_prior: tuple[str, ...] = ()

    def holding(self, held: NDArray, names: tuple[str, ...]) -> "Identifiability":
        """The same analysis with the parameters ``held`` (indices) held fixed by the user: out of the kept set.

        They are not counted as fixed (the measurement may see them); the
        results name them apart, as ``held``.
        """
        held = np.asarray(held, dtype=int)
        if held.size == 0:
            return self
        kept = np.setdiff1d(self.kept_index, held)
        return replace(self, kept=tuple(names[j] for j in kept), kept_index=kept)

    def with_prior(self, names: tuple[str, ...]) -> "Identifiability":
        """The parameter set for an estimator with a prior: fix only what the measurement does not see.

        Parameters
        ----------
        names : tuple of str
            All parameter names (the layout's), to name the kept set.

        Returns
        -------
        Identifiability
            ``kept`` every parameter with a non-zero column, ``fixed`` those
            without, ``combinations`` why they are fixed, and
            ``decided_by_prior`` the confounded combinations the prior now
            decides (see the module docstring for why).
        """
        no_effect = set(self.no_effect_index.tolist())
        kept = np.array([j for j in range(len(names)) if j not in no_effect], dtype=int)
        fixed = np.array(sorted(no_effect), dtype=int)
        return replace(
            self,
            kept=tuple(names[j] for j in kept),
            fixed=tuple(names[j] for j in fixed),
            combinations=tuple(f"{names[j]} does not affect the measurement at these poses" for j in fixed),
            kept_index=kept,
            fixed_index=fixed,
            decided_by_prior=tuple(
                f"{r}; not separated by the data, the prior keeps the split near nominal" for r in self.relations
            ),
        )

    def report(self) -> str:
        s = self.singular_values
        lines = [
            f"Identifiability: {len(s)} parameters, numerical rank {self.rank}, "
            f"{len(self.kept)} kept, {len(self.fixed)} fixed at nominal",
            f"  singular values (column-normalised): max {s[0]:.3g}, min kept {s[self.rank - 1]:.3g}, "
            f"condition number of the identifiable set {self.condition_number:.3g}",
        ]
        lines += [f"  - {c}" for c in self.combinations + self.decided_by_prior]
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {
            "singular_values": self.singular_values,
            "rank": self.rank,
            "kept": list(self.kept),
            "fixed": list(self.fixed),
            "combinations": list(self.combinations),
            "decided_by_prior": list(self.decided_by_prior),
            "condition_number": self.condition_number,
        }


#: A parameter whose tolerance is at least this many times the median tolerance of the parameters
#: with its unit is "declared unknown" (an instrument frame, a target mounted somewhere on the last
#: link): :func:`priority_order` keeps it in preference to the parameters it is confused with.
UNKNOWN_RATIO = 10.0


def priority_order(tolerance: NDArray, units, nuisance: NDArray | None = None) -> NDArray:
    """Greedy order for :func:`analyse_identifiability`: nuisance and declared-unknown parameters first, then layout order.

    Among parameters the measurement confuses exactly (a tool point and the
    origin of the last joint frame, say), the greedy pass keeps the first and
    fixes the others at nominal.  Layout order keeps the machine's parameters
    before the tool.  That is the right gauge when all tolerances are alike,
    but not when one of them is declared unknown (a tolerance ten times or
    more the typical one of its unit): fixing it at nominal and moving a
    0.05 mm joint origin by 100 mm instead would make a regularised fit
    refuse the data.  So such parameters go first (in layout order among
    themselves); everything else keeps layout order.

    Nuisance parameters (not the machine's geometry: ballbar pivots, a
    fitted instrument frame; ``Machine.geometry_part`` says which) go first
    of all, for the same reason: their start is a guess (a ballbar pivot's
    tolerance is 1 mm against 0.2 mm for the delta's geometry, under the
    factor of ten above), and fixing one makes the geometry absorb its error
    (the delta ballbar case of the module docstring: the tower radii moved
    by 0.6-0.8 mm to stand in for a pivot 1 mm off).

    Parameters
    ----------
    tolerance : ndarray, shape (P,)
        One-sigma prior widths, in the parameters' units.
    units : sequence of str, length P
    nuisance : ndarray of int, optional
        Indices of nuisance parameters, kept first (in layout order).

    Returns
    -------
    ndarray of int, shape (P,)
    """
    tol = np.asarray(tolerance, dtype=float)
    units = np.asarray(list(units), dtype=object)
    unknown = np.zeros(tol.size, dtype=bool)
    for u in set(units.tolist()):
        sel = units == u
        med = float(np.median(tol[sel]))
        if med > 0:
            unknown[sel] = tol[sel] >= UNKNOWN_RATIO * med
    first = np.zeros(tol.size, dtype=bool)
    if nuisance is not None:
        first[np.asarray(nuisance, dtype=int)] = True
    unknown &= ~first
    return np.concatenate([np.flatnonzero(first), np.flatnonzero(unknown), np.flatnonzero(~(unknown | first))])


def analyse_identifiability(
    J: NDArray,
    layout: ParamLayout,
    *,
    candidates: NDArray | None = None,
    rtol: float = STRUCTURAL_RTOL,
) -> Identifiability:
    """Find an identifiable parameter set and name what cannot be identified.

    Parameters
    ----------
    J : ndarray, shape (n_rows, P)
        Whitened identification Jacobian (rows divided by the noise sigma).
    layout : ParamLayout
        Names and units of the P parameters.
    candidates : ndarray of int, optional
        Parameters allowed to be identified, in priority order (those earlier
        are kept in preference).  Default: all, in layout order (machine
        parameters before the tool point).
    rtol : float
        Relative singular-value threshold for structural deficiency.

    Returns
    -------
    Identifiability
    """
    J = np.asarray(J, dtype=float)
    P = J.shape[1]
    order = np.arange(P) if candidates is None else np.asarray(candidates, dtype=int)
    norms = np.linalg.norm(J, axis=0)
    safe = np.where(norms > 0, norms, 1.0)
    # columns at round-off level are zero: normalised, their noise would count in the rank
    Js = np.where(norms > 1e-12 * max(norms.max(initial=0.0), 1e-300), J / safe, 0.0)
    s_all = np.linalg.svd(Js[:, order], compute_uv=False)
    rank = int(np.sum(s_all > rtol * s_all[0])) if s_all.size and s_all[0] > 0 else 0
    kept, fixed = _greedy_columns(Js, norms, order, rank, rtol)
    names = layout.names
    combos, relations, no_effect = _fixed_relations(J, kept, fixed, norms, safe, layout)
    s_kept = np.linalg.svd(Js[:, kept], compute_uv=False) if kept else np.array([np.nan])
    return Identifiability(
        singular_values=s_all,
        rank=rank,
        kept=tuple(names[j] for j in kept),
        fixed=tuple(names[j] for j in fixed),
        combinations=tuple(combos),
        condition_number=float(s_kept[0] / s_kept[-1]) if kept else float("inf"),
        kept_index=np.array(sorted(kept), dtype=int),
        fixed_index=np.array(sorted(fixed), dtype=int),
        no_effect_index=np.array(sorted(no_effect), dtype=int),
        relations=tuple(relations),
    )


def _greedy_columns(Js: NDArray, norms: NDArray, order: NDArray, rank: int, rtol: float) -> tuple[list[int], list[int]]:
    """The columns kept (in priority ``order``, each independent of those before) and the ones fixed."""
    P = Js.shape[1]
    kept: list[int] = []
    Q_all = np.zeros((Js.shape[0], P), order="F")  # the kept columns' orthonormal basis, filled in place
    fixed: list[int] = []
    zero = 1e-12 * max(norms.max(), 1e-300)
    for j in order.tolist():
        if norms[j] <= zero:
            fixed.append(j)
            continue
        Q = Q_all[:, : len(kept)]
        c = Js[:, j]
        res = c - Q @ (Q.T @ c)
        res = res - Q @ (Q.T @ res)  # re-orthogonalise (classical Gram-Schmidt twice)
        size = np.sqrt(res.dot(res))  # numpy.linalg.norm's arithmetic, once
        if size > 10 * rtol:
            Q_all[:, len(kept)] = res / size
            kept.append(j)
        else:
            fixed.append(j)
    # the greedy pass keeps at most `rank` columns; trim if round-off let one more through
    while len(kept) > rank:
        fixed.append(kept.pop())
    return kept, fixed


def _fixed_relations(J: NDArray, kept: list[int], fixed: list[int], norms: NDArray, safe: NDArray, layout):
    """In words, what each fixed parameter looks like to the measurement: ``(combos, relations, no_effect)``."""
    combos, relations, no_effect = [], [], []
    names, units = layout.names, layout.units
    zero = 1e-12 * max(norms.max(), 1e-300)
    seen = [j for j in fixed if norms[j] > zero]
    # J_j = J_K c: changing theta_j by 1 looks like changing the kept ones by c; one factorisation for every
    # fixed column (column by column it was a sixth of identifying a 23-pose arm)
    C = np.linalg.lstsq(J[:, kept], J[:, seen], rcond=None)[0] if seen and kept else np.zeros((len(kept), len(seen)))
    col = {j: i for i, j in enumerate(seen)}
    # every column's terms at once: those that matter, and the order they are named in (largest effect first)
    size = np.abs(C) * safe[kept][:, None]
    # one row per fixed column (the same values as column by column); the coefficients as Python floats, whose
    # digits are numpy's scalars' and which format faster
    big, key, coefs = (size > 1e-6 * norms[seen]).T.copy(), (-size).T.copy(), C.T.tolist()
    before, after = [f"{names[k]} by " for k in kept], [f" {units[k]}" for k in kept]  # each kept parameter's term
    for j in fixed:
        if j not in col:
            combos.append(f"{names[j]} does not affect the measurement at these poses")
            no_effect.append(j)
            continue
        i = col[j]
        terms_at = big[i].nonzero()[0]
        cl = coefs[i]
        order = terms_at[key[i][terms_at].argsort()].tolist()
        terms = ", ".join(before[k] + format(cl[k], "+.4g") + after[k] for k in order)
        relations.append(f"{names[j]}: a change of 1 {units[j]} looks the same to the measurement as changing {terms}")
        combos.append(relations[-1] + "; fixed at nominal, only the combination is identified")
    return combos, relations, no_effect
