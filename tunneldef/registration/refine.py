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
from ..spatial import plane_normals, query_workers, voxel_grid
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
    # both clouds in Morton order (Open3D's voxel grids come out in hash order, and their
    # normals and ICP queries then read memory at random), normals about the centroid
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(voxel_grid(ref_pts, voxel)))
    dst.normals = o3d.utility.Vector3dVector(plane_normals(np.asarray(dst.points), 4 * voxel, 30))
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
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(voxel_grid(moved[sel], voxel)))
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
    sectors: int = 32,
    trim: float = 0.2,
    reach: float = 0.1,
    min_points: int = 20,
    neighbours: int = 24,
) -> OffsetTest:
    """How far the compared shell sits off the reference, cell by cell, for several positions
    of the same compared points, and whether the last position is the one the shell asks for.

    Each compared point on the stable shell (as in :func:`refine_stable`, judged at the first
    position, within ``reach`` of a reference point) is tied, once, to the local plane of its
    nearest reference point at the first position: the centroid of that point's
    ``neighbours`` nearest reference points and its normal, turned outward. Its offset at
    every position is its signed distance to that same plane, so a rigid move changes it
    linearly, by exactly the move along the normal: measured against the nearest point at
    each position instead, a move of 1.5 mm along a rough roof with 15 mm noise changed the
    cells' medians by 0.8 mm of noise, as much as it moved the walls. The points are binned
    into cells of ``cell_length`` along the reference centreline and ``sectors`` angular
    sectors of the section (32: twice the cells of 16, each a narrower strip of the outline);
    a cell's offset is the median over its points. The score of a position is the RMS offset
    over the cells, leaving out the ``trim`` share of cells with the largest ones (where the
    tunnel deformed).

    The last position is tested against the first on the cells that hold ``min_points`` at
    both, leaving out the ``trim`` share whose offsets are largest at both (ranked by the
    smaller of their two squares, so that a slide that shows in a few wall cells only is not
    trimmed away): the least-squares share of each cell's move that its offset at the first
    position asks for (``share``: 1 when the move takes the shell onto the reference, 0 when
    the shell sat there already, negative when it moves away) and its standard error
    (``share_se``; :meth:`OffsetTest.verdict` decides with them). The test follows the move's
    own direction cell by cell: a lateral slide is judged on the walls, where it shows, and
    the roof's noise does not dilute it. The cells hold different points, so their medians'
    noise is independent; a share within it (sparse or noisy shells) is undecided.

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
        ``min_points``), ``share`` and ``share_se`` (NaN when fewer than 10 cells are
        shared, or the positions do not differ) and ``cells``.
    """
    first = positions[0]
    idx = np.flatnonzero(_shell_mask(first, ref_cl))
    d, j = ref_tree.query(first[idx], workers=query_workers(len(idx)))
    near = d <= reach
    idx, j = idx[near], j[near]
    uj, j_inv = np.unique(j, return_inverse=True)
    k = min(neighbours, len(ref_xyz))
    _, nb = ref_tree.query(ref_xyz[uj], k=k, workers=query_workers(len(uj)))
    centre = ref_xyz[nb.reshape(len(uj), k)].mean(axis=1)[j_inv]
    p = ref_cl.project(first[idx])
    _, lat, ver = ref_cl.frame_at(p.chainage)
    radial = p.lateral[:, None] * lat + p.vertical[:, None] * ver
    normal = ref_normals[j]
    normal = normal * np.sign(np.einsum("ij,ij->i", normal, radial))[:, None]
    ang = np.arctan2(p.vertical, p.lateral)
    cell = np.floor(p.chainage / cell_length).astype(np.int64) * sectors + (
        np.floor((ang + np.pi) / (2 * np.pi) * sectors).astype(np.int64) % sectors
    )
    _, cell = np.unique(cell, return_inverse=True)
    n_cells = int(cell.max()) + 1 if len(cell) else 0
    meds = np.full((len(positions), n_cells), np.nan)
    for row, pos in enumerate(positions):
        val = np.einsum("ij,ij->i", pos[idx] - centre, normal)
        order = np.lexsort((val, cell))
        key, val = cell[order], val[order]
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
    share, se, used = float("nan"), float("nan"), 0
    if len(positions) >= 2:
        b, a = meds[0], meds[-1]
        both = np.isfinite(b) & np.isfinite(a)
        b, a = b[both], a[both]
        worst = np.minimum(b * b, a * a)
        keep = worst <= np.quantile(worst, 1.0 - trim) if len(worst) else worst.astype(bool)
        b, moved = b[keep], (b - a)[keep]
        used = len(b)
        ss = float(moved @ moved)
        if used >= 10 and ss > 0:
            share = float(b @ moved) / ss
            resid = b - share * moved
            se = float(np.sqrt(resid @ resid / (used - 1) / ss))
    return OffsetTest(scores=scores, share=share, share_se=se, cells=used)


@dataclass(frozen=True)
class OffsetTest:
    """Result of :func:`shell_offset`: trimmed RMS cell offset per position (m), and the
    test of the last position against the first on ``cells`` shared cells: ``share``, the
    least-squares share of the cells' moves that their offsets at the first position ask for
    (1: the move takes the shell onto the reference; 0: the shell sat there already;
    negative: the move takes it away), and its standard error ``share_se``."""

    scores: list[float]
    share: float
    share_se: float
    cells: int

    def verdict(self, z: float, fitted: int = 6) -> str:
        """``"asked"`` when the share is at least one half and above 0 by ``z`` standard
        errors plus ``sqrt(fitted) / 2``, ``"refused"`` when it is below one half and below 1
        by ``z`` standard errors, ``"undecided"`` otherwise (too few cells, or a share within
        the noise).

        The move being judged was fitted to the same shell (``fitted`` parameters: 6 for a
        rigid ICP), so even a move that only follows the noise finds the cells asking for
        part of it: about ``sqrt(fitted) / 2`` standard errors on average. The allowance
        takes that out of the evidence for keeping a move, and not from the evidence
        against it."""
        if not (np.isfinite(self.share) and np.isfinite(self.share_se)):
            return "undecided"
        if self.share >= 0.5 and self.share >= (z + 0.5 * np.sqrt(fitted)) * self.share_se:
            return "asked"
        if self.share < 0.5 and 1.0 - self.share >= z * self.share_se:
            return "refused"
        return "undecided"


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
