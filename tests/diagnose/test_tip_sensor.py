"""A tilt sensor at the tip of a telescopic column, diagnosed with and without its rows (issue 29, item 2).

The bundled telescope (examples/telescope/machine.toml: two column stages, one mimicking the other, an arm and a
coupled wrist) bends under gravity in the independent element-by-element beam statics of
tests/physics/beam_statics.py (no beam formula, no bayescal effect code): the column's stages and the arm are
elastic, the base is tilted by 1.5 degrees, the payload changes from pose to pose.  The tool is measured by a
total station (0.2 mm per axis); an accelerometer on the upper column stage (``accel.joint2.*``) reads the
direction of gravity in that stage's deflected frame (2e-5 rad per tilt angle).  The link masses are stated
(as a URDF's ``<inertial>`` would state them).

With the sensor's rows the diagnosis must still name the bending, recover the column's compliance far more
precisely (the sensor reads the column's tip slope directly), and write a geometry whose uncertainty is
smaller; the written machine must predict fresh poses of the simulated truth no worse.
"""

from dataclasses import replace

import numpy as np
import pytest

from bayescal.diagnose import diagnose
from bayescal.diagnose.calibrated import calibrated_machine
from bayescal.effects.stored import predict_poses
from bayescal.geometry import so3_log
from bayescal.machines.files import load_machine
from bayescal.simulate import draw_errors, draw_poses, measure
from tests.physics.beam_statics import Member, MimicChain, deflected_tool, rodrigues
from tests.physics.test_deflection_diagnosis import TELESCOPE

MASS = np.array([40.0, 25.0, 30.0, 8.0])  # kg, per joint's body
COM = np.array([[0.0, 0, 40], [60.0, 0, 10], [110.0, 5, 0], [20.0, 0, 10]])  # mm, in each body's frame
DOWN = np.array([np.sin(np.radians(1.5)), 0.0, -np.cos(np.radians(1.5))])
B_COLUMN, B_ARM = 30.0, 6.0  # um/N at 1 m: the column's stages, the arm
TILT_SIGMA = 2e-5  # rad, the tip sensor's noise per tilt angle
SETTINGS = {"gravity_deflection": {"link_mass_kg": MASS.tolist(), "link_com_mm": COM.tolist()}}


class _Offsets:
    """A PoseTransform giving the tool offsets the statics computed for these poses."""

    def __init__(self, q, offsets):
        self.q, self.offsets = q, offsets

    def transform(self, q, theta, aux, order):
        return q, theta

    def pose_offset(self, q, theta, aux, order):
        assert np.array_equal(q, self.q)
        return self.offsets


def _statics(chain, members, q, payload):
    """Tool offsets (n, 6) and the tip sensor's unit readings (n, 3), in the upper stage's deflected frame."""
    off, up = np.zeros((len(q), 6)), np.zeros((len(q), 3))
    for i, qq in enumerate(q):
        p0, R0, p1, R1, turns = deflected_tool(chain, qq, members, MASS, COM, DOWN, payload[i], n_elements=30,
                                               bodies=(1,))
        off[i, :3], off[i, 3:] = p1 - p0, so3_log(R1 @ R0.T)
        _, after, _ = chain.frames(qq)
        up[i] = (rodrigues(turns[0]) @ after[1][:3, :3]).T @ (-DOWN)  # the specific force reads up
    return off, up


@pytest.fixture(scope="module")
def study():
    nominal = load_machine(TELESCOPE)
    m = nominal.with_noise(replace(nominal.noise, sigma_position=0.2, sigma_tilt=TILT_SIGMA))
    rng = np.random.default_rng(21)
    theta = draw_errors(m, rng)
    chain = MimicChain.from_text(m.to_toml(theta))
    members = [Member("stage", 0, 1e12 / (3 * B_COLUMN)), Member("stage", 1, 1e12 / (3 * B_COLUMN)),
               Member("link", 2, 1e12 / (3 * B_ARM))]
    q = draw_poses(m, 60, rng, theta)
    payload = rng.choice([0.0, 5.0, 10.0], size=60)
    off, up = _statics(chain, members, q, payload)
    tool_only = measure(m, q, theta, 3, rng, aux={"payload_kg": payload}, effects=[_Offsets(q, off)])
    reading = 9.81 * (up + rng.normal(size=up.shape) * TILT_SIGMA)
    with_tip = replace(tool_only, aux={**tool_only.aux, **{f"accel.joint2.{a}": reading[:, i] for i, a in enumerate("xyz")}})
    fresh = draw_poses(m, 30, np.random.default_rng(5), theta)
    pay_f = np.random.default_rng(6).choice([0.0, 5.0, 10.0], size=30)
    true_f = m.forward(fresh, theta).position + _statics(chain, members, fresh, pay_f)[0][:, :3]
    out = {"q": q, "payload": payload}
    for name, rec in (("without", tool_only), ("with", with_tip)):
        d = diagnose(m, rec, seed=1, n_folds=2, effect_settings=SETTINGS)  # the whole catalogue
        written = calibrated_machine(m, d).machine
        err = predict_poses(written, fresh, {"payload_kg": pay_f}).position - true_f
        out[name] = (d, 1e3 * float(np.sqrt(np.mean(np.sum(err**2, axis=1)))))
    return out


pytestmark = pytest.mark.slow  # two diagnoses with the whole catalogue and the statics of 90 poses: about 10 s


def _bending(d, name="bending.joint1"):
    trial = next(t for t in d.effects if t.name == "gravity_deflection")
    return next(p for p in trial.parameters if p.name == name)


def test_the_tip_sensor_names_the_bending_and_pins_the_column_compliance(study):
    (d0, _), (d1, _) = study["without"], study["with"]
    assert np.ptp(study["q"][:, 0]) > 300.0 and len(set(study["payload"])) == 3  # extensions and payloads vary
    assert d0.verdict == d1.verdict == "gravity_deflection"
    assert d1.selected == ("gravity_deflection",)
    # the tip's readings are measurements of the bending, not conditions it depends on: never a located channel
    assert "payload_kg" in {c.channel for c in d1.location.channels}
    assert not any(c.channel.startswith("accel.joint2") for c in d1.location.channels)
    b0, b1 = _bending(d0), _bending(d1)
    print(f"bending.joint1 without {b0.value:.3f} +- {b0.std:.3f}, with {b1.value:.3f} +- {b1.std:.4f} um/N (truth 30)")
    # the sensor reads the column's tip slope at 2e-5 rad: the compliance 10 times more precise or better, and
    # within 1 % of the simulated one (the statics' second-order terms are beyond the effect's model)
    assert b1.std < 0.1 * b0.std
    assert abs(b1.value - B_COLUMN) < 0.01 * B_COLUMN


def test_the_tip_sensor_shrinks_the_written_geometrys_uncertainty(study):
    (d0, err0), (d1, err1) = study["without"], study["with"]
    u0, u1 = d0.confound.tool_std_um, d1.confound.tool_std_um
    print(f"written geometry uncertain by {u0:.1f} -> {u1:.1f} um; fresh poses {err0:.1f} -> {err1:.1f} um RMS")
    assert u1 < 0.85 * u0  # 130 -> 95 um in this set-up
    assert u1 > d1.confound.geometric_tool_std_um  # still above a geometry-only calibration's: not free
    # the written machines predict fresh poses of the bent truth; the sensor's makes no worse a machine
    assert err1 < 1.05 * err0 and err1 < 120.0


def test_the_written_record_carries_the_bending_parameters_with_the_geometry(study):
    # predict propagates an effect's parameters only if the record holds them (with their trade against the
    # geometry): their block's std equals the diagnosis' own, and the joint covariance is a covariance
    d1 = study["with"][0]
    rec = d1.record
    eff = [n for n in rec.names if n.startswith("effect.gravity_deflection.")]
    assert "effect.gravity_deflection.bending.joint1" in eff
    j = rec.names.index("effect.gravity_deflection.bending.joint1")
    assert rec.std[j] == pytest.approx(_bending(d1).std, rel=1e-6)
    assert np.linalg.eigvalsh(rec.covariance).min() > -1e-9 * np.diag(rec.covariance).max()
