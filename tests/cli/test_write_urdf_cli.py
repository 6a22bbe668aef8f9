"""identify --write-urdf: a serial machine with mimic joints calibrated from a simulated recording, written
as a URDF whose yourdfpy kinematics is the calibrated machine file's; other kinds refused (exit 2)."""

import numpy as np

from bayescal.cli import main
from bayescal.machines.files import load_machine
from tests.conftest import ROOT
from tests.machines.test_mimic import TELESCOPE


def test_identify_writes_a_urdf_that_predicts_like_the_calibrated_machine_file(tmp_path, capsys):
    import yourdfpy

    machine, rec = tmp_path / "m.toml", tmp_path / "rec.csv"
    machine.write_text(TELESCOPE + "[measurement]\nsigma_position = 0.005\nsigma_angle = 5.0e-5\n")
    assert main(["simulate", "--machine", str(machine), "--poses", "40", "--seed", "3", "--out", str(rec), "--quiet"]) == 0
    assert rec.read_text().splitlines()[0].startswith("q1,q2,x")  # one q column per actuator, none for mimics
    urdf, cal = tmp_path / "cal.urdf", tmp_path / "cal.toml"
    code = main(["identify", str(rec), "--machine", str(machine), "--write-machine", str(cal), "--write-urdf", str(urdf)])
    assert code == 0
    assert f"wrote {urdf} (calibrated URDF)" in capsys.readouterr().err
    calibrated = load_machine(cal)
    robot = yourdfpy.URDF.load(str(urdf), build_scene_graph=True, load_meshes=False)
    assert robot.actuated_joint_names == ["joint1", "joint3"]
    q = calibrated.sample_q(6, np.random.default_rng(1))
    poses = calibrated.forward(q)
    for i in range(q.shape[0]):
        robot.update_cfg({"joint1": q[i, 0] / 1000.0, "joint3": q[i, 1]})
        T = robot.get_transform("tool", "base_link")
        np.testing.assert_allclose(1000.0 * T[:3, 3], poses.position[i], rtol=0, atol=1e-9)
        np.testing.assert_allclose(T[:3, :3], poses.rotation[i], rtol=0, atol=1e-12)


def test_write_urdf_is_refused_for_other_kinds_before_fitting(tmp_path, capsys):
    hyb = ROOT / "examples" / "hybrid_wrist"
    out = tmp_path / "x.urdf"
    code = main(["identify", str(hyb / "recording.csv"), "--machine", str(hyb / "machine.toml"), "--write-urdf", str(out)])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--write-urdf: a URDF describes a serial chain" in err[0] and "hybrid" in err[0]
    assert not out.exists()


def test_write_urdf_never_replaces_the_urdf_the_machine_file_reads(tmp_path, capsys):
    # the machine file's urdf = "arm.urdf" was read outside the run's inputs: --write-urdf arm.urdf replaced it
    from tests.machines.test_urdf import FROM_URDF, URDF

    (tmp_path / "arm.urdf").write_text(URDF)
    machine, rec = tmp_path / "m.toml", tmp_path / "rec.csv"
    machine.write_text(FROM_URDF)
    assert main(["simulate", "--machine", str(machine), "--poses", "30", "--seed", "2", "--out", str(rec), "--quiet"]) == 0
    capsys.readouterr()
    code = main(["identify", str(rec), "--machine", str(machine), "--method", "map", "--force",
                 "--write-urdf", str(tmp_path / "arm.urdf")])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "arm.urdf" in err[0], err
    assert (tmp_path / "arm.urdf").read_text() == URDF
