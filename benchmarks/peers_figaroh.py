"""Benchmark: bayescal's identification against FIGAROH, the calibration toolbox a robotics user would pick.

FIGAROH (``pip install figaroh``, Apache-2.0; Pinocchio kinematics, scipy's
Levenberg-Marquardt on its own base-parameter set) calibrates serial robots
from measured end-effector poses with an unknown base (measurement) frame
and an unknown marker: the problem of ``bayescal identify --frame fit``.

Problems (6-DOF measurement, base frame and marker unknown):

* ``ur10``: FIGAROH's own real UR10 example (its examples repository,
  ``examples/ur10``: 23 measured poses, ``data/calibration.csv``, the
  URDF ``urdf/ur10_robot.urdf``), read from ``--examples`` (a checkout or
  ``git archive`` of thanhndv212/figaroh-examples; nothing of it is copied
  into this repository);
* ``sim200``, ``sim2000``: the same URDF with every joint placement
  perturbed (0.3 mm, 0.5 mrad per component), an unknown base frame
  (1.7 m away, turned) and marker, 200 and 2,000 poses simulated **with
  Pinocchio** (not with bayescal), noise 0.02 mm and 2e-5 rad, and 500
  fresh poses to judge the answers against the truth.

Contestants, each in its own process, interleaved, ``--repeats`` rounds:

* FIGAROH 1.x ``BaseCalibration`` (``initialize()`` then ``solve()``: its
  regressor-QR parameter selection, LM, its outlier pass), with the
  example's measurement weighting (position 1 per m, orientation 0.5 per
  rad) and no regularisation (FIGAROH 1.0 removed the example's);
* bayescal ``identify(model, method="ls")`` of the recording with the
  instrument frame fitted (``prepare_model(..., frame="fit")``), the same
  weighting (sigma 1 mm and 2 mrad: the ratio of FIGAROH's weights).

Timed: the calibration inside the process, imports and file reading
excluded for both (FIGAROH's ``initialize`` reads the CSV; it is inside
its time); also the process's wall time and peak memory (``ru_maxrss``).
Answers compared by the position RMS on the recording and, for the
simulated problems, the largest and RMS error of the predicted marker
position on the fresh poses against the truth.

Run (the peers live in a separate environment, see ``pyproject.toml``'s
``bench`` extra)::

    python -m venv .venv-bench && .venv-bench/bin/pip install figaroh pin
    python benchmarks/peers_figaroh.py --examples /path/to/figaroh-examples --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "out" / "peers_figaroh"
sys.path.insert(0, str(Path(__file__).resolve().parent))
from peer_child import run_child  # noqa: E402
SIGMA_MM, SIGMA_RAD = 1.0, 0.002  # FIGAROH's example weights position 1 per m and orientation 0.5 per rad

# ------------------------------------------------------------------ run inside the bench environment
FIGAROH_CHILD = r'''
import json, sys, time, numpy as np
a = json.loads(sys.argv[1])
import pinocchio as pin
from figaroh.calibration.base_calibration import BaseCalibration
from figaroh.calibration.calibration_tools import calc_updated_fkm

class Calibration(BaseCalibration):
    """The UR10 example's cost: measured - estimated, weighted 1 per m and 0.5 per rad (no regularisation)."""
    def cost_function(self, var):
        est = calc_updated_fkm(self.model, self.data, var, self.q_measured, self.calib_config)
        return self.apply_measurement_weighting(self.PEE_measured - est, pos_weight=1.0, orient_weight=0.5)

model = pin.buildModelFromUrdf(a["urdf"])
robot = pin.RobotWrapper(model)
t0, c0 = time.perf_counter(), time.process_time()
c = Calibration(robot, a["config"])
c.calib_config["known_baseframe"] = False
c.calib_config["known_tipframe"] = False
c.initialize()
c.solve(plotting=False, enable_logging=False)
t, tc = time.perf_counter() - t0, time.process_time() - c0
out = {"seconds": t, "cpu": tc, "nfev": int(getattr(c.LM_result, "nfev", -1)), "n_params": len(c.calib_config["param_name"]),
       "status": str(c.STATUS)}
def predict(q):
    cfg = dict(c.calib_config, NbSample=len(q))
    pee = calc_updated_fkm(c.model, c.data, c.var_, np.asarray(q, float), cfg).reshape(-1, len(q))
    return pee[:3].T.tolist()
out["fit"] = predict(np.asarray(c.q_measured))
if a.get("fresh_q"):
    out["fresh"] = predict(np.asarray(a["fresh_q"]))
import resource
out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print("RESULT " + json.dumps(out))
'''

SIMULATE_CHILD = r'''
import json, sys, numpy as np
a = json.loads(sys.argv[1])
import pinocchio as pin
rng = np.random.default_rng(a["seed"])
model = pin.buildModelFromUrdf(a["urdf"])
true = model.copy()
for j in range(1, true.njoints):
    err = pin.SE3(pin.exp3(rng.normal(0.0, 5e-4, 3)), rng.normal(0.0, 3e-4, 3))
    true.jointPlacements[j] = true.jointPlacements[j] * err
data = true.createData()
tool = true.getFrameId(a["tip"])
wMo = pin.SE3(pin.rpy.rpyToMatrix(np.array([0.1, -0.2, 1.2])), np.array([1.5, -0.8, 0.4]))
eeMf = pin.SE3(pin.rpy.rpyToMatrix(np.array([0.3, 0.2, -0.1])), np.array([0.05, 0.02, 0.1]))
lo, hi = np.maximum(model.lowerPositionLimit, -np.pi), np.minimum(model.upperPositionLimit, np.pi)
def poses(q, noisy):
    out = []
    for qi in q:
        pin.framesForwardKinematics(true, data, qi)
        M = wMo * data.oMf[tool] * eeMf
        R = M.rotation
        p = M.translation.copy()
        if noisy:
            p += rng.normal(0.0, a["sigma_m"], 3)
            R = R @ pin.exp3(rng.normal(0.0, a["sigma_rad"], 3))
        out.append(list(p) + list(pin.rpy.matrixToRpy(R)))
    return out
q = rng.uniform(lo, hi, (a["n"], model.nq))
fresh = rng.uniform(lo, hi, (500, model.nq))
print("RESULT " + json.dumps({"q": q.tolist(), "y": poses(q, True), "fresh_q": fresh.tolist(),
                              "fresh_p": [p[:3] for p in poses(fresh, False)]}))
'''

BAYESCAL_CHILD = r'''
import json, sys, time, numpy as np
a = json.loads(sys.argv[1])
sys.path.insert(0, a["root"])
from bayescal.identify import identify
from bayescal.instrument import prepare_model
from bayescal.io import read_recording
from bayescal.machines.files import load_machine
machine = load_machine(a["machine"]); rec = read_recording(a["recording"])
t0, c0 = time.perf_counter(), time.process_time()
m2, model, _ = prepare_model(machine, rec, frame="fit")
res = identify(model, method="ls")
t, tc = time.perf_counter() - t0, time.process_time() - c0
out = {"seconds": t, "cpu": tc, "iterations": int(res.iterations), "n_params": int(res.free.sum()), "success": bool(res.success),
       "fit": m2.forward(model.q, res.theta).position.tolist()}
if a.get("fresh_q"):
    out["fresh"] = m2.forward(np.asarray(a["fresh_q"]), res.theta).position.tolist()
import resource
out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print("RESULT " + json.dumps(out))
'''


def _child(python: str, code: str, args: dict, env_root: bool = False) -> dict:
    return run_child(python, code, args, {"PYTHONPATH": str(ROOT)} if env_root else None)


# ------------------------------------------------------------------ the problems
def _rpy_matrix(rpy):
    import numpy as np

    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _write_pair(work: Path, name: str, q, y) -> tuple[Path, Path]:
    """FIGAROH's CSV (m, rpy) and bayescal's recording (mm, rotation vector) of the same poses."""
    import numpy as np

    sys.path.insert(0, str(ROOT))
    from bayescal.geometry import so3_log

    joints = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
              "wrist_3_joint"]
    fig = work / f"{name}_figaroh.csv"
    lines = [",".join(["x1", "y1", "z1", "phix1", "phiy1", "phiz1"] + joints)]
    lines += [",".join(repr(float(v)) for v in list(yi) + list(qi)) for qi, yi in zip(q, y)]
    fig.write_text("\n".join(lines) + "\n")
    rec = work / f"{name}.csv"
    rows = ["q1,q2,q3,q4,q5,q6,x,y,z,rx,ry,rz"]
    for qi, yi in zip(q, y):
        rv = so3_log(_rpy_matrix(yi[3:]))
        rows.append(",".join(repr(float(v)) for v in list(qi) + list(1000.0 * np.asarray(yi[:3])) + list(rv)))
    rec.write_text("\n".join(rows) + "\n")
    return fig, rec


def prepare(examples: Path, work: Path, bench_python: str, sizes) -> dict:
    """Every problem: FIGAROH's config and CSV, bayescal's machine and recording, fresh poses and truth."""
    import numpy as np

    ur10 = examples / "examples" / "ur10"
    urdf = ur10 / "urdf" / "ur10_robot.urdf"
    if not urdf.exists():
        raise SystemExit(f"{urdf}: not found; --examples must hold FIGAROH's examples repository")
    work.mkdir(parents=True, exist_ok=True)
    cfg_dir = work / "config"
    cfg_dir.mkdir(exist_ok=True)
    # FIGAROH 1.x resolves a template's own `extends` against the config's folder: both templates go there
    for t in ("manipulator_robot.yaml", "base_robot_config.yaml"):
        shutil.copy(examples / "examples" / "templates" / t, cfg_dir / t)
    base_cfg = (ur10 / "config" / "ur10_unified_config.yaml").read_text()
    base_cfg = base_cfg.replace('extends: "../../templates/manipulator_robot.yaml"', 'extends: "manipulator_robot.yaml"')
    # FIGAROH 1.0 refuses the example's regularisation (it mixed metres and radians)
    base_cfg = base_cfg.replace("regularization_coefficient: 0.001", "regularization_coefficient: 0.0")
    machine = work / "ur10.toml"
    machine.write_text("\n".join([
        'kind = "serial"', 'name = "UR10 (FIGAROH example URDF)"', f"urdf = {json.dumps(str(urdf))}",
        'base_link = "base_link"', 'tip_link = "wrist_3_link"', "", "[tool]", "point = [0.0, 0.0, 0.0]", "",
        "[measurement]", f"sigma_position = {SIGMA_MM}", f"sigma_angle = {SIGMA_RAD}", "",
        "[tolerance]            # the marker is unknown (FIGAROH fits it from zero too)",
        "tool_point = 1000.0", "tool_rpy = 1.0", ""]))
    problems = {}
    own = (ur10 / "data" / "calibration.csv").read_text().splitlines()
    head = own[0].split(",")
    arr = np.array([[float(v) for v in line.split(",")] for line in own[1:] if line.strip()])
    y, q = arr[:, :6], arr[:, 6:12]
    assert head[6:12] == ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
                          "wrist_2_joint", "wrist_3_joint"], head
    fig, rec = _write_pair(work, "ur10", q, y)
    problems["ur10"] = {"figaroh_csv": fig, "recording": rec, "n": len(q), "fresh_q": None, "fresh_p": None}
    for n in sizes:
        sim = _child(bench_python, SIMULATE_CHILD, {"urdf": str(urdf), "tip": "wrist_3_link", "n": n, "seed": 7,
                                                    "sigma_m": 2e-5, "sigma_rad": 2e-5})
        fig, rec = _write_pair(work, f"sim{n}", sim["q"], sim["y"])
        problems[f"sim{n}"] = {"figaroh_csv": fig, "recording": rec, "n": n, "fresh_q": sim["fresh_q"],
                               "fresh_p": (1000.0 * np.asarray(sim["fresh_p"])).tolist()}
    for name, p in problems.items():
        cfg = base_cfg.replace('source_file: "data/calibration.csv"', f"source_file: {json.dumps(str(p['figaroh_csv']))}")
        cfg = cfg.replace("number_of_samples: 29", f"number_of_samples: {p['n']}")
        path = cfg_dir / f"{name}.yaml"
        path.write_text(cfg)
        p.update(config=path, urdf=urdf, machine=machine)
    return problems


def run(problems: dict, bench_python: str, repeats: int, baseline: Path | None = None) -> dict:
    who_all = ("bayescal", "figaroh") + (("baseline",) if baseline else ())
    todo = [(name, who) for name in problems for who in who_all]
    runs = {k: [] for k in todo}
    for r in range(repeats):
        order = todo[r % len(todo):] + todo[: r % len(todo)]  # interleaved, the order rotated
        for name, who in order:
            p = problems[name]
            if who == "figaroh":
                runs[(name, who)].append(_child(bench_python, FIGAROH_CHILD, {
                    "urdf": str(p["urdf"]), "config": str(p["config"]), "fresh_q": p["fresh_q"]}))
            else:
                root = baseline if who == "baseline" else ROOT
                runs[(name, who)].append(_child(sys.executable, BAYESCAL_CHILD, {
                    "root": str(root), "machine": str(p["machine"]), "recording": str(p["recording"]),
                    "fresh_q": p["fresh_q"]}, env_root=True))
    return runs


def report(problems: dict, runs: dict) -> str:
    import numpy as np

    sys.path.insert(0, str(ROOT))
    from bayescal.io import read_recording

    lines = ["| problem | contestant | time median [s] (range) | CPU median [s] (range) | process wall [s] | peak [MB] | "
             "evaluations | fit RMS [mm] | fresh poses vs truth: max / RMS [mm] | ratio (time) | ratio (CPU) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, p in problems.items():
        meas = read_recording(p["recording"]).position
        med, cpu = {}, {}
        whos = [w for w in ("bayescal", "figaroh", "baseline") if (name, w) in runs]
        for who in whos:
            rs = runs[(name, who)]
            med[who] = statistics.median(x["seconds"] for x in rs)
            cpu[who] = statistics.median(x["cpu"] for x in rs)
        for who in whos:
            rs = runs[(name, who)]
            last = rs[-1]
            fit = np.asarray(last["fit"]) * (1000.0 if who == "figaroh" else 1.0)
            rms = float(np.sqrt(np.mean(np.sum((fit - meas) ** 2, axis=1))))
            acc = "-"
            if p["fresh_p"] is not None:
                f = np.asarray(last["fresh"]) * (1000.0 if who == "figaroh" else 1.0)
                e = np.linalg.norm(f - np.asarray(p["fresh_p"]), axis=1)
                acc = f"{e.max():.3f} / {np.sqrt(np.mean(e**2)):.3f}"
            evals = (f"{last['iterations']} GN iterations" + ("" if last["success"] else ", not converged")
                     if who != "figaroh" else f"{last['nfev']} cost evaluations (last fit), status {last['status']}")
            t = [x["seconds"] for x in rs]
            tc = [x["cpu"] for x in rs]
            lines.append(f"| {name} ({p['n']} poses) | {who} ({last['n_params']} parameters) | {med[who]:.3f} "
                         f"({min(t):.3f}-{max(t):.3f}) | {cpu[who]:.3f} ({min(tc):.3f}-{max(tc):.3f}) | "
                         f"{statistics.median(x['wall'] for x in rs):.2f} | "
                         f"{max(x['peak_mb'] for x in rs):.0f} | {evals} | {rms:.4f} | {acc} | "
                         f"{med[who] / med['bayescal']:.1f}x | {cpu[who] / cpu['bayescal']:.1f}x |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--examples", type=Path, required=True, help="FIGAROH's examples repository (checkout or archive)")
    ap.add_argument("--bench-python", default=str(ROOT / ".venv-bench" / "bin" / "python"),
                    help="python of the environment with figaroh and pin (default .venv-bench)")
    ap.add_argument("--sizes", default="200,2000", help="simulated recordings, poses (default 200,2000)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--baseline", type=Path, default=None,
                    help="another bayescal checkout (e.g. a git worktree of the previous commit), run as a third "
                         "contestant interleaved with the others: the before/after of a change in one run")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    problems = prepare(args.examples, args.out, args.bench_python, sizes)
    load0 = os.getloadavg()[0]
    runs = run(problems, args.bench_python, args.repeats, args.baseline)
    text = (f"FIGAROH against bayescal, {args.repeats} interleaved rounds, load {load0:.2f} at start, "
            f"{os.getloadavg()[0]:.2f} at end, OPENBLAS_NUM_THREADS=1\n\n" + report(problems, runs))
    print(text)
    (args.out / "table.md").write_text(text + "\n")
    (args.out / "runs.json").write_text(json.dumps({f"{k[0]} {k[1]}": [{x: y for x, y in r.items() if x not in ("fit", "fresh")}
                                                                    for r in v] for k, v in runs.items()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
