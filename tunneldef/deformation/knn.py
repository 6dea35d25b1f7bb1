"""The paper's per-point deformation: KNN-centroid counterparts and the Manhattan split.

For every point of the compared epoch, its counterpart on the reference epoch is the centroid of
its ``k`` nearest reference points (paper §3.3.1, Fig. 10; ``k = 3`` from Table 3). The distance
to the counterpart is the point's deformation; it is signed by comparing both points' distances
to the centreline, which also gives the horizontal and vertical components (paper §3.3.2,
Fig. 11).

The fast path (:func:`knn_counterparts`) sorts both clouds in Morton order before building and
querying a scipy KD-tree, which makes the query several times faster on large clouds, and
scatters the results back to the input order. :func:`knn_counterparts_reference` is a plain
NumPy twin for small inputs, used to test the fast path.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import check_points
from ..curve import Centerline, Projection
from ..errors import InvalidCloudError
from ..progress import ProgressCallback, notify
from ..spatial import morton_order

__all__ = [
    "knn_counterparts",
    "knn_counterparts_reference",
    "manhattan_split",
    "counterpart_projection",
]

logger = logging.getLogger(__name__)

def _check_k(k: int) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise InvalidCloudError(
            f"k (number of nearest neighbours) must be an integer >= 1, got {k!r}; "
            "the paper uses k = 3 (Table 3)"
        )
    return int(k)


def _check_pair(ref_xyz: np.ndarray, cmp_xyz: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    ref = check_points(ref_xyz, name="reference cloud")
    cmp = check_points(cmp_xyz, name="compared cloud")
    if ref.shape[0] < k:
        raise InvalidCloudError(
            f"reference cloud has {ref.shape[0]} points, fewer than k = {k}; "
            "lower k or use a denser reference"
        )
    return ref, cmp


def knn_counterparts(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    *,
    k: int = 3,
    workers: int = -1,
    chunk_size: int = 1_000_000,
    progress: ProgressCallback | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Counterpart of each compared point: the centroid of its k nearest reference points.

    Parameters
    ----------
    ref_xyz : ndarray, shape (M, 3)
        Reference epoch, metres.
    cmp_xyz : ndarray, shape (N, 3)
        Compared epoch, already registered into the reference frame, metres.
    k : int
        Number of nearest reference points averaged (paper §4.3, Table 3: k = 3).
    workers : int
        Threads for the KD-tree query (-1: all cores).
    chunk_size : int
        Compared points queried at once (bounds memory to ~ ``chunk_size * k * 40`` bytes).
    progress : callable, optional
        ``progress(stage, fraction)``.

    Returns
    -------
    counterpart : ndarray, shape (N, 3)
        Centroid of the k nearest reference points, metres, in the input order.
    distance : ndarray, shape (N,)
        Euclidean distance from each compared point to its counterpart, metres.

    Raises
    ------
    InvalidCloudError
        If a cloud is empty, not N x 3 or not finite, or ``k`` < 1 or > M.

    Notes
    -----
    Both clouds are sorted in Morton order (:func:`morton_order`) and shifted to a local origin
    before the tree is built and queried; results are scattered back to the input order. Paper
    §3.3.1, steps (1)-(4).
    """
    k = _check_k(k)
    ref, cmp = _check_pair(ref_xyz, cmp_xyz, k)
    origin = ref.mean(axis=0)
    ref_order = morton_order(ref)
    ref_sorted = ref[ref_order] - origin
    tree = cKDTree(ref_sorted, balanced_tree=False, compact_nodes=False)
    cmp_order = morton_order(cmp)
    n = cmp.shape[0]
    counterpart = np.empty((n, 3))
    distance = np.empty(n)
    chunk_size = max(int(chunk_size), 1)
    for start in range(0, n, chunk_size):
        sel = cmp_order[start : start + chunk_size]
        q = cmp[sel] - origin
        _, idx = tree.query(q, k=k, workers=workers)
        idx = idx.reshape(len(sel), k)
        c = ref_sorted[idx].mean(axis=1)
        counterpart[sel] = c + origin
        distance[sel] = np.linalg.norm(q - c, axis=1)
        notify(progress, "deformation: nearest neighbours", min(start + chunk_size, n) / n)
    return counterpart, distance


def knn_counterparts_reference(
    ref_xyz: np.ndarray, cmp_xyz: np.ndarray, *, k: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Plain NumPy brute-force twin of :func:`knn_counterparts` for small inputs.

    Same parameters and returns; all pairwise distances are computed, so use it only for
    N * M up to a few million (tests).
    """
    k = _check_k(k)
    ref, cmp = _check_pair(ref_xyz, cmp_xyz, k)
    if ref.shape[0] * cmp.shape[0] > 50_000_000:
        raise InvalidCloudError(
            "knn_counterparts_reference is for small clouds (N * M <= 5e7); use knn_counterparts"
        )
    d2 = ((cmp[:, None, :] - ref[None, :, :]) ** 2).sum(axis=2)
    idx = np.argpartition(d2, k - 1, axis=1)[:, :k]
    counterpart = ref[idx].mean(axis=1)
    return counterpart, np.linalg.norm(cmp - counterpart, axis=1)


def manhattan_split(point: Projection, counterpart: Projection) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal and vertical deformation from distances to the centreline (paper §3.3.2).

    Parameters
    ----------
    point, counterpart : Projection
        Each compared point and its counterpart projected on the same centreline.

    Returns
    -------
    horizontal : ndarray, shape (N,)
        ``|lateral(point)| - |lateral(counterpart)|``, metres.
    vertical : ndarray, shape (N,)
        ``|vertical(point)| - |vertical(counterpart)|``, metres.

    Notes
    -----
    The paper measures the distance of a point to the centreline as a Manhattan distance in the
    section (|lateral| + |vertical|, Fig. 11), so the section deformation is
    ``Δd = horizontal + vertical``; negative means the point is closer to the centreline than
    its counterpart: the surface moved into the tunnel (roof sag, wall bulge, floor heave).
    """
    horizontal = np.abs(point.lateral) - np.abs(counterpart.lateral)
    vertical = np.abs(point.vertical) - np.abs(counterpart.vertical)
    return horizontal, vertical


def counterpart_projection(
    centerline: Centerline, xyz: np.ndarray, point: Projection, counterpart: np.ndarray
) -> Projection:
    """Projection of counterparts that lie close to their points, in the points' frames.

    Parameters
    ----------
    centerline : Centerline
    xyz : ndarray, shape (N, 3)
        The points, metres.
    point : Projection
        ``centerline.project(xyz)``.
    counterpart : ndarray, shape (N, 3)
        A counterpart near each point (centimetres away), metres.

    Returns
    -------
    Projection
        The counterparts' chainage and offsets, measured in the centreline frame at each
        point's foot (the frame turns by a negligible angle over a few centimetres, so this
        equals ``centerline.project(counterpart)`` without a second nearest-sample search).
    """
    t, lat, ver = centerline.frame_at(point.chainage)
    delta = np.asarray(counterpart, dtype=np.float64) - xyz
    lateral = point.lateral + np.einsum("ij,ij->i", delta, lat)
    vertical = point.vertical + np.einsum("ij,ij->i", delta, ver)
    chainage = point.chainage + np.einsum("ij,ij->i", delta, t)
    return Projection(
        chainage=chainage,
        lateral=lateral,
        vertical=vertical,
        distance=np.hypot(lateral, vertical),
        inside=(chainage >= 0.0) & (chainage <= centerline.length),
    )
