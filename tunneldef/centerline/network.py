"""Centrelines of a drift network (a graph of drifts joined at junctions).

Steps of :func:`extract_network`:

1. The network's topology from its plan view (:mod:`.skeleton`): a robust plan occupancy grid
   (strays dropped), its skeleton, spurs pruned, straight-on drifts joined through their
   junctions. Each skeleton edge gives a first axis (the medial axis in plan, the middle of
   floor and roof in height).
2. Junction zones: along an edge, the stretch around a junction where another drift's tube
   cuts its section, ``hw_f / sin(a) + hw_e / |tan(a)| + margin`` on either side of the node
   (``hw`` the half-widths, ``a`` the angle between the drifts). Slices there are flagged
   ``junction`` and not fitted; the curve bridges them.
3. Per edge, the paper's per-slice method on the points within its tube: slices normal to the
   axis, floor and roof from the 1-D Gaussian KDE peaks, walls from the 2-D linear-kernel
   density + Canny + Hough (:func:`~tunneldef.centerline.extract.analyse_slice`), slices whose
   width or height jumps against their neighbours rejected, a least-squares NURBS through the
   centres (:func:`~tunneldef.centerline.fit.fit_stiffest`); re-sliced along the fitted curve
   until it moves less than ``converge_tol``.
4. Junction nodes on the fitted curves (on the edge that passes through, where one does); an
   edge that ends at a junction is extended along its end tangent to the node, so the graph is
   connected.

One idea at this length: the per-edge centreline passes of a drift network, with junction zones
flagged and bridged.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..cloud import check_points
from ..config import CenterlineConfig, NetworkConfig, SlicingConfig
from ..curve import Centerline
from ..engine import thread_map
from ..errors import ImplausibleExtentError, NetworkError, NotATunnelError
from ..network import CenterlineNetwork, Junction, NetworkEdge
from ..progress import ProgressCallback, notify
from ..spatial import random_keep
from .extract import (
    SliceRecord,
    _reject_jumps,
    _roll,
    analyse_slice,
    record_lines,
    rejection_summary,
    smooth_roof_lifts,
)
from .fit import fit_stiffest
from .plan import PlanGrid
from .roof_floor import roll_profile
from .skeleton import SkeletonGraph, path_half_width, plan_graph, sharp_turns
from .slicing import slice_along_axis, thickness_for
from .walls import estimate_wall_leans

__all__ = ["NetworkResult", "extract_network"]

logger = logging.getLogger(__name__)

JUNCTION = "junction"
EXTENT_WALLS = "section_extent"
#: A free end whose last half-width turns more than this against the half-width before it
#: is a medial axis' fork to a dead end's corners, degrees.
_FORK_DEG = 15.0
#: Fewest good slices for an edge; fewer than ``min_slices`` of them give a straight line.
MIN_LINE_SLICES = 3
#: A corner splits its edge into two edges meeting at a node when each leg keeps at least
#: this much outside every zone (a line needs a few sections), metres; otherwise it stays a
#: zone that one curve bridges.
SPLIT_LEG = 4.0


@dataclass
class NetworkResult:
    """Output of :func:`extract_network`.

    Attributes
    ----------
    network : CenterlineNetwork
    grid : PlanGrid
        The plan occupancy the topology came from.
    graph : SkeletonGraph
        The simplified skeleton graph (plan cells).
    """

    network: CenterlineNetwork
    grid: PlanGrid
    graph: SkeletonGraph

    def table(self) -> list[dict]:
        """One dict per slice of every edge (:meth:`SliceRecord.row` plus ``edge``)."""
        return [{"edge": e.id, **r.row()} for e in self.network.edges for r in e.slices]


class _Shape(NamedTuple):
    """An edge's section roll along it (:func:`roll_profile`) and its walls' leans."""

    at: np.ndarray  # (K, 3) where along the edge the roll was read (world)
    roll: np.ndarray  # (K,) radians
    leans: tuple[float, float]

    def roll_at(self, axis: Centerline, chainage: np.ndarray) -> np.ndarray | float:
        """The roll at ``chainage`` along ``axis`` (any pass's curve of the edge)."""
        if not np.any(self.roll):
            return 0.0
        s = axis.project(self.at).chainage
        order = np.argsort(s)
        return np.interp(chainage, s[order], self.roll[order])


@dataclass
class _Edge:
    path: np.ndarray  # plan cells
    nodes: list[int]
    through: list[int]
    axis: Centerline
    half_width: float
    tube: float
    index: np.ndarray | None = None  # candidate points
    curve: Centerline | None = None
    records: list[SliceRecord] | None = None
    zones: list[tuple[float, float]] | None = None
    corners: list[tuple[np.ndarray, float]] = dataclasses.field(default_factory=list)


def _corners(axis: Centerline, half_width: float, margin: float) -> list[tuple[np.ndarray, float]]:
    """Sharp turns of an edge (:func:`~tunneldef.centerline.skeleton.sharp_turns`): where the
    walk turns a corner (into a cross-cut whose junction has no third branch left, the main
    drift ending a few metres beyond it). The sections there are no tunnel sections, as at a
    junction. Returns per corner its point (on ``axis``) and the half-length of its zone,
    ``hw / sin(a) + hw |cos(a)| / sin(a) + margin`` as at a junction of the two legs (``a``
    the angle between them).
    """
    out: list[tuple[np.ndarray, float]] = []
    for s, turn in sharp_turns(axis.points, half_width):
        a = np.radians(180.0 - turn)
        sin = max(abs(np.sin(a)), np.sin(np.radians(20.0)))
        half = half_width / sin + half_width * abs(np.cos(a)) / sin + margin
        out.append((axis.point_at(s)[0], float(half)))
    return out


#: A drift's plan width changing by at least this much (m), and this share of the wider
#: width, between the 10 m either side of a station is a change of section
_STEP_WIDTH = 0.5
_STEP_SHARE = 0.15
_STEP_WINDOW = 10.0  # m either side of a station whose plan half-widths are compared
_STEP_GAP = 1.0  # m either side of the station left out of both


def _width_steps(axis: Centerline, grid: PlanGrid, blocked: list[tuple[float, float]],
                 margin: float) -> list[tuple[np.ndarray, float]]:
    """Changes of section along an edge with no junction there: a drift that goes on as a
    narrower ramp or a wider drift. The median plan half-width of the footprint over the
    10 m before a station against the 10 m after it (1 m either side left out, and neither
    stretch reaching into a ``blocked`` zone): where they differ by at least 0.5 m and 15 %
    of the wider, the middle of the stations reading within 10 % of the largest difference
    in each such stretch is a step. One
    curve through a step in its centres (a 5.6 m drift going on as a 4.0 m ramp, its centre
    10 cm lower) rang 4-6 cm about it for 10 m; cut there, each side has a curve of its own
    (:func:`_split_at_corners`), and the node's zone flags the sections of the change.
    Returns per step its point on ``axis`` and the half-length of its zone (the wider
    half-width and ``margin``). A chamber shorter than half the window leaves both medians
    the drift's."""
    step = 0.25
    s = np.arange(0.0, axis.length, step)
    if axis.length < 2 * (_STEP_WINDOW + SPLIT_LEG):
        return []
    cells = (axis.point_at(s)[:, :2] - grid.origin) / grid.cell - 0.5
    cells = np.clip(np.round(cells).astype(np.int64), 0, np.array(grid.footprint.shape) - 1)
    hw = grid.half_width[cells[:, 0], cells[:, 1]]
    w = int(round(_STEP_WINDOW / step))
    g = int(round(_STEP_GAP / step))
    found: list[tuple[float, float, float]] = []  # (station, jump, wider half-width)
    run: list[tuple[float, float, float]] = []
    for i in range(w, len(s) - w):
        lo, hi = s[i] - _STEP_WINDOW, s[i] + _STEP_WINDOW
        if any(a <= hi and b >= lo for a, b in blocked):
            jump = 0.0
        else:
            before = float(np.median(hw[i - w : i - g]))
            after = float(np.median(hw[i + g + 1 : i + w + 1]))
            jump = 2.0 * abs(after - before)
            wide = max(before, after)
            if jump < max(_STEP_WIDTH, _STEP_SHARE * 2.0 * wide):
                jump = 0.0
        if jump > 0.0:
            run.append((float(s[i]), jump, wide))
        elif run:
            found.append(_middle(run))
            run = []
    if run:
        found.append(_middle(run))
    return [(axis.point_at(np.array([at]))[0], wide + margin) for at, wide in found]


def _middle(run: list[tuple[float, float, float]]) -> tuple[float, float]:
    """The middle of the stations whose jump is within 10 % of the largest (with 1 m left out
    either side, every station within a metre of a sharp step reads all of it) and the wider
    half-width there."""
    top = max(j for _, j, _ in run)
    near = [(at, wide) for at, j, wide in run if j >= 0.9 * top]
    return float(np.median([at for at, _ in near])), max(wide for _, wide in near)


def _corner_points(e: _Edge) -> list[np.ndarray]:
    return [xyz for xyz, _ in e.corners]


def _with_corners(
    zones: list[tuple[float, float]], curve: Centerline, corners: list[tuple[np.ndarray, float]]
) -> list[tuple[float, float]]:
    """``zones`` and the corner zones of an edge on ``curve``."""
    out = list(zones)
    for xyz, half in corners:
        at = float(curve.project(xyz[None]).chainage[0])
        out.append((at - half, at + half))
    return out


def _tube(axis: Centerline, half_width: float, pts: np.ndarray) -> tuple[float, np.ndarray]:
    """An edge's tube radius in plan (``1.6 hw + 0.5`` m) and the indices of ``pts`` in it."""
    tube = 1.6 * half_width + 0.5
    near = cKDTree(axis.points[:, :2]).query(pts[:, :2], distance_upper_bound=tube)[0]
    return tube, np.flatnonzero(np.isfinite(near))


def _outside(a: float, b: float, zones: list[tuple[float, float]], step: float = 0.1) -> float:
    """Length of the chainage interval ``[a, b]`` outside every zone, metres."""
    t = np.arange(a, b, step) + step / 2
    inside = np.zeros(len(t), dtype=bool)
    for lo, hi in zones:
        inside |= (t >= lo) & (t <= hi)
    return float((~inside).sum()) * step


def _sub_axis(axis: Centerline, a: float, b: float) -> Centerline:
    """The stretch ``[a, b]`` of ``axis`` as a curve of its own (chainage from ``a``)."""
    s = np.linspace(a, b, max(int(np.ceil((b - a) / 0.1)) + 1, 2))
    return Centerline.from_polyline(axis.point_at(s), step=0.1)


def _split_at_corners(
    edges: list[_Edge], members: dict[int, list[int]], node_xyz: dict[int, np.ndarray],
    zones: list[list[tuple[float, float]]], pts: np.ndarray, grid: PlanGrid,
) -> tuple[list[_Edge], dict[int, list[int]], set[int]]:
    """Edges cut in two at their corners: each leg is a drift of its own (the main drift and
    the cross-cut a walker turned into), its curve fitted to its own sections, and both end
    at a new node where their end tangents meet (:func:`_place_nodes`). One stiff curve round
    a right angle swings about 0.2 m off its drifts for some 6 m past the corner's zone. A
    corner whose legs would keep less than :data:`SPLIT_LEG` outside every zone stays a zone
    of one curve. Returns the edges (longest first), the junction members (the corners' nodes
    among them) and the corners' node ids."""
    corner_nodes: set[int] = set()
    if not any(e.corners for e in edges):
        return edges, members, corner_nodes
    next_v = max([-1, *node_xyz, *(v for e in edges for v in e.nodes)]) + 1
    legs: list[tuple[_Edge, int]] = []  # (leg, edge it came from)
    for k, e in enumerate(edges):
        cuts = sorted(((float(e.axis.project(xyz[None]).chainage[0]), xyz, h)
                       for xyz, h in e.corners), key=lambda c: c[0])
        blocked = list(zones[k]) + [(c - h, c + h) for c, _, h in cuts]
        chosen: list[tuple[float, np.ndarray]] = []
        start = 0.0
        for c, xyz, _ in cuts:
            if (_outside(start, c, blocked) >= SPLIT_LEG
                    and _outside(c, e.axis.length, blocked) >= SPLIT_LEG):
                chosen.append((c, xyz))
                start = c
        if not chosen:
            legs.append((e, k))
            continue
        bounds = [0.0, *(c for c, _ in chosen), e.axis.length]
        ids = [e.nodes[0], *range(next_v, next_v + len(chosen)), e.nodes[1]]
        for (_, xyz), v in zip(chosen, ids[1:-1], strict=True):
            node_xyz[v] = np.asarray(xyz, dtype=np.float64)
            corner_nodes.add(v)
            logger.info("a skeleton edge turns a corner or changes section at %s: cut into "
                        "two drifts there", np.round(xyz, 1).tolist())
        next_v += len(chosen)
        for i in range(len(bounds) - 1):
            a, b = bounds[i], bounds[i + 1]
            axis = _sub_axis(e.axis, a, b)
            cells = (axis.points[:, :2] - grid.origin) / grid.cell - 0.5
            cells = np.clip(cells, 0, np.array(grid.footprint.shape) - 1)
            half = path_half_width(grid, cells)
            tube, index = _tube(axis, half, pts)
            through = [v for v in e.through
                       if a <= float(e.axis.project(node_xyz[v][None]).chainage[0]) < b]
            leg = _Edge(cells, [ids[i], ids[i + 1]], through, axis, half, tube, index)
            leg.corners = [(xyz, h) for c, xyz, h in cuts
                           if a < c < b and all(abs(c - c2) > 1e-9 for c2, _ in chosen)]
            legs.append((leg, k))
    if not corner_nodes:
        return edges, members, corner_nodes
    order = sorted(range(len(legs)), key=lambda i: -legs[i][0].axis.length)  # stable
    out = [legs[i][0] for i in order]
    new_members: dict[int, list[int]] = {v: [] for v in corner_nodes}
    for v, ks in members.items():
        got = []
        for k in ks:
            mine = [n for n, i in enumerate(order) if legs[i][1] == k]
            touch = [n for n in mine if v in out[n].nodes or v in out[n].through]
            if not touch:  # the leg whose stretch holds the node
                d = [float(out[n].axis.project(node_xyz[v][None]).distance[0]) for n in mine]
                touch = [mine[int(np.argmin(d))]]
            got += touch
        new_members[v] = got
    for n, e in enumerate(out):
        for v in e.nodes:
            if v in corner_nodes:
                new_members[v].append(n)
    return out, {v: sorted(set(ks)) for v, ks in new_members.items()}, corner_nodes


def _axis_from_path(path: np.ndarray, grid: PlanGrid) -> Centerline:
    """A first 3-D axis along a skeleton path: smoothed plan position, middle of floor and
    roof in height."""
    xy = grid.to_world(path)
    # resample at ~one cell, smooth over ~1.5 m
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(np.ceil(s[-1] / grid.cell)) + 1, 2)
    t = np.linspace(0.0, s[-1], n)
    xy = np.stack([np.interp(t, s, xy[:, 0]), np.interp(t, s, xy[:, 1])], axis=1)
    ij = np.clip(np.floor((xy - grid.origin) / grid.cell).astype(np.int64), 0,
                 np.array(grid.footprint.shape) - 1)
    z = 0.5 * (grid.z_low[ij[:, 0], ij[:, 1]] + grid.z_high[ij[:, 0], ij[:, 1]])
    ok = np.isfinite(z)
    if not ok.any():
        raise NetworkError("a skeleton edge has no heights; is the cloud a tunnel scan?")
    z = np.interp(t, t[ok], z[ok])
    win = max(int(round(1.5 / grid.cell)) | 1, 3)
    z = ndimage.median_filter(z, size=2 * win + 1, mode="nearest")
    xy = ndimage.uniform_filter1d(xy, size=win, axis=0, mode="nearest")
    z = ndimage.uniform_filter1d(z, size=win, mode="nearest")
    return Centerline.from_polyline(np.column_stack([xy, z]), step=0.1)


def _trim_free_ends(
    path: np.ndarray, free: tuple[bool, ...], cells: float
) -> tuple[np.ndarray, tuple[float, float]]:
    """The skeleton path without its last ``cells`` (a half-width) at each free end, and the
    length cut at either end (cells).

    A medial axis ends a half-width short of a dead end's face, forking to its corners; pruning
    keeps one fork, and slices along it cut the drift obliquely (their widths read 2.5 m in a
    4 m drift, enough of them to look like the drift's own width). Where the end's last
    stretch turns more than ``_FORK_DEG`` against the one before, the axis is drawn on
    straight along its tangent instead. At least half the path is kept."""
    if len(path) < 4 or not any(free):
        return path, (0.0, 0.0)
    xy = path.astype(np.float64)
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    cut = min(cells, 0.25 * s[-1])

    def forks(at: float, away: float) -> bool:
        # the end's last stretch turns against the stretch before it (a fork to a corner)
        a, b, c = (np.array([np.interp(t, s, xy[:, 0]), np.interp(t, s, xy[:, 1])])
                   for t in (at + 2 * away, at + away, at))
        u, v = b - a, c - b
        cos = float(u @ v) / max(float(np.linalg.norm(u) * np.linalg.norm(v)), 1e-12)
        return cos < np.cos(np.radians(_FORK_DEG))

    lo = cut if free[0] and forks(0.0, cut) else 0.0
    hi = s[-1] - cut if len(free) > 1 and free[1] and forks(s[-1], -cut) else s[-1]
    if lo == 0.0 and hi == s[-1]:
        return path, (0.0, 0.0)
    keep = (s >= lo) & (s <= hi)
    if keep.sum() < 2:
        return path, (0.0, 0.0)
    kept = s[keep]
    return path[keep], (float(kept[0]), float(s[-1] - kept[-1]))


def _extent_walls(
    local: np.ndarray, floor: float, roof: float, c: CenterlineConfig, *, band: float = 0.05,
    min_points: int = 30,
) -> tuple[float, float] | None:
    """Left and right wall positions from the section's extent, for a slice in which the wall
    lines show one wall or none (a side drift that a static scanner looks into obliquely sees
    one wall only).

    On each side the wall is the outermost of the wall band's extent (a visible wall) and the
    extent that the floor and the roof both reach (a hidden wall: floor and roof end where it
    stands). None when the floor or the roof has too few points.
    """
    lat, ver = local[:, 1], local[:, 2]
    f = lat[np.abs(ver - floor) < band]
    r = lat[np.abs(ver - roof) < band]
    h = roof - floor
    w = lat[(ver > floor + c.wall_band_low * h) & (ver < floor + c.wall_band_high * h)]
    if len(f) < min_points or len(r) < min_points or len(w) < min_points:
        return None
    fr, fl = np.percentile(f, [0.5, 99.5])
    rr, rl = np.percentile(r, [0.5, 99.5])
    wr, wl = np.percentile(w, [0.5, 99.5])
    return float(max(wl, min(fl, rl))), float(min(wr, max(fr, rr)))


def _drop_bridged_extents(records: list[SliceRecord], widths: float = 2.0,
                          least: float = 10.0) -> None:
    """Leave out the section-extent walls of slices that wall lines bracket closely.

    Where a slice's wall lines show one wall or none, :func:`_extent_walls` reads the walls
    from the section's extent: at the mouth of a drift the walker did not enter (a hole in
    the wall) that is where the floor and roof end, centimetres from the wall line's position
    (2-5 cm at an oblique crossing's mouth, against a few millimetres for the wall lines on
    either side). Such slices are left out (and the curve bridges them, as at a junction)
    when the nearest wall-line slices before and after them lie within ``widths`` section
    widths (at least ``least`` m) of each other; elsewhere (whole edges a static scanner sees
    obliquely) they are the only centres there are and stay.
    """
    lined = [r for r in records if r.ok and r.methods.get("left") != EXTENT_WALLS]
    if not lined:
        return
    st = np.array([r.station for r in lined])
    bridge = max(least, widths * float(np.median([r.width for r in lined])))
    for r in records:
        if not (r.ok and r.methods.get("left") == EXTENT_WALLS):
            continue
        k = int(np.searchsorted(st, r.station))
        if 0 < k < len(st) and st[k] - st[k - 1] <= bridge:
            r.ok = False
            r.reason = "section-extent walls between wall lines (bridged)"


def _in_zones(s: float, zones: list[tuple[float, float]]) -> bool:
    return any(a <= s <= b for a, b in zones)


def _slice_edge(
    pts: np.ndarray,
    axis: Centerline,
    zones: list[tuple[float, float]],
    tube: float,
    sl: SlicingConfig,
    c: CenterlineConfig,
    shape: _Shape | None,
) -> tuple[list[SliceRecord], _Shape]:
    """Slice one edge along ``axis`` and read every slice outside the junction ``zones``.

    ``shape`` is the edge's section roll and wall leans (:func:`estimate_roll`,
    :func:`estimate_wall_leans`, from the slices outside the zones), estimated when None:
    a drift whose section is rolled (an unlevelled or tilted scan: a cross-cut at right angles
    to the tilt's axis) has a floor and roof sloping across it, whose density peaks smear over
    the slope and read the centre's height centimetres apart from slice to slice (3 degrees
    across a 4.2 m drift: 4-6 cm p95); the slices are read levelled.
    """
    pr = axis.project(pts)
    local = np.column_stack([pr.chainage, pr.lateral, pr.vertical])
    local = local[np.abs(pr.lateral) <= tube]
    if shape is None:
        outside = np.ones(len(local), dtype=bool)
        for a, b in zones:
            outside &= (local[:, 0] < a) | (local[:, 0] > b)
        enough = outside.sum() > 1000
        st, ang = (roll_profile(local[outside], sl, c, c.neighbour_window) if enough
                   else (np.zeros(0), np.zeros(0)))
        shape = _Shape(axis.point_at(st), ang, (0.0, 0.0))
        _roll(local, shape.roll_at(axis, local[:, 0]))
        if enough:
            shape = shape._replace(leans=estimate_wall_leans(local[outside], sl, c))
    else:
        _roll(local, shape.roll_at(axis, local[:, 0]))
    leans = shape.leans
    thick = thickness_for(local[:, 0], sl.thickness, sl.min_points)
    slices = slice_along_axis(local[:, 0], step=sl.step, thickness=thick)
    records = [SliceRecord(station=s.station, n_points=len(s.index)) for s in slices]
    todo = []
    for i, rec in enumerate(records):
        if _in_zones(rec.station, zones):
            rec.reason = JUNCTION
        elif rec.n_points < sl.min_points:
            rec.reason = f"too few points ({rec.n_points} < {sl.min_points})"
        else:
            todo.append((i,))

    def one(i: int) -> None:
        # each task fills its own slice's record from that slice alone
        rec, pts_i = records[i], local[slices[i].index]
        rf, walls, _ = analyse_slice(pts_i, rec.station, slicing=sl, settings=c, leans=leans)
        if not record_lines(rec, rf, walls):
            if walls is None:
                return
            edges = _extent_walls(pts_i, rf.floor, rf.roof, c)
            if edges is None:
                return
            rec.left, rec.right = edges
            rec.methods["left"] = rec.methods["right"] = EXTENT_WALLS
            rec.reason = ""
        rec.width, rec.height = rec.left - rec.right, rec.roof - rec.floor
        rec.ok = True

    # the slices are independent (see :func:`.extract._slice_pass`): Dask's threads run them
    # side by side and the records are the serial ones
    thread_map(one, todo)
    smooth_roof_lifts(records, c.neighbour_window)
    _drop_bridged_extents(records)
    _reject_jumps(records, c)
    ok = [r for r in records if r.ok]
    if ok:
        st = np.array([r.station for r in ok])
        _, lat, ver = axis.frame_at(st)
        mid = np.zeros((len(ok), 3))
        mid[:, 1] = 0.5 * np.array([r.left + r.right for r in ok])
        mid[:, 2] = 0.5 * np.array([r.floor + r.roof for r in ok])
        _roll(mid, -shape.roll_at(axis, st))  # back to the axis' own frame
        cen = axis.point_at(st) + mid[:, 1:2] * lat + mid[:, 2:3] * ver
        for r, p in zip(ok, cen, strict=True):
            r.centre = p
    return records, shape


def _on_axis(ok: list[SliceRecord], n_records: int, c: CenterlineConfig, axis: Centerline,
             **meta: object) -> Centerline:
    """The axis the edge was sliced along, moved onto the used centres (their median lateral
    and vertical offset), over the stations they span: the curve of an edge whose centres are
    too few or too gappy for one of its own."""
    st = np.array([r.station for r in ok])
    pr = axis.project(np.array([r.centre for r in ok]))
    s = np.arange(st.min(), st.max() + c.sample_step / 2, c.sample_step)
    _, lat, ver = axis.frame_at(s)
    pts = (axis.point_at(s) + float(np.median(pr.lateral)) * lat
           + float(np.median(pr.vertical)) * ver)
    cl = Centerline.from_polyline(pts, step=c.sample_step,
                                  centres=np.array([r.centre for r in ok]))
    cl.meta.update({"method": "axis_offset", "n_slices": n_records, "n_used": len(ok), **meta})
    for r in ok:
        r.weight = 1.0
    return cl


#: a straight line stands for centres too gappy for a curve of their own only where most of
#: them lie within this of it, m (a tunnel section's centre scatters by 1-2 cm)
SPARSE_LINE_TOLERANCE = 0.1


def _on_line(ok: list[SliceRecord], n_records: int, c: CenterlineConfig) -> Centerline | None:
    """The straight line, in station, that most of the used centres lie on (within
    :data:`SPARSE_LINE_TOLERANCE`), least-squares through those, over the stations they
    span; None when no line holds more than half of them. Every pair of centres proposes a
    line (a few dozen centres: exhaustive, no random draws)."""
    st = np.array([r.station for r in ok])
    xyz = np.array([r.centre for r in ok])
    i, j = np.triu_indices(len(ok), k=1)
    dt = st[j] - st[i]
    good = np.abs(dt) > 1e-6
    i, j, dt = i[good], j[good], dt[good]
    if len(i) == 0:
        return None
    slope = (xyz[j] - xyz[i]) / dt[:, None]
    pred = xyz[i][:, None, :] + slope[:, None, :] * (st[None, :] - st[i][:, None])[..., None]
    near = np.linalg.norm(pred - xyz[None], axis=2) <= SPARSE_LINE_TOLERANCE
    best = int(np.argmax(near.sum(axis=1)))
    inl = near[best]
    if inl.sum() <= len(ok) // 2 or np.ptp(st[inl]) <= 0:
        return None
    a = np.vstack([np.ones(int(inl.sum())), st[inl]]).T
    coef, *_ = np.linalg.lstsq(a, xyz[inl], rcond=None)
    s = np.arange(st.min(), st.max() + c.sample_step / 2, c.sample_step)
    cl = Centerline.from_polyline(coef[0] + s[:, None] * coef[1], step=c.sample_step,
                                  centres=xyz)
    cl.meta.update({"method": "line", "n_slices": n_records, "n_used": len(ok),
                    "n_on_line": int(inl.sum()), "sparse_centres": True})
    for r, w in zip(ok, inl, strict=True):
        r.weight = float(w)
    return cl


def _fit_edge(
    records: list[SliceRecord], c: CenterlineConfig, name: str, axis: Centerline
) -> Centerline:
    ok = [r for r in records if r.ok]
    least = max(c.min_slices, c.degree + 1)
    if MIN_LINE_SLICES <= len(ok) < least:
        # a short branch (a few metres beyond its junction), too few centres for a curve or
        # even a direction: the axis it was sliced along, moved onto the centres
        return _on_axis(ok, len(records), c, axis, short_branch=True)
    if len(ok) < least:
        common = rejection_summary(records)
        raise NetworkError(
            f"{name}: only {len(ok)} of {len(records)} slices show a tunnel section "
            f"(rejected: {common or 'none'}); raise network.min_branch_length to leave it out"
        )
    st = np.array([r.station for r in ok])
    # at least two centres per control point, so that sparse centres (real scans, where many
    # slices fail) are smoothed, not interpolated
    spacing = max(c.ctrl_spacing, float(st[-1] - st[0]) / max(len(ok) // 2 - c.degree, 1))
    # then the stiffest curve that follows the centres' course (bends keep a flexible one)
    try:
        cl, fit = fit_stiffest(
            np.array([r.centre for r in ok]),
            params=st,
            degree=c.degree,
            min_spacing=spacing,
            max_spacing=max(spacing, c.max_ctrl_spacing),
            max_misfit=c.max_misfit,
            sample_step=c.sample_step,
            meta={"n_slices": len(records), "n_used": len(ok)},
        )
    except ImplausibleExtentError:
        # a handful of centres in two clusters either side of a long junction zone (an
        # oblique crossing: 2 and 3 centres 15 m apart) swing a cubic through them 2.5 times
        # the length of the centres' path; the axis through them is the edge's curve, and its
        # centres' scatter about it is still checked. With more centres (sweep case 57000010:
        # 3 scattered by 0.5-2 m at one end, 7 on a line 15 m on: a cubic 555 m long) the
        # curve is the line most of them lie on (the skeleton's axis ran 9 degrees off it),
        # and without such a line the implausible curve is refused
        if len(ok) >= 2 * least:
            line = _on_line(ok, len(records), c)
            if line is None:
                raise
            logger.info("%s: %d centres too gappy for a curve; the line through most of them",
                        name, len(ok))
            return line
        logger.info("%s: %d centres too few and gappy for a curve; the axis moved onto them",
                    name, len(ok))
        return _on_axis(ok, len(records), c, axis, sparse_centres=True)
    for r, w in zip(ok, fit.data_weights, strict=True):
        r.weight = float(w)
    return cl


def _passes(
    p: np.ndarray,
    e: _Edge,
    axis: Centerline,
    zones: list[tuple[float, float]],
    nodes: list[np.ndarray],
    sl: SlicingConfig,
    c: CenterlineConfig,
    name: str,
    *,
    quick: bool = False,
) -> tuple[Centerline, list[SliceRecord]]:
    """Slice, fit and re-slice one edge along its own curve until it stops moving.

    ``quick``: one pass only (slices a metre apart on edges of 20 m or more), which straightens
    the skeleton's axis so that the junction nodes can be placed. Otherwise the passes run at
    the full slice step from ``axis``; a pass that fits worse than the one before (fewer than
    80 % of its good slices, or none) ends them and the one before stands. Zones are kept
    centred on the nodes' chainages on the current axis.
    """
    step = dataclasses.replace(sl, step=max(sl.step, 1.0)) if quick and e.axis.length >= 20.0 \
        else sl
    shape = None
    best: tuple[Centerline, list[SliceRecord], int] | None = None
    # the curve a full pass starts from counts as the previous one: a pass that moves it less
    # than converge_tol is the last
    prev: Centerline | None = None if quick else axis
    for _ in range(1 if quick else max(c.max_iterations, 1)):
        at = [float(axis.project(v[None]).chainage[0]) for v in nodes]
        zones = [(s - (b - a) / 2, s + (b - a) / 2) for s, (a, b) in zip(at, zones, strict=True)]
        records, shape = _slice_edge(p, axis, zones, e.tube, step, c, shape)
        n_ok = sum(r.ok for r in records)
        try:
            curve = _fit_edge(records, c, name, axis)
        except NetworkError:
            if best is None and axis is not e.axis:
                # a pass along a fitted curve failed: once more along the skeleton's axis
                axis = e.axis
                records, shape = _slice_edge(p, axis, zones, e.tube, step, c, shape)
                curve = _fit_edge(records, c, name, axis)
                best = (curve, records, sum(r.ok for r in records))
            if best is None:
                raise
            break
        if best is not None and n_ok < 0.8 * best[2]:
            break
        best = (curve, records, n_ok)
        if prev is not None:
            q = prev.project(curve.points)
            d = q.distance[q.inside]
            if d.size and float(np.percentile(d, 95)) < c.converge_tol:
                break
        prev = axis = curve
    assert best is not None
    return best[0], best[1]


def _place_nodes(
    edges: list[_Edge], curves: list[Centerline], members: dict[int, list[int]],
    node_xyz: dict[int, np.ndarray], *, skip: dict[int, str] | None = None,
    corners: set[int] | None = None,
) -> None:
    """Junction nodes on fitted curves: where the end tangent of an edge that ends there meets
    the edge passing through (else the node's foot point on the first member); a corner's
    node (``corners``) where its two legs' end tangents meet, or midway between their ends
    where they are in line (a change of section). Edges in ``skip`` (left out, no
    fitted curve) neither host nor place a node."""
    skip = skip or {}
    for v, ks in members.items():
        ks = [k for k in ks if k not in skip] or ks
        if v in (corners or set()) and len(ks) == 2:
            a, b = ks
            at = _tangents_meet(curves[a], edges[a].nodes.index(v),
                                curves[b], edges[b].nodes.index(v))
            reach = 2.0 * max(edges[a].half_width, edges[b].half_width)
            if at is None:
                at = _in_line(curves[a], edges[a].nodes.index(v), curves[b],
                              edges[b].nodes.index(v))
            if at is not None and np.linalg.norm(at[:2] - node_xyz[v][:2]) <= reach:
                node_xyz[v] = at
                continue
        through = [k for k in ks if v in edges[k].through]
        host = curves[through[0] if through else ks[0]]
        ending = [k for k in ks if v in edges[k].nodes and k not in through]
        # a meeting point far from the skeleton's node means a poorly determined end tangent
        # (a short branch with few sections): the node's foot point then stands
        reach = 1.5 * edges[through[0] if through else ks[0]].half_width
        meets = [_meet(curves[k], edges[k].nodes.index(v), host, node_xyz[v]) for k in ending]
        meets = [m for m in meets if np.linalg.norm(m[:2] - node_xyz[v][:2]) <= reach]
        if through and meets:
            node_xyz[v] = np.mean(meets, axis=0)
        else:
            s = host.project(node_xyz[v][None]).chainage
            node_xyz[v] = host.point_at(np.clip(s, 0.0, host.length))[0]


#: two edges leaving a junction within 35 degrees of opposite directions are one drift going on
#: through it (the skeleton split it there), not a branch into each other's sections; their
#: chords bend into the fork of an oblique cross-cut (27 degrees between the two legs of a
#: straight drift at a 58 degree cross-cut, whose glancing-angle zones of 11.8 m then covered
#: all of the 18 m between two junctions)
_CONTINUES_COS = float(np.cos(np.radians(35.0)))


def _zones(
    edges: list[_Edge], node_xyz: dict[int, np.ndarray], curves: list[Centerline],
    members: dict[int, list[int]], margin: float,
) -> list[list[tuple[float, float]]]:
    """Junction zones of every edge on ``curves`` (chainage intervals).

    Each drift's direction at a junction is its chord over a few metres either side of the
    node (beyond the other drifts' walls), not the tangent at the node: a skeleton axis bends
    into an oblique crossing's forks there, and the tangent's angle to the other drift read
    as a glancing meeting gave zones of 25 m."""
    zones: list[list[tuple[float, float]]] = [[] for _ in edges]
    sin_min = np.sin(np.radians(20.0))
    for v, ks in members.items():
        p = node_xyz[v][None]
        at = {k: float(curves[k].project(p).chainage[0]) for k in ks}
        reach = 2.0 * max(edges[k].half_width for k in ks) + 1.0
        tan = {}
        away: dict[int, float] = {}  # +1 / -1: the edge leaves the node forward / backward
        for k in ks:
            cv = curves[k]
            s = float(np.clip(at[k], 0.0, cv.length))
            a, b = cv.point_at(np.clip([s - reach, s + reach], 0.0, cv.length))
            t = b - a
            t[2] = 0.0
            if np.linalg.norm(t) < 1e-6:
                t = cv.frame_at(s)[0][0].copy()
                t[2] = 0.0
            tan[k] = t / max(np.linalg.norm(t), 1e-12)
            if s <= reach < cv.length - s:
                away[k] = 1.0
            elif cv.length - s <= reach < s:
                away[k] = -1.0
        for k in ks:
            half = 0.0
            for f in ks:
                if f == k:
                    continue
                if k in away and f in away and away[k] * away[f] * float(
                        tan[k] @ tan[f]) < -_CONTINUES_COS:
                    # the drift itself going on through the node (a skeleton split at the
                    # junction), not a branch into this one's sections: a glancing branch
                    # leaves the node the same way, a continuation the opposite way
                    continue
                cos = abs(float(tan[k] @ tan[f]))
                sin = max(np.sqrt(max(1.0 - cos**2, 0.0)), sin_min)
                half = max(half, edges[f].half_width / sin + edges[k].half_width * cos / sin)
            half += margin
            zones[k].append((at[k] - half, at[k] + half))
    return zones


def _tangents_meet(
    a: Centerline, side_a: int, b: Centerline, side_b: int, min_sin: float = 0.3
) -> np.ndarray | None:
    """Where the end tangents of ``a`` and ``b`` (``side`` 0 start, 1 end) cross in plan, at
    the mean of their heights there (the tangents are the chords of the last 3 m); None when
    they are within ``asin(min_sin)`` (17 degrees) of parallel, or cross more than a metre
    behind either end."""
    (p, u), (q, w) = _end_chord(a, side_a), _end_chord(b, side_b)
    m = np.array([[u[0], -w[0]], [u[1], -w[1]]])
    det = float(np.linalg.det(m))
    if abs(det) < min_sin * max(np.linalg.norm(u[:2]) * np.linalg.norm(w[:2]), 1e-12):
        return None
    lam, mu = np.linalg.solve(m, (q - p)[:2])
    if lam < -1.0 or mu < -1.0:  # behind either end: no corner between them
        return None
    x, y = p[:2] + lam * u[:2]
    return np.array([x, y, 0.5 * ((p + lam * u)[2] + (q + mu * w)[2])])


def _in_line(a: Centerline, side_a: int, b: Centerline, side_b: int) -> np.ndarray | None:
    """Midway between the ends of ``a`` and ``b`` (``side`` 0 start, 1 end) when they leave
    it in line, within 35 degrees of opposite directions in plan (a drift changing section:
    the node's zone then reaches the same distance into either); None otherwise."""
    (p, u), (q, w) = _end_chord(a, side_a), _end_chord(b, side_b)
    u, w = (v[:2] / max(float(np.linalg.norm(v[:2])), 1e-12) for v in (u, w))
    if float(u @ w) > -_CONTINUES_COS:
        return None
    return 0.5 * (p + q)


def _end_chord(cv: Centerline, side: int) -> tuple[np.ndarray, np.ndarray]:
    """The end point of ``cv`` (``side`` 0 start, 1 end) and the unit direction out of the
    curve there: the chord of its last 3 m (at most half its length), not the end's tangent."""
    back = min(3.0, 0.5 * cv.length)
    p, inner = cv.point_at([0.0, back] if side == 0 else [cv.length, cv.length - back])
    t = p - inner
    return p, t / max(float(np.linalg.norm(t)), 1e-12)


def _meet(curve: Centerline, side: int, host: Centerline, near: np.ndarray) -> np.ndarray:
    """Where the tangent line at one end of ``curve`` (``side`` 0 start, 1 end) comes closest
    to ``host`` (in plan), as a point on ``host``; searched up to twice the distance from that
    end to ``near`` (the skeleton's node)."""
    s_end = 0.0 if side == 0 else curve.length
    p0 = curve.point_at(s_end)[0]
    reach = 2.0 * float(np.linalg.norm(near - p0)) + 1.0
    s = (np.linspace(-reach, 0.0, 400) if side == 0
         else curve.length + np.linspace(0.0, reach, 400))
    line = curve.point_at(s)
    pr = host.project(line)
    d = np.where(pr.inside, np.abs(pr.lateral), np.inf)
    i = int(np.argmin(d))
    if not np.isfinite(d[i]):
        return near
    return host.point_at(pr.chainage[i])[0]


def _extend(curve: Centerline, start: float, end: float) -> tuple[Centerline, float]:
    """The curve extended along its end tangents to chainages ``start`` (< 0) and ``end``
    (> length); returns it and the chainage shift of the old samples."""
    lo, hi = min(start, 0.0), max(end, curve.length)
    if lo >= -1e-6 and hi <= curve.length + 1e-6:
        return curve, 0.0
    step = float(np.median(np.diff(curve.chainage)))
    s = np.concatenate([np.arange(lo, 0.0, step), curve.chainage,
                        np.arange(curve.length + step, hi + step / 2, step)])
    out = Centerline.from_polyline(curve.point_at(s), step=step, centres=curve.centres,
                                   meta=dict(curve.meta))
    return out, -lo


def extract_network(
    xyz: np.ndarray,
    *,
    slicing: SlicingConfig | None = None,
    settings: CenterlineConfig | None = None,
    network: NetworkConfig | None = None,
    progress: ProgressCallback | None = None,
    leave_out_any: bool = False,
) -> NetworkResult:
    """The centreline network of a drift-network point cloud.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        World coordinates, metres, z up (drifts near-horizontal; ramps are fine).
    slicing, settings : SlicingConfig, CenterlineConfig, optional
        The per-slice parameters, as for :func:`~tunneldef.centerline.extract_centerline`.
    network : NetworkConfig, optional
        The ``[network]`` parameters (plan grid, spurs, junctions).
    progress : ProgressCallback, optional
        Called with ("network centrelines", fraction).
    leave_out_any : bool
        Leave out any edge whose sections cannot be read, not only a dead end (the compared
        epoch's network, whose edges only place it on the reference's: a cross-cut that
        walker saw a few metres into either side of a crossing is no edge to refuse the
        survey over; the registration is checked on its own). Otherwise an edge between
        junctions, or one other drifts cross, carries the network, and one that cannot be
        read stops the run.

    Returns
    -------
    NetworkResult
        Edges are numbered by decreasing length (edge 0 is the longest drift).

    Raises
    ------
    NetworkError
        Drifts above one another, an implausible extent, or an edge with too few tunnel
        sections.
    NotATunnelError, InvalidCloudError
        If the cloud is too small or not finite.
    """
    sl = slicing or SlicingConfig()
    c = settings or CenterlineConfig()
    nc = network or NetworkConfig()
    t0 = time.perf_counter()
    pts = check_points(xyz, min_points=1)
    need = sl.min_points * c.min_slices
    if len(pts) < need:
        raise NotATunnelError(
            f"the cloud has {len(pts)} points; a centreline needs at least {need}"
        )
    if len(pts) > c.max_points > 0:
        keep = random_keep(len(pts), c.max_points / len(pts))
        pts = pts[keep]
    notify(progress, "network centrelines", 0.0)
    grid, graph = plan_graph(pts, nc)
    pts = pts[grid.keep]
    t_graph = time.perf_counter() - t0
    order = np.argsort([-e.length for e in graph.edges], kind="stable")
    sk_edges = [graph.edges[i] for i in order]
    renum = {int(old): new for new, old in enumerate(order)}
    members = {v: sorted(renum[k] for k in ks) for v, ks in graph.junctions.items()}
    edges: list[_Edge] = []
    for e in sk_edges:
        half = path_half_width(grid, e.path)
        free = tuple(v not in members for v in e.nodes[:2])
        path, cut = _trim_free_ends(e.path, free, half / grid.cell)
        axis = _axis_from_path(path, grid)
        if any(cut):  # straight on to where the skeleton ended
            axis = _extend(axis, -cut[0] * grid.cell, axis.length + cut[1] * grid.cell)[0]
        tube, index = _tube(axis, half, pts)
        edges.append(_Edge(e.path, list(e.nodes), list(getattr(e, "through", [])), axis, half,
                           tube, index))
        edges[-1].corners = _corners(axis, half, nc.zone_margin)
    # node positions from the first axes (plan node, height of the first member's axis)
    node_xyz: dict[int, np.ndarray] = {}
    for v, ks in members.items():
        plan = grid.to_world(graph.nodes[v][None])[0]
        ax = edges[ks[0]].axis
        s = ax.project(np.array([[plan[0], plan[1], float(np.median(ax.points[:, 2]))]]))
        node_xyz[v] = np.array([plan[0], plan[1], float(ax.point_at(s.chainage)[0, 2])])
    axes = [e.axis for e in edges]
    zones = _zones(edges, node_xyz, axes, members, nc.zone_margin)
    for k, e in enumerate(edges):  # a skeleton axis bends into a crossing's forks: no corner
        reach = e.half_width + 2.0
        e.corners = [(xyz, h) for xyz, h in e.corners if not any(
            a - reach <= float(e.axis.project(xyz[None]).chainage[0]) <= b + reach
            for a, b in zones[k])]
    # a change of section with no junction there (a drift going on as a ramp) is treated as
    # a corner
    for k, e in enumerate(edges):
        reach = e.half_width + 2.0
        blocked = [(a - reach, b + reach) for a, b in zones[k]]
        blocked += [(c - h, c + h) for c, h in
                    ((float(e.axis.project(xyz[None]).chainage[0]), h) for xyz, h in e.corners)]
        for xyz, h in _width_steps(e.axis, grid, blocked, nc.zone_margin):
            logger.info("the drift's section changes at %s", np.round(xyz, 1).tolist())
            e.corners.append((xyz, h))
    # a corner (or change of section) with long legs either side cuts its edge in two at a
    # node; a shorter one stays a zone of one curve
    edges, members, corner_nodes = _split_at_corners(edges, members, node_xyz, zones, pts, grid)
    if corner_nodes:
        zones = _zones(edges, node_xyz, [e.axis for e in edges], members, nc.zone_margin)
    for e in edges:
        for xyz, h in e.corners:
            logger.info("a skeleton edge turns a corner or changes section at %s: sections "
                        "within %.1f m of it are flagged as a junction zone",
                        np.round(xyz, 1).tolist(), h)
    at = [[v for v, ks in members.items() if k in ks] for k in range(len(edges))]
    names = [f"edge {k} ({e.axis.length:.1f} m from {np.round(e.axis.points[0], 1).tolist()})"
             for k, e in enumerate(edges)]
    # round 1: straighten every skeleton axis, then place the junctions on those curves. A
    # dead end whose sections cannot be read (a cross-cut seen a few metres in from the main
    # drift, mostly its mouth) is left out, said so, rather than failing the network.
    failed: dict[int, str] = {}
    first = []
    for k, e in enumerate(edges):
        notify(progress, "network centrelines", 0.1 + 0.3 * k / len(edges))
        try:
            first.append(_passes(pts[e.index], e, e.axis, _with_corners(zones[k], e.axis,
                                 e.corners), [node_xyz[v] for v in at[k]] + _corner_points(e),
                                 sl, c, names[k], quick=True)[0])
        except (NetworkError, NotATunnelError) as exc:
            _leave_out(failed, k, e, members, names[k], exc, leave_out_any)
            first.append(e.axis)
    _place_nodes(edges, first, members, node_xyz, skip=failed, corners=corner_nodes)
    zones = _zones(edges, node_xyz, first, members, nc.zone_margin)
    # round 2: the paper's passes along those curves, junction zones at the placed nodes
    for k, e in enumerate(edges):
        notify(progress, "network centrelines", 0.4 + 0.5 * k / len(edges))
        if k not in failed:
            try:
                e.curve, e.records = _passes(pts[e.index], e, first[k],
                                             _with_corners(zones[k], first[k], e.corners),
                                             [node_xyz[v] for v in at[k]] + _corner_points(e),
                                             sl, c, names[k])
                continue
            except (NetworkError, NotATunnelError) as exc:
                _leave_out(failed, k, e, members, names[k], exc, leave_out_any)
        e.curve, e.records = first[k], []
    if len(failed) == len(edges):
        raise NetworkError(f"no edge of the network can be read: {next(iter(failed.values()))}")
    _place_nodes(edges, [e.curve for e in edges], members, node_xyz, skip=failed,
                 corners=corner_nodes)
    # extend edges that end at a junction to its node
    final: list[Centerline] = []
    for e in edges:
        cv = e.curve
        lo, hi = 0.0, cv.length
        for side, v in enumerate(e.nodes):
            if v in members:
                s = float(cv.project(node_xyz[v][None]).chainage[0])
                lo, hi = (min(lo, s), hi) if side == 0 else (lo, max(hi, s))
        cv, shift = _extend(cv, lo, hi)
        for r in e.records:
            r.station += shift
        final.append(cv)
    half = [[(b - a) / 2 for a, b in z] for z in zones]
    zones = [[(s - h, s + h) for s, h in zip(
        [float(final[k].project(node_xyz[v][None]).chainage[0]) for v in at[k]], half[k],
        strict=True)] for k in range(len(edges))]
    jid = {v: i for i, v in enumerate(sorted(members))}
    out_edges = []
    for k, (e, cv) in enumerate(zip(edges, final, strict=True)):
        ok = [r for r in e.records if r.ok]
        if ok:
            s = cv.project(np.array([r.centre for r in ok])).chainage
            for r, si in zip(ok, s, strict=True):
                r.chainage = float(si)
        zs = tuple(sorted((max(a, 0.0), min(b, cv.length))
                          for a, b in _with_corners(zones[k], cv, e.corners)))
        cv.meta.update({"edge": k, "half_width_m": e.half_width})
        out_edges.append(NetworkEdge(k, f"edge-{k}", cv, zs,
                                     tuple(jid.get(v, -1) for v in e.nodes), e.records))
    # each curve was extended to reach its nodes: a node's chainage lies on it (clipped, so
    # rounding cannot put a node at an end a hair outside its own zone)
    junctions = tuple(
        Junction(jid[v], node_xyz[v], tuple(ks),
                 tuple(float(np.clip(final[k].project(node_xyz[v][None]).chainage[0], 0.0,
                                     final[k].length)) for k in ks))
        for v, ks in sorted(members.items())
    )
    meta = {
        "method": "plan skeleton + per-edge slices (paper §3.1)",
        "grid_cell_m": grid.cell,
        "grid_shape": list(grid.footprint.shape),
        "height_m": grid.height,
        "stray_points": int((~grid.keep).sum()),
        "corners": sorted(jid[v] for v in corner_nodes),
        "timings_s": {"graph": t_graph, "total": time.perf_counter() - t0},
    }
    notify(progress, "network centrelines", 1.0)
    net = CenterlineNetwork(tuple(out_edges), junctions, meta).without(failed)
    return NetworkResult(net, grid, graph)


def _leave_out(failed: dict[int, str], k: int, e: _Edge, members: dict[int, list[int]],
               name: str, exc: Exception, any_edge: bool = False) -> None:
    """Record that edge ``k`` is left out because its passes failed (``exc``), or raise a
    :class:`NetworkError` when it is no branch off the network: only a dead end that leaves
    one junction (and passes through none) can be dropped; an edge between junctions, or one
    that other drifts cross, carries the network (``any_edge``: every edge can be dropped)."""
    ends = [v in members for v in e.nodes[:2]]
    if not any_edge and (sum(ends) != 1 or e.through):
        raise NetworkError(str(exc)) from exc
    reason = str(exc).split("; raise")[0]
    logger.warning("network: %s left out, its sections cannot be read: %s", name, reason)
    failed[k] = f"its sections cannot be read: {reason}"

