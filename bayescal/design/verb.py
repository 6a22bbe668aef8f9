"""``plan`` as a user gets it: poses or relations, the defaults and the option checks of ``bayescal plan``.

:func:`plan_files` is what the command line runs (and :func:`bayescal.plan`
in a notebook): a machine file or machine in, a
:class:`~bayescal.design.plan.PosePlan` (``measure="pose"``) or a
:class:`~bayescal.design.relations.RelationPlan` (``"height"``,
``"distance"``) out, with the same defaults and the same refusals.  Errors
name the keyword and the command line's option.
"""

from __future__ import annotations

import os

from ..errors import InputError
from ..machines.base import Machine

__all__ = ["plan_files", "POSE_OPTIONS", "RELATION_OPTIONS"]

#: Keywords only a plan of poses takes, with their defaults (the command line's options).
POSE_OPTIONS = {"dof": 6, "n_candidates": 20000, "scaling": "tolerance", "n_random": 20, "exchange": True,
                "box": True, "exact_bound": False, "certify": None, "certify_nodes": 5000}
#: Keywords only a plan of heights or distances takes, with their defaults.
RELATION_OPTIONS = {"given": None, "centre": None, "radius": 50.0, "spacing": None, "sigma": None,
                    "min_distance": 0.0}
#: The command line's name of each keyword.
_FLAG = {"n_candidates": "--candidates", "n_random": "--random-sets", "exchange": "--no-exchange", "box": "--no-box"}


def _cli(key: str) -> str:
    return _FLAG.get(key, "--" + key.replace("_", "-"))


def _flag(key: str) -> str:
    return f"{key} ({_cli(key)})"


def _machine(machine) -> Machine:
    if isinstance(machine, Machine):
        return machine
    from ..machines.files import load_machine

    return load_machine(machine)


def _whole(name: str, value, least: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise InputError(f"{_flag(name)}: expected a whole number >= {least}, got {value!r}")


def _options(measure: str, options: dict) -> dict:
    """The options of ``measure`` with their defaults; an option of the other kind is refused, not ignored."""
    own, other = (POSE_OPTIONS, RELATION_OPTIONS) if measure == "pose" else (RELATION_OPTIONS, POSE_OPTIONS)
    for key, value in options.items():
        if key in own:
            continue
        if key in other:
            if value == other[key]:
                continue  # a default spelled out does nothing either way
            if measure == "pose":
                raise InputError(f"{_cli(key)} (keyword {key}) goes with --measure height or distance (a grid of "
                                 "relations); it does nothing for a plan of poses")
            raise InputError(f"{_cli(key)}: only for poses; not with --measure {measure} (keyword {key})")
        raise InputError(f"plan: unknown option {key!r}; expected one of "
                         f"{', '.join(sorted({*POSE_OPTIONS, *RELATION_OPTIONS, 'criterion', 'repeats', 'method'}))}")
    return {**own, **{k: v for k, v in options.items() if k in own}}


def plan_files(machine: str | os.PathLike | Machine, n: int, *, measure: str = "pose", criterion: str | None = None,
               frame: str = "base", seed: int = 0, repeats: bool | None = None, method: str | None = None, **options):
    """Plan a measurement session as ``bayescal plan`` does (without ``--separate``).

    Parameters
    ----------
    machine : path or Machine
        Machine file with ``[workspace] q_limits`` (docs/formats.md section 1).
    n : int
        Poses (or relations) to plan, at least 1.
    measure : {"pose", "height", "distance"}
        Poses for a recording (docs/formats.md E7), or probe heights /
        distances between points for a constraint recording (section 6).
    criterion : str, optional
        Default ``"D"`` for poses, ``"EIG"`` for relations
        (:data:`bayescal.design.CRITERIA`).
    frame : {"base", "fit"}
        ``"fit"``: the instrument frame will be fitted with the geometry; its
        six parameters take part in the criterion (poses only).
    seed : int
        Same seed, same plan.
    repeats : bool, optional
        Allow a pose or relation more than once (default: the method's own).
    method : {"greedy", "relaxed"}, optional
        Selection (default: relaxed for criterion I, greedy otherwise).
    **options
        Poses: ``dof`` (6, 5, 3), ``n_candidates``, ``scaling``, ``n_random``, ``exchange``, ``box``,
        ``exact_bound``, ``certify`` (a fraction in (0, 1)), ``certify_nodes``
        (:func:`bayescal.design.plan.plan_poses`).  Relations: ``given`` (a
        constraint recording or its path), ``centre`` (mm), ``radius`` (mm), ``spacing`` (mm), ``sigma`` (mm),
        ``min_distance`` (mm) (:func:`bayescal.design.relations.plan_relations`).

    Returns
    -------
    PosePlan or RelationPlan
        ``report()``, ``to_dict()`` (what ``--json`` writes); a pose plan is written by
        :func:`bayescal.design.write_plan`, a relation plan by
        :func:`bayescal.design.relations.relation_plan_csv`.

    Raises
    ------
    InputError
        An option of the other kind, a count below 1, a ``certify`` outside (0, 1), ``frame`` not base or fit
        (or fit with relations).
    """
    if measure not in ("pose", "height", "distance"):
        raise InputError(f"measure (--measure): expected 'pose', 'height' or 'distance', got {measure!r}")
    if frame not in ("base", "fit"):
        raise InputError(f"frame (--frame): expected 'base' or 'fit', got {frame!r}")
    _whole("n", n, 1)
    opts = _options(measure, options)
    m = _machine(machine)
    if measure != "pose":
        return _relations(m, n, measure, criterion or "EIG", frame, seed, repeats, method, opts)
    _whole("n_candidates", opts["n_candidates"], n)
    _whole("certify_nodes", opts["certify_nodes"], 1)
    _whole("n_random", opts["n_random"], 0)
    c = opts["certify"]
    if c is not None and not (isinstance(c, (int, float)) and not isinstance(c, bool) and 0 < c < 1):
        raise InputError(f"certify (--certify): expected a fraction in (0, 1) (the command line's percentage / 100), "
                         f"got {c!r}")
    if frame == "fit":
        from ..machines.framed import Frame, InstrumentFrame

        # where the instrument stands does not change the information; identity is as good as any frame
        m = InstrumentFrame(m.base_machine(), Frame.identity(), fit=True)
    from .plan import plan_poses

    return plan_poses(m, n, criterion=criterion or "D", seed=seed, repeats=repeats, method=method, **opts)


def _relations(m: Machine, n: int, measure: str, criterion: str, frame: str, seed: int, repeats, method, opts: dict):
    from .relations import plan_relations

    if frame != "base":
        raise InputError("frame (--frame): 'fit' plans poses for a fitted instrument frame; heights and distances "
                         "have no instrument frame")
    given = opts.pop("given")
    if given is not None and not hasattr(given, "check_machine"):
        from ..io.constraints import read_constraints

        given = read_constraints(given)
    if given is not None:
        given.check_machine(m.n_actuators, None, m.source)
    return plan_relations(m, n, measure=measure, given=given, criterion=criterion, repeats=repeats, method=method,
                          seed=seed, **opts)
