import numpy as np
import pytest

from bayescal.errors import MachineFileError
from bayescal.geometry import so3_log
from bayescal.machines import KINDS
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.machines.raspm import Raspm
from tests.conftest import ROOT

FILE = ROOT / "examples" / "raspm" / "machine.toml"


@pytest.fixture(scope="module")
def raspm():
    return load_machine(FILE)


def test_registered_and_example_loads(raspm):
    assert KINDS["RASPM-2T1R"] is Raspm
    assert raspm.n_actuators == 4 and raspm.n_params == 24 and raspm.redundant == (1,)


def test_inverse_forward_round_trip(raspm):
    rng = np.random.default_rng(2)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance * 3
    x = raspm.sample_planar(30, rng)
    q = raspm.inverse_planar(x, th)
    assert np.all((q >= raspm.q_limits[:, 0] - 5) & (q <= raspm.q_limits[:, 1] + 5))
    xf, ok = raspm.forward_planar(q, th)
    assert ok.all() and np.abs(xf - x).max() < 1e-9


def test_symmetric_closed_form(raspm):
    """Pivot straight below the two chain-3 sliders: z from Pythagoras."""
    q = raspm.inverse_planar(np.array([[0.0, 0.0, 0.0]]))
    h = np.sqrt(1000.0**2 - 500.0**2)
    assert np.allclose(q[0, 2:], 1000.0 + h, atol=1e-9)
    poses = raspm.forward(q)
    assert np.allclose(poses.position[0], [0.0, 0.0, -400.0], atol=1e-9)
    assert np.allclose(poses.rotation[0], np.eye(3), atol=1e-12)


def test_nonredundant_jacobian_against_finite_differences(raspm):
    rng = np.random.default_rng(8)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance * 3
    q = raspm.inverse_planar(raspm.sample_planar(5, rng), th)
    poses = raspm.forward(q, th)
    J = raspm.tool_jacobian(q, th, poses)
    assert np.all(J[:, [1, 3, 5]] == 0)
    for k, unit in enumerate(raspm.layout.units):
        h = 1e-4 if unit == "mm" else 1e-7
        e = np.zeros(raspm.n_params)
        e[k] = h
        pp, pm = raspm.forward(q, th + e, guess=poses), raspm.forward(q, th - e, guess=poses)
        fd = (pp.position - pm.position) / (2 * h)
        frot = so3_log(pp.rotation @ np.swapaxes(pm.rotation, 1, 2)) / (2 * h)
        scale = max(1.0, np.abs(J).max())
        assert np.allclose(J[:, :3, k], fd, atol=1e-6 * scale), raspm.layout.names[k]
        assert np.allclose(J[:, 3:, k], frot, atol=1e-8 * scale), raspm.layout.names[k]


def test_ik_parameter_jacobian_against_finite_differences(raspm):
    rng = np.random.default_rng(10)
    x = raspm.sample_planar(4, rng)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance
    G = raspm.ik_parameter_jacobian(x, th)
    for k, unit in enumerate(raspm.layout.units):
        h = 1e-4 if unit == "mm" else 1e-7
        e = np.zeros(raspm.n_params)
        e[k] = h
        fd = (raspm.inverse_planar(x, th + e) - raspm.inverse_planar(x, th - e)) / (2 * h)
        assert np.allclose(G[:, :, k], fd, atol=1e-6 * max(1.0, np.abs(G).max())), raspm.layout.names[k]


def test_written_machine_reproduces_the_model(raspm):
    rng = np.random.default_rng(11)
    th = rng.normal(size=raspm.n_params) * raspm.tolerance * 3
    again = machine_from_text(raspm.to_toml(th))
    x = raspm.sample_planar(10, rng)
    assert np.allclose(raspm.inverse_planar(x, th), again.inverse_planar(x), atol=1e-9)
    assert np.array_equal(again.pose_range, raspm.pose_range) and again.nonredundant == raspm.nonredundant


def test_bad_machine_files_name_the_key():
    text = FILE.read_text()
    cases = {
        text.replace("rail_direction = [0.0, 0.0, 1.0]", "rail_direction = [0.0, 0.6, 0.8]", 1): "rail_direction",
        text.replace("nonredundant = [1, 3, 4]", "nonredundant = [1, 1, 4]"): "nonredundant",
        text.replace("link_length = 1200.0", "link_length = -1.0", 1): "link_length",
        text.replace("rotation = [", "rotation = [1.0, ", 1).replace(", 0.4363323129985824]", "]", 1): "pose_range",
        text.replace("[tool]", "[tol]"): "tol",
    }
    for bad, key in cases.items():
        with pytest.raises(MachineFileError) as ei:
            machine_from_text(bad, "bad.toml")
        assert "bad.toml" in str(ei.value) and key in str(ei.value), str(ei.value)


def test_core_identification_works_on_the_nonredundant_model(raspm):
    """The generic consumers (simulate, MeasurementModel, identify) run on the kind unchanged."""
    from bayescal.identify import identify
    from bayescal.measurement import MeasurementModel
    from bayescal.simulate import simulate_recording

    sim = simulate_recording(raspm, 30, seed=3, dof=6)
    res = identify(MeasurementModel.from_recording(raspm, sim.recording), method="ls")
    assert res.success
    assert res.rms_after["position"] < 3 * raspm.noise.sigma_position < res.rms_before["position"]
