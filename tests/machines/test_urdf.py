"""A serial chain from a URDF file: the same predictions as the [[joint]] description and as
yourdfpy's own forward kinematics; unsupported joints, cycles and files that are no tree refused by name."""

import numpy as np
import pytest

from bayescal.errors import MachineFileError
from bayescal.machines.check import check_machine
from bayescal.machines.files import load_machine, machine_from_text

URDF = """<?xml version="1.0"?>
<robot name="test_arm">
  <link name="world"/><link name="base_link"/><link name="pedestal"/><link name="l1"/><link name="l2"/>
  <link name="l2b"/><link name="l3"/><link name="l4"/><link name="tool_link"/><link name="camera"/>
  <joint name="mount" type="fixed"><parent link="world"/><child link="base_link"/>
    <origin xyz="1 2 3" rpy="0.1 0.2 0.3"/></joint>
  <joint name="riser" type="fixed"><parent link="base_link"/><child link="pedestal"/>
    <origin xyz="0 0 0.1"/></joint>
  <joint name="j1" type="revolute"><parent link="pedestal"/><child link="l1"/>
    <origin xyz="0 0 0.3" rpy="0 0 0.2"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.15 0 0" rpy="1.5707963267948966 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-1.5" upper="1.5" effort="1" velocity="1"/></joint>
  <joint name="camera_mount" type="fixed"><parent link="l1"/><child link="camera"/>
    <origin xyz="0 0.5 0"/></joint>
  <joint name="forearm" type="fixed"><parent link="l2"/><child link="l2b"/>
    <origin xyz="0.6 0 0"/></joint>
  <joint name="j3" type="continuous"><parent link="l2b"/><child link="l3"/>
    <origin xyz="0 0 0" rpy="0 0 0.1"/><axis xyz="0 1 0"/></joint>
  <joint name="j4" type="prismatic"><parent link="l3"/><child link="l4"/>
    <origin xyz="0.1 0 0"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="0.2" effort="1" velocity="1"/></joint>
  <joint name="flange" type="fixed"><parent link="l4"/><child link="tool_link"/>
    <origin xyz="0 0 0.05" rpy="0.3 0 0"/></joint>
</robot>
"""

FROM_URDF = """
kind = "serial"
name = "arm from URDF"
urdf = "arm.urdf"
base_link = "base_link"
tip_link = "tool_link"
[tool]
point = [5.0, -3.0, 20.0]
rpy = [0.2, 0.0, 0.0]
[workspace]
q_limits = [[-3.0, 3.0], [-1.5, 1.5], [-3.0, 3.0], [0.0, 200.0]]
"""

# the same chain by hand: fixed joints folded into the next joint (riser + j1: z 100 + 300; forearm
# into j3), the flange into the tool: point (0, 0, 50) + Rx(0.3) (5, -3, 20), rpy (0.3 + 0.2, 0, 0)
_c, _s = np.cos(0.3), np.sin(0.3)
_TP = np.array([5.0, -3.0 * _c - 20.0 * _s, 50.0 - 3.0 * _s + 20.0 * _c])
FROM_TOML = f"""
kind = "serial"
name = "arm by hand"
[[joint]]
type = "revolute"
origin = [0.0, 0.0, 400.0]
rpy = [0.0, 0.0, 0.2]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "revolute"
origin = [150.0, 0.0, 0.0]
rpy = [1.5707963267948966, 0.0, 0.0]
axis = [0.0, 0.0, 1.0]
[[joint]]
type = "revolute"
origin = [600.0, 0.0, 0.0]
rpy = [0.0, 0.0, 0.1]
axis = [0.0, 1.0, 0.0]
[[joint]]
type = "prismatic"
origin = [100.0, 0.0, 0.0]
axis = [1.0, 0.0, 0.0]
[tool]
point = [{float(_TP[0])!r}, {float(_TP[1])!r}, {float(_TP[2])!r}]
rpy = [0.5, 0.0, 0.0]
[workspace]
q_limits = [[-3.0, 3.0], [-1.5, 1.5], [-3.0, 3.0], [0.0, 200.0]]
"""


@pytest.fixture()
def urdf_machine(tmp_path):
    (tmp_path / "arm.urdf").write_text(URDF)
    (tmp_path / "m.toml").write_text(FROM_URDF)
    return load_machine(tmp_path / "m.toml")


def test_urdf_and_toml_give_the_same_predictions(urdf_machine):
    by_hand = machine_from_text(FROM_TOML)
    assert urdf_machine.joint_type == ("revolute",) * 3 + ("prismatic",)
    rng = np.random.default_rng(5)
    q = urdf_machine.sample_q(20, rng)
    theta = rng.normal(size=urdf_machine.n_params) * urdf_machine.tolerance
    a, b = urdf_machine.forward(q, theta), by_hand.forward(q, theta)
    assert np.allclose(a.position, b.position, atol=1e-9)
    assert np.allclose(a.rotation, b.rotation, atol=1e-12)
    assert urdf_machine.layout.names == by_hand.layout.names


def test_urdf_machine_matches_yourdfpy_forward_kinematics(urdf_machine, tmp_path):
    """yourdfpy's own scene-graph kinematics (metres, its q for the prismatic joint in m) is an
    independent implementation of the URDF semantics."""
    import yourdfpy

    robot = yourdfpy.URDF.load(str(tmp_path / "arm.urdf"), build_scene_graph=True, load_meshes=False)
    q = urdf_machine.sample_q(6, np.random.default_rng(1))
    poses = urdf_machine.forward(q)
    Rt = np.eye(4)
    Rt[:3, :3] = np.array([[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]])
    Rt[:3, 3] = [0.005, -0.003, 0.020]
    for i in range(q.shape[0]):
        robot.update_cfg({"j1": q[i, 0], "j2": q[i, 1], "j3": q[i, 2], "j4": q[i, 3] / 1000.0})
        T = robot.get_transform("tool_link", "base_link") @ Rt
        assert np.allclose(poses.position[i], 1000.0 * T[:3, 3], atol=1e-9)
        assert np.allclose(poses.rotation[i], T[:3, :3], atol=1e-12)


def test_urdf_machine_conforms_and_writes_joint_tables(urdf_machine):
    assert check_machine(urdf_machine, seed=2) == []
    text = urdf_machine.to_toml()
    assert "[[joint]]" in text and "urdf" not in text


def test_q_limits_from_urdf_limits(tmp_path):
    (tmp_path / "arm.urdf").write_text(URDF)
    (tmp_path / "m.toml").write_text('kind = "serial"\nurdf = "arm.urdf"\nbase_link = "base_link"\ntip_link = "l2"\n[tool]\npoint = [0.0, 0.0, 0.0]\n')
    m = load_machine(tmp_path / "m.toml")
    assert np.array_equal(m.q_limits, [[-3.0, 3.0], [-1.5, 1.5]])
    # a continuous joint has no limits: none from the URDF then
    (tmp_path / "m.toml").write_text('kind = "serial"\nurdf = "arm.urdf"\nbase_link = "base_link"\ntip_link = "l4"\n[tool]\npoint = [0.0, 0.0, 0.0]\n')
    assert load_machine(tmp_path / "m.toml").q_limits is None


@pytest.mark.parametrize(
    "urdf_edit,toml_edit,key,match",
    [
        (None, ('tip_link = "tool_link"', 'tip_link = "hand"'), "tip_link", "not in arm.urdf"),
        (None, ('base_link = "base_link"', 'base_link = "camera"'), "base_link", "not an ancestor"),
        (None, ('urdf = "arm.urdf"', 'urdf = "none.urdf"'), "urdf", "file not found"),
        (('type="continuous"', 'type="floating"'), None, "urdf", "'j3' is of type 'floating'"),
        (('<axis xyz="0 1 0"/>', '<axis xyz="0 1 0"/><mimic joint="camera_mount"/>'), None, "urdf",
         "'j3' mimics 'camera_mount', which is not a moving joint between base_link and tip_link"),
        (('<child link="camera"/>', '<child link="l2"/>'), None, "urdf", "link 'l2' of arm.urdf is the child of two joints"),
        (("<robot", "<robt"), None, "urdf", "not a readable URDF"),
        # yourdfpy's IndexError / ValueError named neither the joint nor the line (a probe found them)
        (('rpy="0 0 0.2"', 'rpy="0 0"'), None, "urdf",
         "arm.urdf line 10: joint 'j1', <origin rpy=...>: expected 3 numbers separated by spaces, got '0 0'"),
        (('<axis xyz="0 1 0"/>', '<axis xyz="0 one 0"/>'), None, "urdf", "joint 'j3', <axis xyz=...>: expected 3 numbers"),
        (('lower="0" upper="0.2"', 'lower="zero" upper="0.2"'), None, "urdf", "joint 'j4', <limit lower=...>: expected a number"),
    ],
)
def test_bad_urdf_input_is_named(tmp_path, urdf_edit, toml_edit, key, match):
    (tmp_path / "arm.urdf").write_text(URDF.replace(*urdf_edit) if urdf_edit else URDF)
    (tmp_path / "m.toml").write_text(FROM_URDF.replace(*toml_edit) if toml_edit else FROM_URDF)
    with pytest.raises(MachineFileError, match=match) as err:
        load_machine(tmp_path / "m.toml")
    assert err.value.key == key


# joints j1 -> j2 -> j3 -> j1 form a cycle; walking up from a tip on it never reached the base (memory grew forever)
CYCLE = """<?xml version="1.0"?>
<robot name="loop">
  <link name="base"/><link name="a"/><link name="b"/><link name="c"/><link name="d"/>
  <joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="c"/><child link="a"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j4" type="fixed"><parent link="c"/><child link="d"/></joint>
</robot>
"""


@pytest.mark.parametrize("tip", ["c", "d"])
def test_a_cycle_of_joints_is_refused_naming_it(tmp_path, tip):
    (tmp_path / "loop.urdf").write_text(CYCLE)
    (tmp_path / "m.toml").write_text(f'kind = "serial"\nurdf = "loop.urdf"\nbase_link = "base"\ntip_link = "{tip}"\n'
                                     '[tool]\npoint = [0.0, 0.0, 0.0]\n')
    with pytest.raises(MachineFileError, match=r"the joints 'j2', 'j1', 'j3' of loop.urdf form a cycle \(links c <- b <- a <- c\)") as err:
        load_machine(tmp_path / "m.toml")
    assert err.value.key == "urdf"


def test_a_urdf_that_is_no_regular_file_is_refused_unread(tmp_path):
    import os

    os.mkfifo(tmp_path / "arm.urdf")
    (tmp_path / "m.toml").write_text(FROM_URDF)
    with pytest.raises(MachineFileError, match="arm.urdf is not a regular file") as err:
        load_machine(tmp_path / "m.toml")
    assert err.value.key == "urdf"


def test_a_cycle_through_the_base_is_refused(tmp_path):
    # the tip joined back to the base: the walk up from the tip reached the base and the file was read as a tree
    closed = URDF.replace("</robot>", '  <joint name="back" type="fixed"><parent link="tool_link"/><child link="world"/></joint>\n</robot>')
    (tmp_path / "arm.urdf").write_text(closed)
    (tmp_path / "m.toml").write_text(FROM_URDF)
    with pytest.raises(MachineFileError, match=r"of arm.urdf form a cycle \(links tool_link <- l4 <- .* <- world <- tool_link\)") as err:
        load_machine(tmp_path / "m.toml")
    assert err.value.key == "urdf"


@pytest.mark.parametrize("xyz", ["nan 0 0", "1e300 0 0"])
def test_a_joint_origin_that_is_not_finite_or_beyond_the_limit_is_refused(tmp_path, xyz):
    # a nan origin was read and every pose then failed ("cannot assemble this pose ... non-finite")
    (tmp_path / "arm.urdf").write_text(URDF.replace('<origin xyz="0.15 0 0"', f'<origin xyz="{xyz}"'))
    (tmp_path / "m.toml").write_text(FROM_URDF)
    with pytest.raises(MachineFileError, match=r"joint 'j2' of arm.urdf has the origin xyz .* expected finite numbers, "
                       r"a translation of at most 1e\+06 m") as err:
        load_machine(tmp_path / "m.toml")
    assert err.value.key == "urdf"


@pytest.mark.parametrize("tag,old,new", [("joint", 'name="j2"', 'name="j1"'),
                                         ("link", '<link name="l4"/>', '<link name="l4"/><link name="l4"/>')])
def test_two_elements_of_one_name_are_refused(tmp_path, tag, old, new):
    # yourdfpy kept the last joint 'j1': the chain lost a joint and the error blamed base_link
    (tmp_path / "arm.urdf").write_text(URDF.replace(old, new, 1))
    (tmp_path / "m.toml").write_text(FROM_URDF)
    with pytest.raises(MachineFileError, match=f"arm.urdf has two <{tag}> elements named") as err:
        load_machine(tmp_path / "m.toml")
    assert err.value.key == "urdf"
