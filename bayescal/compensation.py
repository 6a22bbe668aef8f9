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

__all__ = ["CompensationGrid", "build_grid", "read_grid", "write_grid", "GRID_COLUMNS"]

GRID_COLUMNS = ("i", "j", "x", "z", "ex", "ez", "std_ex", "std_ez")


@dataclass(frozen=True)
class CompensationGrid:
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
    xs = np.linspace(*x_range, int(n))
    zs = np.linspace(*z_range, int(n if n_z is None else n_z))
    X, Z = np.meshgrid(xs, zs)
    err = np.asarray(error_at(X.ravel(), Z.ravel()), float).reshape(zs.size, xs.size, 2)
    sd = None if std is None else np.full(err.shape, float(std))
    return CompensationGrid(xs=xs, zs=zs, error=err, std=sd)


def write_grid(path: str | os.PathLike, grid: CompensationGrid) -> Path:
    """Write the grid CSV atomically."""
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
        try:
            with open(path, encoding="utf-8-sig", newline="") as fh:
                text = fh.read()
        except (FileNotFoundError, IsADirectoryError):
            raise RecordingError(path, None, None, "file not found; expected a BIC grid CSV") from None
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
    for line, r in enumerate(a, start=2):
        i, j = int(r[0]), int(r[1])
        if np.isfinite(err[j, i, 0]):
            raise RecordingError(path, line, "i", f"node ({i}, {j}) given twice")
        err[j, i], std[j, i] = r[4:6], r[6:8]
        for arr, idx, v, c in ((xs, i, r[2], "x"), (zs, j, r[3], "z")):
            if np.isfinite(arr[idx]) and arr[idx] != v:
                raise RecordingError(path, line, c, f"node coordinate {v!r} differs from {arr[idx]!r} on the same grid line")
            arr[idx] = v
    try:
        return CompensationGrid(xs=xs, zs=zs, error=err, std=std)
    except InputError as exc:
        raise RecordingError(path, None, None, str(exc)) from None
