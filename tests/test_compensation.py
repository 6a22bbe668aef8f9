import numpy as np
import pytest

from bayescal.compensation import CompensationGrid, build_grid, read_grid
from bayescal.errors import RecordingError


def test_bic_reproduces_a_bilinear_field_exactly():
    f = lambda x, z: np.column_stack([0.01 + 2e-5 * x - 3e-5 * z + 1e-7 * x * z, -0.02 + 1e-5 * x + 4e-7 * x * z])  # noqa: E731
    g = build_grid((-300, 300), (-200, 200), f, n=5)
    rng = np.random.default_rng(0)
    x, z = rng.uniform(-300, 300, 200), rng.uniform(-200, 200, 200)
    assert np.allclose(g.interpolate(x, z), f(x, z), atol=1e-14)
    assert np.allclose(g.compensate(x, z), np.column_stack([x, z]) - f(x, z), atol=1e-12)


def test_grid_csv_round_trip_with_std_room():
    g = build_grid((0, 10), (0, 5), lambda x, z: np.column_stack([x * 1e-3, z * 1e-3]), n=3)
    again = read_grid("g.csv", text=g.to_csv())
    assert np.array_equal(again.error, g.error) and np.isnan(again.std).all()
    std = np.full(g.error.shape, 0.001)
    g2 = CompensationGrid(g.xs, g.zs, g.error, std)
    assert np.array_equal(read_grid("g.csv", text=g2.to_csv()).std, std)


def test_bad_grid_files_name_line_and_column():
    good = build_grid((0, 1), (0, 1), lambda x, z: np.zeros((len(x), 2)), n=2).to_csv().splitlines()
    bad = good[:2] + [good[2].replace("0.0", "x", 1)] + good[3:]
    with pytest.raises(RecordingError, match="line 3"):
        read_grid("g.csv", text="\n".join(bad))
    with pytest.raises(RecordingError, match="every node once"):
        read_grid("g.csv", text="\n".join(good[:-1]))
