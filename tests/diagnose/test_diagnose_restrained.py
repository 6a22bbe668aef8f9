"""bayescal diagnose on RASPM recordings of the true restrained physics (independent of the effect's delta_q)."""

import numpy as np
import pytest

from bayescal.diagnose import diagnose
from bayescal.diagnose.calibrated import calibrated_machine
from bayescal.effects.stored import predict_poses
from bayescal.machines.files import load_machine
from bayescal.redundant.physics import solve_restrained
from bayescal.redundant.restrained_recording import restrained_recording
from bayescal.io.recording import Recording
from tests.conftest import ROOT

RASPM = ROOT / "examples" / "raspm" / "machine.toml"


def _rms(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


@pytest.mark.parametrize("seed, offset", [(11, 0.05), (12, 0.5)])
def test_restrained_recording_named_and_its_calibrated_machine_predicts(seed, offset):
    m = load_machine(RASPM)
    sim = restrained_recording(m, 60, seed, offset_mm=offset)
    d = diagnose(m, sim.recording, seed=1, effects=["redundancy_preload"])
    assert d.verdict == "redundancy_preload", (d.verdict, d.message)
    pre = next(e for e in d.effects if e.name == "redundancy_preload")
    assert {p.name for p in pre.parameters} >= {"compliance_ratio.q1", "offset.q2", "redundant.chain2_slider1_link_length"}
    assert all(p.std is not None and p.std > 0 for p in pre.parameters)
    cal = calibrated_machine(m, d)
    assert cal.effects == ("redundancy_preload",) and "[effect.redundancy_preload]" in cal.text
    # fresh poses of the same true module (the same commanded offset), settled by the restrained physics
    rng = np.random.default_rng(99)
    q = m.inverse_planar(m.sample_planar(100, rng))
    q[:, 1] += offset
    st = solve_restrained(m, q, sim.theta, sim.stiffness)
    true_tool = m.tool_from_planar(st.x, sim.theta)[0]
    # the written machine with its [effect.*] table predicts the machine to about the noise ...
    assert _rms(predict_poses(cal.machine, q).position, true_tool) < 3 * m.noise.sigma_position * np.sqrt(3)
    # ... and its geometry alone is closer to the true geometry than the geometry-only calibration's (not as
    # close as a clean recording's: a direction of the geometry is unobservable, test_redundancy_preload.py,
    # and held by the tolerance prior alone)
    true_fk = m.forward(q, sim.theta).position
    geo = _rms(m.forward(q, d.theta_geometric).position, true_fk)
    final = _rms(cal.machine.with_effects(()).forward(q).position, true_fk)
    assert final < geo, (final, geo)


def test_clean_restrained_module_with_compatible_commands_and_a_soft_redundant_drive_is_none():
    # a redundant drive 1000 times softer than the others carries no force worth seeing: no preload named
    m = load_machine(RASPM)
    sim = restrained_recording(m, 40, 5, stiffness_n_per_um=(150.0, 500.0))
    k = sim.stiffness.copy()
    k[1] /= 1e4
    st = solve_restrained(m, sim.recording.q, sim.theta, k)
    pos = m.tool_from_planar(st.x, sim.theta)[0] + np.random.default_rng(3).normal(0, m.noise.sigma_position, (40, 3))
    d = diagnose(m, Recording(q=sim.recording.q, position=pos, path="soft"), seed=1, effects=["redundancy_preload"])
    assert d.verdict == "none" and not d.selected
