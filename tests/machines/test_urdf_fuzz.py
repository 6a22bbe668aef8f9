"""Fuzzing the URDF reader: any URDF a machine file names is read or refused with a BayescalError (issue 30).

Property-based (hypothesis, derandomised): robots built from a few link
names with random joints between them (cycles, missing or repeated links,
unknown joint types, hostile numbers in origins, axes and limits) and raw
bytes in place of the XML.  A machine that loads is also asked for one
forward pose.  The time limit is hypothesis' per-example deadline.
"""

from __future__ import annotations

import tempfile
from datetime import timedelta
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bayescal.errors import BayescalError

FUZZ = settings(max_examples=30, deadline=timedelta(seconds=5), derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

MACHINE = ('kind = "serial"\nname = "fuzz"\nurdf = "r.urdf"\nbase_link = "base_link"\ntip_link = "tool_link"\n'
           '[tool]\npoint = [0.0, 0.0, 0.0]\n')
LINKS = ["base_link", "a", "b", "c", "tool_link"]
NUMBER = st.one_of(st.floats(-2, 2).map(repr), st.sampled_from(["nan", "inf", "-inf", "1e308", "1e-320", "abc", "",
                                                                "0x10", "1 2", "\u0661"]))
TRIPLE = st.one_of(st.lists(NUMBER, min_size=3, max_size=3).map(" ".join), NUMBER,
                   st.lists(NUMBER, min_size=4, max_size=4).map(" ".join))
TYPES = st.sampled_from(["revolute", "continuous", "prismatic", "fixed", "floating", "planar", "screw", ""])


@st.composite
def joint(draw, k):
    parent, child = draw(st.sampled_from(LINKS)), draw(st.sampled_from(LINKS))
    parts = [f'<joint name="{draw(st.sampled_from([f"j{k}", "j0", ""]))}" type="{draw(TYPES)}">',
             f'<parent link="{parent}"/>', f'<child link="{child}"/>']
    if draw(st.booleans()):
        parts.append(f'<origin xyz="{draw(TRIPLE)}" rpy="{draw(TRIPLE)}"/>')
    if draw(st.booleans()):
        parts.append(f'<axis xyz="{draw(TRIPLE)}"/>')
    if draw(st.booleans()):
        parts.append(f'<limit lower="{draw(NUMBER)}" upper="{draw(NUMBER)}" effort="1" velocity="1"/>')
    if draw(st.booleans()):
        parts.append(f'<mimic joint="{draw(st.sampled_from(["j0", "j1", "nope"]))}" multiplier="{draw(NUMBER)}"/>')
    return "".join(parts) + "</joint>"


GOOD = st.floats(-2, 2).map(repr)


@st.composite
def chain_joint(draw, k, parent, child):
    """A well-formed joint of the chain base_link - a - b - c - tool_link (with an odd axis now and then)."""
    kind = draw(st.sampled_from(["revolute", "prismatic", "fixed", "continuous"]))
    axis = draw(st.sampled_from(["0 0 1", "1 0 0", "0 1 0", "0 0 0", "1 1 0", "0 0 -1"]))
    xyz = " ".join(draw(st.lists(GOOD, min_size=3, max_size=3)))
    rpy = " ".join(draw(st.lists(GOOD, min_size=3, max_size=3)))
    lo = draw(st.floats(-3, 0))
    return (f'<joint name="j{k}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>'
            f'<limit lower="{lo!r}" upper="{lo + draw(st.floats(0, 3))!r}" effort="1" velocity="1"/></joint>')


@st.composite
def urdf_text(draw):
    if draw(st.booleans()):  # a well-formed chain, with at most one hostile joint added: the success path too
        links = list(LINKS)
        joints = [draw(chain_joint(k, p, c)) for k, (p, c) in enumerate(zip(LINKS, LINKS[1:]))]
        joints += [draw(joint(9))] if draw(st.booleans()) else []
    else:
        links = draw(st.lists(st.sampled_from(LINKS), max_size=7))
        joints = [draw(joint(k)) for k in range(draw(st.integers(0, 6)))]
    body = "".join(f'<link name="{name}"/>' for name in links) + "".join(joints)
    text = f'<?xml version="1.0"?><robot name="fuzz">{body}</robot>'
    cut = draw(st.one_of(st.none(), st.none(), st.integers(0, len(text))))
    return text if cut is None else text[:cut]


def _load(data: bytes) -> None:
    from bayescal.machines.files import load_machine

    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "r.urdf").write_bytes(data)
        (Path(d) / "m.toml").write_text(MACHINE)
        try:
            m = load_machine(Path(d) / "m.toml")
        except BayescalError:
            return
        try:
            q = np.zeros((1, m.n_actuators))
            m.forward(q)
        except BayescalError:
            pass


@FUZZ
@given(urdf_text())
def test_urdfs_are_read_or_refused(text):
    _load(text.encode("utf-8"))


@FUZZ
@given(st.binary(max_size=300))
def test_urdf_bytes_are_read_or_refused(data):
    _load(data)


def test_the_generator_reaches_a_machine_that_loads():
    # the fuzz above must also exercise the success path, not only refusals
    from bayescal.machines.files import load_machine

    text = ('<?xml version="1.0"?><robot name="fuzz"><link name="base_link"/><link name="a"/><link name="tool_link"/>'
            '<joint name="j0" type="revolute"><parent link="base_link"/><child link="a"/><axis xyz="0 0 1"/>'
            '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
            '<joint name="j1" type="fixed"><parent link="a"/><child link="tool_link"/><origin xyz="0.1 0 0"/></joint>'
            '</robot>')
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "r.urdf").write_text(text)
        (Path(d) / "m.toml").write_text(MACHINE)
        m = load_machine(Path(d) / "m.toml")
        np.testing.assert_allclose(m.forward(np.zeros((1, 1))).position[0], [100.0, 0.0, 0.0], atol=1e-9)
