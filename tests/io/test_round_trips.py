"""Property tests: what bayescal writes, it reads back identically (recordings, machine files)."""

import math
import re

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bayescal.io import Recording, read_recording
from bayescal.io.recording import recording_to_csv
from bayescal.limits import SIGMA_ANGLE_RANGE, SIGMA_POSITION_RANGE
from bayescal.machines import Prs3
from bayescal.machines.files import machine_from_text
from bayescal.machines.base import MeasurementNoise
from bayescal.machines.prs3 import PRS3_TOLERANCE_DEFAULTS

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
_RESERVED = {"x", "y", "z", "rx", "ry", "rz", "nx", "ny", "nz"}
aux_name = st.from_regex(r"\A[A-Za-z_][A-Za-z0-9_]{0,11}\Z").filter(
    lambda s: s not in _RESERVED and not re.fullmatch(r"q[0-9]+", s)
)


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


direction = st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: math.hypot(*v) > 0.1).map(_unit)


@st.composite
def recordings(draw):
    n = draw(st.integers(1, 6))
    m = draw(st.integers(1, 4))
    arr = lambda k: np.array(draw(st.lists(finite, min_size=n * k, max_size=n * k))).reshape(n, k)  # noqa: E731
    dof = draw(st.sampled_from([3, 5, 6]))
    rotvec = arr(3) if dof == 6 else None
    axis = np.array([draw(direction) for _ in range(n)]) if dof == 5 else None
    names = draw(st.lists(aux_name, max_size=3, unique=True))
    aux = {k: arr(1)[:, 0] for k in names}
    return Recording(q=arr(m), position=arr(3), rotvec=rotvec, axis=axis, aux=aux)


@given(recordings())
@settings(max_examples=40, deadline=None)
def test_recording_write_read_is_identity(rec):
    back = read_recording("r.csv", text=recording_to_csv(rec))
    assert back.dof == rec.dof and list(back.aux) == list(rec.aux)
    assert np.array_equal(back.q, rec.q) and np.array_equal(back.position, rec.position)
    if rec.rotvec is not None:
        assert np.array_equal(back.rotvec, rec.rotvec)
    if rec.axis is not None:
        # the reader re-normalises the axis: at most a last-bit change
        assert np.allclose(back.axis, rec.axis, rtol=0, atol=4e-16)
    for k in rec.aux:
        assert np.array_equal(back.aux[k], rec.aux[k])


coord = st.floats(-1e3, 1e3, allow_nan=False)
vec3 = st.lists(coord, min_size=3, max_size=3).map(np.array)
positive = st.floats(1e-6, 1e3, allow_nan=False)
name_text = st.text(st.characters(blacklist_categories=("Cs",)), max_size=20)


@st.composite
def prs3_machines(draw):
    lo = np.array(draw(st.lists(coord, min_size=3, max_size=3)))
    span = np.array(draw(st.lists(positive, min_size=3, max_size=3)))
    # a stated noise within bayescal.limits' range (outside it a machine file is refused)
    noise = draw(st.one_of(st.just(MeasurementNoise()), st.builds(
        MeasurementNoise, st.floats(*SIGMA_POSITION_RANGE), st.floats(*SIGMA_ANGLE_RANGE), st.just(True))))
    return Prs3(
        rail_origin=np.array([draw(vec3) for _ in range(3)]),
        rail_direction=np.array([draw(direction) for _ in range(3)]),
        revolute_axis=np.array([draw(direction) for _ in range(3)]),
        sphere_center=np.array([draw(vec3) for _ in range(3)]),
        link_length=np.array(draw(st.lists(st.floats(10.0, 1e3), min_size=3, max_size=3))),
        tool_point=draw(vec3),
        name=draw(name_text),
        noise=noise,
        q_limits=draw(st.one_of(st.none(), st.just(np.stack([lo, lo + span], axis=1)))),
        # small enough that nominal + a few sigma keeps the link lengths positive
        tolerance_groups={k: draw(st.floats(1e-6, 0.5)) for k in PRS3_TOLERANCE_DEFAULTS},
        links_against_rail=draw(st.booleans()),
    )


@given(prs3_machines(), st.integers(0, 2**32 - 1))
@settings(max_examples=40, deadline=None)
def test_machine_file_write_read_is_identity(m, seed):
    theta = np.random.default_rng(seed).normal(size=m.n_params) * m.tolerance
    again = machine_from_text(m.to_toml(theta))
    g = m.geometry_arrays(theta)
    assert again.name == m.name and again.links_against_rail == m.links_against_rail
    assert again.noise == m.noise and again.tolerance_groups == m.tolerance_groups
    assert (again.q_limits is None) == (m.q_limits is None)
    if m.q_limits is not None:
        assert np.array_equal(again.q_limits, m.q_limits)
    for key in ("rail_origin", "sphere_center", "link_length", "tool_point"):
        assert np.array_equal(getattr(again, key), g[key]), key
    for key in ("rail_direction", "revolute_axis"):
        # unit vectors are re-normalised on reading: at most a last-bit change
        assert np.allclose(getattr(again, key), g[key], rtol=0, atol=4e-16), key
    # and writing the re-read machine gives the same file, up to those last bits
    assert machine_from_text(again.to_toml()).name == m.name
