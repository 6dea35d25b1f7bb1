"""Registration quality: the paper's fitness score (Table 2) overall and per slice, overlap, and
errors against a known transform.

The fitness score of the paper (§4.2, Table 2) is the root mean square of the distances between
corresponding points of the two clouds, correspondences being nearest neighbours. Pairs farther
apart than ``max_distance`` are not correspondences (they are the parts one epoch has and the
other lacks) and are left out, as in PCL's ``getFitnessScore``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..curve import Centerline
from ..spatial import query_workers
from ..transforms import apply_transform

__all__ = [
    "apply_transform",
    "nearest_distances",
    "fitness",
    "slice_fitness",
    "overlap_fraction",
    "rotation_error_deg",
    "translation_error",
    "point_rms_error",
]




def nearest_distances(
    ref_xyz: np.ndarray, xyz: np.ndarray, *, tree: cKDTree | None = None, workers: int = -1
) -> np.ndarray:
    """Distance (N,) from each point of ``xyz`` to its nearest point of ``ref_xyz``, metres."""
    tree = tree if tree is not None else cKDTree(ref_xyz)
    d, _ = tree.query(xyz, workers=query_workers(len(xyz), workers))
    return d


def fitness(distances: np.ndarray, *, max_distance: float = 0.1) -> float:
    """The paper's fitness score (§4.2): RMSE of nearest-neighbour distances, metres.

    Distances above ``max_distance`` (non-corresponding parts) are ignored; NaN if none is left.
    """
    d = np.asarray(distances, dtype=np.float64)
    d = d[d <= max_distance]
    return float(np.sqrt(np.mean(d**2))) if d.size else float("nan")


def slice_fitness(
    ref_xyz: np.ndarray,
    xyz: np.ndarray,
    centerline: Centerline,
    *,
    n_slices: int = 5,
    thickness: float = 0.2,
    max_distance: float = 0.1,
    chainages: np.ndarray | None = None,
    tree: cKDTree | None = None,
) -> list[dict[str, float]]:
    """Fitness per cross-section slice (the paper's Table 2), metres.

    Parameters
    ----------
    ref_xyz : ndarray, shape (M, 3)
        Reference points.
    xyz : ndarray, shape (N, 3)
        Registered compared points, reference frame.
    centerline : Centerline
        Reference centreline; slices are cut normal to it.
    n_slices : int
        Number of slices evenly spread over the chainage both epochs cover (ignored when
        ``chainages`` is given).
    thickness : float
        Slice thickness along the chainage, metres.
    max_distance : float
        Correspondence cut-off, metres.

    Returns
    -------
    list of dict
        ``{"chainage", "fitness", "points"}`` per slice.
    """
    tree = tree if tree is not None else cKDTree(ref_xyz)
    s = centerline.project(xyz).chainage
    if chainages is None:
        lo = max(float(np.percentile(s, 2)), 0.0)
        hi = min(float(np.percentile(s, 98)), centerline.length)
        if hi <= lo:
            return []
        chainages = np.linspace(lo, hi, n_slices + 2)[1:-1]
    out = []
    for c in np.asarray(chainages, dtype=np.float64):
        m = np.abs(s - c) <= thickness / 2
        d = nearest_distances(ref_xyz, xyz[m], tree=tree) if m.any() else np.empty(0)
        out.append(
            {
                "chainage": float(c),
                "fitness": fitness(d, max_distance=max_distance),
                "points": int(m.sum()),
            }
        )
    return out


def overlap_fraction(distances: np.ndarray, *, radius: float) -> float:
    """Fraction of points whose nearest neighbour in the other epoch is within ``radius`` m."""
    d = np.asarray(distances)
    return float(np.mean(d <= radius)) if d.size else 0.0


def rotation_error_deg(estimated: np.ndarray, truth: np.ndarray) -> float:
    """Angle of the rotation between two 4 x 4 (or 3 x 3) transforms, degrees."""
    r = np.asarray(estimated)[:3, :3].T @ np.asarray(truth)[:3, :3]
    c = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def translation_error(estimated: np.ndarray, truth: np.ndarray, *, at: np.ndarray) -> float:
    """Distance between where two transforms put the point ``at`` (3,), metres (a translation
    error that does not depend on where the origin happens to be)."""
    a = apply_transform(estimated, np.asarray(at, dtype=np.float64)[None])
    b = apply_transform(truth, np.asarray(at, dtype=np.float64)[None])
    return float(np.linalg.norm(a - b))


def point_rms_error(estimated: np.ndarray, truth: np.ndarray, xyz: np.ndarray) -> float:
    """RMS distance between the points mapped by the estimated and the true transform, metres."""
    d = apply_transform(estimated, xyz) - apply_transform(truth, xyz)
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", d, d))))
