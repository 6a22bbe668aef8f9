"""Shared pieces of ``studies/real_recordings.py``: folds, fits, held-out errors, predictive coverage.

Everything here goes through bayescal's measurement model and its
identification methods; the independent baselines live in
``studies/positioner_source.py`` (positioner) and in ``real_recordings.py``
(TIAGo registration).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import chi2, norm

from bayescal.errors import ConvergenceWarning
from bayescal.identify import identify
from bayescal.identify.choose import choose_regularisation
from bayescal.io.recording import Recording
from bayescal.machines.base import Machine
from bayescal.measurement import MeasurementModel

ROOT = Path(__file__).resolve().parents[1]
#: ../shared beside the checkout (<clone>/../shared), or two levels up for a git worktree.
SHARED = next(
    (p / "shared" / "data" / "real" for p in (ROOT.parent, ROOT.parent.parent) if (p / "shared" / "data" / "real").is_dir()),
    ROOT.parent / "shared" / "data" / "real",
)

Z90 = float(norm.ppf(0.95))  # two-sided 90 % interval of one row: |r| <= 1.645 sd


def prepare(machine: Machine, rec: Recording, frame: str = "fit") -> tuple[Machine, MeasurementModel]:
    """The machine and model of ``rec`` with its instrument frame fitted (bayescal's ``--frame fit``)."""
    from bayescal.instrument import prepare_model

    m, model, _ = prepare_model(machine, rec, frame=frame)
    return m, model


def kfold(n: int, k: int, seed: int) -> list[np.ndarray]:
    """``k`` disjoint test sets covering ``range(n)``, seeded shuffle (k = n: leave one out)."""
    perm = np.random.default_rng(seed).permutation(n)
    return [np.sort(f) for f in np.array_split(perm, k)]


def fit(model: MeasurementModel, method: str, *, free="auto", seed: int = 0, quick: bool = False, theta0=None):
    """One identification with bayescal; returns the result object (``theta``, ``free``, ...).

    Warnings bayescal raises (a diverged or unconverged fit) are kept on the
    result's ``success`` / ``message``, not raised: the study reports them.
    ``theta0`` starts the deterministic methods (ls, ridge, tsvd, map) there.
    """
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return _fit(model, method, free=free, seed=seed, quick=quick, theta0=theta0)


#: The longest chain the studies run when the sampler asks for more steps (steps per walker).
MCMC_MAX_STEPS = 6000
#: Resumed runs at most, after the first.
MCMC_MAX_PASSES = 4


def _fit(model, method, *, free, seed, quick, theta0):
    if method in ("ridge", "tsvd"):
        # --quick (the tests' mode): the targets rule's calibration coarse, 30 data sets per scale, 200 draws
        calibration = {"n_data": 30, "n_draws": 200} if quick else None
        return choose_regularisation(model, method, free=free, theta0=theta0, target_calibration=calibration)[1]
    if method in ("ls", "map"):
        return identify(model, method=method, free=free, theta0=theta0)
    if method == "registration":  # frame and tool only: the nominal machine placed and its tool point found
        return identify(model, method="ls", free=free, theta0=theta0)
    if method in ("kalman", "kalman-shuffled"):
        from bayescal.bayes.kalman import kalman_filter

        if method == "kalman-shuffled":  # the same filter over the poses in a seeded random order
            model = model.subset(np.random.default_rng(seed).permutation(model.n_poses))
        return kalman_filter(model, free=free)
    if method == "mcmc":
        import tempfile

        from bayescal.bayes.mcmc import sample_posterior

        steps = 300 if quick else 1500
        with tempfile.TemporaryDirectory() as tmp:
            ck = Path(tmp) / "chain.npz"
            res = sample_posterior(model, free=free, n_steps=steps, seed=seed, progress=False, checkpoint=ck)
            # the sampler's own advice, followed as a user would (--resume: the same draws as one longer run),
            # up to MCMC_MAX_STEPS; each pass at least a quarter longer (the ESS check can ask for a few steps,
            # and every pass repeats the MAP start and the summaries); quick mode stops at 300
            for _ in range(MCMC_MAX_PASSES):
                if quick or res.success or res.more_steps <= 0 or res.n_steps >= MCMC_MAX_STEPS:
                    break
                steps = min(res.n_steps + max(res.more_steps, res.n_steps // 4), MCMC_MAX_STEPS)
                res = sample_posterior(model, free=free, n_steps=steps, seed=seed, progress=False, checkpoint=ck,
                                       resume=True)
        return res
    raise ValueError(method)


def importance_check(model: MeasurementModel, res, *, draws: int = 30000, seed: int = 0) -> dict:
    """The MCMC posterior against self-normalised importance sampling of the same posterior.

    Importance sampling draws independently from a t with heavier tails
    (5 degrees of freedom, scale 1.2) than the sampler's own proposal,
    pushed through the same bent Laplace map, and weights every draw by the
    exact log posterior: no Markov chain, so no mixing to trust.  Returns
    its effective sample size and the largest differences of the marginal
    means (in posterior std) and stds (relative) from the chain's.
    """
    from bayescal.bayes.mcmc import log_posterior_function
    from bayescal.bayes.moves import IndependenceMove
    from bayescal.bayes.priors import prior_from_machine

    bend = res.bend  # the sampler's own bent Laplace map at its MAP
    idx = np.flatnonzero(res.free)
    lp = log_posterior_function(model, prior_from_machine(model.machine), idx,
                                guess=model.predict(res.theta_map).poses)
    g = IndependenceMove(bend.x0, bend.basis @ bend.basis.T, df=5.0, scale=1.2, bend=bend)
    rs = np.random.RandomState(seed)
    chunk = 2000
    X = np.vstack([g.draw(chunk, rs) for _ in range(-(-draws // chunk))])
    lw = np.concatenate([lp(X[i:i + chunk])[:, 0] for i in range(0, len(X), chunk)]) - g.log_density(X)
    w = np.exp(lw - lw.max())
    w /= w.sum()
    mean = w @ X
    std = np.sqrt(w @ (X - mean) ** 2)
    S = res.samples
    return {"draws": int(len(X)), "ess": float(1.0 / np.sum(w**2)),
            "max_mean_diff_in_std": float(np.max(np.abs(S.mean(axis=0) - mean) / std)),
            "max_std_ratio_diff": float(np.max(np.abs(S.std(axis=0) / std - 1.0)))}


def pose_errors(model: MeasurementModel, theta) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Per-pose position error norm (mm), orientation error angle (rad, 6-DOF) and the residual rows."""
    r = model.residual(model.predict(theta))
    pos = np.linalg.norm(r[:, :3], axis=1)
    ang = np.linalg.norm(r[:, 3:], axis=1) if model.dof == 6 else None
    return pos, ang, r


def summary(pos: np.ndarray, ang: np.ndarray | None) -> dict:
    """Mean, RMS and max of per-pose errors (mm; mrad)."""
    out = {"pos_mean": float(pos.mean()), "pos_rms": float(np.sqrt(np.mean(pos ** 2))), "pos_max": float(pos.max())}
    if ang is not None:
        out.update(ang_mean=1e3 * float(ang.mean()), ang_rms=1e3 * float(np.sqrt(np.mean(ang ** 2))),
                   ang_max=1e3 * float(ang.max()))
    return out


def noise_estimate(model: MeasurementModel, res) -> np.ndarray:
    """Noise per row of a pose (dof,) from training residuals: position and angle rows separately.

    Each group's sum of squares is divided by its rows less its share of the
    fitted parameters (shared in proportion to the rows), the unbiased
    estimate for a linear model.
    """
    r = res.residuals_after
    n, dof = r.shape
    p = int(np.count_nonzero(res.free))
    s = np.empty(dof)
    s[:3] = np.sqrt(np.sum(r[:, :3] ** 2) / (3 * n - p * 3 / dof))
    if dof > 3:
        s[3:] = np.sqrt(np.sum(r[:, 3:] ** 2) / ((dof - 3) * n - p * (dof - 3) / dof))
    return s


@dataclass(frozen=True)
class Coverage:
    """Held-out coverage of the 90 % predictive intervals (fractions)."""

    rows_position: float  # per axis x, y, z
    rows_angle: float | None
    poses_position: float  # the 90 % ellipsoid of the 3 position rows
    poses_angle: float | None
    z: np.ndarray  # standardised held-out residual rows (n, dof)


def predictive(train: MeasurementModel, test: MeasurementModel, res, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Held-out residual rows and their predictive covariance ``J C J^T + diag(sigma^2)`` per pose.

    ``C`` is the result's covariance of its free parameters (the Laplace
    covariance for MAP) and ``sigma`` the noise per row.
    """
    pred = test.predict(res.theta)
    r = test.residual(pred)
    J = test.jacobian(res.theta, pred)[:, :, res.free]  # (n, dof, p)
    S = np.einsum("nip,pq,njq->nij", J, res.covariance, J) + np.diag(sigma ** 2)[None]
    return r, S


def coverage(r: np.ndarray, S: np.ndarray) -> Coverage:
    """Fractions of held-out rows / poses inside the 90 % predictive intervals."""
    dof = r.shape[1]
    sd = np.sqrt(np.einsum("nii->ni", S))
    z = r / sd
    inside = np.abs(z) <= Z90
    Sp = S[:, :3, :3]
    m_pos = np.einsum("ni,nij,nj->n", r[:, :3], np.linalg.inv(Sp), r[:, :3])
    pose_pos = float(np.mean(m_pos <= chi2.ppf(0.9, 3)))
    rows_ang = pose_ang = None
    if dof == 6:
        Sa = S[:, 3:, 3:]
        m_ang = np.einsum("ni,nij,nj->n", r[:, 3:], np.linalg.inv(Sa), r[:, 3:])
        pose_ang = float(np.mean(m_ang <= chi2.ppf(0.9, 3)))
        rows_ang = float(inside[:, 3:].mean())
    return Coverage(float(inside[:, :3].mean()), rows_ang, pose_pos, pose_ang, z)


def free_names(res, names) -> list[str]:
    return [n for n, f in zip(names, res.free) if f]


def fmt_table(header: list[str], rows: list[list]) -> str:
    """A Markdown table; floats to 3 significant decimals."""
    def cell(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)
