"""Machine views (bayescal/machines/view.py): every view over every kind has the whole Machine interface, explicitly.

A member no view changes is the machine's (the same object or value); every
other member is the view's own, never a :class:`Machine` default meant for a
plain machine; an attribute outside the interface is not forwarded.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bayescal.constraints.model import PivotAugmented
from bayescal.effects.base import EffectParam
from bayescal.effects.joint_model import EffectAugmented
from bayescal.effects.stored import StoredEffect
from bayescal.machines.base import Machine
from bayescal.machines.files import load_machine
from bayescal.machines.framed import Frame, InstrumentFrame
from bayescal.machines.raspm import Raspm
from bayescal.machines.view import FORWARDED, Forwarded, MachineView
from bayescal.sensors.mounts import SensorMounts
from tests.conftest import ROOT

FILES = sorted(p for p in (ROOT / "examples").glob("*/machine.toml"))
#: The Machine interface: its public members and its declared attributes (name, layout, tolerance, ...).
INTERFACE = sorted({n for n in dir(Machine) if not n.startswith("_")} | set(Machine.__annotations__))


@pytest.fixture(scope="module", params=FILES, ids=lambda p: Path(p).parent.name)
def kind_machine(request):
    """An example machine carrying effects and a calibration of its own (so a Machine default would differ)."""
    m = load_machine(request.param)
    table = StoredEffect("thermal_expansion", (("strain.q1", 1.0),), ("um/m",), "<test>")
    return m.with_effects((table,)).with_calibration(SimpleNamespace(record="test"), SimpleNamespace(discrepancy="test"))


def _views(m: Machine) -> dict[str, tuple[Machine, Machine]]:
    """Every view over ``m`` (alone and nested as the models nest them), with the machine each wraps."""
    frame = Frame.from_rotation_vector([100.0, -20.0, 5.0], [0.01, -0.02, 0.3])
    mounts = SensorMounts(m, ("sensor.link.tilt.x", "sensor.link.tilt.y"), (1e-3, 1e-3))
    framed_mounts = InstrumentFrame(mounts, frame, fit=True)
    params = (EffectParam("compliance.q1", "um/N", 2.0, 0.5, lower=0.0), EffectParam("offset", "um", 10.0))
    return {
        "fitted frame": (InstrumentFrame(m, frame, fit=True), m),
        "known frame": (InstrumentFrame(m, frame, fit=False), m),
        "two stations": (InstrumentFrame(m, stations=("a", "b"), frames0=(frame, Frame.identity())), m),
        "pivots": (PivotAugmented(m, ("1", "2")), m),
        "sensor mounts": (mounts, m),
        "frame around mounts": (framed_mounts, mounts),
        "effects": (EffectAugmented(m, params, ("joint_compliance", "backlash")), m),
        "effects around frame and mounts": (EffectAugmented(framed_mounts, params, ("joint_compliance", "backlash")),
                                            framed_mounts),
    }


def _owner(view: Machine, name: str):
    """The class whose namespace gives ``view.name`` (None: the instance's own attribute)."""
    if name in vars(view):
        return None
    return next(c for c in type(view).__mro__ if name in vars(c))


def _same(a, b) -> bool:
    """Whether two member values are the same: the same object, equal bound methods, or equal values."""
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(a, b)
    if dataclasses.is_dataclass(a) and type(a) is type(b):
        return all(_same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def test_forwarded_members_are_exactly_the_views_descriptors():
    assert set(FORWARDED) == {n for n, v in vars(MachineView).items() if isinstance(v, Forwarded)}
    assert set(FORWARDED) <= set(INTERFACE), "a forwarded member that is not in the Machine interface"


def test_every_view_has_every_member_of_the_interface_from_its_machine_or_its_own(kind_machine):
    for label, (view, wrapped) in _views(kind_machine).items():
        assert isinstance(view, MachineView) and view.wrapped is wrapped, label
        for name in INTERFACE:
            owner = _owner(view, name)
            # a Machine default describes a plain machine (its parameters, its frame): a view decides each member
            assert owner not in (Machine, object), f"{label}: {name} is left to Machine's default"
            value = getattr(view, name)
            if isinstance(vars(owner).get(name) if owner else None, Forwarded):
                # the wrapped machine's: the very member (a bound method, an array) or an equal value; and the
                # members no view changes are the kind's machine's under any nesting of views
                assert _same(value, getattr(wrapped, name)), f"{label}: {name} is not the wrapped machine's"
                assert name not in FORWARDED or _same(value, getattr(kind_machine, name)), f"{label}: {name}"
        # spot checks of what the forwarding gives, against the kind's machine itself
        assert view.kind == kind_machine.kind and view.effects is kind_machine.effects, label
        assert view.calibration is kind_machine.calibration and view.discrepancy is kind_machine.discrepancy, label
        assert view.sensor_bodies == kind_machine.sensor_bodies and view.n_dof == kind_machine.n_dof, label


def test_every_view_owns_a_consistent_layout_over_its_machines(kind_machine):
    for label, (view, wrapped) in _views(kind_machine).items():
        names = view.layout.names
        assert view.n_params == len(names) == len(view.tolerance) >= wrapped.n_params, label  # a known frame adds none
        inner, idx = view.geometry_part
        assert tuple(names[i] for i in idx) == inner.layout.names, label  # the geometry's parameters, by name
        assert set(wrapped.layout.names) <= set(names), label
        for prior in (view.prior_mean, view.prior_lower):
            assert prior is None or np.shape(prior) == (view.n_params,), label
        assert view.check_theta(None).shape == (view.n_params,), label
        frame = view.instrument_frame  # the frame the view is measured in: its parameters lead theta
        assert view.framed == (frame is not None), label
        assert frame is None or names[: frame.n_frame] == frame.layout.names[: frame.n_frame], label


def test_an_effect_view_states_its_priors_and_the_others_pad_them(kind_machine):
    views = _views(kind_machine)
    em, _ = views["effects around frame and mounts"]
    k = em.n_params - 2
    np.testing.assert_array_equal(em.prior_mean, np.r_[np.zeros(k), 0.5, 0.0])
    np.testing.assert_array_equal(em.prior_lower, np.r_[np.full(k, -np.inf), 0.0, -np.inf])
    assert all(views[v][0].prior_mean is None and views[v][0].prior_lower is None
               for v in ("fitted frame", "pivots", "sensor mounts", "frame around mounts"))
    # a frame around a view that states a prior mean pads it (zeros for the frame: centred on its start)
    framed_em = InstrumentFrame(EffectAugmented(kind_machine, em.params, em.effect_names), fit=True)
    np.testing.assert_array_equal(framed_em.prior_mean, np.r_[np.zeros(6 + kind_machine.n_params), 0.5, 0.0])


def test_views_solve_the_kind_machines_kinematics(kind_machine):
    """The views' own forward and tool Jacobian are the machine's, with the view's columns (a known frame: identity)."""
    assert kind_machine.q_limits is not None, "every bundled example states q_limits: the reference pose"
    q = kind_machine.home_q()[None]
    ref = kind_machine.forward(q)
    J = kind_machine.tool_jacobian(q, None, ref)
    for label, (view, _) in _views(kind_machine).items():
        if view.framed:
            continue  # the frame's kinematics are tests/machines/test_framed.py's
        poses = view.forward(q)
        np.testing.assert_allclose(poses.position, ref.position, atol=1e-9, err_msg=label)
        Jv = view.tool_jacobian(q, None, poses)
        inner, idx = view.geometry_part
        np.testing.assert_allclose(Jv[:, :, idx[: kind_machine.n_params]], J, atol=1e-9, err_msg=label)
        assert not np.delete(Jv, idx[: kind_machine.n_params], axis=2).any(), label


def test_an_attribute_outside_the_interface_is_not_forwarded(kind_machine):
    """A kind's own members (a serial chain's bodies, a redundant machine's inverse kinematics) are not a view's."""
    own = sorted(n for n in dir(kind_machine) if not n.startswith("_") and n not in INTERFACE)
    assert own, "a kind with no member of its own: nothing to check"
    for label, (view, _) in _views(kind_machine).items():
        for name in own:
            if any(name in vars(c) for c in type(view).__mro__):
                continue  # the view's own member of that name (an appended view's ``base``, a frame's ``fit``)
            with pytest.raises(AttributeError):
                getattr(view, name)
        with pytest.raises(AttributeError):
            view.no_such_member  # noqa: B018


def test_redundancy_is_the_raspms_own_kinematics_through_a_frame_and_none_through_appended_parameters(kind_machine):
    """Machine.redundancy: the RASPM (one redundant drive, closed-form inverse kinematics) gives itself, every other
    kind None; an instrument frame forwards it (the machine's parameters follow the frame's), a view that appends
    parameters of its own has none (the kinematics do not know them)."""
    raspm = kind_machine.kind == Raspm.kind
    assert (kind_machine.redundancy is kind_machine) if raspm else kind_machine.redundancy is None
    if raspm:
        x = np.array([[0.0, 0.0, 0.0]])
        q, Ja = kind_machine.redundancy.ik_jacobian(x)
        assert q.shape == (1, kind_machine.n_actuators) and Ja.shape == (1, kind_machine.n_actuators, 3)
        assert len(kind_machine.redundancy.redundant) == kind_machine.n_actuators - kind_machine.n_dof
    for label, (view, wrapped) in _views(kind_machine).items():
        if isinstance(view, InstrumentFrame):
            assert view.redundancy is wrapped.redundancy, label  # the frame around body sensors' mountings: None
            assert view.inside.n_params == view.n_params - view.n_frame, label
        else:
            assert view.redundancy is None, label


def test_serial_chain_and_written_modules_are_the_kinds_own_and_no_views(kind_machine):
    """Machine.serial_chain: a serial chain gives itself, every other kind None; Machine.written_modules: a hybrid's
    modules, () for a one-file kind; a view has neither (its parameters are not the chain's, its file is its own)."""
    from bayescal.machines.hybrid import Hybrid
    from bayescal.machines.serial import Serial

    assert (kind_machine.serial_chain is kind_machine) == isinstance(kind_machine, Serial)
    assert kind_machine.serial_chain in (None, kind_machine)
    if isinstance(kind_machine, Hybrid):
        assert kind_machine.written_modules == tuple(kind_machine.modules) and len(kind_machine.written_modules) >= 2
    else:
        assert kind_machine.written_modules == ()
    for label, (view, _) in _views(kind_machine).items():
        assert view.serial_chain is None and view.written_modules == (), label
        inner, _ = view.geometry_part
        if not isinstance(view, EffectAugmented):  # its geometry part keeps the effects: a view again
            assert inner.serial_chain is kind_machine.serial_chain, label


def test_a_forwarded_member_is_read_only():
    view = PivotAugmented(load_machine(FILES[0]), ("1",))
    with pytest.raises(AttributeError, match="wrapped machine's"):
        object.__setattr__(view, "noise", None)


def test_a_view_is_not_read_from_a_machine_file():
    from bayescal.errors import MachineFileError

    with pytest.raises(MachineFileError, match="view"):
        PivotAugmented.from_toml(None, "m.toml")


def test_an_effect_view_around_views_that_state_bounds_keeps_them():
    # review: EffectAugmented kept its base's prior mean but replaced the base's lower bounds by -inf, so effects
    # fitted under another effect view (directly, or under pivots) lost their physical bounds (a compliance >= 0)
    m = load_machine(FILES[0])
    inner = EffectAugmented(m, (EffectParam("compliance.q1", "um/N", 2.0, 0.5, lower=0.0),), ("joint_compliance",))
    for base in (inner, PivotAugmented(inner, ("1",))):
        outer = EffectAugmented(base, (EffectParam("half_band", "um", 10.0, 5.0, lower=1.0),), ("backlash",))
        np.testing.assert_array_equal(outer.prior_lower, np.r_[base.prior_lower, 1.0])
        np.testing.assert_array_equal(outer.prior_mean, np.r_[base.prior_mean, 5.0])
        assert outer.prior_lower[m.n_params] == 0.0  # the inner effect's bound, at its place in theta
