import json

from tests.conftest import ROOT


def test_study_quick_mode_meets_targets(tmp_path):
    import importlib.util

    spec = importlib.util.spec_from_file_location("study", ROOT / "studies" / "seed1_redundant_module.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert all(res["met"].values())
    for name in ("position_errors.png", "orientation_errors.png", "comparison.png", "bic_grid.csv", "rm1.csv", "bic_grid_predicted.csv", "bic_grid_std.png"):
        assert (tmp_path / name).stat().st_size > 0
