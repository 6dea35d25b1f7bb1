"""Core points and cylinder statistics of the robust estimator (:mod:`.robust`).

* :func:`voxel_cores`: the compared cloud's voxel centroids, the points where the change is
  measured;
* :func:`_voxel_normals`: the reference's plane normal and surface variation around each core,
  from per-voxel moments;
* :func:`_ball_planes`: the same fit on the exact points of a small ball, for the cores next
  to an edge of the section, where the wider fit straddles two surfaces;
* :func:`_epoch_stats`: the clipped mean, spread and count of one epoch's points in each core's
  cylinder, projected on its normal; the neighbourhoods come from :class:`_RadiusIndex`
  (Open3D's fixed-radius hash grid), and the clipping runs core by core in compiled code
  (:func:`.kernels.cylinder_stats`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["voxel_cores"]

_CHUNK = 40_000  # cores per neighbourhood query (bounds the flat neighbour arrays)
# innermost fraction of each cylinder that may be dropped (objects lie inward of the rock); off:
# on the synthetic benchmark 0.2 cut false alarms from 0.3 % to 0.08 % but recall at 10 mm in a
# 15 mm sag from 0.92 to 0.87, and the adaptive width already handles objects near the rock
_INNER_TRIM = 0.0
_MAX_ANGLE_DEG = 35.0  # points of the same surface as a core: normals within this angle
_COS_MAX_ANGLE = float(np.cos(np.radians(_MAX_ANGLE_DEG)))
_CLIP_K = 3.0  # sigma clipping of the cylinders' values at max(k * std, floor) from the mean
_CLIP_FLOOR = 0.005  # m


def voxel_cores(
    xyz: np.ndarray, spacing: float, anchor: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Core points: centroids of the points in each occupied cubic voxel.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Coordinates, metres (a local origin keeps the voxel indices small).
    spacing : float
        Voxel edge, metres.
    anchor : ndarray, shape (3,), optional
        Corner of the voxel grid, metres (at most ``xyz.min(axis=0)``); the cloud's own minimum
        corner by default. A piece of a cloud cut out of a larger one gets the larger cloud's
        voxels when it is given that cloud's anchor.

    Returns
    -------
    cores : ndarray, shape (C, 3)
        Centroid of each occupied voxel, ordered by voxel index (spatially coherent).
    inverse : ndarray of intp, shape (N,)
        Core of each point.
    """
    corner = xyz.min(axis=0) if anchor is None else np.asarray(anchor, dtype=np.float64)
    ijk = np.floor((xyz - corner) / spacing).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 2] * dims[1] + ijk[:, 1]) * dims[0] + ijk[:, 0]
    _, inverse = np.unique(key, return_inverse=True)
    inverse = inverse.ravel()
    c = int(inverse.max()) + 1
    count = np.bincount(inverse, minlength=c).astype(np.float64)
    cores = np.stack(
        [np.bincount(inverse, weights=xyz[:, i], minlength=c) / count for i in range(3)], axis=1
    )
    return cores, inverse


def _voxel_order(xyz: np.ndarray, spacing: float) -> np.ndarray:
    """Permutation grouping points voxel by voxel (a cheap spatial sort)."""
    if len(xyz) == 0:
        return np.empty(0, dtype=np.intp)
    ijk = np.floor((xyz - xyz.min(axis=0)) / spacing).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    return np.argsort((ijk[:, 2] * dims[1] + ijk[:, 1]) * dims[0] + ijk[:, 0], kind="stable")


class _RadiusIndex:
    """Fixed-radius neighbour search: Open3D's hash grid (``open3d.core.nns``).

    Multi-threaded, and it returns one flat index array per query batch: on a million points
    about five times faster than ``cKDTree.query_ball_point`` and its per-centre Python lists.
    Coordinates are float32, so they should be offsets from a local origin.
    """

    def __init__(self, pts: np.ndarray, radius: float) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.pts = np.ascontiguousarray(pts, dtype=np.float32)
        self._nns = None
        if len(self.pts):
            self._nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(self.pts))
            if not self._nns.fixed_radius_index(float(radius)):
                raise RuntimeError("Open3D could not build its fixed-radius neighbour index")

    @property
    def empty(self) -> bool:
        return self._nns is None

    def ball(self, centres: np.ndarray, radius: float):
        """Points within ``radius`` of each centre: flat ``group`` (sorted centre index),
        ``idx`` (point index) and ``d2`` (squared distance, float32) arrays."""
        splits, idx, d2 = self.ball_csr(centres, radius)
        group = np.repeat(np.arange(len(centres), dtype=np.intp), np.diff(splits))
        return group, idx.astype(np.intp, copy=False), d2

    def ball_csr(self, centres: np.ndarray, radius: float):
        """Points within ``radius`` of each centre as Open3D gives them: ``splits`` (C + 1),
        ``idx`` (point index) and ``d2`` (squared distance, float32); centre ``c``'s points are
        ``idx[splits[c]:splits[c + 1]]``."""
        if self._nns is None or len(centres) == 0:
            return (np.zeros(len(centres) + 1, np.int64), np.empty(0, np.int64),
                    np.empty(0, np.float32))
        q = self._o3d.core.Tensor(np.ascontiguousarray(centres, dtype=np.float32))
        idx, d2, splits = self._nns.fixed_radius_search(q, float(radius), sort=False)
        return splits.numpy(), idx.numpy(), d2.numpy()


class _Epoch(_RadiusIndex):
    """One epoch's points for the cylinder gathers, with the normal of each point's core
    (cylinders keep only the points of their own surface)."""

    def __init__(self, pts: np.ndarray, pt_normals: np.ndarray, radius: float) -> None:
        super().__init__(pts, radius)
        self.normals = np.ascontiguousarray(pt_normals, dtype=np.float32)


def _voxel_normals(
    ref: np.ndarray, cores: np.ndarray, spacing: float, radius: float,
    lo: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane normal, surface variation and thickness of the reference around each core.

    The reference points are summarised per voxel of edge ``spacing`` (count, first and second
    moments about the voxel centre, one ``np.bincount`` each); a core's neighbourhood is every
    voxel whose centre lies within ``radius + spacing / 2`` of it, and its covariance is the
    sum of those voxels' moments moved to the core. Returns the smallest-eigenvalue
    eigenvectors (C, 3) (unoriented), ``l0 / (l0 + l1 + l2)`` (C,) (about 0 on a plane, up
    to 1/3 on a corner; ``inf`` with fewer than 3 points) and ``sqrt(l0)`` (C,), the points'
    standard deviation across the plane (the noise on a plane, at any radius; ``inf`` with
    fewer than 3 points). ``lo`` is the corner of the voxel grid (default:
    :func:`normal_grid_corner` of these points).
    """
    if lo is None:
        lo = normal_grid_corner(ref, cores, spacing, radius)
    hi = np.maximum(ref.max(axis=0), cores.max(axis=0)) + (radius + 2.0 * spacing)
    dims = np.ceil((hi - lo) / spacing).astype(np.int64) + 1
    strides = np.array([1, dims[0], dims[0] * dims[1]], dtype=np.int64)
    ijk = np.floor((ref - lo) / spacing).astype(np.int64)
    keys, inv = np.unique(ijk @ strides, return_inverse=True)
    inv = inv.ravel()
    vijk = np.stack(
        [keys % dims[0], (keys // dims[0]) % dims[1], keys // (dims[0] * dims[1])], axis=1
    )
    centre = lo + (vijk + 0.5) * spacing
    rel = ref - centre[inv]
    nv = len(keys)
    cnt = np.bincount(inv, minlength=nv).astype(np.float64)
    s1 = np.stack([np.bincount(inv, weights=rel[:, i], minlength=nv) for i in range(3)], axis=1)
    pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    s2 = np.stack(
        [np.bincount(inv, weights=rel[:, i] * rel[:, j], minlength=nv) for i, j in pairs], axis=1
    )

    # voxels whose centre lies within radius + spacing / 2 of each core, as flat pairs
    grid = _RadiusIndex(centre - lo, radius + 0.5 * spacing)
    group, k, _ = grid.ball(cores - lo, radius + 0.5 * spacing)
    d = centre[k] - cores[group]  # voxel centre relative to the core
    c_, a1, a2 = cnt[k], s1[k], s2[k]
    ncore = len(cores)
    n_c = np.bincount(group, weights=c_, minlength=ncore)
    m1 = np.stack(
        [np.bincount(group, weights=a1[:, i] + c_ * d[:, i], minlength=ncore) for i in range(3)],
        axis=1,
    )
    # second moments about the core: sum (r + d)_i (r + d)_j over the voxel's points
    w2 = [
        a2[:, col] + a1[:, i] * d[:, j] + d[:, i] * a1[:, j] + c_ * d[:, i] * d[:, j]
        for col, (i, j) in enumerate(pairs)
    ]
    m2 = np.stack([np.bincount(group, weights=w, minlength=ncore) for w in w2], axis=1)
    safe = np.maximum(n_c, 1.0)
    mean = m1 / safe[:, None]
    cov = np.empty((len(cores), 3, 3))
    for col, (i, j) in enumerate(pairs):
        cov[:, i, j] = cov[:, j, i] = m2[:, col] / safe - mean[:, i] * mean[:, j]
    few = n_c < 3
    cov[few] = np.eye(3)
    vals, vecs = np.linalg.eigh(cov)
    normals = np.ascontiguousarray(vecs[:, :, 0])
    variation = vals[:, 0] / np.maximum(vals.sum(axis=1), 1e-30)
    variation[few] = np.inf
    thickness = np.sqrt(np.maximum(vals[:, 0], 0.0))
    thickness[few] = np.inf
    return normals, variation, thickness


def _ball_planes(
    index: _RadiusIndex, cores: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Plane normal and thickness of the indexed points within ``radius`` of each core.

    The exact-ball counterpart of :func:`_voxel_normals`, for few cores and a radius smaller
    than a voxel (the voxel moments blur a neighbourhood by a voxel's size). Returns the
    unoriented smallest-eigenvalue eigenvectors (C, 3) and ``sqrt(l0)`` (C,), the points'
    standard deviation across the plane (``inf`` with fewer than 6 points).
    """
    nc = len(cores)
    normals = np.zeros((nc, 3))
    thickness = np.full(nc, np.inf)
    if nc == 0 or index.empty:
        return normals, thickness
    for start in range(0, nc, _CHUNK):
        sl = slice(start, min(start + _CHUNK, nc))
        c = cores[sl]
        group, idx, _ = index.ball(c, radius)
        m = len(c)
        rel = index.pts[idx].astype(np.float64) - c[group]
        n = np.bincount(group, minlength=m).astype(np.float64)
        safe = np.maximum(n, 1.0)
        # (float: with no point in reach, np.bincount of empty weights returns integers)
        mean = np.stack([np.bincount(group, rel[:, i], m) for i in range(3)], axis=1)
        mean = mean / safe[:, None]
        dev = rel - mean[group]
        cov = np.empty((m, 3, 3))
        for i in range(3):
            for j in range(i, 3):
                cov[:, i, j] = cov[:, j, i] = np.bincount(group, dev[:, i] * dev[:, j], m) / safe
        few = n < 6
        cov[few] = np.eye(3)
        vals, vecs = np.linalg.eigh(cov)
        normals[sl] = vecs[:, :, 0]
        th = np.sqrt(np.maximum(vals[:, 0], 0.0))
        th[few] = np.inf
        thickness[sl] = th
    return normals, thickness


def normal_grid_corner(
    ref: np.ndarray, cores: np.ndarray, spacing: float, radius: float
) -> np.ndarray:
    """Corner of the voxel grid :func:`_voxel_normals` sums the reference's moments on."""
    return np.minimum(ref.min(axis=0), cores.min(axis=0)) - (radius + 2.0 * spacing)


def _normal_quantile(p: float) -> float:
    """Quantile of the standard normal distribution."""
    from scipy.special import ndtri

    return float(ndtri(p))


def _epoch_stats(epoch: _Epoch, cores, normals, radius, depth):
    """Clipped mean / std / count of the projections on the core normal of one epoch's points
    inside each core's cylinder (radius ``radius`` about the normal, ``|along| <= depth``),
    and the mean offset (C, 3) of those points across the normal from the cylinder's axis
    (how one-sided the cylinder's cover is: at the edge of a hole or of the scan).

    Offsets from a core are small, so they are computed in float32; only points whose own
    normal is within ``_MAX_ANGLE_DEG`` of the core's count. NaN / 0 without points.

    The values along the normal are clipped without sorting: (1) two passes of sigma clipping
    (values farther than ``max(3 std, 5 mm)`` from the mean dropped, the first pass's mean and
    std taken over all values); the standard deviation of the survivors is the spread returned
    (for the level of detection). (2) With ``_INNER_TRIM`` > 0, the innermost fraction is
    dropped (values below ``mean - z std``, ``z`` its normal quantile). (3) Values farther than
    ``max(3 std, 5 mm)`` from the survivors' mean are dropped; the mean and count of the last
    survivors are returned.
    """
    if epoch.empty or len(cores) == 0:
        nan = np.full(len(cores), np.nan)
        centre = np.full((len(cores), 3), np.nan)
        return nan, nan.copy(), np.zeros(len(cores), dtype=np.int32), centre
    from .kernels import cylinder_stats

    splits, idx, d2 = epoch.ball_csr(cores, float(np.hypot(radius, depth)))
    trim_z = _normal_quantile(1.0 - _INNER_TRIM) if _INNER_TRIM > 0 else 0.0
    return cylinder_stats(
        epoch.pts, epoch.normals, np.ascontiguousarray(cores, dtype=np.float32),
        np.ascontiguousarray(normals, dtype=np.float32), splits, idx, d2, float(radius),
        float(depth), _COS_MAX_ANGLE, _CLIP_K, _CLIP_FLOOR, trim_z,
    )
