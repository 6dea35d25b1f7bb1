"""The footprint of a drift network on a plan grid: robust extent, occupancy, heights.

Mine drifts are near-horizontal (ramps climb at 10-15 %), so seen from above the floor and roof
points of a drift fill its footprint; :mod:`.skeleton` turns that footprint into the graph of
the network.

1. Robust extent: points are counted in coarse (1 m) plan cells; cells with fewer than
   ``min_coarse_count`` points are dropped and so are connected groups of cells smaller than
   ``min_component_area``, so a stray point or a small far cluster neither creates an edge nor
   stretches the grid. The fine grid is allocated over what is left, and refused beyond
   ``max_cells`` cells.
2. Footprint: fine cells (``cell``) with at least ``min_count`` points, closed by a small disk
   (sparse scans leave empty cells between points), holes smaller than ``max_hole_area``
   filled (the blind cone under a static scanner, a missing patch of floor); larger holes are
   pillars between drifts and stay.
3. Heights: per cell the 5th and 95th percentiles of z (floor and roof over the interior).
   A cell whose span is far larger than the footprint's typical height shows two drifts above
   one another (or a shaft); the plan view cannot separate them and
   :class:`~tunneldef.errors.NetworkError` is raised.

Why the plan view rather than a 3-D skeleton: a handheld scan samples the shell, not the
volume; filling the inside of a 3-D occupancy grid needs the same "between floor and roof"
rule per plan column that the plan view uses, at 1/100 of the memory (a 250 m network at
0.2 m: 0.1 M plan cells against 10 M voxels). Its limit is drifts above one another, which is
detected and refused, not silently merged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import NetworkError

__all__ = ["PlanGrid", "plan_grid"]


@dataclass
class PlanGrid:
    """The footprint of a network on a plan grid.

    Attributes
    ----------
    origin : ndarray, shape (2,)
        World x, y of the corner of cell (0, 0), metres.
    cell : float
        Cell size, metres.
    footprint : ndarray of bool, shape (nx, ny)
        Cells inside a drift.
    z_low, z_high : ndarray, shape (nx, ny)
        5th / 95th percentile of z per cell (NaN where no points).
    half_width : ndarray, shape (nx, ny)
        Distance to the nearest cell outside the footprint, metres (the medial axis's radius).
    keep : ndarray of bool, shape (N,)
        Points that lie in the retained extent (False: strays).
    height : float
        Median floor-to-roof span over the footprint's interior, metres.
    """

    origin: np.ndarray
    cell: float
    footprint: np.ndarray
    z_low: np.ndarray
    z_high: np.ndarray
    half_width: np.ndarray
    keep: np.ndarray
    height: float

    def to_world(self, ij: np.ndarray) -> np.ndarray:
        """World x, y (K, 2) of cell centres ``ij`` (K, 2)."""
        return self.origin + (np.asarray(ij, dtype=np.float64) + 0.5) * self.cell


def _components(keys: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected components of integer plan cells ``keys`` (K, 2)."""
    pairs = cKDTree(keys).query_pairs(1.5, output_type="ndarray")
    n = len(keys)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    ncomp, labels = connected_components(g, directed=False)
    return labels, ncomp


def plan_grid(
    xyz: np.ndarray,
    *,
    cell: float = 0.2,
    min_count: int = 2,
    coarse: float = 1.0,
    min_coarse_count: int = 20,
    min_component_area: float = 20.0,
    max_hole_area: float = 16.0,
    max_cells: int = 20_000_000,
    max_height_ratio: float = 1.8,
    max_stacked_area: float = 2.0,
) -> PlanGrid:
    """Plan-view occupancy, heights and half-widths of a network cloud.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Points, metres, z up.
    cell : float
        Fine cell size, metres.
    min_count : int
        Least points for a fine cell to be occupied.
    coarse, min_coarse_count, min_component_area :
        Coarse cell size (m), least points per coarse cell, least area (m^2) of a connected
        group of coarse cells: what fails these is stray.
    max_hole_area : float
        Holes of the footprint smaller than this are filled, m^2.
    max_cells : int
        Largest fine grid allocated.
    max_height_ratio, max_stacked_area :
        Cells whose z span exceeds ``max_height_ratio`` times the median span, over more than
        ``max_stacked_area`` m^2, mean drifts above one another.

    Raises
    ------
    NetworkError
        No dense part, an extent too large for the grid, or drifts above one another.
    """
    from skimage.morphology import disk, remove_small_holes, remove_small_objects

    xy = xyz[:, :2]
    ck = np.floor(xy / coarse).astype(np.int64)
    key = (ck[:, 0] + 2**31) * 2**32 + (ck[:, 1] + 2**31)
    ukey, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    uk = np.stack([ukey // 2**32 - 2**31, ukey % 2**32 - 2**31], axis=1)
    dense = cnt >= min_coarse_count
    if not dense.any():
        raise NetworkError(
            f"no part of the cloud holds {min_coarse_count} points per {coarse:g} m plan cell; "
            "is it a tunnel scan in metres?"
        )
    labels, ncomp = _components(uk[dense])
    area = np.bincount(labels, minlength=ncomp) * coarse**2
    good_comp = area >= min_component_area
    if not good_comp.any():
        raise NetworkError(
            f"the cloud's largest dense part covers {area.max():.1f} m^2 of plan, less than "
            f"{min_component_area:g} m^2; is it a tunnel scan in metres?"
        )
    good_cell = np.zeros(len(uk), dtype=bool)
    good_cell[np.flatnonzero(dense)[good_comp[labels]]] = True
    keep = good_cell[inv]
    p = xyz[keep]
    lo = p[:, :2].min(axis=0) - 2 * cell
    hi = p[:, :2].max(axis=0) + 2 * cell
    shape = np.ceil((hi - lo) / cell).astype(np.int64) + 1
    if shape[0] * shape[1] > max_cells:
        raise NetworkError(
            f"the network's plan extent ({hi[0] - lo[0]:.0f} m x {hi[1] - lo[1]:.0f} m) needs "
            f"{shape[0] * shape[1]:,} cells of {cell} m, more than {max_cells:,}; raise the "
            "network cell size"
        )
    ij = np.floor((p[:, :2] - lo) / cell).astype(np.int64)
    lin = ij[:, 0] * shape[1] + ij[:, 1]
    counts = np.bincount(lin, minlength=shape[0] * shape[1]).reshape(shape)
    occ = counts >= min_count
    occ = ndimage.binary_closing(occ, structure=disk(2), border_value=0)
    occ = remove_small_holes(occ, max_size=max(int(max_hole_area / cell**2), 1))
    occ = remove_small_objects(occ, max_size=max(int(min_component_area / cell**2), 1))
    # per-cell z percentiles: sort by (cell, z), pick by rank
    order = np.lexsort((p[:, 2], lin))
    ls, zs = lin[order], p[order, 2]
    starts = np.flatnonzero(np.concatenate([[True], ls[1:] != ls[:-1]]))
    n = np.diff(np.append(starts, len(ls)))
    z_low = np.full(shape[0] * shape[1], np.nan)
    z_high = np.full_like(z_low, np.nan)
    z_low[ls[starts]] = zs[starts + np.floor(0.05 * (n - 1)).astype(np.int64)]
    z_high[ls[starts]] = zs[starts + np.ceil(0.95 * (n - 1)).astype(np.int64)]
    z_low, z_high = z_low.reshape(shape), z_high.reshape(shape)
    half_width = ndimage.distance_transform_edt(occ) * cell
    interior = occ & (half_width > 3 * cell) & (counts >= 4)
    spans = (z_high - z_low)[interior]
    if spans.size == 0:
        raise NetworkError("the cloud's footprint has no interior; is it a tunnel scan?")
    height = float(np.median(spans))
    tall = interior & (z_high - z_low > max_height_ratio * height)
    if tall.sum() * cell**2 > max_stacked_area:
        where = lo + (np.argwhere(tall).mean(axis=0) + 0.5) * cell
        raise NetworkError(
            f"{tall.sum() * cell**2:.0f} m^2 of the plan span more than {max_height_ratio:g} x "
            f"the drifts' {height:.2f} m height (around x={where[0]:.1f}, y={where[1]:.1f}): "
            "drifts above one another or a shaft, which the plan-view network cannot separate"
        )
    return PlanGrid(lo, cell, occ, z_low, z_high, half_width, keep, height)
