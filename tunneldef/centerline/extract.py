"""Tunnel centreline from a point cloud (paper §3.1).

Steps of :func:`extract_centerline`:

1. PCA tunnel frame (:func:`tunneldef.frame.principal_frame`, paper §3.1.1). If the floor and
   roof share a cross-slope (an unlevelled scanner, a rigidly tilted epoch) the section's roll is
   removed first, so floor and roof are level in every slice.
2. Slices along the frame's x (:mod:`.slicing`).
3. Per slice: floor and roof from the first and last significant peaks of the height density
   (:mod:`.roof_floor`, paper §3.1.2), walls from the top view of the wall band: linear-kernel
   density, Canny, Hough, first and last lines (:mod:`.walls`, paper §3.1.3). The slice centre
   is the midpoint of floor/roof and of the two walls.
4. Slices that failed (too few points, no peak, a wall missing, width or height jumping against
   their neighbours: chambers, niches, blind cones) are rejected with a reason.
5. A least-squares cubic NURBS through the accepted centres (:mod:`.fit`, paper §3.1.4).
6. Curved tunnels: the paper slices along one global x, which cuts a bend obliquely. The cloud
   is therefore re-sliced normal to the fitted curve (chainage, lateral, vertical from
   :meth:`Centerline.project`) and refitted until the curve moves less than
   ``converge_tol`` or ``max_iterations`` passes are done.

Why re-slicing could run away, and what keeps it safe: a least-squares curve has free ends,
and where the end centres are sparse or noisy the end hooks. Projection used to scale the
chainage of every point beyond such an end by the end's curvature, so the next pass sliced the
end obliquely and over a stretched chainage, its centres hooked further, and the curve moved by
metres from pass to pass (and grew longer than the cloud). Now: beyond its ends a curve goes on
straight (:meth:`Centerline.project`); a curve turning tighter than half its section is
stiffened (control points twice as far apart, up to 8x); in a re-slicing pass a slice centre
farther from the curve it was cut along than a trust radius (half the width, then three times
the last move) is rejected; every pass is judged (:class:`PassQuality`: residuals, usable
share, length against the cloud's extent along it, distance to the cloud, tightest turn, move
against the trust radius) and one that is impossible, or fits its centres clearly worse than
the best so far, ends the iteration. The last pass is kept when the passes settled, the
best-scoring one when they did not; if not even the first is possible, NotATunnelError. The
slices' span is checked against the longest centreline the cloud can hold
(:func:`plausible_length`) before a curve is sampled, so no time or memory goes into a curve
the data cannot have.

One idea at this length: stage 1's passes and the per-pass quality that decides which pass is
kept; slicing, the section lines and the fit live in their own modules.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import check_points
from ..config import CenterlineConfig, SlicingConfig
from ..curve import Centerline, Projection
from ..engine import thread_map
from ..errors import NotATunnelError
from ..frame import TunnelFrame, principal_frame
from ..progress import ProgressCallback, notify
from ..spatial import random_keep
from .fit import fit_centerline, fit_stiffest
from .roof_floor import Crown, RoofFloor, crown_height, estimate_roll, roof_floor_lines
from .slicing import slice_along_axis
from .walls import WallLines, estimate_wall_leans, wall_lines

__all__ = [
    "Centerline",
    "Projection",
    "SliceRecord",
    "CenterlineResult",
    "PassQuality",
    "plausible_length",
    "extract_centerline",
    "analyse_slice",
    "smooth_roof_lifts",
]

logger = logging.getLogger(__name__)


@dataclass
class SliceRecord:
    """What one slice gave (lengths in metres).

    Attributes
    ----------
    station : float
        Along-axis position of the slice in the pass that produced it (PCA x or the previous
        curve's chainage).
    chainage : float
        Chainage of the slice centre on the final centreline (NaN if the slice has no centre).
    centre : ndarray, shape (3,)
        World coordinates of the slice centre (NaN if rejected).
    width, height : float
        Wall-to-wall and floor-to-roof distances.
    floor, roof : float
        Vertical offsets of the floor and roof lines from the slicing axis.
    left, right : float
        Lateral offsets of the left (+) and right (-) wall lines from the slicing axis.
    methods : dict
        How each line was found: ``{"floor": "kde_peak", "roof": ..., "left": "hough" |
        "fallback", "right": ...}`` ("" where it was not).
    ok : bool
        True if the centre was used for the centreline.
    reason : str
        Why the slice was rejected ("" if ok).
    n_points : int
        Points in the slice.
    weight : float
        Robust weight of the centre in the NURBS fit (NaN if not used).
    roof_lift : float
        How far the roof was raised above its density peak towards an arch's crown (judged
        on the neighbouring slices' crown fits; 0 on a flat roof).
    crown : Crown or None
        This slice's own crown fit (:func:`.roof_floor.crown_height`).
    """

    station: float
    chainage: float = np.nan
    centre: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    width: float = np.nan
    height: float = np.nan
    floor: float = np.nan
    roof: float = np.nan
    left: float = np.nan
    right: float = np.nan
    methods: dict[str, str] = field(default_factory=dict)
    ok: bool = False
    reason: str = ""
    n_points: int = 0
    weight: float = np.nan
    roof_lift: float = 0.0
    crown: Crown | None = None

    def row(self) -> dict[str, Any]:
        """Flat dict for a CSV row."""
        return {
            "chainage": self.chainage,
            "station": self.station,
            "x": float(self.centre[0]),
            "y": float(self.centre[1]),
            "z": float(self.centre[2]),
            "width": self.width,
            "height": self.height,
            "floor": self.floor,
            "roof": self.roof,
            "left": self.left,
            "right": self.right,
            "floor_method": self.methods.get("floor", ""),
            "roof_method": self.methods.get("roof", ""),
            "left_method": self.methods.get("left", ""),
            "right_method": self.methods.get("right", ""),
            "ok": self.ok,
            "reason": self.reason,
            "n_points": self.n_points,
            "weight": self.weight,
        }


@dataclass
class CenterlineResult:
    """Output of :func:`extract_centerline`.

    Attributes
    ----------
    centerline : Centerline
        The fitted centreline (world coordinates).
    slices : list of SliceRecord
        The slices of the last pass, in order of chainage.
    frame : TunnelFrame
        The PCA frame of the cloud.
    passes : int
        Slicing passes run (1 = the paper's single pass along the PCA axis).
    axis : Centerline or None
        The curve the last pass was sliced along (None when it was the PCA axis).
    slicing : SlicingConfig
        The slicing parameters used.
    settings : CenterlineConfig
        The line and curve parameters used.
    roll : float
        Roll of the section about the axis (radians, positive = the floor rises to the left),
        estimated from the floor and roof cross-slopes and removed before the lines are found;
        0 for a levelled scan.
    leans : (float, float)
        Lean dv/dz of the left and right walls (0 = vertical), measured once per cloud; leaning
        walls are measured at the middle of the wall band.
    quality : list of PassQuality
        Every pass's quality figures (also rejected passes); ``quality_of_curve`` is the
        chosen one's.
    """

    centerline: Centerline
    slices: list[SliceRecord]
    frame: TunnelFrame
    passes: int = 1
    axis: Centerline | None = None
    slicing: SlicingConfig = field(default_factory=SlicingConfig)
    settings: CenterlineConfig = field(default_factory=CenterlineConfig)
    roll: float = 0.0
    leans: tuple[float, float] = (0.0, 0.0)
    quality: list[PassQuality] = field(default_factory=list)

    @property
    def quality_of_curve(self) -> PassQuality | None:
        """Quality figures of the pass that gave :attr:`centerline` (None if unknown)."""
        return next((q for q in self.quality if q.number == self.passes), None)

    def table(self) -> list[dict[str, Any]]:
        """One dict per slice (see :meth:`SliceRecord.row`), for CSV."""
        return [r.row() for r in self.slices]

    @property
    def accepted(self) -> list[SliceRecord]:
        return [r for r in self.slices if r.ok]

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """World (N, 3) coordinates of (along, lateral, vertical) in the last pass's axes."""
        return _local_to_world(np.atleast_2d(local), self.axis, self.frame, self.roll)

    def slice_coordinates(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) along / lateral / vertical coordinates of points in the last pass's axes."""
        return _axis_coordinates(xyz, self.axis, self.frame, self.roll)


def _roll(local: np.ndarray, angle: float | np.ndarray) -> np.ndarray:
    """Rotate (lateral, vertical) by ``-angle`` in place (levels a section rolled by ``angle``;
    one angle, or one per row)."""
    if np.any(angle):
        c, s = np.cos(angle), np.sin(angle)
        v, w = local[:, 1].copy(), local[:, 2].copy()
        local[:, 1] = c * v + s * w
        local[:, 2] = -s * v + c * w
    return local


def _axis_coordinates(
    xyz: np.ndarray, axis: Centerline | None, frame: TunnelFrame, roll: float = 0.0
) -> np.ndarray:
    if axis is None:
        return _roll(frame.to_local(xyz), roll)
    p = axis.project(xyz)
    return _roll(np.stack([p.chainage, p.lateral, p.vertical], axis=1), roll)


def _local_to_world(
    local: np.ndarray, axis: Centerline | None, frame: TunnelFrame, roll: float = 0.0
) -> np.ndarray:
    local = _roll(np.array(local, dtype=np.float64), -roll)
    if axis is None:
        return frame.to_world(local)
    return _curve_to_world(axis)(local)


def analyse_slice(
    local: np.ndarray,
    station: float,
    *,
    slicing: SlicingConfig | None = None,
    settings: CenterlineConfig | None = None,
    leans: tuple[float, float] = (0.0, 0.0),
) -> tuple[RoofFloor, WallLines | None, np.ndarray]:
    """Roof, floor and wall lines of one slice.

    Parameters
    ----------
    local : ndarray, shape (N, 3)
        The slice's points as (along, lateral, vertical), metres.
    station : float
        Along-axis position of the slice, metres.
    slicing, settings : SlicingConfig, CenterlineConfig, optional
        The ``[slicing]`` and ``[centerline]`` parameters.
    leans : (float, float)
        Lean of the left and right wall (dv/dw, 0 = vertical), see
        :func:`~tunneldef.centerline.walls.estimate_wall_leans`.

    Returns
    -------
    roof_floor : RoofFloor
    walls : WallLines or None
        None when the floor or roof is missing (the wall band is then unknown).
    band : ndarray of bool, shape (N,)
        The points of the wall band.
    """
    sl = slicing or SlicingConfig()
    c = settings or CenterlineConfig()
    rf = roof_floor_lines(
        local[:, 2],
        bandwidth=c.kde_bandwidth,
        min_share=c.min_peak_share,
        refine_bandwidth=c.refine_bandwidth,
        lateral=local[:, 1] if c.max_beyond_cover < 1.0 else None,
        beyond_gap=c.beyond_gap,
        max_beyond_cover=c.max_beyond_cover,
    )
    if not rf.ok:
        return rf, None, np.zeros(len(local), dtype=bool)
    h = rf.roof - rf.floor
    band = (local[:, 2] > rf.floor + c.wall_band_low * h) & (
        local[:, 2] < rf.floor + c.wall_band_high * h
    )
    walls = wall_lines(
        local[band, 0],
        local[band, 1],
        station=station,
        thickness=sl.thickness,
        grid_cell=c.grid_cell,
        kernel_half_width=c.wall_kernel,
        max_angle_deg=c.max_wall_angle_deg,
        peak_ratio=c.hough_peak_ratio,
        refine_bandwidth=c.refine_bandwidth,
        w=local[band, 2],
        w_ref=rf.floor + 0.5 * (c.wall_band_low + c.wall_band_high) * h,
        leans=leans,
    )
    if c.crown_fit and walls.ok:
        crown = crown_height(local[:, 1], local[:, 2], rf.roof,
                             0.5 * (walls.left + walls.right), 0.5 * (walls.left - walls.right))
        rf = dataclasses.replace(rf, crown=crown)
    return rf, walls, band


def record_lines(rec: SliceRecord, rf: RoofFloor, walls: WallLines | None) -> bool:
    """Put a slice's section lines and how they were found into its record; False (with the
    reason recorded) when the floor, the roof or a wall is missing."""
    rec.floor, rec.roof, rec.crown = rf.floor, rf.roof, rf.crown
    rec.methods = {"floor": rf.method, "roof": rf.method, "left": "", "right": ""}
    if walls is None:
        rec.reason = rf.reason
        return False
    rec.left, rec.right = walls.left, walls.right
    rec.methods["left"] = rec.methods["right"] = walls.method
    if not walls.ok:
        rec.reason = walls.reason
        return False
    return True


def _slice_pass(
    local: np.ndarray,
    slicing: SlicingConfig,
    settings: CenterlineConfig,
    progress: ProgressCallback | None,
    stage: str,
    leans: tuple[float, float] = (0.0, 0.0),
) -> list[SliceRecord]:
    slices = slice_along_axis(local[:, 0], step=slicing.step, thickness=slicing.thickness)
    records = [SliceRecord(station=sl.station, n_points=len(sl.index)) for sl in slices]
    todo = [i for i, rec in enumerate(records) if rec.n_points >= slicing.min_points]
    for i in set(range(len(records))) - set(todo):
        records[i].reason = f"too few points ({records[i].n_points} < {slicing.min_points})"

    def one(i: int) -> None:
        # each task fills its own slice's record and lets go of the slice's density images
        # (kept for all slices at once they took 0.9 GB over 350 m)
        rf, walls, _ = analyse_slice(local[slices[i].index], slices[i].station,
                                     slicing=slicing, settings=settings, leans=leans)
        rec = records[i]
        if record_lines(rec, rf, walls):
            rec.width, rec.height = rec.left - rec.right, rec.roof - rec.floor
            rec.ok = True

    # slices are independent: Dask's threads run them side by side (the image work releases
    # the GIL); every record is filled from its own slice alone, so the result is the serial
    # one
    notify(progress, stage, 0.0)
    thread_map(one, [(i,) for i in todo], stage=stage, progress=progress)
    notify(progress, stage, 1.0)
    smooth_roof_lifts(records, settings.neighbour_window)
    _reject_jumps(records, settings)
    return records


def smooth_roof_lifts(records: list[SliceRecord], window: float) -> None:
    """Raise each accepted slice's roof from its density peak towards the crown of an arch
    (:meth:`.roof_floor.Crown.lift`), judged on the medians of the crown fits within
    ``window`` m (in place; ``height`` and ``roof_lift`` follow).

    The crown's offset from the peak is a property of the section's shape and the scan's
    noise, both steady along a drift, while one slice's parabola is noisy: on a 2.2 m arched
    drift at +-1.9 cm noise the slices' own crowns scattered the centres by 4 cm (p95)."""
    ok = [r for r in records if r.ok and r.crown is not None and np.isfinite(r.crown.height)]
    if not ok:
        return
    st = np.array([r.station for r in ok])
    fits = np.array([(r.crown.height - r.roof, r.crown.curvature, r.crown.sigma) for r in ok])
    for r in ok:
        near = fits[np.abs(st - r.station) <= window]
        offset, curvature, sigma = np.median(near, axis=0)
        lift = Crown(r.roof + offset, curvature, sigma).lift(r.roof)
        r.roof += lift
        r.roof_lift = lift
        if np.isfinite(r.floor):
            r.height = r.roof - r.floor


def reference_width(widths: np.ndarray, tol: float, share: float = 0.3) -> float:
    """The width a drift has among neighbouring slices' widths: the narrowest width that at
    least ``share`` of them agree with (within ``tol``), as the median of those that do.

    Chambers, niches and junctions only ever widen a tunnel, so the reference is the narrowest
    well-supported width, right even where wide slices are the majority. Slices read too
    narrow (a wall read on pipes; slices cutting a dead end's face, which the walls' lines
    cross) scatter and find too little support. A plain low quantile failed at a face: five
    of seventeen slices narrower than the drift put the 30th percentile 0.3 m below its true
    width and rejected every true slice as a chamber.
    """
    w = np.sort(np.asarray(widths, dtype=np.float64))
    if w.size == 0:
        return float("nan")
    lo = np.searchsorted(w, w - tol, side="left")
    hi = np.searchsorted(w, w + tol, side="right")
    enough = np.flatnonzero(hi - lo >= share * w.size)
    if enough.size == 0:  # no agreement at all: the old low quantile
        return float(np.percentile(w, 100 * share))
    i = int(enough[0])
    return float(np.median(w[lo[i]:hi[i]]))


def _reject_jumps(records: list[SliceRecord], c: CenterlineConfig) -> None:
    """Reject slices whose width or height jumps against their neighbours (within
    ``neighbour_window``): width against :func:`reference_width`, height against the median.

    Then the finer, noise-scaled rule of :func:`_reject_narrow`. Rejected slices are bridged
    by the curve.
    """
    ok = [r for r in records if r.ok]
    if len(ok) < 3:
        return
    st = np.array([r.station for r in ok])
    wid = np.array([r.width for r in ok])
    hei = np.array([r.height for r in ok])
    for r in ok:
        near = np.abs(st - r.station) <= c.neighbour_window
        mw = reference_width(wid[near], c.max_width_jump)
        mh = float(np.median(hei[near]))
        if r.width - mw > c.max_width_jump:
            r.ok, r.reason = False, f"chamber or niche: width {r.width:.2f} m vs {mw:.2f} m nearby"
        elif mw - r.width > c.max_width_jump:
            r.ok, r.reason = (
                False,
                f"inconsistent walls: width {r.width:.2f} m vs {mw:.2f} m nearby",
            )
        elif abs(r.height - mh) > c.max_height_jump:
            r.ok, r.reason = (
                False,
                (f"inconsistent floor/roof: height {r.height:.2f} m vs {mh:.2f} m nearby"),
            )
    _reject_narrow(records, c)


#: A slice wider than its neighbours is left out only beyond this too (its centre moves by
#: half of it): the robust spread of the widths is 3-4 mm on a clean 120 points/m^2 scan,
#: where slices 12 mm wider are harmless, m.
_WIDER_FLOOR = 0.1


def _reject_narrow(records: list[SliceRecord], c: CenterlineConfig, min_slices: int = 10) -> None:
    """Among the slices the jump rules kept, reject those narrower or wider than their
    neighbours' median width, or higher or lower than their median height, by more than
    ``narrow_sigmas`` robust spreads (1.4826 MAD of the values against those medians); with
    fewer than ``min_slices`` the spreads are not known.

    Walls and roof do not move in and out by centimetres from one slice to the next, but a
    wall read on pipes where a hole hides it does, so does a wall read a little way into the
    mouth of a short drift the skeleton did not keep as a branch (0.22 m: that slice's centre
    took a 90 m drift's curve 0.1 m off its axis), and so does a sparse arch's roof peak that
    lands on its shoulder: each moves the centre by half the difference (wider: only beyond
    ``_WIDER_FLOOR`` too).
    """
    ok = [r for r in records if r.ok]
    if c.narrow_sigmas <= 0 or len(ok) < min_slices:
        return
    st = np.array([r.station for r in ok])
    near = np.abs(st[:, None] - st[None, :]) <= c.neighbour_window
    verdicts = []
    for key in ("width", "height"):
        v = np.array([getattr(r, key) for r in ok])
        med = np.array([np.median(v[m]) for m in near])
        spread = 1.4826 * float(np.median(np.abs(v - med)))
        jump = c.max_width_jump if key == "width" else c.max_height_jump
        limit = min(jump, c.narrow_sigmas * spread)
        if key == "width":  # wider: only where the centre would move by more than noise
            bad = (med - v > limit) | (v - med > max(limit, _WIDER_FLOOR))
        else:
            bad = np.abs(v - med) > limit
        verdicts.append((key, v, med, bad))
    for i, r in enumerate(ok):
        for key, v, med, bad in verdicts:
            if bad[i]:
                if key == "height":
                    what, cause = "height unlike", "roof or floor read off the surface"
                elif v[i] < med[i]:
                    what, cause = "narrower than", "a wall hidden, or read on equipment"
                else:
                    what, cause = "wider than", "a wall read in a niche, a hole or a drift's mouth"
                r.ok, r.reason = (
                    False, f"{what} nearby: {key} {v[i]:.3f} m vs {med[i]:.3f} m ({cause})")
                break


def _centres(records: list[SliceRecord], to_world: Callable[[np.ndarray], np.ndarray]) -> None:
    ok = [r for r in records if r.ok]
    if not ok:
        return
    local = np.array([[r.station, (r.left + r.right) / 2, (r.floor + r.roof) / 2] for r in ok])
    world = to_world(local)
    for r, c in zip(ok, world, strict=True):
        r.centre = c


def _curve_to_world(axis: Centerline) -> Callable[[np.ndarray], np.ndarray]:
    def f(local: np.ndarray) -> np.ndarray:
        _, lat, ver = axis.frame_at(local[:, 0])
        return axis.point_at(local[:, 0]) + local[:, 1:2] * lat + local[:, 2:3] * ver

    return f


def rejection_summary(records: list[SliceRecord]) -> str:
    """Why slices were rejected, most common first: ``"no wall line (12), ..."``."""
    reasons: dict[str, int] = {}
    for r in records:
        if not r.ok:
            key = r.reason.split(":")[0].split(" (")[0]
            reasons[key] = reasons.get(key, 0) + 1
    return ", ".join(f"{k} ({v})" for k, v in sorted(reasons.items(), key=lambda x: -x[1]))


def _fit(
    records: list[SliceRecord], c: CenterlineConfig, meta: dict, max_length: float = np.inf
) -> Centerline:
    ok = [r for r in records if r.ok]
    n_slices = len(records)
    if len(ok) < max(c.min_slices, c.degree + 1):
        common = rejection_summary(records)
        raise NotATunnelError(
            f"only {len(ok)} of {n_slices} slices show a floor, a roof and two walls "
            f"(rejected: {common or 'none'}); is this a tunnel scan? check units (metres) and "
            "the [slicing] thickness/step"
        )
    centres = np.array([r.centre for r in ok])
    stations = np.array([r.station for r in ok])
    span = float(stations[-1] - stations[0])
    if not span <= max_length:
        # checked before the curve is sampled: its sample count grows with this span
        raise NotATunnelError(
            f"the slices span {span:.1f} m of axis but the cloud can hold at most "
            f"{max_length:.1f} m of tunnel; the axis left the cloud"
        )
    meta = {**meta, "n_slices": n_slices, "n_used": len(ok)}
    cl, fit = fit_stiffest(centres, params=stations, degree=c.degree,
                           min_spacing=c.ctrl_spacing, max_spacing=c.max_ctrl_spacing,
                           max_misfit=c.max_misfit, sample_step=c.sample_step, meta=meta)
    # a curve turning tighter than half the section folds the section over itself when the
    # cloud is re-sliced along it (sparse or noisy centres let the free ends hook): stiffen it,
    # doubling the control-point spacing up to 8 x ctrl_spacing
    half_width = 0.5 * float(np.median([r.width for r in ok]))
    spacing = float(cl.meta["ctrl_spacing_m"])
    keep = {k: cl.meta[k] for k in ("systematic_misfit_m", "centre_scatter_p95_m")}
    while _min_radius(cl) < half_width and spacing < 8 * c.ctrl_spacing:
        logger.info("centreline: turns tighter than the section; control points every %.0f m",
                    2 * spacing)
        spacing *= 2
        cl, fit = fit_centerline(centres, params=stations, degree=c.degree,
                                 ctrl_spacing=spacing, sample_step=c.sample_step,
                                 meta={**meta, **keep, "ctrl_spacing_m": spacing})
    for r, w in zip(ok, fit.data_weights, strict=True):
        r.weight = float(w)
    return cl


def _shift(new: Centerline, old: Centerline) -> float:
    """How far a refitted curve moved: 95th percentile of its distance to the previous one
    (the maximum would measure the slice noise at the free ends)."""
    p = old.project(new.points)
    d = p.distance[p.inside]
    return float(np.percentile(d, 95)) if d.size else np.inf


_MIN_DRIFT_WIDTH = 1.0  # m: no drift is narrower; bounds a centreline's length by the plan area
_PLAN_CELL = 0.5  # m: plan cells of that bound
_CENTRE_NOISE = 0.005  # m: slice centres scatter this much (fit_nurbs's sigma floor); scores
# closer than this are alike
_CLOUD_MARGIN = 0.5  # m: a curve sample may lie this much farther from the cloud than the
# half-diagonal of the section before it counts as outside the cloud (holes, noise)


def plausible_length(xyz: np.ndarray) -> float:
    """The longest centreline a cloud can hold, metres.

    A drift at least ``_MIN_DRIFT_WIDTH`` (1 m) wide cannot have a centreline longer than the
    cloud's occupied plan area (0.5 m cells) divided by that width, nor shorter than its
    bounding-box diagonal; the larger of the two is returned. It bounds what a fit may be
    asked to sample (time and memory grow with the length, not with the data).
    """
    pts = np.asarray(xyz, dtype=np.float64)
    ij = np.floor((pts[:, :2] - pts[:, :2].min(axis=0)) / _PLAN_CELL).astype(np.int64)
    # one integer key per occupied cell: a 1-D unique sorts ~20x faster than rows
    cells = np.unique(ij[:, 0] * (int(ij[:, 1].max(initial=0)) + 1) + ij[:, 1])
    area = len(cells) * _PLAN_CELL**2
    diagonal = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    return max(area / _MIN_DRIFT_WIDTH, diagonal)


@dataclass
class PassQuality:
    """How good one slicing pass's curve is, and whether it is possible at all (metres).

    Attributes
    ----------
    number : int
        Pass number (1 = along the PCA axis).
    slices, used : int
        Slices cut and slices whose centre was used.
    usable_share : float
        ``used / slices``.
    residual_p50, residual_p95 : float
        Median and 95th percentile distance of the used slice centres from the curve.
    curve_uncertainty : float
        About the 95 % uncertainty of the curve: the local scatter of its centres (p95
        distance from the most flexible curve, ``ctrl_spacing``), with no credit for
        averaging. The centres' errors are correlated along the tunnel (rock relief, holes,
        clutter span several slices; ``2.08 * residual_p50 * sqrt(control points / centres)``
        claimed 3-6 x less than the true error). On the 104 epochs of 52 random featured
        sweep pairs the true p95 error of the 2 m curve was 0.5-2.7 x this figure (median
        0.97); that of the stiffer curve kept where it fits
        (:func:`~tunneldef.centerline.fit.fit_stiffest`) 0.1-2.1 x (median 0.45, p95 1.2;
        the worst ratios on errors of 6-10 mm).
    length, extent : float
        Length of the curve and the extent of the cloud along it (the 0.1-99.9 % chainage
        span / 0.998).
    cloud_distance, cloud_distance_limit : float
        Largest distance from a curve sample (every 0.5 m) to the nearest cloud point, and the
        most a curve inside the tunnel can show: half the section's diagonal plus 0.5 m.
    min_radius, min_radius_limit : float
        Tightest radius of curvature (over 1 m) and half the section width: a tighter turn
        folds the section over itself, so re-slicing along it mixes chainages.
    shift, trust_radius : float
        How far the curve moved from the previous pass (p95), and the most it was allowed to
        (NaN in pass 1).
    possible : bool
        False if the curve is longer than the cloud along it, leaves the cloud, turns tighter
        than the section, or moved beyond the trust radius.
    reason : str
        Why it is not possible ("" if it is).
    """

    number: int
    slices: int
    used: int
    usable_share: float
    residual_p50: float
    residual_p95: float
    curve_uncertainty: float
    length: float
    extent: float
    cloud_distance: float
    cloud_distance_limit: float
    min_radius: float
    min_radius_limit: float
    shift: float = np.nan
    trust_radius: float = np.nan
    possible: bool = True
    reason: str = ""

    @property
    def score(self) -> float:
        """The pass's quality measure, lower is better: the median centre residual divided by
        the share of usable slices (a curve that fits fewer centres, or fits them worse, is
        worse), metres."""
        return self.residual_p50 / max(self.usable_share, 1e-9)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        out = {k: v for k, v in self.__dict__.items()}
        out["score"] = self.score
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v)
                for k, v in out.items()}


def _section_size(records: list[SliceRecord]) -> tuple[float, float]:
    ok = [r for r in records if r.ok]
    if not ok:
        return np.nan, np.nan
    return (float(np.median([r.width for r in ok])), float(np.median([r.height for r in ok])))


def _min_radius(cl: Centerline, step: float = 1.0) -> float:
    """Tightest radius of curvature of a curve, from its tangents ``step`` metres apart."""
    if cl.length < 2 * step:
        return np.inf
    s = np.arange(0.0, cl.length + 1e-9, step)
    t = cl.frame_at(s)[0]
    cosang = np.clip(np.einsum("ij,ij->i", t[1:], t[:-1]), -1.0, 1.0)
    ang = np.arccos(cosang)
    big = float(ang.max()) if ang.size else 0.0
    return step / big if big > 1e-12 else np.inf


def _pass_quality(
    number: int,
    cl: Centerline,
    records: list[SliceRecord],
    tree: cKDTree,
    shift: float = np.nan,
    trust: float = np.nan,
) -> PassQuality:
    ok = [r for r in records if r.ok]
    width, height = _section_size(records)
    res = cl.project(np.array([r.centre for r in ok])).distance if ok else np.array([np.inf])
    s = cl.project(tree.data).chainage
    # the span of the middle 99.8 % of the points (a few strays do not count), scaled back to
    # the whole (evenly spread points leave 0.2 % of the length outside it: 2 m of 1 km)
    extent = float(np.percentile(s, 99.9) - np.percentile(s, 0.1)) / 0.998
    samples = cl.point_at(np.linspace(0.0, cl.length, max(int(cl.length / 0.5), 1) + 1))
    gap = float(tree.query(samples, workers=-1)[0].max())
    q = PassQuality(
        number=number,
        slices=len(records),
        used=len(ok),
        usable_share=len(ok) / max(len(records), 1),
        residual_p50=float(np.median(res)),
        residual_p95=float(np.percentile(res, 95)),
        curve_uncertainty=float(cl.meta.get("centre_scatter_p95_m",
                                            np.percentile(res, 95))),  # (see PassQuality)
        length=cl.length,
        extent=extent,
        cloud_distance=gap,
        cloud_distance_limit=0.5 * float(np.hypot(width, height)) + _CLOUD_MARGIN,
        min_radius=_min_radius(cl),
        min_radius_limit=0.5 * width,
        shift=shift,
        trust_radius=trust,
    )
    reasons = []
    if q.length > q.extent + 1.0:
        reasons.append(f"the curve is {q.length:.1f} m long but the cloud extends only "
                       f"{q.extent:.1f} m along it")
    if not q.cloud_distance <= q.cloud_distance_limit:
        reasons.append(f"the curve leaves the cloud ({q.cloud_distance:.2f} m from the nearest "
                       f"point > {q.cloud_distance_limit:.2f} m)")
    if q.min_radius < q.min_radius_limit:
        reasons.append(f"the curve turns tighter than the section (radius {q.min_radius:.2f} m "
                       f"< {q.min_radius_limit:.2f} m)")
    if np.isfinite(trust) and not shift <= trust:
        reasons.append(f"the curve moved {shift:.2f} m (p95) from the previous pass, more than "
                       f"the trust radius {trust:.2f} m")
    q.possible, q.reason = not reasons, "; ".join(reasons)
    return q


def _reject_centre_jumps(records: list[SliceRecord], trust: float) -> None:
    """Reject slices of a re-slicing pass whose centre lies farther than ``trust`` from the
    curve they were cut along (the curve lies inside the tunnel, so a centre farther away is a
    wrong wall or floor line, not the tunnel moving)."""
    for r in records:
        if not r.ok:
            continue
        off = float(np.hypot((r.left + r.right) / 2, (r.floor + r.roof) / 2))
        if off > trust:
            r.ok, r.reason = (
                False,
                f"centre jumps: {off:.2f} m off the previous curve (trust radius {trust:.2f} m)",
            )


def extract_centerline(
    xyz: np.ndarray,
    *,
    slicing: SlicingConfig | None = None,
    settings: CenterlineConfig | None = None,
    progress: ProgressCallback | None = None,
) -> CenterlineResult:
    """The centreline of a tunnel point cloud (paper §3.1).

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        World coordinates, metres (z up unless ``settings.vertical == "pca"``).
    slicing : SlicingConfig, optional
        The ``[slicing]`` parameters (slice step, thickness, least points).
    settings : CenterlineConfig, optional
        The ``[centerline]`` parameters (kernel densities, Hough, NURBS, passes).
    progress : ProgressCallback, optional
        Called with ("centreline pass k", fraction) per slice.

    Returns
    -------
    CenterlineResult
        The centreline, the per-slice records of the last pass and the PCA frame.

    Raises
    ------
    NotATunnelError
        If the cloud is not elongated, or too few slices show a floor, a roof and two walls.
    InvalidCloudError
        If ``xyz`` is not a finite N x 3 array.

    References
    ----------
    Sensors 2024, 24, 2299, doi:10.3390/s24072299, §3.1.
    """
    sl = slicing or SlicingConfig()
    c = settings or CenterlineConfig()
    pts = check_points(xyz, min_points=1)
    need = sl.min_points * c.min_slices
    if len(pts) < need:
        raise NotATunnelError(
            f"the cloud has {len(pts)} points; a centreline needs at least {need} "
            f"({c.min_slices} slices x {sl.min_points} points); is the file complete?"
        )
    if len(pts) > c.max_points > 0:
        keep = random_keep(len(pts), c.max_points / len(pts))
        logger.info("centreline: %d of %d points used", int(keep.sum()), len(pts))
        pts = pts[keep]
    if c.remove_strays:
        from ..outliers import robust_extent

        # a return 130 m away or a small far cluster stretches the frame and the slicing:
        # what lies more than 3 m beyond the box of the 0.1-99.9 % of the points goes; a ghost
        # inside the drift is left to the slices' own tests (the full stray tests also thin a
        # terrestrial scan's sparse far end, whose last slices then fail, and cost a second
        # per epoch)
        box = robust_extent(pts)
        inside = np.all((pts >= box.lower - 3.0) & (pts <= box.upper + 3.0), axis=1)
        if not inside.all() and inside.sum() >= need:
            logger.info("centreline: %d far stray points left out", int((~inside).sum()))
            pts = pts[inside]
    frame = principal_frame(pts, vertical=c.vertical)
    roll = estimate_roll(frame.to_local(pts), sl, c)
    if roll:
        logger.info("centreline: section rolled by %.2f deg about the axis", np.degrees(roll))
    local = _axis_coordinates(pts, None, frame, roll)
    leans = estimate_wall_leans(local, sl, c)
    if any(leans):
        logger.info("centreline: walls lean by %.3f / %.3f (dv/dz)", *leans)
    max_length = plausible_length(pts)
    tree = cKDTree(pts[:: max(1, len(pts) // 200_000)])
    records = _slice_pass(local, sl, c, progress, "centreline pass 1", leans)
    _centres(records, lambda loc: _local_to_world(loc, None, frame, roll))
    centerline = _fit(records, c, {"pass": 1, "axis": "pca"}, max_length)
    qualities = [_pass_quality(1, centerline, records, tree)]
    history: list[tuple[Centerline, list[SliceRecord], Centerline | None]] = [
        (centerline, records, None)
    ]
    shifts: list[float] = []
    settled = True  # False once a pass is rejected or the curve stops converging
    for it in range(c.max_iterations):
        if not qualities[-1].possible:
            break
        width = _section_size(records)[0]
        # trust radius: a curve inside the tunnel is within half a width of its centre; once
        # the passes converge, a centre may move only a few times the last shift
        trust = 0.5 * width
        if shifts:
            trust = min(trust, max(3.0 * shifts[-1], 10.0 * c.converge_tol))
        local = _axis_coordinates(pts, centerline, frame, roll)
        new_records = _slice_pass(local, sl, c, progress, f"centreline pass {it + 2}", leans)
        _reject_centre_jumps(new_records, trust)
        _centres(new_records, lambda loc, a=centerline: _local_to_world(loc, a, frame, roll))
        try:
            new = _fit(new_records, c, {"pass": it + 2, "axis": "curve"}, max_length)
        except NotATunnelError as exc:
            logger.warning("centreline pass %d failed (%s); keeping an earlier pass", it + 2, exc)
            settled = False
            break
        shift = _shift(new, centerline)
        q = _pass_quality(it + 2, new, new_records, tree, shift, trust)
        qualities.append(q)
        logger.info("centreline pass %d: curve moved by %.4f m (p95)", it + 2, shift)
        if not q.possible:
            logger.warning("centreline pass %d rejected: %s", it + 2, q.reason)
            settled = False
            break
        best = min(x.score for x in qualities[:-1] if x.possible)
        if q.score > 1.5 * best + _CENTRE_NOISE:
            logger.warning(
                "centreline pass %d rejected: its centres fit worse (score %.4f m vs %.4f m)",
                it + 2, q.score, best,
            )
            q.possible, q.reason = False, "centres fit worse than an earlier pass"
            settled = False
            break
        shifts.append(shift)
        history.append((new, new_records, centerline))
        centerline, records = new, new_records
        if shift < c.converge_tol:
            break
        if len(shifts) > 1 and shift > 0.7 * shifts[-2]:
            # no longer converging: the centres' own noise (rough walls) moves the curve
            logger.info("centreline: re-slicing stopped at the noise floor (%.3f m)", shift)
            settled = False
            break
    good = [q for q in qualities if q.possible]
    if not good:
        raise NotATunnelError(
            f"no centreline pass is possible: {qualities[0].reason}; is the cloud one tunnel "
            "(not a room, a plane or several drifts)? check units (metres)"
        )
    # every accepted pass fits its centres within 1.5 x the best score (+5 mm); when the
    # passes settled the last one is kept (it is sliced normal to the curve), when one was
    # rejected or the curve stopped converging, the best-scoring accepted pass is kept
    chosen = good[-1] if settled else min(good, key=lambda q: (q.score, -q.number))
    # accepted passes are 1..k in order (the first rejected one ends the loop)
    centerline, records, axis = history[chosen.number - 1]
    passes = chosen.number
    ok = [r for r in records if r.ok]
    if ok:
        s = centerline.project(np.array([r.centre for r in ok])).chainage
        for r, si in zip(ok, s, strict=True):
            r.chainage = float(si)
    centerline.meta.update(
        {
            "passes": passes,
            "passes_run": len(qualities),
            "shifts_m": shifts,
            "roll_deg": float(np.degrees(roll)),
            "wall_leans": list(leans),
            "pass_quality": [q.to_dict() for q in qualities],
        }
    )
    return CenterlineResult(
        centerline, records, frame, passes, axis, sl, c, roll, leans, qualities
    )
