"""map_state: the one way consumers select, tile and merge poses in a kind's (possibly nested) state."""

from dataclasses import dataclass

import numpy as np

from bayescal.machines.base import map_state


@dataclass(frozen=True)
class _Leaf:
    p: np.ndarray
    R: np.ndarray


@dataclass(frozen=True)
class _Nest:
    position: np.ndarray
    modules: tuple


def test_map_state_recurses_through_dataclasses_and_tuples():
    leaf = _Leaf(p=np.arange(6.0).reshape(3, 2), R=np.arange(3.0))
    st = _Nest(position=np.arange(3.0), modules=(leaf, None))
    sub = map_state(lambda a: a[[2, 0]], st)
    assert isinstance(sub, _Nest) and isinstance(sub.modules[0], _Leaf) and sub.modules[1] is None
    assert np.array_equal(sub.modules[0].p, [[4.0, 5.0], [0.0, 1.0]])
    assert np.array_equal(sub.position, [2.0, 0.0])
    tiled = map_state(lambda a: np.tile(a, (2,) + (1,) * (a.ndim - 1)), st)
    assert tiled.modules[0].p.shape == (6, 2) and tiled.position.shape == (6,)
    assert map_state(lambda a: a, None) is None


def test_map_state_merges_two_states_leaf_by_leaf():
    a = _Nest(position=np.zeros(3), modules=(_Leaf(np.zeros((3, 2)), np.zeros(3)),))
    b = _Nest(position=np.ones(3), modules=(_Leaf(np.ones((3, 2)), np.ones(3)),))
    take = np.array([False, True, False])
    m = map_state(lambda x, y: np.where(take.reshape((-1,) + (1,) * (x.ndim - 1)), y, x), a, b)
    assert np.array_equal(m.position, [0.0, 1.0, 0.0])
    assert np.array_equal(m.modules[0].p[:, 1], [0.0, 1.0, 0.0])
