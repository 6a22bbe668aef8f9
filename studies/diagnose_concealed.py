"""Study: does `bayescal diagnose` name concealed physics, and stay quiet on clean data?

For every effect of the library that applies to the 3-PRS, for clean data
and for two kinds of physics outside the library (a rail straightness error
quadratic in the slider position; a sudden step of the measured point, as
when a reflector is knocked), simulate recordings on randomly generated
3-PRS machines (radii, link lengths, chain angles, tool offsets, stroke and
instrument noise drawn per recording), with 60-200 poses, 6-, 5- or 3-DOF
measurements, magnitudes log-uniform from barely above the noise to large,
and auxiliary channels present or absent where the effect allows.  Each
recording is diagnosed exactly as `bayescal diagnose` does.  Two further
classes run on random redundantly actuated 2T1R modules (RASPM: rails,
links, platform joints, tool, workspace and noise drawn per recording):
clean, and with a concealed `redundancy_preload` of 20 um to 1.5 mm.

Outputs (in --out, default studies/out/diagnose_concealed): results.csv
(one row per recording), summary.md (confusion matrix, accuracy per effect
by size of the effect's out-of-sample contribution, false detections on
clean data, out-of-sample RMS improvement), confusion.png.

Run: python studies/diagnose_concealed.py [--quick] [--out DIR] [--workers 2]
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CLASSES = ("none", "joint_compliance", "thermal_expansion", "backlash", "screw_periodic_error", "outside_straightness", "outside_step",
           "raspm_none", "raspm_redundancy_preload")
#: Classes simulated on random redundantly actuated 2T1R modules (RASPM) instead of random 3-PRS.
RASPM_CLASSES = ("raspm_none", "raspm_redundancy_preload")
#: The library effect concealed in each class (None: clean or outside the library).
EFFECT_OF = {"joint_compliance": "joint_compliance", "thermal_expansion": "thermal_expansion", "backlash": "backlash",
             "screw_periodic_error": "screw_periodic_error", "raspm_redundancy_preload": "redundancy_preload"}
VERDICTS = ("none", "joint_compliance", "thermal_expansion", "backlash", "screw_periodic_error", "redundancy_preload", "unexplained")
#: Log-uniform magnitude ranges (the effect's magnitude unit).
MAGNITUDES = {
    "joint_compliance": (0.03, 1.0),        # um/N
    "thermal_expansion": (1.5, 25.0),       # um/m/K
    "backlash": (2.0, 60.0),                # um
    "screw_periodic_error": (1.5, 30.0),    # um
    "outside_straightness": (0.02, 0.15),   # mm, deviation at the ends of the stroke
    "outside_step": (0.01, 0.08),           # mm
    # um of actuator deflection c_i P: 20 um (a 200 N preload on 10 N/um) to 1.5 mm (kN on apparent compliances of
    # 0.3 um/N); about 99 % of it is absorbed by the geometry, so only the upper part is visible (docs/diagnose.md)
    "raspm_redundancy_preload": (20.0, 1500.0),
}


def random_machine_text(rng: np.random.Generator) -> str:
    """A 3-PRS machine file with random radii, link length, chain angles, tool offset, stroke and noise."""
    rb, ra = rng.uniform(200, 400), rng.uniform(80, 200)
    link = rng.uniform(max(300.0, (rb - ra) * 1.3), 550.0)
    ang = np.deg2rad(np.array([0.0, 120.0, 240.0]) + rng.uniform(-8, 8, 3) + rng.uniform(0, 360))
    tool = [rng.uniform(-30, 30), rng.uniform(-30, 30), -rng.uniform(40, 220)]
    lo = rng.uniform(300, 500)
    # stroke relative to the platform radius keeps the platform tilt below about 25 degrees (no near-singular poses)
    stroke = rng.uniform(0.3, 0.7) * ra
    sp = rng.uniform(0.002, 0.01)
    lines = ['kind = "3-PRS"', 'name = "random 3-PRS"', ""]
    for a in ang:
        c, s = np.cos(a), np.sin(a)
        lines += [
            "[[chain]]",
            f"rail_origin = [{float(rb * c)!r}, {float(rb * s)!r}, 0.0]",
            "rail_direction = [0.0, 0.0, 1.0]",
            f"revolute_axis = [{float(-s)!r}, {float(c)!r}, 0.0]",
            f"link_length = {float(link)!r}",
            f"sphere_center = [{float(ra * c)!r}, {float(ra * s)!r}, 0.0]",
            "",
        ]
    lines += ["[tool]", f"point = [{float(tool[0])!r}, {float(tool[1])!r}, {float(tool[2])!r}]", ""]
    lines += ["[measurement]", f"sigma_position = {float(sp)!r}", "sigma_angle = 5.0e-5", ""]
    lines += ["[workspace]", "q_limits = [" + ", ".join([f"[{float(lo)!r}, {float(lo + stroke)!r}]"] * 3) + "]", ""]
    return "\n".join(lines)


class RailStraightness:
    """Outside the library: a rail bows sideways, quadratically along the stroke (per-pose geometry)."""

    def __init__(self, machine, amp_mm: float, rng):
        self.lim = machine.q_limits
        self.chain = int(rng.integers(0, 3))
        self.comp = int(rng.integers(0, 2))  # x or y of the rail origin
        self.amp = amp_mm * rng.choice([-1, 1])
        self.index = machine.layout.index(f"chain{self.chain + 1}.rail_origin.{'xy'[self.comp]}")

    def transform(self, q, theta, aux, order):
        lo, hi = self.lim[self.chain]
        u = (q[:, self.chain] - (lo + hi) / 2) / ((hi - lo) / 2)  # -1..1 along the stroke
        th = np.array(theta, dtype=float, copy=True)
        th[:, self.index] += self.amp * (u**2 - 1.0 / 3.0)
        return q, th


class SuddenStep:
    """Outside the library: the measured point jumps once during the session (a knocked reflector)."""

    def __init__(self, machine, amp_mm: float, rng):
        self.at = rng.uniform(0.3, 0.7)
        v = rng.normal(size=3)
        self.step = amp_mm * v / np.linalg.norm(v)
        self.index = [machine.layout.index(f"tool.point.{c}") for c in "xyz"]

    def transform(self, q, theta, aux, order):
        n = q.shape[0]
        th = np.array(theta, dtype=float, copy=True)
        after = np.asarray(order) >= int(self.at * n)
        th[np.ix_(after, self.index)] += self.step
        return q, th


def random_raspm_text(rng: np.random.Generator) -> str:
    """A RASPM-2T1R (the example's topology) with random rails, links, platform joints, tool, workspace and noise.

    Chains 1 and 2 (one slider each) set the rotation, chain 3 (two sliders,
    one platform joint) the translation.  Geometries whose links cannot reach
    some pose of the drawn workspace, or with a near-singular pose, are
    redrawn; ``q_limits`` enclose the strokes the workspace needs.
    """
    from bayescal.machines import machine_from_text

    for _ in range(200):
        xo, xi = rng.uniform(900, 1300), rng.uniform(380, 620)
        lo_, li = rng.uniform(1050, 1350), rng.uniform(850, 1150)
        pj_x, pj_z = float(rng.uniform(330, 560)), -float(rng.uniform(120, 280))
        rail_z = -rng.uniform(900, 1100)
        tilt = rng.uniform(-0.08, 0.08, 4)  # rails up to 5 degrees off vertical
        dirs = [[float(np.sin(t)), 0.0, float(np.cos(t))] for t in tilt]  # plain floats: their repr is TOML
        tool = [rng.uniform(-60, 60), 0.0, -rng.uniform(250, 550)]
        rx, rz, rphi = float(rng.uniform(150, 320)), float(rng.uniform(100, 220)), float(np.deg2rad(rng.uniform(12, 25)))
        sp = float(rng.uniform(0.0008, 0.004))
        rails = [(-xo, -400.0, lo_, dirs[0], 0), (xo, 400.0, lo_, dirs[1], 1), (-xi, 0.0, li, dirs[2], 2), (xi, 0.0, li, dirs[3], 2)]
        pjs = [[-pj_x, -400.0, pj_z], [pj_x, 400.0, pj_z], [0.0, 0.0, 0.0]]
        lines = ['kind = "RASPM-2T1R"', 'name = "random RASPM"', "nonredundant = [1, 3, 4]", ""]
        for c in range(3):
            lines += ["[[chain]]", f"platform_joint = [{pjs[c][0]!r}, {pjs[c][1]!r}, {pjs[c][2]!r}]", ""]
            for x, y, ln, d, ch in rails:
                if ch == c:
                    lines += ["[[chain.slider]]", f"rail_origin = [{float(x)!r}, {y!r}, {float(rail_z)!r}]",
                              f"rail_direction = [{d[0]!r}, 0.0, {d[2]!r}]", f"link_length = {float(ln)!r}", ""]
        lines += ["[tool]", f"point = [{float(tool[0])!r}, 0.0, {float(tool[2])!r}]", ""]
        lines += ["[pose_range]", f"x = [{-rx!r}, {rx!r}]", f"z = [{-rz!r}, {rz!r}]", f"rotation = [{-rphi!r}, {rphi!r}]", ""]
        lines += ["[measurement]", f"sigma_position = {sp!r}", "sigma_angle = 5.0e-6", ""]
        text = "\n".join(lines)
        m = machine_from_text(text, "random-raspm.toml")
        grid = np.stack(np.meshgrid(*[np.linspace(-1, 1, 5)] * 3, indexing="ij"), -1).reshape(-1, 3)
        x = grid * np.array([rx, rz, rphi])
        q, Ja = m.ik_jacobian(x)
        if not np.isfinite(q).all():
            continue
        Js = Ja[:, list(m.nonredundant)] * np.array([1.0, 1.0, 1e-3])  # rotation per 1000 mm: unit-free condition
        if np.linalg.cond(Js).max() > 30.0:
            continue  # a near-singular pose somewhere in the workspace (the example module: 6.6)
        lo, hi = q.min(axis=0) - 5.0, q.max(axis=0) + 5.0
        return text + "[workspace]\nq_limits = [" + ", ".join(f"[{float(a)!r}, {float(b)!r}]" for a, b in zip(lo, hi)) + "]\n"
    raise RuntimeError("no reachable random RASPM in 200 draws")


def make_case(cls: str, i: int, seed0: int, n_range=(60, 200)) -> dict:
    rng = np.random.default_rng([seed0, CLASSES.index(cls), i])
    n = int(rng.integers(n_range[0], n_range[1] + 1))
    dof = int(rng.choice([6, 5, 3]))
    mag = None
    if cls in MAGNITUDES:
        lo, hi = MAGNITUDES[cls]
        mag = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    if cls == "joint_compliance":
        aux = ["payload_kg"] if rng.random() < 0.7 else []
    elif cls == "thermal_expansion":
        aux = [["temp_C"], ["time_s"], ["time_s", "temp_C"]][int(rng.integers(0, 3))]
    else:
        aux = [c for c in ("time_s", "temp_C", "payload_kg") if rng.random() < 0.4]
    return {"cls": cls, "i": i, "seed": int(rng.integers(0, 2**31)), "n": n, "dof": dof, "mag": mag, "aux": aux,
            "machine": random_raspm_text(rng) if cls in RASPM_CLASSES else random_machine_text(rng)}


def run_case(case: dict) -> dict:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import time

    from bayescal.diagnose import diagnose
    from bayescal.effects.simulate import simulate_with_effects
    from bayescal.machines import machine_from_text

    machine = machine_from_text(case["machine"], f"random-{case['cls']}-{case['i']}.toml")
    cls, rng = case["cls"], np.random.default_rng(case["seed"])
    effects, extra = [], []
    if cls in EFFECT_OF:
        effects = [(EFFECT_OF[cls], case["mag"])]
    elif cls == "outside_straightness":
        extra = [RailStraightness(machine, case["mag"], rng)]
    elif cls == "outside_step":
        extra = [SuddenStep(machine, case["mag"], rng)]
    sim = simulate_with_effects(machine, case["n"], seed=case["seed"], dof=case["dof"], effects=effects,
                                record=case["aux"], extra=extra)
    t0 = time.perf_counter()
    try:
        d = diagnose(machine, sim.recording, seed=case["seed"] % 1000, n_perm=case.get("n_perm", 199))
    except Exception as exc:  # a failure is a result of the study, not its end
        return {"cls": cls, "i": case["i"], "n_poses": case["n"], "dof": case["dof"], "magnitude": case["mag"],
                "aux": "+".join(case["aux"]), "sigma_position": machine.noise.sigma_position,
                "verdict": f"error: {type(exc).__name__}", "selected": "", "located": "", "located_significant": False,
                "rms_cv_geometric": float("nan"), "rms_cv_final": float("nan"), "contribution": float("nan"),
                "p_geometric": float("nan"), "seconds": time.perf_counter() - t0}
    secs = time.perf_counter() - t0
    trial = {e.name: e for e in d.effects}
    eff = EFFECT_OF.get(cls)
    true_after = trial[eff].rms_after if eff in trial else float("nan")
    # out-of-sample contribution of the effect: what the true effect model removes from the CV RMS
    # (nan when the true effect was not fitted: skipped as non-physical or failed, see the verdict)
    contrib = float(np.sqrt(max(d.rms_cv_geometric**2 - true_after**2, 0.0))) if eff in trial else float("nan")
    return {
        "cls": cls, "i": case["i"], "n_poses": case["n"], "dof": case["dof"], "magnitude": case["mag"],
        "aux": "+".join(case["aux"]), "sigma_position": machine.noise.sigma_position, "verdict": d.verdict,
        "selected": "+".join(d.selected), "located": d.located.channel if d.located else "",
        "located_significant": bool(d.located and d.located.significant),
        "rms_cv_geometric": d.rms_cv_geometric, "rms_cv_final": d.rms_cv_final, "contribution": contrib,
        "p_geometric": d.p_geometric, "seconds": secs,
    }


def correct(row: dict) -> bool:
    if row["cls"] in ("none", "raspm_none"):
        return row["verdict"] == "none"
    if row["cls"].startswith("outside"):
        return row["verdict"] == "unexplained"
    return row["verdict"] == EFFECT_OF[row["cls"]]


def summarise(rows: list[dict], out: Path) -> str:
    verdicts = list(VERDICTS)
    L = ["# Concealed-effect benchmark of `bayescal diagnose`", ""]
    L.append(f"{len(rows)} recordings; median diagnosis time {np.median([r['seconds'] for r in rows]):.1f} s.")
    L.append("")
    L.append("## Confusion matrix (rows: truth, columns: verdict)")
    L.append("")
    L.append("| truth | n | " + " | ".join(verdicts) + " |")
    L.append("|---|---|" + "---|" * len(verdicts))
    for c in CLASSES:
        rs = [r for r in rows if r["cls"] == c]
        if rs:
            L.append(f"| {c} | {len(rs)} | " + " | ".join(str(sum(r['verdict'] == v for r in rs)) for v in verdicts) + " |")
    L.append("")
    L.append("## Correct verdicts")
    L.append("")
    L.append("Contribution = sqrt(CV RMS(geometric)^2 - CV RMS(geometric + true effect)^2), the effect's out-of-sample")
    L.append("position RMS; 'noise' = the instrument's sigma_position per axis.  Target: >= 90% correct where the")
    L.append("contribution exceeds twice the noise; <= 5% false detections on clean data; 'unexplained' for most outside effects.")
    L.append("")
    L.append("| truth | all | contribution < 1 sigma | 1-2 sigma | >= 2 sigma | median CV RMS before -> after (um) |")
    L.append("|---|---|---|---|---|---|")
    for c in CLASSES:
        rs = [r for r in rows if r["cls"] == c]
        if not rs:
            continue

        def frac(sel):
            return f"{sum(correct(r) for r in sel)}/{len(sel)}" if sel else "-"

        ratio = [r["contribution"] / r["sigma_position"] if np.isfinite(r["contribution"]) else np.nan for r in rs]
        lo = [r for r, x in zip(rs, ratio) if x < 1]
        mid = [r for r, x in zip(rs, ratio) if 1 <= x < 2]
        hi = [r for r, x in zip(rs, ratio) if x >= 2]
        rms = f"{1e3 * np.median([r['rms_cv_geometric'] for r in rs]):.1f} -> {1e3 * np.median([r['rms_cv_final'] for r in rs]):.1f}"
        if c not in EFFECT_OF:
            L.append(f"| {c} | {frac(rs)} | - | - | - | {rms} |")
        else:
            L.append(f"| {c} | {frac(rs)} | {frac(lo)} | {frac(mid)} | {frac(hi)} | {rms} |")
    for cname, label in (("none", "3-PRS"), ("raspm_none", "RASPM")):
        clean = [r for r in rows if r["cls"] == cname]
        if clean:
            fd = sum(r["verdict"] not in ("none",) for r in clean)
            named = sum(r["verdict"] not in ("none", "unexplained") for r in clean)
            L.append("")
            L.append(f"False detections on clean data ({label}): {fd}/{len(clean)} not 'none' ({named} named an effect).")
    mags = [(r["magnitude"], r["contribution"] / r["sigma_position"], correct(r)) for r in rows
            if r["cls"] == "raspm_redundancy_preload" and np.isfinite(r["contribution"])]
    if mags:
        L.append("")
        L.append("RASPM preload: magnitude (um) vs out-of-sample contribution (noise sigmas), correct verdict:")
        L.append("")
        L.append("| magnitude range (um) | n | median contribution / sigma | correct |")
        L.append("|---|---|---|---|")
        for lo, hi in ((0, 100), (100, 300), (300, 700), (700, 1e9)):
            sel = [x for x in mags if lo <= x[0] < hi]
            if sel:
                L.append(f"| {lo:g}-{hi:g} | {len(sel)} | {np.median([x[1] for x in sel]):.2f} | {sum(x[2] for x in sel)}/{len(sel)} |"
                         .replace("-1e+09", "+"))
    text = "\n".join(L) + "\n"
    return text


def plot_confusion(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    verdicts = list(VERDICTS)
    M = np.array([[sum(r["cls"] == c and r["verdict"] == v for r in rows) for v in verdicts] for c in CLASSES], float)
    M /= np.maximum(M.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(7.5, 5))
    ax.imshow(M, cmap="Blues", vmin=0, vmax=1)
    ax.set_xticks(range(len(verdicts)), verdicts, rotation=35, ha="right", fontsize=8)
    ax.set_yticks(range(len(CLASSES)), CLASSES, fontsize=8)
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            if M[i, j] > 0:
                ax.text(j, i, f"{M[i, j]:.2f}", ha="center", va="center", fontsize=7, color="k" if M[i, j] < 0.6 else "w")
    ax.set_xlabel("verdict")
    ax.set_ylabel("truth")
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, path)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="1 recording of 60-70 poses per class (a smoke test)")
    ap.add_argument("--out", default=str(ROOT / "studies" / "out" / "diagnose_concealed"))
    ap.add_argument("--per-class", type=int, default=None, help="recordings per class (default 30; 2 with --quick)")
    ap.add_argument("--workers", type=int, default=1, help="dask worker processes (default 1: run in this process)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--classes", default=",".join(CLASSES), help="comma-separated subset of: " + ", ".join(CLASSES))
    args = ap.parse_args(argv)
    per = args.per_class or (1 if args.quick else 30)
    n_range = (60, 70) if args.quick else (60, 200)
    classes = [c.strip() for c in args.classes.split(",") if c.strip()]
    bad = [c for c in classes if c not in CLASSES]
    if bad:
        ap.error(f"--classes: unknown {', '.join(bad)}")
    cases = [make_case(c, i, args.seed, n_range) for c in classes for i in range(per)]
    for c in cases:
        c["n_perm"] = 49 if args.quick else 199
    if args.workers > 1:
        from dask.distributed import Client, LocalCluster

        with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
                Client(cluster) as client:
            rows = client.gather(client.map(run_case, cases, pure=False))
    else:
        rows = [run_case(c) for c in cases]
    from bayescal.io import write_text_atomic

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    keys = list(rows[0])
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows(rows)
    write_text_atomic(out / "results.csv", buf.getvalue())
    text = summarise(rows, out)
    write_text_atomic(out / "summary.md", text)
    plot_confusion(rows, out / "confusion.png")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
