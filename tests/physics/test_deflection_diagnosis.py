"""Diagnosis of gravity deflection and gravity-side backlash on recordings made by the independent simulators.

The telescope's column, boom and wrist bend in tests/physics/beam_statics.py
(element by element, no beam formula); the boom's joints play in a stepwise
simulation (tests/physics/test_gravity_backlash.py).  ``bayescal diagnose``
with its whole catalogue must name the effect, and the machine it writes
must predict fresh poses of the simulated truth.
"""

import json
from pathlib import Path

import numpy as np

from bayescal.cli import main
from bayescal.effects import fit_map
from bayescal.effects.stored import predict_poses
from bayescal.geometry import so3_log
from bayescal.io.recording import write_recording
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.measurement import MeasurementModel
from bayescal.simulate import draw_errors, draw_poses, measure
from tests.physics.beam_statics import Member, MimicChain, deflected_tool
from tests.physics.test_gravity_backlash import BOOM, G, stepwise

ROOT = Path(__file__).resolve().parents[2]
TELESCOPE = ROOT / "examples" / "telescope" / "machine.toml"


class BendingStructure:
    """A PoseTransform: the tool of the true machine as the element-by-element statics deflects it."""

    def __init__(self, text, members, mass, com, down):
        self.chain, self.members, self.mass, self.com, self.down = MimicChain.from_text(text), members, mass, com, down

    def transform(self, q, theta, aux, order):
        return q, theta

    def pose_offset(self, q, theta, aux, order):
        out = np.zeros((q.shape[0], 6))
        for i, qq in enumerate(q):
            p0, R0, p1, R1 = deflected_tool(self.chain, qq, self.members, self.mass, self.com, self.down, 0.0, n_elements=30)
            out[i, :3], out[i, 3:] = p1 - p0, so3_log(R1 @ R0.T)
        return out


def _rms_um(a):
    return 1e3 * float(np.sqrt(np.mean(np.sum(a**2, axis=1))))


def test_a_bending_telescope_is_named_and_the_written_machine_predicts_it(tmp_path):
    m = load_machine(TELESCOPE)
    rng = np.random.default_rng(21)
    theta = draw_errors(m, rng)
    truth = m.to_toml(theta)
    mass = np.array([40.0, 25.0, 30.0, 8.0])
    com = np.array([[0.0, 0, 40], [60.0, 0, 10], [110.0, 5, 0], [20.0, 0, 10]])
    a = np.radians(1.5)
    down = np.array([np.sin(a), 0.0, -np.cos(a)])
    b_col, b_arm = 3.0, 6.0  # um/N at 1 m
    structure = BendingStructure(truth, [Member("stage", 0, 1e12 / (3 * b_col)), Member("stage", 1, 1e12 / (3 * b_col)),
                                         Member("link", 2, 1e12 / (3 * b_arm))], mass, com, down)
    q = draw_poses(m, 60, rng, theta)
    rec = measure(m, q, theta, 6, rng, effects=[structure])
    path = tmp_path / "telescope.csv"
    write_recording(path, rec)
    out = tmp_path / "calibrated.toml"
    assert main(["diagnose", str(path), "--machine", str(TELESCOPE), "--quiet", "--json", str(tmp_path / "d.json"),
                 "--write-machine", str(out)]) == 0
    d = json.loads((tmp_path / "d.json").read_text())
    assert d["verdict"] == "gravity_deflection"
    trial = next(e for e in d["effects"] if e["name"] == "gravity_deflection")
    assert {p["name"] for p in trial["parameters"]} >= {"bending.joint1", "bending.link3"}
    # fresh poses of the true machine (bent by the simulator) against the written machine, geometry and table
    fresh = draw_poses(m, 20, np.random.default_rng(5), theta)
    bend = structure.pose_offset(fresh, None, {}, None)[:, :3]
    true_pos = m.forward(fresh, theta).position + bend
    written = load_machine(out)
    assert [e.name for e in written.effects] == ["gravity_deflection"]
    err = _rms_um(predict_poses(written, fresh).position - true_pos)
    size = _rms_um(bend)
    unaware = fit_map(MeasurementModel.from_recording(m, rec)).theta
    err_unaware = _rms_um(m.forward(fresh, unaware).position - true_pos)
    print(f"deflection {size:.0f} um; written machine {err:.1f} um; geometry-only {err_unaware:.1f} um (noise 8.7 um per pose)")
    assert size > 100.0
    assert err < 8.0 and err_unaware > 4 * err


def test_play_on_the_gravity_side_is_named_over_plain_backlash(tmp_path):
    m = machine_from_text(BOOM + "\n[measurement]\nsigma_position = 0.002\nsigma_angle = 2e-5\n", str(tmp_path / "boom.toml"))
    (tmp_path / "boom.toml").write_text(BOOM + "\n[measurement]\nsigma_position = 0.002\nsigma_angle = 2e-5\n")
    rng = np.random.default_rng(3)
    theta = draw_errors(m, rng)
    q = np.column_stack([rng.uniform(-1.2, 1.2, 70), rng.uniform(0.0, 200.0, 70)])
    m1, c1, m2, c2 = 30.0, 0.3, 15.0, 0.05
    h = np.array([5e-5, 0.015])  # rad, mm: a 100 urad band on the boom joint, 30 um on the slider

    def load(y):
        return [G * np.cos(y[0]) * (m1 * c1 + m2 * ((100.0 + y[1]) / 1000 + c2)), m2 * G * np.sin(y[0])]

    lag = stepwise(q, h, np.array([1.0, 10.0]), load, coarse=[0.004, 2.0])

    class Play:
        def transform(self, qq, th, aux, order):
            return qq + lag, th

    rec = measure(m, q, theta, 6, rng, effects=[Play()])
    path = tmp_path / "boom.csv"
    write_recording(path, rec)
    masses = ["--effect-input", "gravity_backlash.link_mass_kg=30,15",
              "--effect-input", "gravity_backlash.link_com_mm=300,0,0,50,0,0"]
    assert main(["diagnose", str(path), "--machine", str(tmp_path / "boom.toml"), "--quiet", "--json",
                 str(tmp_path / "d.json"), "--effects", "backlash,gravity_backlash"] + masses) == 0
    d = json.loads((tmp_path / "d.json").read_text())
    assert d["verdict"] == "gravity_backlash"
    got = {p["name"]: p for p in next(e for e in d["effects"] if e["name"] == "gravity_backlash")["parameters"]}
    assert abs(got["backlash.q1"]["value"] - 2e6 * h[0]) < 4 * got["backlash.q1"]["std"]
    assert abs(got["backlash.q2"]["value"] - 2e3 * h[1]) < 4 * got["backlash.q2"]["std"]
    by_name = {e["name"]: e for e in d["effects"]}
    assert by_name["gravity_backlash"]["rms_after"] < by_name["backlash"]["rms_after"]
