"""Optional last stage of the centreline registration: robust point-to-plane ICP restricted to
the stable shell (beyond the paper).

The centreline stages leave errors of a few millimetres to a centimetre that come from the
centrelines themselves (their extraction noise, and what roof sag, coal or equipment do to the
slice centres). Aligning the shell surfaces directly removes them, but a whole-cloud ICP would
also pull the compared epoch towards its deformed parts. Here equipment and clutter (points off
the section outline) and the compared points with the largest residuals (where deformation is)
are left out, and a Tukey kernel ignores what remains of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from ..curve import Centerline
from ..spatial import query_workers
from ..transforms import apply_transform

__all__ = ["OffsetTest", "refine_stable", "shell_offset"]


def refine_stable(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    ref_cl: Centerline,
    *,
    voxel: float,
    keep_fraction: float = 0.8,
    iterations: int = 30,
) -> np.ndarray:
    """Robust point-to-plane ICP on the stable shell (optional last stage).

    Points off the shell (equipment, clutter: more than 10 cm from the median distance to the
    centreline in their 0.5 m x 7.5 degree cell) and the compared points with the largest
    residuals after a first wide-kernel round (the ``1 - keep_fraction`` worst, where
    deformation is) are left out of the second round; the rest is voxel-downsampled and aligned
    with a Tukey kernel (width 3 voxels, then 1 voxel).

    Returns
    -------
    ndarray, shape (4, 4)
        Correction to apply after the compared points' current transform.
    """
    ref_s = _shell_mask(ref_xyz, ref_cl)
    cmp_s = _shell_mask(cmp_xyz, ref_cl)
    ref_pts = ref_xyz[ref_s]
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ref_pts)).voxel_down_sample(voxel)
    dst.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    reg = o3d.pipelines.registration
    tree = cKDTree(ref_pts)
    total = np.eye(4)
    # round 1: the whole stable shell, wide kernel; round 2: without the worst residuals
    for kernel, reach, keep in ((3 * voxel, 5 * voxel, 1.0), (voxel, 2 * voxel, keep_fraction)):
        moved = apply_transform(total, cmp_xyz)
        sel = cmp_s.copy()
        if keep < 1.0:
            d, _ = tree.query(moved, workers=query_workers(len(moved)))
            sel &= d <= np.quantile(d[cmp_s], keep)
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(moved[sel]))
        src = src.voxel_down_sample(voxel)
        res = reg.registration_icp(
            src,
            dst,
            reach,
            np.eye(4),
            reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=kernel)),
            reg.ICPConvergenceCriteria(max_iteration=iterations),
        )
        total = np.asarray(res.transformation) @ total
    return total


def shell_offset(
    ref_xyz: np.ndarray,
    ref_normals: np.ndarray,
    ref_tree: cKDTree,
    ref_cl: Centerline,
    positions: list[np.ndarray],
    *,
    cell_length: float = 1.0,
    sectors: int = 16,
    trim: float = 0.2,
    reach: float = 0.1,
    min_points: int = 20,
) -> OffsetTest:
    """How far the compared shell sits off the reference, cell by cell, for several positions
    of the same compared points, and whether the last position sits closer than the first
    beyond the noise.

    The compared points on the stable shell (as in :func:`refine_stable`, judged at the first
    position) are binned into cells of ``cell_length`` along the reference centreline and
    ``sectors`` angular sectors of the section; in each cell the median signed point-to-plane
    distance to the nearest reference point (normals turned outward) is the cell's offset.
    The score of a position is the RMS offset over the cells, leaving out the ``trim`` share
    of cells with the largest ones (where the tunnel deformed). A rigid misalignment shows in
    most cells (a lateral slide in every wall cell, a tilt in every roof cell); a local change
    only in its own few, which the trim drops: the medians and the trim make the score a test
    the robust ICP was not fitted to.

    The first and last positions are also compared cell by cell (paired, on the cells that
    hold ``min_points`` at both, leaving out the ``trim`` share whose offsets are largest at
    both: ranked by the smaller of their two squares, so that a slide that shows only in a
    few wall cells is not trimmed away): the fall of the squared offset per cell, its mean
    over its standard error is ``z``. The cells hold
    different points, so their medians' noise is independent; a fall of the score that is
    within it (sparse or noisy shells: cell medians of a few tens of points) gives a small
    ``z`` whatever the two scores say.

    Parameters
    ----------
    ref_xyz, ref_normals : ndarray, shape (M, 3)
        Reference points and their (unoriented) unit normals; ``ref_tree`` is a KD-tree of
        ``ref_xyz``.
    ref_cl : Centerline
        Reference centreline, same frame.
    positions : list of ndarray, shape (N, 3)
        The same compared points (row for row) at each candidate position.

    Returns
    -------
    OffsetTest
        ``scores`` (metres, one per position; NaN when fewer than 10 cells hold
        ``min_points``), ``z`` (NaN when fewer than 10 cells are shared) and ``cells``.
    """
    first = positions[0]
    shell = _shell_mask(first, ref_cl)
    p = ref_cl.project(first[shell])
    _, lat, ver = ref_cl.frame_at(p.chainage)
    radial = p.lateral[:, None] * lat + p.vertical[:, None] * ver
    ang = np.arctan2(p.vertical, p.lateral)
    cell = np.floor(p.chainage / cell_length).astype(np.int64) * sectors + (
        np.floor((ang + np.pi) / (2 * np.pi) * sectors).astype(np.int64) % sectors
    )
    _, cell = np.unique(cell, return_inverse=True)
    n_cells = int(cell.max()) + 1 if len(cell) else 0
    meds = np.full((len(positions), n_cells), np.nan)
    for row, pos in enumerate(positions):
        pts = pos[shell]
        d, j = ref_tree.query(pts, workers=query_workers(len(pts)))
        n = ref_normals[j]
        signed = np.einsum("ij,ij->i", pts - ref_xyz[j], n)
        signed *= np.sign(np.einsum("ij,ij->i", n, radial))
        ok = d <= reach
        key, val = cell[ok], signed[ok]
        order = np.lexsort((val, key))
        key, val = key[order], val[order]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        ends = np.r_[starts[1:], len(key)]
        full = ends - starts >= min_points
        lo, hi = starts[full], ends[full]
        meds[row, key[lo]] = 0.5 * (val[(lo + hi - 1) // 2] + val[(lo + hi) // 2])
    scores = []
    for med in meds:
        off = np.sort(med[np.isfinite(med)] ** 2)
        if len(off) < 10:
            scores.append(float("nan"))
            continue
        scores.append(float(np.sqrt(off[: max(1, int(round((1.0 - trim) * len(off))))].mean())))
    z, used = float("nan"), 0
    if len(positions) >= 2:
        b2, a2 = meds[0] ** 2, meds[-1] ** 2
        both = np.isfinite(b2) & np.isfinite(a2)
        worst = np.minimum(b2, a2)[both]
        keep = worst <= np.quantile(worst, 1.0 - trim) if both.any() else worst.astype(bool)
        fall = (b2[both] - a2[both])[keep]
        used = len(fall)
        if used >= 10:
            se = fall.std(ddof=1) / np.sqrt(used)
            z = float(fall.mean() / se) if se > 0 else float("inf") * np.sign(fall.mean())
    return OffsetTest(scores=scores, z=z, cells=used)


@dataclass(frozen=True)
class OffsetTest:
    """Result of :func:`shell_offset`: trimmed RMS cell offset per position (m), and the
    paired test of the last position against the first (``z``: mean fall of the squared cell
    offsets over its standard error; positive = closer) on ``cells`` shared cells."""

    scores: list[float]
    z: float
    cells: int


def _shell_mask(xyz: np.ndarray, cl: Centerline, tol: float = 0.1) -> np.ndarray:
    p = cl.project(xyz)
    i = np.floor(p.chainage / 0.5).astype(np.int64)
    i -= i.min()
    j = (np.floor((np.arctan2(p.vertical, p.lateral) + np.pi) / (2 * np.pi) * 48)).astype(
        np.int64
    ) % 48
    key = i * 48 + j
    order = np.argsort(key, kind="stable")
    k_sorted = key[order]
    r_sorted = p.distance[order]
    starts = np.flatnonzero(np.r_[True, k_sorted[1:] != k_sorted[:-1]])
    # median per cell: sort by (cell, r) and take the middle element
    order2 = np.lexsort((r_sorted, k_sorted))
    r2 = r_sorted[order2]
    ends = np.r_[starts[1:], len(k_sorted)]
    med = r2[(starts + ends) // 2]
    cell_med = np.repeat(med, ends - starts)
    mask = np.empty(len(xyz), dtype=bool)
    mask[order] = np.abs(r_sorted - cell_med) <= tol
    return mask
