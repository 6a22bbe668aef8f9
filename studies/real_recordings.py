"""The first real recordings end to end: the two-axis positioner and the TIAGo arm (issue #14, items 4-6).

Regenerates every table and figure of ``docs/real-recordings.md`` from the
data alone (seeded; no state carried between runs):

**Positioner** (``examples/positioner/``, converted once from the Apache-2.0
industrial_calibration recording; 205 6-DOF poses in the sensor frame).
The instrument frame is fitted with the geometry (bayescal's ``--frame fit``);
the target mount on the turntable is the tool frame, whose nominal is only
the source's guess, so the machine file gives it tolerances (1 m, 1 rad)
that leave it effectively free.

1. In-sample, every method (``ls``, ``ridge --lam auto``, ``tsvd --k auto``,
   ``map``, ``kalman``, ``mcmc``): mean / RMS / max position and orientation
   errors, and the parameters the data cannot determine (bayescal's
   identifiability analysis), named also as the source's DH parameters.
2. K-fold cross-validation by observation (seeded): held-out errors of
   (a) the nominal machine with only frame and tool fitted, bayescal's
   methods, (b) the independent scipy baselines of
   ``studies/positioner_source.py`` (the source's own cost ``fit_source``,
   static and calibrated DH, and the full-parameter noise-whitened LS
   ``fit_full``), against (c) the source's reported 2020 result.
3. Coverage of the 90 % predictive intervals of MAP (Laplace covariance plus
   the noise estimated from each fold's training residuals) on held-out poses.
4. ``bayescal diagnose --frame fit``.

**TIAGo** (``examples/tiago/``, converted once by ``studies/convert_tiago.py``
from the Apache-2.0 figaroh recording; the chain, ``base_footprint`` to
``wrist_ft_tool_link``, is written from the kinematic parameters of the URDF
figaroh loads, whose file is CC BY-NC-ND and not used).  Frame (mocap frame)
and tool point fitted; leave-one-out and k-fold cross-validation of registration
only, ``ls`` / ``map`` / ``ridge``; an independent registration by scipy;
the rows bayescal flags against those the data's README names; ``diagnose``.

Run::

    python studies/real_recordings.py [--quick] [--out DIR] [--seed 0] [--folds 5]

``--quick`` (used by ``tests/studies/test_real_recordings.py``): ls and map
only, two folds, the scipy full-parameter baseline only (started from the
source's guesses), no diagnosis, a 3-fold TIAGo cross-validation instead of
leave-one-out, one command-line run.
Everything runs from the bundled examples (the positioner's source YAML, for the
independent baselines, is bundled in ``examples/positioner/source/``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "studies"))

from bayescal.io.answers import write_json_atomic, write_text_atomic  # noqa: E402
from bayescal.io.recording import read_recording  # noqa: E402
from bayescal.machines.files import load_machine  # noqa: E402
from bayescal.measurement import MeasurementModel  # noqa: E402

import real_common as rc  # noqa: E402

EXAMPLE = ROOT / "examples" / "positioner"
OUT = ROOT / "studies" / "out" / "real_recordings"
METHODS = ("ls", "ridge", "tsvd", "map", "kalman", "kalman-shuffled", "mcmc")
CV_METHODS = ("ls", "ridge", "tsvd", "map", "kalman", "kalman-shuffled")
FRAME = ("frame.origin.x", "frame.origin.y", "frame.origin.z",
         "frame.rotation_vector.x", "frame.rotation_vector.y", "frame.rotation_vector.z")
TOOL6 = ("tool.point.x", "tool.point.y", "tool.point.z", "tool.rpy.r", "tool.rpy.p", "tool.rpy.y")
#: The source's DH offsets (row ``[d, theta, r, alpha]`` of joint j) as exact combinations of bayescal's serial
#: parameters of the converted chain (studies/convert_positioner.py: joint i's fixed transform is
#: ``Rz(theta_(i-1)) Tx(r_(i-1)) Rx(alpha_(i-1)) Tz(d_i)``, the base offset ``Trans Rx(pi/2)`` for i = 1, so that
#: ``d_1`` moves joint 1's origin along -y and ``alpha_1`` turns joint 2's frame and swings ``d_2 = -475 mm``
#: about x).  ``j2.r`` and ``j2.alpha`` act after the last joint, on the target mount, which is six free
#: parameters in both models: redundant by construction (the source masks them for that reason).
DH_COLUMNS = {
    "j1.d": {"joint1.origin.y": -1.0}, "j1.theta": {"joint1.offset": 1.0},
    "j1.r": {"joint2.origin.x": 1.0}, "j1.alpha": {"joint2.rpy.r": 1.0, "joint2.origin.z": -475.0},
    "j2.d": {"joint2.origin.y": 1.0}, "j2.theta": {"joint2.offset": 1.0},
}
#: PR #79 of robot_cal_tools (2020, Ceres), in-sample, mm and mrad.
SOURCE_REPORTED = {"calibrated DH": (1.745, 3.231), "static DH": (3.824, 5.344)}


def _stamp(msg: str, t0: float) -> None:
    print(f"[{time.time() - t0:7.1f} s] {msg}", flush=True)


# ================================================================ positioner
def positioner(out: Path, *, quick: bool, seed: int, folds: int, t0: float) -> dict:
    machine = load_machine(EXAMPLE / "machine.toml")
    rec = read_recording(EXAMPLE / "recording.csv")
    fm, model = rc.prepare(machine, rec)
    names = fm.layout.names
    result: dict = {"n_poses": rec.n_poses, "in_sample": {}, "cv": {}}

    # ---- 1. in-sample, every method
    thetas = {}
    for method in METHODS if not quick else ("ls", "map"):
        res = rc.fit(model, method, seed=seed, quick=quick)
        pos, ang, _ = rc.pose_errors(model, res.theta)
        row = rc.summary(pos, ang) | {"success": bool(res.success), "n_free": int(np.count_nonzero(res.free))}
        if method == "mcmc":  # how long the chain ran (the sampler's advice followed up to rc.MCMC_MAX_STEPS)
            row |= {"steps": int(res.n_steps), "message": res.message, "acceptance": float(res.acceptance),
                    "max_tau": float(np.max(res.tau))}
            if res.success:  # the chain against importance sampling of the same posterior (no chain to trust)
                result["mcmc_check"] = rc.importance_check(model, res, seed=seed)
        result["in_sample"][method] = row
        thetas[method] = res.theta
        _stamp(f"positioner {method}: {row['pos_mean']:.3f} mm mean, {row.get('ang_mean', 0):.3f} mrad", t0)
        if method == "ls":
            ls = res
    reg = rc.identify(model, method="ls", free=list(FRAME + TOOL6))
    pos, ang, _ = rc.pose_errors(model, reg.theta)
    result["in_sample"]["frame+tool only"] = rc.summary(pos, ang) | {"success": bool(reg.success), "n_free": 12}

    # ---- identifiability: what the data cannot determine, and how poorly the rest is
    std = np.full(len(names), np.nan)
    std[ls.free] = np.sqrt(np.diag(ls.covariance))
    tol = fm.tolerance
    result["fixed"] = list(ls.fixed)
    result["unidentifiable"] = list(ls.unidentifiable)
    result["dh"] = dh_identifiability(model, ls)
    result["ls_parameters"] = [
        {"name": n, "value": float(ls.theta[i]), "std": float(std[i]), "tolerance": float(tol[i])}
        for i, n in enumerate(names) if ls.free[i]
    ]

    # ---- 2./3. k-fold cross-validation by observation
    source = ROOT / "examples" / "positioner" / "source"  # the source YAML, bundled (Apache-2.0)
    src = None
    if (source / "measurements.yaml").is_file():
        import positioner_source as ps

        data = ps.load_positioner(source)
        guesses = ps.load_guesses(source)
        # the recording is the converter's output, row for row (same keys, same order)
        assert np.array_equal(np.array(data.keys, dtype=float), rec.aux["source_key"])
        src = (ps, data, guesses)
    if src is not None:  # the baselines in sample, the noise weights of fit_full from bayescal's ls residuals
        ps, data, guesses = src
        s = rc.noise_estimate(model, ls)
        allidx = np.arange(rec.n_poses)
        start = ps.SourceFit(np.zeros((2, 4)), ps._x6(guesses[0]), ps._x6(guesses[1]), np.nan, 0)
        sols = []
        if not quick:
            start = ps.fit_source(data, guesses)
            sols = [("scipy: source cost, calibrated DH", start), ("scipy: source cost, static DH",
                                                                  ps.fit_source(data, guesses, static_dh=True))]
        sols.append(("scipy: full-parameter LS", ps.fit_full(data, start, sigma_position_mm=float(s[0]),
                                                             sigma_angle=float(s[3]))))
        for key, sol in sols:
            p_, a_ = ps.errors(data, sol.predict(data.q), allidx)
            result["in_sample"][key] = rc.summary(p_, a_) | {"success": True, "n_free": None}
    test_sets = rc.kfold(rec.n_poses, folds, seed)
    held: dict[str, list] = {}
    cover = []
    sig_hat = []

    def add(key, idx, pos, ang):
        held.setdefault(key, []).append((idx, pos, ang))

    for f, te in enumerate(test_sets):
        tr = np.setdiff1d(np.arange(rec.n_poses), te)
        fmf, mtr = rc.prepare(machine, rec.subset(tr))
        mte = MeasurementModel.from_recording(fmf, rec.subset(te))
        r = rc.identify(mtr, method="ls", free=list(FRAME + TOOL6))
        p, a, _ = rc.pose_errors(mte, r.theta)
        add("(a) nominal, frame + tool fitted", te, p, a)
        for method in CV_METHODS if not quick else ("ls", "map"):
            res = rc.fit(mtr, method, seed=seed, quick=quick)
            p, a, _ = rc.pose_errors(mte, res.theta)
            add(f"bayescal {method}", te, p, a)
        # MAP with the noise estimated from this fold's training residuals
        res = rc.fit(mtr, "map")
        s = rc.noise_estimate(mtr, res)
        sig_hat.append(s)
        mtr2 = mtr.with_pose_sigma(np.tile(s, (mtr.n_poses, 1)))
        res2 = rc.identify(mtr2, method="map")
        rr, S = rc.predictive(mtr2, mte, res2, s)
        cover.append((rr, S))
        if src is not None:
            ps, data, guesses = src
            sols = []
            if quick:  # the full-parameter baseline only, started from the source's guesses
                start = ps.SourceFit(np.zeros((2, 4)), ps._x6(guesses[0]), ps._x6(guesses[1]), np.nan, 0)
            else:
                start = ps.fit_source(data, guesses, tr)
                sols = [("(b) source cost, calibrated DH (scipy)", start),
                        ("(b) source cost, static DH (scipy)", ps.fit_source(data, guesses, tr, static_dh=True))]
            ff = ps.fit_full(data, start, tr, sigma_position_mm=float(s[0]), sigma_angle=float(s[3]))
            for key, sol in sols + [("(b) full-parameter LS (scipy)", ff)]:
                p, a = ps.errors(data, sol.predict(data.q[te]), te)
                add(key, te, p, a)
        _stamp(f"positioner fold {f + 1}/{folds}", t0)

    cv = {}
    for key, parts in held.items():
        pos = np.concatenate([p for _, p, _ in parts])
        ang = np.concatenate([a for _, _, a in parts])
        cv[key] = rc.summary(pos, ang)
    result["cv"] = cv
    result["folds"] = folds
    rr = np.concatenate([c[0] for c in cover])
    S = np.concatenate([c[1] for c in cover])
    cov = rc.coverage(rr, S)
    result["coverage"] = {
        "rows_position": cov.rows_position, "rows_angle": cov.rows_angle,
        "poses_position": cov.poses_position, "poses_angle": cov.poses_angle,
        "noise_estimate_per_fold": [[float(s[0]), 1e3 * float(s[3])] for s in sig_hat],
        "std_z_position": float(np.std(cov.z[:, :3])), "std_z_angle": float(np.std(cov.z[:, 3:])),
    }
    _figures_positioner(out, held, cov, rec.n_poses)
    return result


def dh_identifiability(model: MeasurementModel, res) -> dict:
    """Which of the source's DH offsets the data determine: bayescal's analysis on the source's parametrisation.

    Columns in priority order: the instrument frame (6) and the target mount (6), the two transforms of the
    source's model, then the DH offsets as exact combinations of bayescal's columns (:data:`DH_COLUMNS`),
    whitened by the noise, at the LS solution ``res``.
    """
    from bayescal.identifiability import analyse_identifiability
    from bayescal.identify import whitened_system
    from bayescal.params import ParamLayout, ParamSpec

    names = model.machine.layout.names
    _, J = whitened_system(model, res.theta, model.predict(res.theta))
    cols = [J[:, names.index(n)] for n in FRAME + TOOL6]
    specs = [ParamSpec(n, u, "x") for n, u in zip(FRAME + TOOL6, ("mm",) * 3 + ("rad",) * 3 + ("mm",) * 3 + ("rad",) * 3)]
    for dh, combo in DH_COLUMNS.items():
        cols.append(sum(c * J[:, names.index(n)] for n, c in combo.items()))
        specs.append(ParamSpec(f"dh.{dh}", "rad" if dh.endswith(("theta", "alpha")) else "mm", "x"))
    ida = analyse_identifiability(np.column_stack(cols), ParamLayout(tuple(specs)))
    return {"kept": [k for k in ida.kept if k.startswith("dh.")], "fixed": [k for k in ida.fixed if k.startswith("dh.")],
            "combinations": [c for c in ida.combinations if c.startswith("dh.")],
            "by_construction": ["dh.j2.r", "dh.j2.alpha"], "condition_number": float(ida.condition_number)}


def _figures_positioner(out: Path, held: dict, cov, n: int) -> None:
    from bayescal.plots._backend import pyplot, save

    plt = pyplot()
    keys = list(held)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
    for ax, j, label in ((axes[0], 1, "held-out position error (mm)"), (axes[1], 2, "held-out orientation error (mrad)")):
        vals = [np.concatenate([p[j] for p in held[k]]) * (1e3 if j == 2 else 1.0) for k in keys]
        ax.boxplot(vals, orientation="horizontal", tick_labels=[k.replace("bayescal ", "") for k in keys], showfliers=True)
        ax.set_xlabel(label)
        ax.grid(axis="x", alpha=0.3)
    axes[1].set_yticklabels([])
    fig.suptitle(f"Positioner: {len(held[keys[0]])}-fold cross-validation by observation ({n} poses)")
    fig.tight_layout()
    save(fig, out / "positioner_heldout.png")

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    z = cov.z
    bins = np.linspace(-4, 4, 41)
    ax.hist(z[:, :3].ravel(), bins=bins, density=True, alpha=0.6, label="position rows (x, y, z)")
    ax.hist(z[:, 3:].ravel(), bins=bins, density=True, alpha=0.6, label="orientation rows")
    g = np.linspace(-4, 4, 200)
    ax.plot(g, np.exp(-g ** 2 / 2) / np.sqrt(2 * np.pi), "k-", label="N(0, 1)")
    for s in (-rc.Z90, rc.Z90):
        ax.axvline(s, color="k", ls=":")
    ax.set_xlabel("held-out residual / predictive std (MAP Laplace + estimated noise), 1")
    ax.set_ylabel("density, 1")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save(fig, out / "positioner_coverage.png")


# ================================================================ TIAGo
#: The bundled example (studies/convert_tiago.py: the Apache-2.0 recording, and the chain written from the kinematic
#: parameters of tiago_48_schunk.urdf, the URDF figaroh's calibration.py loads; the CC BY-NC-ND URDF is not used).
TIAGO = ROOT / "examples" / "tiago"


def tiago_scipy_registration(rec, n_starts: int = 20) -> dict:
    """Independent registration (frame + tool point) by numpy's 4x4 forward kinematics and scipy, random starts.

    The forward kinematics is ``convert_tiago.forward`` (the chain's table composed with scipy's rotations),
    not bayescal's serial model.
    """
    import convert_tiago as ct
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    T = ct.forward(rec.q)  # wrist_ft_tool_link in base_footprint, mm
    y = rec.position

    def resid(x):
        R = Rotation.from_rotvec(x[3:6]).as_matrix()
        p_base = np.einsum("nij,j->ni", T[:, :3, :3], x[6:9]) + T[:, :3, 3]
        return ((p_base - x[:3]) @ R - y).ravel()  # p_inst = R^T (p_base - o)

    rng = np.random.default_rng(0)
    best = None
    for _ in range(n_starts):
        x0 = np.concatenate([rng.normal(0, 300, 3), Rotation.random(random_state=rng).as_rotvec(), rng.normal(0, 100, 3)])
        sol = least_squares(resid, x0, method="lm", xtol=1e-12, ftol=1e-12)
        if best is None or sol.cost < best.cost:
            best = sol
    e = np.linalg.norm(best.fun.reshape(-1, 3), axis=1)
    return {"rms": float(np.sqrt(np.mean(e ** 2))), "max": float(e.max()), "worst_line": int(np.argmax(e)) + 2,
            "frame_origin_mm": best.x[:3].tolist(), "frame_rotvec": best.x[3:6].tolist(), "tool_mm": best.x[6:].tolist(),
            "per_pose": e}


def tiago(out: Path, *, quick: bool, seed: int, t0: float) -> dict | None:
    machine_path, rec_path = TIAGO / "machine.toml", TIAGO / "recording.csv"
    if not rec_path.is_file():
        print(f"TIAGo example absent ({TIAGO}): skipped")
        return None
    result: dict = {}
    with tempfile.TemporaryDirectory(prefix="bayescal_tiago_") as tmp:
        machine = load_machine(machine_path)
        rec = read_recording(rec_path)
        fm, model = rc.prepare(machine, rec)
        names = fm.layout.names
        TOOL3 = ("tool.point.x", "tool.point.y", "tool.point.z")
        REG = list(FRAME + TOOL3)

        # ---- in sample
        ins = {}
        fits = {}
        # one command (--frame fit: the frame start registers the frame with a tool-point offset, and the
        # tool point, declared unknown by its tolerance, is kept identifiable), and the staged route: the
        # 9-parameter registration first, the full fits started from it (see the docs page)
        reg = rc.fit(model, "registration", free=REG)
        for key, method, free, start in (
            ("registration (frame + tool point)", "registration", REG, None),
            ("map, one command (--frame fit)", "map", "auto", None),
            ("ls", "ls", "auto", reg.theta), ("map", "map", "auto", reg.theta),
            ("ridge --lam auto", "ridge", "auto", reg.theta), ("tsvd --k auto", "tsvd", "auto", reg.theta),
        ):
            res = rc.fit(model, method, free=free, theta0=start, quick=quick)
            pos, _, _ = rc.pose_errors(model, res.theta)
            ins[key] = rc.summary(pos, None) | {"n_free": int(np.count_nonzero(res.free)), "success": bool(res.success),
                                                "message": res.message, "k": getattr(res, "k", None)}
            fits[key] = res
            _stamp(f"tiago {key}: {ins[key]['pos_rms']:.2f} mm RMS", t0)
        result["in_sample"] = ins
        ls = fits["ls"]
        result["ls_unidentifiable_count"] = len(ls.fixed)
        result["ls_free"] = rc.free_names(ls, names)
        sv = ls.singular_values
        result["ls_condition"] = float(sv[0] / sv[-1]) if sv.size else None
        result["ls_message"] = ls.message
        reg = fits["registration (frame + tool point)"]
        frame = fm.frame_at(reg.theta)
        # the machine's tool point lives in the last moving joint's frame (arm_7_link; the fixed joints to
        # wrist_ft_tool_link are folded in): carried back into wrist_ft_tool_link to compare with the README
        import convert_tiago as ct

        tail = ct.folded_chain()[1]
        R_tail, p_tail = tail[:3, :3], tail[:3, 3] * ct.M_TO_MM
        tool_arm7 = fm.inside.tool_point + reg.theta[[names.index(n) for n in TOOL3]]
        result["registration_frame"] = {"origin_mm": frame.origin.tolist(), "rotation_vector": frame.rotation_vector.tolist(),
                                        "tool_mm": (R_tail.T @ (tool_arm7 - p_tail)).tolist()}

        # ---- independent registration
        sc = tiago_scipy_registration(rec, 5 if quick else 20)
        pos_reg, _, _ = rc.pose_errors(model, reg.theta)
        result["scipy_registration"] = {k: v for k, v in sc.items() if k != "per_pose"}
        result["scipy_vs_bayescal_per_pose_max_diff_mm"] = float(np.max(np.abs(sc["per_pose"] - pos_reg)))

        # ---- cross-validation: leave one out (quick: 4 folds)
        test_sets = rc.kfold(rec.n_poses, 3 if quick else rec.n_poses, seed)
        held: dict[str, np.ndarray] = {}
        for te in test_sets:
            tr = np.setdiff1d(np.arange(rec.n_poses), te)
            fmf, mtr = rc.prepare(machine, rec.subset(tr))
            mte = MeasurementModel.from_recording(fmf, rec.subset(te))
            r0 = rc.fit(mtr, "registration", free=REG)
            for key, method, free in (("registration", "registration", REG), ("map", "map", "auto"),
                                      ("tsvd --k auto", "tsvd", "auto")):
                res = r0 if method == "registration" else rc.fit(mtr, method, free=free, theta0=r0.theta, quick=quick)
                p, _, _ = rc.pose_errors(mte, res.theta)
                held.setdefault(key, np.full(rec.n_poses, np.nan))[te] = p
        result["cv"] = {k: rc.summary(v, None) for k, v in held.items()}
        result["cv_kind"] = "3-fold" if quick else "leave-one-out"
        order = np.argsort(-held["registration"])
        result["worst_lines_heldout_registration"] = [[int(i) + 2, float(held["registration"][i])] for i in order[:6]]
        _stamp("tiago cross-validation done", t0)

        # ---- bayescal's outlier screen (docs/formats.md section 4), from the registered machine (no local minimum)
        result["outlier_screen"] = _outlier_screen(fm.to_toml(reg.theta), rec, Path(tmp), REG)
        _stamp("tiago outlier screen done", t0)

        # ---- what bayescal's own commands say: identify (outliers) and diagnose, through the CLI
        cli = {}
        for key, args in (("identify map", ["identify", "--method", "map"]),
                          ("identify tsvd", ["identify", "--method", "tsvd", "--k", "auto"]))[: 1 if quick else 2]:
            cli[key] = _cli_json(args + [str(rec_path), "--machine", str(machine_path), "--frame", "fit"], Path(tmp))
        # the command-line route around the local minimum: register first (frame + tool point, written to a
        # machine file with its [instrument] table), then the full fit from that machine
        reg_toml = Path(tmp) / "registered.toml"
        cli["identify ls, registration only"] = _cli_json(
            ["identify", "--method", "ls", "--free", ",".join(REG), str(rec_path), "--machine", str(machine_path),
             "--frame", "fit", "--write-machine", str(reg_toml)], Path(tmp))
        if reg_toml.is_file():
            cli["identify map, from the registered machine"] = _cli_json(
                ["identify", "--method", "map", str(rec_path), "--machine", str(reg_toml), "--frame", "fit"], Path(tmp))
        if not quick:
            cli["diagnose"] = _cli_json(["diagnose", str(rec_path), "--machine", str(machine_path), "--frame", "fit"], Path(tmp))
        result["cli"] = cli
        _figure_tiago(out, held, sc["per_pose"], result["outlier_screen"])
    return result


def _outlier_screen(registered_toml: str, rec, tmp: Path, reg_free: list[str]) -> dict:
    """The per-pose outlier test of bayescal's robust identification, for registration and MAP."""
    from bayescal.outliers.handling import identify_with_outliers
    from bayescal.outliers import recording_lines

    path = tmp / "registered_lib.toml"
    write_text_atomic(path, registered_toml)
    _, model = rc.prepare(load_machine(path), rec)
    lines = recording_lines(rec.n_poses, rec)
    out = {}
    for key, kw in (("registration", dict(method="ls", free=reg_free)), ("map", dict(method="map"))):
        res, h = identify_with_outliers(model, lines=lines, **kw)
        d = h.to_dict()
        out[key] = {"outliers": [o["line"] for o in d["outliers"]], "handling": d["outlier_handling"],
                    "flagged_before_refit": (d.get("outlier_test") or {}).get("flagged_before_refit", []),
                    "report": h.report().strip()}
    return out


def _cli_json(args: list[str], tmp: Path) -> dict:
    """Run ``python -m bayescal ARGS --json`` and return the answer with the exit code (never raises)."""
    path = tmp / f"answer_{abs(hash(tuple(args)))}.json"
    env = {"PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    proc = subprocess.run([sys.executable, "-m", "bayescal", *args, "--json", str(path), "--quiet"],
                          capture_output=True, text=True, env=env, cwd=ROOT)
    out = {"exit": proc.returncode, "stderr": proc.stderr.strip()[-2000:]}
    if path.is_file():
        answer = json.loads(path.read_text())
        test = answer.get("outlier_test") or {}
        if "flagged_before_refit" in test:
            out["flagged_before_refit"] = test["flagged_before_refit"]
        for k in ("outliers", "outlier_handling", "verdict", "rms_before", "rms_after", "frame", "located", "unidentifiable",
                  "effects", "success", "message"):
            if k in answer:
                out[k] = answer[k]
    return out


def _figure_tiago(out: Path, held: dict, reg_in: np.ndarray, screen: dict) -> None:
    from bayescal.plots._backend import pyplot, save

    plt = pyplot()
    n = reg_in.size
    lines = np.arange(n) + 2
    fig, ax = plt.subplots(figsize=(10, 4.2))
    w = 0.27
    ax.bar(lines - w, reg_in, w, label="registration, in sample (scipy)")
    ax.bar(lines, held["registration"], w, label="registration, held out")
    ax.bar(lines + w, held["map"], w, label="bayescal map, held out")
    flagged = sorted(set(screen.get("registration", {}).get("flagged_before_refit", []))
                     | set(screen.get("registration", {}).get("outliers", [])))
    for ln in flagged:
        ax.axvspan(ln - 0.5, ln + 0.5, color="red", alpha=0.12)
    ax.set_xlabel("CSV line of qualysis_base_hand_calibration.csv (header = 1)")
    ax.set_ylabel("position error (mm)")
    ax.set_title("TIAGo: per-posture position error"
                 + (f"; shaded: lines the outlier test flags after registration ({len(flagged)})" if flagged else ""))
    ax.legend(fontsize=8)
    fig.tight_layout()
    save(fig, out / "tiago_per_line.png")


# ================================================================ tables
def tables(res: dict) -> str:
    """The Markdown tables of the docs page, from the results."""
    out = []
    p = res.get("positioner")
    if p:
        out.append(f"### Positioner: in sample ({p['n_poses']} poses, frame fitted)\n")
        rows = [[k, v["n_free"], v["pos_mean"], v["pos_rms"], v["pos_max"], v["ang_mean"], v["ang_rms"],
                 "yes" if v["success"] else "no"] for k, v in p["in_sample"].items()]
        rows += [[f"source 2020 (PR #79), {k}", "-", m, None, None, a, None, "-"] for k, (m, a) in SOURCE_REPORTED.items()]
        out.append(rc.fmt_table(["method", "free", "pos mean mm", "pos RMS mm", "pos max mm", "ang mean mrad",
                                 "ang RMS mrad", "success"], rows))
        mc = p["in_sample"].get("mcmc")
        if mc:
            out.append(f"\nmcmc: {mc['steps']} steps, acceptance {mc.get('acceptance', float('nan')):.2f}, "
                       f"largest autocorrelation time {mc.get('max_tau', float('nan')):.1f} steps; {mc['message'] or 'converged'}")
        if "mcmc_check" in p:
            k = p["mcmc_check"]
            out.append(f"\nmcmc against importance sampling ({k['draws']} independent draws, ESS {k['ess']:.0f}): marginal "
                       f"means within {k['max_mean_diff_in_std']:.3f} posterior std, stds within "
                       f"{100 * k['max_std_ratio_diff']:.1f} %")
        out.append(f"\n### Positioner: held out ({p['folds']}-fold cross-validation by observation)\n")
        rows = [[k, v["pos_mean"], v["pos_rms"], v["pos_max"], v["ang_mean"], v["ang_rms"]] for k, v in p["cv"].items()]
        rows += [[f"(c) source 2020, {k} (in sample)", m, None, None, a, None] for k, (m, a) in SOURCE_REPORTED.items()]
        out.append(rc.fmt_table(["fit", "pos mean mm", "pos RMS mm", "pos max mm", "ang mean mrad", "ang RMS mrad"], rows))
        c = p["coverage"]
        out.append("\n### Positioner: 90 % predictive intervals of MAP on held-out poses\n")
        out.append(rc.fmt_table(["quantity", "coverage"], [
            ["position rows (x, y, z), per row", c["rows_position"]], ["orientation rows, per row", c["rows_angle"]],
            ["position, 90 % ellipsoid per pose", c["poses_position"]], ["orientation, 90 % ellipsoid per pose", c["poses_angle"]],
            ["std of standardised position residuals", c["std_z_position"]],
            ["std of standardised orientation residuals", c["std_z_angle"]],
        ]))
        out.append("\nnoise estimated per fold (mm, mrad): " + ", ".join(f"({a:.3f}, {b:.3f})" for a, b in c["noise_estimate_per_fold"]))
        d = p["dh"]
        out.append("\n### Positioner: the source's DH offsets (bayescal's identifiability analysis, frame and mount first)\n")
        out.append(f"determined: {', '.join(d['kept'])}; not determined: {', '.join(d['fixed'] + d['by_construction'])}\n")
        out.extend(f"- {c}" for c in d["combinations"])
        out.append("- dh.j2.r, dh.j2.alpha: act on the target mount after the last joint, six free parameters: redundant by construction")
        out.append("\nbayescal's own parameters (ls, frame fitted), identified with std:\n")
        out.append(rc.fmt_table(["parameter", "value", "std", "tolerance"],
                                [[q["name"], q["value"], q["std"], q["tolerance"]] for q in p["ls_parameters"]]))
        out.append("\nfixed at nominal by the analysis of bayescal's own parameters (its words):\n")
        out.extend(f"- {u}" for u in p["unidentifiable"])
        if "diagnose" in p:
            d = p["diagnose"]
            out.append(f"\n### Positioner: diagnose --frame fit\n\nexit {d.get('exit')}, verdict `{d.get('verdict')}`, "
                       f"located {json.dumps(d.get('located'))}")
            for e in d.get("effects", []) or []:
                out.append(f"- {e.get('name')}: detected {e.get('detected')}, evidence {e.get('evidence')}, "
                           f"CV RMS {e.get('rms_before')} -> {e.get('rms_after')} mm")
    t = res.get("tiago")
    if t:
        out.append("\n### TIAGo: in sample (34 postures, position only, frame and tool point fitted)\n")
        # a refused fit (LS on the rank-deficient arm) has no calibration to judge: say so, not its last iterate's errors
        rows = [[k, v["n_free"], v["pos_mean"], v["pos_rms"], v["pos_max"]] if v["success"]
                else [k, v["n_free"], "refused: " + (v.get("message") or "not successful").split(":")[0], None, None]
                for k, v in t["in_sample"].items()]
        s = t["scipy_registration"]
        rows.append(["registration, independent (numpy 4x4 chain + scipy, random starts)", 9, None, s["rms"], s["max"]])
        out.append(rc.fmt_table(["fit", "free", "mean mm", "RMS mm", "max mm"], rows))
        out.append(f"\n### TIAGo: held out ({t['cv_kind']})\n")
        out.append(rc.fmt_table(["fit", "mean mm", "RMS mm", "max mm"],
                                [[k, v["pos_mean"], v["pos_rms"], v["pos_max"]] for k, v in t["cv"].items()]))
        scr = t.get("outlier_screen", {})
        for key in ("registration", "map"):
            if key in scr:
                s_ = scr[key]
                out.append(f"\noutlier screen, {key}: outliers {s_['outliers'] or 'none'}; the unweighted fit's test flags "
                           f"lines {', '.join(map(str, s_['flagged_before_refit'])) or 'none'}\n\n```\n{s_['report']}\n```")
        out.append("\nworst held-out lines (registration): " + ", ".join(f"line {a} ({b:.1f} mm)" for a, b in t["worst_lines_heldout_registration"]))
        for k, v in t["cli"].items():
            o = v.get("outliers")
            flagged = "n/a (this bayescal has no outlier screen)" if o is None else (", ".join(str(x["line"]) for x in o) or "none")
            ra = v.get("rms_after")
            ra = ra.get("position") if isinstance(ra, dict) else ra  # identify: {"position": ...}; diagnose: mm
            if v.get("flagged_before_refit"):
                flagged += "; lines the unweighted fit's test flags: " + ", ".join(str(x) for x in v["flagged_before_refit"])
            if v.get("outlier_handling"):
                flagged += f"; handling: {v['outlier_handling']}"
            out.append(f"\n`{k} --frame fit`: exit {v['exit']}" + (f", RMS after {ra:.2f} mm" if ra is not None else "")
                       + f"; outlier lines: {flagged}"
                       + (f"; verdict `{v.get('verdict')}`" if "verdict" in v else ""))
            if k == "diagnose":
                for e in v.get("effects", []) or []:
                    out.append(f"- {e.get('name')}: detected {e.get('detected')}, evidence {e.get('evidence')}, "
                               f"CV RMS {e.get('rms_before')} -> {e.get('rms_after')} mm")
                if v.get("located"):
                    out.append(f"- located: {json.dumps(v['located'])}")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="ls and map, 2 folds, no diagnosis (the test's mode)")
    ap.add_argument("--out", type=Path, default=OUT, help=f"output folder (default {OUT.relative_to(ROOT)})")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--folds", type=int, help="positioner folds (default 5; 3 with --quick)")
    ap.add_argument("--only", choices=("positioner", "tiago"), help="run one of the two")
    a = ap.parse_args(argv)
    t0 = time.time()
    folds = a.folds or (2 if a.quick else 5)
    res: dict = {"quick": a.quick, "seed": a.seed}
    if a.only in (None, "positioner"):
        res["positioner"] = positioner(a.out, quick=a.quick, seed=a.seed, folds=folds, t0=t0)
        if not a.quick:
            res["positioner"]["diagnose"] = _cli_json(
                ["diagnose", str(EXAMPLE / "recording.csv"), "--machine", str(EXAMPLE / "machine.toml"), "--frame", "fit"],
                Path(tempfile.mkdtemp(prefix="bayescal_pos_")))
            _stamp("positioner diagnose done", t0)
    if a.only in (None, "tiago"):
        t = tiago(a.out, quick=a.quick, seed=a.seed, t0=t0)
        if t is not None:
            res["tiago"] = t
    if not a.quick:  # the docs page shows the figures of the full run
        import shutil

        for png in sorted(a.out.glob("*.png")):
            shutil.copyfile(png, ROOT / "docs" / "figures" / f"real_{png.name}")
    res["seconds"] = time.time() - t0
    write_json_atomic(a.out / "results.json", res)
    text = tables(res)
    write_text_atomic(a.out / "tables.md", text)
    print(text)
    _stamp(f"wrote {a.out}", t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
