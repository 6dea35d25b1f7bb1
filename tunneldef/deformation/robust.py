"""Robust signed deformation: local reference surfaces, cylinder means and a level of detection.

The paper's per-point KNN-centroid distance (§3.3.1) measures the scanner's noise as much as the
tunnel's motion: with k = 3 the counterpart is a noisy point and the distance is unsigned, so on
shell that did not move it reports about the noise amplitude (the paper's Table 4 mean, 26.7 mm).
This module implements the multiscale model-to-model idea instead (M3C2, Lague et al. 2013):

1. *Core points*: the compared cloud is cut into cubic voxels of ``core_spacing``; each voxel's
   centroid is a core point. Every compared point gets a Gaussian-weighted mean (sigma 0.6 core
   spacings) of the cores around it on its own surface (its voxel's core included), which
   interpolates the smooth field between the overlapping cylinders.
2. *Normal*: the reference points around a core (voxel moments of the reference within
   ``normal_radius``) are fitted by a plane (PCA, smallest eigenvector); the normal is oriented
   outward, away from the centreline.
3. *Cylinder means*: reference and compared points inside a cylinder of radius
   ``cylinder_radius`` along that normal are projected on the normal. Only points of the same
   surface count (their nearest core's normal within 35 degrees of this one). Each epoch's
   location is a robust mean: three passes of 3-sigma clipping (stray points, and objects a
   few centimetres in front of the rock - cables, pipe backs - which all lie inward of it).
   The deformation is the compared location minus the reference location: negative means the
   surface moved into the tunnel (the paper's sign convention).
4. *Bias correction*: averaging over a cylinder and then between cores reads a curved field
   low (a 1 m wide sag by about 6 % at its peak). Each planar core's value is sharpened,
   ``d + beta (d - mean of its neighbours on the same surface)`` (an unsharp mask), which
   removes that bias at ``beta = 1`` but amplifies the core's noise by ``1 + 0.4 beta``; so
   ``beta`` is as large as keeps the core's standard error ``se`` within 2 mm: 1 at the
   handheld scanner's density, 0 on sparse scans (``sharpen=False`` turns it off).
5. *Pooling on sparse scans*: a planar core whose ``se`` exceeds 1.5 mm (fully from 2 mm) takes
   instead ``2 S1 - S2``, two Gaussian means of the plain core values on its surface whose
   total smoothing variances are ``T^2`` and ``2 T^2`` (``S1``: sigma one cylinder radius).
   The combination cancels their smoothing bias to second order (Richardson extrapolation)
   while averaging over about 0.3 m: on sparse scans it trades resolution for noise, which
   is what lets a 15 mm sag through (``pool=False`` turns it off).
6. *Level of detection*:
   ``lod95 = 1.96 (se' + registration_sigma)``, ``se = sqrt(s_r^2 / n_r + s_c^2 / n_c)``
   from the spread ``s`` and count ``n`` of each epoch's cylinder, ``se' = se (1 + 0.4 beta)``
   where sharpened, and the pooled combination's propagated error where pooled (neighbouring
   cylinders share points, which is counted); ``significant = |d| > lod95``.

Depth: the core lies on the compared surface, so compared points are taken within
``min(max_depth, cylinder_radius)`` of it along the normal; reference points first within the
same depth, and within ``max_depth`` where the reference surface was not found there.
Adaptive scale: a core whose cylinder holds fewer than ``min_points`` points of either epoch
(but some of each), or, on a planar surface, is more than 1.5 times (and 5 mm) rougher than
the median cylinder (shadowed rock behind pipes, objects close to the rock), is measured
again with a cylinder twice as wide. A core gets NaN only when no reference point of its
surface lies in its cylinder within ``max_depth`` (the surface moved further than
``max_depth``, the reference epoch did not see it, or the point is a stray return in
mid-air). Where fewer than three reference points lie within ``normal_radius``, the normal
falls back to the radial direction from the centreline. Corners: points whose core
straddles two surfaces (surface variation above 0.02) take the value of the nearest planar
core whose plane passes closest to them.

Everything is vectorised: cylinder neighbourhoods come from Open3D's fixed-radius hash grid
(``open3d.core.nns``, multi-threaded) on spatially sorted copies of the clouds as one flat
index array per chunk of cores, and every per-core statistic is a ``np.bincount`` over that
flat array.

References
----------
Lague, D., Brodu, N., Leroux, J. (2013). Accurate 3D comparison of complex topography with
terrestrial laser scanner. ISPRS J. Photogramm. 82, 10-26. doi:10.1016/j.isprsjprs.2013.04.009
Paper: Sensors 2024, 24, 2299, doi:10.3390/s24072299 (§3.3.1, Table 4, Table 5).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..centerline.curve import Centerline
from ..cloud import check_points
from ..errors import ConfigError, InvalidCloudError
from ..progress import ProgressCallback, report

__all__ = ["RobustDeformation", "robust_deformation", "voxel_cores"]

logger = logging.getLogger(__name__)

_Z95 = 1.959964
_CHUNK = 40_000  # cores per neighbourhood query (bounds the flat neighbour arrays)
_ROUGH_FACTOR = 1.5  # a cylinder this much rougher than the median one is measured wider,
_ROUGH_EXCESS = 0.005  # and by at least this much, m: with a low-noise scanner (2 mm) the
# curvature of a 30 mm sag alone makes its cylinders 1.5 times rougher, and widening them
# blurred the sag (its peak read 10 % low instead of 6 %); pipes and cables add centimetres
# innermost fraction of each cylinder that may be dropped (objects lie inward of the rock); off:
# on the synthetic benchmark 0.2 cut false alarms from 0.3 % to 0.08 % but recall at 10 mm in a
# 15 mm sag from 0.92 to 0.87, and the adaptive width already handles objects near the rock
_INNER_TRIM = 0.0
_MAX_VARIATION = 0.02  # a plane with 2 cm noise at a 0.3 m radius: ~0.005; a corner: > 0.05
_K_SPREAD = 6  # cores interpolated at each point
# bias correction (an unsharp mask of the core field, see _sharpen): its full strength takes
# a noise-free 30 mm synthetic sag (1 m wide) from 6.4 % low at its peak to within 1 %; it
# amplifies a core's noise by about 1 + 0.4 beta (measured), so it is applied only as far as
# the core's standard error stays within 2 mm: fully at the handheld scanner's density
# (2,600 points/m^2, about 1.2 mm), not at all on sparse scans (400 points/m^2, about 3 mm)
_SHARPEN = 1.0
_SHARPEN_GAIN = 0.4
_SHARPEN_SE = 0.002
# pooling on sparse scans (see _pool): a core whose plain standard error exceeds _POOL_SE is
# blended, fully from _POOL_SE + _POOL_RAMP, into a bias-corrected Gaussian mean of the cores
# around it on its surface. On the synthetic pairs (+-3 cm noise, 15 mm sag, perfect
# registration, 8 seeds at 400 points/m^2) it takes the noise floor from 2.0 to 1.7 mm and
# recall at 10 mm from 0.80 to 0.89 (lowest seed 0.61 to 0.76); at 1,000 points/m^2 the
# lowest recall of 3 seeds from 0.86 to 0.90; at 2,600 points/m^2 it changes nothing that
# shows. Starting at 2 mm (where sharpening stops) left 1,000 points/m^2 between the two.
_POOL_SE = 0.0015
_POOL_RAMP = 0.0005
_POOL_SCALE = 1.0  # sigma of the finer pooled mean, in cylinder radii; 0.75 kept a 1.2 m wide
# bulge 3 mm deeper (30.8 against 27.9 mm of a true 35.8 mm) but the noise floor only to 1.95 mm
_SPREAD_SIGMA = 0.6  # of the core spacing: Gaussian weights of the interpolation
_SPREAD_PLANE = 0.1  # a core's plane must pass this close to a point to be interpolated, m
_K_ASSIGN = 8  # candidate planar cores for a point of a corner core
_MAX_ANGLE_DEG = 35.0  # points of the same surface as a core: normals within this angle
_COS_MAX_ANGLE = float(np.cos(np.radians(_MAX_ANGLE_DEG)))


@dataclass(frozen=True)
class RobustDeformation:
    """Per-point result of :func:`robust_deformation` (arrays have one row per compared point).

    Attributes
    ----------
    deformation : ndarray, shape (N,)
        Signed distance along the outward normal from the reference surface to the compared
        surface, metres; negative = moved into the tunnel. NaN where no reference surface lies
        within ``max_depth``.
    lod95 : ndarray, shape (N,)
        Level of detection at 95 % confidence, metres (NaN where ``deformation`` is NaN).
    significant : ndarray of bool, shape (N,)
        ``|deformation| > lod95``.
    normal : ndarray, shape (N, 3)
        Outward unit normal used at each point (its core's).
    n_ref, n_cmp : ndarray of int32, shape (N,)
        Points of each epoch kept in the cylinder.
    sigma_ref, sigma_cmp : ndarray, shape (N,)
        Spread (standard deviation along the normal) of each epoch in the cylinder, metres.
    core : ndarray of intp, shape (N,)
        Index of each point's own core (its voxel's, or on a corner the planar core whose
        plane fits it best): ``normal``, ``n_ref``, ``n_cmp``, ``sigma_ref`` and ``sigma_cmp``
        are that core's.
    core_xyz : ndarray, shape (C, 3)
        Core points, metres, in the input frame.
    core_deformation, core_lod95 : ndarray, shape (C,)
        Deformation and level of detection measured at each core, metres (the per-point
        values interpolate these).
    core_normal : ndarray, shape (C, 3)
        Outward unit normal of each core.
    core_radius : ndarray, shape (C,)
        Cylinder radius each core was measured with, metres.
    core_ref_depth : ndarray, shape (C,)
        Half-length along the normal within which its reference points were taken, metres.
    meta : dict
        Parameters used and counts (cores, fallbacks, NaN cores).
    """

    deformation: np.ndarray
    lod95: np.ndarray
    significant: np.ndarray
    normal: np.ndarray
    n_ref: np.ndarray
    n_cmp: np.ndarray
    sigma_ref: np.ndarray
    sigma_cmp: np.ndarray
    core: np.ndarray
    core_xyz: np.ndarray
    core_deformation: np.ndarray
    core_lod95: np.ndarray
    core_normal: np.ndarray
    core_radius: np.ndarray
    core_ref_depth: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)


def voxel_cores(xyz: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Core points: centroids of the points in each occupied cubic voxel.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Coordinates, metres (a local origin keeps the voxel indices small).
    spacing : float
        Voxel edge, metres.

    Returns
    -------
    cores : ndarray, shape (C, 3)
        Centroid of each occupied voxel, ordered by voxel index (spatially coherent).
    inverse : ndarray of intp, shape (N,)
        Core of each point.
    """
    ijk = np.floor((xyz - xyz.min(axis=0)) / spacing).astype(np.int64)
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
        if self._nns is None or len(centres) == 0:
            return np.empty(0, np.intp), np.empty(0, np.intp), np.empty(0, np.float32)
        q = self._o3d.core.Tensor(np.ascontiguousarray(centres, dtype=np.float32))
        idx, d2, splits = self._nns.fixed_radius_search(q, float(radius), sort=False)
        counts = np.diff(splits.numpy())
        group = np.repeat(np.arange(len(centres), dtype=np.intp), counts)
        return group, idx.numpy().astype(np.intp, copy=False), d2.numpy()


class _Epoch(_RadiusIndex):
    """One epoch's points for the cylinder gathers, with the normal of each point's core
    (cylinders keep only the points of their own surface)."""

    def __init__(self, pts: np.ndarray, pt_normals: np.ndarray, radius: float) -> None:
        super().__init__(pts, radius)
        self.normals = np.ascontiguousarray(pt_normals, dtype=np.float32)


def _voxel_normals(
    ref: np.ndarray, cores: np.ndarray, spacing: float, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Plane normal and surface variation of the reference around each core.

    The reference points are summarised per voxel of edge ``spacing`` (count, first and second
    moments about the voxel centre, one ``np.bincount`` each); a core's neighbourhood is every
    voxel whose centre lies within ``radius + spacing / 2`` of it, and its covariance is the
    sum of those voxels' moments moved to the core. Returns the smallest-eigenvalue
    eigenvectors (C, 3) (unoriented) and ``l0 / (l0 + l1 + l2)`` (C,) (about 0 on a plane, up
    to 1/3 on a corner; ``inf`` with fewer than 3 points).
    """
    lo = np.minimum(ref.min(axis=0), cores.min(axis=0)) - (radius + 2.0 * spacing)
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
    return normals, variation


def _group_moments(group, values, keep, ngroups):
    """Count, mean and standard deviation of the kept values of each group."""
    w = keep.astype(np.float64)
    n = np.bincount(group, weights=w, minlength=ngroups)
    mean = np.bincount(group, weights=w * values, minlength=ngroups) / np.maximum(n, 1.0)
    dev = values - mean[group]
    var = np.bincount(group, weights=w * dev * dev, minlength=ngroups) / np.maximum(n - 1.0, 1.0)
    return n, mean, np.sqrt(var), dev


def _clipped_stats(
    group: np.ndarray,
    values: np.ndarray,
    ngroups: int,
    *,
    k: float = 3.0,
    floor: float = 0.005,
    trim: float = _INNER_TRIM,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust location, spread and count of ``values`` (positions along the outward normal)
    per group, without sorting.

    (1) Two passes of sigma clipping: values farther than ``max(k * std, floor)`` from the
    mean are dropped, the first pass's mean and std taken over all values; the standard
    deviation of the survivors is the spread returned (for the level of detection). (2) The
    innermost ``trim`` fraction is dropped: values below ``mean - z * std``, ``z`` the
    ``trim`` quantile of a normal distribution (cables, pipe backs, the other surface near a
    corner all lie inward of the shell; the rock behind it is clean). (3) Values farther than
    ``k`` standard deviations from the survivors' mean are dropped. Returns the mean of the last
    survivors, the spread and their count; groups without values get NaN and 0.
    """
    keep = np.ones(values.shape[0], dtype=bool)
    _, _, std, dev = _group_moments(group, values, keep, ngroups)
    keep = np.abs(dev) <= np.maximum(k * std[group], floor)
    _, mean, spread, dev = _group_moments(group, values, keep, ngroups)
    keep = np.abs(dev) <= np.maximum(k * spread[group], floor)
    if trim > 0:
        keep &= dev >= -_normal_quantile(1.0 - trim) * spread[group]
    _, _, std, dev = _group_moments(group, values, keep, ngroups)
    keep &= np.abs(dev) <= np.maximum(k * std[group], floor)
    n, mean, _, _ = _group_moments(group, values, keep, ngroups)
    empty = n < 1
    mean[empty] = np.nan
    spread[empty] = np.nan
    return mean, spread, n.astype(np.int32)


def _normal_quantile(p: float) -> float:
    """Quantile of the standard normal distribution."""
    from scipy.special import ndtri

    return float(ndtri(p))


def _outward(centerline: Centerline, xyz: np.ndarray, workers: int) -> np.ndarray:
    """Unit vectors from the centreline towards each point, in the normal plane of the curve."""
    proj = centerline.project(xyz, workers=workers)
    _, lat, ver = centerline.frame_at(proj.chainage)
    out = proj.lateral[:, None] * lat + proj.vertical[:, None] * ver
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.maximum(norm, 1e-12)


def _check_positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    value = float(value)
    ok = value >= 0.0 if allow_zero else value > 0.0
    if not np.isfinite(value) or not ok:
        sign = "non-negative" if allow_zero else "positive"
        raise ConfigError(f"{name} must be a {sign} number of metres, got {value!r}")
    return value


def robust_deformation(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    centerline: Centerline,
    *,
    normal_radius: float = 0.3,
    cylinder_radius: float = 0.2,
    max_depth: float = 0.3,
    core_spacing: float = 0.2,
    min_points: int = 20,
    registration_sigma: float = 0.0,
    sharpen: bool = True,
    pool: bool = True,
    ref_mask: np.ndarray | None = None,
    cmp_mask: np.ndarray | None = None,
    workers: int = -1,
    progress: ProgressCallback | None = None,
) -> RobustDeformation:
    """Signed deformation of every compared point with a per-point level of detection.

    Parameters
    ----------
    ref_xyz : ndarray, shape (M, 3)
        Reference epoch, metres.
    cmp_xyz : ndarray, shape (N, 3)
        Compared epoch, already registered into the reference frame, metres.
    centerline : Centerline
        Centreline in the reference frame; orients normals outward.
    normal_radius : float
        Radius of the reference neighbourhood fitted by a plane for the normal, metres.
    cylinder_radius : float
        Radius of the cylinder along the normal whose points are averaged, metres.
    max_depth : float
        Half-length of the cylinder along the normal, metres: the largest measurable motion.
    core_spacing : float
        Edge of the voxels whose centroids are the core points, metres.
    min_points : int
        Fewer points of either epoch in a cylinder and the core is measured again with a
        cylinder twice as wide.
    registration_sigma : float
        Standard uncertainty of the registration, metres, added to the level of detection.
    sharpen : bool
        Take out the smoothing bias of the cylinders and the interpolation where the
        cylinders are dense enough (see the module docstring); False keeps the plain means.
    pool : bool
        Where the cylinders are too sparse for that (standard error above 1.5 mm, fully from
        2 mm), blend each core into a bias-corrected mean of the cores around it on its
        surface (see the module docstring); False keeps the plain means.
    ref_mask, cmp_mask : ndarray of bool, optional
        Points allowed to contribute to the local surfaces (e.g. the tunnel shell from
        :func:`tunneldef.deformation.shell.classify_shell`); all by default. Every compared
        point gets a value whatever its mask.
    workers : int
        Threads for SciPy's KD-tree queries (-1: all cores); the cylinder and normal
        neighbourhoods come from Open3D's radius search, which uses every core.
    progress : callable, optional
        ``progress(stage, fraction)``.

    Returns
    -------
    RobustDeformation
        Per-point deformation, lod95, significance, normals and cylinder statistics.

    Raises
    ------
    InvalidCloudError
        If a cloud is not N x 3 finite coordinates, or a mask has the wrong shape or leaves too
        few reference points.
    ConfigError
        If a radius, depth or spacing is not a positive number.

    Notes
    -----
    See the module docstring for the steps (M3C2, Lague et al. 2013, on voxel core points).
    """
    ref = check_points(ref_xyz, name="reference cloud", min_points=3)
    cmp_ = check_points(cmp_xyz, name="compared cloud")
    normal_radius = _check_positive("normal_radius", normal_radius)
    cylinder_radius = _check_positive("cylinder_radius", cylinder_radius)
    max_depth = _check_positive("max_depth", max_depth)
    core_spacing = _check_positive("core_spacing", core_spacing)
    registration_sigma = _check_positive("registration_sigma", registration_sigma, allow_zero=True)
    if int(min_points) < 1:
        raise ConfigError(f"min_points must be at least 1, got {min_points!r}")
    ref_use = ref if ref_mask is None else ref[_check_mask(ref_mask, len(ref), "ref_mask")]
    cmp_use = cmp_ if cmp_mask is None else cmp_[_check_mask(cmp_mask, len(cmp_), "cmp_mask")]
    if len(ref_use) < 3:
        raise InvalidCloudError("ref_mask keeps fewer than 3 reference points; pass a wider mask")

    origin = ref.mean(axis=0)
    shift = np.eye(4)
    shift[:3, 3] = -origin
    line = centerline.transformed(shift)
    cores, inverse = voxel_cores(cmp_ - origin, core_spacing)
    n_cores = len(cores)
    report(progress, "robust deformation", 0.0)
    # spatially sorted copies make the neighbour gathers cache-friendly
    ref_use = ref_use - origin
    ref_use = ref_use[_voxel_order(ref_use, core_spacing)]
    cmp_core = inverse if cmp_mask is None else inverse[cmp_mask]
    order = _voxel_order(cmp_use - origin, core_spacing)
    cmp_use, cmp_core = cmp_use[order] - origin, cmp_core[order]

    # pass 1: outward plane normal of the reference around each core (voxel moments)
    normal, variation = _voxel_normals(ref_use, cores, core_spacing, normal_radius)
    radial = _outward(line, cores, workers)
    flat = ~np.isfinite(variation)
    normal[flat] = radial[flat]
    normal[np.einsum("ij,ij->i", normal, radial) < 0] *= -1.0
    report(progress, "robust deformation", 0.2)
    # every point carries the normal of its nearest core: cylinders keep only the points of
    # the same surface (a wall cylinder near a corner drops the roof's points)
    _, near = cKDTree(cores).query(ref_use, workers=workers)
    n32 = normal.astype(np.float32)
    index_radius = float(np.hypot(cylinder_radius, min(max_depth, cylinder_radius)))
    ref_epoch = _Epoch(ref_use, n32[near], index_radius)
    cmp_epoch = _Epoch(cmp_use, n32[cmp_core], index_radius)
    del near

    # pass 2: cylinder statistics of both epochs; the core lies on the compared surface, so
    # the compared points are taken within a short depth, and the reference first within the
    # same depth, then within max_depth where its surface was not found there
    short = min(max_depth, cylinder_radius)
    out = {k: np.zeros(n_cores) for k in ("mr", "sr", "nr", "mc", "sc", "nc")}
    radius_used = np.full(n_cores, cylinder_radius)
    depth_used = np.full(n_cores, short)
    n_deep = 0
    for start in range(0, n_cores, _CHUNK):
        sl = slice(start, min(start + _CHUNK, n_cores))
        c, nrm = cores[sl], normal[sl]
        stats = [
            *_epoch_stats(ref_epoch, c, nrm, cylinder_radius, short),
            *_epoch_stats(cmp_epoch, c, nrm, cylinder_radius, short),
        ]
        if max_depth > short:
            # no reference point, or its mean close to the end of the short cylinder
            deep = (stats[2] == 0) | ~(np.abs(stats[0]) < short - 3.0 * np.maximum(stats[1], 0.01))
            if deep.any():
                n_deep += int(deep.sum())
                ref_deep = _epoch_stats(ref_epoch, c[deep], nrm[deep], cylinder_radius, max_depth)
                for s_, w in zip(stats[:3], ref_deep, strict=True):
                    s_[deep] = w
                depth_used[np.arange(sl.start, sl.stop)[deep]] = max_depth
        for key, s_ in zip(out, stats, strict=True):
            out[key][sl] = s_
        report(progress, "robust deformation", 0.2 + 0.5 * sl.stop / n_cores)

    # pass 3, adaptive scale: cores with too few points of an epoch (but some of each: a core
    # without any is off the surface, or its surface has no counterpart) or a cylinder much
    # rougher than is typical (objects close to the shell, shadowed shell) are measured again
    # with a cylinder twice as wide
    weak = (out["nr"] < min_points) | (out["nc"] < min_points)
    weak &= (out["nr"] > 0) & (out["nc"] > 0)
    n_sparse = int(weak.sum())
    for key in ("sr", "sc"):
        typical = np.nanmedian(out[key]) if np.isfinite(out[key]).any() else np.inf
        with np.errstate(invalid="ignore"):
            rough = np.maximum(_ROUGH_FACTOR * typical, typical + _ROUGH_EXCESS)
            weak |= (out[key] > rough) & (variation <= _MAX_VARIATION)
    wide_ids = np.flatnonzero(weak)
    for start in range(0, len(wide_ids), _CHUNK):
        ids = wide_ids[start : start + _CHUNK]
        c, nrm, rw = cores[ids], normal[ids], 2.0 * cylinder_radius
        ref_d = depth_used[ids]
        stats = [np.zeros(len(ids)) for _ in range(6)]
        for depth in np.unique(ref_d):
            m = ref_d == depth
            for s_, w in zip(
                stats[:3], _epoch_stats(ref_epoch, c[m], nrm[m], rw, depth), strict=True
            ):
                s_[m] = w
        cmp_w = _epoch_stats(cmp_epoch, c, nrm, rw, short)
        for s_, w in zip(stats[3:], cmp_w, strict=True):
            s_[:] = w
        for key, w in zip(out, stats, strict=True):
            out[key][ids] = w
        radius_used[ids] = rw
        report(
            progress,
            "robust deformation",
            0.7 + 0.25 * min(start + _CHUNK, len(wide_ids)) / len(wide_ids),
        )
    n_fallback = len(wide_ids)

    d_mean = out["mc"] - out["mr"]
    n_r, n_c = out["nr"], out["nc"]
    with np.errstate(invalid="ignore", divide="ignore"):
        se = np.sqrt(out["sr"] ** 2 / n_r + out["sc"] ** 2 / n_c)
    # pass 4: take the smoothing bias out where the cylinders are dense enough to afford it,
    # and where they are too sparse for that, pool each core with its neighbours instead
    d_plain = d_mean
    beta = _sharpening(se) if sharpen else np.zeros(n_cores)
    if beta.any():
        d_mean = _sharpen(
            cores, normal, variation, d_mean, beta, spacing=core_spacing, workers=workers
        )
    se_used = se * (1.0 + _SHARPEN_GAIN * beta)
    n_pooled = 0
    if pool:
        ids, lam, d_pool, se_pool = _pool(
            cores,
            normal,
            variation,
            d_plain,
            se,
            sigma=_POOL_SCALE * cylinder_radius,
            base=0.25 * cylinder_radius**2 + (_SPREAD_SIGMA * core_spacing) ** 2,
            overlap=max(1.0, np.pi * cylinder_radius**2 / core_spacing**2),
        )
        d_mean = d_mean.copy()
        d_mean[ids] = (1.0 - lam) * d_mean[ids] + lam * d_pool
        se_used[ids] = (1.0 - lam) * se_used[ids] + lam * se_pool
        n_pooled = int(ids.size)
    with np.errstate(invalid="ignore"):
        lod = _Z95 * (se_used + registration_sigma)
    lod[~np.isfinite(d_mean)] = np.nan
    point_core = _assign_cores(
        cmp_ - origin,
        inverse,
        cores,
        normal,
        variation,
        np.isfinite(d_mean),
        reach=normal_radius + 2.0 * core_spacing,
        workers=workers,
    )
    n_nan = int((~np.isfinite(d_mean)).sum())
    if n_nan:
        logger.info(
            "%d of %d cores have no reference surface within %.2f m", n_nan, n_cores, max_depth
        )
    d, lod_p = _spread(
        cmp_ - origin,
        point_core,
        cores,
        normal,
        variation,
        d_mean,
        lod,
        spacing=core_spacing,
        workers=workers,
    )
    inverse = point_core
    with np.errstate(invalid="ignore"):
        significant = np.abs(d) > lod_p
    return RobustDeformation(
        deformation=d,
        lod95=lod_p,
        significant=significant,
        normal=normal[inverse],
        n_ref=n_r.astype(np.int32)[inverse],
        n_cmp=n_c.astype(np.int32)[inverse],
        sigma_ref=out["sr"][inverse],
        sigma_cmp=out["sc"][inverse],
        core=inverse,
        core_xyz=cores + origin,
        core_deformation=d_mean,
        core_lod95=lod,
        core_normal=normal,
        core_radius=radius_used,
        core_ref_depth=depth_used,
        meta={
            "method": "robust",
            "normal_radius": normal_radius,
            "cylinder_radius": cylinder_radius,
            "max_depth": max_depth,
            "core_spacing": core_spacing,
            "min_points": int(min_points),
            "registration_sigma": registration_sigma,
            "cores": n_cores,
            "wide_cylinder_cores": n_fallback,
            "sparse_cores": n_sparse,
            "deep_cylinder_cores": n_deep,
            "nan_cores": n_nan,
            "sharpened_cores": int((beta > 0).sum()),
            "sharpen_strength_mean": float(beta[beta > 0].mean()) if beta.any() else 0.0,
            "pooled_cores": n_pooled,
        },
    )


def _epoch_stats(epoch: _Epoch, cores, normals, radius, depth):
    """Clipped mean / std / count of the projections on the core normal of one epoch's points
    inside each core's cylinder (radius ``radius`` about the normal, ``|along| <= depth``).

    Offsets from a core are small, so they are computed in float32; only points whose own
    normal is within ``_MAX_ANGLE_DEG`` of the core's count. NaN / 0 without points.
    """
    if epoch.empty or len(cores) == 0:
        nan = np.full(len(cores), np.nan)
        return nan, nan.copy(), np.zeros(len(cores), dtype=np.int32)
    group, idx, d2 = epoch.ball(cores, float(np.hypot(radius, depth)))
    n32 = normals.astype(np.float32)
    cn = n32[group]
    a = np.einsum("ij,ij->i", epoch.pts[idx] - cores.astype(np.float32)[group], cn)
    inside = (np.abs(a) <= depth) & (d2 - a * a <= radius * radius)
    group, idx, a, cn = group[inside], idx[inside], a[inside], cn[inside]
    same = np.einsum("ij,ij->i", epoch.normals[idx], cn) >= _COS_MAX_ANGLE
    return _clipped_stats(group[same], a[same].astype(np.float64), len(cores))


def _assign_cores(
    pts: np.ndarray,
    inverse: np.ndarray,
    cores: np.ndarray,
    normals: np.ndarray,
    variation: np.ndarray,
    valid: np.ndarray,
    *,
    reach: float,
    workers: int,
) -> np.ndarray:
    """Core whose value each compared point takes.

    A point keeps its voxel's core unless that core straddles two surfaces (surface variation
    above ``_MAX_VARIATION``, e.g. a voxel on a wall-roof corner, whose tilted cylinder mixes
    both): then it takes, among the ``_K_ASSIGN`` nearest planar cores within ``reach``, the one
    whose plane passes closest to it.
    """
    planar = valid & (variation <= _MAX_VARIATION)
    corner = np.isfinite(variation) & (variation > _MAX_VARIATION)  # not: no reference near
    point_core = inverse.copy()
    move = np.flatnonzero(corner[inverse])
    if move.size == 0 or not planar.any():
        return point_core
    ids = np.flatnonzero(planar)
    k = min(_K_ASSIGN, ids.size)
    dist, j = cKDTree(cores[ids]).query(pts[move], k=k, distance_upper_bound=reach, workers=workers)
    dist, j = dist.reshape(len(move), k), j.reshape(len(move), k)
    found = np.isfinite(dist)
    jj = ids[np.where(found, j, 0)]
    res = np.abs(np.einsum("ijk,ijk->ij", pts[move][:, None, :] - cores[jj], normals[jj]))
    res[~found] = np.inf
    best = np.argmin(res, axis=1)
    ok = found.any(axis=1)
    point_core[move[ok]] = jj[ok, best[ok]]
    return point_core


def _surface_weights(
    q: np.ndarray,
    own: np.ndarray,
    cores: np.ndarray,
    normals: np.ndarray,
    ids: np.ndarray,
    *,
    spacing: float,
    k: int,
    workers: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian weights (sigma ``_SPREAD_SIGMA`` core spacings) of the cores ``ids`` among the
    ``k`` nearest within ``1.5 * spacing`` of each position ``q`` that lie on the surface of
    its own core ``own``: normals within ``_MAX_ANGLE_DEG``, plane within ``_SPREAD_PLANE`` of
    the position; the own core itself is left out.

    Returns the core indices ``jj`` (Q, k) and their weights ``w`` (Q, k), 0 where unused.
    """
    k = min(k, ids.size)
    dist, j = cKDTree(cores[ids]).query(
        q, k=k, distance_upper_bound=1.5 * spacing, workers=workers
    )
    dist, j = dist.reshape(len(q), k), j.reshape(len(q), k)
    found = np.isfinite(dist)
    jj = ids[np.where(found, j, 0)]
    # float32 products: normals are unit vectors and the plane offsets are taken about each
    # core (``q.n - c.n``, float64), so single precision loses nothing that matters
    n32 = normals.astype(np.float32)
    nj = n32[jj]
    same = np.einsum("ijk,ik->ij", nj, n32[own]) >= _COS_MAX_ANGLE
    cn = np.einsum("ij,ij->i", cores, normals)
    plane = np.abs(np.einsum("ijk,ik->ij", nj, q) - cn[jj])
    del nj
    use = found & same & (plane <= _SPREAD_PLANE) & (jj != own[:, None])
    inv2s2 = -0.5 / (_SPREAD_SIGMA * spacing) ** 2
    w = np.where(use, np.exp(inv2s2 * np.where(found, dist, 0.0) ** 2), 0.0)
    return jj, w


def _spread(
    pts: np.ndarray,
    point_core: np.ndarray,
    cores: np.ndarray,
    normals: np.ndarray,
    variation: np.ndarray,
    d_core: np.ndarray,
    lod_core: np.ndarray,
    *,
    spacing: float,
    workers: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Deformation and level of detection of every point from the cores around it.

    Each point takes a Gaussian-weighted mean (sigma ``_SPREAD_SIGMA`` spacings) of the valid
    planar cores among its ``_K_SPREAD`` nearest within ``1.5 * spacing`` that lie on its own
    core's surface (see :func:`_surface_weights`), its own core always included: neighbouring
    cylinders overlap, so this interpolates the smooth field between cores rather than copying
    one core's value over its voxel, and averages some of the noise. The level of detection
    is the same weighted mean of the cores' levels (conservative: it ignores the averaging).
    """
    d = d_core[point_core].copy()
    lod = lod_core[point_core].copy()
    valid = np.isfinite(d_core) & (variation <= _MAX_VARIATION)
    ids = np.flatnonzero(valid)
    todo = np.flatnonzero(np.isfinite(d))
    if ids.size < 2 or todo.size == 0:
        return d, lod
    p = pts[todo]
    own = point_core[todo]
    jj, w = _surface_weights(
        p, own, cores, normals, ids, spacing=spacing, k=_K_SPREAD, workers=workers
    )
    use = w > 0
    off = p - cores[own]
    w_own = np.exp(-0.5 * np.einsum("ij,ij->i", off, off) / (_SPREAD_SIGMA * spacing) ** 2)
    total = w.sum(axis=1) + w_own
    d[todo] = (np.einsum("ij,ij->i", w, np.where(use, d_core[jj], 0.0)) + w_own * d[todo]) / total
    lod[todo] = (
        np.einsum("ij,ij->i", w, np.where(use, lod_core[jj], 0.0)) + w_own * lod[todo]
    ) / total
    return d, lod


def _sharpening(se: np.ndarray) -> np.ndarray:
    """Strength ``beta`` of the bias correction of each core from its standard error ``se``:
    as much of ``_SHARPEN`` as keeps the amplified error ``se * (1 + _SHARPEN_GAIN * beta)``
    within ``_SHARPEN_SE``; 0 where the cylinders are too sparse (or ``se`` is NaN)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        beta = np.clip((_SHARPEN_SE / se - 1.0) / _SHARPEN_GAIN, 0.0, _SHARPEN)
    beta[~np.isfinite(beta)] = 0.0
    return beta


def _sharpen(
    cores: np.ndarray,
    normals: np.ndarray,
    variation: np.ndarray,
    d_core: np.ndarray,
    beta: np.ndarray,
    *,
    spacing: float,
    workers: int,
) -> np.ndarray:
    """Core deformations with the smoothing bias taken out (an unsharp mask).

    The cylinder mean and the interpolation between cores both average the field over a
    patch, which reads a curved field low by about half its Laplacian times the patch's second
    moment: 6 % at the peak of a 1 m wide sag. The difference between a core and the
    Gaussian mean of its planar neighbours on the same surface (:func:`_surface_weights`)
    is proportional to that Laplacian, so ``d + beta * (d - neighbours)`` removes the bias at
    ``beta`` near 1 (calibrated on a noise-free synthetic sag), at the price of amplifying
    the core's noise by about ``1 + _SHARPEN_GAIN * beta``.
    """
    out = d_core.copy()
    valid = np.isfinite(d_core) & (variation <= _MAX_VARIATION)
    ids = np.flatnonzero(valid & (beta > 0))
    nb_ids = np.flatnonzero(valid)
    if ids.size == 0 or nb_ids.size < 2:
        return out
    jj, w = _surface_weights(
        cores[ids], ids, cores, normals, nb_ids, spacing=spacing, k=_K_SPREAD + 1,
        workers=workers,
    )
    total = w.sum(axis=1)
    ok = total > 0
    nb = np.einsum("ij,ij->i", w, np.where(w > 0, d_core[jj], 0.0))[ok] / total[ok]
    i = ids[ok]
    out[i] = d_core[i] + beta[i] * (d_core[i] - nb)
    return out


def _pool(
    cores: np.ndarray,
    normals: np.ndarray,
    variation: np.ndarray,
    d_core: np.ndarray,
    se: np.ndarray,
    *,
    sigma: float,
    base: float,
    overlap: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Deformations of the sparse cores pooled with their neighbours, bias-corrected.

    Each valid planar core whose standard error ``se`` exceeds ``_POOL_SE`` gets
    ``2 S1 - S2``, where ``S1`` and ``S2`` are Gaussian-weighted means of the valid planar
    cores on its surface (normals within ``_MAX_ANGLE_DEG``, planes within ``_SPREAD_PLANE``
    of it; itself included) with sigmas ``sigma`` and ``sqrt(2 sigma^2 + base)``. ``base``
    is the variance of the smoothing the cylinder mean and the interpolation already apply,
    so the two smoothings' total variances are ``T^2`` and ``2 T^2`` and the combination
    cancels their bias to second order (Richardson extrapolation; about 3 % of a 1 m wide
    sag's depth is left). Its standard error is ``sqrt(overlap * sum_j c_j^2 se_j^2)`` over
    the combination's weights ``c_j``, where ``overlap`` (the cores each cylinder covers)
    accounts for neighbouring cylinders sharing points.

    Returns the pooled cores' indices, their blend weights ``lam`` (0 at ``_POOL_SE``, 1 from
    ``_POOL_SE + _POOL_RAMP``), pooled deformations and standard errors.
    """
    valid = np.isfinite(d_core) & np.isfinite(se) & (variation <= _MAX_VARIATION)
    with np.errstate(invalid="ignore"):
        lam = np.clip((se - _POOL_SE) / _POOL_RAMP, 0.0, 1.0)
    todo = np.flatnonzero(valid & (lam > 0))
    ids = np.flatnonzero(valid)
    d_out, se_out = np.empty(todo.size), np.empty(todo.size)
    if todo.size == 0 or ids.size < 2:
        return todo[:0], lam[todo[:0]], d_out[:0], se_out[:0]
    s2 = float(np.sqrt(2.0 * sigma**2 + base))
    reach = 3.0 * s2
    index = _RadiusIndex(cores[ids], reach)
    cn = np.einsum("ij,ij->i", cores, normals)
    for start in range(0, todo.size, _CHUNK):
        sl = slice(start, min(start + _CHUNK, todo.size))
        t = todo[sl]
        g, j, d2 = index.ball(cores[t], reach)
        j = ids[j]
        own = t[g]
        same = np.einsum("ij,ij->i", normals[j], normals[own]) >= _COS_MAX_ANGLE
        near = np.abs(np.einsum("ij,ij->i", normals[j], cores[own]) - cn[j]) <= _SPREAD_PLANE
        keep = same & near
        g, j, d2 = g[keep], j[keep], d2[keep].astype(np.float64)
        w1 = np.exp(-0.5 * d2 / sigma**2)
        w2 = np.exp(-0.5 * d2 / s2**2)
        w1 /= np.bincount(g, w1, len(t))[g]
        w2 /= np.bincount(g, w2, len(t))[g]
        c = 2.0 * w1 - w2
        d_out[sl] = np.bincount(g, c * d_core[j], len(t))
        se_p = np.sqrt(overlap * np.bincount(g, c**2 * se[j] ** 2, len(t)))
        se_out[sl] = np.minimum(se_p, se[t])
    return todo, lam[todo], d_out, se_out


def _check_mask(mask: np.ndarray, n: int, name: str) -> np.ndarray:
    m = np.asarray(mask)
    if m.shape != (n,) or m.dtype != bool:
        raise InvalidCloudError(
            f"{name} must be a boolean array of shape ({n},), got {m.dtype} {m.shape}"
        )
    return m
