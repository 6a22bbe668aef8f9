"""Mimic joints (docs/formats.md section 8) in [[joint]] tables and URDF files: forward kinematics against an
independent product of 4x4 transforms built from the file text itself, the Jacobians against central
differences (check_machine), per-joint parameter names, written files, weight bodies, recordings with
q columns for the actuators only, identification, and refusals by name."""

import tomllib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.errors import InputError, MachineFileError
from bayescal.geometry import so3_log
from bayescal.identifiability import analyse_identifiability
from bayescal.machines.check import check_machine
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.machines.serial import Serial
from bayescal.measurement import MeasurementModel

# a telescopic column (joint 2 follows joint 1 one to one) carrying a head whose joint 4 turns
# at -0.5 times joint 3 plus 0.2 rad (a coupled wrist)
TELESCOPE = """
kind = "serial"
name = "telescopic column with a coupled head"
[[joint]]
type = "prismatic"
origin = [0.0, 0.0, 300.0]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "prismatic"
origin = [0.0, 0.0, 50.0]
rpy = [0.01, -0.02, 0.0]
axis = [0.0, 0.0, 1.0]
mimic = 1
multiplier = 1.0
[[joint]]
type = "revolute"
origin = [100.0, 0.0, 20.0]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "revolute"
origin = [200.0, 0.0, 0.0]
rpy = [1.5707963267948966, 0.0, 0.0]
axis = [0.0, 0.0, 1.0]
mimic = 3
multiplier = -0.5
offset = 0.2
[tool]
point = [50.0, 0.0, 10.0]
rpy = [0.1, 0.0, 0.0]
[workspace]
q_limits = [[0.0, 400.0], [-2.0, 2.0]]
"""

# the same idea in a URDF (metres), with a driver after its mimic, a prismatic joint mimicking a
# revolute one (multiplier in m/rad) and fixed joints in between
URDF = """<?xml version="1.0"?>
<robot name="mimic_test">
  <link name="base"/><link name="stage1"/><link name="stage2"/><link name="mount"/><link name="head"/>
  <link name="slide"/><link name="flange"/>
  <joint name="lift" type="prismatic"><parent link="base"/><child link="stage1"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 0 1"/><limit lower="0" upper="0.4" effort="1" velocity="1"/></joint>
  <joint name="lift2" type="prismatic"><parent link="stage1"/><child link="stage2"/>
    <origin xyz="0 0 0.05" rpy="0.01 -0.02 0"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.4" effort="1" velocity="1"/><mimic joint="lift" multiplier="1"/></joint>
  <joint name="bracket" type="fixed"><parent link="stage2"/><child link="mount"/>
    <origin xyz="0.1 0 0.02" rpy="0 0 0.3"/></joint>
  <joint name="swing" type="revolute"><parent link="mount"/><child link="head"/>
    <origin xyz="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/><mimic joint="turn" multiplier="-0.5" offset="0.2"/></joint>
  <joint name="feed" type="prismatic"><parent link="head"/><child link="slide"/>
    <origin xyz="0.2 0 0" rpy="1.5707963267948966 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-0.1" upper="0.1" effort="1" velocity="1"/><mimic joint="turn" multiplier="0.05" offset="0.01"/></joint>
  <joint name="turn" type="revolute"><parent link="slide"/><child link="flange"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
</robot>
"""

FROM_URDF = """
kind = "serial"
urdf = "m.urdf"
base_link = "base"
tip_link = "flange"
[tool]
point = [5.0, 0.0, 30.0]
"""


@pytest.fixture(scope="module")
def telescope():
    return machine_from_text(TELESCOPE)


@pytest.fixture()
def urdf_machine(tmp_path):
    (tmp_path / "m.urdf").write_text(URDF)
    (tmp_path / "m.toml").write_text(FROM_URDF)
    return load_machine(tmp_path / "m.toml")


def _T(R=np.eye(3), t=np.zeros(3)):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rpy(rpy):
    return Rotation.from_euler("xyz", rpy).as_matrix()  # extrinsic x, y, z: Rz(y) Ry(p) Rx(r)


def _fk_from_toml(text: str, q) -> np.ndarray:
    """The tool frame from the [[joint]] text: actuators fill the non-mimic joints in order, a mimic
    joint takes multiplier * (its driver's position) + offset; then the literal product of 4x4s."""
    doc = tomllib.loads(text)
    joints = doc["joint"]
    pos, it = {}, iter(q)
    for i, j in enumerate(joints):
        if "mimic" not in j:
            pos[i] = next(it)
    for i, j in enumerate(joints):
        if "mimic" in j:
            pos[i] = j.get("multiplier", 1.0) * pos[j["mimic"] - 1] + j.get("offset", 0.0)
    T = np.eye(4)
    for i, j in enumerate(joints):
        a = np.array(j["axis"], float)
        T = T @ _T(t=np.array(j.get("origin", [0, 0, 0]), float)) @ _T(R=_rpy(j.get("rpy", [0, 0, 0])))
        T = T @ (_T(R=Rotation.from_rotvec(a * pos[i]).as_matrix()) if j["type"] == "revolute" else _T(t=a * pos[i]))
    tool = doc["tool"]
    return T @ _T(t=np.array(tool["point"], float)) @ _T(R=_rpy(tool.get("rpy", [0, 0, 0])))


def _fk_urdf_by_hand(q) -> np.ndarray:
    """The URDF above by hand, in mm: q = (lift mm, turn rad)."""
    lift, turn = q
    lift_m = lift / 1000.0
    swing, feed_m = -0.5 * turn + 0.2, 0.05 * turn + 0.01
    T = _T(t=[0, 0, 300.0]) @ _T(t=[0, 0, lift_m * 1000.0])
    T = T @ _T(t=[0, 0, 50.0]) @ _T(R=_rpy([0.01, -0.02, 0])) @ _T(t=[0, 0, lift_m * 1000.0])
    T = T @ _T(t=[100.0, 0, 20.0]) @ _T(R=_rpy([0, 0, 0.3]))
    T = T @ _T(R=Rotation.from_rotvec([0, 0, swing]).as_matrix())
    T = T @ _T(t=[200.0, 0, 0]) @ _T(R=_rpy([np.pi / 2, 0, 0])) @ _T(t=[feed_m * 1000.0, 0, 0])
    T = T @ _T(t=[0, 0, 100.0]) @ _T(R=Rotation.from_rotvec([0, turn, 0]).as_matrix())
    return T @ _T(t=[5.0, 0, 30.0])


def test_actuators_are_the_non_mimic_joints(telescope, urdf_machine):
    assert (telescope.n_joints, telescope.n_actuators, telescope.actuator_units) == (4, 2, ("mm", "rad"))
    assert telescope.mimic == (None, (0, 1.0, 0.0), None, (2, -0.5, 0.2))
    # URDF: the mimic's multiplier and offset in bayescal units (feed: m per rad -> mm per rad)
    assert urdf_machine.joint_names == ("lift", "lift2", "swing", "feed", "turn")
    assert urdf_machine.actuator_units == ("mm", "rad")
    assert urdf_machine.mimic[3] == (4, pytest.approx(50.0), pytest.approx(10.0))
    assert np.array_equal(urdf_machine.q_limits, [[0.0, 400.0], [-2.0, 2.0]])  # the actuators' limits only
    np.testing.assert_allclose(urdf_machine.joint_positions([[100.0, 0.4]]), [[100.0, 100.0, 0.0, 30.0, 0.4]])


def test_toml_forward_matches_an_independent_product_of_transforms(telescope):
    q = telescope.sample_q(12, np.random.default_rng(1))
    poses = telescope.forward(q)
    for i in range(q.shape[0]):
        T = _fk_from_toml(TELESCOPE, q[i])
        np.testing.assert_allclose(poses.position[i], T[:3, 3], atol=1e-9)
        np.testing.assert_allclose(poses.rotation[i], T[:3, :3], atol=1e-12)


def test_a_telescopic_column_extends_twice_its_drive():
    text = TELESCOPE.replace("rpy = [0.01, -0.02, 0.0]\n", "")
    m = machine_from_text(text)
    a, b = m.forward([[0.0, 0.3]]), m.forward([[100.0, 0.3]])
    np.testing.assert_allclose(b.position - a.position, [[0.0, 0.0, 200.0]], atol=1e-9)


def test_urdf_forward_matches_a_hand_product_and_yourdfpy(urdf_machine, tmp_path):
    import yourdfpy

    robot = yourdfpy.URDF.load(str(tmp_path / "m.urdf"), build_scene_graph=True, load_meshes=False)
    q = urdf_machine.sample_q(10, np.random.default_rng(2))
    poses = urdf_machine.forward(q)
    for i in range(q.shape[0]):
        T = _fk_urdf_by_hand(q[i])
        np.testing.assert_allclose(poses.position[i], T[:3, 3], atol=1e-9)
        np.testing.assert_allclose(poses.rotation[i], T[:3, :3], atol=1e-12)
        robot.update_cfg({"lift": q[i, 0] / 1000.0, "turn": q[i, 1]})  # yourdfpy applies the mimics itself
        Y = robot.get_transform("flange", "base") @ _T(t=[0.005, 0.0, 0.030])
        np.testing.assert_allclose(poses.position[i], 1000.0 * Y[:3, 3], atol=1e-9)


@pytest.mark.parametrize("which", ["toml", "urdf"])
def test_mimic_chains_conform(which, telescope, urdf_machine):
    """check_machine: the analytic tool Jacobian against central differences for every parameter, the
    written file read back (mimic, multiplier, offset kept), per-pose theta."""
    m = telescope if which == "toml" else urdf_machine
    if m.q_limits is None:
        pytest.fail("needs q_limits")
    assert check_machine(m, seed=4) == []


def test_actuator_jacobian_sums_the_driven_joints(telescope):
    from bayescal.machines.base import Machine

    rng = np.random.default_rng(3)
    q = telescope.sample_q(6, rng)
    theta = rng.normal(size=telescope.n_params) * telescope.tolerance
    poses = telescope.forward(q, theta)
    fd = Machine.actuator_jacobian(telescope, q, theta, poses)  # the base class: central differences
    np.testing.assert_allclose(telescope.actuator_jacobian(q, theta, poses), fd, atol=1e-6)


def test_every_joint_keeps_its_parameters_and_the_column_offsets_are_one_combination(telescope):
    names = telescope.layout.names
    assert len(names) == 9 * 4 + 6
    for i in range(1, 5):
        assert f"joint{i}.offset" in names and f"joint{i}.origin.x" in names and f"joint{i}.rpy.y" in names
    assert not any("multiplier" in n for n in names)  # multipliers are exact transmission ratios
    straight = machine_from_text(TELESCOPE.replace("rpy = [0.01, -0.02, 0.0]\n", ""))  # both stages along z
    q = straight.sample_q(60, np.random.default_rng(0))
    model = MeasurementModel(straight, q, 6)
    J = (model.jacobian(None, model.predict(None)) / model.sigma[None, :, None]).reshape(-1, straight.n_params)
    ida = analyse_identifiability(J, straight.layout)
    # both stages of the column move along z by their offsets: the measurement sees only their sum
    assert "joint2.offset" in ida.fixed and "joint1.offset" in ida.kept
    assert ("joint2.offset: a change of 1 mm looks the same to the measurement as changing joint1.offset by +1 mm; "
            "fixed at nominal, only the combination is identified") in ida.combinations


def test_written_file_keeps_the_mimic_keys(telescope, urdf_machine):
    theta = np.random.default_rng(5).normal(size=telescope.n_params) * telescope.tolerance
    doc = tomllib.loads(telescope.to_toml(theta))
    assert [j.get("mimic") for j in doc["joint"]] == [None, 1, None, 3]
    assert doc["joint"][3]["multiplier"] == -0.5 and doc["joint"][3]["offset"] == 0.2
    # a URDF chain writes its joint names and its mimics in [[joint]] tables
    again = machine_from_text(urdf_machine.to_toml())
    assert again.joint_names == urdf_machine.joint_names and again.mimic == urdf_machine.mimic


def test_weight_bodies_are_the_links_derivatives_per_actuator(telescope):
    rng = np.random.default_rng(6)
    theta = rng.normal(size=telescope.n_params) * telescope.tolerance
    q = telescope.sample_q(4, rng)
    wb = telescope.weight_bodies(q, theta, telescope.forward(q, theta))
    assert wb.names == ("link1", "link2", "link3", "link4") and wb.jacobian.shape == (4, 4, 6, 2)
    for i, h in enumerate((1e-4, 1e-6)):
        e = np.zeros(2)
        e[i] = h
        a = telescope.weight_bodies(q + e, theta, telescope.forward(q + e, theta))
        b = telescope.weight_bodies(q - e, theta, telescope.forward(q - e, theta))
        np.testing.assert_allclose(wb.jacobian[:, :, :3, i], (a.origin - b.origin) / (2 * h), atol=1e-5)
        w = so3_log(a.rotation @ np.swapaxes(b.rotation, -1, -2)) / (2 * h)
        np.testing.assert_allclose(wb.jacobian[:, :, 3:, i], w, atol=1e-7)
    # the column's second stage moves twice as fast as the first with the one drive
    np.testing.assert_allclose(wb.jacobian[:, 1, 2, 0], 2 * wb.jacobian[:, 0, 2, 0], rtol=1e-3)


def test_urdf_masses_are_per_link_mimic_links_included(tmp_path):
    urdf = URDF.replace('<link name="stage2"/>', '<link name="stage2"><inertial><mass value="3"/>'
                        '<origin xyz="0 0 0.1"/></inertial></link>')
    (tmp_path / "m.urdf").write_text(urdf)
    (tmp_path / "m.toml").write_text(FROM_URDF)
    m = load_machine(tmp_path / "m.toml")
    bi = m.body_inertials
    assert len(m.weight_body_names) == 5 and bi.mass_kg.shape == (5,)
    np.testing.assert_allclose(bi.mass_kg, [0.0, 3.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(bi.com_mm[1], [0.0, 0.0, 100.0])


def test_recordings_have_q_columns_for_the_actuators_only_and_identify(telescope):
    from bayescal.identify import identify
    from bayescal.simulate import simulate_recording

    sim = simulate_recording(telescope, 80, seed=2, dof=6)
    assert sim.recording.q.shape[1] == 2
    res = identify(MeasurementModel.from_recording(telescope, sim.recording), method="ls")
    assert res.success
    q = telescope.sample_q(50, np.random.default_rng(8))
    fit, true, nominal = telescope.forward(q, res.theta), telescope.forward(q, sim.theta_true), telescope.forward(q)
    assert np.abs(fit.position - true.position).max() < 0.02 < np.abs(nominal.position - true.position).max() / 5


@pytest.mark.parametrize(
    "edit,key,match",
    [
        (("mimic = 3\n", "mimic = 2\n"), "joint[4].mimic", "joint 4 mimics joint 2, which mimics joint 1"),
        (("mimic = 3\n", "mimic = 4\n"), "joint[4].mimic", "joint 4 mimics itself"),
        (("mimic = 3\n", "mimic = 5\n"), "joint[4].mimic", "expected the index of another joint, 1..4"),
        (("mimic = 3\n", "mimic = 0\n"), "joint[4].mimic", "expected the index of another joint"),
        (("mimic = 3\n", "mimic = 1.5\n"), "joint[4].mimic", "1-based integer"),
        (("mimic = 3\n", 'mimic = "joint3"\n'), "joint[4].mimic", "1-based integer"),
        (("mimic = 3\nmultiplier = -0.5\n", "multiplier = -0.5\n"), "joint[4].multiplier", "only allowed together with mimic"),
        (("q_limits = [[0.0, 400.0], [-2.0, 2.0]]", "q_limits = [[0.0, 400.0], [-2.0, 2.0], [0.0, 1.0], [0.0, 1.0]]"),
         "workspace.q_limits", "expected 2 lists"),
    ],
)
def test_bad_mimic_tables_are_named(edit, key, match):
    with pytest.raises(MachineFileError, match=match) as err:
        machine_from_text(TELESCOPE.replace(*edit), "t.toml")
    assert err.value.key == key


@pytest.mark.parametrize(
    "edit,match",
    [
        (('<mimic joint="lift" multiplier="1"/>', '<mimic joint="lift2"/>'), "'lift2' mimics itself"),
        (('<mimic joint="turn" multiplier="0.05" offset="0.01"/>', '<mimic joint="swing"/>'),
         "'feed' mimics 'swing', which mimics 'turn'"),
        (('<mimic joint="lift" multiplier="1"/>', '<mimic joint="elsewhere"/>'), "'lift2' mimics 'elsewhere', which is not a moving joint"),
        (('<mimic joint="lift" multiplier="1"/>', '<mimic joint="bracket"/>'), "'lift2' mimics 'bracket', which is not a moving joint"),
    ],
)
def test_bad_urdf_mimics_are_named(tmp_path, edit, match):
    (tmp_path / "m.urdf").write_text(URDF.replace(*edit))
    (tmp_path / "m.toml").write_text(FROM_URDF)
    with pytest.raises(MachineFileError, match=match) as err:
        load_machine(tmp_path / "m.toml")
    assert err.value.key == "urdf"


def test_the_library_constructor_checks_mimic_entries(telescope):
    kw = dict(joint_type=telescope.joint_type, origin=telescope.origin, rpy=telescope.rpy, axis=telescope.axis,
              tool_point=telescope.tool_point)
    with pytest.raises(InputError, match="mimics joint 2, which mimics"):
        Serial(**kw, mimic=(None, (0, 1.0, 0.0), None, (1, 1.0, 0.0)))
    with pytest.raises(InputError, match="one entry per joint"):
        Serial(**kw, mimic=(None, (0, 1.0, 0.0)))


def test_joint_names_must_be_distinct():
    text = TELESCOPE.replace('type = "revolute"\norigin = [100.0', 'name = "arm"\ntype = "revolute"\norigin = [100.0')
    assert machine_from_text(text).joint_names == ("joint1", "joint2", "arm", "joint4")
    with pytest.raises(MachineFileError, match="joint name 'joint1' is also the default name of unnamed joint 1") as err:
        machine_from_text(text.replace('name = "arm"', 'name = "joint1"'), "t.toml")
    assert err.value.key == "joint[3].name"
