"""An independent look at a finished registration: does it fit as well as the scans allow, and
do two different measures of the position along the axis agree?

Neither figure is produced by the registration itself, so neither can be talked into agreeing
with it:

* **fit against the scans' own noise.** The compared points' robust point-to-plane distance to
  the reference surface is set against the same distance measured within each epoch (one half
  of its points against the planes of the other half). A correct registration leaves the
  cross-epoch figure at the level of the noisier epoch; a tilt or a lateral offset adds to it.
  Deformation touches a minority of the shell and the robust scale (1.4826 MAD) ignores it.
* **the along-axis position twice.** From the final pose, the section-correlation
  (:func:`.axial.coarse_shift`, to a 0.25 m bin, with the spread of equally good matches) and
  the point-to-plane slide (:func:`.axial.fine_shift`, with its standard deviation) must both
  find no further shift, and agree with each other within their uncertainties. A slide along a
  featureless prism passes the first test and fails this one (or shows as undetermined).
* **convergence.** The same slide started 2 cm before and after the registered position must
  end where it ends from the position itself: on noisy normals the slide sticks where it
  starts, and then reads no remaining slide wherever the registration stopped.

A drift network (:func:`verify_network`) has no one axis to slide along: its cross-cuts fix
the position in plan where a single drift cannot. There the fit is judged as above, and the
position by a three-degree-of-freedom point-to-plane translation from the registered pose and
from 2 cm beside it along x and y: it must find nothing left to move, and end in one place
from every start. A drift the curves' shapes placed (a bend, a flat stretch going on up a ramp)
is judged by the same translation and by a rigid fit, rotations included, started 2 cm before
and after the registered position along the drift (:func:`rigid_convergence`): on a ramp a
translation alone reads a slide cancelled by a small pitch as no slide at all.

One idea at this length: the independent check of a finished registration, of a drift and of
a network.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..curve import Centerline
from ..engine import thread_map
from ..spatial import random_subset, unique_rows
from ..transforms import apply_transform
from .axial import (
    AxialShift,
    _mismatch,
    coarse_shift,
    concurrent_slides,
    neighbour_centroids,
    noise_kernel,
    rigid_fit,
    section_image,
    translation_fit,
)
from .views import axial_correction, normals

__all__ = [
    "RegistrationCheck", "verify_registration", "NetworkCheck", "verify_network",
    "coherent_misfit", "patch_medians", "PatchMedians", "rigid_convergence",
]

_SAMPLE = 25_000  # least points per epoch and half the plane fits use
_IMAGE_SAMPLE = 200_000  # least points per epoch of the section images (as the registration)
_REACH = 0.1  # m: correspondences farther apart are not the same surface
_NORMAL_RADIUS = 0.15  # m, as the registration's normals
_PROBE = 0.02  # m: the slide is started this far either side of the registered position
_PATCH = 2.0  # m: patches whose mean misfit is a registration error (coherent_misfit)
_Q75 = 1.1503  # 75th percentile of |N(0, 1)|
_EXCESS_Z = 2.0  # standard errors of cross^2 - own^2 that are the sigmas' own noise


@dataclass(frozen=True)
class RegistrationCheck:
    """Independent figures of a registration (metres).

    Attributes
    ----------
    cross_residual : float
        Robust sigma (1.4826 MAD) of the compared points' distance to the reference planes:
        the median over the full 2 m patches of each patch's sigma about its own median.
    ref_residual, cmp_residual : float
        The same within each epoch (half of its points against the planes of the other half):
        what the scans themselves show.
    residual_ratio : float
        ``cross_residual / max(ref_residual, cmp_residual)``; about 1 when registered.
    excess : float
        ``sqrt(max(cross^2 - max(ref, cmp)^2, 0))``: the misfit the scans' noise does not
        explain (registration error); each sigma is the median of the 2 m patches' own
        (:func:`_typical_spread`), so a change on a minority of the patches does not count.
    coarse_shift, coarse_spread : float
        Remaining along-axis shift by section correlation (0.25 m bins) and the spread of
        equally good matches (large: the overlap has no feature along the axis).
    fine_shift, fine_sigma : float
        Remaining along-axis shift by point-to-plane sliding, and its standard deviation.
    centreline_difference : float
        95th percentile distance between the registered compared centreline and the reference
        one over the common stretch (1 m inside its ends), divided by sqrt(2): about the p95
        error of either curve when both are equally good, plus what the registration leaves;
        NaN without a compared centreline.
    pose_mismatch : float
        How much worse the section images match at the registered position than at the best
        shift within the search, in units of the mismatch's own noise (``(score(0) / best -
        1) / (3 sqrt(2 / n))``, the tolerance of :func:`.axial.coarse_shift`): <= 1 when the
        registered position is among the equally good ones. Unlike ``coarse_shift`` it stays
        meaningful on a stretch with several equally good matches.
    probe_shifts : tuple of float
        Where the point-to-plane slide (0.15 m normals) ends when started ``_PROBE`` (2 cm)
        before and after the registered position along the axis, metres from that position.
    axial_spread : float
        The spread (max - min) of where the slide ends from the registered position and from
        the two probes: 0 when the surfaces truly fix the position (the slide is drawn back
        to one place from either side; a few mm with a chamber), up to 4 cm when the slide
        sticks where it starts (relief drowned in noise, a featureless drift: the registered
        position is then only where the registration happened to stop). NaN when the slide
        found nothing to hold on to.
    narrow_shifts : tuple of float
        ``fine_shift`` and ``wide_shift`` again with the kernel narrowing to 5 cm whatever
        the noise (NaN where the slide found nothing).
    wide_shift, scale_disagreement : float
        The point-to-plane slide again with normals over 0.3 m instead of 0.15 m, and
        ``|fine_shift - wide_shift|`` in units of their combined sigma: <= 3 when the surfaces
        that fix the position are real at both scales (NaN if either found nothing).
    axial_disagreement : float
        ``|coarse_shift - fine_shift|`` expressed in units of their combined uncertainty
        (half a bin and ``fine_sigma`` added in quadrature); <= 3 when they agree; NaN when
        the point-to-plane slide found nothing to hold on to or the section correlation has
        equally good matches more than 1 m apart (then ``pose_mismatch`` judges).
    coherent : float
        The misfit shared by neighbouring points (:func:`coherent_misfit`); with
        ``excess_beyond_noise`` it makes :attr:`registration_sigma`.
    excess_beyond_noise : float
        The excess taken patch by patch and beyond its own sampling error
        (:func:`_paired_excess`): the registration's part of the LoD95 with ``coherent``.
        NaN when too few patches pair up (then ``excess`` stands in).
    """

    cross_residual: float
    ref_residual: float
    cmp_residual: float
    residual_ratio: float
    excess: float
    coarse_shift: float
    coarse_spread: float
    fine_shift: float
    fine_sigma: float
    axial_disagreement: float
    centreline_difference: float = np.nan
    pose_mismatch: float = np.nan
    wide_shift: float = np.nan
    narrow_shifts: tuple[float, float] = (np.nan, np.nan)
    scale_disagreement: float = np.nan
    probe_shifts: tuple[float, float] = (np.nan, np.nan)
    axial_spread: float = np.nan
    coherent: float = np.nan
    excess_beyond_noise: float = np.nan

    @property
    def registration_sigma(self) -> float:
        """The registration's error along the normals passed to the level of detection."""
        return _registration_sigma(_beyond(self), self.coherent)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (non-finite values become None)."""
        def num(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {k: ([num(x) for x in v] if isinstance(v, tuple) else num(v))
                for k, v in self.__dict__.items()}


def _plane_sigma(src: np.ndarray, dst: np.ndarray, dst_n: np.ndarray, tree: cKDTree) -> float:
    d, j = tree.query(src, distance_upper_bound=_REACH, workers=-1)
    ok = np.isfinite(d)
    if ok.sum() < 100:
        return np.inf
    r = np.einsum("ij,ij->i", src[ok] - dst[j[ok]], dst_n[j[ok]])
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


@dataclass(frozen=True)
class PatchMedians:
    """Signed point-to-plane misfits summed up by patch (:func:`patch_medians`).

    Attributes
    ----------
    cell : ndarray, shape (N,)
        Each source point's patch (-1: no reference surface within reach, or trimmed).
    median, count : ndarray, shape (P,)
        Each patch's median misfit (m; the sign follows the patch's main normal) and points.
    full : ndarray of bool, shape (P,)
        Patches a surface crosses in full.
    sigma : float
        Robust sigma of the point misfits (m).
    spread : ndarray, shape (P,)
        Each patch's robust sigma (1.4826 MAD) about its own median (m; NaN when empty).
    key : ndarray of int64, shape (P, 3)
        Each patch's cell index (``floor(xyz / cell)``): the same patch in another cloud.
    """

    cell: np.ndarray
    median: np.ndarray
    count: np.ndarray
    full: np.ndarray
    sigma: float
    spread: np.ndarray
    key: np.ndarray

    @property
    def noise(self) -> np.ndarray:
        """Each patch median's own standard deviation: sqrt((pi / 2) sigma^2 / n)."""
        return np.sqrt(0.5 * np.pi * self.sigma**2 / np.maximum(self.count, 1))


def patch_medians(
    src: np.ndarray, dst: np.ndarray, dst_n: np.ndarray, tree: cKDTree, *,
    cell: float = _PATCH, min_points: int = 30,
) -> PatchMedians | None:
    """The signed point-to-plane misfit of ``src`` against the planes of ``dst`` (normals
    ``dst_n``, ``tree`` over ``dst``) by ``cell``-metre patch: normals turned to their patch's
    main normal, 3-sigma trimmed, summed up by the median. A patch is full when it holds at
    least ``min_points`` and half the 90th percentile of the patches' counts. None when fewer
    than 100 points find the surface."""
    d, j = tree.query(src, distance_upper_bound=_REACH, workers=-1)
    ok = np.isfinite(d)
    if ok.sum() < 100:
        return None
    p, nrm = src[ok], dst_n[j[ok]]
    key, cells, _ = unique_rows(np.floor(p / cell).astype(np.int64))
    # normals carry no sign: turn each to agree with its patch's main normal (the structure
    # tensor's first eigenvector), so that one offset reads with one sign across the patch
    outer = (nrm[:, :, None] * nrm[:, None, :]).reshape(-1, 9)
    tensor = np.stack([np.bincount(cells, weights=outer[:, k]) for k in range(9)], axis=1)
    main = np.linalg.eigh(tensor.reshape(-1, 3, 3))[1][:, :, -1]
    nrm = nrm * np.where(np.einsum("ij,ij->i", nrm, main[cells]) < 0, -1.0, 1.0)[:, None]
    r = np.einsum("ij,ij->i", p - dst[j[ok]], nrm)
    med = float(np.median(r))
    sigma = 1.4826 * float(np.median(np.abs(r - med)))
    keep = np.abs(r - med) <= 3.0 * sigma
    rk, ck = r[keep], cells[keep]
    n = np.bincount(ck, minlength=len(main))
    # patches a surface crosses in full: one cut by an edge or a corner holds few points, and
    # there points matched to the other surface's plane (within reach of the corner) are the
    # many and bias its median by centimetres
    full = n >= max(min_points, 0.5 * float(np.percentile(n[n > 0], 90)))
    # each patch's median (points matched across a corner to the other surface's plane read
    # centimetres off, on one side only, and would bias a mean)
    order = np.lexsort((rk, ck))
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    lo = np.minimum(start + (np.maximum(n, 1) - 1) // 2, max(len(rk) - 1, 0))
    hi = np.minimum(start + n // 2, max(len(rk) - 1, 0))
    median = np.where(n > 0, 0.5 * (rk[order[lo]] + rk[order[hi]]), np.nan)
    dev = np.abs(rk - np.nan_to_num(median)[ck])
    order = np.lexsort((dev, ck))
    spread = np.where(n > 0, 1.4826 * 0.5 * (dev[order[lo]] + dev[order[hi]]), np.nan)
    point_cell = np.full(len(src), -1, dtype=np.int64)
    idx = np.flatnonzero(ok)
    point_cell[idx[keep]] = ck
    return PatchMedians(point_cell, median, n, full, sigma, spread, key)


def coherent_misfit(
    src: np.ndarray, dst: np.ndarray, dst_n: np.ndarray, tree: cKDTree, *,
    cell: float = _PATCH, min_points: int = 30,
) -> float:
    """The part of the misfit of ``src`` against the planes of ``dst`` that is shared by
    neighbouring points: a registration error (a tilt, SLAM drift left after the correction),
    as a standard deviation along the normals, metres.

    The signed point-to-plane distances (normals turned to their patch's main normal,
    3-sigma trimmed) are summed up by their median in ``cell``-metre patches of at least
    ``min_points`` and half the 90th percentile of the patches' counts (a surface crosses
    them in full). Each median holds its own noise, (pi / 2) sigma^2 / n, and the coherent
    part c is the one at which the medians divided by sqrt(c^2 + noise) spread as a
    standard normal at their 75th percentile (real deformation touches a minority of the
    patches). The scans' noise averages out of a patch, a registration error does not: at
    +-1.5 cm noise a 5 mm misfit over 20 m hides inside the point-to-plane sigma (24.4
    against 24.0 mm) but not here. NaN when fewer
    than 10 patches are full enough.
    """
    return _coherent(patch_medians(src, dst, dst_n, tree, cell=cell, min_points=min_points))


def _coherent(patches: PatchMedians | None) -> float:
    """The coherent part of the patches' medians (:func:`coherent_misfit`), NaN when fewer
    than 10 patches are full."""
    if patches is None or patches.full.sum() < 10:
        return np.nan
    mid, m, sigma = patches.median[patches.full], patches.count[patches.full], patches.sigma
    # each patch's median has its own noise ((pi / 2) sigma^2 / n); the coherent part c is
    # where the medians, each divided by sqrt(c^2 + its noise), spread as a standard normal
    # at their 75th percentile (1.15): real deformation may take a quarter of the patches, a
    # drift residue left on a third of them still shows
    se2 = 0.5 * np.pi * sigma**2 / m

    def q75(c: float) -> float:
        return float(np.percentile(np.abs(mid) / np.sqrt(c**2 + se2), 75))

    if q75(0.0) <= _Q75:
        return 0.0
    lo, hi = 0.0, float(np.max(np.abs(mid)))
    for _ in range(40):
        c = 0.5 * (lo + hi)
        lo, hi = (c, hi) if q75(c) > _Q75 else (lo, c)
    return 0.5 * (lo + hi)


def _typical_spread(
    patches: PatchMedians | None, src: np.ndarray, dst: np.ndarray, dst_n: np.ndarray,
    tree: cKDTree,
) -> float:
    """The point-to-plane sigma of ``src`` against ``dst`` as the median, over the full
    2 m patches, of each patch's robust sigma about its own median (the whole cloud's when
    fewer than 10 patches are full). A change covering a minority of the patches (a sag, a
    bulge, a new coal load) leaves it alone, where it widened a sigma over all the points
    (three changes of 15-40 mm over a few square metres each took a correctly registered
    16 m pair 7-8 mm beyond the scans' own noise); what the patches' medians share is the
    coherent misfit's part."""
    if patches is None or patches.full.sum() < 10:
        return _plane_sigma(src, dst, dst_n, tree)
    return float(np.median(patches.spread[patches.full]))


def _fit_figures(
    ref: np.ndarray, cmp: np.ndarray
) -> tuple[float, float, float, float, float, float, float]:
    """Cross-epoch and within-epoch robust point-to-plane sigmas of two registered subsets:
    (cross, own_ref, own_cmp, ratio, excess, excess_beyond_noise, coherent), see
    :class:`RegistrationCheck`."""
    ref_a, ref_b = ref[0::2], ref[1::2]
    cmp_a, cmp_b = cmp[0::2], cmp[1::2]
    ref_bn = normals(ref_b, _NORMAL_RADIUS)
    ref_tree = cKDTree(ref_b)
    patches = patch_medians(cmp_a, ref_b, ref_bn, ref_tree)
    coherent = _coherent(patches)
    cross = _typical_spread(patches, cmp_a, ref_b, ref_bn, ref_tree)
    ref_patches = patch_medians(ref_a, ref_b, ref_bn, ref_tree)
    own_ref = _typical_spread(ref_patches, ref_a, ref_b, ref_bn, ref_tree)
    cmp_patches = None
    if len(cmp_b) >= 100:
        cmp_bn, cmp_tree = normals(cmp_b, _NORMAL_RADIUS), cKDTree(cmp_b)
        cmp_patches = patch_medians(cmp_a, cmp_b, cmp_bn, cmp_tree)
        own_cmp = _typical_spread(cmp_patches, cmp_a, cmp_b, cmp_bn, cmp_tree)
    else:
        own_cmp = np.inf
    own = max(own_ref, own_cmp)
    ratio = cross / own if own > 0 and np.isfinite(own) else np.inf
    if not np.isfinite(ratio):
        return cross, own_ref, own_cmp, float(ratio), np.inf, np.inf, coherent
    excess = float(np.sqrt(max(cross**2 - own**2, 0.0)))
    beyond = _paired_excess(patches, ref_patches if own_ref >= own_cmp else cmp_patches)
    return cross, own_ref, own_cmp, float(ratio), excess, beyond, coherent


def _paired_excess(cross: PatchMedians | None, own: PatchMedians | None) -> float:
    """The fit excess patch by patch, beyond its own sampling error: ``sqrt(max(D - 2 se, 0))``
    with ``D`` the median over the 2 m patches full in both of ``cross_i^2 - own_i^2`` (each
    patch's sigma across the epochs and within the noisier one) and ``se`` that median's
    standard error (1.2533 robust sigma / sqrt(n)). Pairing the patches takes out what the
    surfaces themselves vary by (a chamber's patches spread wider than the plain walls' in both
    figures alike); what is left within two standard errors is the sigmas' sampling noise, not
    misfit (the plain difference of the two medians read 6.8 mm on the demo, registered to
    1 mm). NaN when fewer than 10 patches pair up (the plain excess then stands in)."""
    if cross is None or own is None:
        return np.nan
    a = cross.key[cross.full]
    b = own.key[own.full]
    if len(a) < 10 or len(b) < 10:
        return np.nan
    both = np.concatenate([a, b])
    _, inv, counts = unique_rows(both)
    ia = np.flatnonzero(counts[inv[: len(a)]] == 2)
    if len(ia) < 10:
        return np.nan
    # the matching patch of ``own`` for each paired patch of ``cross``
    slot = np.full(len(counts), -1, dtype=np.int64)
    slot[inv[len(a):]] = np.arange(len(b))
    ib = slot[inv[ia]]
    d = cross.spread[cross.full][ia] ** 2 - own.spread[own.full][ib] ** 2
    d = d[np.isfinite(d)]
    if len(d) < 10:
        return np.nan
    mid = float(np.median(d))
    se = 1.2533 * 1.4826 * float(np.median(np.abs(d - mid))) / float(np.sqrt(len(d)))
    return float(np.sqrt(max(mid - _EXCESS_Z * se, 0.0)))


def _beyond(check: Any) -> float:
    """A check's excess beyond the sigmas' noise, or its plain excess where not computed."""
    b = check.excess_beyond_noise
    return b if np.isfinite(b) or not np.isfinite(check.excess) else check.excess


def _registration_sigma(excess: float, coherent: float) -> float:
    """The registration's error along the normals for the level of detection: the larger of
    the unexplained misfit and its patch-coherent part (0 when neither is finite)."""
    vals = [v for v in (excess, coherent) if np.isfinite(v)]
    return float(max(vals)) if vals else 0.0


def verify_registration(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    ref_centerline: Centerline,
    *,
    transform: np.ndarray | None = None,
    cmp_centerline: Centerline | None = None,
    search: float = 10.0,
    points_per_metre: int = 1500,
) -> RegistrationCheck:
    """Independent figures of a registration (see the module notes).

    Parameters
    ----------
    ref_xyz : ndarray, shape (N, 3)
        Reference points, metres.
    cmp_xyz : ndarray, shape (M, 3)
        Compared points, metres: registered already, or in their own frame with
        ``transform``.
    ref_centerline : Centerline
        The reference centreline (reference frame).
    transform : ndarray, shape (4, 4), optional
        Compared -> reference transform (applied to a subsample only).
    cmp_centerline : Centerline, optional
        The compared epoch's centreline in its own frame (``transform`` is applied).
    search : float
        Largest along-axis shift the section correlation looks for, metres (at most a quarter
        of the common stretch is searched, at least 2 m).
    points_per_metre : int
        Points per metre of the reference centreline in the section images, and in each half
        of the plane fits (at least 200 000 and 25 000): the registration's own density
        (``[registration] max_points_per_metre``). A fixed count would thin a long tunnel
        until its normals and its one chamber are lost (350 m: slides of 2 cm read where the
        registration was 3 mm off).

    Returns
    -------
    RegistrationCheck
    """
    origin = np.asarray(ref_xyz[0], dtype=np.float64)
    # the section images want many points (as many as the registration used), the plane fits
    # far fewer: a large random subset in random order for the first, its head for the second
    # (a head of the cloud in its own order would be one end of the tunnel only)
    length = float(ref_centerline.length)
    n_image = max(_IMAGE_SAMPLE, int(points_per_metre * length))
    n_plane = max(2 * _SAMPLE, int(2 * points_per_metre * length))
    n_all = max(n_image, n_plane)
    ref_all = _shuffled_subset(np.asarray(ref_xyz), n_all, 11) - origin
    cmp_all = _shuffled_subset(np.asarray(cmp_xyz), n_all, 12)
    if transform is not None:
        cmp_all = apply_transform(np.asarray(transform, dtype=np.float64), cmp_all)
    cmp_all = cmp_all - origin
    cl = ref_centerline.transformed(_shift_matrix(-origin))
    # only the stretch both epochs cover, 0.5 m inside the reference's ends
    ma = cl.project(cmp_all)
    inside_all = (ma.chainage > 0.5) & (ma.chainage < cl.length - 0.5)
    ref_big = ref_all[:n_image]
    mp = _head(ma, n_image)  # the compared section image's points
    ref = ref_all[:n_plane]
    cmp = cmp_all[inside_all][:n_plane]
    cross, own_ref, own_cmp, ratio, excess, beyond, coherent = _fit_figures(ref, cmp)

    rp = cl.project(ref_big)
    # a quarter of the common stretch at most: beyond it a short overlap matches partial
    # overlaps of itself as well as the true one
    common = float(np.percentile(mp.chainage, 99) - np.percentile(mp.chainage, 1))
    reach = float(np.clip(0.25 * common, 2.0, search))
    ref_proj = (rp.chainage, rp.lateral, rp.vertical)
    cmp_proj = (mp.chainage, mp.lateral, mp.vertical)
    c_shift, c_spread = coarse_shift(ref_proj, cmp_proj, cl, search=reach)
    pose_ratio = _pose_ratio(ref_proj, cmp_proj, cl, reach)
    # as many compared points per metre as the plane fits hold (at least the registration's
    # 60 000): over 350 m, 60 000 leave a chamber's end walls a few dozen points, and the
    # slide then moved by centimetres with the rounding of the input coordinates
    slide_points = max(60_000, min(len(cmp), int(points_per_metre * length)))
    ref_n = normals(ref, _NORMAL_RADIUS)
    # the same slide with normals over twice the radius: a real surface across the axis gives
    # the same answer at both scales, relief drowned in noise does not (a 2.8 m drift with
    # 1.9 cm relief under 2.9 cm noise: 0 vs 8.7 cm, where the registration was 7.5 cm off)
    wide_n = normals(ref, 2 * _NORMAL_RADIUS)
    # every slide below runs on the same reference points, most on the same compared ones
    same = {"tree": cKDTree(ref), "chainage": cl.project(cmp).chainage}
    tan = cl.frame_at(same["chainage"])[0]
    slides = [
        (ref_n, cmp, True, same),
        # started 2 cm either side of the registered position, the same slide must end where
        # it ends from there: a sparse, noisy rough-rock pair registered 11.9 mm off read a
        # remaining slide of 0.3 mm, and ended at -10.8 and +12.5 mm from starts 2 cm off
        # (it had stuck)
        (ref_n, cmp - _PROBE * tan, True, {"tree": same["tree"]}),
        (ref_n, cmp + _PROBE * tan, True, {"tree": same["tree"]}),
        (wide_n, cmp, True, same),
        # and both scales with the kernel narrowing to 5 cm whatever the noise: the noise-wide
        # kernel is the unbiased one under heavy noise (+-29 mm: 11 mm off with the narrow
        # one), but on relief alone the narrow one saw a 13.8 mm misplacement the wide one
        # read as 7 mm
        (ref_n, cmp, False, same),
        (wide_n, cmp, False, same),
    ]

    def slide(n: np.ndarray, pts: np.ndarray, floor: bool, reuse: dict) -> AxialShift:
        return axial_correction(ref, n, pts, cl, slide_points, noise_floor=floor, **reuse)[1]

    # independent slides: Dask's local threads run them side by side, as many as the slides'
    # memory budget allows
    fine, low, high, wide, *narrow = thread_map(
        slide, slides, threads=concurrent_slides(slide_points, os.cpu_count() or 1))
    probes = [side * _PROBE + p.shift if p.informative else np.nan
              for side, p in ((-1.0, low), (1.0, high))]
    # nothing to judge when the slide itself found no surface across the axis; a start 2 cm
    # off that finds none is as bad as one that sticks
    ends = np.array([fine.shift, *probes])
    spread = (float(np.ptp(ends)) if np.all(np.isfinite(ends)) else np.inf) \
        if fine.informative else np.nan
    scales = (
        abs(fine.shift - wide.shift) / float(np.hypot(fine.uncertainty, wide.uncertainty))
        if fine.informative and wide.informative
        else np.nan
    )
    combined = float(np.hypot(0.125, fine.uncertainty))
    # without a point-to-plane solution (no surface across the axis) there is nothing to
    # compare: NaN, and the spread of the section correlation decides alone
    disagreement = (
        abs(c_shift - fine.shift) / combined
        if fine.informative and c_spread <= _DETERMINED
        else np.nan
    )
    difference = np.nan
    if cmp_centerline is not None:
        cc = cmp_centerline if transform is None else cmp_centerline.transformed(transform)
        pc = ref_centerline.project(cc.points)
        keep = (pc.chainage > 1.0) & (pc.chainage < ref_centerline.length - 1.0)
        if keep.sum() >= 10:
            difference = float(np.percentile(pc.distance[keep], 95)) / np.sqrt(2.0)
    return RegistrationCheck(
        cross_residual=cross,
        ref_residual=own_ref,
        cmp_residual=own_cmp,
        residual_ratio=float(ratio),
        excess=excess,
        excess_beyond_noise=beyond,
        coherent=coherent,
        coarse_shift=float(c_shift),
        coarse_spread=float(c_spread),
        fine_shift=float(fine.shift),
        fine_sigma=float(fine.uncertainty),
        axial_disagreement=float(disagreement),
        centreline_difference=difference,
        pose_mismatch=pose_ratio,
        wide_shift=float(wide.shift),
        narrow_shifts=tuple(float(a.shift) if a.informative else np.nan for a in narrow),
        scale_disagreement=float(scales),
        probe_shifts=(float(probes[0]), float(probes[1])),
        axial_spread=spread,
    )


def _head(p: Any, n: int) -> Any:
    """The first ``n`` points of a projection."""
    return type(p)(**{f.name: getattr(p, f.name)[:n] for f in dataclasses.fields(p)})


def _shuffled_subset(xyz: np.ndarray, n: int, seed: int) -> np.ndarray:
    """At most ``n`` of the points in random order (seeded), so that any head of the result is
    a random subset too; :func:`~tunneldef.spatial.random_subset` keeps a small cloud whole,
    in its own order."""
    sub = random_subset(xyz, n, seed)
    if sub is xyz:
        sub = xyz[np.random.default_rng(seed).permutation(len(xyz))]
    return sub


_DETERMINED = 1.0  # m: a coarse spread up to this is one basin (the registration's rule)


def _pose_ratio(
    ref_proj: tuple[np.ndarray, np.ndarray, np.ndarray],
    cmp_proj: tuple[np.ndarray, np.ndarray, np.ndarray],
    cl: Centerline,
    search: float,
    step: float = 0.25,
) -> float:
    nb = int(np.ceil((cl.length + 2 * search) / step))
    ref_img, _ = section_image(*ref_proj, start=-search, step=step, n_bins=nb)
    cmp_img, _ = section_image(*cmp_proj, start=-search, step=step, n_bins=nb)
    n_cmp = int(np.isfinite(cmp_img).sum())
    kmax = int(np.ceil(search / step))
    shifts = np.arange(-kmax, kmax + 1)
    scores, _, _ = _mismatch(ref_img, cmp_img, shifts, clip=0.3,
                             min_cells=max(int(0.3 * n_cmp), 10))
    best = float(np.min(scores))
    at_zero = float(scores[kmax])
    if not (np.isfinite(best) and np.isfinite(at_zero)) or best <= 0:
        return np.nan
    noise = 3.0 * np.sqrt(2.0 / max(n_cmp // 4, 1))
    return (at_zero / best - 1.0) / noise


def _shift_matrix(t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


# ---------------------------------------------------------------------------------------------
# drift networks
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NetworkCheck:
    """Independent figures of a network registration (metres).

    Attributes
    ----------
    cross_residual, ref_residual, cmp_residual, residual_ratio, excess : float
        As in :class:`RegistrationCheck`, over the whole network.
    remaining : ndarray, shape (3,)
        The translation a robust point-to-plane fit still finds from the registered pose.
    probe_ends : ndarray, shape (4, 3)
        Where that fit ends when started 2 cm off along +x, -x, +y and -y.
    spread : float
        Largest distance between any two of the five ends: 0 when the surfaces fix the
        position in every direction (the fit is drawn back to one place from any side), up to
        4 cm along a direction nothing fixes (the fit sticks where it starts).
    coherent : float
        As in :class:`RegistrationCheck`.
    alternative_margin : float
        The registration's evidence for its chosen pose less that for the best other pose
        more than 10 m away
        (:attr:`~tunneldef.registration.network.NetworkRegistration.evidence` and
        ``alternative_evidence``; NaN when not given).
    excess_beyond_noise : float
        As in :class:`RegistrationCheck`.
    weak_direction : ndarray, shape (3,)
        The direction in which the fit's surfaces hold the position least (the eigenvector of
        the smallest eigenvalue of its point-to-plane normal matrix at the registered pose).
    weak_share : float
        That eigenvalue's share of the matrix's trace: 1/3 when walls face every way, near 0
        along a plain drift. The normals' own tilt noise gives every direction a floor (a 6 m
        arch with a gentle bend at +-2.5 cm and 180 points/m^2 held 2.7 % along its drift,
        about 1.4 % with normals over 0.3 m), so a small share says the position there rests
        on little but that noise.
    """

    cross_residual: float
    ref_residual: float
    cmp_residual: float
    residual_ratio: float
    excess: float
    remaining: np.ndarray
    probe_ends: np.ndarray
    spread: float
    coherent: float = np.nan
    alternative_margin: float = np.nan
    excess_beyond_noise: float = np.nan
    weak_direction: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    weak_share: float = np.nan

    @property
    def registration_sigma(self) -> float:
        """The registration's error along the normals passed to the level of detection."""
        return _registration_sigma(_beyond(self), self.coherent)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (non-finite values become None)."""
        def num(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {
            "cross_residual": num(self.cross_residual), "ref_residual": num(self.ref_residual),
            "cmp_residual": num(self.cmp_residual), "residual_ratio": num(self.residual_ratio),
            "excess": num(self.excess), "excess_beyond_noise": num(self.excess_beyond_noise),
            "remaining": [num(v) for v in self.remaining],
            "probe_ends": [[num(v) for v in row] for row in self.probe_ends],
            "spread": num(self.spread),
            "coherent": num(self.coherent),
            "alternative_margin": num(self.alternative_margin),
            "weak_direction": [num(v) for v in self.weak_direction],
            "weak_share": num(self.weak_share),
        }


def edge_centreline_differences(
    ref_net: Any, cmp_edges: list[np.ndarray], *, step: float = 0.5, margin: float = 1.0,
    min_samples: int = 10,
) -> dict[int, float]:
    """Per reference edge, how far the compared epoch's own centreline runs from it after
    registration: the p95 distance, over the common part, of the compared curves' samples
    from the edge's curve, divided by sqrt(2) (about either curve's p95 error, as
    :attr:`RegistrationCheck.centreline_difference` for a single drift).

    Static rock relief and overbreak move both epochs' section centres alike, so they do not
    show here, where they make each epoch's centres scatter about its own curve; a centreline
    that wanders with the noise, or reads a wall on clutter in one epoch, does.

    Parameters
    ----------
    ref_net : CenterlineNetwork
        The reference network.
    cmp_edges : list of ndarray, shape (K, 3)
        The compared network's curves as points in the reference frame (every edge, after
        the registration and any drift correction).
    step : float
        Spacing of the compared samples used, metres.
    margin : float
        Samples within this of an edge's ends or junction zones are left out, metres.
    min_samples : int
        Fewer common samples on an edge give NaN (nothing to judge).

    Returns
    -------
    dict of int -> float
        Edge id -> figure, metres (NaN where the epochs share too little of the edge).
    """
    out: dict[int, float] = {}
    pieces = []
    for pts in cmp_edges:
        if len(pts) < 2:
            continue
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        idx = np.searchsorted(s, np.arange(0.0, s[-1], step))
        tan = np.gradient(pts, axis=0)
        tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-12)
        pieces.append((pts[idx], tan[idx]))
    for e in ref_net.edges:
        half = float(e.centerline.meta.get("half_width_m", 1.0))
        dist = []
        for pts, tan in pieces:
            pr = e.centerline.project(pts)
            keep = ((pr.chainage > margin) & (pr.chainage < e.length - margin)
                    & (pr.distance < half))
            for a, b in e.zones:
                keep &= (pr.chainage < a - margin) | (pr.chainage > b + margin)
            if not keep.any():
                continue
            t_ref = e.centerline.frame_at(pr.chainage[keep])[0]
            parallel = np.abs(np.einsum("ij,ij->i", t_ref, tan[keep])) > 0.9
            dist.append(pr.distance[keep][parallel])
        d = np.concatenate(dist) if dist else np.zeros(0)
        out[e.id] = (float(np.percentile(d, 95)) / np.sqrt(2.0) if d.size >= min_samples
                     else np.nan)
    return out


def verify_network(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    length: float,
    *,
    points_per_metre: int = 1500,
) -> NetworkCheck:
    """Independent figures of a registered drift-network pair (see the module notes).

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (N, 3), (M, 3)
        Reference points and the compared points in the reference frame (after any drift
        correction), metres.
    length : float
        Total length of the reference network's edges, metres: with ``points_per_metre`` it
        sets how many points the fits use (at least 50 000 per epoch).

    Returns
    -------
    NetworkCheck
    """
    origin = np.asarray(ref_xyz[0], dtype=np.float64)
    n_plane = max(2 * _SAMPLE, int(2 * points_per_metre * length))
    ref = _shuffled_subset(np.asarray(ref_xyz) - origin, n_plane, 11)
    cmp = _shuffled_subset(np.asarray(cmp_xyz), n_plane, 12) - origin
    # only compared points with the reference surface within reach take part
    tree = cKDTree(ref)
    near = np.isfinite(tree.query(cmp, distance_upper_bound=0.3, workers=-1)[0])
    cmp = cmp[near]
    cross, own_ref, own_cmp, ratio, excess, beyond, coherent = _fit_figures(ref, cmp)
    ref_n = normals(ref, _NORMAL_RADIUS)
    # a translation has three unknowns: a fifth of the registration's points per metre holds
    # it to a fraction of a millimetre (the five fits took 93 s of a 0.5 M-point network)
    sub = cmp[: max(60_000, int(points_per_metre * length) // 5)]
    remaining = translation_fit(ref, ref_n, sub, tree=tree)
    starts = _PROBE * np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    ends = np.array([translation_fit(ref, ref_n, sub, start=s, tree=tree) for s in starts])
    every = np.vstack([remaining[None], ends])
    spread = (float(np.max(np.linalg.norm(every[:, None] - every[None], axis=2)))
              if np.all(np.isfinite(every)) else np.inf)
    weak, share = _weakest_direction(ref, ref_n, sub, tree)
    return NetworkCheck(cross, own_ref, own_cmp, ratio, excess, remaining, ends, spread,
                        coherent, excess_beyond_noise=beyond, weak_direction=weak,
                        weak_share=share)


def _weakest_direction(
    ref_xyz: np.ndarray, ref_normals: np.ndarray, cmp_xyz: np.ndarray, tree: cKDTree,
) -> tuple[np.ndarray, float]:
    """The direction (3,) in which Tukey-weighted point-to-plane residuals at the given pose
    hold a translation least, and its share of the normal matrix's trace (kernel: the
    residuals' noise, at least 5 cm, as the last stage of :func:`translation_fit`)."""
    d, j = tree.query(cmp_xyz, distance_upper_bound=0.3, workers=-1)
    ok = np.isfinite(d)
    if ok.sum() < 100:
        return np.full(3, np.nan), np.nan
    n = ref_normals[j[ok]]
    r = np.einsum("ij,ij->i", n, cmp_xyz[ok] - ref_xyz[j[ok]])
    kernel = max(0.05, noise_kernel(r))
    w = np.where(np.abs(r) < kernel, (1 - (r / kernel) ** 2) ** 2, 0.0)
    vals, vecs = np.linalg.eigh((n * w[:, None]).T @ n)
    total = float(vals.sum())
    if total <= 0:
        return np.full(3, np.nan), np.nan
    return vecs[:, 0] * np.sign(vecs[np.argmax(np.abs(vecs[:, 0])), 0]), float(vals[0] / total)


def rigid_convergence(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    along: np.ndarray,
    *,
    sample: int = 60_000,
) -> tuple[float, np.ndarray]:
    """Where a rigid point-to-plane fit (rotations included) ends from the registered pose
    and from 2 cm before and after it along the drift.

    A drift that runs flat and then goes on up a ramp holds the position along it on the
    ramp's floor and roof alone, and those trade a slide for a small pitch: on a 120 m pair
    registered 30 mm off along the drift, the translation fit read 1.1 mm left to move (a
    pitch of 0.003 degrees cancels the slide's height on the ramp). The rigid fit
    (:func:`~.axial.rigid_fit`, planes through the centroids of 16 neighbours) fits both;
    where they hold each other only weakly, it stops near wherever it starts. So the
    figure is how far apart the three fits end.

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (N, 3), (M, 3)
        Reference points and the registered compared points (reference frame), metres.
    along : ndarray, shape (3,)
        The drift's direction (need not be unit).
    sample : int
        Compared points the fits use (those with the reference within 0.3 m).

    Returns
    -------
    spread : float
        Largest distance, metres, by which any compared point of the sample lies apart in
        two of the three fitted poses (``inf`` when a fit finds too few points on the
        reference).
    ends : ndarray, shape (3, 3)
        The mean displacement of the sample from its registered place in each fitted pose
        (from the pose, 2 cm before, 2 cm after), metres.
    """
    origin = np.asarray(ref_xyz[0], dtype=np.float64)
    ref = np.asarray(ref_xyz, dtype=np.float64) - origin
    tree = cKDTree(ref)
    cmp = np.asarray(cmp_xyz, dtype=np.float64) - origin
    near = np.isfinite(tree.query(cmp, distance_upper_bound=0.3, workers=-1)[0])
    pts = _shuffled_subset(cmp[near], sample, 13)
    u = np.asarray(along, dtype=np.float64)
    u = u / np.linalg.norm(u)
    ref_n, planes = normals(ref, _NORMAL_RADIUS), neighbour_centroids(ref, tree)
    placed = []
    for side in (0.0, -1.0, 1.0):
        start = pts + side * _PROBE * u
        fit = rigid_fit(ref, ref_n, start, tree=tree, plane_points=planes)
        if not np.all(np.isfinite(fit)):
            return float("inf"), np.full((3, 3), np.nan)
        placed.append(apply_transform(fit, start))
    spread = max(float(np.max(np.linalg.norm(placed[i] - placed[j], axis=1)))
                 for i in range(3) for j in range(i + 1, 3))
    return spread, np.array([(p - pts).mean(axis=0) for p in placed])
