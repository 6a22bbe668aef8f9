"""The real TIAGo conversion (studies/convert_tiago.py): the bundled source is the upstream files, the shipped
example is the converter's output, the recording is the source's columns in mm, and the machine file's chain is
the forward kinematics of the data set's parameter table (and, when the shared copy is present, of the URDF it
tabulates, read in place: it is CC BY-NC-ND and never copied)."""

import csv
import hashlib
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bayescal.io.recording import read_recording
from bayescal.machines.check import check_machine
from bayescal.machines.files import load_machine
from tests.studies.conftest import load_study

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "tiago"
SOURCE = EXAMPLE / "source"
SHARED = next(
    (p / "shared" / "data" / "real" / "tiago" for p in (ROOT.parent, ROOT.parent.parent) if (p / "shared").is_dir()),
    ROOT.parent / "shared" / "data" / "real" / "tiago",
)
needs_shared = pytest.mark.skipif(not (SHARED / "tiago_48_schunk.urdf").is_file(), reason="shared TIAGo data absent")


@pytest.fixture(scope="module")
def conv():
    return load_study("convert_tiago")


def _git_blob(data: bytes) -> str:
    """The id git gives a file's content (sha1 of ``blob <size>\\0<data>``)."""
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def test_bundled_files_are_the_upstream_ones(conv):
    readme = (EXAMPLE / "README.md").read_text()
    for name, blob in conv.BLOBS.items():
        path = EXAMPLE / "LICENSE" if name == "LICENSE" else SOURCE / name
        assert _git_blob(path.read_bytes()) == blob, name
        assert blob in readme
    # the data set's README gives the CSV's sha256 prefix too
    assert hashlib.sha256((SOURCE / conv.CSV_NAME).read_bytes()).hexdigest().startswith("d7fcbd96e3e67319")
    assert "Apache License" in (EXAMPLE / "LICENSE").read_text()
    text = (EXAMPLE / "LICENSE-Apache-2.0.txt").read_text()
    assert "Version 2.0, January 2004" in text and "TERMS AND CONDITIONS" in text
    # the CC BY-NC-ND URDFs are not bundled, in any form
    assert not list(EXAMPLE.rglob("*.urdf")) and "urdf" not in tomllib.loads((EXAMPLE / "machine.toml").read_text())


@needs_shared
def test_bundled_files_are_the_shared_copy(conv):
    for name in (conv.CSV_NAME, *conv.CONFIGS):
        assert (SOURCE / name).read_bytes() == (SHARED / name).read_bytes(), name
    assert (EXAMPLE / "LICENSE").read_bytes() == (SHARED / "LICENSE").read_bytes()
    assert (EXAMPLE / "LICENSE-Apache-2.0.txt").read_bytes() == (SHARED.parent / "positioner" / "LICENSE").read_bytes()


def test_shipped_example_is_the_converters_output(conv, tmp_path):
    conv.convert(SOURCE, tmp_path, apache_text=EXAMPLE / "LICENSE-Apache-2.0.txt")
    for name in ("machine.toml", "recording.csv", "README.md", "LICENSE", "LICENSE-Apache-2.0.txt"):
        assert (tmp_path / name).read_bytes() == (EXAMPLE / name).read_bytes(), name
    for name in (conv.CSV_NAME, *conv.CONFIGS):
        assert (tmp_path / "source" / name).read_bytes() == (SOURCE / name).read_bytes()


def test_recording_is_the_sources_columns_in_mm():
    with open(SOURCE / "qualysis_base_hand_calibration.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    rec = read_recording(EXAMPLE / "recording.csv")
    assert rec.n_poses == len(rows) == 34 and rec.dof == 3
    joints = ["torso_lift_joint"] + [f"arm_{i}_joint" for i in range(1, 8)]
    q = np.array([[float(r[j]) for j in joints] for r in rows])
    q[:, 0] *= 1000.0
    assert np.allclose(rec.q, q, rtol=1e-15, atol=1e-12)
    assert np.allclose(rec.position, 1000.0 * np.array([[float(r[c]) for c in ("x1", "y1", "z1")] for r in rows]),
                       rtol=1e-15, atol=1e-12)


def _urdf_like_fk(q: np.ndarray) -> np.ndarray:
    """The chain of the data set's README table, written out here once more: Trans(xyz) Rz Ry Rx, then the joint."""
    h = np.pi / 2
    table = [((0, 0, 0.0985 + 0.193 + 0.597), (0, 0, 0), -0.062), ((0.15505, 0.014, -0.151), (0, 0, -h), 0),
             ((0.125, 0.0195, -0.031), (h, 0, 0), 0), ((0.0895, 0, -0.0015), (-h, 0, h), 0),
             ((-0.02, -0.027, -0.222), (-h, -h, 0), 0), ((-0.162, 0.02, 0.027), (0, -h, 0), 0),
             ((0, 0, 0.15), (0, -h, -h), 0), ((0, 0, 0), (h, 0, h), 0)]
    tail = [((0, 0, 0.046), (h, -h, np.pi)), ((0.00785, 0, 0), (h, 0, h)), ((0, 0, 0.012725), (-h, -h, 0))]

    def T(xyz, rpy):
        M = np.eye(4)
        M[:3, :3] = Rotation.from_euler("ZYX", rpy[::-1]).as_matrix()  # intrinsic z-y-x = Rz(y) Ry(p) Rx(r)
        M[:3, 3] = xyz
        return M

    out = []
    for qi in q:
        M = np.eye(4)
        for k, ((x, y, z), rpy, dx) in enumerate(table):
            M = M @ T((x + dx, y, z), rpy)
            M = M @ (T((0, 0, qi[0] / 1000.0), (0, 0, 0)) if k == 0 else T((0, 0, 0), (0, 0, qi[k])))
        for xyz, rpy in tail:
            M = M @ T(xyz, rpy)
        out.append(M[:3, 3] * 1000.0)
    return np.array(out)


def test_machine_is_the_tabled_chain(conv):
    m = load_machine(EXAMPLE / "machine.toml")
    assert check_machine(m) == []
    assert m.kind == "serial" and m.actuator_units == ("mm",) + ("rad",) * 7
    rec = read_recording(EXAMPLE / "recording.csv")
    rng = np.random.default_rng(0)
    q = np.vstack([rec.q, m.sample_q(20, rng)])
    p = m.forward(q)
    assert np.allclose(p.position, _urdf_like_fk(q), atol=1e-9)
    T = conv.forward(q)
    assert np.allclose(p.position, T[:, :3, 3], atol=1e-9) and np.allclose(p.rotation, T[:, :3, :3], atol=1e-12)
    assert np.all(m.check_q(rec.q) == rec.q)  # every recorded posture within q_limits


@needs_shared
def test_machine_is_the_urdf_figaroh_loads(tmp_path):
    """Against bayescal's reading of the URDF itself (in place): the same tool poses, the same parameters."""
    urdf = (SHARED / "tiago_48_schunk.urdf").resolve()
    (tmp_path / "u.toml").write_text(f'kind = "serial"\nurdf = "{urdf.as_posix()}"\nbase_link = "base_footprint"\n'
                                     'tip_link = "wrist_ft_tool_link"\n[tool]\npoint = [0.0, 0.0, 0.0]\n')
    u = load_machine(tmp_path / "u.toml")
    m = load_machine(EXAMPLE / "machine.toml")
    q = m.sample_q(50, np.random.default_rng(1))
    assert m.layout.names == u.layout.names
    pu, pm = u.forward(q), m.forward(q)
    assert np.allclose(pm.position, pu.position, atol=1e-6) and np.allclose(pm.rotation, pu.rotation, atol=1e-9)
    # the same parametrisation: at a pitch of -pi/2 the roll/yaw split decides what the rpy parameters perturb,
    # and a MAP fit depends on it; the joints keep the URDF's split (the tool's rpy is not measured by a point)
    assert np.allclose(m.rpy, u.rpy, atol=1e-10)
    keep = [i for i, n in enumerate(m.layout.names) if not n.startswith("tool.rpy")]
    Jm, Ju = m.tool_jacobian(q, None, pm)[:, :3, keep], u.tool_jacobian(q, None, pu)[:, :3, keep]
    assert np.allclose(Jm, Ju, atol=1e-6 * np.abs(Ju).max())
