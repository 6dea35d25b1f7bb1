"""Registration by the tunnel centreline (paper §3.2): three views of the tunnel aligned in turn.

All stages work in the reference's principal (PCA) frame, x along the tunnel, z up, origin at the
reference centroid (survey coordinates never enter the numerics):

1. coarse (§3.2.1): the compared epoch's principal frame is put onto the reference's. PCA axes
   have no sign, so the candidate sign flips (the tunnel can point either way) are each carried
   through the whole chain and the one with the best final overlap is kept;
2. cross-section (§3.2.2): floor points are segmented, a RANSAC plane is fitted to each epoch's
   floor and the compared floor normal is rotated onto the reference's about the centre of the
   compared bounding box, then the floors are brought to the same height;
3. longitudinal (§3.2.3): least-squares lines z = a x + b through both centrelines' (x, z); the
   compared line is rotated parallel to the reference's (about the floor below its middle, so
   that the height stays set by the floors, which roof sag does not bias);
4. plan (§3.2.4): the rotation minimising the variance of nearest-point distances between the
   centrelines' xoy projections (small-angle steps), the shift along the axis from a
   cross-correlation (eq. 12, generalised in :mod:`.axial`), and the mean lateral offset; on a
   curved tunnel the shift slides the compared centreline along the reference one;
5. optional refinement (:mod:`.refine`): robust point-to-plane ICP on the stable shell.

One idea at this length: the paper's three views (cross-section, longitudinal, plan) applied in
turn, with the floor planes and the along-axis slide they need.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..curve import Centerline
from ..errors import RegistrationError
from ..spatial import plane_normals
from ..transforms import apply_transform
from .axial import (
    AxialShift,
    coarse_shift,
    curve_shift,
    fine_shift,
    rigid_fit,
)
from .metrics import rotation_error_deg

__all__ = [
    "ViewsResult",
    "align_views",
    "floor_plane",
    "rotation_between",
    "normals",
    "axial_correction",
]

logger = logging.getLogger(__name__)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking unit vector ``a`` onto unit vector ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        raise RegistrationError(
            "the floors of the two epochs face opposite ways; is one epoch upside down?"
        )
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def _about(rot: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """4 x 4 rotation about a point."""
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = centre - rot @ centre
    return m


def _translation(t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def floor_plane(
    xyz: np.ndarray,
    centerline: Centerline,
    *,
    distance: float,
    chainage_range: tuple[float, float] | None = None,
    seed: int = 0,
) -> tuple[np.ndarray, float, int]:
    """Floor plane of one epoch: seeded RANSAC refined by least squares.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Points in a frame with z roughly up, metres.
    centerline : Centerline
        The epoch's centreline in the same frame; the floor level is the median height of the
        points below it (within ~40 degrees of the downward vertical), and the floor points
        are all points within 0.2 m of that level.
    distance : float
        RANSAC inlier distance, metres.
    chainage_range : (float, float), optional
        Use only the floor between these chainages of ``centerline`` (default: all of it).

    Returns
    -------
    normal : ndarray, shape (3,)
        Unit normal pointing up.
    offset : float
        ``d`` of the plane ``normal . x + d = 0``, metres.
    inliers : int
        Number of floor points on the plane.
    """
    p = centerline.project(xyz)
    if chainage_range is not None:
        p = dataclasses.replace(
            p, inside=(p.chainage >= chainage_range[0]) & (p.chainage <= chainage_range[1])
        )
    core = p.inside & (p.vertical < 0) & (np.abs(p.lateral) < 0.8 * np.abs(p.vertical))
    level = float(np.median(p.vertical[core])) if core.sum() >= 100 else 0.0
    # the whole floor width: everything near the floor level found below the centreline
    m = p.inside & (np.abs(p.vertical - level) < 0.2) & (p.vertical < 0)
    pts = xyz[m] if core.sum() >= 100 else xyz[core]
    if pts.shape[0] < 100:
        raise RegistrationError(
            f"only {pts.shape[0]} floor points found; the cross-section alignment needs a "
            "scanned floor (check that the scan covers the floor)"
        )
    rng = np.random.default_rng(seed)
    if pts.shape[0] > 60_000:
        pts = pts[rng.choice(pts.shape[0], 60_000, replace=False)]
    n, d, idx = _ransac_plane(pts, distance, 1000, rng)
    # least-squares refits on the points near the plane (tighter each time)
    for tol in (distance, distance / 2, distance / 2):
        r = pts @ n + d
        inl = pts[np.abs(r) < tol]
        if inl.shape[0] < 50:
            break
        c = inl.mean(axis=0)
        _, _, vt = np.linalg.svd(inl - c, full_matrices=False)
        n = vt[2] / np.linalg.norm(vt[2])
        d = -float(n @ c)
    if n[2] < 0:
        n, d = -n, -d
    if n[2] < 0.7:
        raise RegistrationError(
            "the floor plane is steeper than 45 degrees; the epoch is not "
            'levelled (set registration.coarse_vertical = "pca")'
        )
    return n, d, int(len(idx))


def _ransac_plane(
    pts: np.ndarray, distance: float, iterations: int, rng: np.random.Generator
) -> tuple[np.ndarray, float, np.ndarray]:
    """Plane with the most points within ``distance``: RANSAC on ``iterations`` random triplets.

    Open3D's ``segment_plane`` is not reproducible with several threads even when seeded (its
    multi-threaded sampler, Open3D issues #5647 and #7270), so the same epochs would register
    differently from run to run; this one is vectorised numpy, seeded by ``rng``. Returns the
    unit normal, the offset ``d`` of ``n . x + d = 0`` and the inlier indices.
    """
    c = pts.mean(axis=0)
    q = pts - c
    tri = q[rng.integers(0, len(q), size=(iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    if not ok.any():
        raise RegistrationError("the floor points are collinear; no floor plane can be fitted")
    n = n[ok] / norm[ok, None]
    d = -np.einsum("ij,ij->i", n, tri[ok, 0])
    # preemptive scoring: every plane on a random subset, the best few on all points (the
    # count on all 60 000 points of each of 1000 planes was 10 % of a 60 m registration)
    if len(q) > 4 * _RANSAC_PRESCORE:
        sub = q[rng.choice(len(q), _RANSAC_PRESCORE, replace=False)]
        pre = _inlier_counts(sub, n, d, distance)
        top = np.sort(np.argsort(-pre, kind="stable")[:_RANSAC_KEEP])
        n, d = n[top], d[top]
    counts = _inlier_counts(q, n, d, distance)
    best = int(np.argmax(counts))
    normal = n[best]
    idx = np.flatnonzero(np.abs(q @ normal + d[best]) <= distance)
    return normal, float(d[best] - normal @ c), idx


def _inlier_counts(q: np.ndarray, n: np.ndarray, d: np.ndarray, distance: float) -> np.ndarray:
    """Points of ``q`` within ``distance`` of each plane ``n . x + d = 0`` (100 at a time)."""
    counts = np.empty(len(n), dtype=np.int64)
    for start in range(0, len(n), 100):
        block = np.abs(q @ n[start : start + 100].T + d[start : start + 100]) <= distance
        counts[start : start + 100] = block.sum(axis=0)
    return counts


def _line_xz(
    cl: Centerline,
    trim: float,
    chainage: np.ndarray | None = None,
    chainage_range: tuple[float, float] | None = None,
) -> tuple[float, float, np.ndarray]:
    """Least-squares line z = a x + b through the centreline (eqs. 7-10), ends trimmed, or
    only the samples whose ``chainage`` lies in ``chainage_range``."""
    m = (cl.chainage >= trim) & (cl.chainage <= cl.length - trim)
    if chainage_range is not None and chainage is not None:
        m &= (chainage >= chainage_range[0]) & (chainage <= chainage_range[1])
    p = cl.points[m] if m.sum() >= 5 else cl.points
    a, b = np.polyfit(p[:, 0], p[:, 2], 1)
    return float(a), float(b), p


def _rot_z(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _plan_rotation(
    ref_cl: Centerline, cmp_cl: Centerline, *, step_deg: float, span_deg: float = 10.0
) -> float:
    """Rotation about z (radians) minimising the variance of nearest-point distances between
    the xoy projections of the two centrelines (paper §3.2.4), by small-angle steps."""
    q = ref_cl.points[:, :2]
    tree = cKDTree(q)
    end = max(1, int(np.searchsorted(ref_cl.chainage, 0.5)))
    p = cmp_cl.points[:, :2]
    c = p.mean(axis=0)

    def variance(theta: float) -> float:
        r = _rot_z(theta)[:2, :2]
        pp = (p - c) @ r.T + c
        d, i = tree.query(pp)
        keep = (i >= end) & (i < len(q) - end)
        if keep.sum() < max(10, 0.2 * len(p)):
            return np.inf
        return float(np.var(d[keep]))

    grid = np.radians(np.arange(-span_deg, span_deg + 1e-9, 0.5))
    vals = np.array([variance(t) for t in grid])
    if not np.isfinite(vals).any():
        raise RegistrationError(
            "the two centrelines do not overlap in plan; do the epochs "
            "cover the same stretch of tunnel?"
        )
    theta = float(grid[int(np.argmin(vals))])
    best = float(vals.min())
    step = np.radians(0.25)
    while step >= np.radians(step_deg) * 0.999:
        moved = False
        for cand in (theta - step, theta + step):
            v = variance(cand)
            if v < best:
                theta, best, moved = cand, v, True
                break
        if not moved:
            step /= 2
    return theta


def _plan_motion(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The (4, 4) turn about z and plan translation best mapping ``src`` (N, 2) onto ``dst``."""
    th, t = _kabsch_2d(src, dst)
    m = np.eye(4)
    m[:3, :3] = _rot_z(th)
    m[:2, 3] = t
    return m


def _kabsch_2d(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray]:
    """Rotation angle and translation (2,) best mapping src (N, 2) onto dst (N, 2)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    h = (src - cs).T @ (dst - cd)
    theta = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
    r = _rot_z(theta)[:2, :2]
    return theta, cd - r @ cs


@dataclass
class ViewsResult:
    """The stages after the coarse alignment, in the reference's principal frame."""

    transform: np.ndarray
    stages: dict[str, np.ndarray] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    axial_uncertainty: float = float("inf")
    axial_informative: bool = False
    info: dict[str, Any] = field(default_factory=dict)


def align_views(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    ref_cl: Centerline,
    cmp_cl: Centerline,
    *,
    floor_distance: float,
    angle_step_deg: float,
    axial_search: float,
    ref_normals: np.ndarray | None = None,
    common: tuple[float, float] | None = None,
    plan_iterations: int = 2,
    axial_points: int = 60_000,
    ref_tree: cKDTree | None = None,
    curve_only: bool = False,
) -> ViewsResult:
    """Stages 2-4 of the centreline registration (paper §3.2.2-3.2.4).

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (N, 3) and (M, 3)
        Reference and coarsely aligned compared points (subsampled), reference principal frame.
    ref_cl, cmp_cl : Centerline
        Their centrelines, same frame.
    floor_distance : float
        RANSAC inlier distance of the floor plane, metres.
    angle_step_deg : float
        Smallest rotation step of the plan alignment, degrees.
    axial_search : float
        Largest along-axis shift searched, metres.
    ref_normals : ndarray, shape (N, 3), optional
        Unit normals of the reference points (computed when not given).
    common : (float, float), optional
        Chainage range of the reference centreline both epochs cover. When the compared epoch
        is already close (a second pass), the floors and the centreline lines are taken over
        this common stretch only, the compared floor being selected with the reference
        centreline, so that both planes and both lines describe the same piece of tunnel.
    axial_points : int
        Most compared points of the point-to-plane slide along the axis (a random sample);
        long tunnels want more, so that the few surfaces facing along the axis keep enough.
    ref_tree : cKDTree, optional
        A KD-tree of ``ref_xyz`` (built when not given).
    curve_only : bool
        Place the compared epoch along the axis by the curves' shapes alone
        (:func:`.axial.curve_shift`), as a second pass does where the surfaces left the
        position open in the first: over a short search their slides find a spurious local
        minimum (a featureless drift with one bend: 25 cm off, claimed +-2 mm).

    Returns
    -------
    ViewsResult
        ``transform`` (4, 4) maps the coarse compared points onto the reference.
    """
    out = ViewsResult(np.eye(4))
    total = np.eye(4)

    # --- cross-section (§3.2.2)
    t0 = time.perf_counter()
    n_ref, d_ref, _ = floor_plane(ref_xyz, ref_cl, distance=floor_distance)
    if common is None:
        n_cmp, d_cmp, _ = floor_plane(cmp_xyz, cmp_cl, distance=floor_distance)
    else:
        n_ref, d_ref, _ = floor_plane(
            ref_xyz, ref_cl, distance=floor_distance, chainage_range=common
        )
        n_cmp, d_cmp, _ = floor_plane(
            cmp_xyz, ref_cl, distance=floor_distance, chainage_range=common
        )
    lo, hi = cmp_xyz.min(axis=0), cmp_xyz.max(axis=0)
    m = _about(rotation_between(n_cmp, n_ref), (lo + hi) / 2)
    p0 = apply_transform(m, (-d_cmp * n_cmp)[None])[0]
    m = _translation(-(n_ref @ p0 + d_ref) * n_ref) @ m
    total = m @ total
    out.stages["cross_section"] = total.copy()
    out.timings["cross_section"] = time.perf_counter() - t0
    out.info["floor_tilt_deg"] = float(np.degrees(np.arccos(np.clip(n_cmp @ n_ref, -1, 1))))

    # --- longitudinal (§3.2.3)
    t0 = time.perf_counter()
    cl = cmp_cl.transformed(total)
    a_r, b_r, _ = _line_xz(ref_cl, 0.5, ref_cl.chainage, common)
    a_c, b_c, pc = _line_xz(cl, 0.5, ref_cl.project(cl.points).chainage if common else None, common)
    alpha = float(np.arctan(a_r) - np.arctan(a_c))
    ca, sa = np.cos(alpha), np.sin(alpha)
    rot = np.array([[ca, 0.0, -sa], [0.0, 1.0, 0.0], [sa, 0.0, ca]])
    # The paper rotates about the lines' intersection, which also moves the compared line's
    # height onto the reference's. Here the rotation is about the floor below the compared
    # centreline's middle instead, so the height stays where the floors put it: mid-height
    # centrelines are pulled down by roof sag and up by coal, the floor plane much less.
    xm = float(pc[:, 0].mean())
    centre = np.array([xm, 0.0, -(d_ref + n_ref[0] * xm) / n_ref[2]])
    m = _about(rot, centre)
    total = m @ total
    out.stages["longitudinal"] = total.copy()
    out.timings["longitudinal"] = time.perf_counter() - t0
    out.info["longitudinal_angle_deg"] = float(np.degrees(alpha))

    # --- plan (§3.2.4)
    t0 = time.perf_counter()
    cl = cmp_cl.transformed(total)
    theta = _plan_rotation(ref_cl, cl, step_deg=angle_step_deg)
    c = np.r_[cl.points[:, :2].mean(axis=0), 0.0]
    total = _about(_rot_z(theta), c) @ total
    ref_p = ref_cl.project(ref_xyz)
    ref_proj = (ref_p.chainage, ref_p.lateral, ref_p.vertical)

    def slide(total: np.ndarray, shift: float) -> np.ndarray:
        # move the compared centreline onto the reference one, ``shift`` further along it
        # (x shift, mean y difference and residual rotation in one 2-D least-squares fit)
        cl = cmp_cl.transformed(total)
        s = ref_cl.project(cl.points).chainage + shift
        keep = (s > 0.5) & (s < ref_cl.length - 0.5)
        if keep.sum() < 10:
            raise RegistrationError(
                "the two centrelines share less than a metre; the epochs do not overlap"
            )
        return _plan_motion(cl.points[keep, :2], ref_cl.point_at(s[keep])[:, :2]) @ total

    plan = total.copy()  # before any slide along the axis
    ref_n = ref_normals if ref_normals is not None else normals(ref_xyz)
    tree = ref_tree if ref_tree is not None else cKDTree(ref_xyz)
    shift = None
    ambiguous = True
    if not curve_only:
        moved = apply_transform(total, cmp_xyz)
        p = ref_cl.project(moved)
        coarse, spread = coarse_shift(
            ref_proj, (p.chainage, p.lateral, p.vertical), ref_cl, search=axial_search
        )
        total = slide(total, coarse)
        out.info["axial_coarse_shift"] = coarse
        out.info["axial_coarse_spread"] = spread
        for _ in range(plan_iterations):
            moved = apply_transform(total, cmp_xyz)
            pm = ref_cl.project(moved)
            tan = ref_cl.frame_at(pm.chainage)[0]
            sel = _axial_sample(pm.chainage, ref_cl.length, common, axial_points)
            shift = fine_shift(
                ref_xyz,
                ref_n,
                moved[sel],
                tan[sel],
                tree=tree,
                blocks=np.floor(pm.chainage[sel]).astype(np.int64),
            )
            total = slide(total, shift.shift)
            out.info.setdefault("axial_fine_shifts", []).append(shift.shift)
        # a featureless overlap matches equally well at many shifts: then the coarse spread,
        # not the local least-squares value, says how well the position along the axis is known
        ambiguous = spread > 1.0
        if ambiguous and shift is not None and shift.informative \
                and shift.strongest_block is not None:
            # on a long overlap one feature (a chamber in 350 m) is lost in the whole tunnel's
            # clutter; judge the match again on the stretch around the feature the fine stage
            # used
            moved = apply_transform(total, cmp_xyz)
            local_shift, local_spread = _feature_window_shift(
                ref_proj, moved, ref_cl, float(shift.strongest_block) + 0.5, axial_search
            )
            out.info["axial_feature_window"] = {
                "chainage": float(shift.strongest_block) + 0.5,
                "shift": local_shift,
                "spread": local_spread,
            }
            ambiguous = not (local_spread <= 1.0 and abs(local_shift) <= _FEATURE_AGREE)
            if not ambiguous:
                # the window confirms the position to a bin; the few points on one feature
                # make the fine stage's own figure optimistic (350 m, 2,600 points/m^2: 18 mm
                # off where it claimed +-2 mm), so claim no better than half a bin
                floor = max(float(shift.uncertainty), _FEATURE_FLOOR)
                shift = dataclasses.replace(shift, uncertainty=floor)
    # (beyond its basin the mismatch of a partial overlap is no measure: report it unknown)
    out.axial_uncertainty = (float("inf") if ambiguous or shift is None
                             else float(shift.uncertainty))
    out.axial_informative = bool(shift is not None and shift.informative and not ambiguous)
    if not out.axial_informative:
        # the surfaces left the position open; the curves' shapes may fix it (a drift that
        # bends between two straights: the section images follow the reference curve round
        # the bend and cannot see it, a rigid slide of the compared curve can)
        cl = cmp_cl.transformed(plan)
        bend = curve_shift(ref_cl, cl, search=axial_search)
        out.info["axial_curve"] = {"shift": bend.shift, "uncertainty": bend.uncertainty,
                                   "informative": bend.informative, "rms": bend.rms,
                                   "rise": bend.rise}
        if bend.informative:
            # the plan part of the rigid motion that pairs the curves at that slide (the
            # heights and tilts stay the floors' and the centrelines' lines')
            assert bend.pairs is not None
            total = _plan_motion(bend.pairs[0][:, :2], bend.pairs[1][:, :2]) @ plan
            # then a rigid motion on the surfaces themselves, which the walls round a bend
            # hold along the straights and a ramp's floor and roof along a grade change (the
            # curves carry the noise of their slices). Rotations too: a translation alone
            # trades the weak slide for the small tilt the floors and centrelines left (a flat
            # drift going on up a 12 % ramp ended 45 mm off along it, 5 mm with them)
            moved = apply_transform(total, cmp_xyz)
            pm = ref_cl.project(moved)
            sel = _axial_sample(pm.chainage, ref_cl.length, common, axial_points)
            fit = rigid_fit(ref_xyz, ref_n, moved[sel], tree=tree)
            if np.all(np.isfinite(fit)):
                sample = moved[sel]
                reach = float(np.max(np.linalg.norm(apply_transform(fit, sample) - sample,
                                                    axis=1)))
                out.info["axial_curve"]["surface_fit"] = {
                    "translation": [float(v) for v in fit[:3, 3]],
                    "angle_deg": rotation_error_deg(fit, np.eye(4)), "largest_move": reach}
                if reach <= 3.0 * bend.uncertainty:
                    total = fit @ total
            out.axial_uncertainty = bend.uncertainty
            out.axial_informative = True
            out.info.pop("axial_feature_window", None)
    out.stages["plan"] = total.copy()
    out.timings["plan"] = time.perf_counter() - t0
    out.transform = total
    return out


_AXIAL_END_MARGIN = 0.5  # m
_FEATURE_WINDOW = 10.0  # m either side of the strongest along-axis feature
_FEATURE_AGREE = 0.5  # m: the window's coarse shift must confirm the fine solution this closely
_FEATURE_FLOOR = 0.125  # m: half the coarse bin, the least along-axis uncertainty then claimed


def _feature_window_shift(
    ref_proj: tuple[np.ndarray, np.ndarray, np.ndarray],
    moved: np.ndarray,
    ref_cl: Centerline,
    centre: float,
    search: float,
) -> tuple[float, float]:
    """Coarse shift and spread (:func:`.axial.coarse_shift`) of the compared points within
    ``_FEATURE_WINDOW`` of chainage ``centre`` (already aligned, so the shift should be about
    0) against the reference around them."""
    p = ref_cl.project(moved)
    cs = np.abs(p.chainage - centre) < _FEATURE_WINDOW
    rs = np.abs(ref_proj[0] - centre) < _FEATURE_WINDOW + search
    if cs.sum() < 1000 or rs.sum() < 1000:
        return 0.0, float("inf")
    return coarse_shift(
        (ref_proj[0][rs], ref_proj[1][rs], ref_proj[2][rs]),
        (p.chainage[cs], p.lateral[cs], p.vertical[cs]),
        ref_cl,
        search=search,
    )
_AXIAL_MAX_POINTS = 60_000
_RANSAC_PRESCORE = 4_000  # floor points every RANSAC plane is first counted on
_RANSAC_KEEP = 20  # planes then counted on all the floor points


def _axial_sample(
    chainage: np.ndarray, length: float, common: tuple[float, float] | None,
    max_points: int = _AXIAL_MAX_POINTS,
) -> np.ndarray:
    """Compared points the along-axis alignment uses: a random sample of at most 60 000
    points lying over the reference, at least 0.5 m inside its ends (and inside ``common``).

    Near an end of the reference the nearest neighbours are all on one side and the normals
    are fitted to half-neighbourhoods; those correspondences pull the shift by centimetres
    (synthetic rough-rock pairs). Choosing points by their normals (those facing along the axis)
    is worse still on rough rock: at survey density most axial normal components are noise, and
    the selected points bias the shift by up to ~4 cm. A random sample keeps the estimate
    unbiased; points with no axial surface component simply carry no weight in it.
    """
    lo, hi = _AXIAL_END_MARGIN, length - _AXIAL_END_MARGIN
    if common is not None:
        lo, hi = max(lo, common[0]), min(hi, common[1])
    sel = (chainage > lo) & (chainage < hi)
    if sel.sum() < 200:
        sel = np.ones(chainage.shape[0], dtype=bool)
    idx = np.flatnonzero(sel)
    if idx.size > max_points:
        keep = np.random.default_rng(0).choice(idx, max_points, replace=False)
        sel = np.zeros(chainage.shape[0], dtype=bool)
        sel[keep] = True
    return sel


def axial_correction(
    ref_xyz: np.ndarray,
    ref_normals: np.ndarray,
    cmp_xyz: np.ndarray,
    ref_cl: Centerline,
    max_points: int = _AXIAL_MAX_POINTS,
    noise_floor: bool = True,
    *,
    tree: cKDTree | None = None,
    chainage: np.ndarray | None = None,
) -> tuple[np.ndarray, AxialShift]:
    """A last along-axis correction (4, 4) and its uncertainty, by the 1-DOF point-to-plane
    alignment of :func:`.axial.fine_shift` (compared points already in place; at most
    ``max_points`` of them, at random, are used; ``noise_floor`` as there). ``tree`` (of
    ``ref_xyz``) and ``chainage`` (of ``cmp_xyz`` on ``ref_cl``) spare repeated calls on the
    same clouds building and projecting them again."""
    s = ref_cl.project(cmp_xyz).chainage if chainage is None else chainage
    tan = ref_cl.frame_at(s)[0]
    sel = _axial_sample(s, ref_cl.length, None, max_points)
    shift = fine_shift(
        ref_xyz,
        ref_normals,
        cmp_xyz[sel],
        tan[sel],
        blocks=np.floor(s[sel]).astype(np.int64),
        noise_floor=noise_floor,
        tree=tree,
    )
    t = tan[sel].mean(axis=0)
    m = _translation(shift.shift * t / np.linalg.norm(t))
    return m, shift


def normals(xyz: np.ndarray, radius: float = 0.15) -> np.ndarray:
    """Unit normals (N, 3) of points (N, 3) from their 16 nearest neighbours within ``radius``
    m (:func:`~tunneldef.spatial.plane_normals`), unoriented."""
    return plane_normals(xyz, radius, 16)
