"""Link masses from a URDF's <inertial> elements, against yourdfpy's own kinematics of every link's centre of mass."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.effects import get_effect
from bayescal.effects.stored import machine_file_text
from bayescal.machines.files import load_machine, machine_from_text
from tests.machines.test_urdf import FROM_URDF, URDF

# masses (kg) and centres of mass (m, rpy ignored by the centre) of links on and off the chain: the pedestal is
# before the first moving joint (does not move); the camera hangs from l1 by a fixed joint; l2b is on the chain
# between j2 and j3 (fixed); a finger hangs from l4 by a prismatic joint off the chain; tool_link beyond the last
INERTIALS = {
    "pedestal": (20.0, (0.0, 0.0, 0.05)),
    "l1": (6.0, (0.05, 0.01, 0.02)),
    "camera": (0.8, (0.0, 0.02, 0.01)),
    "l2": (4.0, (0.3, 0.0, -0.01)),
    "l2b": (1.5, (0.02, 0.0, 0.0)),
    "l3": (2.0, (0.05, 0.01, 0.0)),
    "l4": (1.0, (0.0, 0.0, 0.02)),
    "finger": (0.3, (0.01, 0.0, 0.03)),
    "tool_link": (0.5, (0.0, 0.0, 0.04)),
}


def _urdf_with_inertials() -> str:
    text = URDF.replace('<link name="camera"/>', '<link name="camera"/><link name="finger"/>')
    text = text.replace("</robot>", """  <joint name="grip" type="prismatic"><parent link="l4"/><child link="finger"/>
    <origin xyz="0.02 0 0.01" rpy="0 0.4 0"/><axis xyz="0 1 0"/>
    <limit lower="0" upper="0.04" effort="1" velocity="1"/></joint>
</robot>""")
    for name, (mass, xyz) in INERTIALS.items():
        el = (f'<link name="{name}"><inertial><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}" rpy="0.3 0 0.2"/>'
              f'<mass value="{mass}"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>')
        text = text.replace(f'<link name="{name}"/>', el)
    return text


@pytest.fixture()
def arm(tmp_path):
    (tmp_path / "arm.urdf").write_text(_urdf_with_inertials())
    (tmp_path / "m.toml").write_text(FROM_URDF)
    return load_machine(tmp_path / "m.toml"), tmp_path / "arm.urdf"


def test_link_masses_fold_everything_a_moving_link_carries(arm):
    m, _ = arm
    known = m.body_inertials
    moved = ["l1", "camera"], ["l2", "l2b"], ["l3"], ["l4", "finger", "tool_link"]
    np.testing.assert_allclose(known.mass_kg, [sum(INERTIALS[x][0] for x in links) for links in moved], rtol=1e-12)
    assert m.weight_body_names == ("link1", "link2", "link3", "link4")


def test_mass_moments_match_yourdfpy_kinematics_of_every_link(arm):
    """sum_b m_b x_b of the weight bodies equals the sum over the URDF's moving links of their inertial origins placed
    by yourdfpy's scene graph (metres), the finger at its zero position."""
    import yourdfpy

    m, path = arm
    robot = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    known = m.body_inertials
    rng = np.random.default_rng(3)
    q = m.sample_q(5, rng)
    wb = m.weight_bodies(q, None, m.forward(q))
    ours = np.einsum("b,nbi->ni", known.mass_kg, wb.origin + np.einsum("nbij,bj->nbi", wb.rotation, known.com_mm))
    moving = [x for x in INERTIALS if x != "pedestal"]
    for i in range(q.shape[0]):
        robot.update_cfg({"j1": q[i, 0], "j2": q[i, 1], "j3": q[i, 2], "j4": q[i, 3] / 1000.0, "grip": 0.0})
        theirs = sum(INERTIALS[x][0] * 1000.0 * (robot.get_transform(x, "base_link") @ np.r_[INERTIALS[x][1], 1.0])[:3]
                     for x in moving)
        np.testing.assert_allclose(ours[i], theirs, rtol=1e-10, atol=1e-8)


def test_the_effect_uses_the_urdf_masses_and_a_written_file_keeps_them(arm):
    m, _ = arm
    eff = get_effect("joint_compliance")
    q = m.sample_q(4, np.random.default_rng(1))
    f = eff.features(m, q, np.zeros(m.n_params), {}, None, None)
    assert f.const["known"] and "URDF" in eff.model_note(f)
    names = [p.name for p in eff.params(m, f)]
    assert names == ["compliance.q1", "compliance.q2", "compliance.q3", "compliance.q4", "gravity.tilt_1", "gravity.tilt_2"]
    assert [p.unit for p in eff.params(m, f)][:4] == ["urad/(N m)"] * 3 + ["um/N"]
    # a machine carrying the effect, written out without the URDF: the masses go into its table
    text = FROM_URDF + "\n[effect.joint_compliance]\n" + "".join(f'"{n}" = 1.0\n' for n in names)
    with_effect = machine_from_text(text.replace('urdf = "arm.urdf"', f'urdf = "{arm[1]}"'), "m.toml")
    written = machine_file_text(with_effect)
    assert "urdf" not in written.split("[effect")[0] and "link_mass_kg" in written
    again = machine_from_text(written, "written.toml")
    np.testing.assert_allclose(dict(again.effects[0].settings)["link_mass_kg"], m.body_inertials.mass_kg)
    from bayescal.effects.stored import effect_delta_q

    np.testing.assert_allclose(effect_delta_q(again, again.effects, q), effect_delta_q(with_effect, with_effect.effects, q),
                               rtol=1e-9, atol=1e-15)
    # platform inputs beside the URDF's masses are refused, naming what to state instead
    from bayescal.errors import InputError

    with pytest.raises(InputError, match="state link_mass_kg"):
        get_effect("joint_compliance", platform_mass_kg=5.0).features(m, q, np.zeros(m.n_params), {}, None, None)


def test_a_negative_mass_is_refused_by_name(tmp_path):
    from bayescal.errors import MachineFileError

    (tmp_path / "arm.urdf").write_text(_urdf_with_inertials().replace('<mass value="2.0"/>', '<mass value="-2.0"/>'))
    (tmp_path / "m.toml").write_text(FROM_URDF)
    with pytest.raises(MachineFileError, match="link 'l3' of arm.urdf has mass -2.0"):
        load_machine(tmp_path / "m.toml")


def test_a_urdf_without_inertials_gives_no_masses(tmp_path):
    (tmp_path / "arm.urdf").write_text(URDF)
    (tmp_path / "m.toml").write_text(FROM_URDF)
    assert load_machine(tmp_path / "m.toml").body_inertials is None


_ROOT = Path(__file__).resolve().parents[2]
SHARED = next((p / "shared" / "data" / "real" / "tiago" for p in (_ROOT.parent, _ROOT.parent.parent)
               if (p / "shared" / "data" / "real" / "tiago").is_dir()), _ROOT.parent / "shared" / "data" / "real" / "tiago")


@pytest.mark.skipif(not (SHARED / "tiago.urdf").is_file(), reason="shared TIAGo URDF absent")
def test_tiago_link_masses_are_everything_above_the_torso_lift(tmp_path):
    """The TIAGo URDF (read in place, never copied): the moving links carry every mass hanging from the torso lift's
    child link (head, arm, gripper), summed here from the XML with lxml, independently of yourdfpy."""
    from lxml import etree

    urdf = (SHARED / "tiago.urdf").resolve()
    (tmp_path / "t.toml").write_text(f'kind = "serial"\nurdf = "{urdf.as_posix()}"\nbase_link = "base_footprint"\n'
                                     'tip_link = "arm_7_link"\n[tool]\npoint = [0.0, 0.0, 0.0]\n')
    m = load_machine(tmp_path / "t.toml")
    known = m.body_inertials
    assert known is not None and len(known.mass_kg) == m.n_actuators and np.all(known.mass_kg >= 0)
    root = etree.parse(str(urdf)).getroot()
    children = {}
    first = None
    for j in root.findall("joint"):
        children.setdefault(j.find("parent").get("link"), []).append(j.find("child").get("link"))
        if j.get("name") == "torso_lift_joint":
            first = j.find("child").get("link")
    mass = {ln.get("name"): float(ln.find("inertial/mass").get("value")) for ln in root.findall("link")
            if ln.find("inertial/mass") is not None}
    total, stack = 0.0, [first]
    while stack:
        link = stack.pop()
        total += mass.get(link, 0.0)
        stack += children.get(link, [])
    assert known.mass_kg.sum() == pytest.approx(total, rel=1e-12)


def test_a_written_calibrated_urdf_machine_keeps_its_links_and_their_weights(arm):
    # a URDF chain is written as [[joint]] tables: before, its link names (the bodies sensors are named after) and
    # its links' weights were lost, so a calibrated machine could not read its own recording's accel.<link> columns
    # and its gravity effects no longer knew the masses; checked against the URDF machine at the calibrated theta
    m, _ = arm
    rng = np.random.default_rng(3)
    theta = rng.normal(size=m.n_params) * m.tolerance
    again = machine_from_text(m.to_toml(theta), "written.toml")
    assert again.sensor_bodies == m.sensor_bodies and "tool_link" in again.sensor_bodies
    np.testing.assert_allclose(again.body_inertials.mass_kg, m.body_inertials.mass_kg, rtol=0, atol=0)
    np.testing.assert_allclose(again.body_inertials.com_mm, m.body_inertials.com_mm, rtol=0, atol=1e-12)
    q = m.sample_q(5, rng)
    frames = [m.body_frame(b) for b in m.sensor_bodies]
    R0, _ = m.body_rotations(q, theta, frames)
    R1, _ = again.body_rotations(q, None, [again.body_frame(b) for b in again.sensor_bodies])
    np.testing.assert_allclose(R1, R0, atol=1e-12)
    np.testing.assert_allclose(again.forward(q).position, m.forward(q, theta).position, atol=1e-9)


@pytest.mark.parametrize("edit, match", [
    (lambda t: t.replace("[tool]", "[[body]]\nname = \"cam\"\njoint = 7\n\n[tool]"), r"body\[1\]\.joint.*1 to 4"),
    (lambda t: t.replace("[tool]", "[[body]]\nname = \"joint2\"\njoint = 1\n\n[tool]"), r"body\[1\]\.name.*taken"),
    (lambda t: t.replace("mass = 1.0", "mass = -1.0", 1), r"joint\[1\]\.mass.*>= 0"),
    (lambda t: t.replace("mass = 1.0\n", "", 1), r"joint\[1\]\.mass'?: missing"),
])
def test_bad_body_and_mass_keys_are_named(edit, match):
    from bayescal.errors import MachineFileError

    text = ('kind = "serial"\n' + "".join(
        f'[[joint]]\ntype = "revolute"\norigin = [0.0, 0.0, {100.0 * k}]\naxis = [0.0, 0.0, 1.0]\nmass = 1.0\n'
        f"com = [0.0, 0.0, 10.0]\n\n" for k in range(1, 5)) + "[tool]\npoint = [0.0, 0.0, 50.0]\n")
    assert machine_from_text(text, "ok.toml").body_inertials.mass_kg.tolist() == [1.0] * 4
    with pytest.raises(MachineFileError, match=match):
        machine_from_text(edit(text), "bad.toml")
