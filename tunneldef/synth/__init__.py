"""Synthetic mine-tunnel epochs with exact ground truth, for tests, the demo and benchmarks.

A tunnel is a cross-section outline (rectangle, arch or trapezoid; paper §4: rectangular,
5.8 m x 2.86 m) swept along a design axis (straight or a horizontal circular curve, with a
constant grade). Points are drawn on the shell at a given density (points per m^2) with
Gaussian noise, occlusion holes, uneven density along the walk and outliers; optional clutter
(pipes and cables on the walls, a conveyor belt with a coal load, a side chamber) makes it look
like a working coal-mine roadway.

:func:`make_tunnel` gives one epoch in the design frame. :func:`make_pair` gives two epochs:
the reference in the design frame and the compared epoch, independently resampled over a shifted
stretch, deformed (roof sag, wall bulge, floor heave) and moved by a rigid motion, with per-point
truth (coordinates in the reference frame, signed normal displacement, chainage, label, surface).

Coordinates of a section are ``(u, v)``: ``u`` lateral, positive to the LEFT of increasing
chainage, ``v`` perpendicular to the axis, positive up; the design axis is the section centre
(mid-width, mid-height between floor and roof/crown), as in
:class:`tunneldef.curve.Centerline`. Deformation sign (the paper's, §3.3.2):
negative = the shell moved into the tunnel.

Notes
-----
- Noise: isotropic Gaussian on x, y and z, sigma 0.015 m by default: the scanner's stated
  ±3 cm (paper §4, Table 1) read as 2 sigma.
- Points are stored in walk order (increasing chainage), like a SLAM scan along the drift.
- Truth chainage is that of the noisy point: exact on a straight axis, first-order on a curve.
- Truth displacement is the movement of the shell along the design outline's normal; it is 0
  for equipment, coal, people and outliers (select the shell with ``label == 0``).
- Everything is vectorised: about 1 s per million points on one core; a pair of two
  16-19 M point epochs peaks below 3 GB of memory.

Modules: ``design`` (specifications, outlines, deformation patches), ``scene`` (what both
epochs share: axis, relief, clutter), ``sampling`` (drawing one epoch's points); this package
chains them and holds the truth records.

One idea at this length: the public face of the generator (pair, tunnel, truth, writing) that
the tests, the demo and the benchmarks use.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cloud import Cloud
from ..curve import Centerline
from ..progress import ProgressCallback, notify, timed_stage
from ..transforms import apply_transform
from .design import (
    LABEL_DYNAMIC,
    LABEL_EQUIPMENT,
    LABEL_OUTLIER,
    LABEL_SHELL,
    SURFACE_FLOOR,
    SURFACE_LEFT,
    SURFACE_NONE,
    SURFACE_RIGHT,
    SURFACE_ROOF,
    DeformationSpec,
    Outline,
    PairSpec,
    SectionSpec,
    TunnelSpec,
    _check_deformations,
    _rigid_motion,
    section_outline,
)
from .network import (
    BranchDeformation,
    EdgeSpec,
    JunctionSpec,
    NetworkPair,
    NetworkPairSpec,
    NetworkSpec,
    Stretch,
    make_network_pair,
    network_250m,
    network_250m_pair,
    ramp_survey,
    ramp_survey_pair,
    write_network_pair,
)
from .sampling import _sample_epoch, write_epochs
from .scene import _Axis, _draw_heaps, _make_scene, _pair_scene

__all__ = [
    "SectionSpec",
    "TunnelSpec",
    "DeformationSpec",
    "PairSpec",
    "Outline",
    "TunnelTruth",
    "PairTruth",
    "SynthPair",
    "make_tunnel",
    "make_pair",
    "section_outline",
    "write_pair",
    "LABEL_SHELL",
    "LABEL_EQUIPMENT",
    "LABEL_DYNAMIC",
    "LABEL_OUTLIER",
    "SURFACE_ROOF",
    "SURFACE_LEFT",
    "SURFACE_RIGHT",
    "SURFACE_FLOOR",
    "SURFACE_NONE",
    "EdgeSpec",
    "JunctionSpec",
    "NetworkSpec",
    "BranchDeformation",
    "Stretch",
    "NetworkPairSpec",
    "NetworkPair",
    "make_network_pair",
    "write_network_pair",
    "network_250m",
    "network_250m_pair",
    "ramp_survey",
    "ramp_survey_pair",
]

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# public results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TunnelTruth:
    """Ground truth of one epoch (arrays shape (N,), in the cloud's point order).

    Attributes
    ----------
    label : uint8, 0 shell, 1 equipment, 2 dynamic (coal load), 3 outlier.
    surface : uint8, 0 roof, 1 left wall, 2 right wall, 3 floor, 255 not shell.
    chainage : float64, m along the design axis (``centerline``) of the noisy point.
    displacement : float64, signed normal displacement of shell points, m (negative = into
        the tunnel); 0 for undeformed points and for every non-shell point.
    centerline : Centerline of the design axis (section centre), chainage 0 at its start.
    outline : the design section :class:`Outline` (``signed_distance(lateral, vertical)``).
    chainage_range : (start, end) of the scanned stretch on the design axis, m.
    chamber : bool, True on the side chamber's rock surfaces (label 0, outside the outline).
    """

    label: np.ndarray
    surface: np.ndarray
    chainage: np.ndarray
    displacement: np.ndarray
    centerline: Centerline
    outline: Outline
    chainage_range: tuple[float, float]
    chamber: np.ndarray | None = None


@dataclass(frozen=True)
class PairTruth:
    """Ground truth of an epoch pair; ``cmp`` arrays shape (N,), ``ref_*`` shape (M,).

    Attributes
    ----------
    transform : (4, 4) float64, maps compared-epoch coordinates to the reference frame.
    cmp_xyz_in_ref : (N, 3) float64, the compared points in the reference frame
        (``transform`` applied to ``cmp.xyz``; noise included).
    displacement, chainage, label, surface : per compared point (see :class:`TunnelTruth`).
    ref_label, ref_chainage, ref_surface : per reference point.
    centerline : design axis in the reference frame, chainage 0 at the start of the reference.
    outline : design section outline.
    deformations : the applied deformations.
    ref_range, cmp_range : scanned stretches on the reference design axis, m.
    yaw_deg, tilt_deg, tilt_axis : the rigid motion's rotation (tilt axis horizontal, (3,)).
    chamber, ref_chamber : bool, True on the side chamber's rock surfaces (label 0).
    """

    transform: np.ndarray
    cmp_xyz_in_ref: np.ndarray
    displacement: np.ndarray
    chainage: np.ndarray
    label: np.ndarray
    surface: np.ndarray
    ref_label: np.ndarray
    ref_chainage: np.ndarray
    ref_surface: np.ndarray
    centerline: Centerline
    outline: Outline
    deformations: tuple[DeformationSpec, ...]
    ref_range: tuple[float, float]
    cmp_range: tuple[float, float]
    yaw_deg: float
    tilt_deg: float
    tilt_axis: np.ndarray
    chamber: np.ndarray | None = None
    ref_chamber: np.ndarray | None = None

    @property
    def cmp_centerline(self) -> Centerline:
        """The design axis over the compared stretch, in the compared epoch's frame (its
        chainage 0 at the start of the compared stretch)."""
        axis = _Axis(self.centerline.meta["radius"], self.centerline.meta["grade"])
        return axis.centerline(*self.cmp_range).transformed(np.linalg.inv(self.transform))


@dataclass(frozen=True)
class SynthPair:
    """A reference epoch, a compared epoch and their truth."""

    ref: Cloud
    cmp: Cloud
    truth: PairTruth
    spec: PairSpec


# --------------------------------------------------------------------------------------------
# entry points
# --------------------------------------------------------------------------------------------


def _streams(seed: int) -> list[np.random.Generator]:
    # scene, reference sampling, compared sampling, rigid motion, compared coal
    return [np.random.default_rng(c) for c in np.random.SeedSequence(seed).spawn(5)]


def make_tunnel(
    tunnel: TunnelSpec | None = None,
    *,
    seed: int = 0,
    deformations: tuple[DeformationSpec, ...] = (),
    progress: ProgressCallback | None = None,
) -> tuple[Cloud, TunnelTruth]:
    """One synthetic epoch in the design frame (z up, axis starting at the origin along +x).

    Parameters
    ----------
    tunnel : TunnelSpec, optional
        Geometry and scanning parameters (default: a 30 m straight rectangular drift).
    seed : int
        Random seed; the same seed gives the same cloud as the reference of :func:`make_pair`.
    deformations : tuple of DeformationSpec
        Deformations applied to this epoch (none by default).
    progress : ProgressCallback, optional
        Called with ``("synthetic epoch", fraction)``.

    Returns
    -------
    cloud : Cloud
        ``xyz`` (N, 3) in metres and a ``uint16`` ``intensity`` field.
    truth : TunnelTruth
    """
    tunnel = TunnelSpec() if tunnel is None else tunnel
    deformations = tuple(deformations)
    _check_deformations(tunnel, deformations)
    g_scene, g_ref, _, _, _ = _streams(seed)
    scene = _make_scene(tunnel, g_scene)
    heaps = _draw_heaps(g_scene, 0.0, tunnel.length) if tunnel.conveyor else None
    notify(progress, "synthetic epoch", 0.0)
    with timed_stage(log, "synthetic epoch"):
        ep = _sample_epoch(scene, 0.0, tunnel.length, g_ref, deformations, heaps)
    notify(progress, "synthetic epoch", 1.0)
    cloud = Cloud(
        ep["xyz"],
        {"intensity": ep["intensity"]},
        {"source": "tunneldef.synth", "epoch": "ref", "seed": seed},
    )
    truth = TunnelTruth(
        ep["label"],
        ep["surface"],
        ep["chainage"],
        ep["displacement"],
        scene.axis.centerline(0.0, tunnel.length),
        scene.outline,
        (0.0, float(tunnel.length)),
        ep["chamber"],
    )
    log.debug("synthetic epoch: %d points", len(cloud))
    return cloud, truth






def make_pair(
    spec: PairSpec | None = None, *, progress: ProgressCallback | None = None, **changes
) -> SynthPair:
    """Two epochs of a synthetic tunnel with exact ground truth.

    Parameters
    ----------
    spec : PairSpec, optional
        The pair; keyword arguments (any :class:`PairSpec` field, e.g. ``seed=1,
        tunnel=TunnelSpec(...)``) build or override it.
    progress : ProgressCallback, optional
        Called with ``("synthetic pair", fraction)``.

    Returns
    -------
    SynthPair
        ``ref`` in the design (reference) frame; ``cmp`` resampled over
        ``[cmp_shift, cmp_shift + cmp_length]``, deformed, and moved by a rigid motion
        (yaw, tilt about a random horizontal axis, translation); ``truth`` (:class:`PairTruth`).

    Notes
    -----
    Epochs share the scene (section, axis, pipes, conveyor, chamber) but not the draw: point
    positions, noise, holes, density modulation and outliers are independent; the coal load
    changes when ``coal_change``.
    """
    if spec is None:
        spec = PairSpec(**changes)
    elif changes:
        spec = dataclasses.replace(spec, **changes)
    g_scene, g_ref, g_cmp, g_motion, g_coal = _streams(spec.seed)
    scene, ref_range, cmp_range, heaps_ref, heaps_cmp = _pair_scene(spec, g_scene, g_coal)
    notify(progress, "synthetic pair", 0.0)
    with timed_stage(log, "synthetic reference epoch"):
        ref = _sample_epoch(scene, *ref_range, g_ref, (), heaps_ref)
    notify(progress, "synthetic pair", 0.5)
    with timed_stage(log, "synthetic compared epoch"):
        cmp = _sample_epoch(scene, *cmp_range, g_cmp, spec.deformations, heaps_cmp)
    notify(progress, "synthetic pair", 0.95)

    motion, transform, yaw, tilt_axis = _rigid_motion(
        g_motion, spec.yaw_deg, spec.tilt_deg, spec.translation
    )

    local = cmp.pop("xyz")
    cmp_xyz = apply_transform(motion, local, blas=False)
    del local
    in_ref = apply_transform(transform, cmp_xyz, blas=False)

    ref_cloud = Cloud(
        ref["xyz"],
        {"intensity": ref["intensity"]},
        {"source": "tunneldef.synth", "epoch": "ref", "seed": spec.seed},
    )
    cmp_cloud = Cloud(
        cmp_xyz,
        {"intensity": cmp["intensity"]},
        {"source": "tunneldef.synth", "epoch": "cmp", "seed": spec.seed},
    )
    truth = PairTruth(
        transform=transform,
        cmp_xyz_in_ref=in_ref,
        displacement=cmp["displacement"],
        chainage=cmp["chainage"],
        label=cmp["label"],
        surface=cmp["surface"],
        ref_label=ref["label"],
        ref_chainage=ref["chainage"],
        ref_surface=ref["surface"],
        centerline=scene.axis.centerline(*ref_range),
        outline=scene.outline,
        deformations=spec.deformations,
        ref_range=ref_range,
        cmp_range=cmp_range,
        yaw_deg=float(yaw),
        tilt_deg=float(spec.tilt_deg),
        chamber=cmp["chamber"],
        ref_chamber=ref["chamber"],
        tilt_axis=tilt_axis,
    )
    log.debug("synthetic pair: %d reference, %d compared points", len(ref_cloud), len(cmp_cloud))
    notify(progress, "synthetic pair", 1.0)
    return SynthPair(ref_cloud, cmp_cloud, truth, spec)


def write_pair(pair: SynthPair, out_dir: str | Path, *, fmt: str = "ply") -> dict[str, Path]:
    """Write ``ref.<fmt>``, ``cmp.<fmt>`` and ``truth.npz`` into ``out_dir``.

    Clouds go through :func:`tunneldef.io.write` (only the ``intensity`` field; truth stays in
    ``truth.npz``: every truth array, the 4 x 4 transform, the centreline samples and the
    pair's specification as JSON in ``spec_json``; ``np.load`` reads it without pickle).

    Returns
    -------
    dict
        ``{"ref": path, "cmp": path, "truth": path}``.
    """
    paths = write_epochs(pair.ref, pair.cmp, out_dir, fmt)
    t = pair.truth
    np.savez_compressed(
        paths["truth"],
        transform=t.transform,
        cmp_xyz_in_ref=t.cmp_xyz_in_ref,
        displacement=t.displacement,
        chainage=t.chainage,
        label=t.label,
        surface=t.surface,
        ref_label=t.ref_label,
        ref_chainage=t.ref_chainage,
        ref_surface=t.ref_surface,
        chamber=t.chamber,
        ref_chamber=t.ref_chamber,
        centerline_points=t.centerline.points,
        centerline_chainage=t.centerline.chainage,
        ref_range=np.array(t.ref_range),
        cmp_range=np.array(t.cmp_range),
        spec_json=np.array(json.dumps(dataclasses.asdict(pair.spec))),
    )
    return paths

