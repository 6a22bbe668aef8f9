"""The hybrid kind (docs/formats.md section 5): stacking against a hand-composed chain of 4x4
transforms, the chain-rule Jacobian against central differences, conformance, the inline
calibrated file, nested states through measurement subsets and stacked parameter sets, and
the identifiability across modules."""

from pathlib import Path

import numpy as np
import pytest

from bayescal.errors import MachineFileError
from bayescal.geometry import so3_log
from bayescal.identifiability import analyse_identifiability
from bayescal.machines import KINDS, Hybrid
from bayescal.machines.check import check_machine
from bayescal.machines.files import load_machine, machine_from_text
from bayescal.machines.base import Machine
from bayescal.measurement import MeasurementModel

ROOT = Path(__file__).resolve().parents[2]
WRIST = ROOT / "examples" / "hybrid_wrist" / "machine.toml"
TABLE = ROOT / "examples" / "hybrid_table" / "machine.toml"


@pytest.fixture(scope="module")
def wrist():
    return load_machine(WRIST)


@pytest.fixture(scope="module")
def table():
    return load_machine(TABLE)


def _T(R, p):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def test_registered_layout_and_units(wrist, table):
    assert KINDS["hybrid"] is Hybrid
    assert wrist.n_actuators == 5 and wrist.actuator_units == ("mm",) * 3 + ("rad",) * 2
    assert wrist.layout.names[0] == "m1.chain1.sphere_center.x"
    assert "m2.joint2.offset" in wrist.layout.names and "m2.tool.rpy.y" == wrist.layout.names[-1]
    assert wrist.n_params == 36 + 2 * 9 + 6
    assert table.roles == ("tool", "table")
    assert np.array_equal(table.q_limits[3], [-3.14159, 3.14159])


@pytest.mark.parametrize("which", ["wrist", "table"])
def test_stacking_matches_hand_composed_transforms(which, wrist, table):
    """Each module's forward kinematics alone, composed here as 4x4 matrices: the wrist on the
    head's tool frame, and the head's tool relative to the table's last frame."""
    m = wrist if which == "wrist" else table
    rng = np.random.default_rng(3)
    q = m.sample_q(10, rng)
    theta = rng.normal(size=m.n_params) * m.tolerance * 20
    head, second = m.modules
    th_head, th_second = theta[: head.n_params], theta[head.n_params :]
    ph = head.forward(q[:, :3], th_head)
    ps = second.forward(q[:, 3:], th_second)
    got = m.forward(q, theta)
    assert got.success.all()
    for i in range(q.shape[0]):
        Th, Ts = _T(ph.rotation[i], ph.position[i]), _T(ps.rotation[i], ps.position[i])
        M = Th @ Ts if which == "wrist" else np.linalg.inv(Ts) @ Th
        assert np.allclose(got.position[i], M[:3, 3], atol=1e-9)
        assert np.allclose(got.rotation[i], M[:3, :3], atol=1e-12)


def test_table_rotation_turns_the_measured_tool_the_other_way(table):
    """A turn of the table by a about its (vertical, nominal) axis turns the tool seen from the
    workpiece by -a about the axis through the table centre."""
    q = np.array([[500.0, 500.0, 500.0, 0.0], [500.0, 500.0, 500.0, 0.7]])
    p = table.forward(q)
    Rz = np.array([[np.cos(-0.7), -np.sin(-0.7), 0], [np.sin(-0.7), np.cos(-0.7), 0], [0, 0, 1]])
    assert np.allclose(p.position[1], Rz @ p.position[0], atol=1e-9)
    assert np.allclose(p.rotation[1], Rz @ p.rotation[0], atol=1e-12)


@pytest.mark.parametrize("which", ["wrist", "table"])
def test_jacobian_matches_central_differences(which, wrist, table):
    m = wrist if which == "wrist" else table
    rng = np.random.default_rng(8)
    q = m.sample_q(6, rng)
    theta = rng.normal(size=m.n_params) * m.tolerance * 3
    poses = m.forward(q, theta)
    J = m.tool_jacobian(q, theta, poses)
    for k in range(m.n_params):
        h = 1e-3 * m.tolerance[k]
        e = np.zeros(m.n_params)
        e[k] = h
        a, b = m.forward(q, theta + e, guess=poses), m.forward(q, theta - e, guess=poses)
        fd_p = (a.position - b.position) / (2 * h)
        fd_w = so3_log(a.rotation @ np.swapaxes(b.rotation, 1, 2)) / (2 * h)
        assert np.abs(J[:, :3, k] - fd_p).max() <= 1e-5 * (1 + np.abs(fd_p).max()), m.layout.names[k]
        assert np.abs(J[:, 3:, k] - fd_w).max() <= 1e-5 * (1e-3 + np.abs(fd_w).max()), m.layout.names[k]
    Ja = m.actuator_jacobian(q, theta, poses)
    assert np.allclose(Ja, Machine.actuator_jacobian(m, q, theta, poses), atol=1e-6)


@pytest.mark.parametrize("which", ["wrist", "table"])
def test_check_machine(which, wrist, table):
    assert check_machine(wrist if which == "wrist" else table, seed=5) == []


def test_calibrated_file_is_self_contained(table, tmp_path):
    """to_toml writes the modules inline; the text alone, read elsewhere, predicts the same."""
    rng = np.random.default_rng(2)
    theta = rng.normal(size=table.n_params) * table.tolerance
    text = table.to_toml(theta)
    assert "file =" not in text and "[module.machine]" in text and "[[module.machine.chain]]" in text
    (tmp_path / "cal.toml").write_text(text)
    again = load_machine(tmp_path / "cal.toml")
    q = table.sample_q(5, rng)
    a, b = table.forward(q, theta), again.forward(q)
    assert np.allclose(a.position, b.position, atol=1e-9)
    assert again.noise == table.noise and np.array_equal(again.q_limits, table.q_limits)


def test_nested_state_survives_subsets_and_stacked_parameter_sets(wrist):
    """MeasurementModel.subset and the tiling of warm starts for k stacked parameter vectors go
    through the modules' states inside the hybrid's state."""
    rng = np.random.default_rng(4)
    q = wrist.sample_q(8, rng)
    model = MeasurementModel(wrist, q, 6, guess=wrist.forward(q))
    sub = model.subset([1, 5, 6])
    assert np.allclose(sub.predict(None).y, model.predict(None).y[[1, 5, 6]], atol=1e-9)
    thetas = rng.normal(size=(3, wrist.n_params)) * wrist.tolerance
    stacked = model.predict(np.repeat(thetas, 8, axis=0))
    for s in range(3):
        assert np.allclose(stacked.y[8 * s : 8 * s + 8], model.predict(thetas[s]).y, atol=1e-9)


def _ida(m, dof):
    q = m.sample_q(80, np.random.default_rng(0))
    model = MeasurementModel(m, q, dof)
    J = (model.jacobian(None, model.predict(None)) / model.sigma[None, :, None]).reshape(-1, m.n_params)
    return analyse_identifiability(J, m.layout)


@pytest.mark.parametrize("dof,head_rank", [(6, 33), (5, 32), (3, 30)])
def test_identifiability_across_modules(wrist, table, dof, head_rank):
    """The head keeps what it has alone (33 / 32 / 30); each rotary axis adds the 4 parameters of
    its line (two tilts, two positions); the table's placement and zero offset, and the wrist's
    mounting on the platform, are a rigid motion of the head's frames and are not separated."""
    w, t = _ida(wrist, dof), _ida(table, dof)
    assert w.rank == head_rank + 8
    assert t.rank == head_rank + 4
    assert [k for k in t.kept if k.startswith("m2.")] == [
        "m2.joint1.axis.tilt_x", "m2.joint1.axis.tilt_y", "m2.tool.point.x", "m2.tool.point.y"
    ]
    assert {"m2.joint1.offset", "m2.joint1.origin.x", "m2.joint1.origin.y", "m2.joint1.origin.z"} <= set(t.fixed)
    assert {"m2.joint1.origin.x", "m2.joint1.origin.y", "m2.joint1.origin.z"} <= set(w.fixed)
    text = "\n".join(t.combinations)
    assert "m2.joint1.origin.x: a change of 1 mm looks the same" in text and "rail_origin.x by -1 mm" in text


@pytest.mark.parametrize(
    "edit,key",
    [
        (('role = "table"', 'role = "workpiece"'), "module[2].role"),
        (('role = "table"', 'role = "table"\nmachine = 1'), "module[2].file"),
        (('file = "table.toml"', 'file = "none.toml"'), "module[2].file"),  # named from the key that points there
        (('role = "tool"', 'role = "table"'), "module"),
    ],
)
def test_bad_hybrid_files(edit, key, tmp_path):
    for f in ("head.toml", "table.toml"):
        (tmp_path / f).write_text((TABLE.parent / f).read_text())
    (tmp_path / "machine.toml").write_text(TABLE.read_text().replace(*edit))
    with pytest.raises(MachineFileError) as err:
        load_machine(tmp_path / "machine.toml")
    assert err.value.key == key


def test_inline_module_errors_name_the_nested_key():
    text = 'kind = "hybrid"\n[[module]]\nrole = "tool"\n[module.machine]\nkind = "serial"\n[[module.machine.joint]]\ntype = "revolute"\norigin = [0.0, 0.0, 0.0]\n[module.machine.tool]\npoint = [0.0, 0.0, 1.0]\n'
    with pytest.raises(MachineFileError) as err:
        machine_from_text(text, "h.toml")
    assert err.value.key == "module[1].machine.joint[1].axis"


def test_example_recording_identifies_the_true_machine(table):
    """The shipped simulated recording: the calibrated hybrid (written with to_toml and read back)
    predicts the true machine (recording.truth.toml) on fresh poses to a few micrometres."""
    from bayescal.identify import identify
    from bayescal.io.recording import read_recording

    rec = read_recording(TABLE.parent / "recording.csv")
    res = identify(MeasurementModel.from_recording(table, rec), method="ls")
    assert res.success
    calibrated = machine_from_text(table.to_toml(res.theta))
    truth = load_machine(TABLE.parent / "recording.truth.toml")
    q = table.sample_q(50, np.random.default_rng(1))
    a, b, nominal = calibrated.forward(q), truth.forward(q), table.forward(q)
    assert np.abs(a.position - b.position).max() < 0.01 < np.abs(nominal.position - b.position).max()
    assert np.abs(so3_log(a.rotation @ np.swapaxes(b.rotation, 1, 2))).max() < 1e-4


def test_write_machine_files_uses_module_files(table, tmp_path):
    """The file-per-module form of docs/formats.md section 5: module files beside the hybrid file,
    each a plain machine file of its kind, read back to the same predictions."""
    from bayescal.machines import write_machine_files

    theta = np.random.default_rng(6).normal(size=table.n_params) * table.tolerance
    written = write_machine_files(tmp_path / "cal.toml", table, theta)
    assert [p.name for p in written] == ["cal.toml", "cal.m1.toml", "cal.m2.toml"]
    main = (tmp_path / "cal.toml").read_text()
    assert 'file = "cal.m1.toml"' in main and "[module.machine]" not in main
    assert load_machine(tmp_path / "cal.m2.toml").kind == "serial"
    again = load_machine(tmp_path / "cal.toml")
    q = table.sample_q(5, np.random.default_rng(0))
    a, b = table.forward(q, theta), again.forward(q)
    assert np.allclose(a.position, b.position, atol=1e-9) and np.allclose(a.rotation, b.rotation, atol=1e-12)
    assert again.noise == table.noise and np.array_equal(again.q_limits, table.q_limits)


# ----------------------------------------------------------------- files that used to hang or recurse
_WRIST_FILE = ROOT / "examples" / "hybrid_wrist" / "wrist.toml"


def _hybrid_of(path, *modules):
    path.write_text('kind = "hybrid"\n' + "".join(f'[[module]]\nfile = "{m}"\nrole = "tool"\n' for m in modules))
    return path


def test_a_module_file_that_includes_itself_is_refused_naming_the_cycle(tmp_path):
    _hybrid_of(tmp_path / "self.toml", "self.toml")
    with pytest.raises(MachineFileError, match=r"self.toml includes itself \(.*self.toml -> .*self.toml\)") as err:
        load_machine(tmp_path / "self.toml")
    assert err.value.key == "module[1].file"
    (tmp_path / "wrist.toml").write_text(_WRIST_FILE.read_text())
    _hybrid_of(tmp_path / "a.toml", "b.toml")
    _hybrid_of(tmp_path / "b.toml", "wrist.toml", "./c.toml")
    _hybrid_of(tmp_path / "c.toml", "a.toml")
    with pytest.raises(MachineFileError, match=r"a.toml is part of a cycle of module files \(.*a.toml -> .*b.toml -> .*c.toml -> .*a.toml\)") as err:
        load_machine(tmp_path / "a.toml")
    assert err.value.key == "module[1].file" and str(tmp_path / "c.toml") in str(err.value)


def test_the_same_module_file_twice_side_by_side_is_no_cycle(tmp_path):
    (tmp_path / "wrist.toml").write_text(_WRIST_FILE.read_text())
    m = load_machine(_hybrid_of(tmp_path / "h.toml", "wrist.toml", "wrist.toml"))
    assert m.n_actuators == 4


def test_nesting_is_allowed_to_the_stated_depth_and_refused_beyond(tmp_path):
    from bayescal.machines.hybrid import MAX_NESTING

    (tmp_path / "wrist.toml").write_text(_WRIST_FILE.read_text())
    prev = "wrist.toml"
    for k in range(MAX_NESTING + 1):
        prev = _hybrid_of(tmp_path / f"n{k}.toml", prev).name
    deepest = load_machine(tmp_path / f"n{MAX_NESTING - 1}.toml")  # MAX_NESTING hybrids around the wrist
    assert deepest.n_actuators == 2 and deepest.layout.names[0] == "m1." * MAX_NESTING + "joint1.offset"
    with pytest.raises(MachineFileError, match=f"nested more than {MAX_NESTING} levels deep") as err:
        load_machine(tmp_path / f"n{MAX_NESTING}.toml")
    assert err.value.key == "module"


def _unblock_fifo_later(path):
    """If a reader ever blocks on the FIFO (the bug), a writer opens and closes it after a few seconds so
    that the test fails instead of hanging."""
    import os
    import threading

    def later():
        import time

        time.sleep(5.0)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
            os.close(fd)
        except OSError:  # no reader: nothing was blocked
            pass

    threading.Thread(target=later, daemon=True).start()


def test_a_fifo_or_device_module_file_is_refused_unread(tmp_path):
    import os

    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    _unblock_fifo_later(fifo)
    with pytest.raises(MachineFileError, match="not a regular file") as err:
        load_machine(_hybrid_of(tmp_path / "h.toml", "fifo.toml"))
    # named from the key that points there, with the module's path
    assert err.value.path == str(tmp_path / "h.toml") and err.value.key.endswith(".file") and str(fifo) in str(err.value)
    with pytest.raises(MachineFileError, match="not a regular file"):
        load_machine(fifo)
    if os.path.exists("/dev/null"):  # a character device (reading /dev/zero instead never ended)
        with pytest.raises(MachineFileError, match="not a regular file"):
            load_machine(_hybrid_of(tmp_path / "d.toml", "/dev/null"))


def test_a_module_file_with_a_whole_machine_table_is_refused_by_name(tmp_path):
    import shutil

    from bayescal.errors import MachineFileError
    from bayescal.machines.files import load_machine

    src = Path(__file__).resolve().parents[2] / "examples" / "hybrid_table"
    for f in src.glob("*.toml"):
        shutil.copy(f, tmp_path / f.name)
    head = tmp_path / "head.toml"
    head.write_text(head.read_text() + "\n[instrument]\norigin = [0.0, 0.0, 0.0]\n")
    with pytest.raises(MachineFileError, match=r"a module has a \[instrument\] table; expected it in the hybrid"):
        load_machine(tmp_path / "machine.toml")


def test_a_missing_module_file_is_named_from_its_key(tmp_path):
    """A probe found 'nope.toml: file not found' without the hybrid file and key that named it."""
    with pytest.raises(MachineFileError, match="nope.toml: file not found") as err:
        load_machine(_hybrid_of(tmp_path / "h.toml", "nope.toml"))
    assert err.value.path == str(tmp_path / "h.toml") and err.value.key.endswith(".file")
