import numpy as np
import pytest

from bayescal.identifiability import analyse_identifiability
from bayescal.measurement import MeasurementModel
from bayescal.params import ParamLayout, ParamSpec


def _jac(prs3, dof, n=36, seed=0):
    q = prs3.sample_q(n, np.random.default_rng(seed))
    model = MeasurementModel(prs3, q, dof)
    pred = model.predict(None)
    return (model.jacobian(None, pred) / model.sigma[None, :, None]).reshape(-1, prs3.n_params)


@pytest.mark.parametrize("dof,rank", [(6, 33), (5, 32), (3, 30)])
def test_prs3_identifiable_counts(prs3, dof, rank):
    """6-DOF: the seed's 33 (11 per chain); the tool point is the platform-frame gauge.
    5-DOF loses the torsion gauge, position-only loses the two tilt gauges as well."""
    ida = analyse_identifiability(_jac(prs3, dof), prs3.layout)
    assert ida.rank == rank
    assert len(ida.kept) == rank
    if dof == 6:
        assert set(ida.fixed) == {"tool.point.x", "tool.point.y", "tool.point.z"}
        assert all(f"chain{i}.sphere_center.x" in c for c in ida.combinations[:1] for i in (1, 2, 3))


def test_known_dependency_named():
    """Two columns that enter only as their sum: the second is fixed and named."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(20, 1))
    J = np.hstack([a, a, rng.normal(size=(20, 2))])
    layout = ParamLayout(tuple(ParamSpec(n, "mm", "g") for n in ("rail_z", "offset", "p3", "p4")))
    ida = analyse_identifiability(J, layout)
    assert ida.rank == 3
    assert ida.fixed == ("offset",)
    assert "rail_z by +1 mm" in ida.combinations[0]


def test_round_off_columns_do_not_count_in_the_rank():
    """Columns at round-off level (1e-14 of the others) are zero, not unit columns of noise."""
    rng = np.random.default_rng(3)
    J = rng.normal(size=(40, 5))
    J = np.column_stack([J, 1e-15 * rng.normal(size=(40, 2))])
    layout = ParamLayout(tuple(ParamSpec(f"p{i}", "mm", "g") for i in range(7)))
    ida = analyse_identifiability(J, layout)
    assert ida.rank == 5 and len(ida.kept) == 5
    assert set(ida.fixed) == {"p5", "p6"}
    assert ida.singular_values[5:].max() == 0.0


def test_priority_order_puts_declared_unknown_parameters_first():
    from bayescal.identifiability import priority_order

    tol = np.array([0.05, 2e-4, 0.05, 100.0, 0.1, 1.0, 0.05])
    units = ["mm", "rad", "mm", "mm", "rad", "rad", "mm"]
    # 100 mm >= 10 x median(mm) and 1 rad >= 10 x median(rad) go first, the rest keep their order
    assert priority_order(tol, units).tolist() == [3, 5, 0, 1, 2, 4, 6]
    assert priority_order(np.full(4, 0.05), ["mm"] * 4).tolist() == [0, 1, 2, 3]


def test_priority_order_puts_nuisance_parameters_first():
    from bayescal.identifiability import priority_order

    tol = np.array([0.2, 0.2, 1.0, 0.2, 0.2, 5.0, 1.0])
    units = ["mm"] * 7
    # 5 is declared unknown (>= 10 x the median); 2 and 6 are nuisance (pivots) below that ratio
    assert priority_order(tol, units, nuisance=np.array([6, 2])).tolist() == [2, 6, 5, 0, 1, 3, 4]
    assert priority_order(tol, units, nuisance=np.array([5])).tolist() == [5, 0, 1, 2, 3, 4, 6]
