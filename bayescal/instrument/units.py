"""Recordings whose numbers look like another unit than their columns say.

The rules (docs/formats.md section 4: "refused with a message that names the unit
it suspects and the suffix to use"), applied only to columns without a unit
suffix, and all independent of the instrument frame:

* **Positions.**  The spread of the measured tool points (RMS distance
  from their centroid) is compared with the spread of the nominal machine's
  tool points at the same commanded poses.  Below 1/100 of it: metres
  (suffix ``_m``); above 100 times and above 1 mm: micrometres (``_um``).  Comparing with
  the same poses, not with the whole workspace, keeps a legitimate
  small-workspace recording (poses a millimetre apart) from being refused.
  Skipped when the nominal points do not move (spread below 1e-6 mm).
* **Orientations.**  A rotation vector with a norm above pi is not in
  radians: degrees (``_deg``).  Otherwise the angle of each measured
  platform orientation relative to the first pose's is compared with the
  nominal machine's at the same poses: more than 10 times larger (RMS)
  and above 0.01 rad means degrees (``_deg``; the factor is 57).  Smaller angles are not
  refused (an orientation that hardly changes is legitimate).  Skipped when
  the nominal orientation does not change (RMS angle below 1e-6 rad).  A
  tool axis (5-DOF) is a unit vector and has no unit.
"""

from __future__ import annotations

import numpy as np

from ..errors import RecordingError
from ..geometry import so3_exp, so3_log
from ..io.recording import Recording
from ..machines.base import Machine

__all__ = ["check_recording_units", "POSITION_RATIO", "ANGLE_RATIO"]

#: Measured/nominal spread outside [1/POSITION_RATIO, POSITION_RATIO]: another length unit.
POSITION_RATIO = 100.0
#: Measured/nominal RMS relative angle above this: degrees.
ANGLE_RATIO = 10.0
#: Largest measured coordinate, mm (1000 km: beyond it no unit makes a value a measurement).
MAX_COORDINATE = 1e9
#: Largest rotation vector component, rad (a rotation vector in degrees stays far below; the norm rule names those).
MAX_ROTATION = 1e6


def _spread(p: np.ndarray, groups: np.ndarray | None = None) -> float:
    """RMS distance of the points from their centre, each group (station: its own frame) about its own centre."""
    if groups is None or np.unique(groups).size == 1:
        return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))
    centred = p.copy()
    for g in np.unique(groups):
        sel = groups == g
        centred[sel] -= p[sel].mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(centred**2, axis=1))))


def _relative_angles(R: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
    """Angle (rad) of each rotation relative to the first (of its group: a station's frame), valid up to pi."""
    # bayescal's own SO(3) log, not scipy's Rotation: a units heuristic needs no more, and scipy.spatial
    # costs about half a second to import on every 6-DOF recording
    if groups is None:
        return np.linalg.norm(so3_log(R @ np.swapaxes(R[0], -1, -2)), axis=1)
    first = {int(g): int(np.flatnonzero(groups == g)[0]) for g in np.unique(groups)}
    ref = R[[first[int(g)] for g in groups]]
    return np.linalg.norm(so3_log(R @ np.swapaxes(ref, -1, -2)), axis=1)


def _axis_angles(a: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip(a @ a[0], -1.0, 1.0))


def check_recording_units(machine: Machine, rec: Recording) -> None:
    """Raise RecordingError when positions look like metres or micrometres, or angles like degrees.

    Parameters
    ----------
    machine : Machine
        Nominal machine (any instrument frame it carries does not matter:
        the rules compare spreads and relative angles).
    rec : Recording
        Columns with a unit suffix are not judged.
    """
    declared = getattr(rec, "declared_units", {}) or {}
    _check_magnitudes(rec)
    q = machine.check_q(rec.q)
    nom = machine.forward(q)
    ok = nom.success
    if ok.sum() < 2:
        return
    # stations measure in frames of their own, metres apart: spreads are taken about each station's centre
    groups = rec.station_index[ok] if getattr(rec, "station", None) is not None else None
    if not any(declared.get(c) for c in ("x", "y", "z")):
        s_nom, s_meas = _spread(nom.position[ok], groups), _spread(rec.position[ok], groups)
        if s_nom > 1e-6 and s_meas > 0:
            ratio = s_meas / s_nom
            if ratio < 1.0 / POSITION_RATIO:
                raise RecordingError(
                    rec.path, None, "x",
                    f"the measured tool points spread over {s_meas:.4g} (RMS about their centre) where the nominal machine "
                    f"moves them {s_nom:.4g} mm at the same poses: the positions look like metres; expected mm, or name "
                    "the columns x_m, y_m, z_m",
                )
            # and at least a millimetre: a nominal machine that hardly moves the tool must not make
            # instrument noise look like micrometres
            if ratio > POSITION_RATIO and s_meas > 1.0:
                raise RecordingError(
                    rec.path, None, _widest(rec.position[ok]),
                    f"the measured tool points spread over {s_meas:.4g} (RMS about their centre) where the nominal machine "
                    f"moves them {s_nom:.4g} mm at the same poses: the positions look like micrometres; expected mm, or "
                    "name the columns x_um, y_um, z_um",
                )
    if rec.rotvec is not None and not any(declared.get(c) for c in ("rx", "ry", "rz")):
        norms = np.linalg.norm(rec.rotvec, axis=1)
        if norms.max() > np.pi + 1e-9:
            i = int(np.argmax(norms))
            raise RecordingError(
                rec.path, i + 2, "rx",
                f"rotation vector of norm {norms[i]:.4g}, above pi: the orientations look like degrees; expected rad, "
                "or name the columns rx_deg, ry_deg, rz_deg",
            )
        a_nom, a_meas = _relative_angles(nom.rotation[ok], groups), _relative_angles(so3_exp(rec.rotvec[ok]), groups)
        _angle_rule(rec, a_nom, a_meas, "rx", "the orientations look like degrees; expected rad, or name the columns rx_deg, ry_deg, rz_deg")


def _widest(p: np.ndarray) -> str:
    """The position column (x, y or z) whose values spread the most: the one a message about the spread names."""
    return "xyz"[int(np.argmax(np.std(p, axis=0)))]


def _check_magnitudes(rec: Recording) -> None:
    """RecordingError naming line and column for a measured coordinate beyond :data:`MAX_COORDINATE` mm.

    Such a value is no measurement in any unit (1e308 is an overflow or a
    typo); judged before the spread rules, whose statistics it would make
    infinite and whose message would then blame another column.
    """
    for values, names in ((rec.position, ("x", "y", "z")), (rec.rotvec, ("rx", "ry", "rz"))):
        if values is None:
            continue
        limit = MAX_COORDINATE if names[0] == "x" else MAX_ROTATION
        big = np.argwhere(~(np.abs(values) <= limit))
        if big.size:
            r, c = (int(v) for v in big[0])
            unit = "mm" if names[0] == "x" else "rad"
            raise RecordingError(rec.path, r + 2, names[c], f"{float(values[r, c])!r} {unit}; expected a "
                                 f"measured {'coordinate' if unit == 'mm' else 'rotation vector component'} within "
                                 f"+-{limit:g} {unit}")


def _angle_rule(rec, a_nom, a_meas, col, what) -> None:
    r_nom = float(np.sqrt(np.mean(a_nom**2)))
    r_meas = float(np.sqrt(np.mean(a_meas**2)))
    # and at least 0.01 rad: a machine that nominally hardly turns must not make its real errors
    # (a fraction of a milliradian) look like degrees
    if r_nom > 1e-6 and r_meas > ANGLE_RATIO * r_nom and r_meas > 0.01:
        raise RecordingError(
            rec.path, None, col,
            f"the measured orientations turn by {r_meas:.4g} (RMS angle from the first pose) where the nominal machine "
            f"turns by {r_nom:.4g} rad at the same poses: {what}",
        )
