"""Registration of the compared epoch onto the reference (paper §3.2).

``register(ref_xyz, cmp_xyz, method="centerline")`` returns a :class:`Registration` whose
``transform`` maps compared coordinates into the reference frame. ``method`` is the paper's
centreline registration (:mod:`.views`: cross-section, longitudinal and plan views) or one of
the whole-cloud baselines
(:mod:`.baselines`: ``icp_point``, ``icp_plane``, ``gicp``, ``ndt``), all started from the same
coarse PCA alignment with its direction ambiguity resolved.

One idea at this length: the stage's driver, its steps (candidates, common stretch, shell
refinement) and the overlap checks all decide one transform; the views, the along-axis shift
and the refinement live in their own modules.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import check_points
from ..config import RegistrationConfig
from ..curve import Centerline
from ..engine import thread_map
from ..errors import NotATunnelError, RegistrationError
from ..frame import TunnelFrame, principal_frame
from ..progress import ProgressCallback, notify
from ..spatial import query_workers, random_subset
from .axial import concurrent_slides
from .baselines import BASELINES
from .metrics import (
    apply_transform,
    fitness,
    overlap_fraction,
    rotation_error_deg,
    slice_fitness,
)
from .refine import refine_stable, shell_offset
from .result import Registration
from .views import align_views, axial_correction, normals

__all__ = ["register", "Registration", "METHODS"]

logger = logging.getLogger(__name__)

METHODS = ("centerline", "icp_point", "icp_plane", "gicp", "ndt")


def _flips(vertical: str) -> list[np.ndarray]:
    """Proper sign flips of the principal axes: the tunnel pointing either way (and, without a
    known vertical, either side up)."""
    out = [np.diag([1.0, 1.0, 1.0, 1.0]), np.diag([-1.0, -1.0, 1.0, 1.0])]
    if vertical == "pca":
        out += [np.diag([1.0, -1.0, -1.0, 1.0]), np.diag([-1.0, 1.0, -1.0, 1.0])]
    return out


def register(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    ref_centerline: Centerline | None = None,
    cmp_centerline: Centerline | None = None,
    *,
    method: str = "centerline",
    settings: RegistrationConfig | None = None,
    progress: ProgressCallback | None = None,
) -> Registration:
    """Register the compared epoch onto the reference.

    Parameters
    ----------
    ref_xyz : ndarray, shape (N, 3)
        Reference epoch, metres.
    cmp_xyz : ndarray, shape (M, 3)
        Compared epoch in its own frame (any heading, a few degrees of tilt, any offset).
    method : {"centerline", "icp_point", "icp_plane", "gicp", "ndt"}
        The paper's centreline registration (§3.2) or a whole-cloud baseline started from the
        same coarse alignment.
    ref_centerline, cmp_centerline : Centerline
        Each epoch's centreline in its own frame
        (:func:`tunneldef.centerline.extract_centerline`); required by ``"centerline"``,
        unused by the baselines.
    settings : RegistrationConfig, optional
        The ``[registration]`` parameters (``method`` there is ignored: pass ``method``).
    progress : callable, optional
        ``progress(stage, fraction)``.

    Returns
    -------
    Registration

    Raises
    ------
    RegistrationError
        If an epoch has no tunnel axis, the epochs overlap too little, or do not match.
    TypeError
        If ``method="centerline"`` is asked for without both centrelines.

    Notes
    -----
    Steps: coarse PCA alignment for each sign candidate, then cross-section, longitudinal and
    plan alignment (or a baseline), the candidate with the best overlap kept
    (:func:`_best_candidate`), a second pass of the three stages over the common stretch
    (:func:`_common_stretch`), an optional robust refinement on the stable shell, applied only
    when it corrects more than the noise (:func:`_refine_on_shell`), then the checks of overlap
    and the fitness score. A featureless overlap leaves the position along the axis
    undetermined: that is logged as a warning and shows in ``axial_uncertainty`` (metres,
    large), not raised.

    References
    ----------
    Sensors 2024, 24, 2299, doi:10.3390/s24072299, §3.2.
    """
    rc = settings or RegistrationConfig()
    if method not in METHODS:
        raise RegistrationError(
            f"unknown registration method {method!r}; use one of {', '.join(METHODS)}"
        )
    if method == "centerline" and not (
        isinstance(ref_centerline, Centerline) and isinstance(cmp_centerline, Centerline)
    ):
        raise TypeError(
            "register(method='centerline') needs both epochs' Centerline "
            "(tunneldef.extract_centerline(xyz).centerline)"
        )
    ref_xyz = check_points(ref_xyz, name="reference points", min_points=100)
    cmp_xyz = check_points(cmp_xyz, name="compared points", min_points=100)
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    notify(progress, "registration", 0.0)  # its stage time starts here, not at the first view

    try:
        ref_frame = principal_frame(ref_xyz, vertical=rc.coarse_vertical)
        cmp_frame = principal_frame(cmp_xyz, vertical=rc.coarse_vertical)
    except NotATunnelError as exc:
        raise RegistrationError(f"no common tunnel axis: {exc}") from None
    f_ref, f_cmp = ref_frame.matrix, cmp_frame.matrix
    f_ref_inv = np.linalg.inv(f_ref)
    ref_l = apply_transform(f_ref, random_subset(ref_xyz, _point_budget(ref_frame, rc), 1))
    cmp_s = random_subset(cmp_xyz, _point_budget(cmp_frame, rc), 2)
    ref_tree = cKDTree(ref_l)

    ref_cl = cmp_cl = ref_n = None
    if method == "centerline":
        ref_cl = ref_centerline.transformed(f_ref)
        cmp_cl = cmp_centerline
        ref_n = normals(ref_l)
    ctx = _Context(ref_l, ref_n, ref_tree, ref_cl, cmp_cl, cmp_s, ref_frame, rc, method, progress)
    coarse, local, info, world_stages = _best_candidate(ctx, f_cmp, f_ref_inv, timings)
    axial_floor = _axial_floor(info)
    if method == "centerline":
        if rc.refine:
            local = _refine_on_shell(ctx, coarse, local, info, axial_floor, world_stages,
                                     timings, f_ref_inv)
        if info.get("axial_curve", {}).get("informative"):
            local = _curve_placed_fit(ref_xyz, ctx, coarse, local, info, world_stages,
                                      timings, f_ref_inv)
        if info.get("axial_uncertainty", 0.0) > 1.0:
            logger.warning(
                "the position along the axis is not determined: the overlap has no feature "
                "along the tunnel (equally good matches over +-%.1f m)",
                info.get("axial_coarse_spread", float("nan")),
            )
    notify(progress, "registration", 0.9)

    transform = f_ref_inv @ local @ coarse
    moved_l = apply_transform(local @ coarse, cmp_s)
    d, _ = ref_tree.query(moved_l, workers=query_workers(len(moved_l)))
    overlap = _common_overlap(d, moved_l, ref_cl, ref_l, ref_frame)
    _check_overlap(moved_l, ref_l, ref_cl, ref_frame, overlap, rc)
    fit = fitness(d)
    per_slice = slice_fitness(
        ref_l, moved_l, ref_cl if ref_cl is not None else _axis_line(ref_l), tree=ref_tree
    )
    timings["total"] = time.perf_counter() - t_all
    notify(progress, "registration", 1.0)
    axial = float(info.pop("axial_uncertainty", np.nan))
    logger.info(
        "registered (%s): fitness %.4f m, overlap %.2f, axial +-%.3f m", method, fit, overlap, axial
    )
    return Registration(
        transform, method, fit, per_slice, axial, overlap, world_stages, timings, info
    )


@dataclass(frozen=True)
class _Context:
    """What every step of :func:`register` reads: both epochs in the reference's PCA frame."""

    ref_l: np.ndarray  # reference points (subset), PCA frame
    ref_n: np.ndarray | None  # their normals (centreline method)
    ref_tree: cKDTree
    ref_cl: Centerline | None  # reference centreline, PCA frame
    cmp_cl: Centerline | None  # compared centreline, its own frame
    cmp_s: np.ndarray  # compared points (subset), its own frame
    ref_frame: TunnelFrame
    rc: RegistrationConfig
    method: str
    progress: ProgressCallback | None


def _best_candidate(
    ctx: _Context, f_cmp: np.ndarray, f_ref_inv: np.ndarray, timings: dict[str, float]
) -> tuple[np.ndarray, np.ndarray, dict[str, Any], dict[str, np.ndarray]]:
    """Coarse PCA alignment for each sign candidate, then the three views (or a baseline);
    the candidate with the best overlap. Returns ``(coarse, local, info, world_stages)``."""
    rc, method = ctx.rc, ctx.method
    flips = list(enumerate(_flips(rc.coarse_vertical)))
    if method != "centerline":
        # the baselines start from the coarse candidate a quick rough ICP likes best
        flips = [_best_flip(flips, f_cmp, ctx.ref_l, ctx.cmp_s, ctx.ref_tree)]

    def candidate(q: int, flip: np.ndarray) -> tuple:
        second: dict[str, np.ndarray] = {}  # world stages of the common-stretch pass
        coarse = flip @ f_cmp
        cmp_l = apply_transform(coarse, ctx.cmp_s)
        t0 = time.perf_counter()
        try:
            if method == "centerline":
                assert ctx.ref_cl is not None and ctx.cmp_cl is not None
                fine = align_views(
                    ctx.ref_l,
                    cmp_l,
                    ctx.ref_cl,
                    ctx.cmp_cl.transformed(coarse),
                    floor_distance=rc.floor_ransac_distance,
                    angle_step_deg=rc.plan_angle_step_deg,
                    axial_search=rc.axial_search
                    or 0.5 * (ctx.ref_cl.length + ctx.cmp_cl.length),
                    ref_normals=ctx.ref_n,
                    axial_points=_axial_points(ctx.ref_cl, rc),
                    ref_tree=ctx.ref_tree,
                )
                local, stages, info = fine.transform, fine.stages, dict(fine.info)
                info["axial_uncertainty"] = fine.axial_uncertainty
                stage_t = dict(fine.timings)
                # each direction is judged after its second pass over the common stretch: the
                # first pass's floor fit can leave the right direction 0.16 m too high (its
                # overlap within 0.1 m then reads 0.32 against 0.78 for the wrong way round)
                local = _common_stretch(ctx, coarse, local, info, _axial_floor(info), second,
                                        stage_t, f_ref_inv)
            else:
                local = BASELINES[method](ctx.ref_l, cmp_l, np.eye(4), voxel=rc.voxel)
                stages, info, stage_t = {method: local}, {}, {}
        except RegistrationError as exc:
            logger.info("direction candidate %d rejected: %s", q, exc)
            return (-1.0, np.inf, q, None, str(exc))
        moved = apply_transform(local, cmp_l)
        d, _ = ctx.ref_tree.query(moved, workers=query_workers(len(moved)))
        # ranked by the evidence of all compared points: inside the reference's stretch one
        # on the reference counts for the candidate, one off it against; outside it, none
        # either way (the epochs may cover different stretches). The share inside alone let
        # a wrong direction win on a short featureless stretch at the end of its search (a
        # 16 m pair slid 10 m: 97 % of its points inside on the reference, but a third of
        # the epoch); the share of all points let one win where the later epoch covers 7 m
        # more (1000045: 89 % inside on it against 98 %)
        score = _overlap_evidence(d, moved, ctx.ref_cl, ctx.ref_l)
        fit = fitness(d)
        stage_t[method if method != "centerline" else "fine"] = time.perf_counter() - t0
        return (score, fit, q, (coarse, local, stages, info, stage_t, second), "")

    # the direction candidates are independent: Dask's local threads run them side by side,
    # as many as the slides' memory budget allows
    slides = concurrent_slides(_axial_points(ctx.ref_cl, rc) if ctx.ref_cl is not None
                               else len(ctx.cmp_s), os.cpu_count() or 1)
    candidates = thread_map(
        candidate, flips, threads=min(len(flips), slides), stage="registration",
        progress=(None if ctx.progress is None
                  else lambda _stage, f: notify(ctx.progress, "registration", 0.5 + 0.2 * f)),
    )
    ok = [c for c in candidates if c[3] is not None]
    if not ok:
        raise RegistrationError(f"the epochs could not be registered: {candidates[0][4]}")
    ok.sort(key=lambda c: (-round(c[0], 3), c[1]))
    pick, extra = 0, {}
    if (len(ok) > 1 and _determined(ok[1]) and not _determined(ok[0])
            and ok[1][0] >= ok[0][0] - DIRECTION_POSITION_MARGIN):
        # turned end for end, a straight drift's chamber lies on the other side: its images
        # match nowhere along the drift and that way round is left undetermined, yet it may
        # overlap the reference a little more (a later survey 8 m longer: 0.861 against
        # 0.849, and the run was refused where the other way round registered exactly). The
        # way round whose features fix its position is the survey's.
        pick = 1
        extra = {"direction_by_position": True}
        logger.info("the way round whose position along the tunnel its features fix is kept "
                    "(overlap evidence %.3f against %.3f)", ok[1][0], ok[0][0])
    elif (len(ok) > 1 and ok[1][0] > ok[0][0] - 0.01
            and abs(ok[1][1] - ok[0][1]) < 0.1 * ok[0][1]
            and _apart(ok[0][3], ok[1][3], ctx.cmp_s) > _SAME_POSE):
        # the tunnel looks the same both ways round (a flat drift going on up a ramp, turned
        # end for end and tipped by the grade, lies on itself): with levelled scans the way
        # round that tips the compared epoch least is the survey's; otherwise it is open
        tilts = [tilt_deg(f_ref_inv @ c[3][1] @ c[3][0]) for c in ok[:2]]
        gap = abs(tilts[1] - tilts[0]) if rc.coarse_vertical == "world" else 0.0
        extra = {"direction_tilt_gap_deg": gap}
        if gap > DIRECTION_TILT_GAP_DEG:
            pick = int(tilts[1] < tilts[0])
            logger.info("the tunnel fits both ways round; the way that tips the compared "
                        "epoch least (%.2f against %.2f degrees) is kept", min(tilts),
                        max(tilts))
        else:
            logger.warning("the tunnel looks the same both ways round; the direction is "
                           "ambiguous")
            extra["direction_ambiguous"] = True
        extra["direction_tilts_deg"] = [tilts[pick], tilts[1 - pick]]
    score, fit, q, (coarse, local, stages, info, stage_t, second), _ = ok[pick]
    info["direction_candidates"] = [
        {"flip": c[2], "overlap": c[0], "fitness": c[1]} for c in candidates
    ]
    info.update(extra)
    timings.update(stage_t)
    world_stages = {"coarse": f_ref_inv @ coarse}
    for name, m in stages.items():
        world_stages[name] = f_ref_inv @ m @ coarse
    world_stages.update(second)
    return coarse, local, info, world_stages


#: with levelled scans (``coarse_vertical = "world"``), two ways round that fit alike are told
#: apart when one tips the compared epoch's vertical by more than this, degrees, beyond the
#: other (a 12 % ramp: 6.8 degrees)
DIRECTION_TILT_GAP_DEG = 1.0


#: two direction candidates that end this close (largest move of a compared point, m) are one
#: pose: the views turned one of them round
_SAME_POSE = 0.5

#: a direction candidate whose position along the axis is determined is kept over one whose
#: position is not when its overlap evidence trails by at most this
DIRECTION_POSITION_MARGIN = 0.05


def _determined(candidate: tuple) -> bool:
    """Whether a direction candidate's position along the axis is fixed (its uncertainty
    finite and at most a metre, the limit beyond which :func:`register` calls it open)."""
    u = float(candidate[3][3].get("axial_uncertainty", np.inf))
    return bool(np.isfinite(u) and u <= 1.0)


def _apart(a: tuple, b: tuple, cmp_xyz: np.ndarray) -> float:
    """Largest distance between where two candidates (``(coarse, local, ...)``) put the same
    compared points, metres."""
    pts = cmp_xyz[:: max(1, len(cmp_xyz) // 2000)]
    moved = [apply_transform(c[1] @ c[0], pts) for c in (a, b)]
    return float(np.max(np.linalg.norm(moved[0] - moved[1], axis=1)))


def tilt_deg(transform: np.ndarray) -> float:
    """Angle between the vertical and the vertical turned by ``transform``, degrees."""
    return float(np.degrees(np.arccos(np.clip(transform[2, 2], -1.0, 1.0))))


def _axial_floor(info: dict[str, Any]) -> float:
    """A position the first pass could confirm only around one feature (a long overlap) is
    known to half a coarse bin at best, and one that only the curves' shapes fixed (a bend
    between straights, smooth rock) to the curves' own figure, whatever the later local fits
    claim: their point-to-plane slides on walls parallel to the axis see noise."""
    if "axial_feature_window" in info:
        return float(info.get("axial_uncertainty", 0.0))
    bend = info.get("axial_curve")
    if bend is not None and bend.get("informative"):
        return float(bend["uncertainty"])
    return 0.0


def _common_stretch(
    ctx: _Context,
    coarse: np.ndarray,
    local: np.ndarray,
    info: dict[str, Any],
    axial_floor: float,
    world_stages: dict[str, np.ndarray],
    timings: dict[str, float],
    f_ref_inv: np.ndarray,
) -> np.ndarray:
    """Second pass of the three views over the stretch both epochs cover, from where the
    first pass left off; returns the updated local transform."""
    assert ctx.ref_cl is not None and ctx.cmp_cl is not None
    t0 = time.perf_counter()
    cmp_l = apply_transform(local @ coarse, ctx.cmp_s)
    s = ctx.ref_cl.project(cmp_l[:: max(1, len(cmp_l) // 20000)]).chainage
    common = (
        max(0.0, float(np.percentile(s, 1))),
        min(ctx.ref_cl.length, float(np.percentile(s, 99))),
    )
    if common[1] - common[0] > 1.0:
        fine = align_views(
            ctx.ref_l,
            cmp_l,
            ctx.ref_cl,
            ctx.cmp_cl.transformed(local @ coarse),
            floor_distance=ctx.rc.floor_ransac_distance,
            angle_step_deg=ctx.rc.plan_angle_step_deg,
            axial_search=1.0,
            ref_normals=ctx.ref_n,
            common=common,
            axial_points=_axial_points(ctx.ref_cl, ctx.rc),
            ref_tree=ctx.ref_tree,
            # where the surfaces left the position open and the curves' shapes fixed it, the
            # surfaces' slides over a short search are no evidence either
            curve_only=bool(info.get("axial_curve", {}).get("informative")),
        )
        local = fine.transform @ local
        world_stages["common_stretch"] = f_ref_inv @ local @ coarse
        if info.get("axial_uncertainty", np.inf) < 1.0:
            info["axial_uncertainty"] = max(fine.axial_uncertainty, axial_floor)
    timings["common_stretch"] = time.perf_counter() - t0
    return local


def _refine_on_shell(
    ctx: _Context,
    coarse: np.ndarray,
    local: np.ndarray,
    info: dict[str, Any],
    axial_floor: float,
    world_stages: dict[str, np.ndarray],
    timings: dict[str, float],
    f_ref_inv: np.ndarray,
) -> np.ndarray:
    """Robust point-to-plane refinement on the stable shell, kept only when it corrects more
    than the noise (``refine_keep``: by thresholds, or by :func:`shell_offset`); returns the
    (possibly) updated local transform. The shell offsets before and after are reported
    either way."""
    ref_cl, rc = ctx.ref_cl, ctx.rc
    assert ref_cl is not None and ctx.ref_n is not None
    t0 = time.perf_counter()
    cmp_l = apply_transform(local @ coarse, ctx.cmp_s)
    corr = refine_stable(ctx.ref_l, cmp_l, ref_cl, voxel=rc.voxel)
    cmp_r = apply_transform(corr, cmp_l)
    # the shell ICP holds the axis position loosely: put it back where the features say
    # (not where only the curves' shapes placed it: the slide along the local axis direction
    # sees no bend, and read 21 mm on a bent drift registered 0.8 mm off; the rigid ICP holds
    # a bend)
    if info.get("axial_uncertainty", np.inf) < 1.0 \
            and not info.get("axial_curve", {}).get("informative"):
        ax, shift = axial_correction(ctx.ref_l, ctx.ref_n, cmp_r, ref_cl)
        if shift.informative:
            corr = ax @ corr
            info["refine_axial_uncertainty"] = shift.uncertainty
    angle = rotation_error_deg(corr, np.eye(4))
    # (the slide along the axis is left out: on a featureless stretch it is noise)
    delta = apply_transform(corr, cmp_l) - cmp_l
    tan = ref_cl.frame_at(ref_cl.project(cmp_l).chainage)[0]
    delta -= np.einsum("ij,ij->i", delta, tan)[:, None] * tan
    move = float(np.sqrt(np.mean(np.einsum("ij,ij->i", delta, delta))))
    sub = cmp_l[:: max(1, len(cmp_l) // 200_000)]
    test = shell_offset(
        ctx.ref_l, ctx.ref_n, ctx.ref_tree, ref_cl, [sub, apply_transform(corr, sub)]
    )
    before, after = test.scores
    # 'thresholds': a correction within the noise would only move the epoch towards its
    # deformed parts, so it is kept only when the centreline stages were measurably off;
    # 'offset': kept when the stable shell's cells ask for the move (their offsets before it,
    # cell by cell, are at least half the move, beyond the cell medians' noise: the ICP also
    # pulls towards deformed parts, which the trimmed cell medians do not ask for), refused
    # when they ask for less than half of it, judged by the thresholds where they cannot tell
    by_thresholds = angle > rc.refine_min_angle_deg or move > rc.refine_min_shift
    verdict = test.verdict(rc.refine_offset_z)
    if rc.refine_keep == "offset" and verdict != "undecided":
        applied, rule = verdict == "asked", "offset"
    else:
        applied, rule = by_thresholds, "thresholds"
    info["refine"] = {"angle_deg": angle, "shift_m": move, "applied": bool(applied),
                      "offset_before_m": before, "offset_after_m": after,
                      "offset_share": test.share, "offset_share_se": test.share_se,
                      "offset_cells": test.cells, "rule": rule}
    if applied:
        local = corr @ local
        if "refine_axial_uncertainty" in info:
            info["axial_uncertainty"] = max(info["refine_axial_uncertainty"], axial_floor)
    info.pop("refine_axial_uncertainty", None)
    world_stages["refine"] = f_ref_inv @ local @ coarse
    timings["refine"] = time.perf_counter() - t0
    return local


def _curve_placed_fit(
    ref_xyz: np.ndarray,
    ctx: _Context,
    coarse: np.ndarray,
    local: np.ndarray,
    info: dict[str, Any],
    world_stages: dict[str, np.ndarray],
    timings: dict[str, float],
    f_ref_inv: np.ndarray,
) -> np.ndarray:
    """The last stage of a registration whose position along the axis the curves' shapes
    gave (:func:`~.axial.curve_shift`): a rigid point-to-plane fit (:func:`~.axial.rigid_fit`)
    on a reference as dense as its check's (:func:`~.verify.verify_network`, at least 400 000
    points), kept when it moves no compared point by more than 3 x the curves' uncertainty.

    The surfaces hold such a position only weakly (a bend's walls, a ramp's floor and roof);
    on the registration's own sparser subset the slide read by the nearest neighbours is
    biased towards where it starts, and more so the noisier the planes' points (a flat drift
    going on up a 12 % ramp: 29 mm off after the plan view's fit on 180 000 points; fitted
    again on 400 000, 13 mm off, and on the centroids of their neighbours, 0-5 mm)."""
    from .axial import neighbour_centroids, rigid_fit
    from .views import _AXIAL_MAX_POINTS, _axial_sample

    ref_cl, rc = ctx.ref_cl, ctx.rc
    assert ref_cl is not None
    t0 = time.perf_counter()
    n = max(400_000, int(2 * rc.max_points_per_metre * ref_cl.length))
    ref_d = apply_transform(ctx.ref_frame.matrix, random_subset(ref_xyz, n, 11))
    tree = cKDTree(ref_d)
    moved = apply_transform(local @ coarse, ctx.cmp_s)
    sel = _axial_sample(ref_cl.project(moved).chainage, ref_cl.length, None,
                        _AXIAL_MAX_POINTS)
    fit = rigid_fit(ref_d, normals(ref_d), moved[sel], tree=tree,
                    plane_points=neighbour_centroids(ref_d, tree))
    limit = 3.0 * float(info["axial_curve"]["uncertainty"])
    rec: dict[str, Any] = {"applied": False, "limit": limit}
    if np.all(np.isfinite(fit)):
        sample = moved[sel]
        reach = float(np.max(np.linalg.norm(apply_transform(fit, sample) - sample, axis=1)))
        rec.update(translation=[float(v) for v in fit[:3, 3]],
                   angle_deg=rotation_error_deg(fit, np.eye(4)), largest_move=reach,
                   applied=reach <= limit)
        if reach <= limit:
            local = fit @ local
    info["curve_placed_fit"] = rec
    world_stages["curve_placed_fit"] = f_ref_inv @ local @ coarse
    timings["curve_placed_fit"] = time.perf_counter() - t0
    return local


def _axial_points(ref_cl: Centerline, rc: RegistrationConfig) -> int:
    """Compared points of the slide along the axis: 60 000, or ``max_points_per_metre`` of
    the reference centreline for long tunnels (350 m with one chamber: 60 000 left its end
    walls a few dozen points and the registration 11 mm off along the axis)."""
    return max(60_000, int(rc.max_points_per_metre * ref_cl.length))


def _point_budget(frame: TunnelFrame, rc: RegistrationConfig) -> int:
    """Points of an epoch the stages use: ``max_points``, or more for long tunnels
    (``max_points_per_metre`` times the length, estimated as sqrt(12 var) along the axis), so
    that the unrolled section images keep enough points per cell to find the along-axis shift."""
    length = float(np.sqrt(12.0 * frame.variances[0]))
    return max(int(rc.max_points), int(rc.max_points_per_metre * length))


def _best_flip(
    flips: list[tuple[int, np.ndarray]],
    f_cmp: np.ndarray,
    ref_l: np.ndarray,
    cmp_s: np.ndarray,
    ref_tree: cKDTree,
) -> tuple[int, np.ndarray]:
    """The direction candidate with the best overlap after a rough point-to-plane ICP."""
    best, best_score = flips[0], -1.0
    for q, flip in flips:
        coarse = flip @ f_cmp
        cmp_l = apply_transform(coarse, cmp_s)
        m = BASELINES["icp_plane"](
            ref_l, cmp_l, np.eye(4), voxel=0.25, max_distance=1.0, iterations=15
        )
        d, _ = ref_tree.query(apply_transform(m, cmp_l[:: max(1, len(cmp_l) // 20000)]))
        score = overlap_fraction(d, radius=0.15)
        if score > best_score:
            best, best_score = (q, flip), score
    return best


def _axis_line(ref_l: np.ndarray) -> Centerline:
    """The x axis of the reference's principal frame over its extent (for slicing)."""
    x0, x1 = float(ref_l[:, 0].min()), float(ref_l[:, 0].max())
    return Centerline.from_polyline(np.array([[x0, 0.0, 0.0], [x1, 0.0, 0.0]]), step=0.1)


def _common_overlap(
    d: np.ndarray, moved: np.ndarray, ref_cl: Centerline | None, ref_l: np.ndarray, frame: Any
) -> float:
    """Fraction of compared points within the reference's stretch that lie within 0.1 m."""
    cl = ref_cl if ref_cl is not None else _axis_line(ref_l)
    s = cl.project(moved).chainage
    inside = (s >= 0) & (s <= cl.length)
    if inside.sum() < 100:
        return 0.0
    return overlap_fraction(d[inside], radius=0.1)


def _overlap_evidence(
    d: np.ndarray, moved: np.ndarray, ref_cl: Centerline | None, ref_l: np.ndarray
) -> float:
    """``(on - off) / all`` over the compared points inside the reference's stretch: ``on``
    within 0.1 m of the reference, ``off`` farther (points outside the stretch count neither
    way)."""
    cl = ref_cl if ref_cl is not None else _axis_line(ref_l)
    s = cl.project(moved).chainage
    inside = (s >= 0) & (s <= cl.length)
    on = int(np.sum(inside & (d <= 0.1)))
    return (2 * on - int(inside.sum())) / max(len(d), 1)


def _check_overlap(
    moved: np.ndarray,
    ref_l: np.ndarray,
    ref_cl: Centerline | None,
    frame: Any,
    overlap: float,
    rc: Any,
) -> None:
    cl = ref_cl if ref_cl is not None else _axis_line(ref_l)
    s = cl.project(moved).chainage
    inside = (s >= 0) & (s <= cl.length)
    common = 0.0
    if inside.sum() >= 100:
        common = float(np.percentile(s[inside], 99) - np.percentile(s[inside], 1))
    span = float(np.percentile(s, 99) - np.percentile(s, 1))
    need = max(rc.min_overlap_length, 0.2 * min(span, cl.length))
    if common < need:
        raise RegistrationError(
            f"the epochs share only {common:.1f} m of tunnel (at least {need:.1f} m needed); "
            "scan an overlapping stretch"
        )
    if overlap < rc.min_overlap:
        raise RegistrationError(
            f"after registration only {overlap:.0%} of the compared points lie on the "
            f"reference (at least {rc.min_overlap:.0%} needed); the epochs do not show the "
            "same tunnel"
        )
