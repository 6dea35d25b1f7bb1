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
   outward, away from the centreline. A core that straddles two surfaces at that radius
   (surface variation above 0.02) is fitted again on the reference points within half of it;
   where that plane is as thin as the planar cores around show the rock to be, the core lies
   on one surface next to an edge (a wall's foot, a chamber's rim) and is measured as a
   planar core, on its own cylinder (never widened: that would reach across the edge).
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
6. *Support*: a cylinder whose two epochs cover different parts of it (the centres of their
   points across the normal more than ``max(0.25, 4 chance deviations)`` radii apart: the edge
   of a hole, of the scan, of a shadow), that holds fewer than 5 points of an epoch, or that
   is still more than twice (and 10 mm) rougher than the median cylinder after widening (no
   single surface: the floor in one epoch, the conveyor's frame in the other) gets no value
   (NaN, flagged ``unsupported``): one epoch's one-sided mean takes in the relief between the
   two parts, and these were the tails of the field (values beyond 10 mm on unchanged rock).
7. *Scale from the data*: where the value of steps 4-5 exceeds three times the LoD95 of its
   own noise (a change no noise explains: flat rock reaches it in about 1e-8 of its cores;
   the registration's term, shared by a whole neighbourhood, is left out), or where the
   core's own cylinder does so by its own noise (a change narrower than the pooling, which
   pools it below that margin: one wrapped round an edge of a sparse scan), the core is
   read at the finest support instead, its own cylinder with the smoothing bias taken out in
   full (``beta = 1``), so a narrow or strong change reads at its full size while flat rock
   keeps the quiet, pooled value (in the spirit of multi-scale M3C2: the smallest support
   whose level of detection still separates the change from noise).
8. *Level of detection*:
   ``lod95 = 1.96 (se' + registration_sigma) + structure``, ``se = sqrt(s_r^2 / n_r + s_c^2 / n_c)``
   from the spread ``s`` and count ``n`` of each epoch's cylinder, ``se' = se (1 + 0.4 beta)``
   where sharpened (``se (1 + 0.4)`` where read finely), and the pooled combination's
   propagated error where pooled (neighbouring cylinders share points, which is counted);
   ``significant = |d| > lod95``. ``structure`` is 0 where a cylinder holds one smooth
   surface; where it is still rougher than ``max(1.5 x, 5 mm +)`` the typical one after
   widening (a pipe or cable a few centimetres in front of the rock, closer than the noise
   can separate; or both faces of a sharp bend), it is the spread beyond the typical one,
   ``sqrt(s^2 - t^2)`` (the larger epoch's): the mean of two surfaces reads the rock's
   motion times the rock's share, a bias that no number of points averages away (a 41 mm
   bulge behind a pipe 2-8 cm off the wall, at +-1.8 cm noise, read -10 mm against -30 mm
   with a LoD95 of 11 mm before this term). On a bare 20 m arch it is set on 7 % of the
   cores, at the wall-floor corners and the springing lines.

Depth: the core lies on the compared surface, so compared points are taken within
``min(max_depth, cylinder_radius)`` of it along the normal; reference points first within the
same depth, and within ``max_depth`` where the reference surface was not found there.
Adaptive scale: a core whose cylinder holds fewer than ``min_points`` points of either epoch
(but some of each), or, on a planar surface, is more than 1.5 times (and 5 mm) rougher than
the median cylinder (shadowed rock behind pipes, objects close to the rock), is measured
again with a cylinder twice as wide; a core that is only sparse first with one sqrt(2) times
as wide (twice the area), and twice as wide only if that still holds too few points: the
smallest of the three supports that holds enough. A core gets NaN only when no reference
point of its surface lies in its cylinder within ``max_depth`` (the surface moved further than
``max_depth``, the reference epoch did not see it, or the point is a stray return in
mid-air). Where fewer than three reference points lie within ``normal_radius``, the normal
falls back to the radial direction from the centreline. Corners: points whose core
straddles two surfaces (surface variation above 0.02) even on the smaller ball, or whose
edge core's cylinder is rough, sparse or unsupported, take the value of the nearest planar
core whose plane passes closest to them, if it passes within 0.1 m (the interpolation's own
test); otherwise they keep their own core's value, or none (the rock behind pipes, where the
closest plane was the floor's 0.65 m away, read a 41 mm bulge as +6 mm).

Everything is vectorised: cylinder neighbourhoods come from Open3D's fixed-radius hash grid
(``open3d.core.nns``, multi-threaded) on spatially sorted copies of the clouds as one flat
index array per chunk of cores, and every per-core statistic is a ``np.bincount`` over that
flat array. Steps 1-3 live in :mod:`.cylinders`, steps 4-5 and the interpolation in
:mod:`.core_pooling`; this module chains them.

References
----------
Lague, D., Brodu, N., Leroux, J. (2013). Accurate 3D comparison of complex topography with
terrestrial laser scanner. ISPRS J. Photogramm. 82, 10-26. doi:10.1016/j.isprsjprs.2013.04.009
Paper: Sensors 2024, 24, 2299, doi:10.3390/s24072299 (§3.3.1, Table 4, Table 5).

One idea at this length: the local-surface estimator's passes (normals, cylinders, adaptive
support, pooling, level of detection) over one set of core points.
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import check_points
from ..config import check_positive
from ..curve import Centerline
from ..errors import ConfigError, InvalidCloudError
from ..progress import ProgressCallback, notify
from .core_pooling import (
    _MAX_VARIATION,
    _POOL_SCALE,
    _SHARPEN_GAIN,
    _SPREAD_SIGMA,
    _assign_cores,
    _pool,
    _sharpen,
    _sharpening,
    _spread,
)
from .cylinders import (
    _CHUNK,
    _ball_planes,
    _Epoch,
    _epoch_stats,
    _voxel_normals,
    _voxel_order,
    normal_grid_corner,
    voxel_cores,
)

__all__ = [
    "RobustDeformation", "CylinderPass", "robust_deformation", "voxel_cores", "normal_grid_corner",
]

logger = logging.getLogger(__name__)

_Z95 = 1.959964
_FINE_GATE = 3.0  # a change beyond this many LoD95 of the quiet estimate is read finely (pass 5);
# flat rock reaches 3 LoD95 (5.9 standard errors) in about 1e-8 of its cores
_SUPPORT_SHIFT = 0.25  # of the cylinder radius: largest distance between the centres of the two
# epochs' points in a cylinder (about 0.05 r on full cover at 400 points/m^2; a hole's edge
# through the axis moves one centre by 0.42 r)
_SUPPORT_MIN_POINTS = 5  # fewer points of an epoch in the (widened) cylinder: no value
_NONPLANAR_FACTOR = 2.0  # a cylinder rougher than this many times the median one, and by
_NONPLANAR_EXCESS = 0.010  # at least this much (m), after widening holds no single surface
_EDGE_SCALE = 0.5  # of the normal radius: the ball that fits a core next to an edge again
_EDGE_NEIGHBOURS = 8  # planar cores whose thickness gives the noise next to an edge,
_EDGE_REACH = 1.0  # within this distance, m
_ROUGH_FACTOR = 1.5  # a cylinder this much rougher than the median one is measured wider,
_MID_WIDTH = float(np.sqrt(2.0))  # a sparse cylinder is widened this much first (twice the
# area), and to twice its radius only if that still holds too few points
_ROUGH_EXCESS = 0.005  # and by at least this much, m: with a low-noise scanner (2 mm) the
# curvature of a 30 mm sag alone makes its cylinders 1.5 times rougher, and widening them
# blurred the sag (its peak read 10 % low instead of 6 %); pipes and cables add centimetres


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
    unsupported : ndarray of bool, shape (N,)
        Points whose cylinder held reference points but no supported estimate (the two
        epochs cover different parts of it, too few points, no single surface): NaN, and
        unlike a point without any reference surface in reach, not a case for another
        estimator.
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
    unsupported: np.ndarray | None = None


_PASS_ARRAYS = ("cores", "inverse", "normal", "variation", "variation_wide", "edge_ids",
                "radius_used", "depth_used", "ref_order", "cmp_order", "ref_core", "cmp_core")


@dataclass
class CylinderPass:
    """The estimator's state after its cylinder statistics (passes 1 and 2), to resume from.

    A tile computes it once to learn its cylinder spreads (whose medians over the whole survey
    are the typical spreads every tile needs), saves it, and the tile's measuring pass resumes
    from it instead of fitting the same normals and gathering the same cylinders again.
    Positions are offsets from the estimator's local origin; ``ref_order`` / ``cmp_order``
    sort the surface points voxel by voxel, ``ref_core`` / ``cmp_core`` give each sorted point
    its nearest core (whose normal it carries in the cylinder gathers).
    """

    cores: np.ndarray
    inverse: np.ndarray
    normal: np.ndarray
    variation: np.ndarray
    variation_wide: np.ndarray
    edge_ids: np.ndarray
    out: dict[str, np.ndarray]
    radius_used: np.ndarray
    depth_used: np.ndarray
    n_deep: int
    ref_order: np.ndarray
    cmp_order: np.ndarray
    ref_core: np.ndarray
    cmp_core: np.ndarray
    _epochs: tuple[_Epoch, _Epoch] | None = field(default=None, repr=False, compare=False)

    @property
    def spread_ref(self) -> np.ndarray:
        """Spread of each core's reference cylinder, m (NaN without points)."""
        return self.out["sr"]

    @property
    def spread_cmp(self) -> np.ndarray:
        """Spread of each core's compared cylinder, m (NaN without points)."""
        return self.out["sc"]

    def save(self, path: str) -> None:
        """Write the state to ``path`` (an uncompressed ``.npz``)."""
        arrays = {k: getattr(self, k) for k in _PASS_ARRAYS}
        for k in ("inverse", "ref_order", "cmp_order", "ref_core", "cmp_core", "edge_ids"):
            a = arrays[k]
            if a.size == 0 or int(a.max()) < 2**31 - 1:
                arrays[k] = a.astype(np.int32)
        arrays.update({f"out_{k}": v for k, v in self.out.items()})
        with open(path, "wb") as f:
            np.savez(f, n_deep=np.int64(self.n_deep), **arrays)

    @classmethod
    def load(cls, path: str) -> CylinderPass:
        """Read a state written by :meth:`save`."""
        with np.load(path) as z:
            kw = {k: z[k] for k in _PASS_ARRAYS}
            for k in ("inverse", "ref_order", "cmp_order", "ref_core", "cmp_core", "edge_ids"):
                kw[k] = kw[k].astype(np.intp)
            out = {k[4:]: z[k] for k in z.files if k.startswith("out_")}
            return cls(out=out, n_deep=int(z["n_deep"]), **kw)

    def checked(self, n_ref: int, n_cmp: int, n_todo: int) -> CylinderPass:
        """This state, if it was computed for that many reference surface points, compared
        surface points and measured points; a ``ValueError`` otherwise."""
        if (len(self.ref_order), len(self.cmp_order), len(self.inverse)) != (n_ref, n_cmp, n_todo):
            raise ValueError(
                f"resume: the saved cylinder pass holds {len(self.ref_order)} reference, "
                f"{len(self.cmp_order)} compared and {len(self.inverse)} measured points, "
                f"the inputs {n_ref}, {n_cmp} and {n_todo}"
            )
        return self

    def epochs(
        self, ref_use: np.ndarray, cmp_use: np.ndarray, origin: np.ndarray, index_radius: float
    ) -> tuple[_Epoch, _Epoch]:
        """Both epochs' cylinder indexes (built again from the inputs on a resumed state)."""
        if self._epochs is None:
            n32 = self.normal.astype(np.float32)
            ref_sorted = (ref_use - origin)[self.ref_order]
            cmp_sorted = cmp_use[self.cmp_order] - origin
            self._epochs = (_Epoch(ref_sorted, n32[self.ref_core], index_radius),
                            _Epoch(cmp_sorted, n32[self.cmp_core], index_radius))
        return self._epochs


def _cylinder_pass(
    ref_use: np.ndarray, cmp_use: np.ndarray, todo: np.ndarray, line: Centerline,
    origin: np.ndarray, *, cmp_mask, measure, normal_radius, cylinder_radius, max_depth,
    core_spacing, core_anchor, normal_corner, workers, progress,
) -> CylinderPass:
    """Passes 1 and 2 of :func:`robust_deformation`: the cores, their outward normals and both
    epochs' cylinder statistics (``line`` is the centreline moved by ``-origin``)."""
    cores, inverse = voxel_cores(todo - origin, core_spacing, core_anchor)
    n_cores = len(cores)
    notify(progress, "robust deformation", 0.0)
    # spatially sorted copies make the neighbour gathers cache-friendly
    ref_use = ref_use - origin
    ref_order = _voxel_order(ref_use, core_spacing)
    ref_use = ref_use[ref_order]
    order = _voxel_order(cmp_use - origin, core_spacing)
    cmp_use = cmp_use[order] - origin
    if measure is None:
        cmp_core = (inverse if cmp_mask is None else inverse[cmp_mask])[order]

    # pass 1: outward plane normal of the reference around each core (voxel moments)
    if normal_corner is None:
        normal_corner = normal_grid_corner(ref_use, cores, core_spacing, normal_radius)
    normal, variation, thickness = _voxel_normals(
        ref_use, cores, core_spacing, normal_radius, np.asarray(normal_corner, dtype=np.float64)
    )
    index_radius = float(np.hypot(cylinder_radius, min(max_depth, cylinder_radius)))
    ref_epoch = _Epoch(ref_use, np.empty((0, 3), np.float32), index_radius)
    # pass 1b: cores next to an edge of the section, planar on a smaller ball
    variation_wide = variation.copy()
    edge_ids = _edge_planes(
        ref_epoch, cores, normal, variation, thickness, _EDGE_SCALE * normal_radius, workers
    )
    radial = _outward(line, cores, workers)
    flat = ~np.isfinite(variation)
    normal[flat] = radial[flat]
    normal[np.einsum("ij,ij->i", normal, radial) < 0] *= -1.0
    notify(progress, "robust deformation", 0.2)
    # every point carries the normal of its nearest core: cylinders keep only the points of
    # the same surface (a wall cylinder near a corner drops the roof's points)
    core_tree = cKDTree(cores)
    _, near = core_tree.query(ref_use, workers=workers)
    if measure is not None:
        _, cmp_core = core_tree.query(cmp_use, workers=workers)
    n32 = normal.astype(np.float32)
    ref_epoch.normals = np.ascontiguousarray(n32[near])
    cmp_epoch = _Epoch(cmp_use, n32[cmp_core], index_radius)

    # pass 2: cylinder statistics of both epochs; the core lies on the compared surface, so
    # the compared points are taken within a short depth, and the reference first within the
    # same depth, then within max_depth where its surface was not found there
    short = min(max_depth, cylinder_radius)
    out = {k: np.zeros(n_cores) for k in ("mr", "sr", "nr", "or", "mc", "sc", "nc", "oc")}
    out["or"], out["oc"] = np.zeros((n_cores, 3)), np.zeros((n_cores, 3))
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
                for s_, w in zip(stats[:4], ref_deep, strict=True):
                    s_[deep] = w
                depth_used[np.arange(sl.start, sl.stop)[deep]] = max_depth
        for key, s_ in zip(out, stats, strict=True):
            out[key][sl] = s_
        notify(progress, "robust deformation", 0.2 + 0.5 * sl.stop / n_cores)
    return CylinderPass(
        cores=cores, inverse=inverse, normal=normal, variation=variation,
        variation_wide=variation_wide, edge_ids=np.asarray(edge_ids, dtype=np.intp), out=out,
        radius_used=radius_used, depth_used=depth_used, n_deep=n_deep, ref_order=ref_order,
        cmp_order=order, ref_core=near, cmp_core=np.asarray(cmp_core, dtype=np.intp),
        _epochs=(ref_epoch, cmp_epoch),
    )


def _outward(centerline: Centerline, xyz: np.ndarray, workers: int) -> np.ndarray:
    """Unit vectors from the centreline towards each point, in the normal plane of the curve."""
    proj = centerline.project(xyz, workers=workers)
    _, lat, ver = centerline.frame_at(proj.chainage)
    out = proj.lateral[:, None] * lat + proj.vertical[:, None] * ver
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.maximum(norm, 1e-12)


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
    measure: np.ndarray | None = None,
    workers: int = -1,
    progress: ProgressCallback | None = None,
    origin: np.ndarray | None = None,
    core_anchor: np.ndarray | None = None,
    normal_corner: np.ndarray | None = None,
    typical_spread: tuple[float, float] | None = None,
    spreads_only: bool = False,
    resume: CylinderPass | None = None,
) -> RobustDeformation | CylinderPass:
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
        cylinder sqrt(2) times as wide, and if that still holds fewer, twice as wide.
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
    origin, core_anchor, normal_corner, typical_spread : optional
        The inputs that otherwise come from the whole clouds, for a piece of the clouds cut
        out along the chainage (:mod:`tunneldef.tiles`) to get the whole clouds' values:
        the local origin (default ``ref_xyz.mean(axis=0)``), the corner of the core voxel grid
        relative to it (default: the compared points' minimum corner), the corner of the
        normals' voxel grid (default :func:`normal_grid_corner`) and the typical cylinder
        spreads of the reference and compared epochs (default: their medians over all cores).
    spreads_only : bool
        Stop after the cylinder statistics and return them as a :class:`CylinderPass`
        (the spreads whose medians are ``typical_spread`` among them).
    resume : CylinderPass, optional
        The state a ``spreads_only`` call returned for the same clouds, masks, ``measure``
        and parameters (a tile's second pass, after the survey's typical spreads are known):
        passes 1 and 2 are not computed again. Its sizes are checked against the inputs'.

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
    normal_radius = check_positive("normal_radius", normal_radius)
    cylinder_radius = check_positive("cylinder_radius", cylinder_radius)
    max_depth = check_positive("max_depth", max_depth)
    core_spacing = check_positive("core_spacing", core_spacing)
    registration_sigma = check_positive("registration_sigma", registration_sigma, allow_zero=True)
    if int(min_points) < 1:
        raise ConfigError(f"min_points must be at least 1, got {min_points!r}")
    ref_use = ref if ref_mask is None else ref[_check_mask(ref_mask, len(ref), "ref_mask")]
    cmp_use = cmp_ if cmp_mask is None else cmp_[_check_mask(cmp_mask, len(cmp_), "cmp_mask")]
    if len(ref_use) < 3:
        raise InvalidCloudError("ref_mask keeps fewer than 3 reference points; pass a wider mask")

    origin = ref.mean(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
    shift = np.eye(4)
    shift[:3, 3] = -origin
    line = centerline.transformed(shift)
    n_all = len(cmp_)
    if measure is not None:
        measure = _check_mask(measure, n_all, "measure")
        if not measure.any():
            return _nothing_measured(n_all, cmp_.shape[1])
    todo = cmp_ if measure is None else cmp_[measure]
    index_radius = float(np.hypot(cylinder_radius, min(max_depth, cylinder_radius)))
    short = min(max_depth, cylinder_radius)
    if resume is None:
        state = _cylinder_pass(
            ref_use, cmp_use, todo, line, origin, cmp_mask=cmp_mask, measure=measure,
            normal_radius=normal_radius, cylinder_radius=cylinder_radius, max_depth=max_depth,
            core_spacing=core_spacing, core_anchor=core_anchor, normal_corner=normal_corner,
            workers=workers, progress=progress,
        )
    else:  # (the passes below change some of its per-core arrays: the caller's stay as given)
        state = dataclasses.replace(
            resume.checked(len(ref_use), len(cmp_use), len(todo)),
            variation=resume.variation.copy(), radius_used=resume.radius_used.copy(),
            out={k: v.copy() for k, v in resume.out.items()},
        )
    if spreads_only:
        return state
    cores, inverse, normal = state.cores, state.inverse, state.normal
    variation, variation_wide, edge_ids = state.variation, state.variation_wide, state.edge_ids
    out, radius_used, depth_used = state.out, state.radius_used, state.depth_used
    n_deep, n_cores = state.n_deep, len(state.cores)

    # pass 3, adaptive scale: cores with too few points of an epoch (but some of each: a core
    # without any is off the surface, or its surface has no counterpart) or a cylinder much
    # rougher than is typical (objects close to the shell, shadowed shell) are measured again
    # with a wider cylinder (see below)
    weak = (out["nr"] < min_points) | (out["nc"] < min_points)
    weak &= (out["nr"] > 0) & (out["nc"] > 0)
    sparse = weak.copy()  # and not rough (below)
    n_sparse = int(weak.sum())
    typicals = {}
    edge = np.zeros(n_cores, dtype=bool)
    edge[edge_ids] = True
    rough_any = np.zeros(n_cores, dtype=bool)
    for i, key in enumerate(("sr", "sc")):
        if typical_spread is not None:
            typical = float(typical_spread[i])
        else:
            typical = np.nanmedian(out[key]) if np.isfinite(out[key]).any() else np.inf
        typicals[key] = float(typical)
        with np.errstate(invalid="ignore"):
            rough = np.maximum(_ROUGH_FACTOR * typical, typical + _ROUGH_EXCESS)
            rough_cores = out[key] > rough
        weak |= rough_cores & (variation <= _MAX_VARIATION)
        sparse &= ~(rough_cores & (variation <= _MAX_VARIATION))
        rough_any |= rough_cores
    # a core next to an edge whose cylinder is rough did not find one plane there (its small
    # ball took in the other surface and tilted), and one whose cylinder is sparse would be
    # widened across the edge: it stays a corner, and its points take the value of a planar
    # core
    edge_back = edge & (rough_any | weak)
    variation[edge_back] = variation_wide[edge_back]
    weak &= ~edge_back
    wide_ids = np.flatnonzero(weak)
    if len(wide_ids):
        ref_epoch, cmp_epoch = state.epochs(ref_use, cmp_use, origin, index_radius)

    def widen(ids: np.ndarray, rw: float, done: float, span: float) -> None:
        """Both epochs' statistics of the cores ``ids`` again on cylinders of radius ``rw``
        (the reference at each core's own depth), in place."""
        for start in range(0, len(ids), _CHUNK):
            part = ids[start : start + _CHUNK]
            c, nrm, ref_d = cores[part], normal[part], depth_used[part]
            stats = [np.zeros((len(part), 3) if i % 4 == 3 else len(part)) for i in range(8)]
            for depth in np.unique(ref_d):
                m = ref_d == depth
                for s_, w in zip(
                    stats[:4], _epoch_stats(ref_epoch, c[m], nrm[m], rw, depth), strict=True
                ):
                    s_[m] = w
            cmp_w = _epoch_stats(cmp_epoch, c, nrm, rw, short)
            for s_, w in zip(stats[4:], cmp_w, strict=True):
                s_[:] = w
            for key, w in zip(out, stats, strict=True):
                out[key][part] = w
            radius_used[part] = rw
            notify(progress, "robust deformation",
                   done + span * min(start + _CHUNK, len(ids)) / len(ids))

    # a core that is only sparse (not rough) is widened by sqrt(2) first, twice the area,
    # and twice only if that still holds too few points: the smallest support that holds
    # enough (a 40 mm bulge 1.2 m wide in the shadow of pipes, 9-15 points of an epoch per
    # 0.2 m cylinder at 400 points/m^2, read 40 % low on 0.4 m cylinders)
    mid_ids = wide_ids[sparse[wide_ids]]
    widen(mid_ids, _MID_WIDTH * cylinder_radius, 0.7, 0.1)
    still = (out["nr"][mid_ids] < min_points) | (out["nc"][mid_ids] < min_points)
    n_mid = int(len(mid_ids) - still.sum())
    widen(np.union1d(wide_ids[~sparse[wide_ids]], mid_ids[still]), 2.0 * cylinder_radius,
          0.8, 0.15)
    n_fallback = len(wide_ids)

    d_mean = out["mc"] - out["mr"]
    n_r, n_c = out["nr"], out["nc"]
    # support: the two epochs must cover the same part of the cylinder; at the edge of a hole,
    # of the scan or of a shadow one of them is one-sided and the difference of the means
    # takes in the relief between the two parts (the tails of the field): no value there
    with np.errstate(invalid="ignore", divide="ignore"):
        # on full cover the centres differ by chance by about r / 2 sqrt(1/n_r + 1/n_c) per
        # axis: the limit stays 4 such deviations away (1 in 3,000 cores on flat rock)
        chance = 0.5 * np.sqrt(1.0 / out["nr"] + 1.0 / out["nc"])
        shift_limit = np.maximum(_SUPPORT_SHIFT, 4.0 * chance) * radius_used
        one_sided = np.linalg.norm(out["or"] - out["oc"], axis=1) > shift_limit
    unsupported = one_sided | (np.minimum(n_r, n_c) < _SUPPORT_MIN_POINTS)
    # a cylinder still far rougher than the typical one at twice the width does not hold
    # one surface (the floor seen in one epoch, the conveyor's frame in the other): no value
    for key, typical in typicals.items():
        with np.errstate(invalid="ignore"):
            limit = np.maximum(_NONPLANAR_FACTOR * typical, typical + _NONPLANAR_EXCESS)
            unsupported |= out[key] > limit
    d_mean[unsupported] = np.nan
    n_unsupported = int(unsupported.sum())
    # likewise a core next to an edge whose cylinder holds no value: its points take the
    # value of a planar core, as every corner's do
    edge_nan = edge & ~edge_back & unsupported
    variation[edge_nan] = variation_wide[edge_nan]
    with np.errstate(invalid="ignore", divide="ignore"):
        se = np.sqrt(out["sr"] ** 2 / n_r + out["sc"] ** 2 / n_c)
    n_edge = int((edge & ~edge_back & ~edge_nan).sum())
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
    # pass 5, the scale from the data: where the quiet estimate above (pooled on sparse scans)
    # separates a change from noise by a wide margin, the change is real and is read at the
    # finest support instead, the core's own cylinder with its smoothing bias taken out in
    # full: a narrow or strong change reads at its full size, flat rock keeps the quiet value
    with np.errstate(invalid="ignore"):
        # the estimate's own noise only: the registration's error is shared by a whole
        # neighbourhood, so it widens the LoD95 but says nothing about the support (with it,
        # the wider LoD of a registration with a larger misfit kept a change at the coarser,
        # smoothed support, and the cores that still cleared the gate were the ones noise
        # had pushed up)
        lod_quiet = _Z95 * se_used
        fine = np.isfinite(d_mean) & (np.abs(d_mean) > _FINE_GATE * lod_quiet)
        # or where the core's own cylinder does so by the same margin of its own noise: a
        # change narrower than the pooling (one wrapped round an edge of a sparse scan,
        # whose neighbours on the surface are unchanged rock) is pooled away below the gate
        fine |= np.isfinite(d_plain) & (np.abs(d_plain) > _FINE_GATE * _Z95 * se)
    fine &= variation <= _MAX_VARIATION
    n_fine = int(fine.sum())
    if fine.any() and sharpen:
        d_fine = _sharpen(
            cores, normal, variation, d_plain, fine.astype(float), spacing=core_spacing,
            workers=workers,
        )
        d_mean = d_mean.copy()
        d_mean[fine] = d_fine[fine]
        se_used[fine] = se[fine] * (1.0 + _SHARPEN_GAIN)
    # pass 6, cylinders that hold more than one surface: a pipe or cable a few centimetres in
    # front of the rock lies within the cylinder, and with the scanner's noise the two cannot
    # be told apart; their mean is the rock's motion times the rock's share, not noise that
    # averages away, so the level of detection takes in the spread beyond one surface's
    structure = _structure(out, typicals)
    with np.errstate(invalid="ignore"):
        lod = _Z95 * (se_used + registration_sigma) + structure
    lod[~np.isfinite(d_mean)] = np.nan
    point_core = _assign_cores(
        todo - origin,
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
        todo - origin,
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
    normal_p = normal[inverse]
    unsupported_p = unsupported[inverse]
    n_ref_p, n_cmp_p = n_r.astype(np.int32)[inverse], n_c.astype(np.int32)[inverse]
    s_ref_p, s_cmp_p = out["sr"][inverse], out["sc"][inverse]
    if measure is not None:  # back to every compared point (NaN / 0 / -1 where not measured)
        d, lod_p, s_ref_p, s_cmp_p = (
            _scatter(a, measure, np.nan) for a in (d, lod_p, s_ref_p, s_cmp_p)
        )
        n_ref_p, n_cmp_p = (_scatter(a, measure, 0) for a in (n_ref_p, n_cmp_p))
        normal_p, inverse = _scatter(normal_p, measure, np.nan), _scatter(inverse, measure, -1)
        unsupported_p = _scatter(unsupported_p, measure, False)
    with np.errstate(invalid="ignore"):
        significant = np.abs(d) > lod_p
    return RobustDeformation(
        deformation=d,
        lod95=lod_p,
        significant=significant,
        normal=normal_p,
        n_ref=n_ref_p,
        n_cmp=n_cmp_p,
        sigma_ref=s_ref_p,
        sigma_cmp=s_cmp_p,
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
            "typical_spread": (typicals["sr"], typicals["sc"]),
            "wide_cylinder_cores": n_fallback,
            "mid_cylinder_cores": n_mid,
            "sparse_cores": n_sparse,
            "deep_cylinder_cores": n_deep,
            "nan_cores": n_nan,
            "edge_cores": n_edge,
            "unsupported_cores": n_unsupported,
            "sharpened_cores": int((beta > 0).sum()),
            "sharpen_strength_mean": float(beta[beta > 0].mean()) if beta.any() else 0.0,
            "pooled_cores": n_pooled,
            "fine_cores": n_fine,
            "structured_cores": int(((structure > 0) & np.isfinite(d_mean)).sum()),
        },
        unsupported=unsupported_p,
    )


def _structure(out: dict[str, np.ndarray], typicals: dict[str, float]) -> np.ndarray:
    """Spread of each core's cylinder beyond one surface's, where it holds more than one, m.

    A cylinder still rougher than ``max(1.5 x, 5 mm +)`` the typical one after widening (the
    gate that widened it) holds something besides the rock: the spread beyond the typical,
    ``sqrt(s^2 - t^2)``, is about half the separation of two surfaces. Where the epochs see
    the two in other shares, the cylinder's mean moves by up to that separation; where the
    rock moves and the object in front of it does not, by the motion times the object's
    share. Neither averages down with ``sqrt(n)``, so this allowance is added to the level
    of detection as it is. It is an allowance, not a proof bound: it covered the bulge
    behind a pipe of sweep case 16000002 (error 18 mm, LoD95 38 mm), and a much larger
    motion behind a pipe can exceed it. The larger of the two epochs' (0 where both are as
    smooth as one surface).
    """
    structure = np.zeros(len(next(iter(out.values()))))
    for key, typical in typicals.items():
        s = out[key]
        with np.errstate(invalid="ignore"):
            rough = s > max(_ROUGH_FACTOR * typical, typical + _ROUGH_EXCESS)
            extra = np.sqrt(np.maximum(s * s - typical * typical, 0.0))
        structure = np.maximum(structure, np.where(rough, extra, 0.0))
    return structure


def _edge_planes(
    ref_index: _Epoch,
    cores: np.ndarray,
    normal: np.ndarray,
    variation: np.ndarray,
    thickness: np.ndarray,
    radius: float,
    workers: int,
) -> np.ndarray:
    """Fit the cores that straddle two surfaces at ``normal_radius`` again on a smaller ball.

    A core within a normal radius of an edge of the section (wall meeting floor or roof) is
    not planar at that radius (surface variation above ``_MAX_VARIATION``), and its points
    would take the value of a planar core farther from the edge: a change along the edge
    itself (a bulge low on a wall that wraps round onto the floor) was read from cores
    0.3 m or more away, at a fraction of its size. Such a core is fitted again on the
    reference points within ``radius``; where that plane is as thin as the planar cores
    around it (its thickness, the points' spread across the plane, within
    ``_ROUGH_FACTOR`` times and ``_ROUGH_EXCESS`` of their median), the core lies on one
    surface at that scale: it takes the new normal and counts as planar from here on
    (``variation`` is set to ``_MAX_VARIATION``). Cores on the edge itself stay as they
    were. ``normal`` and ``variation`` are changed in place; returns the indices of the cores
    that were.
    """
    corner = np.flatnonzero(np.isfinite(variation) & (variation > _MAX_VARIATION))
    planar = np.flatnonzero(variation <= _MAX_VARIATION)
    if corner.size == 0 or planar.size == 0:
        return corner[:0]
    # the noise the planar cores around show (their spread across the plane)
    k = min(_EDGE_NEIGHBOURS, planar.size)
    dist, j = cKDTree(cores[planar]).query(
        cores[corner], k=k, distance_upper_bound=_EDGE_REACH, workers=workers
    )
    dist, j = dist.reshape(len(corner), k), j.reshape(len(corner), k)
    found = np.isfinite(dist)
    near_thick = np.where(found, thickness[planar[np.where(found, j, 0)]], np.nan)
    with warnings.catch_warnings():  # a core without planar cores in reach: NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        noise = np.nanmedian(near_thick, axis=1)
    ok = np.isfinite(noise)
    corner, noise = corner[ok], noise[ok]
    if corner.size == 0:
        return corner
    n_fine, t_fine = _ball_planes(ref_index, cores[corner], radius)
    limit = np.maximum(_ROUGH_FACTOR * noise, noise + _ROUGH_EXCESS)
    keep = t_fine <= limit
    ids = corner[keep]
    normal[ids] = n_fine[keep]
    variation[ids] = _MAX_VARIATION
    return ids


def _scatter(values: np.ndarray, where: np.ndarray, fill: float) -> np.ndarray:
    """``values`` (one row per True of ``where``) placed into an array of ``where``'s length,
    ``fill`` elsewhere."""
    out = np.full((where.size, *values.shape[1:]), fill, dtype=values.dtype)
    out[where] = values
    return out


def _nothing_measured(n: int, dim: int) -> RobustDeformation:
    """The result when no compared point is to be measured: NaN everywhere."""
    nan = np.full(n, np.nan)
    empty = np.empty((0, 3))
    return RobustDeformation(
        deformation=nan,
        lod95=nan.copy(),
        significant=np.zeros(n, dtype=bool),
        normal=np.full((n, dim), np.nan),
        n_ref=np.zeros(n, dtype=np.int32),
        n_cmp=np.zeros(n, dtype=np.int32),
        sigma_ref=nan.copy(),
        sigma_cmp=nan.copy(),
        core=np.full(n, -1, dtype=np.intp),
        core_xyz=empty,
        core_deformation=np.empty(0),
        core_lod95=np.empty(0),
        core_normal=empty,
        core_radius=np.empty(0),
        core_ref_depth=np.empty(0),
        meta={"method": "robust", "cores": 0},
        unsupported=np.zeros(n, dtype=bool),
    )


def _check_mask(mask: np.ndarray, n: int, name: str) -> np.ndarray:
    m = np.asarray(mask)
    if m.shape != (n,) or m.dtype != bool:
        raise InvalidCloudError(
            f"{name} must be a boolean array of shape ({n},), got {m.dtype} {m.shape}"
        )
    return m
