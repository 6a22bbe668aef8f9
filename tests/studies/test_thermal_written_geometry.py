"""studies/thermal_written_geometry.py: its variants, its truth at a temperature, and a --quick run."""

import numpy as np

from tests.studies.conftest import load_study


def _study():
    return load_study("thermal_written_geometry")


def test_variants_change_only_the_start_and_the_channels():
    st = _study()
    case = st._concealed().make_case("phys_thermal", 1, 2026, (60, 70))
    case = {**case, "aux": ["time_s"]}
    assert st.variant_case(case, "as run") == case
    assert st.variant_case(case, "T0 = 20")["start_C"] == 20.0
    assert st.variant_case(case, "temp_C")["aux"] == ["time_s", "temp_C"]
    both = st.variant_case(case, "both")
    assert both["aux"] == ["time_s", "temp_C"] and both["start_C"] == 20.0 and both["seed"] == case["seed"]


def test_start_override_keeps_the_other_draws_and_truth_at_temperature():
    from bayescal.machines.files import machine_from_text

    st = _study()
    mod = st._concealed()
    case = mod.make_case("phys_thermal", 0, 2026, (60, 70))
    machine = machine_from_text(case["machine"], "m.toml")
    rec, theta, info = mod.physics_recording(machine, case, np.random.default_rng(case["seed"]))
    rec20, theta20, info20 = mod.physics_recording(machine, {**case, "start_C": 20.0}, np.random.default_rng(case["seed"]))
    assert info20["start_C"] == 20.0 and info["start_C"] != 20.0
    np.testing.assert_array_equal(theta, theta20)
    np.testing.assert_array_equal(rec.q, rec20.q)
    # the warm-up shifted by the start offset, nothing else
    np.testing.assert_allclose(info["transform"].dT - info20["transform"].dT, info["start_C"] - 20.0, atol=1e-12)
    q = rec.q[:20]
    np.testing.assert_allclose(st.truth_at(machine, info["transform"], theta, q, 20.0), machine.forward(q, theta).position,
                               atol=1e-9)
    # 5 K warmer: parts of ~1e2..1e3 mm grow by alpha (>= 0.9 um/m/K) * 5 K, i.e. by more than 0.1 um somewhere
    moved = np.linalg.norm(st.truth_at(machine, info["transform"], theta, q, 25.0) - machine.forward(q, theta).position, axis=1)
    assert moved.max() > 1e-4


def test_quick_run_writes_the_table(tmp_path):
    assert _study().main(["--quick", "--out", str(tmp_path)]) == 0
    text = (tmp_path / "summary.md").read_text()
    for v in ("as run", "T0 = 20", "temp_C", "both"):
        assert f"| {v} | 2 |" in text
