import numpy as np

from bayescal.cli import main
from bayescal.compensation import read_grid


def test_compensate_writes_and_evaluates(tmp_path):
    rng = np.random.default_rng(1)
    f = lambda x, z: (1e-4 * x + 2e-4 * z, -1e-4 * x)  # noqa: E731
    X, Z = np.meshgrid(np.linspace(-300, 300, 9), np.linspace(-200, 200, 9))
    rows = ["x,z,ex,ez"] + [f"{x},{z},{f(x, z)[0]},{f(x, z)[1]}" for x, z in zip(X.ravel(), Z.ravel())]
    (tmp_path / "e.csv").write_text("\n".join(rows) + "\n")
    xs, zs = rng.uniform(-300, 300, 20), rng.uniform(-200, 200, 20)
    (tmp_path / "f.csv").write_text("\n".join(["x,z,ex,ez"] + [f"{x},{z},{f(x, z)[0]},{f(x, z)[1]}" for x, z in zip(xs, zs)]) + "\n")
    assert main(["compensate", "--errors", str(tmp_path / "e.csv"), "--x-range", "-300", "300", "--z-range", "-200", "200",
                 "--out", str(tmp_path / "g.csv"), "--evaluate", str(tmp_path / "f.csv"), "--json", str(tmp_path / "a.json")]) == 0
    g = read_grid(tmp_path / "g.csv")
    assert g.error.shape == (5, 5, 2)
    import json

    ans = json.loads((tmp_path / "a.json").read_text())
    assert ans["max_after_mm"] < 1e-9 < ans["max_before_mm"]
    (tmp_path / "bad.csv").write_text("x,z,ex,ez\n1,2,oops,4\n")
    assert main(["compensate", "--grid", str(tmp_path / "g.csv"), "--evaluate", str(tmp_path / "bad.csv")]) == 2


def test_compensate_node_std_is_written(tmp_path):
    X, Z = np.meshgrid(np.linspace(-300, 300, 5), np.linspace(-200, 200, 5))
    (tmp_path / "e.csv").write_text("\n".join(["x,z,ex,ez"] + [f"{x},{z},0.001,0.002" for x, z in zip(X.ravel(), Z.ravel())]) + "\n")
    assert main(["compensate", "--errors", str(tmp_path / "e.csv"), "--x-range", "-300", "300", "--z-range", "-200", "200",
                 "--node-std", "0.00065", "--out", str(tmp_path / "g.csv")]) == 0
    assert np.all(read_grid(tmp_path / "g.csv").std == 0.00065)
    assert main(["compensate", "--errors", str(tmp_path / "e.csv"), "--x-range", "-300", "300", "--z-range", "-200", "200",
                 "--node-std", "-1"]) == 2
