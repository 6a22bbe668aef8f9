"""`bayescal grid --space tool` applies the machine file's [effect.*] tables under --aux, as the actuator space does."""

import json

import numpy as np

from bayescal.cli import main
from bayescal.machines.files import load_machine
from bayescal.redundant.restrained_recording import true_effect_values
from bayescal.simulate import draw_errors
from tests.conftest import PRS3_FILE, ROOT

RASPM = ROOT / "examples" / "raspm" / "machine.toml"
COMPLIANCE = """
[effect.joint_compliance]
"com.x" = 20.0
"com.y" = -15.0
"com.z" = -60.0
"gravity.tilt_1" = 0.0
"gravity.tilt_2" = 0.0
"compliance.q1" = 0.4
"compliance.q2" = 0.7
"compliance.q3" = 0.55
"platform_mass" = 40.0
"""


def test_tool_space_grid_under_a_payload(tmp_path, capsys):
    cal, rec = tmp_path / "cal.toml", tmp_path / "rec.csv"
    cal.write_text(PRS3_FILE.read_text() + COMPLIANCE)
    assert main(["simulate", "--machine", str(cal), "--poses", "40", "--seed", "2", "--aux", "payload_kg",
                 "--out", str(rec), "--quiet"]) == 0
    for payload in ("0", "25"):
        assert main(["grid", str(rec), "--machine", str(cal), "--space", "tool", "--nodes", "3",
                     "--aux", f"payload_kg={payload}", "--nc", str(tmp_path / f"nc{payload}.csv"),
                     "--json", str(tmp_path / f"g{payload}.json")]) == 0
    assert "joint_compliance applied at payload_kg = 25" in capsys.readouterr().out
    g0, g25 = (np.loadtxt(tmp_path / f"nc{p}.csv", delimiter=",", skiprows=1) for p in ("0", "25"))
    np.testing.assert_array_equal(g0[:, :6], g25[:, :6])  # same nodes
    assert np.abs(g25[:, 6:9] - g0[:, 6:9]).max() > 2e-3  # 25 kg on ~0.5 um/N drives: microns at the tool
    assert json.loads((tmp_path / "g25.json").read_text())["aux"] == {"payload_kg": 25.0}
    # the table was fitted with a payload: without --aux payload_kg it cannot be applied, and says what to give
    assert main(["grid", str(rec), "--machine", str(cal), "--space", "tool", "--nodes", "3"]) == 2
    err = capsys.readouterr().err
    assert str(cal) in err and "effect.joint_compliance" in err and "--aux payload_kg=VALUE" in err


def test_raspm_tool_grid_applies_the_redundancy_preload(tmp_path, capsys):
    m = load_machine(RASPM)
    from bayescal.effects import get_effect

    eff = get_effect("redundancy_preload")
    f = eff.features(m, m.sample_q(3, np.random.default_rng(0)), np.zeros(m.n_params), {}, None, None)

    class Sim:
        theta, stiffness = 0.2 * draw_errors(m, np.random.default_rng(4)), np.array([300.0, 200.0, 400.0, 250.0]) * 1e3

    vals = true_effect_values(m, Sim, eff.params(m, f))
    cal, rec = tmp_path / "raspm_cal.toml", tmp_path / "rec.csv"
    cal.write_text(RASPM.read_text() + "\n[effect.redundancy_preload]\n" + "".join(f'"{k}" = {v!r}\n' for k, v in vals.items()))
    assert main(["simulate", "--machine", str(cal), "--poses", "40", "--seed", "1", "--out", str(rec), "--quiet"]) == 0
    box = ["--range", "x=-150:150", "--range", "z=-480:-300", "--nodes", "3"]
    assert main(["grid", str(rec), "--machine", str(cal), *box, "--out", str(tmp_path / "g.csv")]) == 0
    assert "redundancy_preload applied at no auxiliary channel" in capsys.readouterr().out
    g = np.loadtxt(tmp_path / "g.csv", delimiter=",", skiprows=1)
    # columns x, y, z, q1..q4, dx, dy, dz: the redundant drive q2 is commanded as the pose requires (it was
    # left at mid-stroke before, and the preload of that jammed command was put in the grid)
    q = g[:, 3:7]
    np.testing.assert_allclose(q, m.inverse_planar(m.forward_planar(q)[0]), atol=1e-6)
    # the preload's size at the nodes against the restrained physics: tests/bayes/test_tool_grid_effects.py
    # (here the identification on the simulated recording differs between the two machines, so the grids do too)
