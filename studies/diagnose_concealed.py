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
Three classes (``phys_*``) come from the independent simulators of
tests/physics, which never call an effect's ``delta_q``: full statics of a
compliant 3-PRS with an unknown platform mass and centre of mass, a tilted
mounting and the payload at the tool; growing screws, links and frame; a
stepwise nut and screw measured in serpentine order (see
:func:`physics_recording`).

For every effect class the machine ``diagnose --write-machine`` would write
is scored against the true geometry (no effect) at fresh poses, beside a
calibration of a clean recording of the same machine (issue 12, item 2;
:func:`calibration_scores`).  The stated targets (:func:`targets`) are
printed PASS / MISS (NOT TESTED when too few recordings fall in the tested
range); the exit code is 1 when any is missed.

Outputs (in --out, default studies/out/diagnose_concealed): results.csv
(one row per recording), summary.md (confusion matrix, accuracy per effect
by size of the effect's out-of-sample contribution, false detections on
clean data, out-of-sample RMS improvement, calibrated machines against the
truth, targets), confusion.png.

Run: python studies/diagnose_concealed.py [--quick] [--out DIR] [--per-class N] [--raspm-per-class N] [--workers 2]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from studies.targets import exit_code, verdict  # noqa: E402

CLASSES = ("none", "joint_compliance", "thermal_expansion", "backlash", "screw_periodic_error", "outside_straightness", "outside_step",
           "raspm_none", "raspm_redundancy_preload", "phys_compliance", "phys_thermal", "phys_backlash")
#: Classes simulated by the independent physics of tests/physics (full statics, growing parts, a stepwise nut and
#: screw), which never call an effect's delta_q.  Appended after the older classes: a case's seed depends on its
#: class's index, so the older classes keep their cases.
PHYS_CLASSES = ("phys_compliance", "phys_thermal", "phys_backlash")
#: Classes simulated on random redundantly actuated 2T1R modules (RASPM) instead of random 3-PRS.
RASPM_CLASSES = ("raspm_none", "raspm_redundancy_preload")
#: The library effect concealed in each class (None: clean or outside the library).
EFFECT_OF = {"joint_compliance": "joint_compliance", "thermal_expansion": "thermal_expansion", "backlash": "backlash",
             "screw_periodic_error": "screw_periodic_error", "raspm_redundancy_preload": "redundancy_preload",
             "phys_compliance": "joint_compliance", "phys_thermal": "thermal_expansion", "phys_backlash": "backlash"}
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
    "phys_compliance": (0.03, 1.0),         # um/N, mean drive compliance
    "phys_thermal": (1.5, 25.0),            # um/m/K, mean screw (and link, frame) expansion coefficient
    "phys_backlash": (2.0, 60.0),           # um, mean dead band
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
    from bayescal.machines.files import machine_from_text

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


def serpentine(machine, q: NDArray, rng: np.random.Generator) -> NDArray:
    """Row order of a raster over the workspace, as an operator plans it: bands along x, y alternating.

    The tool positions of the nominal machine are cut into about
    ``sqrt(n / 4)`` bands along a random horizontal direction; the poses of
    each band are visited along the perpendicular direction, alternately
    forwards and backwards.  Time (warm-up) and approach direction then
    follow the pose instead of being shuffled.
    """
    xy = machine.forward(q).position[:, :2]
    a = rng.uniform(0, np.pi)
    u, v = xy @ np.array([np.cos(a), np.sin(a)]), xy @ np.array([-np.sin(a), np.cos(a)])
    k = max(2, int(round(np.sqrt(len(q) / 4))))
    band = np.minimum((np.argsort(np.argsort(u)) * k) // len(q), k - 1)
    return np.lexsort((np.where(band % 2 == 0, v, -v), band))


def physics_recording(machine, case: dict, rng: np.random.Generator):
    """A recording of a ``phys_*`` class from the independent simulators of tests/physics.

    * ``phys_compliance``: full statics iterated with the forward kinematics
      (``tests/physics/statics_3prs.py``): drive compliances around the
      magnitude (+-40 %), an unknown platform of 20-100 kg with its centre of
      mass up to 80 mm sideways and -150..+50 mm along z of the platform
      frame, the machine mounted tilted by up to 15 degrees in a random
      direction, the payload (0-25 kg, changed between poses; zero when not
      recorded) hanging at the tool point.
    * ``phys_thermal``: growing parts (``tests/physics/thermal_growth.py``):
      screws fixed at either end (a bearing at the base or 50 mm beyond the
      top of the stroke), links and, in half the recordings, the base radii,
      all with coefficients around the magnitude (+-40 %); a warm-up of 2-8 K
      with a 15-50 minute time constant from a start within 1 K of 20 degC
      (the time-only model assumes exactly 20; ``case["start_C"]`` fixes the
      start, the other draws unchanged), 0.02 K sensor noise, 20-40 s
      per pose; half the recordings in serpentine order (``case["sequence"]``,
      a function of the drawn poses, replaces the order, the other draws
      unchanged).
    * ``phys_backlash``: a stepwise nut and screw (``tests/physics/nut_screw.py``)
      with dead bands around the magnitude (+-40 %) and an unknown first
      gap, the poses measured in serpentine order.

    Returns
    -------
    recording, theta_true, info : Recording, ndarray, dict
        ``info["transform"]`` is the simulator's pose transform.
    """
    from bayescal.simulate import draw_errors, draw_poses, measure
    from tests.physics.nut_screw import LostMotion
    from tests.physics.statics_3prs import CompliantDrives, GravityLoad, tilted_down
    from tests.physics.thermal_growth import PartGrowth

    cls, n, mag = case["cls"], case["n"], case["mag"]
    theta = draw_errors(machine, rng)
    q = draw_poses(machine, n, rng, theta)
    per_drive = mag * rng.uniform(0.6, 1.4, machine.n_actuators)
    info = {"serpentine": False}
    aux: dict = {}
    if cls == "phys_compliance":
        mp = rng.uniform(20.0, 100.0)
        com = np.array([*rng.uniform(-80, 80, 2), rng.uniform(-150, 50)])
        down = tilted_down(rng, 15.0)
        mass = rng.choice(np.arange(0.0, 26.0, 5.0), n) if "payload_kg" in case["aux"] else np.zeros(n)
        if "payload_kg" in case["aux"]:
            aux["payload_kg"] = mass
        tilt = float(np.degrees(np.arccos(-down[2])))
        info.update(platform_kg=mp, com_mm=com.tolist(), tilt_deg=tilt)
        transform = CompliantDrives(machine, per_drive, GravityLoad(mp, com, down), mass)
    elif cls == "phys_thermal":
        drawn = q
        if rng.random() < 0.5:
            q = q[serpentine(machine, q, rng)]
            info["serpentine"] = True
        if case.get("sequence") is not None:
            # studies/thermal_information_cost.py: the poses measured in another sequence (a function of the
            # drawn poses, e.g. random order or repeated reference poses); every other draw unchanged
            q = case["sequence"](drawn)
            info["serpentine"] = False
        t = np.cumsum(rng.uniform(20.0, 40.0, n))
        t -= t[0]
        start, rise, tau = 20.0 + rng.uniform(-1.0, 1.0), rng.uniform(2.0, 8.0), rng.uniform(900.0, 3000.0)
        if case.get("start_C") is not None:  # studies/thermal_written_geometry.py: the start known; same draws
            start = float(case["start_C"])
        temp = start + rise * (1.0 - np.exp(-t / tau)) + rng.normal(0.0, 0.02, n)
        a_link = mag * rng.uniform(0.6, 1.4, machine.n_actuators)
        a_frame = mag * rng.uniform(0.6, 1.4) if rng.random() < 0.5 else 0.0
        bearing = np.where(rng.random(machine.n_actuators) < 0.5, 0.0, machine.q_limits[:, 1] + 50.0)
        full = {"time_s": t, "temp_C": temp}
        aux = {c: full[c] for c in case["aux"]}
        info.update(start_C=start, rise_K=rise, tau_s=tau, alpha_frame=a_frame)
        transform = PartGrowth(machine, temp, alpha_screw=per_drive, bearing_mm=bearing, alpha_link=a_link, alpha_frame=a_frame)
    elif cls == "phys_backlash":
        q = q[serpentine(machine, q, rng)]
        info["serpentine"] = True
        full = {"time_s": np.cumsum(rng.uniform(20.0, 40.0, n)), "temp_C": 20.0 + rng.normal(0.0, 0.02, n),
                "payload_kg": np.zeros(n)}  # channels that carry no physics here
        aux = {c: full[c] for c in case["aux"]}
        transform = LostMotion(per_drive, rng)
    else:
        raise ValueError(f"not a physics class: {cls}")
    info["transform"] = transform
    rec = measure(machine, q, theta, case["dof"], rng, aux=aux, effects=[transform])
    return rec, theta, info


def calibration_scores(machine, rec, theta_true: NDArray, diagnosis, seed: int) -> dict:
    """How well calibrations predict the true geometry (no effect) at fresh poses: position RMS, mm.

    * ``cal_written``: the machine ``diagnose --write-machine`` writes
      (:func:`bayescal.diagnose.calibrated.calibrated_machine`), its geometry
      alone;
    * ``cal_geometric``: the geometry-only calibration of the same recording
      (what a calibration that ignores the effect gives);
    * ``cal_clean``: the geometry-only calibration (MAP, as the diagnosis'
      geometric model) of a clean recording of the same machine: the same
      commanded poses and instrument, no effect, fresh noise.

    The fresh poses are 300 new poses within ``q_limits``; RMS of the 3-D
    position error.
    """
    from bayescal.diagnose.calibrated import calibrated_machine
    from bayescal.effects.model import fit_map
    from bayescal.measurement import MeasurementModel
    from bayescal.simulate import draw_poses, measure

    rng = np.random.default_rng([seed, 7])
    clean = measure(machine, rec.q, theta_true, diagnosis.dof, rng, aux=dict(rec.aux))
    theta_clean = fit_map(MeasurementModel.from_recording(machine, clean)).theta
    qf = draw_poses(machine, 300, rng, theta_true)
    truth = machine.forward(qf, theta_true).position

    def rms(pos):
        return float(np.sqrt(np.mean(np.sum((pos - truth) ** 2, axis=1))))

    written = calibrated_machine(machine, diagnosis).machine.with_effects(())
    return {"cal_written": rms(written.forward(qf).position),
            "cal_geometric": rms(machine.forward(qf, diagnosis.theta_geometric).position),
            "cal_clean": rms(machine.forward(qf, theta_clean).position)}


def make_case(cls: str, i: int, seed0: int, n_range=(60, 200)) -> dict:
    rng = np.random.default_rng([seed0, CLASSES.index(cls), i])
    n = int(rng.integers(n_range[0], n_range[1] + 1))
    dof = int(rng.choice([6, 5, 3]))
    mag = None
    if cls in MAGNITUDES:
        lo, hi = MAGNITUDES[cls]
        mag = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    if cls in ("joint_compliance", "phys_compliance"):
        aux = ["payload_kg"] if rng.random() < 0.7 else []
    elif cls in ("thermal_expansion", "phys_thermal"):
        aux = [["temp_C"], ["time_s"], ["time_s", "temp_C"]][int(rng.integers(0, 3))]
    else:
        aux = [c for c in ("time_s", "temp_C", "payload_kg") if rng.random() < 0.4]
    return {"cls": cls, "i": i, "seed": int(rng.integers(0, 2**31)), "n": n, "dof": dof, "mag": mag, "aux": aux,
            "machine": random_raspm_text(rng) if cls in RASPM_CLASSES else random_machine_text(rng)}


def run_case(case: dict) -> dict:
    """Simulate one recording, diagnose it as ``bayescal diagnose`` does, score the verdict and the written machine."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    cpu0 = time.process_time()
    row = _run_case(case)
    row["cpu_seconds"] = time.process_time() - cpu0  # the whole case: simulation, diagnosis, calibration scores
    return row


def _run_case(case: dict) -> dict:
    from bayescal.diagnose import diagnose
    from bayescal.effects.simulate import simulate_with_effects
    from bayescal.machines.files import machine_from_text

    machine = machine_from_text(case["machine"], f"random-{case['cls']}-{case['i']}.toml")
    cls, rng = case["cls"], np.random.default_rng(case["seed"])
    row = {"cls": cls, "i": case["i"], "n_poses": case["n"], "dof": case["dof"], "magnitude": case["mag"],
           "aux": "+".join(case["aux"]), "sigma_position": machine.noise.sigma_position}
    info: dict = {}
    if cls in PHYS_CLASSES:
        rec, theta_true, info = physics_recording(machine, case, rng)
    else:
        effects, extra = [], []
        if cls in EFFECT_OF:
            effects = [(EFFECT_OF[cls], case["mag"])]
        elif cls == "outside_straightness":
            extra = [RailStraightness(machine, case["mag"], rng)]
        elif cls == "outside_step":
            extra = [SuddenStep(machine, case["mag"], rng)]
        sim = simulate_with_effects(machine, case["n"], seed=case["seed"], dof=case["dof"], effects=effects,
                                    record=case["aux"], extra=extra)
        rec, theta_true = sim.recording, sim.theta_true
    row["serpentine"] = bool(info.get("serpentine", False))
    row["tilt_deg"] = float(info.get("tilt_deg", float("nan")))
    nan = float("nan")
    t0 = time.perf_counter()
    try:
        d = diagnose(machine, rec, seed=case["seed"] % 1000, n_perm=case.get("n_perm", 199))
    except Exception as exc:  # a failure is a result of the study, not its end
        return {**row, "verdict": f"error: {type(exc).__name__}", "selected": "", "located": "", "located_significant": False,
                "rms_cv_geometric": nan, "rms_cv_final": nan, "contribution": nan, "p_geometric": nan,
                "seconds": time.perf_counter() - t0, "cal_written": nan, "cal_geometric": nan, "cal_clean": nan,
                "note": f"{type(exc).__name__}: {exc}"}
    secs = time.perf_counter() - t0
    trial = {e.name: e for e in d.effects}
    eff = EFFECT_OF.get(cls)
    true_after = trial[eff].rms_after if eff in trial else float("nan")
    # out-of-sample contribution of the effect: what the true effect model removes from the CV RMS
    # (nan when the true effect was not fitted: skipped as non-physical or failed, see the verdict)
    contrib = float(np.sqrt(max(d.rms_cv_geometric**2 - true_after**2, 0.0))) if eff in trial else float("nan")
    row.update({
        "verdict": d.verdict, "selected": "+".join(d.selected), "located": d.located.channel if d.located else "",
        "located_significant": bool(d.located and d.located.significant),
        "rms_cv_geometric": d.rms_cv_geometric, "rms_cv_final": d.rms_cv_final, "contribution": contrib,
        "p_geometric": d.p_geometric, "seconds": secs,
    })
    scores = {"cal_written": nan, "cal_geometric": nan, "cal_clean": nan}
    if eff is not None:
        try:
            scores = calibration_scores(machine, rec, theta_true, d, case["seed"])
        except Exception as exc:  # noqa: BLE001 - recorded as the study's result
            row["note"] = f"calibration score failed: {type(exc).__name__}: {exc}"
    row.update(scores)
    row.setdefault("note", "")
    return row


def correct(row: dict) -> bool:
    if row["cls"] in ("none", "raspm_none"):
        return row["verdict"] == "none"
    if row["cls"].startswith("outside"):
        return row["verdict"] == "unexplained"
    return row["verdict"] == EFFECT_OF[row["cls"]]


def binomial_se(k: int, n: int) -> float:
    """Standard error of a rate ``k / n`` (binomial; with one success or failure added when ``k`` is 0 or ``n``,
    so that a clean sweep of a small sample is not reported as certain)."""
    p = (k + 0.5 * (k in (0, n))) / (n + (k in (0, n)))
    return float(np.sqrt(p * (1 - p) / n))


#: Issue 12, item 2: the machine diagnose writes predicts the true geometry "about as well as a calibration of
#: a clean recording": here, the median ratio of their fresh-pose position RMS at most this.
CAL_RATIO_TARGET = 1.5


def calibration_table(rows: list[dict]) -> list[str]:
    """Markdown lines: per effect class, fresh-pose RMS against the true geometry of the three calibrations."""
    L = ["", "## Calibrated machines against the true geometry", "",
         "Position RMS (3-D, um) at 300 fresh poses of the true geometry (no effect) predicted by: the machine",
         "`diagnose --write-machine` writes (its geometry), the geometry-only calibration of the same recording, and",
         "the geometry-only calibration of a clean recording of the same machine (same poses, fresh noise).  Medians;",
         "ratio = written / clean per recording; 'right' = recordings with the right verdict.", "",
         "| truth | n | clean | geometry only | written | median ratio written/clean (all; right) | ratio <= 1.5 |",
         "|---|---|---|---|---|---|---|"]
    for c in CLASSES:
        rs = [r for r in rows if r["cls"] == c and c in EFFECT_OF and np.isfinite(r.get("cal_written", np.nan))]
        if not rs:
            continue
        ratio = np.array([r["cal_written"] / r["cal_clean"] for r in rs])
        right = np.array([correct(r) for r in rs])
        med_right = f"{np.median(ratio[right]):.2f}" if right.any() else "-"
        L.append(f"| {c} | {len(rs)} | {1e3 * np.median([r['cal_clean'] for r in rs]):.1f} | "
                 f"{1e3 * np.median([r['cal_geometric'] for r in rs]):.1f} | {1e3 * np.median([r['cal_written'] for r in rs]):.1f} | "
                 f"{np.median(ratio):.2f}; {med_right} | {int(np.sum(ratio <= CAL_RATIO_TARGET))}/{len(rs)} |")
    return L


def targets(rows: list[dict]) -> list[tuple[str, bool | None, str]]:
    """The study's stated targets: (target, met (None: too few recordings to test), the numbers)."""
    out: list[tuple[str, bool | None, str]] = []
    for c in CLASSES:
        rs = [r for r in rows if r["cls"] == c]
        if not rs:
            continue
        if c in EFFECT_OF:
            hi = [r for r in rs if np.isfinite(r["contribution"]) and r["contribution"] >= 2 * r["sigma_position"]]
            k = sum(correct(r) for r in hi)
            met = None if len(hi) < 5 else k >= 0.9 * len(hi)
            out.append((f"{c}: >= 90 % right where the contribution >= 2 sigma (tested from 5 such recordings)", met,
                        f"{k}/{len(hi)}"))
        elif c in ("none", "raspm_none"):
            k = sum(r["verdict"] != "none" for r in rs)
            out.append((f"{c}: <= 5 % not 'none' on clean data", k <= 0.05 * len(rs), f"{k}/{len(rs)}"))
        elif c.startswith("outside"):
            k = sum(correct(r) for r in rs)
            out.append((f"{c}: 'unexplained' in most (> 50 %)", k > 0.5 * len(rs), f"{k}/{len(rs)}"))
        if c in PHYS_CLASSES:
            ok = [r for r in rs if np.isfinite(r.get("cal_written", np.nan))]
            med = float(np.median([r["cal_written"] / r["cal_clean"] for r in ok])) if ok else float("nan")
            out.append((f"{c}: written machine predicts the true geometry about as well as a clean calibration "
                        f"(median ratio <= {CAL_RATIO_TARGET:g})", bool(ok) and med <= CAL_RATIO_TARGET, f"{med:.2f} over {len(ok)}"))
    return out


def targets_text(checks) -> str:
    """PASS / MISS (or NOT TESTED) lines of :func:`targets`."""
    return "\n".join(f"{verdict(m):10s} {name}: {nums}" for name, m, nums in checks) + "\n"


def summarise(rows: list[dict], out: Path) -> str:
    verdicts = list(VERDICTS)
    L = ["# Concealed-effect benchmark of `bayescal diagnose`", ""]
    L.append(f"{len(rows)} recordings; median diagnosis time {np.median([r['seconds'] for r in rows]):.1f} s; "
             f"CPU time {sum(r.get('cpu_seconds', np.nan) for r in rows):.0f} s in all.")
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

        def rate(sel):
            k, n = sum(correct(r) for r in sel), len(sel)
            return f"{k}/{n} ({100 * k / n:.0f} +- {100 * binomial_se(k, n):.0f} %)"

        ratio = [r["contribution"] / r["sigma_position"] if np.isfinite(r["contribution"]) else np.nan for r in rs]
        lo = [r for r, x in zip(rs, ratio) if x < 1]
        mid = [r for r, x in zip(rs, ratio) if 1 <= x < 2]
        hi = [r for r, x in zip(rs, ratio) if x >= 2]
        rms = f"{1e3 * np.median([r['rms_cv_geometric'] for r in rs]):.1f} -> {1e3 * np.median([r['rms_cv_final'] for r in rs]):.1f}"
        if c not in EFFECT_OF:
            L.append(f"| {c} | {rate(rs)} | - | - | - | {rms} |")
        else:
            L.append(f"| {c} | {rate(rs)} | {frac(lo)} | {frac(mid)} | {frac(hi)} | {rms} |")
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
    L += calibration_table(rows)
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
    ap.add_argument("--per-class", type=int, default=None, help="recordings per 3-PRS class (default 15; 1 with --quick)")
    ap.add_argument("--raspm-per-class", type=int, default=None,
                    help="recordings per RASPM class (default 8, about 5x the cost of a 3-PRS recording; 1 with --quick)")
    ap.add_argument("--workers", type=int, default=1, help="dask worker processes (default 1: run in this process)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--classes", default=",".join(CLASSES), help="comma-separated subset of: " + ", ".join(CLASSES))
    ap.add_argument("--resume", action="store_true",
                    help="keep the recordings an interrupted run of the same settings finished (OUT/partial.jsonl)")
    ap.add_argument("--summarise", metavar="CSV", default=None,
                    help="only rewrite the tables and targets from the results.csv of an earlier run (into --out)")
    args = ap.parse_args(argv)
    if args.summarise:
        return write_outputs(read_rows(Path(args.summarise)), Path(args.out), wall=None)
    per = args.per_class or (1 if args.quick else 15)
    per_raspm = args.raspm_per_class or (1 if args.quick else 8)
    n_range = (60, 70) if args.quick else (60, 200)
    classes = [c.strip() for c in args.classes.split(",") if c.strip()]
    bad = [c for c in classes if c not in CLASSES]
    if bad:
        ap.error(f"--classes: unknown {', '.join(bad)}")
    t_start = time.perf_counter()
    cases = [make_case(c, i, args.seed, n_range) for c in classes for i in range(per_raspm if c in RASPM_CLASSES else per)]
    for c in cases:
        c["n_perm"] = 49 if args.quick else 199
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = run_cases(cases, out / "partial.jsonl", workers=args.workers, resume=args.resume)
    wall = time.perf_counter() - t_start
    from bayescal.io import write_text_atomic

    keys = list(rows[0])
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows(rows)
    write_text_atomic(out / "results.csv", buf.getvalue())
    (out / "partial.jsonl").unlink(missing_ok=True)  # the run is complete: results.csv holds every row
    return write_outputs(rows, out, wall)


def _plain(o):
    """numpy scalars as the Python numbers and flags they hold (so a resumed row reads as a fresh one)."""
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not a number or flag: {o!r}")


def _case_key(case: dict) -> str:
    """What makes a finished row reusable: the recording's class, index, seed, size and test permutations."""
    return f"{case['cls']}/{case['i']}/{case['seed']}/{case['n']}/{case['n_perm']}"


def run_cases(cases: list[dict], partial: Path, *, workers: int = 1, resume: bool = False) -> list[dict]:
    """Run every case (progress bar on stderr), appending each finished row to ``partial`` as it comes.

    A killed run loses at most the recordings in progress: ``resume`` reuses the rows of ``partial``
    whose key (:func:`_case_key`) matches a case; without it ``partial`` is started afresh.  Rows are
    returned in the order of ``cases``.
    """
    from tqdm import tqdm

    done: dict[str, dict] = {}
    if resume and partial.exists():
        for line in partial.read_text(encoding="utf-8").splitlines():
            if line.strip():  # a line cut by the kill is not valid JSON; it is run again
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:
                    continue
                done[rec["key"]] = rec["row"]
    keep = {_case_key(c) for c in cases}
    done = {k: r for k, r in done.items() if k in keep}
    todo = [c for c in cases if _case_key(c) not in done]
    with partial.open("w", encoding="utf-8") as fh:  # rewritten: only the reused rows, then each new one
        def record(key: str, row: dict) -> None:
            done[key] = row
            fh.write(json.dumps({"key": key, "row": row}, default=_plain) + "\n")
            fh.flush()
            os.fsync(fh.fileno())

        for k, r in done.items():
            fh.write(json.dumps({"key": k, "row": r}, default=_plain) + "\n")
        bar = tqdm(total=len(cases), initial=len(cases) - len(todo), desc="recordings", unit="rec", file=sys.stderr)
        if workers > 1:
            from dask.distributed import Client, LocalCluster, as_completed

            with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
                    Client(cl) as client:
                futs = {client.submit(run_case, c, pure=False): _case_key(c) for c in todo}
                for f in as_completed(futs):
                    record(futs[f], f.result())
                    bar.update()
        else:
            for c in todo:
                record(_case_key(c), run_case(c))
                bar.update()
        bar.close()
    return [done[_case_key(c)] for c in cases]


def read_rows(path: Path) -> list[dict]:
    """The rows of a results.csv, with numbers and flags as :func:`run_case` returns them."""
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    text_cols = {"cls", "aux", "verdict", "selected", "located", "note"}
    for r in rows:
        for k, v in r.items():
            if k in ("located_significant", "serpentine"):
                r[k] = v == "True"
            elif k in ("i", "n_poses", "dof"):
                r[k] = int(v)
            elif k not in text_cols:
                r[k] = float(v) if v not in ("", "None") else float("nan")
    return rows


def write_outputs(rows: list[dict], out: Path, wall: float | None) -> int:
    """summary.md, confusion.png and the targets (printed); 1 if a target is missed."""
    from bayescal.io import write_text_atomic

    out.mkdir(parents=True, exist_ok=True)
    text = summarise(rows, out)
    if wall is not None:
        text = text.replace("recordings; median", f"recordings, wall time {wall:.0f} s; median", 1)
    checks = targets(rows)
    ttext = targets_text(checks)
    write_text_atomic(out / "summary.md", text + "\n## Targets\n\n```\n" + ttext + "```\n")
    plot_confusion(rows, out / "confusion.png")
    print(text)
    print(ttext)
    return exit_code(m for _, m, _ in checks)


if __name__ == "__main__":
    sys.exit(main())
