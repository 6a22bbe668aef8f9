"""The stated noise of the tool's position rows and of its orientation rows, tested apart.

A machine file states two noises, ``sigma_position`` (mm) and ``sigma_angle``
(rad).  The chi-square test of :mod:`bayescal.identify.noise` sums every row:
with ``sigma_position`` stated 100 times too large and ``sigma_angle`` right,
the position rows add almost nothing, the angle rows about their count, and the
reduced chi-square (0.4 on the bundled 3-PRS recording) "fits", while the
calibration, weighting the positions 10^4 times too little against the prior,
leaves 0.11 mm where 0.0073 mm is reachable.  Each group is therefore tested on
its own rows (degrees of freedom: its distinct rows less its share of the
effective parameters, shared in proportion to the rows), and where the groups
disagree (one contradicted, and the groups' own noise estimates
``sqrt(chi2 / dof)`` more than :data:`DISAGREE` apart) each contradicted group's sigma is rescaled
by its own estimate before the fit is redone and the whole noise tested as
before.  Where both are off by about the same factor, the one scale of the
whole test serves, as it always did.

The body sensors' tilt rows have their own test (:func:`bayescal.identify.calibrate.tilt_noise_check`).
The written machine file keeps ``[measurement]`` as stated; the report names
the sigma the data support, to be corrected there.
"""

from __future__ import annotations

import math

import numpy as np

from ..contract import whiten
from .noise import NoiseCheck, check_noise, distinct_rows

__all__ = ["tool_group_checks", "group_scales", "with_group_scales", "group_report", "DISAGREE"]

#: Groups whose noise estimates differ by more than this factor (one of them contradicted) are rescaled apart.
DISAGREE = 3.0
#: The groups: name, the machine file's key, the tool rows (position first, then the orientation rows).
GROUPS = (("position", "sigma_position", slice(0, 3)), ("angle", "sigma_angle", slice(3, None)))


def tool_group_checks(model, res, *, stated: bool, weights=None) -> dict[str, NoiseCheck] | None:
    """The chi-square test of the position rows and of the orientation rows alone (None: one group, no fit).

    Parameters
    ----------
    model : MeasurementModel
        The model ``res`` was fitted to (its ``row_sigma`` the sigmas tested).
    res : bayescal.contract.Result
        A fit (nothing is tested without its ``residuals_after``).
    stated : bool
        Whether the noise is stated; without it the sigmas are weights and nothing is tested.
    weights : ndarray, shape (n_poses,), optional
        The robust pass's weights (:class:`bayescal.outliers.handling.OutlierHandling`): a gross pose
        down-weighted in the fit is down-weighted here too, or its residual alone would read as a
        contradicted sigma of its group (one gross pose of the 3-PRS: position rows "10 times too
        noisy", its outlier statistic then divided by 100).
    """
    tool = int(model.tool_dof)
    if not stated or tool <= 3 or not res.success or res.residuals_after is None:
        return None
    r = whiten(model, res.residuals_after)[:, :tool]
    if weights is not None:
        r = r * np.sqrt(np.asarray(weights, dtype=float))[:, None]
    if not np.all(np.isfinite(r)):
        return None
    p_eff = res.effective_params
    n_distinct = distinct_rows(model.q, model.y_measured)
    out = {}
    for name, _, cols in GROUPS:
        g = r[:, cols]
        share = g.shape[1] / model.dof
        out[name] = check_noise(float(np.sum(g**2)), n_distinct * g.shape[1] - p_eff * share, stated=True)
    return out


def group_scales(checks: dict[str, NoiseCheck] | None) -> dict[str, float]:
    """The groups to rescale apart and their scales (empty: the whole test's one scale serves)."""
    if not checks:
        return {}
    bad = {name: c.scale for name, c in checks.items() if c.contradicted}
    seen = [math.sqrt(c.reduced) for c in checks.values() if math.isfinite(c.reduced) and c.reduced > 0]
    if not bad or len(seen) < len(checks):
        return {}
    # the groups' own noise estimates must differ by more than DISAGREE: a real arm's position rows at reduced
    # chi-square 0.22 ("overstated") and angle rows at 0.35 ("consistent") are one noise, not two
    if max(seen) <= DISAGREE * min(seen):
        return {}
    return bad


def with_group_scales(model, scales: dict[str, float], minimum: float):
    """``model`` with each named group's sigma multiplied by its scale (at least ``minimum``), the others unchanged."""
    sigma = np.array(model.row_sigma, dtype=float)
    for name, _, cols in GROUPS:
        if name in scales:
            idx = np.arange(model.tool_dof)[cols]
            sigma[:, idx] *= max(float(scales[name]), minimum)
    return model.with_pose_sigma(sigma)


def group_report(block: dict | None) -> str:
    """The report's lines for the answer's ``tool_noise`` block (empty when no group was rescaled)."""
    if not block or not block.get("scale_used"):
        return ""
    lines = []
    for name, key, _ in GROUPS:
        s = block["scale_used"].get(name)
        if s is None:
            continue
        c = block[name]
        lines.append(f"  {name + ' noise':<16}{name} rows alone: reduced chi-square {c['reduced_chi2']:.3g} at the stated "
                     f"{key} ({c['verdict']}); {key} used: {s:.3g} x the stated one (correct [measurement] {key} "
                     "in the machine file: the written file keeps it as stated)")
    return "\n".join(lines)
