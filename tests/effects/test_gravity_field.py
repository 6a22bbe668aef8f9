"""Gravity per pose from a base tilt sensor (accel.base.*), for every effect that needs gravity."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.effects import get_effect
from bayescal.effects.gravity_field import gravity_per_pose, tilt_basis, tilted_gravity
from bayescal.errors import InputError
from bayescal.machines.files import load_machine

ROOT = Path(__file__).resolve().parents[2]
TELESCOPE = ROOT / "examples" / "telescope" / "machine.toml"
DOWN = np.array([0.0, 0.0, -1.0])


def _sensor(rng, n, max_tilt=0.05):
    """Unit gravity directions tilted by up to ``max_tilt`` rad, and accelerometer readings (the specific force, up, in g)."""
    t = rng.uniform(-max_tilt, max_tilt, (n, 2))
    d = np.column_stack([np.sin(t[:, 0]), np.sin(t[:, 1]), -np.ones(n)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, {"accel.base.x": -9.81 * d[:, 0], "accel.base.y": -9.81 * d[:, 1], "accel.base.z": -9.81 * d[:, 2]}


def test_sensor_readings_give_each_pose_its_direction_in_either_convention(rng):
    d, aux = _sensor(rng, 7)
    got, sensor = gravity_per_pose(aux, DOWN, 7)
    assert sensor
    np.testing.assert_allclose(got, d, atol=1e-12)
    # columns holding gravity itself (pointing down) read the same
    flipped = {k: -v for k, v in aux.items()}
    np.testing.assert_allclose(gravity_per_pose(flipped, DOWN, 7)[0], d, atol=1e-12)
    # without a sensor: the stated direction at every pose
    got, sensor = gravity_per_pose({}, DOWN, 3)
    assert not sensor and got.shape == (3, 3)


def test_sensor_columns_are_checked():
    with pytest.raises(InputError, match="accel.base.z"):
        gravity_per_pose({"accel.base.x": np.ones(2), "accel.base.y": np.ones(2)}, DOWN, 2)
    with pytest.raises(InputError, match="pose 2"):
        zero = np.array([1.0, 0.0])
        gravity_per_pose({"accel.base.x": zero, "accel.base.y": zero, "accel.base.z": zero}, DOWN, 2)


def test_tilted_gravity_derivative_by_finite_differences(rng):
    down = rng.normal(size=(4, 3))
    down /= np.linalg.norm(down, axis=1, keepdims=True)
    E = tilt_basis(DOWN)
    t = np.array([0.03, -0.02])
    d, dd = tilted_gravity(down, E, t)
    for k in range(2):
        e = np.zeros(2)
        e[k] = 1e-6
        fd = (tilted_gravity(down, E, t + e)[0] - tilted_gravity(down, E, t - e)[0]) / 2e-6
        np.testing.assert_allclose(dd[:, :, k], fd, atol=1e-8)


@pytest.mark.parametrize("name", ["gravity_deflection", "joint_compliance", "gravity_backlash"])
def test_a_base_sensor_drives_each_pose_with_its_own_gravity(rng, name):
    # the effect with the sensor equals, pose by pose, the effect with that pose's direction stated
    m = load_machine(TELESCOPE)
    n = 5
    q = m.sample_q(n, rng)
    d, aux = _sensor(rng, n, max_tilt=0.3)
    masses = dict(link_mass_kg=[20.0, 15.0, 30.0, 8.0], link_com_mm=[[0, 0, 20.0], [40.0, 0, 10], [100.0, 0, 0], [20.0, 5, 0]])
    theta = np.zeros(m.n_params)
    eff = get_effect(name, **masses)
    f = eff.features(m, q, theta, aux, None, None)
    params = eff.params(m, f)
    assert [p.prior_sd for p in params if p.name.startswith("gravity.tilt")] in ([0.02, 0.02], [])
    eta = np.array([{"um/N": 2.0, "urad/(N m)": 50.0, "um": 40.0, "urad": 400.0}.get(p.unit, 0.0) for p in params])
    got = eff.delta_x(f, eta) if eff.moves_tool else eff.delta_q(f, eta)
    for i in range(n):
        one = get_effect(name, gravity=d[i], **masses)
        fi = one.features(m, q[i : i + 1], theta, {}, None, None)
        want = one.delta_x(fi, eta) if eff.moves_tool else one.delta_q(fi, eta)
        np.testing.assert_allclose(got[i], want[0], rtol=1e-9, atol=1e-12)
    assert "base sensor" in eff.model_note(f)


@pytest.mark.parametrize("name", ["joint_compliance", "gravity_deflection"])
def test_links_stated_unknown_are_fitted_and_read_back_from_a_table(rng, name):
    from bayescal.effects import check_effect
    from bayescal.effects.stored import StoredEffect, machine_file_text, predict_poses
    from bayescal.machines.files import machine_from_text

    m = load_machine(TELESCOPE)
    com = [[0, 0, 20.0], [40.0, 0, 10], [100.0, 0, 0], [20.0, 5, 0]]
    partly = get_effect(name, link_mass_kg=[20.0, float("nan"), float("nan"), 8.0], link_com_mm=com)
    check_effect(partly, m)
    q = m.sample_q(6, rng)
    theta = np.zeros(m.n_params)
    f = partly.features(m, q, theta, {}, None, None)
    params = partly.params(m, f)
    names = [p.name for p in params]
    assert "mass.link2" in names and "mass.link3" in names and "mass.link1" not in names and "mass.link4" not in names
    # at fitted masses 15 and 30 kg the effect is the one with those masses stated
    eta = np.array([{"mass.link2": 15.0, "mass.link3": 30.0}.get(p.name, 3.0 if "tilt" not in p.name else 0.01) for p in params])
    stated = get_effect(name, link_mass_kg=[20.0, 15.0, 30.0, 8.0], link_com_mm=com)
    fs = stated.features(m, q, theta, {}, None, None)
    eta_s = np.array([v for p, v in zip(params, eta) if not p.name.startswith("mass.")])
    move = (lambda e, ff, x: e.delta_x(ff, x)) if partly.moves_tool else (lambda e, ff, x: e.delta_q(ff, x))
    np.testing.assert_allclose(move(partly, f, eta), move(stated, fs, eta_s), rtol=1e-10, atol=1e-14)
    # a table with nan masses is written and read back, and predicts the same
    table = StoredEffect(name, tuple((p.name, float(v)) for p, v in zip(params, eta)),
                         settings=(("link_mass_kg", [20.0, float("nan"), float("nan"), 8.0]), ("link_com_mm", com)))
    with_table = m.with_effects((table,))
    again = machine_from_text(machine_file_text(with_table), "again.toml")
    np.testing.assert_allclose(predict_poses(again, q).position, predict_poses(with_table, q).position, atol=1e-12)
