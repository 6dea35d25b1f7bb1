"""The along-axis shift between two epochs, by correlating their unrolled sections.

Along a straight prism the position along the axis is the one degree of freedom the section
shape says nothing about; only what changes along the tunnel (chambers, width and height changes,
curvature, niches, equipment, rock texture) fixes it. The paper (§3.2.4, eq. 12) takes the shift
at the maximum of the cross-correlation of the two centrelines' y values. Here the same idea is
applied to everything the two epochs share: both clouds are expressed relative to the reference
centreline as an unrolled section image ``r(s, phi)`` (mean distance from the centreline per
chainage bin and per angle around it; its columns at 0 and 180 degrees are the half-widths,
at 90 and 270 degrees the half-heights, their difference the centreline's y), and the shift is
the minimum of a robust mismatch between the two images, searched coarse-to-fine with sub-bin
interpolation. The curvature of the mismatch at its minimum gives the shift's uncertainty.

One idea at this length: the one degree of freedom the section shape leaves free, found
coarse (the section images) and fine (the point-to-plane slide with its cached nearest
neighbours and its memory budget), with the uncertainty of each.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..curve import Centerline
from ..spatial import morton_order, query_workers
from .kernels import candidate_terms, nearest_two, slide_residuals

__all__ = [
    "AxialShift", "CurveShift", "coarse_shift", "curve_shift", "fine_shift", "noise_kernel",
    "section_image", "concurrent_slides", "neighbour_centroids", "rigid_fit",
    "translation_fit",
]

logger = logging.getLogger(__name__)

_N_ANGLES = 48  # 7.5 degree sectors around the centreline
_MIN_CELL_POINTS = 3
_SIGMA_FLOOR = 0.002  # m


@dataclass(frozen=True)
class AxialShift:
    """Result of :func:`axial_shift`.

    Attributes
    ----------
    shift : float
        Chainage correction, metres: a compared point at reference chainage ``s`` belongs at
        ``s + shift``.
    uncertainty : float
        One standard deviation of ``shift``, metres (``inf`` when the tunnel has no feature
        along its axis within the overlap).
    informative : bool
        False when the mismatch has no clear minimum (then ``shift`` is 0).
    cells : int
        Number of image cells both epochs share at the optimum.
    strongest_block : int or None
        The chainage block (an id of ``blocks`` in :func:`fine_shift`) holding the largest
        share of the information about the shift: where the feature that fixes it is.
    """

    shift: float
    uncertainty: float
    informative: bool
    cells: int
    strongest_block: int | None = None


def section_image(
    chainage: np.ndarray,
    lateral: np.ndarray,
    vertical: np.ndarray,
    *,
    start: float,
    step: float,
    n_bins: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Unrolled section image: mean distance from the centreline per (angle, chainage) cell.

    Returns
    -------
    mean : ndarray, shape (48, n_bins)
        Mean distance, metres (NaN in cells with fewer than 3 points).
    count : ndarray, shape (48, n_bins)
        Points per cell.
    """
    i = np.floor((chainage - start) / step).astype(np.int64)
    phi = np.arctan2(vertical, lateral)
    j = np.floor((phi + np.pi) / (2 * np.pi) * _N_ANGLES).astype(np.int64) % _N_ANGLES
    ok = (i >= 0) & (i < n_bins)
    flat = j[ok] * n_bins + i[ok]
    r = np.hypot(lateral, vertical)[ok]
    size = _N_ANGLES * n_bins
    cnt = np.bincount(flat, minlength=size).astype(np.float64)
    tot = np.bincount(flat, weights=r, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(cnt >= _MIN_CELL_POINTS, tot / cnt, np.nan)
    return mean.reshape(_N_ANGLES, n_bins), cnt.reshape(_N_ANGLES, n_bins)


def _mismatch(
    ref: np.ndarray, cmp: np.ndarray, shifts: np.ndarray, *, clip: float, min_cells: int
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Robust mean square difference of the images for integer bin shifts (cmp column i
    compared with ref column i + k), after removing a constant offset per angle."""
    n = ref.shape[1]
    scores = np.full(len(shifts), np.inf)
    cells = np.zeros(len(shifts), dtype=np.int64)
    residuals: list[np.ndarray] = []
    for q, k in enumerate(shifts):
        if k >= 0:
            a, b = ref[:, k:], cmp[:, : n - k]
        else:
            a, b = ref[:, : n + k], cmp[:, -k:]
        e = a - b
        valid = np.isfinite(e)
        nv = int(valid.sum())
        if nv < min_cells:
            residuals.append(np.empty((0, 0)))
            continue
        e = np.where(valid, e, 0.0)
        per_angle = valid.sum(axis=1)
        offset = np.where(per_angle > 0, e.sum(axis=1) / np.maximum(per_angle, 1), 0.0)
        e = np.where(valid, e - offset[:, None], np.nan)
        scores[q] = float(np.nanmean(np.minimum(e**2, clip**2)))
        cells[q] = nv
        residuals.append(e)
    return scores, cells, residuals


def coarse_shift(
    ref_proj: tuple[np.ndarray, np.ndarray, np.ndarray],
    cmp_proj: tuple[np.ndarray, np.ndarray, np.ndarray],
    centerline: Centerline,
    *,
    search: float,
    step: float = 0.25,
    clip: float = 0.3,
    min_overlap: float = 0.3,
) -> tuple[float, float]:
    """Chainage shift to within a bin, from the unrolled section images (eq. 12 generalised).

    Parameters
    ----------
    ref_proj, cmp_proj : tuple of ndarray, each shape (N,)
        (chainage, lateral, vertical) of reference and compared points relative to the reference
        centreline, metres.
    centerline : Centerline
        The reference centreline.
    search : float
        Largest shift searched, metres.
    step : float
        Chainage bin, metres.
    clip : float
        Larger differences count as this (deformation, moved equipment, coal), metres.

    Returns
    -------
    shift : float
        A compared point at reference chainage ``s`` belongs at ``s + shift``, metres.
    spread : float
        Half-width of the basin of shifts matching as well as the best within the noise, or
        the distance to an equally good match outside it, metres (a bin or two when the overlap
        has features along the axis, a large part of the search range on a featureless prism;
        ``inf`` when nothing overlaps).
    """
    nb = int(np.ceil((centerline.length + 2 * search) / step))
    ref_img, _ = section_image(*ref_proj, start=-search, step=step, n_bins=nb)
    cmp_img, _ = section_image(*cmp_proj, start=-search, step=step, n_bins=nb)
    n_cmp = int(np.isfinite(cmp_img).sum())
    kmax = int(np.ceil(search / step))
    shifts = np.arange(-kmax, kmax + 1)
    scores, _, _ = _mismatch(
        ref_img, cmp_img, shifts, clip=clip, min_cells=max(int(min_overlap * n_cmp), 10)
    )
    if not np.isfinite(scores).any():
        return 0.0, float("inf")
    best = int(np.argmin(scores))
    # shifts whose mismatch is within the noise of the best one are equally good matches:
    # the mean of n squared differences scatters by about sqrt(2 / n) of itself
    n_eff = max(int(np.isfinite(cmp_img).sum()) // 4, 1)
    tol = scores[best] * (1.0 + 3.0 * np.sqrt(2.0 / n_eff))
    alike = np.isfinite(scores) & (scores <= tol)
    # the basin around the best shift is what the fine stage resolves; equally good matches
    # outside it are other places the compared stretch could be
    lo = best
    while lo > 0 and alike[lo - 1]:
        lo -= 1
    hi = best
    while hi < len(shifts) - 1 and alike[hi + 1]:
        hi += 1
    spread = float(max(best - lo, hi - best) * step)
    outside = alike.copy()
    outside[lo : hi + 1] = False
    if outside.any():
        spread = max(spread, float(np.max(np.abs(shifts[outside] - shifts[best])) * step))
    return float(shifts[best] * step), spread


@dataclass(frozen=True)
class CurveShift:
    """Result of :func:`curve_shift`.

    Attributes
    ----------
    shift : float
        Slide, metres, from where the current pose lays the compared curve's middle on the
        reference curve (0 when not informative).
    uncertainty : float
        Metres: the slide at which the curves' rigid misfit grows by their own noise (``inf``
        when it does not grow, or another slide matches about as well).
    informative : bool
        True when the curves' shapes fix the position along the axis.
    rms : float
        Rigid misfit of the two curves at the best slide, metres (their noise).
    rise : float
        Growth of the misfit per metre of slide away from the best, m/m.
    pairs : (ndarray, ndarray) or None
        The compared curve's samples and the reference curve's points they pair with at the
        best slide (each (K, 3)): what a rigid fit at that slide is made on.
    """

    shift: float
    uncertainty: float
    informative: bool
    rms: float = float("nan")
    rise: float = 0.0
    pairs: tuple[np.ndarray, np.ndarray] | None = None


_CURVE_STEP = 0.25  # m between curve samples and between slides
_CURVE_MARGIN = 1.0  # m kept clear of either curve's ends (a fit's ends curl)
_CURVE_NOISE_FLOOR = 0.005  # m: the least misfit taken as the curves' noise
_CURVE_PROBE = 1.0  # m: the slide at which the misfit's growth is read
_CURVE_MAX_RMS = 0.05  # m: a best misfit beyond this brings no two curves of one drift together
_CURVE_MAX_SIGMA = 1.0  # m: a misfit that grows slower than this tells no position (a straight
# drift's curves wobbling by their noise read +-9 to +-115 m)
_CURVE_ALIKE = 3.0  # a slide farther than the basin matching within this many noises: ambiguous


def curve_shift(
    ref_cl: Centerline, cmp_cl: Centerline, *, search: float, min_common: float = 10.0,
    min_overlap: float = 0.3,
) -> CurveShift:
    """Chainage shift from the shapes of the two centrelines (their bends and grade changes).

    A drift that runs straight, bends and runs straight again is fixed along its axis by the
    bend even where the rock is smooth and the section constant: slid along the reference
    curve, the compared curve no longer fits it by any rigid motion. The section images of
    :func:`coarse_shift` cannot see that, since they follow the reference curve round the
    bend. For each slide (every 0.25 m within ``search`` of where the current pose lays the
    compared curve's middle on the reference) and either way round, the compared curve's
    samples are paired with the reference curve's points at their own chainage plus the slide,
    and the RMS distance left after the best turn about the vertical and translation is the
    misfit. A bend of constant
    radius slides along itself (the misfit stays flat) and is no feature; nor is one that
    another slide matches within three times the curves' noise, nor one that fixes the
    position to no better than a metre.

    Parameters
    ----------
    ref_cl, cmp_cl : Centerline
        The reference centreline and the compared one, roughly in place (same frame).
    search : float
        Largest slide searched, metres.
    min_common, min_overlap : float
        A slide counts only when the curves share at least ``min_common`` metres and
        ``min_overlap`` of the shorter curve's usable length.

    Returns
    -------
    CurveShift
        ``pairs`` at the best slide (the rigid motion is fitted to them); ``uncertainty`` is
        the slide at which the misfit grows by the curves' own noise
        (``max(rms, 5 mm) / rise``): the curves' errors are correlated along them over
        metres, so no averaging over their samples is claimed.
    """
    none = CurveShift(0.0, float("inf"), False)
    step, margin = _CURVE_STEP, _CURVE_MARGIN
    sc = np.arange(margin, cmp_cl.length - margin, step)
    if sc.size < 8 or ref_cl.length < 2 * margin + min_common:
        return none
    p = cmp_cl.point_at(sc)
    # either way round (the fit turns the curve about the vertical: a candidate whose compared
    # epoch points the wrong way still pairs the curves right), each slide counted from where
    # the current pose lays the compared curve's middle on the reference
    mid = len(sc) // 2
    at = float(ref_cl.project(p[mid : mid + 1]).chainage[0])
    # the common part asked for is a share of the shorter curve: a later survey that goes on
    # for 130 m more still pairs
    need = max(min_common, min_overlap * min(sc[-1] - sc[0], ref_cl.length - 2 * margin)) / step
    kmax = int(np.ceil(search / step))
    shifts = np.arange(-kmax, kmax + 1) * step
    ways = (1.0, -1.0)
    rms = np.full((2, len(shifts)), np.nan)
    for w, way in enumerate(ways):
        base = at + way * (sc - sc[mid])
        for q, d in enumerate(shifts):
            s = base + d
            k = (s > margin) & (s < ref_cl.length - margin)
            if k.sum() >= need:
                rms[w, q] = _rigid_rms(p[k], ref_cl.point_at(s[k]))
    ok = np.isfinite(rms)
    if ok.sum() < 3:
        return none
    w, best = np.unravel_index(int(np.nanargmin(rms)), rms.shape)
    r0 = float(rms[w, best])
    line, fine = rms[w], ok[w]
    noise = max(r0, _CURVE_NOISE_FLOOR)
    h = int(round(_CURVE_PROBE / step))
    rises = [np.sqrt(max(line[j] ** 2 - r0**2, 0.0)) / _CURVE_PROBE
             for j in (best - h, best + h) if 0 <= j < len(line) and fine[j]]
    if not rises or min(rises) <= 0.0:
        return CurveShift(0.0, float("inf"), False, r0, 0.0)
    rise = float(min(rises))
    sigma = noise / rise
    if r0 > _CURVE_MAX_RMS or not (best > 0 and fine[best - 1]) \
            or not (best < len(line) - 1 and fine[best + 1]):
        # no slide brings the curves together, or the best is at the end of the search
        return CurveShift(0.0, float("inf"), False, r0, rise)
    # sub-bin: the vertex of the parabola through the misfits' squares around the best
    shift = float(shifts[best])
    a_, b_, c_ = line[best - 1] ** 2, line[best] ** 2, line[best + 1] ** 2
    den = a_ - 2 * b_ + c_
    if den > 0:
        shift += float(np.clip(0.5 * (a_ - c_) / den, -0.5, 0.5)) * step
    # another slide (or the other way round) that matches about as well: no feature
    far = ok.copy()
    far[w] &= np.abs(shifts - shifts[best]) > max(_CURVE_PROBE, 3.0 * sigma)
    alike = bool(np.any(rms[far] < _CURVE_ALIKE * noise))
    if alike or not sigma <= _CURVE_MAX_SIGMA:
        return CurveShift(0.0, float("inf"), False, r0, rise)
    base = at + ways[w] * (sc - sc[mid])
    s = base + shift
    k = (s > margin) & (s < ref_cl.length - margin)
    return CurveShift(shift, float(sigma), True, r0, rise, (p[k], ref_cl.point_at(s[k])))


def _rigid_rms(src: np.ndarray, dst: np.ndarray) -> float:
    """RMS distance between paired points left after the best motion of ``src`` onto ``dst``
    that keeps the vertical: a turn about z and a translation (the floors have levelled the
    epochs; a free rotation would also turn a curve upside down, which lays a left-hand bend
    on a right-hand one and a rise on a fall). In plan, the sums of squares about the
    centroids less twice the length of their summed dot and cross products; in height, the
    spread of the differences."""
    a = src[:, :2] - src[:, :2].mean(axis=0)
    b = dst[:, :2] - dst[:, :2].mean(axis=0)
    dot = float(np.einsum("ij,ij->", a, b))
    cross = float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    rss = float(np.einsum("ij,ij->", a, a) + np.einsum("ij,ij->", b, b)) - 2.0 * np.hypot(dot,
                                                                                         cross)
    dz = dst[:, 2] - src[:, 2]
    rss += float(np.sum((dz - dz.mean()) ** 2))
    return float(np.sqrt(max(rss, 0.0) / len(src)))


def noise_kernel(residuals: np.ndarray) -> float:
    """The narrowest Tukey kernel the residuals' own noise allows: 4.685 robust sigmas
    (1.4826 x their median absolute value), Tukey's 95 %-efficiency constant, metres.

    A kernel narrower than the scans' noise cuts the residual distribution off at its
    shoulders, and where surfaces end (a chamber's edges) the cut is one-sided: the fit is
    biased and its sigma too small (+-29 mm noise, 5 cm kernel: a slide 11 mm off along the
    axis, claimed +-2 mm)."""
    r = np.asarray(residuals, dtype=np.float64)
    return 4.685 * 1.4826 * float(np.median(np.abs(r))) if r.size else 0.0


#: Working memory of one slide per sliding point, bytes: the KD-tree's 8 candidates with
#: their distances (transient), the cached candidates and their two terms, the residuals
_SLIDE_BYTES_PER_POINT = 8 * (8 + 8) + 8 * (8 + 8 + 8) + 64
#: Memory the slides that run side by side may take together, bytes
SLIDE_MEMORY_BUDGET = 600e6


def concurrent_slides(points: int, wanted: int) -> int:
    """How many slides of ``points`` sliding points each may run at once (at most ``wanted``,
    the cores): as many as fit :data:`SLIDE_MEMORY_BUDGET`, at least one. A 60 m or 350 m
    survey's slides run side by side; a 1 km survey's (1.5 M points each, 0.6 GB) one at a
    time, so that its peak stays that of one slide."""
    per = max(int(points), 1) * _SLIDE_BYTES_PER_POINT
    return max(1, min(int(wanted), int(SLIDE_MEMORY_BUDGET // per)))


class _SlidingNearest:
    """Nearest reference point of ``x + delta * t`` for points ``x`` that only slide along
    their unit directions ``t``: exactly what ``tree.query(x + delta * t, distance_upper_bound=
    bound)`` gives, at a fraction of the cost when ``delta`` changes by millimetres.

    The ``k`` nearest neighbours within ``reach`` of ``x + delta0 * t`` are found once. A point
    at most ``dk`` from its base has no other reference point closer than ``dk - |delta -
    delta0|`` after a slide, so a candidate nearer than that is the true nearest neighbour, and
    when both are beyond ``bound`` there is none within it; the few points this does not decide
    are queried in the tree, and the candidates are drawn again when they are more than
    30 %. Squared distances along the slide are ``|x0 - c|^2 + D (2 t.(x0 - c) + D)`` with
    ``D = delta - delta0``: one pass over the candidates per step instead of a tree query.
    That formula rounds differently from the tree, so a point whose two nearest candidates, or
    whose nearest candidate and the bound, lie within ``_EPS`` of each other goes to the tree:
    the answer is the tree's to the last index, not only to the millimetre.
    """

    _K = 8
    _REBASE = 0.3  # share of undecided points that draws the candidates again
    MARGIN = 0.05  # m of reach beyond the widest bound: slides this long need no tree query
    _EPS = 1e-7  # m: distances this close to a tie or to the bound are left to the tree

    def __init__(
        self, tree: cKDTree, ref_xyz: np.ndarray, xyz: np.ndarray, tangents: np.ndarray,
        reach: float, delta: float = 0.0,
    ) -> None:
        self.tree, self.reach = tree, reach
        self.ref = np.asarray(ref_xyz, dtype=np.float64)
        self.xyz = np.asarray(xyz, dtype=np.float64)
        self.tan = np.asarray(tangents, dtype=np.float64)
        self.queries = 0
        self._base(delta)

    def _base(self, delta: float) -> None:
        p = self.xyz + delta * self.tan
        d, j = self.tree.query(
            p, k=self._K, distance_upper_bound=self.reach, workers=query_workers(len(p))
        )
        self.queries += 1
        self.delta0 = delta
        # every reference point outside the set lies at least this far from the base point
        self.dk = np.where(np.isfinite(d[:, -1]), d[:, -1], self.reach)
        self.cand, self.a, self.b = candidate_terms(
            p, self.ref, np.asarray(j, dtype=np.int64), d, self.tan
        )

    def query(self, delta: float, bound: float) -> tuple[np.ndarray, np.ndarray]:
        """``(d, j)`` as ``tree.query(x + delta * t, distance_upper_bound=bound)``."""
        if bound > self.reach:
            raise ValueError(f"bound {bound} beyond the candidates' reach {self.reach}")
        for attempt in range(2):
            step = delta - self.delta0
            # the nearest two of each point's candidates, ascending (one compiled pass)
            dmin, second, best = nearest_two(self.a, self.b, step)
            rows = np.arange(len(best))
            free = self.dk - abs(step)  # no point outside the set is nearer than this
            # the tree's own rounding decides near-ties and points near the bound
            eps = self._EPS
            with np.errstate(invalid="ignore"):  # inf - inf where no candidate is in reach
                apart = second - dmin > eps
            nearest = (dmin < free - eps) & apart & (np.abs(dmin - bound) > eps)
            none = ~nearest & (np.minimum(dmin, free) >= bound + eps)
            undecided = ~(nearest | none)
            if attempt == 0 and undecided.mean() > self._REBASE:
                self._base(delta)
                continue
            break
        within = nearest & (dmin <= bound)
        d = np.where(within, dmin, np.inf)
        j = np.where(within, self.cand[rows, best], len(self.ref))
        if undecided.any():
            p = self.xyz[undecided] + delta * self.tan[undecided]
            d[undecided], j[undecided] = self.tree.query(
                p, distance_upper_bound=bound, workers=query_workers(len(p))
            )
            self.queries += 1
        return d, j


def fine_shift(
    ref_xyz: np.ndarray,
    ref_normals: np.ndarray,
    cmp_xyz: np.ndarray,
    tangents: np.ndarray,
    *,
    blocks: np.ndarray,
    kernels: tuple[float, ...] = (0.2, 0.1, 0.05),
    iterations: int = 12,
    tree: cKDTree | None = None,
    noise_floor: bool = True,
) -> AxialShift:
    """Along-axis shift by one-degree-of-freedom robust point-to-plane alignment.

    Each compared point may only slide along the local tunnel direction; the shift minimising
    the Tukey-weighted point-to-plane residuals is found by Gauss-Newton, with a kernel that
    narrows from ``kernels[0]`` to ``kernels[-1]`` (wide basin first, deformation excluded
    last). Only surfaces whose normals have a component along the axis (chamber ends, niches,
    width changes, rough rock, equipment) carry information. The uncertainty is the larger of
    the least-squares value ``sigma_r / sqrt(sum(w (n . t)^2))`` and a delete-one-block
    jackknife over chainage blocks (features are few, errors within a block correlated).
    No kernel after the first is narrower than :func:`noise_kernel` of the first stage's
    residuals, so noisy scans keep an unbiased kernel (``noise_floor=False``: the kernels as
    given; the registration check reads the slide both ways, since either can be the one
    that sees a misplacement).

    Parameters
    ----------
    ref_xyz, ref_normals : ndarray, shape (N, 3)
        Reference points and unit normals, metres.
    cmp_xyz : ndarray, shape (M, 3)
        Compared points, within ~0.2 m of their place along the axis.
    tangents : ndarray, shape (M, 3)
        Unit tunnel direction at each compared point.
    blocks : ndarray, shape (M,) of int
        Chainage block of each compared point (for the jackknife).
    kernels : tuple of float
        Tukey kernel widths, metres (later ones widened to the noise, see above);
        correspondences farther than 1.5 x the kernel are dropped.

    Returns
    -------
    AxialShift
        ``shift`` along ``tangents``, metres.
    """
    tree = tree if tree is not None else cKDTree(ref_xyz)
    # in Morton order, as rigid_fit: the queries run faster and the sums are the same
    order = morton_order(cmp_xyz)
    cmp_xyz = np.asarray(cmp_xyz, dtype=np.float64)[order]
    tangents = np.asarray(tangents, dtype=np.float64)[order]
    blocks = np.asarray(blocks)[order]
    reach = 1.5 * max(kernels) + _SlidingNearest.MARGIN
    nearest = _SlidingNearest(tree, ref_xyz, cmp_xyz, tangents, reach)
    ref_pn = np.hstack([ref_xyz, ref_normals]).astype(np.float64, copy=False)
    delta = 0.0
    scale = 0.0  # noise_kernel of the residuals, once the widest kernel settled
    for stage, kernel in enumerate(kernels):
        kernel = max(kernel, scale)
        if 1.5 * kernel > nearest.reach:  # a noise kernel wider than the first
            reach = 1.5 * kernel + _SlidingNearest.MARGIN
            nearest = _SlidingNearest(tree, ref_xyz, cmp_xyz, tangents, reach, delta)
        for _ in range(iterations):
            d, j = nearest.query(delta, 1.5 * kernel)
            ok = np.isfinite(d)
            if ok.sum() < 20:
                return AxialShift(0.0, float("inf"), False, 0)
            r, a = slide_residuals(cmp_xyz, tangents, ref_pn, np.flatnonzero(ok), j, delta)
            w = np.where(np.abs(r) < kernel, (1 - (r / kernel) ** 2) ** 2, 0.0)
            info = float(np.sum(w * a * a))
            if info <= 1e-9:
                return AxialShift(0.0, float("inf"), False, 0)
            step = -float(np.sum(w * a * r)) / info
            delta += float(np.clip(step, -kernel / 2, kernel / 2))
            if abs(step) < 1e-5:
                break
        if stage == 0 and noise_floor:
            scale = noise_kernel(r)
    sw = float(w.sum())
    sigma_r = np.sqrt(float(np.sum(w * r * r)) / max(sw - 1, 1.0))
    used = j[ok][w > 0]
    shared = len(used) / max(len(np.unique(used)), 1)
    sigma = float(sigma_r * np.sqrt(shared / info))
    # delete-one-block jackknife of the linearised solution
    b = blocks[ok]
    ub, inv = np.unique(b, return_inverse=True)
    den = np.bincount(inv, weights=w * a * a, minlength=len(ub))
    strongest = int(ub[np.argmax(den)])
    if len(ub) >= 3:
        num = np.bincount(inv, weights=w * a * r, minlength=len(ub))
        rest = info - den
        good = rest > 1e-9
        d_minus = delta - (num.sum() - num[good]) / rest[good]
        g = int(good.sum())
        if g >= 3:
            sigma = max(
                sigma, float(np.sqrt((g - 1) / g * np.sum((d_minus - d_minus.mean()) ** 2)))
            )
    # plus a floor for what neither estimate sees: the sampling of the reference surface and
    # the centreline's shape bias the solution by a few mm (ten synthetic rough-rock pairs at
    # 120 points/m^2: RMS axial error 2.7 mm where both estimates above said 1.2 mm)
    sigma = float(np.hypot(sigma, _SIGMA_FLOOR))
    return AxialShift(delta, sigma, sigma < 0.1, int((w > 0).sum()), strongest)


def translation_fit(
    ref_xyz: np.ndarray,
    ref_normals: np.ndarray,
    cmp_xyz: np.ndarray,
    *,
    start: np.ndarray | None = None,
    kernels: tuple[float, ...] = (0.2, 0.1, 0.05),
    iterations: int = 12,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Translation (3,) moving ``cmp_xyz`` onto the reference surface, by Gauss-Newton on
    Tukey-weighted point-to-plane residuals with a narrowing kernel, never narrower than the
    noise (as :func:`.axial.fine_shift`, with three degrees of freedom instead of one),
    started at ``start``; NaN when fewer than 100 points find the surface."""
    tree = tree if tree is not None else cKDTree(ref_xyz)
    cmp_xyz = cmp_xyz[morton_order(cmp_xyz)]  # faster queries, the same fit (see rigid_fit)
    t = np.zeros(3) if start is None else np.array(start, dtype=np.float64)
    scale = 0.0  # no later kernel narrower than the noise (see noise_kernel)
    for stage, kernel in enumerate(kernels):
        kernel = max(kernel, scale)
        for _ in range(iterations):
            p = cmp_xyz + t
            found = _plane_residuals(tree, ref_xyz, ref_normals, p, kernel)
            if found is None:
                return np.full(3, np.nan)
            _, n, r, w = found
            a = (n * w[:, None]).T @ n
            step = -np.linalg.lstsq(a + 1e-9 * np.eye(3), (n * w[:, None]).T @ r, rcond=None)[0]
            size = float(np.linalg.norm(step))
            if size > kernel / 2:
                step *= kernel / 2 / size
            t += step
            if size < 1e-5:
                break
        if stage == 0:
            scale = noise_kernel(r)
    return t


def _plane_residuals(
    tree: cKDTree, anchors: np.ndarray, normals: np.ndarray, p: np.ndarray, kernel: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Point-to-plane residuals of ``p`` against the plane (``anchors``, ``normals``) of its
    nearest reference point within 1.5 kernels, with their Tukey weights: ``(found, normals,
    residuals, weights)``, or None when fewer than 100 points find one."""
    d, j = tree.query(p, distance_upper_bound=1.5 * kernel, workers=-1)
    ok = np.isfinite(d)
    if ok.sum() < 100:
        return None
    n = normals[j[ok]]
    r = np.einsum("ij,ij->i", n, p[ok] - anchors[j[ok]])
    return ok, n, r, np.where(np.abs(r) < kernel, (1 - (r / kernel) ** 2) ** 2, 0.0)


def rigid_fit(
    ref_xyz: np.ndarray,
    ref_normals: np.ndarray,
    cmp_xyz: np.ndarray,
    *,
    kernels: tuple[float, ...] = (0.2, 0.1, 0.05),
    iterations: int = 40,
    tree: cKDTree | None = None,
    tolerance: float = 1e-5,
    plane_points: np.ndarray | None = None,
) -> np.ndarray:
    """Rigid motion (4, 4) moving ``cmp_xyz`` onto the reference surface: :func:`translation_fit`
    with the three rotations as well (Gauss-Newton on Tukey-weighted point-to-plane residuals,
    small rotations about the points' centroid, a narrowing kernel never narrower than the
    noise); all NaN when fewer than 100 points find the surface.

    Where the surfaces hold the position along the axis only weakly (a flat drift going on up
    a ramp: only the ramp's floor and roof, tilted by the grade, see a slide), a translation
    alone trades that slide for any small tilt left by the earlier stages: 0.005 degrees of
    pitch over an 80 m drift reads as 3 cm along it on a 12 % ramp. Fitted together, the flat
    stretch holds the tilt and the ramp the slide. A step stops the iterations of a kernel
    when it moves no point of the cloud's extent by more than ``tolerance``.

    ``plane_points`` (N, 3), when given, are the points the reference planes pass through
    (default: ``ref_xyz`` itself), e.g. :func:`neighbour_centroids`: a nearest point's own
    noise across the surface makes the residual jump as the points slide past each other,
    and along a weakly held direction the fit then stops where it started from (a flat
    drift going on up a ramp: 27 mm off along it fitted to 5-13 mm depending on the sample,
    to 0-5 mm on the centroids of 16 neighbours).
    """
    tree = tree if tree is not None else cKDTree(ref_xyz)
    anchor = ref_xyz if plane_points is None else plane_points
    # the points in Morton order: each iteration's nearest-neighbour query then runs about
    # four times faster than in the random order of a sample (233,000 points: 0.66 -> 0.15 s
    # on 2 cores), and the fit, a sum over the points, is the same
    cmp_xyz = cmp_xyz[morton_order(cmp_xyz)]
    centre = cmp_xyz.mean(axis=0)
    local = cmp_xyz - centre
    reach = float(np.max(np.linalg.norm(local, axis=1))) if len(local) else 0.0
    rot, t = np.eye(3), np.zeros(3)
    scale = 0.0  # no later kernel narrower than the noise (see noise_kernel)
    for stage, kernel in enumerate(kernels):
        kernel = max(kernel, scale)
        for _ in range(iterations):
            p = local @ rot.T + t
            found = _plane_residuals(tree, anchor, ref_normals, p + centre, kernel)
            if found is None:
                return np.full((4, 4), np.nan)
            ok, n, r, w = found
            # residual change for a small rotation omega about the centroid and a translation
            jac = np.hstack([np.cross(p[ok], n), n])
            a = (jac * w[:, None]).T @ jac
            step = -np.linalg.lstsq(a + 1e-9 * np.eye(6), (jac * w[:, None]).T @ r,
                                    rcond=None)[0]
            omega, shift = step[:3], step[3:]
            size = float(np.linalg.norm(shift) + np.linalg.norm(omega) * reach)
            if size > kernel / 2:
                omega, shift = omega * (kernel / 2 / size), shift * (kernel / 2 / size)
            turn = Rotation.from_rotvec(omega).as_matrix()
            rot, t = turn @ rot, turn @ t + shift
            if size < tolerance:
                break
        if stage == 0:
            scale = noise_kernel(r)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = centre + t - rot @ centre
    return out


def neighbour_centroids(xyz: np.ndarray, tree: cKDTree, k: int = 16) -> np.ndarray:
    """The centroid (N, 3) of each point's ``k`` nearest neighbours (itself included): points
    on the local surface with its noise across it averaged out, for
    :func:`rigid_fit`'s ``plane_points``."""
    centroids = np.empty_like(xyz)
    for lo in range(0, len(xyz), 200_000):  # bounded memory: (chunk, k) indices at a time
        _, nb = tree.query(xyz[lo:lo + 200_000], k=k, workers=query_workers(len(xyz)))
        centroids[lo:lo + 200_000] = xyz[nb].mean(axis=1)
    return centroids
