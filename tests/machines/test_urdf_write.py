"""A calibrated serial chain written as a URDF: yourdfpy's own forward kinematics of the written file
equals the calibrated machine's (1e-9 mm), mimic joints included; bayescal reads it back as the same
chain; other kinds are refused and nothing is written."""

import numpy as np
import pytest

from bayescal.errors import InputError
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.machines.framed import Frame, InstrumentFrame
from bayescal.machines.urdf_write import urdf_text, write_calibrated_urdf
from tests.conftest import ROOT
from tests.machines.test_mimic import FROM_URDF, TELESCOPE, URDF
from tests.machines.test_serial import ARM


def _yourdfpy_tool(path, machine, q):
    """Tool frames (mm) by yourdfpy's scene graph, the actuators set by name in URDF units."""
    import yourdfpy

    robot = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    names = machine.joint_names or tuple(f"joint{i + 1}" for i in range(machine.n_joints))
    out = []
    for row in q:
        cfg = {}
        for k, i in enumerate(machine.actuated_joints):
            cfg[names[i]] = row[k] / 1000.0 if machine.joint_type[i] == "prismatic" else row[k]
        robot.update_cfg(cfg)
        T = robot.get_transform("tool", "base_link").copy()
        T[:3, 3] *= 1000.0
        out.append(T)
    return np.array(out)


def _machines(tmp_path):
    (tmp_path / "m.urdf").write_text(URDF)
    (tmp_path / "m.toml").write_text(FROM_URDF)
    return {"arm": machine_from_text(ARM), "telescope": machine_from_text(TELESCOPE), "urdf": load_machine(tmp_path / "m.toml")}


@pytest.mark.parametrize("which", ["arm", "telescope", "urdf"])
def test_yourdfpy_kinematics_of_the_written_urdf_is_the_calibrated_machine(which, tmp_path):
    m = _machines(tmp_path)[which]
    rng = np.random.default_rng(11)
    theta = rng.normal(size=m.n_params) * m.tolerance * 20  # offsets, tilts, origins, rpy, tool all moved
    path = write_calibrated_urdf(tmp_path / "cal.urdf", m, theta)
    q = m.sample_q(8, rng)
    poses = m.forward(q, theta)
    T = _yourdfpy_tool(path, m, q)
    np.testing.assert_allclose(T[:, :3, 3], poses.position, rtol=0, atol=1e-9)
    np.testing.assert_allclose(T[:, :3, :3], poses.rotation, rtol=0, atol=1e-12)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary file left


def test_bayescal_reads_the_written_urdf_back_as_the_same_chain(tmp_path):
    m = _machines(tmp_path)["urdf"]
    theta = np.random.default_rng(12).normal(size=m.n_params) * m.tolerance * 5
    write_calibrated_urdf(tmp_path / "out" / "cal.urdf", m, theta)
    (tmp_path / "out" / "cal.toml").write_text('kind = "serial"\nurdf = "cal.urdf"\nbase_link = "base_link"\n'
                                               'tip_link = "tool"\n[tool]\npoint = [0.0, 0.0, 0.0]\n')
    back = load_machine(tmp_path / "out" / "cal.toml")
    assert back.joint_names == m.joint_names and back.joint_type == m.joint_type
    assert [None if x is None else x[0] for x in back.mimic] == [None if x is None else x[0] for x in m.mimic]
    np.testing.assert_allclose(back.q_limits, m.q_limits, rtol=1e-15)
    q = m.sample_q(10, np.random.default_rng(13))
    a, b = back.forward(q), m.forward(q, theta)
    np.testing.assert_allclose(a.position, b.position, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a.rotation, b.rotation, rtol=0, atol=1e-12)


def test_limits_mimic_limits_and_continuous_joints():
    m = machine_from_text(TELESCOPE)
    text = urdf_text(m)
    assert text.count('lower="0.0" upper="0.4"') == 2  # the column's drive (m) and its mimic stage
    assert 'lower="-0.8" upper="1.2"' in text  # joint 4: -0.5 * [-2, 2] + 0.2, ordered
    assert '<mimic joint="joint3" multiplier="-0.5" offset="0.2"' in text
    free = machine_from_text(TELESCOPE.split("[workspace]")[0])
    assert 'type="continuous"' in urdf_text(free)  # a revolute joint without limits


def test_an_instrument_frame_is_not_written_and_the_chain_is(tmp_path):
    m = machine_from_text(TELESCOPE)
    framed = InstrumentFrame(m, Frame.from_rotation_vector([100.0, -50.0, 30.0], [0.1, 0.2, -0.3]), fit=True)
    theta = np.random.default_rng(14).normal(size=framed.n_params) * framed.tolerance
    assert urdf_text(framed, theta) == urdf_text(m, theta[framed.n_frame:])


def test_other_kinds_are_refused_and_nothing_is_written(tmp_path):
    hybrid = load_machine(ROOT / "examples" / "hybrid_wrist" / "machine.toml")
    with pytest.raises(InputError, match="a URDF describes a serial chain; .* is a hybrid machine"):
        write_calibrated_urdf(tmp_path / "x.urdf", hybrid)
    assert list(tmp_path.iterdir()) == []
