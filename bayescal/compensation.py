"""Bilinear interpolation compensation (BIC) grids over a planar translation range.

The range ``[x0, x1] x [z0, z1]`` is meshed into ``n_x x n_z`` nodes (5 x 5 by
default); each node holds the residual position error ``(ex, ez)`` (actual
minus commanded, mm) measured there.  At a commanded point inside a cell
the error is interpolated linearly in ``x`` on the cell's two edges, then
linearly in ``z`` between them, and the command is revised by subtracting
it.  Each node also carries the standard deviation of its value
(``std_ex``, ``std_ez``; NaN when unknown): for a measured node the
instrument's one-sigma (``build_grid(..., std=)``), for a node predicted from
an identified model the propagated model uncertainty
(:func:`bayescal.redundant.grid_std.predicted_grid`).

Grid CSV (what an NC system loads), one row per node, ``i`` fastest::

    i,j,x,z,ex,ez,std_ex,std_ez

``i``/``j``: 0-based node indices along x / z; ``x``, ``z``: node
coordinates (mm); ``ex``, ``ez``: error (mm); ``std_*``: mm or empty.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError, RecordingError
from .io.answers import write_text_atomic
from .notebook import ShowsReport

__all__ = ["CompensationGrid", "build_grid", "read_grid", "write_grid", "table_interpolator", "evaluate_grid", "GRID_COLUMNS",
           "Compensation", "compensate_files", "read_error_table"]

GRID_COLUMNS = ("i", "j", "x", "z", "ex", "ez", "std_ex", "std_ez")

#: Largest plausible node error or std as a fraction of the grid's longer side.
MAX_ERROR_FRACTION = 0.1
#: Bytes per node while a grid is built from an error table (node coordinates, interpolation, the grid).
_BYTES_PER_NODE = 8 * 32


@dataclass(frozen=True)
class CompensationGrid(ShowsReport):
    """Node errors on a rectangular grid.

    Attributes
    ----------
    xs : ndarray, shape (n_x,)
        Node x coordinates, increasing, mm.
    zs : ndarray, shape (n_z,)
        Node z coordinates, increasing, mm.
    error : ndarray, shape (n_z, n_x, 2)
        ``(ex, ez)`` at each node, mm.
    std : ndarray, shape (n_z, n_x, 2)
        Standard deviation of each node value, mm (NaN when unknown).
    """

    xs: NDArray
    zs: NDArray
    error: NDArray
    std: NDArray | None = None

    def __post_init__(self) -> None:
        xs, zs = np.asarray(self.xs, float), np.asarray(self.zs, float)
        if xs.size < 2 or zs.size < 2 or np.any(np.diff(xs) <= 0) or np.any(np.diff(zs) <= 0):
            raise InputError("grid nodes: expected at least 2 strictly increasing coordinates along x and along z")
        err = np.asarray(self.error, float)
        if err.shape != (zs.size, xs.size, 2):
            raise InputError(f"grid error: expected shape ({zs.size}, {xs.size}, 2), got {err.shape}")
        std = np.full(err.shape, np.nan) if self.std is None else np.asarray(self.std, float)
        if std.shape != err.shape:
            raise InputError(f"grid std: expected shape {err.shape}, got {std.shape}")
        object.__setattr__(self, "xs", xs)
        object.__setattr__(self, "zs", zs)
        object.__setattr__(self, "error", err)
        object.__setattr__(self, "std", std)

    @property
    def error_limit(self) -> float:
        """Largest plausible node error or std, mm: a tenth of the grid's longer side (:meth:`check_plausible`)."""
        return MAX_ERROR_FRACTION * max(self.xs[-1] - self.xs[0], self.zs[-1] - self.zs[0])

    def check_plausible(self, where: str = "grid") -> None:
        """InputError for a node error or std that is not finite or above :attr:`error_limit`.

        A residual error a tenth as large as the range it is measured over is
        not something a bilinear correction should apply (recalibrate instead);
        1e300 is a typo or an overflow.
        """
        limit = self.error_limit
        for name, values in (("error", self.error), ("std", self.std)):
            a = np.abs(values)
            # a std may be NaN (unknown); an error may not
            bad = (np.isnan(a) if name == "error" else np.zeros(a.shape, bool)) | np.isinf(a) | (np.nan_to_num(a) > limit)
            if bad.any():
                j, i, c = (int(v) for v in np.argwhere(bad)[0])
                col = ("ex", "ez")[c] if name == "error" else ("std_ex", "std_ez")[c]
                raise InputError(f"{where}: node ({i}, {j}) has {col} = {float(values[j, i, c])!r} mm; expected a finite "
                                 f"value of at most {limit:.4g} mm (a tenth of the grid's longer side)")

    def outside(self, x: ArrayLike, z: ArrayLike) -> NDArray:
        """Which points ``(x, z)`` lie outside the grid's range (beyond 1e-9 of a side), shape (n,) bool."""
        x, z = np.atleast_1d(np.asarray(x, float)), np.atleast_1d(np.asarray(z, float))
        tx = 1e-9 * (self.xs[-1] - self.xs[0])
        tz = 1e-9 * (self.zs[-1] - self.zs[0])
        return ~((x >= self.xs[0] - tx) & (x <= self.xs[-1] + tx) & (z >= self.zs[0] - tz) & (z <= self.zs[-1] + tz))

    def interpolate(self, x: ArrayLike, z: ArrayLike) -> NDArray:
        """Bilinear interpolation of the node errors at points ``(x, z)``, shape (n, 2), mm.

        Points outside the grid take the nearest cell's bilinear form
        (clamped to the range): compensation is only defined inside it.
        """
        x = np.clip(np.atleast_1d(np.asarray(x, float)), self.xs[0], self.xs[-1])
        z = np.clip(np.atleast_1d(np.asarray(z, float)), self.zs[0], self.zs[-1])
        i = np.clip(np.searchsorted(self.xs, x, side="right") - 1, 0, self.xs.size - 2)
        j = np.clip(np.searchsorted(self.zs, z, side="right") - 1, 0, self.zs.size - 2)
        tx = ((x - self.xs[i]) / (self.xs[i + 1] - self.xs[i]))[:, None]
        tz = ((z - self.zs[j]) / (self.zs[j + 1] - self.zs[j]))[:, None]
        e = self.error
        low = (1 - tx) * e[j, i] + tx * e[j, i + 1]  # along x on the lower edge
        high = (1 - tx) * e[j + 1, i] + tx * e[j + 1, i + 1]  # and on the upper edge
        return (1 - tz) * low + tz * high

    def compensate(self, x: ArrayLike, z: ArrayLike) -> NDArray:
        """Revised commands ``(x, z) - e(x, z)``, shape (n, 2), mm."""
        return np.column_stack([np.atleast_1d(x), np.atleast_1d(z)]) - self.interpolate(x, z)

    def to_csv(self) -> str:
        out = io.StringIO()
        w = csv.writer(out, lineterminator="\n")
        w.writerow(GRID_COLUMNS)
        for j, z in enumerate(self.zs):
            for i, x in enumerate(self.xs):
                s = ["" if not np.isfinite(v) else repr(float(v)) for v in self.std[j, i]]
                w.writerow([i, j, repr(float(x)), repr(float(z)), repr(float(self.error[j, i, 0])), repr(float(self.error[j, i, 1])), *s])
        return out.getvalue()

    def report(self) -> str:
        e = np.abs(self.error)
        return (
            f"BIC grid {self.xs.size} x {self.zs.size}: x {self.xs[0]:g}..{self.xs[-1]:g} mm, z {self.zs[0]:g}..{self.zs[-1]:g} mm; "
            f"node errors max |ex| {e[..., 0].max() * 1e3:.1f} um, max |ez| {e[..., 1].max() * 1e3:.1f} um"
        )

    def to_dict(self) -> dict:
        return {"xs": self.xs.tolist(), "zs": self.zs.tolist(), "error": self.error.tolist(), "std": self.std.tolist()}


def build_grid(
    x_range: ArrayLike, z_range: ArrayLike, error_at, *, n: int = 5, n_z: int | None = None, std: float | None = None
) -> CompensationGrid:
    """Mesh a translation range and evaluate ``error_at(x, z) -> (k, 2)`` at the nodes.

    Parameters
    ----------
    x_range, z_range : (min, max), mm
    error_at : callable
        Measures (or models) the residual position error at node coordinates.
    n : int
        Nodes along x (and along z unless ``n_z``); 5 by default.
    std : float, optional
        One-sigma of every node value (mm) when the nodes are measured: the
        instrument's reading error (NaN, i.e. unknown, by default).
    """
    if std is not None and not (np.isfinite(std) and std >= 0):
        raise InputError(f"std: expected a finite non-negative number (mm), got {std!r}")
    if int(n) != n or n < 2 or (n_z is not None and (int(n_z) != n_z or n_z < 2)):
        raise InputError(f"grid size: expected integers >= 2, got n={n!r}, n_z={n_z!r}")
    from .limits import check_memory

    nz = int(n if n_z is None else n_z)
    check_memory(float(n) * nz * _BYTES_PER_NODE, f"a grid of {int(n)} x {nz} nodes", "lower the nodes per axis (--n)")
    xs = np.linspace(*x_range, int(n))
    zs = np.linspace(*z_range, nz)
    X, Z = np.meshgrid(xs, zs)
    err = np.asarray(error_at(X.ravel(), Z.ravel()), float).reshape(zs.size, xs.size, 2)
    sd = None if std is None else np.full(err.shape, float(std))
    grid = CompensationGrid(xs=xs, zs=zs, error=err, std=sd)
    grid.check_plausible("grid")
    return grid


def table_interpolator(path: str, table: NDArray):
    """``error_at(x, z) -> (k, 2)``: linear interpolation of an error table ``x, z, ex, ez`` (mm).

    Raises
    ------
    RecordingError
        Fewer than three points, points on one line (no area to interpolate
        over), or a grid node outside the points' convex hull (raised by the
        returned function), naming ``path``.
    """
    from scipy.interpolate import griddata
    from scipy.spatial import QhullError

    pts = np.asarray(table[:, :2], float)
    uniq, first, inverse = np.unique(pts, axis=0, return_index=True, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    differs = np.flatnonzero(np.any(np.asarray(table[:, 2:4], float) != np.asarray(table, float)[first[inverse], 2:4], axis=1))
    if differs.size:
        # one point with two errors: the triangulation kept one of them, silently
        i = int(differs[0])
        j = int(first[inverse[i]])
        raise RecordingError(path, i + 2, None, f"the point ({pts[i, 0]:g}, {pts[i, 1]:g}) mm is measured again with "
                             f"another error (line {j + 2}); expected one error per point (average repeated measurements)")
    with np.errstate(over="ignore", invalid="ignore"):  # coordinates near the float range: judged as not finite
        centred = (uniq - uniq.mean(axis=0)) if len(uniq) else uniq
    if not np.isfinite(centred).all():
        raise RecordingError(path, None, None, "coordinates too large to interpolate between; expected x, z in mm")
    span = np.abs(centred).max() if uniq.size else 0.0
    if len(uniq) < 3 or np.linalg.matrix_rank(centred, tol=1e-9 * max(span, 1e-300)) < 2:
        line = " on one line" if len(uniq) >= 3 else ""
        raise RecordingError(path, None, None, f"{len(uniq)} distinct point(s){line}; expected measured points spanning "
                             "an area (at least three not on one line) around every grid node")

    def at(x, z):
        xi = np.column_stack([x, z])
        try:
            e = np.column_stack([griddata(pts, table[:, k], xi, method="linear") for k in (2, 3)])
        except (QhullError, ValueError) as exc:
            raise RecordingError(path, None, None, f"the points cannot be triangulated ({str(exc).splitlines()[0]})") from None
        if not np.isfinite(e).all():
            raise RecordingError(path, None, None, "the measured points do not cover every grid node of the ranges given")
        return e

    return at


def evaluate_grid(grid: CompensationGrid, table: NDArray, path: str) -> dict:
    """Errors of fresh measured points ``x, z, ex, ez`` (mm) before and after compensation by ``grid``.

    Raises
    ------
    RecordingError
        A point outside the grid's range (compensation is defined only
        inside it; :meth:`CompensationGrid.interpolate` would extrapolate the
        edge cells), naming its line.
    """
    out = np.flatnonzero(grid.outside(table[:, 0], table[:, 1]))
    if out.size:
        i = int(out[0])
        raise RecordingError(
            path, i + 2, "x", f"point ({float(table[i, 0])!r}, {float(table[i, 1])!r}) mm is outside the grid "
            f"(x {grid.xs[0]:g}..{grid.xs[-1]:g}, z {grid.zs[0]:g}..{grid.zs[-1]:g} mm); the grid compensates only "
            "inside its range"
        )
    after = table[:, 2:4] - grid.interpolate(table[:, 0], table[:, 1])
    before = table[:, 2:4]
    return {"max_before_mm": float(np.abs(before).max()), "max_after_mm": float(np.abs(after).max()),
            "rms_before_mm": float(np.sqrt(np.mean(before**2))), "rms_after_mm": float(np.sqrt(np.mean(after**2)))}


def write_grid(path: str | os.PathLike, grid: CompensationGrid) -> Path:
    """Write the grid CSV atomically; implausible node values (:meth:`CompensationGrid.check_plausible`) are refused."""
    grid.check_plausible(f"not writing {path}")
    return write_text_atomic(path, grid.to_csv())


def read_grid(path: str | os.PathLike, *, text: str | None = None) -> CompensationGrid:
    """Read a grid CSV strictly (every node once, numbers, std cells may be empty).

    Raises
    ------
    RecordingError
        Naming the file, line and column.
    """
    path = str(path)
    if text is None:
        from .io.safe_paths import MAX_CSV_BYTES, read_input_text

        text = read_input_text(path, "a BIC grid CSV", limit=MAX_CSV_BYTES, error=lambda msg: RecordingError(path, None, None, msg))
    rows = [r for r in csv.reader(io.StringIO(text))]
    while rows and all(c.strip() == "" for c in rows[-1]):
        rows.pop()
    if not rows or tuple(h.strip() for h in rows[0]) != GRID_COLUMNS:
        raise RecordingError(path, 1, None, f"expected the header {','.join(GRID_COLUMNS)}")
    recs = []
    for k, row in enumerate(rows[1:]):
        line = k + 2
        if len(row) != len(GRID_COLUMNS):
            raise RecordingError(path, line, None, f"{len(row)} cells, expected {len(GRID_COLUMNS)}")
        vals = []
        for c, cell in zip(GRID_COLUMNS, row):
            s = cell.strip()
            if s == "" and c.startswith("std"):
                vals.append(math.nan)
                continue
            try:
                v = float(s)
            except ValueError:
                raise RecordingError(path, line, c, f"expected a number, got {s!r}") from None
            if not math.isfinite(v) or (c in ("i", "j") and (v != int(v) or v < 0)):
                raise RecordingError(path, line, c, f"expected a {'non-negative integer' if c in ('i', 'j') else 'finite number'}, got {s!r}")
            if c.startswith("std") and v < 0:  # a one-sigma of -1 mm was read and carried into the evaluation
                raise RecordingError(path, line, c, f"expected a one-sigma >= 0 (mm) or an empty cell, got {s!r}")
            vals.append(v)
        recs.append(vals)
    if not recs:
        raise RecordingError(path, 2, None, "no nodes")
    a = np.array(recs)
    nx, nz = int(a[:, 0].max()) + 1, int(a[:, 1].max()) + 1
    if len(a) != nx * nz:
        raise RecordingError(path, None, None, f"{len(a)} nodes for a {nx} x {nz} grid; expected every node once")
    err = np.full((nz, nx, 2), np.nan)
    std = np.full((nz, nx, 2), np.nan)
    xs, zs = np.full(nx, np.nan), np.full(nz, np.nan)
    first: dict[tuple[str, int], int] = {}  # the line that set each grid line's coordinate
    for line, r in enumerate(a, start=2):
        i, j = int(r[0]), int(r[1])
        if np.isfinite(err[j, i, 0]):
            raise RecordingError(path, line, "i", f"node ({i}, {j}) given twice")
        err[j, i], std[j, i] = r[4:6], r[6:8]
        for arr, idx, v, c, k in ((xs, i, r[2], "x", "i"), (zs, j, r[3], "z", "j")):
            if np.isfinite(arr[idx]) and arr[idx] != v:
                raise RecordingError(path, line, c, f"node coordinate {float(v):g} mm differs from {float(arr[idx]):g} mm "
                                     f"at line {first[c, idx]} on the same grid line ({k} = {idx}); expected one {c} "
                                     f"per {k}")
            arr[idx] = v
            first.setdefault((c, idx), line)
    try:
        grid = CompensationGrid(xs=xs, zs=zs, error=err, std=std)
        grid.check_plausible("the grid")
    except InputError as exc:
        raise RecordingError(path, None, None, str(exc)) from None
    return grid


def read_error_table(path: str | os.PathLike) -> NDArray:
    """A table of measured residual errors: a CSV with the header ``x,z,ex,ez`` (mm), one point per row.

    Returns
    -------
    ndarray, shape (n, 4)
        ``x, z, ex, ez`` per point (mm).
    """
    from .errors import RecordingError
    from .io.recording import parse_table, read_csv_rows

    cols = ["x", "z", "ex", "ez"]
    header, _, rows = read_csv_rows(str(path), None, "a CSV x,z,ex,ez")
    if header != cols:
        raise RecordingError(str(path), 1, None, "expected the header x,z,ex,ez")
    if not rows:
        raise RecordingError(str(path), 2, None, "no data rows")
    return parse_table(str(path), cols, rows)


@dataclass(frozen=True)
class Compensation:
    """What ``bayescal compensate`` computes: a grid (built or read) and, with fresh points, its evaluation.

    Attributes
    ----------
    grid : CompensationGrid
    built : bool
        Built from an error table (else read from a grid file).
    evaluation : dict or None
        :func:`evaluate_grid` on the fresh points (what ``--json`` writes).
    """

    grid: CompensationGrid
    built: bool
    evaluation: dict | None


def compensate_files(*, errors: str | os.PathLike | None = None, grid: str | os.PathLike | None = None,
                     evaluate: str | os.PathLike | None = None, x_range=None, z_range=None, n: int = 5,
                     node_std: float | None = None) -> Compensation:
    """Build a BIC grid from measured errors, or read one, and evaluate it on fresh points, as ``bayescal compensate``.

    Parameters
    ----------
    errors : path, optional
        Error table (:func:`read_error_table`) to build the grid from, over ``x_range`` and ``z_range``
        ((min, max), mm) with ``n`` nodes per axis and ``node_std`` (mm) the measured nodes' one-sigma.
    grid : path, optional
        A grid CSV to evaluate instead (module docstring).
    evaluate : path, optional
        Error table of fresh points: their errors before and after compensation.

    Returns
    -------
    Compensation
    """
    from .errors import InputError

    if errors is not None and grid is not None:
        raise InputError("errors (--errors) builds a grid and grid (--grid) reads one; give one of them")
    if errors is not None:
        if not x_range or not z_range:
            raise InputError("x_range and z_range (--x-range, --z-range) are required with errors (--errors)")
        table = read_error_table(errors)
        g = build_grid(x_range, z_range, table_interpolator(str(errors), table), n=n, std=node_std)
    elif grid is not None:
        g = read_grid(grid)
    else:
        raise InputError("give errors (--errors, build a grid) or grid (--grid, evaluate one)")
    ev = evaluate_grid(g, read_error_table(evaluate), str(evaluate)) if evaluate is not None else None
    return Compensation(g, errors is not None, ev)
