"""Per-point deformation of a registered compared epoch against the reference (paper §3.3).

:func:`compute_deformation` runs the paper's KNN centroid (:mod:`.knn`) or the local-surface
estimator (:mod:`.local_surface`, beyond the paper), after cutting the shell from clutter
(:mod:`.shell`), and splits the change into horizontal and vertical parts (§3.3.2).

One idea at this length: the stage's dispatch between the two estimators and what both share
(shell cuts, whole-cloud grids, the pass for points the classifier left out, coverage,
horizontal/vertical split).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import fields as dataclass_fields
from typing import TYPE_CHECKING

import numpy as np

from ..cloud import check_points
from ..config import DeformationConfig
from ..curve import Centerline, Projection
from ..errors import ConfigError, InvalidCloudError
from ..progress import ProgressCallback, notify, scaled, timed_stage
from ..spatial import unique_rows
from . import shell as shell_module
from .knn import counterpart_projection, knn_counterparts, manhattan_split
from .result import DeformationResult
from .sections import surface_labels

if TYPE_CHECKING:
    from .local_surface import CylinderPass, RobustDeformation

__all__ = ["compute_deformation", "common_masks", "global_inputs", "METHODS"]

logger = logging.getLogger(__name__)

METHODS = ("knn", "robust")


def _envelope(
    xyz: np.ndarray, centerline: Centerline, workers: int, projection: Projection | None = None
) -> tuple[Projection, shell_module.ShellEnvelope, np.ndarray, np.ndarray]:
    """Projection of the points, their shell's envelope and their offsets from it."""
    proj = centerline.project(xyz, workers=workers) if projection is None else projection
    env, off, obl = shell_module.shell_envelope(xyz, centerline, projection=proj, workers=workers)
    return proj, env, off, obl


_COVERAGE_SAMPLE = 200_000
_COVERAGE_QUANTILE = 0.0005


def global_inputs(
    ref: np.ndarray, cmp: np.ndarray, settings: DeformationConfig
) -> dict[str, object]:
    """The local-surface estimator's inputs that must come from the whole clouds.

    The local origin (the reference's centroid), the corner of the core voxel grid (the compared
    points' minimum corner) and the corner of the normals' voxel grid (below both clouds by the
    normal radius and two core spacings). Data of both estimator passes
    (:func:`compute_deformation`) and of every tile (:mod:`tunneldef.tiles`) lie inside them,
    so each gets the same voxels.
    """
    origin = ref.mean(axis=0)
    # min(x - o) is min(x) - o exactly (rounding is monotonic): no shifted copy of the clouds
    lo_cmp = cmp.min(axis=0) - origin
    lo = np.minimum(ref.min(axis=0) - origin, lo_cmp)
    corner = lo - (settings.normal_radius + 2.0 * settings.core_spacing)
    return {"origin": origin, "core_anchor": lo_cmp, "normal_corner": corner}


def common_masks(
    ref_env: shell_module.ShellEnvelope,
    ref_pp: Projection,
    ref_off: np.ndarray,
    ref_obl: np.ndarray,
    cmp_env: shell_module.ShellEnvelope,
    cmp_pp: Projection,
    cmp_off: np.ndarray,
    cmp_obl: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Shell masks of both epochs cut at one level: the inner of the two envelopes once their
    local difference (the motion) is taken out (see :func:`compute_deformation`, Notes).

    Returns the reference's and the compared epoch's masks, each shape (N,) of bool.
    """
    with ThreadPoolExecutor(max_workers=1) as pool:
        other_job = pool.submit(cmp_env.matched_offset, ref_pp, ref_off)
        cmp_other = ref_env.matched_offset(cmp_pp, cmp_off)
        ref_other = other_job.result()
    ref_mask = shell_module.shell_mask(ref_off, ref_obl, other=ref_other)
    cmp_mask = shell_module.shell_mask(cmp_off, cmp_obl, other=cmp_other)
    return ref_mask, cmp_mask


def _coverage(
    ref: np.ndarray, centerline: Centerline, workers: int, chainage: np.ndarray | None = None
) -> tuple[float, float]:
    """Chainage range covered by the reference points (a subsample; outliers ignored);
    ``chainage`` is the reference points' chainage when it is already known."""
    step = max(ref.shape[0] // _COVERAGE_SAMPLE, 1)
    if chainage is None:
        s = centerline.project(ref[::step], workers=workers).chainage
    else:
        s = chainage[::step]
    lo, hi = np.quantile(s, [_COVERAGE_QUANTILE, 1.0 - _COVERAGE_QUANTILE])
    return float(lo), float(hi)


def _knn_deformation(
    ref: np.ndarray,
    cmp: np.ndarray,
    centerline: Centerline,
    pp: Projection,
    *,
    k: int,
    workers: int,
    progress: ProgressCallback | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The paper's KNN-centroid deformation (§3.3.1) and its Manhattan split (§3.3.2).

    Returns signed deformation, horizontal, vertical and the unsigned distance, each (N,).
    """
    counterpart, dist = knn_counterparts(ref, cmp, k=k, workers=workers, progress=progress)
    pc = counterpart_projection(centerline, cmp, pp, counterpart)
    horizontal, vertical = manhattan_split(pp, pc)
    sign = np.where(horizontal + vertical < 0.0, -1.0, 1.0)
    return sign * dist, horizontal, vertical, dist


def _robust_kwargs(cfg: object) -> dict[str, object]:
    """Robust-estimator parameters present in the deformation config section."""
    names = ("normal_radius", "cylinder_radius", "max_depth", "core_spacing", "pool")
    return {n: getattr(cfg, n) for n in names if hasattr(cfg, n)}


_PROBE_RADIUS = 0.06  # m: radius of the ray behind a surface in which rock is looked for
_PROBE_START = 0.12  # m: the ray starts this far behind the surface (8 sigma of its noise)
_PROBE_MIN_POINTS = 2  # points on the ray that make a surface an object in front (8 noise sigma
# behind a shell surface there is nothing; shadows behind objects thin out what is there)


_PASS2_CELL = 0.6  # m: points farther than one such voxel from every point to measure in the
# second pass (cylinders up to 0.4 m wide and 0.3 m deep, normals over 0.3 m) play no part


def _near(points: np.ndarray, centres: np.ndarray, cell: float) -> np.ndarray:
    """Points in the voxels (edge ``cell``) holding a centre, or next to one (a coarse test
    that keeps every point within ``cell`` of a centre)."""
    if len(centres) == 0:
        return np.zeros(len(points), dtype=bool)
    lo = centres.min(axis=0) - 2.0 * cell

    def keys(ijk: np.ndarray) -> np.ndarray:
        return (ijk[:, 0] * 1_000_003 + ijk[:, 1]) * 1_000_033 + ijk[:, 2]

    ijk = unique_rows(np.floor((centres - lo) / cell).astype(np.int64))[0]
    steps = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    around = np.unique(keys((ijk[:, None, :] + steps[None]).reshape(-1, 3)))
    pk = keys(np.floor((points - lo) / cell).astype(np.int64))
    pos = np.clip(np.searchsorted(around, pk), 0, len(around) - 1)
    return around[pos] == pk


_TWO_SURFACE_SIGMAS = 3.0  # a change at least this many noise sigmas is tested (below, the
# two windows overlap and one surface's own noise fills the other's)
_TWO_SURFACE_WINDOW = 1.5  # noise sigmas: half-width of the window about each surface
_TWO_SURFACE_SHARE = 0.3  # an epoch shows both surfaces when the other surface's window holds
_TWO_SURFACE_MIN = 5  # at least this share of its own surface's points, and this many


def two_surfaces(
    ref: np.ndarray, cmp: np.ndarray, candidates: np.ndarray, deformation: np.ndarray,
    normal: np.ndarray, sigma: float, radius: float,
) -> np.ndarray:
    """Which measured changes one of the epochs contradicts by showing both surfaces.

    A real change leaves one surface in each epoch, ``d`` apart along the normal. Where one
    epoch shows both (a SLAM map whose second pass over a stretch did not close onto the
    first: the wall twice, centimetres apart; a lining or mesh in front of rock that moved
    behind it), the shell classifier keeps the outer one and the change between the
    surfaces reads as a clean, confident deformation that did not happen: a double wall
    8 cm apart read +74 mm with a LoD95 of 8 mm and raised a danger zone 10 m long.

    For each candidate compared point (on its surface, value ``d``, unit normal ``n``), the
    points of each epoch within ``radius`` of the normal line through it are counted in two
    windows of half-width ``1.5 sigma`` along it: about the compared surface (the mean
    offset of the compared points nearer to the point than ``|d| / 2``) and about the
    reference surface (``d`` behind it). The compared epoch shows both when the reference
    window holds at least 30 % as many of its points (and 5) as its own; the reference epoch
    likewise. Changes under 3 sigma are not tested (the windows overlap).

    Parameters
    ----------
    ref, cmp : ndarray, shape (M, 3), (N, 3)
        All points of both epochs (shell or not), registered, metres.
    candidates : ndarray of bool, shape (N,)
        Compared points to test (measured values).
    deformation : ndarray, shape (N,)
        Their signed change along ``normal``, metres.
    normal : ndarray, shape (N, 3)
        Unit normals of the compared surface at the points.
    sigma : float
        The scans' noise across a surface (the cylinders' typical spread), metres.
    radius : float
        Radius of the cylinder about the normal line, metres.

    Returns
    -------
    ndarray of bool, shape (N,)
        True where an epoch shows both surfaces of the change.
    """
    from .cylinders import _RadiusIndex

    out = np.zeros(len(cmp), dtype=bool)
    d_all = np.where(candidates, deformation, np.nan)
    with np.errstate(invalid="ignore"):
        test = np.flatnonzero(np.abs(d_all) >= _TWO_SURFACE_SIGMAS * sigma)
    if len(test) == 0 or not np.isfinite(sigma) or sigma <= 0:
        return out
    w = _TWO_SURFACE_WINDOW * sigma
    d = deformation[test]
    reach = float(np.hypot(radius, np.max(np.abs(d)) + w))
    centres = cmp[test]
    origin = centres.min(axis=0)
    n = normal[test]
    indexes = []
    for pts in (cmp, ref):
        near = pts[_near(pts, centres, reach)]
        indexes.append((near, _RadiusIndex(near - origin, reach)))
    # a chunk of points at a time: a survey-wide change (or a wrong registration, which its
    # own check refuses) may make most points candidates, each with about a thousand
    # neighbours at the handheld scanner's density
    for a in range(0, len(test), _TWO_SURFACE_CHUNK):
        part = slice(a, a + _TWO_SURFACE_CHUNK)
        out[test[part]] = _both_surfaces(indexes, centres[part], origin, n[part], d[part],
                                         w, radius, reach)
    return out


_TWO_SURFACE_CHUNK = 4_000


def _both_surfaces(indexes, centres, origin, n, d, w, radius, reach) -> np.ndarray:
    """:func:`two_surfaces` for one chunk of points (``indexes``: each epoch's points near
    them and their radius index, compared first)."""
    offsets = []
    for near, index in indexes:
        group, idx, d2 = index.ball(centres - origin, reach)
        rel = (near[idx] - centres[group]).astype(np.float64)
        off = np.einsum("ij,ij->i", rel, n[group])
        inside = d2.astype(np.float64) - off**2 <= radius**2
        offsets.append((group[inside], off[inside]))
    # the compared surface's own offset from the (noisy) point: the mean of its points
    # nearer to it than to the reference surface
    m = len(centres)
    g, off = offsets[0]
    mine = np.abs(off) < 0.5 * np.abs(d[g])
    m0 = np.bincount(g[mine], weights=off[mine], minlength=m) / np.maximum(
        np.bincount(g[mine], minlength=m), 1)
    counts = []
    for g, off in offsets:
        at_cmp = np.abs(off - m0[g]) <= w
        at_ref = np.abs(off - (m0[g] - d[g])) <= w
        counts.append((np.bincount(g[at_cmp], minlength=m), np.bincount(g[at_ref], minlength=m)))
    (c_here, c_there), (r_here, r_there) = counts
    both_cmp = c_there >= np.maximum(_TWO_SURFACE_MIN, _TWO_SURFACE_SHARE * c_here)
    both_ref = r_here >= np.maximum(_TWO_SURFACE_MIN, _TWO_SURFACE_SHARE * r_there)
    return both_cmp | both_ref


def _spread_ratio(r: RobustDeformation, shell: np.ndarray) -> np.ndarray:
    """Per compared point of the measured shell, its compared cylinder's spread over its
    reference cylinder's (float16, a ratio needs no more and a kilometre's survey holds 55 M
    of them; NaN elsewhere).

    A map that holds a surface twice closer than the noise can separate (a SLAM pass 2-4 cm
    off the other) shows no second surface, only a thicker one: at +-1.5 cm noise a wall
    held twice 3 cm apart reads a spread 1.2-1.35 times the other epoch's, and its values there
    drift by up to half the offset with a LoD95 that widens only where a cylinder passes
    the roughness gate. The ratio is about 1 wherever both epochs see one surface alike (it
    is not taken over the typical spreads: a map held twice throughout would raise those)."""
    out = np.full(len(shell), np.nan, dtype=np.float16)
    sr = np.asarray(r.sigma_ref, dtype=np.float64)
    sc = np.asarray(r.sigma_cmp, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = sc / sr
    use = shell & np.isfinite(np.asarray(r.deformation)) & np.isfinite(ratio) & (sr > 0)
    out[use] = ratio[use]
    return out


_AMBIGUOUS_COS = 0.5  # |normal . radial| below this: the outward side of a surface is unsure


def _ray_counts(index, local: np.ndarray, c: np.ndarray, n: np.ndarray, reach: float) -> np.ndarray:
    """Points of ``local`` (indexed by ``index``, a :class:`.cylinders._RadiusIndex` built with
    radius ``1.5 * _PROBE_RADIUS``) on a thin ray (radius ``_PROBE_RADIUS``) from
    ``_PROBE_START`` to ``reach`` metres along each direction ``n`` (C, 3) from each position
    ``c`` (C, 3), in the same local frame."""
    if len(c) == 0:
        return np.zeros(0, dtype=np.int64)
    ball = 1.5 * _PROBE_RADIUS  # balls along the ray, spaced to cover it
    steps = np.arange(_PROBE_START, reach + ball, ball)
    probes = (c[:, None, :] + steps[None, :, None] * n[:, None, :]).reshape(-1, 3)
    group, idx, _ = index.ball(probes, ball)
    core = group // len(steps)
    rel = local[idx] - c[core]
    along = np.einsum("ij,ij->i", rel, n[core])
    across2 = np.einsum("ij,ij->i", rel, rel) - along**2
    on_ray = (along >= _PROBE_START) & (along <= reach) & (across2 <= _PROBE_RADIUS**2)
    # a point can sit in two neighbouring balls: count it once per ray
    key = np.unique(core[on_ray].astype(np.int64) * (len(local) + 1) + idx[on_ray])
    return np.bincount(key // (len(local) + 1), minlength=len(c))


def _stands_off(
    ref: np.ndarray,
    centerline: Centerline,
    cores: np.ndarray,
    normals: np.ndarray,
    point_core: np.ndarray,
    reach: float,
) -> np.ndarray:
    """Whether each point's core surface stands in front of other points ``ref`` (both epochs).

    Points are looked for on a thin ray behind each core along its outward normal
    (:func:`_ray_counts`, up to ``reach``): a pipe, the conveyor, a coal load or a person has
    the rock (or the floor) behind it, the shell has nothing (also not in a corner, where a
    ball behind a tilted normal would touch the other wall). Where the normal is nearly
    across the ray from the centreline (``|n . radial| < _AMBIGUOUS_COS``: the roof and floor
    of a side chamber, the belt, the top of a pipe), which side is outward is unsure: the
    surface stands off only with points on both sides within twice ``reach`` (a chamber's
    roof has its floor on one side and rock on the other; the belt has the floor below and
    the roof above). ``point_core`` is each point's core (-1: none, False).
    """
    out = np.zeros(point_core.shape[0], dtype=bool)
    ok = point_core >= 0
    if not ok.any() or len(cores) == 0:
        return out
    used = np.unique(point_core[ok])
    c, n = cores[used], normals[used]
    proj = centerline.project(c)
    _, lat, ver = centerline.frame_at(proj.chainage)
    radial = proj.lateral[:, None] * lat + proj.vertical[:, None] * ver
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12)
    unsure = np.abs(np.einsum("ij,ij->i", n, radial)) < _AMBIGUOUS_COS
    from .cylinders import _RadiusIndex

    origin = c.mean(axis=0)
    c = c - origin
    far = 2.0 * reach
    margin = far + 2.0 * _PROBE_RADIUS
    local = ref - origin
    local = local[np.all((local >= c.min(axis=0) - margin) & (local <= c.max(axis=0) + margin), 1)]
    index = _RadiusIndex(local, 1.5 * _PROBE_RADIUS)
    behind = np.zeros(len(used), dtype=bool)
    sure = ~unsure
    behind[sure] = _ray_counts(index, local, c[sure], n[sure], reach) >= _PROBE_MIN_POINTS
    if unsure.any():
        both = _ray_counts(index, local, c[unsure], n[unsure], far) >= _PROBE_MIN_POINTS
        both &= _ray_counts(index, local, c[unsure], -n[unsure], far) >= _PROBE_MIN_POINTS
        behind[unsure] = both
    stand = np.zeros(len(cores), dtype=bool)
    stand[used] = behind
    out[ok] = stand[point_core[ok]]
    return out


def compute_deformation(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    centerline: Centerline,
    *,
    settings: DeformationConfig | None = None,
    shell: np.ndarray | None = None,
    projection: Projection | None = None,
    registration_sigma: float = 0.0,
    workers: int = -1,
    progress: ProgressCallback | None = None,
    coverage: tuple[float, float] | None = None,
    robust_inputs: dict[str, object] | None = None,
    masks: tuple[np.ndarray, np.ndarray] | None = None,
    resume: CylinderPass | None = None,
) -> DeformationResult:
    """Signed per-point deformation of a registered compared epoch against the reference.

    Parameters
    ----------
    ref_xyz : ndarray, shape (M, 3)
        Reference epoch, metres.
    cmp_xyz : ndarray, shape (N, 3)
        Compared epoch, registered into the reference frame, metres.
    centerline : Centerline
        The reference centreline (chainage, lateral/vertical offsets).
    settings : DeformationConfig, optional
        The ``[deformation]`` parameters; ``settings.method`` chooses the estimator: ``knn``,
        the paper's KNN-centroid distance (§3.3.1) with ``settings.k`` neighbours (paper
        Table 3: 3), or ``robust``, the local-surface estimator of
        :mod:`tunneldef.deformation.local_surface` (the default).
    shell : ndarray of bool, shape (N,), optional
        Precomputed shell mask; by default
        :func:`tunneldef.deformation.shell.classify_shell` decides (with this mask, the
        reference is classified on its own, without the common cut of the Notes).
    projection : Projection, optional
        ``centerline.project(cmp_xyz)`` when the caller already has it.
    registration_sigma : float
        ``robust`` only: standard uncertainty of the registration, metres, added to the level
        of detection (never less than ``settings.registration_sigma_floor``).
    workers : int
        Threads for KD-tree queries (-1: all cores).
    progress : callable, optional
        ``progress(stage, fraction)``.
    coverage : (float, float), optional
        Chainage range covered by the reference (see Notes), when the caller measured it on
        the whole reference: a piece of the clouds (:mod:`tunneldef.tiles`) must not take its
        own.
    robust_inputs : dict, optional
        ``robust`` only: keyword arguments passed on to
        :func:`tunneldef.deformation.local_surface.robust_deformation` (``origin``,
        ``core_anchor``, ``normal_corner``, ``typical_spread``: the whole clouds' values for a
        piece of them).
    masks : (ndarray, ndarray) of bool, optional
        ``robust`` only, with ``shell``: the reference's and the compared epoch's shell masks
        cut at one level (:func:`common_masks`) when the caller already has them (a tile's
        first pass); the envelopes are then not computed again.
    resume : CylinderPass, optional
        ``robust`` only, with ``masks``: the estimator's cylinder pass on the shell points,
        computed for the same clouds, masks and ``robust_inputs`` (a tile's spreads pass);
        the estimator resumes from it (see
        :func:`tunneldef.deformation.local_surface.robust_deformation`).

    Returns
    -------
    DeformationResult

    Raises
    ------
    InvalidCloudError
        If a cloud is empty or malformed, or ``k`` < 1.
    ConfigError
        If ``method`` is unknown.

    Notes
    -----
    ``knn``: (1) counterpart = centroid of the k nearest reference points of each compared
    point, (2) both projected on the centreline, (3) horizontal = change of |lateral|,
    vertical = change of |vertical| (Manhattan split, Fig. 11), (4) deformation = distance to
    the counterpart with the sign of ``horizontal + vertical`` (closer to the centreline than
    the counterpart: negative). ``robust``: the estimator's signed normal distance, split into
    horizontal and vertical parts along its normal. The points the shell classifier kept are
    measured on the surfaces of the shell points of both epochs, cut from the inner of the two
    epochs' envelopes (after their local difference, the motion, is taken out:
    :meth:`tunneldef.deformation.shell.ShellEnvelope.matched_offset`). Every other point with
    a reference surface in reach is measured too, on the surfaces of all points: the side
    chamber, the edges of the envelope, rough rock and corners the classifier left out are
    shell all the same. Only what stands in front of other points (a pipe, the conveyor, a
    coal load, a person: points of either epoch lie behind its surface within
    ``settings.standoff_reach``, see :func:`_stands_off`) or has no reference surface within
    ``max_depth`` keeps the paper's KNN change, so that moved clutter still shows, without a
    level of detection and never significant. A point whose cylinder holds reference points
    but no supported estimate (the two epochs cover different parts of it, at the edge of a
    hole or of the scan; too few points; no single surface) gets NaN. The ``shell`` field stays
    the classifier's decision, and danger is judged on it as before (a coal load whose rock
    behind is shadowed can pass the stand-off test and be measured as a surface; it must not
    raise danger).
    Both: points beyond the chainage range of the reference points (their 0.05-99.95 %
    quantiles) get NaN, and so do (``knn``) points farther than
    ``config.deformation.max_distance`` from their counterpart (holes in the reference).
    """
    dcfg = settings or DeformationConfig()
    method = dcfg.method
    if method not in METHODS:
        raise ConfigError(f"unknown deformation method {method!r}; use one of {METHODS}")
    cmp = check_points(cmp_xyz, name="compared cloud")
    ref = check_points(ref_xyz, name="reference cloud")
    k = dcfg.k
    registration_sigma = max(float(registration_sigma), dcfg.registration_sigma_floor)
    if shell is not None and np.shape(shell) != (cmp.shape[0],):
        raise InvalidCloudError(
            f"shell mask has shape {np.shape(shell)}, expected ({cmp.shape[0]},)"
        )
    if masks is not None and (
        shell is None or np.shape(masks[0]) != (ref.shape[0],)
        or np.shape(masks[1]) != (cmp.shape[0],)
    ):
        raise InvalidCloudError(
            "masks must come with the shell mask and hold one value per reference and per "
            "compared point"
        )
    if resume is not None and masks is None:
        raise ValueError("resume comes with the masks its cylinder pass was computed on")

    with timed_stage(logger, f"deformation ({method}) of {cmp.shape[0]} points"):
        notify(progress, "deformation", 0.0)
        ref_job = None
        if method == "robust" and masks is None:
            # the reference's projection and shell envelope are independent of the compared
            # cloud's: a second thread computes them meanwhile (NumPy's sorts and array
            # arithmetic release the GIL)
            pool = ThreadPoolExecutor(max_workers=1)
            ref_job = pool.submit(_envelope, ref, centerline, workers)
            pool.shutdown(wait=False)
        pp = centerline.project(cmp, workers=workers) if projection is None else projection
        cmp_env = None
        if shell is None:
            _, cmp_env, cmp_off, cmp_obl = _envelope(cmp, centerline, workers, pp)
            shell_mask = shell_module.shell_mask(cmp_off, cmp_obl)
        else:
            shell_mask = np.asarray(shell, dtype=bool)
        notify(progress, "deformation", 0.1)
        ref_chainage = None
        significant = lod95 = double = spread_ratio = typical_spread = None
        if method == "knn":
            deformation, horizontal, vertical, dist = _knn_deformation(
                ref, cmp, centerline, pp, k=k, workers=workers, progress=scaled(progress, 0.1, 0.85)
            )
        else:
            from .local_surface import robust_deformation

            if masks is not None:  # the caller's masks, cut at one level already
                ref_mask, cmp_mask = (np.asarray(m, dtype=bool) for m in masks)
            else:
                assert ref_job is not None
                ref_pp, ref_env, ref_off, ref_obl = ref_job.result()
                ref_chainage = ref_pp.chainage
                if cmp_env is None:  # the caller's own shell mask: each epoch on its own
                    ref_mask = shell_module.shell_mask(ref_off, ref_obl)
                    cmp_mask = shell_mask
                else:
                    # both epochs' surfaces are measured on points cut at one level, from the
                    # inner of the two envelopes once their local difference (the motion) is
                    # taken out
                    ref_mask, cmp_mask = common_masks(
                        ref_env, ref_pp, ref_off, ref_obl, cmp_env, pp, cmp_off, cmp_obl
                    )
            # the grids and typical spreads come from the whole clouds (or, for a tile, from
            # the whole survey's: robust_inputs), the same for both passes below, so that a
            # tile's values are the untiled ones
            grids = dict(robust_inputs) if robust_inputs else global_inputs(ref, cmp, dcfg)
            kwargs = {**_robust_kwargs(dcfg), **grids}
            r = robust_deformation(
                ref,
                cmp,
                centerline,
                ref_mask=ref_mask,
                cmp_mask=cmp_mask,
                measure=shell_mask,
                registration_sigma=registration_sigma,
                workers=workers,
                progress=scaled(progress, 0.1, 0.75),
                resume=resume,
                **kwargs,
            )
            deformation = np.asarray(r.deformation, dtype=np.float64)
            nrm = np.asarray(r.normal, dtype=np.float64)
            significant = np.asarray(r.significant, dtype=bool)
            lod95 = np.asarray(r.lod95, dtype=np.float64)
            spread_ratio = _spread_ratio(r, shell_mask)
            typical_spread = r.meta.get("typical_spread")
            rest = ~shell_mask
            take = np.zeros_like(rest)
            no_value = np.zeros_like(rest)
            if rest.any():
                # points the classifier did not keep (chamber walls, edges of the shell's
                # envelope, rough rock, but also equipment, coal, people): measured on the
                # surfaces of all points; those that stand in front of other reference
                # points (rock behind them) are clutter, see below
                # only the points within reach of them take part (a coarse voxel test)
                reach = _PASS2_CELL
                kr, kc = _near(ref, cmp[rest], reach), _near(cmp, cmp[rest], reach)
                kc |= rest
                r2 = robust_deformation(
                    ref[kr],
                    cmp[kc],
                    centerline,
                    measure=rest[kc],
                    registration_sigma=registration_sigma,
                    workers=workers,
                    progress=scaled(progress, 0.75, 0.85),
                    **{**kwargs, "typical_spread": r.meta.get("typical_spread")},
                )
                standing = np.zeros(len(cmp), dtype=bool)
                in_rest = rest[kc]
                standing[rest] = _stands_off(
                    np.concatenate([ref, cmp]),
                    centerline,
                    r2.core_xyz,
                    r2.core_normal,
                    r2.core[in_rest],
                    dcfg.standoff_reach,
                )
                r2_d = np.full(len(cmp), np.nan)
                r2_d[kc] = r2.deformation
                r2_unsupported = np.zeros(len(cmp), dtype=bool)
                r2_unsupported[kc] = r2.unsupported
                take = rest & ~standing & np.isfinite(r2_d)
                # on the shell surface but without a supported estimate: NaN, not the KNN
                no_value |= rest & ~standing & r2_unsupported
                sub = take[kc]
                deformation[take] = r2.deformation[sub]
                nrm[take] = r2.normal[sub]
                significant[take] = r2.significant[sub]
                lod95[take] = r2.lod95[sub]
            # a change that one epoch contradicts by showing both of its surfaces (a SLAM
            # map's double wall): no value there, rather than a confident wrong one
            sigma = float(np.nanmax(typical_spread)) if typical_spread is not None else np.nan
            double = two_surfaces(ref, cmp, np.isfinite(deformation) & significant,
                                  deformation, nrm, sigma,
                                  float(getattr(dcfg, "cylinder_radius", 0.2)))
            if double.any():
                logger.info(
                    "%d compared points (chainage %.1f-%.1f m) show a change that one epoch "
                    "contradicts with both surfaces (a SLAM map's double wall?): NaN",
                    int(double.sum()), float(pp.chainage[double].min()),
                    float(pp.chainage[double].max()))
                deformation[double] = np.nan
                significant[double] = False
                lod95[double] = np.nan
                no_value |= double
            _, lat_dir, ver_dir = centerline.frame_at(pp.chainage)
            # the displacement vector deformation * normal, split into the changes of
            # |lateral| and |vertical| (NaN where the estimator gave no value)
            horizontal = deformation * np.einsum("ij,ij->i", nrm, lat_dir) * np.sign(pp.lateral)
            vertical = deformation * np.einsum("ij,ij->i", nrm, ver_dir) * np.sign(pp.vertical)
            clutter = ~shell_mask & ~np.isfinite(deformation) & ~no_value
            if clutter.any():
                # equipment, coal, people in front of the shell have no surface of their own
                # to measure along: they get the paper's KNN-centroid change, so that moved
                # clutter still shows (never as danger, which is judged on the shell)
                sub_pp = Projection(
                    *(getattr(pp, f.name)[clutter] for f in dataclass_fields(Projection))
                )
                dc, hc, vc, distc = _knn_deformation(
                    ref, cmp[clutter], centerline, sub_pp, k=dcfg.k, workers=workers
                )
                far = distc > dcfg.max_distance
                dc[far] = hc[far] = vc[far] = np.nan
                deformation[clutter], horizontal[clutter], vertical[clutter] = dc, hc, vc
                significant[clutter] = False
                lod95[clutter] = np.nan
            k = None
        # no counterpart beyond the reference's ends or farther than max_distance (holes)
        if coverage is None:
            lo, hi = _coverage(ref, centerline, workers, ref_chainage)
        else:
            lo, hi = coverage
        unmatched = (pp.chainage < lo) | (pp.chainage > hi)
        if method == "knn":
            unmatched |= dist > dcfg.max_distance
        if unmatched.any():
            logger.info(
                "%d of %d compared points have no reference counterpart (NaN)",
                int(unmatched.sum()),
                unmatched.size,
            )
            for a in (deformation, horizontal, vertical, lod95):
                if a is not None:
                    a[unmatched] = np.nan
            if significant is not None:
                significant[unmatched] = False
        notify(progress, "deformation", 0.9)
        surface = surface_labels(pp.chainage, pp.lateral, pp.vertical, step=dcfg.section_step)
        notify(progress, "deformation", 1.0)

    return DeformationResult(
        deformation=deformation,
        horizontal=horizontal,
        vertical=vertical,
        chainage=pp.chainage,
        surface=surface,
        shell=shell_mask,
        xyz=cmp,
        method=method,
        k=k,
        significant=significant,
        lod95=lod95,
        centerline_length=centerline.length,
        two_surfaces=double,
        spread_ratio=spread_ratio,
        typical_spread=typical_spread,
    )
