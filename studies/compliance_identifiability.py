"""What a compliant recording can tell about the geometry "without gravity" (issue 12, joint_compliance).

The constant part of the sag, ``S_i = mean over poses of dq_i``, is exactly an
actuator zero offset; only the pose-dependent part of the sag, tied to the
constant part by the physics (compliance, platform mass, centre of mass,
gravity direction), can tell them apart.  This study measures how well, by
the Laplace (linearised) posterior of the joint model at the truth, on random
3-PRS machines (vertical and inclined rails), tilted mountings, off-centre
platform masses and payloads at the tool:

* ``truth err``: the expected RMS error (um) of the tool point predicted by
  the fitted geometry against the true geometry (without the effect), on 200
  fresh poses: ``sqrt(trace(G Sigma_theta G^T) / n)``, ``G`` the tool
  Jacobian by the geometric errors.  This is what the blind check scores;
* ``sag std``: the posterior one-sigma (um) of the constant sag ``S_i``
  (RMS over the drives).

Priors (columns): ``geometry only`` = a clean recording's calibration (the
yardstick); ``unknown`` = the effect's default priors (mass, centre of mass
and tilt unknown); ``mass`` = platform mass stated (2 %); ``stated`` = mass,
centre of mass and gravity direction stated; ``flat`` = no prior on the
effect's parameters at all (what the data alone determine); ``flat/10``
the same at a tenth of the noise (an error falling tenfold means the split
is determined in principle and limited by the noise only).

A second table fits full-statics recordings (tests/physics/statics_3prs.py)
as the diagnosis does and compares the realized truth error with the
uncertainty the diagnosis reports (:mod:`bayescal.diagnose.confound`).

Run: ``PYTHONPATH=. python studies/compliance_identifiability.py [--quick]``.
Prints the table; exits 0 (a measurement, no targets).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bayescal.effects import get_effect  # noqa: E402
from bayescal.effects.joint_compliance import GRAVITY  # noqa: E402
from bayescal.machines.files import machine_from_text  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402
from bayescal.simulate import draw_poses  # noqa: E402
from tests.physics.statics_3prs import random_prs3_text, tilted_down  # noqa: E402

PRIORS = ("unknown", "mass", "stated", "flat", "flat/10")


def _truth_eta(eff, machine, f, c, mp, com, down):
    """The effect's parameters of the physics (names from ``eff.params``)."""
    d0 = eff.down
    keep = [i for i in range(3) if i != int(np.argmax(np.abs(d0)))]
    e = np.eye(3)[keep] - np.outer(np.eye(3)[keep] @ d0, d0)
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    tilt = e @ (down / (down @ d0))
    val = {f"compliance.q{i + 1}": c[i] for i in range(3)} | {"platform_mass": mp}
    val |= {f"weight_deflection.q{i + 1}": c[i] * mp * GRAVITY for i in range(3)}
    val |= {"com.x": com[0], "com.y": com[1], "com.z": com[2], "gravity.tilt_1": tilt[0], "gravity.tilt_2": tilt[1]}
    return np.array([val[p.name] for p in eff.params(machine, f)])


def linearised(machine, theta, q, aux, eff, eta):
    """Whitened Jacobian of the joint model at the truth, its column scales, and d S / d eta.

    Returns
    -------
    J : ndarray (rows, P + K)
        ``d h / d (theta, eta)`` divided by the row sigmas (unscaled columns).
    scale : ndarray (P + K,)
        Prior sigmas (tolerances, then the effect's prior sds).
    mean : ndarray (P + K,)
        Prior means.
    dS : ndarray (m, K)
        Derivative of the constant sag ``S_i = mean_n dq_i`` (mm) by ``eta``.
    """
    model = MeasurementModel(machine, q, dof=6, aux=aux)
    f = eff.features(machine, q, theta, aux, None, machine.forward(q, theta))
    params = eff.params(machine, f)
    sub = replace(model, q=q + eff.delta_q(f, eta))
    pred = sub.predict(theta)
    Jg = sub.jacobian(theta, pred)
    Jq = sub.rows_jacobian(machine.actuator_jacobian(sub.q, theta, pred.poses), pred)
    dqj = eff.delta_q_jacobian(f, eta)
    Je = np.einsum("ndm,nmk->ndk", Jq, dqj)
    J = (np.concatenate([Jg, Je], axis=2) / sub.row_sigma[:, :, None]).reshape(-1, machine.n_params + len(params))
    scale = np.concatenate([machine.tolerance, [p.prior_sd for p in params]])
    mean = np.concatenate([np.zeros(machine.n_params), [p.prior_mean for p in params]])
    return J, scale, mean, dqj.mean(axis=0)


def posterior(J, scale, P, flat=False):
    """Posterior covariance (unscaled) of ``(theta, eta)``; ``flat``: no prior on ``eta``."""
    A = J * scale
    prior = np.ones(A.shape[1])
    if flat:
        prior[P:] = 1e-10
    cov = np.linalg.inv(A.T @ A + np.diag(prior))
    return cov * np.outer(scale, scale)


def truth_error_um(machine, theta, qf, cov_theta):
    """Expected RMS (um) of the tool point of a geometry with covariance ``cov_theta``, on poses ``qf``."""
    G = machine.tool_jacobian(qf, theta, machine.forward(qf, theta))[:, :3, :].reshape(-1, machine.n_params)
    return 1e3 * float(np.sqrt(np.einsum("ij,jk,ik->", G, cov_theta, G) / qf.shape[0]))


def one_case(seed, *, incline, payload, n):
    rng = np.random.default_rng(seed)
    machine = machine_from_text(random_prs3_text(rng, incline_deg=incline), f"random-{seed}.toml")
    theta = rng.normal(size=machine.n_params) * machine.tolerance
    q = draw_poses(machine, n, rng, theta)
    qf = draw_poses(machine, 200, np.random.default_rng(seed + 1000), theta)
    down = tilted_down(rng, 15.0)
    com = np.array([*rng.uniform(-80, 80, 2), rng.uniform(-150, 50)])
    mp = rng.uniform(20, 100)
    c = rng.uniform(0.2, 1.0, 3)
    aux = {"payload_kg": rng.choice(np.arange(0.0, 26.0, 5.0), n)} if payload else {}
    P = machine.n_params
    out = {}
    # the yardstick: geometry only on a clean recording

    model = MeasurementModel(machine, q, dof=6, aux=aux)
    pred = model.predict(theta)
    Jg = (model.jacobian(theta, pred) / model.row_sigma[:, :, None]).reshape(-1, P)
    cov0 = np.linalg.inv((Jg * machine.tolerance).T @ (Jg * machine.tolerance) + np.eye(P)) * np.outer(machine.tolerance, machine.tolerance)
    out["geometry only"] = (truth_error_um(machine, theta, qf, cov0), np.nan)
    for prior in PRIORS:
        settings = {}
        if prior in ("mass", "stated"):
            settings["platform_mass_kg"] = mp
        if prior == "stated":
            settings |= {"platform_com_mm": com, "gravity": down}
        eff = get_effect("joint_compliance", **settings)
        f = eff.features(machine, q, theta, aux, None, machine.forward(q, theta))
        eta = _truth_eta(eff, machine, f, c, mp, com, down)
        J, scale, _, dS = linearised(machine, theta, q, aux, eff, eta)
        if prior == "flat/10":
            J = 10.0 * J  # a tenth of the noise: shows whether the data determine the split in principle
        cov = posterior(J, scale, P, flat=prior.startswith("flat"))
        # the constant sag S_i = mean_n dq_i, linear in eta at the truth
        vS = np.einsum("ij,jk,ik->i", dS, cov[P:, P:], dS)
        out[prior] = (truth_error_um(machine, theta, qf, cov[:P, :P]), 1e3 * float(np.sqrt(np.mean(vS))))
    return out


def realized_case(seed, *, incline, n=160):
    """Fit a full-statics recording (tests/physics) like diagnose does; truth error and reported std, um."""
    from bayescal.diagnose.confound import geometry_confound
    from bayescal.effects import fit_map
    from bayescal.simulate import measure
    from tests.physics.statics_3prs import CompliantDrives, GravityLoad

    rng = np.random.default_rng(seed)
    machine = machine_from_text(random_prs3_text(rng, incline_deg=incline), f"random-{seed}.toml")
    theta = rng.normal(size=machine.n_params) * machine.tolerance
    q = draw_poses(machine, n, rng, theta)
    down = tilted_down(rng, 15.0)
    com = np.array([*rng.uniform(-80, 80, 2), rng.uniform(-150, 50)])
    mp = rng.uniform(20, 100)
    c = rng.uniform(0.2, 1.0, 3)
    mass = rng.choice(np.arange(0.0, 26.0, 5.0), n)
    rec = measure(machine, q, theta, 6, rng, aux={"payload_kg": mass},
                  effects=[CompliantDrives(machine, c, GravityLoad(mp, com, down), mass)])
    model = MeasurementModel.from_recording(machine, rec)
    qf = draw_poses(machine, 200, np.random.default_rng(seed + 1000), theta)
    truth = machine.forward(qf, theta).position
    fit0 = fit_map(model)
    out = {}
    for prior in ("unknown", "stated"):
        settings = {"platform_mass_kg": mp, "platform_com_mm": com, "gravity": down} if prior == "stated" else {}
        eff = get_effect("joint_compliance", **settings)
        f = eff.features(machine, model.q, fit0.theta, dict(rec.aux), None, model.predict(fit0.theta).poses)
        fit = fit_map(model, [(eff, f)], theta0=fit0.theta)
        conf = geometry_confound(machine, model.q, fit, fit0, [eff])
        err = 1e3 * float(np.sqrt(np.mean(np.sum((machine.forward(qf, fit.theta).position - truth) ** 2, axis=1))))
        out[prior] = (err, conf.tool_std_um)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    seeds = range(3) if args.quick else range(8)
    cols = ("geometry only",) + PRIORS
    print("truth err um (RMS over fresh poses), sag std um; mean over seeds")
    print(f"{'rails':10s} {'payload':8s} {'n':>5s} | " + " | ".join(f"{c:>13s}" for c in cols))
    for incline in (0.0, 25.0):
        for payload in (True, False):
            for n in ((160,) if args.quick else (160, 1000)):
                rows = [one_case(s, incline=incline, payload=payload, n=n) for s in seeds]
                cells = []
                for c in cols:
                    v = np.array([r[c] for r in rows])
                    cells.append(f"{np.mean(v[:, 0]):6.1f} {np.mean(v[:, 1]):6.1f}" if c != "geometry only" else f"{np.mean(v[:, 0]):6.1f}")
                rails = "vertical" if incline == 0 else f"incl {incline:g}"
                print(f"{rails:10s} {str(payload):8s} {n:5d} | " + " | ".join(f"{c:>13s}" for c in cells), flush=True)
    print()
    print("realized: joint fit of full-statics recordings (160 poses, payload), truth error vs the reported std (um)")
    for incline in (0.0, 25.0):
        rows = [realized_case(100 + s, incline=incline) for s in seeds]
        for prior in ("unknown", "stated"):
            e = np.array([r[prior] for r in rows])
            ratio = e[:, 0] / e[:, 1]
            rails = "vertical" if incline == 0 else f"incl {incline:g}"
            print(f"{rails:10s} {prior:8s}: error {np.mean(e[:, 0]):6.1f} (max {np.max(e[:, 0]):6.1f}), reported "
                  f"{np.mean(e[:, 1]):6.1f}; error / reported: median {np.median(ratio):.2f}, max {np.max(ratio):.2f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
