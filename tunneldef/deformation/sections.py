"""Per-section deformation statistics along the chainage (paper §3.3.2, §4.3, Table 4).

Also the surface label of each point (roof, left wall, right wall, floor) from its position in
the cross-section, used to split the statistics and to name danger zones.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigError, InvalidCloudError
from ..surfaces import FLOOR, LEFT_WALL, RIGHT_WALL, ROOF, SURFACE_NAMES
from ..textfiles import write_text_atomic

if TYPE_CHECKING:
    from .result import DeformationResult

__all__ = [
    "SURFACE_NAMES",
    "ROOF",
    "LEFT_WALL",
    "RIGHT_WALL",
    "FLOOR",
    "surface_labels",
    "section_statistics",
    "write_sections_csv",
]

logger = logging.getLogger(__name__)


_EXTENT_QUANTILE = 0.95
_MIN_EXTENT_POINTS = 30
_CHUNK = 1_000_000  # points labelled at once
_GROUP = 2_000_000  # points of the chainage bins gathered at once for their extents


def _bins(s: np.ndarray, step: float) -> np.ndarray:
    """Chainage bin of each point, from 0, computed a chunk at a time (int32 where the bins
    fit; stray chainages far off get the occupied bins in their order)."""
    lo = math.floor(float(np.min(s)) / step)
    hi = math.floor(float(np.max(s)) / step)
    if hi - lo > len(s) + 1_000_000:
        b = np.floor(s / step).astype(np.int64)
        return np.unique(b, return_inverse=True)[1].reshape(-1)
    out = np.empty(len(s), dtype=np.int32 if hi - lo < 2**31 - 1 else np.int64)
    for a in range(0, len(s), _CHUNK):
        out[a:a + _CHUNK] = np.floor(s[a:a + _CHUNK] / step).astype(np.int64) - lo
    return out


def _side(values: np.ndarray, sign: float) -> np.ndarray:
    """``sign * values`` where that is positive, in order, gathered a chunk at a time into one
    array (no whole-cloud mask, product or list of pieces)."""
    chunks = range(0, len(values), _CHUNK)
    counts = [int(np.count_nonzero(values[a:a + _CHUNK] * sign > 0)) for a in chunks]
    out = np.empty(sum(counts))
    at = 0
    for a, m in zip(chunks, counts, strict=True):
        v = values[a:a + _CHUNK] * sign
        out[at:at + m] = v[v > 0]
        at += m
    return out


def _half_extents(values: np.ndarray, fallback: float) -> float:
    """The 95th percentile of ``values`` (a scratch copy: partitioned in place)."""
    if values.size < _MIN_EXTENT_POINTS:
        return fallback
    e = float(np.quantile(values, _EXTENT_QUANTILE, overwrite_input=True))
    return e if e > 1e-3 else fallback


def surface_labels(
    chainage: np.ndarray,
    lateral: np.ndarray,
    vertical: np.ndarray,
    *,
    step: float = 1.0,
) -> np.ndarray:
    """Surface of each point from its angle in the cross-section.

    Parameters
    ----------
    chainage, lateral, vertical : ndarray, shape (N,)
        Position relative to the centreline (``Centerline.project``), metres; ``lateral`` is
        positive to the left, ``vertical`` positive up.
    step : float
        Length of the chainage bins in which the section's extents are measured, metres.

    Returns
    -------
    ndarray, shape (N,), uint8
        0 roof, 1 left wall, 2 right wall, 3 floor (:data:`SURFACE_NAMES`).

    Notes
    -----
    In each chainage bin the half-width to the left and right and the half-height up and down
    are the 95th percentiles of the positive offsets on each side (the whole cloud's when a bin
    has too few points). Offsets are divided by the half-extent of their side; a point is on the
    roof or floor when its normalised vertical offset exceeds its normalised lateral one, i.e.
    the boundaries are the diagonals from the centre to the section's corners.
    """
    s = np.asarray(chainage, dtype=np.float64)
    lat = np.asarray(lateral, dtype=np.float64)
    ver = np.asarray(vertical, dtype=np.float64)
    n = s.shape[0]
    labels = np.empty(n, dtype=np.uint8)
    if n == 0:
        return labels
    if not step > 0:
        raise ConfigError(f"section step must be > 0 m, got {step!r}")
    glob = [  # the whole cloud's, for bins with too few points
        _half_extents(_side(lat, 1.0), 1.0),
        _half_extents(_side(lat, -1.0), 1.0),
        _half_extents(_side(ver, 1.0), 1.0),
        _half_extents(_side(ver, -1.0), 1.0),
    ]
    # per bin, not per point: a large survey's labels need no (N, 4) array of extents, and
    # the bins are gathered a group at a time (no argsort of the whole survey)
    b = _bins(s, step)
    counts = np.bincount(b)
    ext = np.empty((len(counts), 4))  # half-extents (left, right, up, down) of each bin
    ends = np.cumsum(counts)
    k0 = 0
    while k0 < len(counts):
        # the bins [k0, k1) hold about _GROUP points (at least one bin)
        k1 = max(k0 + 1, int(np.searchsorted(ends, ends[k0] - counts[k0] + _GROUP, "right")))
        k1 = min(k1, len(counts))
        sel = np.flatnonzero((b >= k0) & (b < k1))
        sel = sel[np.argsort(b[sel], kind="stable")]
        start = 0
        for k in range(k0, k1):
            part = sel[start:start + counts[k]]
            start += counts[k]
            if part.size == 0:
                continue
            la, ve = lat[part], ver[part]
            ext[k] = [
                _half_extents(la[la > 0], glob[0]),
                _half_extents(-la[la < 0], glob[1]),
                _half_extents(ve[ve > 0], glob[2]),
                _half_extents(-ve[ve < 0], glob[3]),
            ]
        k0 = k1
        del sel
    for a in range(0, n, _CHUNK):  # a chunk at a time (point by point: the same labels)
        e, la, ve = ext[b[a:a + _CHUNK]], lat[a:a + _CHUNK], ver[a:a + _CHUNK]
        nl = np.where(la >= 0, la / e[:, 0], -la / e[:, 1])
        nv = np.where(ve >= 0, ve / e[:, 2], -ve / e[:, 3])
        labels[a:a + _CHUNK] = np.where(
            nv >= nl,
            np.where(ve >= 0, ROOF, FLOOR),
            np.where(la >= 0, LEFT_WALL, RIGHT_WALL),
        )
    return labels


def _near_sections(s: np.ndarray, step: float, half: float) -> np.ndarray:
    """Indices (ascending) of the points within ``half`` of a multiple of ``step``, with a
    margin of rounding (a chunk at a time)."""
    tol = half + 1e-6 * step
    parts = []
    for a in range(0, len(s), _CHUNK):
        c = s[a:a + _CHUNK]
        parts.append(np.flatnonzero(np.abs(c - np.rint(c / step) * step) <= tol) + a)
    return np.concatenate(parts) if parts else np.empty(0, dtype=np.intp)


def _stats(prefix: str, v: np.ndarray) -> dict[str, float]:
    if v.size == 0:
        nan = math.nan
        return {f"{prefix}mean": nan, f"{prefix}std": nan, f"{prefix}mean_abs": nan}
    return {
        f"{prefix}mean": float(v.mean()),
        f"{prefix}std": float(v.std()),
        f"{prefix}mean_abs": float(np.abs(v).mean()),
    }


def section_statistics(
    d: DeformationResult,
    *,
    step: float = 1.0,
    thickness: float = 0.2,
    start: float | None = None,
    stop: float | None = None,
    shell_only: bool = True,
) -> list[dict[str, Any]]:
    """Deformation statistics of cross-sections along the chainage (paper Table 4 analogue).

    Parameters
    ----------
    d : DeformationResult
        Per-point deformation (:func:`tunneldef.deformation.compute_deformation`).
    step : float
        Distance between sections, metres (paper Table 4: 1 m).
    thickness : float
        A section holds the points within ``thickness / 2`` of its chainage, metres.
    start, stop : float, optional
        Chainage range of the sections (default: the points' range clipped to the
        centreline, ``[0, length]``, at multiples of ``step``).
    shell_only : bool
        Compute the statistics on shell points only (equipment, coal, people left out).

    Returns
    -------
    list of dict
        One row per section with at least one point, in order of chainage, with keys
        ``chainage``, ``n_points`` (all points), ``n_shell``, ``n_valid`` (points the
        statistics are computed on: shell, with a counterpart), ``mean``, ``std``, ``mean_abs``,
        ``min``, ``max`` (signed deformation, m), ``mean_horizontal``, ``mean_vertical``
        (Manhattan components, m), and ``<surface>_n``, ``<surface>_mean``,
        ``<surface>_std``, ``<surface>_mean_abs`` for roof, left_wall, right_wall, floor, plus
        ``roof_mean_vertical``, ``floor_mean_vertical``, ``left_wall_mean_horizontal`` and
        ``right_wall_mean_horizontal`` (the component along each surface's normal).

    Raises
    ------
    ConfigError
        If ``step`` or ``thickness`` is not positive.
    InvalidCloudError
        If ``d`` holds no points.
    """
    if not step > 0:
        raise ConfigError(f"section step must be > 0 m, got {step!r}")
    if not thickness > 0:
        raise ConfigError(f"section thickness must be > 0 m, got {thickness!r}")
    s = np.asarray(d.chainage, dtype=np.float64)
    if s.size == 0:
        raise InvalidCloudError("no points to compute section statistics on")
    length = d.centerline_length
    lo = float(s.min()) if start is None else float(start)
    hi = float(s.max()) if stop is None else float(stop)
    if start is None and length is not None:
        lo = max(lo, 0.0)
    if stop is None and length is not None:
        hi = min(hi, length)
    k0, k1 = math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9)
    half = thickness / 2.0
    # only the points within half a thickness of a section's chainage are sorted: a fifth of
    # a large survey at the defaults (the sections are those of a sort of every point)
    order = _near_sections(s, step, half) if thickness < step else np.arange(len(s))
    order = order[np.argsort(s[order], kind="stable")]
    s_sorted = s[order]
    rows: list[dict[str, Any]] = []
    for kk in range(k0, k1 + 1):
        c = kk * step
        i0 = np.searchsorted(s_sorted, c - half, side="left")
        i1 = np.searchsorted(s_sorted, c + half, side="right")
        sel = order[i0:i1]
        if sel.size == 0:
            continue
        shell = d.shell[sel]
        use = sel[shell] if shell_only else sel
        use = use[np.isfinite(d.deformation[use])]  # points without a counterpart left out
        v = d.deformation[use]
        row: dict[str, Any] = {
            "chainage": round(c, 9),
            "n_points": int(sel.size),
            "n_shell": int(shell.sum()),
            "n_valid": int(use.size),
        }
        row.update(_stats("", v))
        row["min"] = float(v.min()) if v.size else math.nan
        row["max"] = float(v.max()) if v.size else math.nan
        h, ve = d.horizontal[use], d.vertical[use]
        row["mean_horizontal"] = float(h.mean()) if v.size else math.nan
        row["mean_vertical"] = float(ve.mean()) if v.size else math.nan
        surf = d.surface[use]
        for code, name in enumerate(SURFACE_NAMES):
            m = surf == code
            row[f"{name}_n"] = int(m.sum())
            row.update(_stats(f"{name}_", v[m]))
            comp = ve[m] if code in (ROOF, FLOOR) else h[m]
            key = f"{name}_mean_vertical" if code in (ROOF, FLOOR) else f"{name}_mean_horizontal"
            row[key] = float(comp.mean()) if comp.size else math.nan
        rows.append(row)
    logger.debug("section statistics: %d sections", len(rows))
    return rows


def write_sections_csv(rows: Sequence[dict[str, Any]], path: str | os.PathLike[str]) -> None:
    """Write section rows as CSV (one row per section, columns in the first row's order).

    The file is written to a temporary file in the same folder and renamed, so a reader never
    sees a half-written table.
    """
    p = Path(path)
    columns: list[str] = list(rows[0].keys()) if rows else ["chainage"]
    for r in rows[1:]:
        columns.extend(key for key in r if key not in columns)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, restval="", lineterminator="\r\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    write_text_atomic(p, buf.getvalue())
