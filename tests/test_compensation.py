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


# ------------------------------------------------------------------ refusals (issue 30)
from bayescal.compensation import evaluate_grid, table_interpolator, write_grid  # noqa: E402
from bayescal.errors import InputError  # noqa: E402


@pytest.mark.parametrize("pts, match", [
    ([[0, 0]], "1 distinct point"),
    ([[0, 0], [1, 0], [2, 0]], "3 distinct point.* on one line"),
    ([[0, 0], [0, 0], [1, 1], [2, 2]], "on one line"),
])
def test_error_tables_without_an_area_are_refused(pts, match):
    t = np.column_stack([np.asarray(pts, float), np.zeros((len(pts), 2))])
    with pytest.raises(RecordingError, match=f"e.csv: .*{match}"):
        table_interpolator("e.csv", t)


def test_a_table_interpolator_reproduces_a_linear_field_and_names_uncovered_nodes():
    X, Z = np.meshgrid(np.linspace(-1, 1, 3), np.linspace(-1, 1, 3))
    t = np.column_stack([X.ravel(), Z.ravel(), 0.01 * X.ravel(), -0.02 * Z.ravel()])
    at = table_interpolator("e.csv", t)
    assert np.allclose(at(np.array([0.5]), np.array([-0.25])), [[0.005, 0.005]], atol=1e-15)
    with pytest.raises(RecordingError, match="do not cover every grid node"):
        at(np.array([5.0]), np.array([0.0]))


def test_implausible_node_errors_are_neither_built_nor_written_nor_read(tmp_path):
    with pytest.raises(InputError, match=r"node \(0, 0\) has ex = 1e\+300 mm; expected a finite value of at most 2 mm"):
        build_grid((-10, 10), (-10, 10), lambda x, z: np.column_stack([np.where(x < 0, 1e300, 0.0), 0 * z]), n=2)
    g = build_grid((-10, 10), (-10, 10), lambda x, z: np.zeros((len(x), 2)), n=2)
    bad = CompensationGrid(g.xs, g.zs, np.full(g.error.shape, 3.0))
    with pytest.raises(InputError, match="not writing .*g.csv"):
        write_grid(tmp_path / "g.csv", bad)
    assert not (tmp_path / "g.csv").exists()
    with pytest.raises(RecordingError, match="g.csv: the grid: node"):
        read_grid("g.csv", text=bad.to_csv())
    with pytest.raises(InputError, match="std_ex = inf"):
        CompensationGrid(g.xs, g.zs, g.error, np.full(g.error.shape, np.inf)).check_plausible()


def test_evaluation_refuses_points_outside_the_grid_naming_the_line():
    g = build_grid((-10, 10), (-10, 10), lambda x, z: np.column_stack([1e-3 * x, 0 * z]), n=3)
    inside = np.array([[0.0, 0.0, 0.002, 0.0], [10.0, -10.0, 0.01, 0.0]])
    ans = evaluate_grid(g, inside, "f.csv")
    assert ans["max_before_mm"] == 0.01 and ans["max_after_mm"] == pytest.approx(0.002)
    with pytest.raises(RecordingError, match=r"f.csv: line 3, column 'x': point \(5000.0, 0.0\) mm is outside the grid"):
        evaluate_grid(g, np.vstack([inside[:1], [5000.0, 0.0, 0.1, 0.1]]), "f.csv")


def test_a_grid_too_large_for_memory_is_refused_before_it_is_built():
    with pytest.raises(InputError, match=r"a grid of 100000000 x 100000000 nodes needs about .* lower the nodes per axis \(--n\)"):
        build_grid((0, 1), (0, 1), lambda x, z: np.zeros((len(x), 2)), n=10**8)


def test_a_point_measured_again_with_another_error_is_refused_and_exact_repeats_are_read():
    # the triangulation kept one of the two errors, silently
    square = [[0, 0, 0.01, 0.0], [10, 0, 0.02, 0.0], [0, 10, 0.0, 0.01], [10, 10, 0.01, 0.01]]
    t = np.array(square + [[10, 0, 0.05, 0.0]], float)
    with pytest.raises(RecordingError, match=r"line 6: the point \(10, 0\) mm is measured again with another error "
                       r"\(line 3\)") as err:
        table_interpolator("e.csv", t)
    assert err.value.row == 6
    at = table_interpolator("e.csv", np.array(square + [square[1]], float))
    np.testing.assert_allclose(at(np.array([5.0]), np.array([5.0])), [[0.01, 0.005]])


def test_a_negative_node_std_in_a_grid_file_is_refused():
    good = build_grid((0, 1), (0, 1), lambda x, z: np.zeros((len(x), 2)), n=2).to_csv().splitlines()
    cells = good[2].split(",")
    cells[6] = "-1"
    with pytest.raises(RecordingError, match=r"line 3, column 'std_ex': expected a one-sigma >= 0 \(mm\)"):
        read_grid("g.csv", text="\n".join(good[:2] + [",".join(cells)] + good[3:]))
