"""The whole flow, two clouds in, one result out: the only place that chains the stages.

``detect(ref, cmp)``: check the epochs -> centrelines of both (paper §3.1) -> registration of the
compared epoch onto the reference (§3.2) -> per-point deformation against the reference
centreline (§3.3.1-3.3.2) -> per-section statistics and danger zones (§4.3). Hosts (CLI,
CloudCompare plugin, scripts) convert their inputs to :class:`~tunneldef.cloud.Cloud`, call
:func:`detect` and write ``result.cloud`` back.

One idea at this length: the chaining of the stages for single drifts and for networks, with
the checks and the result objects they return.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import __version__
from .cloud import Cloud, check_points
from .config import Config
from .curve import Centerline
from .errors import EpochMismatchError, NotATunnelError, RegistrationError
from .frame import principal_frame
from .progress import ProgressCallback, notify, under
from .quality import (
    UNVERIFIED,
    QualityReport,
    centerline_checks,
    deformation_checks,
    direction_check,
    edge_checks,
    edge_difference_checks,
    network_registration_checks,
    registration_checks,
    tilt_check,
    topology_checks,
    upright_check,
)
from .transforms import apply_transform

__all__ = ["detect", "detect_network", "register_epochs", "check_epochs", "is_network",
           "Result", "NetworkResult", "RegisteredPair", "OUTPUT_FIELDS"]

log = logging.getLogger(__name__)

#: Fields every output of :func:`detect` carries (DESIGN.md output contract).
OUTPUT_FIELDS = ("deformation", "deformation_horizontal", "deformation_vertical", "chainage",
                 "danger")

_MIN_POINTS = 1000
_MAX_SCALE_RATIO = 4.0
_MIN_OVERLAP = 0.2
_CHUNK = 2_000_000  # points mapped at once by an in-place transform


def check_epochs(ref: Cloud, cmp: Cloud, *, network: bool = False) -> None:
    """Refuse pairs that cannot be compared: too small, or in different units.

    ``network``: the epochs are drift networks, which need not be elongated as a whole (an
    80 m drift with a 40 m cross-cut is not); only their sizes are checked here, and their
    drifts' widths once their centrelines are known (:func:`detect_network`).

    Raises
    ------
    InvalidCloudError, NotATunnelError, EpochMismatchError
    """
    check_points(ref.xyz, name="reference", min_points=_MIN_POINTS)
    check_points(cmp.xyz, name="compared", min_points=_MIN_POINTS)
    if network:
        return
    with epoch_named("reference"):
        fr = principal_frame(ref.xyz)
    with epoch_named("compared"):
        fc = principal_frame(cmp.xyz)
    # the spread across the axis is the section size, independent of length and heading
    sr = float(np.sqrt(fr.variances[1] + fr.variances[2]))
    sc = float(np.sqrt(fc.variances[1] + fc.variances[2]))
    ratio = max(sr, sc) / max(min(sr, sc), 1e-12)
    if ratio > _MAX_SCALE_RATIO:
        raise EpochMismatchError(
            f"the epochs differ in scale by about x{ratio:.0f} (section spread {sr:.3g} vs "
            f"{sc:.3g}); are both in metres?"
        )


@contextmanager
def epoch_named(name: str | None) -> Iterator[None]:
    """Name the epoch in a not-a-tunnel error raised inside (``reference epoch: the cloud is
    not elongated ...``): the stages see one cloud and cannot tell which file it came from.
    ``None`` (a single cloud) leaves the error as it is."""
    try:
        yield
    except NotATunnelError as exc:
        if name is None or str(exc).startswith(f"{name} epoch"):
            raise
        raise type(exc)(f"{name} epoch: {exc}") from exc


def is_network(clouds: Any, config: Config | None = None) -> bool:
    """True if any of ``clouds`` is a drift network: the skeleton of its plan footprint has
    a junction, or turns a corner (a walk from a drift into a cross-cut: one drift's slices
    and curve cannot follow a right angle, the network's edges flag it as a junction zone)
    (:func:`~tunneldef.centerline.skeleton.plan_topology`, on at most 2 M points: a few
    seconds). How ``tunneldef detect`` and the plugin choose between :func:`detect` and
    :func:`detect_network` unless told."""
    from .centerline.skeleton import plan_topology

    nc = (config or Config()).network
    clouds = list(clouds)
    names = ("reference", "compared") if len(clouds) == 2 else (None,) * len(clouds)
    for name, cloud in zip(names, clouds, strict=True):
        with epoch_named(name):
            topo = plan_topology(cloud.xyz, nc)
        if topo.junctions > 0 or topo.corners > 0:
            log.info("%s: measuring as a drift network", topo.describe())
            return True
    return False


_MOMENT_CHUNK = 4_000_000  # values summed at once by shell_moments


def shell_moments(d: np.ndarray, keep: np.ndarray | None = None) -> dict[str, Any]:
    """Count, mean, standard deviation, mean / median / p95 of the absolute value, min and max
    of the finite values of ``d`` where ``keep`` (all by default).

    Sums run in float64 a few million values at a time, and the percentiles are NumPy's
    linear ones on the order statistics of one array of ``|v|`` in ``d``'s dtype: a survey's
    field of 55 M float32 values needs no float64 copy of it, no mask as long as it, nor
    NumPy's ``std`` temporary of the same size.
    """
    n_all = len(d)

    def chunks():
        for a in range(0, n_all, _MOMENT_CHUNK):
            v = d[a:a + _MOMENT_CHUNK]
            ok = np.isfinite(v)
            if keep is not None:
                ok &= keep[a:a + _MOMENT_CHUNK]
            yield v[ok]

    n, total, lo, hi = 0, 0.0, np.inf, -np.inf
    for v in chunks():
        if v.size:
            n += v.size
            total += float(np.sum(v, dtype=np.float64))
            lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
    if n == 0:
        return {"count": 0}
    mean = total / n
    a = np.empty(n, dtype=d.dtype)
    ss = total_abs = 0.0
    at = 0
    for v in chunks():
        ss += float(np.sum((v.astype(np.float64) - mean) ** 2))
        np.abs(v, out=a[at:at + v.size])
        total_abs += float(np.sum(a[at:at + v.size], dtype=np.float64))
        at += v.size
    pos = [(n - 1) * q for q in (0.50, 0.95)]
    ks = sorted({int(p) for p in pos} | {min(int(p) + 1, n - 1) for p in pos})
    a.partition(ks)
    pct = []
    for p in pos:
        k = int(p)
        x0, x1, t = float(a[k]), float(a[min(k + 1, n - 1)]), p - k
        # NumPy's _lerp: from the nearer end
        pct.append(x1 - (x1 - x0) * (1.0 - t) if t >= 0.5 else x0 + (x1 - x0) * t)
    return {"count": n, "mean": mean, "std": float(np.sqrt(ss / n)), "mean_abs": total_abs / n,
            "p50_abs": pct[0], "p95_abs": pct[1], "min": lo, "max": hi}


@dataclass
class RegisteredPair:
    """Both epochs' centreline extractions and the registration of compared onto reference."""

    ref_extraction: Any
    cmp_extraction: Any
    registration: Any
    quality: QualityReport = field(default_factory=QualityReport)
    registration_check: Any = None
    #: the compared points in the reference frame when ``register_epochs`` moved them itself
    #: (``correct_drift``): rigidly, then corrected for SLAM drift where that was used
    moved_xyz: np.ndarray | None = None
    #: the compared centreline carried along with ``moved_xyz``
    moved_cmp_centerline: Any = None
    #: the drift correction's figures (:func:`~tunneldef.registration.network.correct_drift`)
    drift_correction: dict[str, Any] = field(default_factory=dict)


def register_epochs(
    ref: Cloud, cmp: Cloud, config: Config | None = None, *,
    progress: ProgressCallback | None = None,
    correct_drift: bool = False,
) -> RegisteredPair:
    """Extract both centrelines and register the compared epoch onto the reference.

    Parameters
    ----------
    ref, cmp : Cloud
        Reference and compared epochs, any frames, metres.
    config : Config
        Parameters.
    progress : callable, optional
        ``progress(stage, fraction)``.
    correct_drift : bool
        After the rigid centreline registration, also correct SLAM drift along the
        reference centreline (``[network] drift_correction``, blocks of ``drift_block``
        metres, or ``drift_block_fine`` where those take out more of it:
        :func:`~tunneldef.registration.network.correct_drift`), and check the
        registration on the corrected points. The result is then no rigid transform: the
        moved points come back in ``moved_xyz``. Off for a registration whose product is
        the transform alone.

    Returns
    -------
    RegisteredPair
        ``registration.transform`` maps compared coordinates into the reference frame.
    """
    from .centerline import extract_centerline
    from .centerline.skeleton import plan_topology
    from .registration import register

    config = config or Config()
    check_epochs(ref, cmp)
    report = QualityReport(enforced=config.quality.enforce)
    # first, is each epoch one drift? (a network's cross-cuts are no sections of one tube)
    notify(progress, "plan topology", 0.0)
    for name, cloud in (("reference", ref), ("compared", cmp)):
        with epoch_named(name):
            topo = plan_topology(cloud.xyz, config.network)
        log.info("%s epoch: %s", name, topo.describe())
        report.add(topology_checks(topo, config.quality, name))
    notify(progress, "plan topology", 1.0)
    lines = {"slicing": config.slicing, "settings": config.centerline}
    with epoch_named("reference"):
        ref_ex = extract_centerline(ref.xyz, **lines,
                                    progress=under(progress, "reference centreline"))
    report.add(centerline_checks(ref_ex, config.quality, "reference"))
    report.add([upright_check(ref_ex, config.quality)])
    with epoch_named("compared"):
        cmp_ex = extract_centerline(cmp.xyz, **lines,
                                    progress=under(progress, "compared centreline"))
    report.add(centerline_checks(cmp_ex, config.quality, "compared"))
    _check_section_sizes(ref_ex, cmp_ex)
    reg = register(ref.xyz, cmp.xyz, ref_ex.centerline, cmp_ex.centerline,
                   method=config.registration.method, settings=config.registration,
                   progress=under(progress, "registration"))
    limit = config.registration.max_axial_uncertainty
    if not reg.axial_uncertainty <= limit:
        raise RegistrationError(
            f"the position of the compared epoch along the tunnel is undetermined "
            f"(+-{reg.axial_uncertainty:.2f} m > {limit} m): {_why_undetermined(reg.info)}; set "
            "registration.max_axial_uncertainty = inf to accept it anyway"
        )
    check = None
    moved_xyz, moved_cl, drift = None, None, {"enabled": False, "used": False}
    if reg.method == "centerline":
        from .registration.register import tilt_deg
        from .registration.verify import verify_registration

        cmp_xyz, transform, cmp_cl = cmp.xyz, np.asarray(reg.transform), cmp_ex.centerline
        if correct_drift and config.network.drift_correction:
            moved_xyz, moved_cl, drift = _single_drift_correction(
                ref, cmp, ref_ex.centerline, cmp_ex.centerline, transform, config, progress)
            cmp_xyz, transform, cmp_cl = moved_xyz, np.eye(4), moved_cl
        notify(progress, "registration check", 0.0)
        check = verify_registration(ref.xyz, cmp_xyz, ref_ex.centerline, transform=transform,
                                    cmp_centerline=cmp_cl,
                                    search=config.registration.axial_search or 10.0,
                                    points_per_metre=config.registration.max_points_per_metre)
        levelled = config.registration.coarse_vertical == "world"
        tilt = tilt_deg(reg.transform) if levelled else float("nan")
        checks = registration_checks(check, config.quality) + [
            direction_check(reg.info), tilt_check(tilt, config.quality)]
        if reg.info.get("axial_curve", {}).get("informative"):
            checks = _bend_checks(checks, ref, cmp_xyz, ref_ex.centerline, transform, config)
        notify(progress, "registration check", 1.0)
        report.add(checks)
    return RegisteredPair(ref_ex, cmp_ex, reg, report, check, moved_xyz, moved_cl, drift)


def _single_drift_correction(
    ref: Cloud, cmp: Cloud, ref_cl: Centerline, cmp_cl: Centerline, transform: np.ndarray,
    config: Config, progress: ProgressCallback | None,
) -> tuple[np.ndarray, Centerline, dict[str, Any]]:
    """The compared points moved by ``transform`` and then corrected for SLAM drift along the
    reference centreline (a network of one edge), with the compared centreline carried along.

    A handheld SLAM map of one drift bends slowly away from the other epoch's (a few
    centimetres per 100 m): one rigid transform leaves it there, and the deformation field
    reads it as change. On a 166 m bent drift drifting about 6 cm per epoch, registered
    rigidly and verified, 33 % of the unchanged shell read beyond 10 mm and a 36 mm wall
    bulge read 24 mm.
    """
    from .network import CenterlineNetwork, NetworkEdge
    from .registration.network import correct_drift

    notify(progress, "drift correction", 0.0)
    moved = apply_transform(transform, cmp.xyz)
    net = CenterlineNetwork((NetworkEdge(0, "drift", ref_cl),))
    moved, drift = correct_drift(ref.xyz, moved, net, inplace=True,
                                 **_drift_settings(config))
    drift["enabled"] = True
    cl = cmp_cl.transformed(transform)
    if drift["used"]:
        step = max(len(moved) // 200_000, 1)
        before = apply_transform(transform, cmp.xyz[::step])
        pts = cl.points + _carried(before, moved[::step], cl.points)
        cl = Centerline.from_polyline(pts, step=float(np.median(np.diff(cl.chainage))),
                                      centres=cl.centres, meta=cl.meta)
    _log_drift(drift)
    notify(progress, "drift correction", 1.0)
    return moved, cl, drift


def _drift_settings(config: Config) -> dict[str, Any]:
    """``correct_drift``'s block lengths (longest first) and change limit from ``[network]``."""
    nc = config.network
    blocks = (nc.drift_block,)
    if 0 < nc.drift_block_fine < nc.drift_block:
        blocks = (nc.drift_block, nc.drift_block_fine)
    return {"block": blocks, "change": nc.drift_change if nc.drift_change > 0 else None}


def _log_drift(drift: dict[str, Any]) -> None:
    """One log line: whether the SLAM-drift correction was used, and what it changed."""
    if not drift.get("enabled"):
        return
    cb, ca = drift.get("coherent_before_m", np.nan), drift.get("coherent_after_m", np.nan)
    log.info("SLAM-drift correction (%.0f m blocks) %s: coherent misfit %.1f -> %.1f mm",
             drift.get("block_m", np.nan), "used" if drift.get("used") else "not used",
             1e3 * cb, 1e3 * ca)


#: checks of the position along the axis by the section images and by the slides along the
#: local axis direction: both follow the reference curve round a bend and are blind to it
_SLIDE_CHECKS = ("registration.axial_residual", "registration.axial_convergence",
                 "registration.axial_pose", "registration.axial_agreement")


def _bend_checks(checks: list, ref: Cloud, cmp_xyz: np.ndarray, ref_cl: Any,
                 transform: np.ndarray, config: Config) -> list:
    """The position along the axis of a drift that the curves' shapes placed (a bend between
    straights, surfaces without features): its check is a rigid point-to-plane translation
    fit from the registered pose and from 2 cm off, which the bend's walls hold
    (:func:`~tunneldef.registration.verify.verify_network`'s figures), in place of the checks
    by the slides along the local axis direction and by the section images, which follow the
    reference curve round the bend and see none of it (on a featureless bent drift registered
    0.8 mm off the slides read 21 mm from one start and ended 71 mm apart from starts 2 cm
    either side, where the rigid fit read 0.3 mm, and 0.5 mm apart; on another, 2.8 mm off,
    the section images "matched better" elsewhere: these positions are the ones the images
    had already left open). A rigid fit with the rotations, started from the pose and 2 cm
    either side of it along the drift, must end in one place too
    (:func:`~tunneldef.registration.verify.rigid_convergence`): on a ramp the translation
    alone reads a slide that a small pitch cancels as none."""
    from .quality import network_registration_checks, rigid_convergence_check
    from .registration.verify import rigid_convergence, verify_network
    from .spatial import random_subset

    ppm = config.registration.max_points_per_metre
    n = max(400_000, int(2 * ppm * ref_cl.length))
    moved = apply_transform(transform, random_subset(cmp_xyz, n, 12))
    rigid = verify_network(random_subset(ref.xyz, n, 11), moved, ref_cl.length,
                           points_per_metre=ppm)
    keep = ("registration.translation_residual", "registration.translation_convergence")
    ends = ref_cl.point_at(np.array([0.0, ref_cl.length]))
    spread, _ = rigid_convergence(random_subset(ref.xyz, n, 11), moved, ends[1] - ends[0])
    return ([c for c in checks if c.name not in _SLIDE_CHECKS]
            + [c for c in network_registration_checks(rigid, config.quality) if c.name in keep]
            + [rigid_convergence_check(spread, config.quality)])


def _why_undetermined(info: dict[str, Any]) -> str:
    """Why the registration left the position along the axis open, from its ``info``: no
    feature at all, or none that the section images around the point-to-plane slide's
    strongest one confirm (a prism's noise, or a small chamber beside a conveyor whose coal
    changed: both read the same here)."""
    window = info.get("axial_feature_window")
    if not window:
        return ("the common stretch has no features along the axis (chamber, bend, width "
                "change, rough rock)")
    seen = (f"match about as well {window['spread']:.2f} m either way"
            if np.isfinite(window["spread"]) else "hold too few points to judge")
    return ("the common stretch shows no feature along the axis that the section images "
            "confirm (around the point-to-plane slide's strongest one, near chainage "
            f"{window['chainage']:.1f} m, they {seen}; changed clutter such as coal or moved "
            "equipment can drown a small chamber)")


def _check_section_sizes(ref_ex: Any, cmp_ex: Any) -> None:
    """Refuse epochs whose drifts differ in width by more than ``_MAX_SCALE_RATIO`` (the
    median width of the fitted slices of a single-drift extraction, or of every edge of a
    network)."""
    def median_size(ex: Any) -> float:
        slices = ex.slices if hasattr(ex, "slices") else [
            r for e in ex.network.edges for r in e.slices]
        vals = [r.width for r in slices if getattr(r, "ok", True) and np.isfinite(r.width)]
        return float(np.median(vals)) if vals else float("nan")

    wr, wc = median_size(ref_ex), median_size(cmp_ex)
    if np.isfinite(wr) and np.isfinite(wc) and max(wr, wc) > _MAX_SCALE_RATIO * min(wr, wc):
        raise EpochMismatchError(
            f"the tunnels differ in width ({wr:.3g} vs {wc:.3g} in file units); "
            "are both epochs of the same tunnel, in metres?"
        )


@dataclass
class Result:
    """Everything :func:`detect` found.

    Attributes
    ----------
    cloud : Cloud
        The compared epoch's points (same order, original fields), coordinates in the
        reference frame, with the float32 fields ``deformation``, ``deformation_horizontal``,
        ``deformation_vertical``, ``chainage`` (m) and uint8 ``danger`` (plus ``shell``,
        ``surface``, ``significant``, ``lod95`` when the estimator gives them).
    transform : ndarray, shape (4, 4)
        Compared -> reference rigid transform (before the SLAM-drift correction, when that
        was used: ``drift_correction["used"]``).
    drift_correction : dict
        The piecewise-rigid SLAM-drift correction along the reference centreline
        (:func:`~tunneldef.registration.network.correct_drift`): whether it was enabled and
        used, the coherent misfit before and after, the blocks' shifts.
    """

    cloud: Cloud
    transform: np.ndarray
    registration: Any
    ref_centerline: Centerline
    cmp_centerline: Centerline
    deformation: Any
    sections: list[dict[str, Any]]
    zones: list[dict[str, Any]]
    danger_threshold: float
    config: Config
    ref_slices: list[Any] = field(default_factory=list)
    cmp_slices: list[Any] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    quality: QualityReport | None = None
    drift_correction: dict[str, Any] = field(default_factory=dict)

    def statistics(self) -> dict[str, Any]:
        """Global statistics of the signed deformation on shell points (m)."""
        d = np.asarray(self.cloud.fields["deformation"])
        # (not .get("shell", np.ones(...)): its default, float64 as long as the survey, was
        # built even when the field is there: 0.41 GiB at the end of a 1 km run)
        shell = self.cloud.fields.get("shell")
        shell = np.ones(len(d), dtype=bool) if shell is None else np.asarray(shell, dtype=bool)
        out: dict[str, Any] = {"count": 0, "points": int(d.size)}
        out.update(shell_moments(d, shell))
        danger = np.asarray(self.cloud.fields["danger"])
        out["danger_points"] = int(danger.sum())
        if "significant" in self.cloud.fields:
            out["significant_fraction"] = float(np.mean(self.cloud.fields["significant"][shell]))
        return out

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable summary: transform, centrelines, sections, zones, parameters."""
        reg = self.registration
        return {
            "software": {"name": "tunneldef", "version": __version__},
            "transform_compared_to_reference": np.asarray(self.transform).tolist(),
            "registration": reg.to_dict() if hasattr(reg, "to_dict") else {},
            "statistics": self.statistics(),
            "danger_threshold_m": self.danger_threshold,
            "danger_zones": self.zones,
            "sections": self.sections,
            "reference_centerline": self.ref_centerline.to_dict(),
            "compared_centerline": self.cmp_centerline.to_dict(),
            "parameters": self.config.to_dict(),
            "timings_s": self.timings,
            "sign_convention": "negative = the surface moved into the tunnel (roof sag, wall "
                               "bulge, floor heave); positive = outward",
            "quality": self.quality.to_dict() if self.quality is not None else None,
            "drift_correction": self.drift_correction,
        }


def detect(
    ref: Cloud, cmp: Cloud, config: Config | None = None, *,
    progress: ProgressCallback | None = None,
    tiles: dict[str, Any] | None = None,
    overwrite_compared: bool = False,
) -> Result:
    """Register the compared epoch onto the reference and measure deformation.

    Parameters
    ----------
    ref, cmp : Cloud
        Reference (earlier) and compared (later) epochs, any frames, metres.
    config : Config
        Parameters (defaults: the paper's where it gives them).
    progress : callable, optional
        ``progress(stage, fraction)``; may raise :class:`tunneldef.progress.Cancelled`.
    tiles : dict, optional
        Run the deformation stage in chainage tiles as Dask tasks: keyword arguments of
        :func:`tunneldef.tiles.tiled_deformation` (``tile_length``, ``memory_gb``, ``engine``,
        ``workdir``); the values are those of the untiled stage.
    overwrite_compared : bool
        Map ``cmp``'s coordinates into the reference frame in place and return ``cmp`` itself
        as ``Result.cloud`` (its fields added), instead of a copy: one copy of the compared
        epoch less in memory, for callers that no longer need it in its own frame.

    Returns
    -------
    Result

    Raises
    ------
    TunnelDefError
        On inputs that cannot be compared (too few points, not a tunnel, different units,
        no overlap, failed registration).

    Notes
    -----
    Steps: centrelines of both epochs (paper §3.1), centreline registration (§3.2), KNN-centroid
    or robust per-point deformation with its horizontal/vertical split (§3.3), per-section
    statistics (Table 4) and danger classification (Fig. 22).

    References
    ----------
    Sensors 2024, 24, 2299, doi:10.3390/s24072299.
    """
    from .deformation import (
        compute_deformation,
        danger_threshold,
        danger_zones,
        section_statistics,
    )

    config = config or Config()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    reg_all = register_epochs(ref, cmp, config, progress=progress, correct_drift=True)
    reg = reg_all.registration
    timings["centrelines_and_registration"] = time.perf_counter() - t0

    t = time.perf_counter()
    transform = np.asarray(reg.transform, dtype=np.float64)
    # the compared points in the reference frame: moved rigidly here, or already moved (and
    # corrected for SLAM drift) by the registration
    xyz, reg_all.moved_xyz = reg_all.moved_xyz, None
    if overwrite_compared and cmp.xyz.flags.writeable:
        for a in range(0, len(cmp), _CHUNK):
            cmp.xyz[a:a + _CHUNK] = (apply_transform(transform, cmp.xyz[a:a + _CHUNK])
                                     if xyz is None else xyz[a:a + _CHUNK])
        moved = cmp
    elif xyz is None:
        moved = cmp.transformed(transform)
    else:
        moved = Cloud(xyz, dict(cmp.fields), dict(cmp.meta))
    del xyz
    ref_cl = reg_all.ref_extraction.centerline
    if tiles is None:
        projection = ref_cl.project(moved.xyz)
        inside = projection.inside
    else:
        from .deformation.sections import surface_labels
        from .tiles import project_chunked

        # the offsets serve the surface labels only: dropped before the tiles run
        chainage, lateral, vertical, inside = project_chunked(ref_cl, moved.xyz, full=True)
        surface = surface_labels(chainage, lateral, vertical,
                                 step=config.deformation.section_step)
        del lateral, vertical
    overlap = float(np.mean(inside))
    del inside
    if overlap < _MIN_OVERLAP:
        raise EpochMismatchError(
            f"only {100 * overlap:.0f} % of the compared points lie along the reference "
            "centreline after registration; do the epochs cover the same tunnel?"
        )
    # the registration's error along the surface normals: the misfit the scans' own noise
    # does not explain, or that neighbouring points share (tunneldef.registration.verify)
    check = reg_all.registration_check
    reg_sigma = check.registration_sigma if check is not None else 0.0
    if tiles is None:
        d = compute_deformation(ref.xyz, moved.xyz, ref_cl, settings=config.deformation,
                                projection=projection, registration_sigma=reg_sigma,
                                progress=under(progress, "deformation"))
    else:
        from .tiles import tiled_deformation

        d = tiled_deformation(ref.xyz, moved.xyz, ref_cl, settings=config.deformation,
                              chainage=chainage, surface=surface,
                              registration_sigma=reg_sigma, progress=progress, **tiles)
        del chainage, surface
    reg_all.quality.add(deformation_checks(d, config.quality))
    if not reg_all.quality.verified:
        log.warning("%s: %s", UNVERIFIED, "; ".join(c.reason() for c in reg_all.quality.failed))
    timings["deformation"] = time.perf_counter() - t

    t = time.perf_counter()
    notify(progress, "sections and danger zones", 0.0)
    dc = config.danger
    threshold = danger_threshold(d, threshold=dc.threshold, rule=dc.rule)
    danger, zones = danger_zones(d, threshold=threshold, rule="absolute",
                                 min_zone_length=dc.min_zone_length, merge_gap=dc.merge_gap,
                                 neighbours=dc.neighbours, peak_points=dc.peak_points)
    sections = section_statistics(d, step=config.deformation.section_step,
                                  thickness=config.deformation.section_thickness)
    fields = d.fields()
    fields["danger"] = np.asarray(danger, dtype=np.uint8)
    moved.add_fields(fields)
    if not reg_all.quality.verified:
        moved.meta["note"] = UNVERIFIED
    notify(progress, "sections and danger zones", 1.0)
    timings["sections_and_danger"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0

    return Result(
        cloud=moved,
        transform=transform,
        registration=reg,
        ref_centerline=ref_cl,
        cmp_centerline=(reg_all.moved_cmp_centerline if reg_all.moved_cmp_centerline
                        is not None else reg_all.cmp_extraction.centerline.transformed(transform)),
        deformation=d,
        sections=sections,
        zones=zones,
        danger_threshold=threshold,
        config=config,
        ref_slices=list(reg_all.ref_extraction.slices),
        cmp_slices=list(reg_all.cmp_extraction.slices),
        timings=timings,
        quality=reg_all.quality,
        drift_correction=reg_all.drift_correction,
    )


# ---------------------------------------------------------------------------------------------
# drift networks
# ---------------------------------------------------------------------------------------------


def _carried(before: np.ndarray, after: np.ndarray, pts: np.ndarray, k: int = 16) -> np.ndarray:
    """The displacement (K, 3) that moved the points ``before`` to ``after`` (a drift
    correction), carried to other points ``pts``: the median over their ``k`` nearest points
    within 5 m (0 where none)."""
    from scipy.spatial import cKDTree

    sub = slice(None, None, max(len(before) // 200_000, 1))
    src, disp = before[sub], after[sub] - before[sub]
    d, j = cKDTree(src).query(pts, k=k, distance_upper_bound=5.0)
    out = np.zeros((len(pts), 3))
    found = np.isfinite(d)
    for i in range(3):
        v = np.where(found, disp[np.minimum(j, len(src) - 1), i], np.nan)
        some = found.any(axis=1)
        out[some, i] = np.nanmedian(v[some], axis=1)
    return out


def _check_edges(extraction: Any, report: QualityReport, config: Config, epoch: str) -> None:
    """Every edge's checks into ``report``; a short dead end that fails its own checks (a
    cross-cut seen a few metres in, mostly its mouth) is left out of the network instead
    (``[network] max_left_out_length``), with a warning and the reason in the network's
    ``meta["left_out"]``. The compared epoch's checks are advisory: its curves only feed
    the registration, which is checked on its own (:func:`~tunneldef.quality.edge_checks`)."""
    from .centerline.network import JUNCTION

    net = extraction.network
    drop: dict[int, str] = {}
    for e in net.edges:
        checks = edge_checks(e, config.quality, epoch, JUNCTION, advisory=epoch == "compared")
        bad = [c for c in checks if not c.passed]
        if bad and net.is_dead_end(e.id) and e.length <= config.network.max_left_out_length:
            c = bad[0]
            op = ">" if c.comparison == "<=" else "<"
            drop[e.id] = f"{c.name} {c.figure:.4g} {op} limit {c.limit:.4g}"
            log.warning("%s network: dead end %s (%.1f m) left out of the measurement: %s",
                        epoch, e.name, e.length, drop[e.id])
            continue
        report.add(checks)
    extraction.network = net.without(drop)


@dataclass
class NetworkResult:
    """Everything :func:`detect_network` found.

    Attributes
    ----------
    cloud : Cloud
        The compared epoch's points (same order, original fields) in the reference frame, with
        the fields of :class:`Result` plus uint16 ``branch`` (the reference edge a point is
        measured against; 65535 for none); ``chainage`` is along that edge.
    transform : ndarray, shape (4, 4)
        Compared -> reference rigid transform.
    registration : NetworkRegistration
    ref_network, cmp_network : CenterlineNetwork
        The compared network is given in the reference frame.
    sections, zones : list of dict
        Per-section statistics and danger zones, each with ``branch`` and ``branch_name``.
    common_length : dict of int -> float
        Per reference edge, the length both epochs cover, metres.
    drift_correction : dict
        Whether the piecewise-rigid SLAM-drift correction was used, its residuals and blocks
        (:func:`~tunneldef.registration.network.correct_drift`); the compared points in
        ``cloud`` carry it, ``transform`` is the rigid part only.
    quality : QualityReport
        Every self-check: each edge's centreline in both epochs, the registration
        (:func:`~tunneldef.registration.verify.verify_network`), each edge's deformation.
    registration_check : NetworkCheck or None
        The registration's independent figures.
    """

    cloud: Cloud
    transform: np.ndarray
    registration: Any
    ref_network: Any
    cmp_network: Any
    sections: list[dict[str, Any]]
    zones: list[dict[str, Any]]
    danger_threshold: float
    common_length: dict[int, float]
    config: Config
    timings: dict[str, float] = field(default_factory=dict)
    drift_correction: dict[str, Any] = field(default_factory=dict)
    quality: QualityReport = field(default_factory=QualityReport)
    registration_check: Any = None

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable summary: transform, both networks, per-edge names, lengths and
        common lengths, sections and danger zones keyed by branch and chainage, the quality
        block, parameters."""
        d = np.asarray(self.cloud.fields["deformation"], dtype=np.float64)
        shell = np.asarray(self.cloud.fields["shell"], dtype=bool)
        branch = np.asarray(self.cloud.fields["branch"])
        edges = []
        for e in self.ref_network.edges:
            v = d[shell & (branch == e.id) & np.isfinite(d)]
            width, height, _ = e.section_size()
            edges.append({
                "branch": e.id, "name": e.name, "length_m": e.length,
                "width_m": width if np.isfinite(width) else None,
                "height_m": height if np.isfinite(height) else None,
                "common_length_m": self.common_length.get(e.id, 0.0),
                "junction_zones_m": [list(z) for z in e.zones],
                "shell_points": int(v.size),
                "mean_abs_m": float(np.mean(np.abs(v))) if v.size else None,
            })
        return {
            "software": {"name": "tunneldef", "version": __version__},
            "transform_compared_to_reference": np.asarray(self.transform).tolist(),
            "registration": self.registration.to_dict(),
            "drift_correction": self.drift_correction,
            "registration_check": (self.registration_check.to_dict()
                                   if self.registration_check is not None else None),
            "quality": self.quality.to_dict(),
            "branches": edges,
            "branches_left_out": {
                "reference": self.ref_network.meta.get("left_out", []),
                "compared": self.cmp_network.meta.get("left_out", []),
            },
            "danger_threshold_m": self.danger_threshold,
            "danger_zones": self.zones,
            "sections": self.sections,
            "reference_network": self.ref_network.to_dict(),
            "compared_network": self.cmp_network.to_dict(),
            "parameters": self.config.to_dict(),
            "timings_s": self.timings,
            "sign_convention": "negative = the surface moved into the tunnel (roof sag, wall "
                               "bulge, floor heave); positive = outward",
        }


def detect_network(
    ref: Cloud, cmp: Cloud, config: Config | None = None, *,
    progress: ProgressCallback | None = None,
    tiles: dict[str, Any] | None = None,
) -> NetworkResult:
    """Deformation of a drift network: every compared point measured against its branch.

    Steps: the centreline network of each epoch
    (:func:`~tunneldef.centerline.network.extract_network`), registration by the common part
    of the two graphs (:func:`~tunneldef.registration.network.register_networks`), then per
    reference edge the single-tube deformation, sections and danger zones on the compared
    points that belong to that edge (and the reference points near it).

    ``tiles``: as for :func:`detect`, the keyword arguments of
    :func:`tunneldef.tiles.tiled_deformation`; each edge's deformation then runs in its own
    chainage tiles.

    Raises
    ------
    TunnelDefError
        As :func:`detect`; :class:`~tunneldef.errors.NetworkError` for a network the method
        cannot vouch for.
    """
    from .centerline.network import extract_network
    from .deformation import (
        compute_deformation,
        danger_threshold,
        danger_zones,
        section_statistics,
    )
    from .network import NO_BRANCH
    from .registration.network import common_lengths, correct_drift, register_networks
    from .registration.verify import edge_centreline_differences, verify_network

    config = config or Config()
    qc = config.quality
    report = QualityReport(enforced=qc.enforce)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    check_epochs(ref, cmp, network=True)
    lines = {"slicing": config.slicing, "settings": config.centerline,
             "network": config.network}
    with epoch_named("reference"):
        ref_net = extract_network(ref.xyz, **lines, progress=under(progress, "reference network"))
    _check_edges(ref_net, report, config, "reference")
    report.add([upright_check(ref_net, config.quality)])
    with epoch_named("compared"):
        cmp_net = extract_network(cmp.xyz, **lines, progress=under(progress, "compared network"),
                                  leave_out_any=True)
    _check_edges(cmp_net, report, config, "compared")
    _check_section_sizes(ref_net, cmp_net)
    timings["centrelines"] = time.perf_counter() - t0
    t = time.perf_counter()
    reg = register_networks(ref.xyz, cmp.xyz, ref_net.network, cmp_net.network)
    transform = np.asarray(reg.transform, dtype=np.float64)
    moved = cmp.transformed(transform)
    net = ref_net.network
    drift: dict[str, Any] = {"used": False, "enabled": config.network.drift_correction}
    cmp_curves = [e.centerline.transformed(transform).points for e in cmp_net.network.edges]
    if config.network.drift_correction:
        xyz, drift = correct_drift(ref.xyz, moved.xyz, net, **_drift_settings(config))
        drift["enabled"] = True
        _log_drift(drift)
        if drift["used"]:
            cmp_curves = [p + _carried(moved.xyz, xyz, p) for p in cmp_curves]
        moved = Cloud(xyz, moved.fields, moved.meta)
    notify(progress, "registration check", 0.0)
    check = verify_network(ref.xyz, moved.xyz, net.length,
                           points_per_metre=config.registration.max_points_per_metre)
    check = dataclasses.replace(check, alternative_margin=reg.evidence - reg.alternative_evidence)
    notify(progress, "registration check", 1.0)
    report.add(network_registration_checks(check, qc))
    report.add(edge_difference_checks(edge_centreline_differences(net, cmp_curves), qc))
    reg_sigma = check.registration_sigma
    timings["registration"] = time.perf_counter() - t
    t = time.perf_counter()
    reach = 2.0 * max(float(ref_net.grid.half_width.max()), 1.0)
    # each point's edge, a chunk at a time (full-size projections of both epochs would take
    # about 100 bytes per point)
    branch_c = net.branches(moved.xyz, max_distance=reach, chunk=_CHUNK)
    branch_r = net.branches(ref.xyz, max_distance=reach, chunk=_CHUNK)
    n = len(moved.xyz)
    out: dict[str, np.ndarray] = {}
    branch = np.full(n, NO_BRANCH, dtype=np.uint16)
    dc = config.danger
    results = []
    for e in net.edges:
        # both epochs cut alike: the points assigned to this edge (reference points of other
        # drifts near a junction put the shell envelope of a section where the compared
        # epoch has none, and read as false change of 0.2 m beside a 45 degree junction)
        mc = np.flatnonzero(branch_c == e.id)
        mr = branch_r == e.id
        if len(mc) < 1000 or mr.sum() < 1000:
            continue
        notify(progress, "deformation", e.id / len(net.edges))
        proj = e.centerline.project(moved.xyz[mc])
        if tiles is None:
            d = compute_deformation(ref.xyz[mr], moved.xyz[mc], e.centerline,
                                    settings=config.deformation, projection=proj,
                                    registration_sigma=reg_sigma)
        else:  # the edge's own chainage tiles, as Dask tasks
            from .deformation.sections import surface_labels
            from .tiles import tiled_deformation

            surface = surface_labels(proj.chainage, proj.lateral, proj.vertical,
                                     step=config.deformation.section_step)
            d = tiled_deformation(ref.xyz[mr], moved.xyz[mc], e.centerline,
                                  settings=config.deformation, chainage=proj.chainage,
                                  surface=surface, registration_sigma=reg_sigma, **tiles)
        report.add([dataclasses.replace(c, name=c.name.replace(".", f".edge{e.id}.", 1))
                    for c in deformation_checks(d, qc)])
        results.append((e, mc, d))
        branch[mc] = e.id
        for k, v in d.fields().items():
            if k not in out:
                fill = np.nan if v.dtype.kind == "f" else 0
                out[k] = np.full(n, fill, dtype=v.dtype)
            out[k][mc] = v
    if not results:
        raise EpochMismatchError("no branch of the reference network has compared points "
                                 "after registration; do the epochs cover the same drifts?")
    timings["deformation"] = time.perf_counter() - t
    t = time.perf_counter()
    threshold = float(np.median([danger_threshold(d, threshold=dc.threshold, rule=dc.rule)
                                 for _, _, d in results]))
    danger = np.zeros(n, dtype=np.uint8)
    sections: list[dict[str, Any]] = []
    zones: list[dict[str, Any]] = []
    for e, mc, d in results:
        flags, zs = danger_zones(d, threshold=threshold, rule="absolute",
                                 min_zone_length=dc.min_zone_length, merge_gap=dc.merge_gap,
                                 neighbours=dc.neighbours, peak_points=dc.peak_points)
        danger[mc] = np.asarray(flags, dtype=np.uint8)
        keyed = {"branch": e.id, "branch_name": e.name}
        # a zone at a junction (or beyond the edge's ends, inside another drift) is flagged:
        # there the section is no tunnel section
        zones += [{**keyed, **z, "junction": bool(
            np.any(e.in_zone(np.array([z["start"], z["end"]])))
            or z["start"] < 0.0 or z["end"] > e.length)} for z in zs]
        sections += [{**keyed, **s} for s in section_statistics(
            d, step=config.deformation.section_step,
            thickness=config.deformation.section_thickness)]
    out["danger"] = danger
    out["branch"] = branch
    moved.add_fields(out)
    if not report.verified:
        moved.meta["note"] = UNVERIFIED
        log.warning("%s: %s", UNVERIFIED, "; ".join(c.reason() for c in report.failed))
    common = common_lengths(net, ref.xyz, moved.xyz)
    timings["sections_and_danger"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0
    return NetworkResult(moved, transform, reg, net, cmp_net.network.transformed(transform),
                         sections, zones, threshold, common, config, timings, drift, report,
                         check)
