"""Per-point deformation of a registered compared epoch against the reference (paper §3.3).

:func:`compute_deformation` runs the paper's KNN centroid (:mod:`.knn`) or the local-surface
estimator (:mod:`.local_surface`, beyond the paper), after cutting the shell from clutter
(:mod:`.shell`), and splits the change into horizontal and vertical parts (§3.3.2).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import fields as dataclass_fields

import numpy as np

from ..cloud import check_points
from ..config import DeformationConfig
from ..curve import Centerline, Projection
from ..errors import ConfigError, InvalidCloudError
from ..progress import ProgressCallback, notify, scaled, timed_stage
from . import shell as shell_module
from .knn import counterpart_projection, knn_counterparts, manhattan_split
from .result import DeformationResult
from .sections import surface_labels

__all__ = ["compute_deformation", "common_masks", "METHODS"]

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
        of detection.
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
    horizontal and vertical parts along its normal; points it cannot measure because they lie
    off the shell surface (equipment, coal, people) get the ``knn`` value, so that moved
    clutter still shows. The estimator's surfaces are fitted to the shell points of both
    epochs, cut from the inner of the two epochs' envelopes (after their local difference, the
    motion, is taken out: :meth:`tunneldef.deformation.shell.ShellEnvelope.matched_offset`);
    the ``shell`` field is each compared point's own classification.
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
    if shell is not None and np.shape(shell) != (cmp.shape[0],):
        raise InvalidCloudError(
            f"shell mask has shape {np.shape(shell)}, expected ({cmp.shape[0]},)"
        )

    with timed_stage(logger, f"deformation ({method}) of {cmp.shape[0]} points"):
        notify(progress, "deformation", 0.0)
        ref_job = None
        if method == "robust":
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
        significant = lod95 = None
        if method == "knn":
            deformation, horizontal, vertical, dist = _knn_deformation(
                ref, cmp, centerline, pp, k=k, workers=workers, progress=scaled(progress, 0.1, 0.85)
            )
        else:
            from .local_surface import robust_deformation

            assert ref_job is not None
            ref_pp, ref_env, ref_off, ref_obl = ref_job.result()
            ref_chainage = ref_pp.chainage
            if cmp_env is None:  # the caller's own shell mask: each epoch on its own
                ref_mask = shell_module.shell_mask(ref_off, ref_obl)
                cmp_mask = shell_mask
            else:
                # both epochs' surfaces are measured on points cut at one level, from the inner
                # of the two envelopes once their local difference (the motion) is taken out
                ref_mask, cmp_mask = common_masks(
                    ref_env, ref_pp, ref_off, ref_obl, cmp_env, pp, cmp_off, cmp_obl
                )
            r = robust_deformation(
                ref,
                cmp,
                centerline,
                ref_mask=ref_mask,
                cmp_mask=cmp_mask,
                registration_sigma=registration_sigma,
                workers=workers,
                progress=scaled(progress, 0.1, 0.85),
                **_robust_kwargs(dcfg),
                **(robust_inputs or {}),
            )
            deformation = np.asarray(r.deformation, dtype=np.float64)
            nrm = np.asarray(r.normal, dtype=np.float64)
            _, lat_dir, ver_dir = centerline.frame_at(pp.chainage)
            # the displacement vector deformation * normal, split into the changes of
            # |lateral| and |vertical| (NaN where the estimator gave no value)
            horizontal = deformation * np.einsum("ij,ij->i", nrm, lat_dir) * np.sign(pp.lateral)
            vertical = deformation * np.einsum("ij,ij->i", nrm, ver_dir) * np.sign(pp.vertical)
            significant = np.asarray(r.significant, dtype=bool)
            lod95 = np.asarray(r.lod95, dtype=np.float64)
            clutter = ~shell_mask & ~np.isfinite(deformation)
            if clutter.any():
                # equipment, coal, people away from the shell have no surface to measure along:
                # they get the paper's KNN-centroid change, so that moved clutter still shows
                # (never as danger, which is judged on the shell); points off the shell mask
                # but on the shell surface keep the estimator's value
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
    )
