"""The topology of a drift network: the skeleton of its plan footprint as a graph.

Steps of :func:`skeleton_graph`, on a :class:`~tunneldef.centerline.plan.PlanGrid`:

1. Skeleton (scikit-image) and its pixel graph: nodes are skeleton pixels with other than two
   neighbours (clusters of adjacent ones merged), edges the pixel chains between them.
2. Simplification: spurs (leaf edges protruding less than ``min_branch_length`` beyond the
   tunnel wall at their node: the corners of a drift's end, niches) are pruned, nodes of
   degree two are dissolved, and nodes closer than the tunnel's half-width are merged (a
   four-way crossing often skeletonises as two three-way nodes).
3. Through edges: at each junction the two most nearly opposite edges (within
   ``through_angle_deg`` of a straight line) are joined into one edge that passes the junction,
   so the main drift keeps one chainage through its cross-cuts and a through cross-cut is one
   branch; what remains ends at the junction.

:func:`plan_topology` is the same look at an epoch in a fraction of a second per million
points, for a single-tube run to ask first whether its epochs are one drift at all.

One idea at this length: one algorithm, the plan skeleton and its simplification into a graph, whose
three steps share the pixel graph.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..config import NetworkConfig
from ..errors import NetworkError, TunnelDefError
from ..spatial import random_keep
from .plan import PlanGrid, plan_grid

__all__ = [
    "SkeletonEdge", "SkeletonGraph", "skeleton_graph", "PlanTopology", "plan_graph",
    "plan_topology", "sharp_turns", "path_half_width", "CORNER_TURN_DEG",
]

#: a drift turning more than this (degrees) within a chord of its half-width + 2 m either side
#: turns a corner: its sections there are no tunnel sections (a bend of radius below about
#: 1.3 chords; mine bends of 10 m and more turn some 25 degrees over that chord)
CORNER_TURN_DEG = 45.0


def path_half_width(grid: PlanGrid, path: np.ndarray) -> float:
    """Median half-width (m) of the plan footprint along a skeleton path (plan cells); 1 m
    for an empty path."""
    hw = grid.half_width[tuple(np.round(path).astype(np.int64).T)]
    return float(np.median(hw)) if hw.size else 1.0


def sharp_turns(
    xy: np.ndarray, half_width: float, *, trim: float = 0.0, step: float = 0.25,
    min_leg: float = 0.0,
) -> list[tuple[float, float]]:
    """Corners along a plan polyline: the arclength (m) and turn (degrees) of each stretch
    where the heading over a chord of ``half_width + 2`` m before a station differs from the
    one after by more than :data:`CORNER_TURN_DEG` (the sharpest station of each stretch).
    Stations within a chord plus ``trim`` of either end are not looked at.

    Parameters
    ----------
    xy : ndarray, shape (K, 2) or (K, 3)
        Points in order, metres: the arclength is along them, the headings in plan.
    half_width : float
        The drift's half-width, metres.
    min_leg : float
        A corner's legs must both reach this far from the corner across the other leg's
        heading (the polyline's farthest point before it from the line of the heading after,
        and the other way round), metres; 0 keeps every turn. An alcove or chamber at a
        drift's end bends the end of its medial axis by a right angle too, but its "leg"
        reaches no farther than a niche does (the rule that prunes dead ends:
        ``network.min_branch_length`` beyond the drift's wall).
    """
    pts = np.asarray(xy, dtype=np.float64)
    if len(pts) < 2:
        return []
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    xy = pts[:, :2]
    chord = half_width + 2.0
    s = np.arange(chord + trim, arc[-1] - chord - trim, step)
    if s.size < 3:
        return []

    def at(t: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, arc, xy[:, 0]), np.interp(t, arc, xy[:, 1])])

    p0, p1, p2 = at(s - chord), at(s), at(s + chord)
    u, w = p1 - p0, p2 - p1
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    w /= np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-12)
    turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", u, w), -1.0, 1.0)))
    out = []
    sharp = turn > CORNER_TURN_DEG
    edges = np.flatnonzero(np.diff(np.concatenate([[0], sharp.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        j = a + int(np.argmax(turn[a:b]))
        if min_leg > 0:
            rel = xy - p1[j]
            before, after = arc < s[j], arc > s[j]
            # farthest reach of each leg across the other leg's heading
            reach_after = np.abs(rel[after] @ np.array([-u[j, 1], u[j, 0]]))
            reach_before = np.abs(rel[before] @ np.array([-w[j, 1], w[j, 0]]))
            if min(reach_after.max(initial=0.0), reach_before.max(initial=0.0)) < min_leg:
                continue
        out.append((float(s[j]), float(turn[j])))
    return out


@dataclass
class SkeletonEdge:
    """A chain of skeleton pixels between two nodes (``-1``: a free end)."""

    nodes: list[int]
    path: np.ndarray  # (P, 2) cell indices, from nodes[0] to nodes[1]
    length: float = 0.0


@dataclass
class SkeletonGraph:
    """Nodes (plan cell positions, radii) and edges of a network's skeleton.

    Attributes
    ----------
    nodes : dict of int -> ndarray, shape (2,)
        Node positions as fractional cell indices.
    radius : dict of int -> float
        Half-width of the footprint at each node, metres.
    edges : list of SkeletonEdge
    junctions : dict of int -> list of (edge index, end)
        After :func:`skeleton_graph`: which edge ends (0 start / 1 end), or edges passing
        through, meet at each junction node.
    """

    nodes: dict[int, np.ndarray]
    radius: dict[int, float]
    edges: list[SkeletonEdge]
    junctions: dict[int, list[int]] = field(default_factory=dict)


def _pixel_graph(skel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Skeleton pixel coordinates (K, 2) and their neighbour pairs (E, 2), 8-connected but
    without diagonal links that a 4-connected path already joins (staircases)."""
    pix = np.argwhere(skel)
    idx = -np.ones(skel.shape, dtype=np.int64)
    idx[pix[:, 0], pix[:, 1]] = np.arange(len(pix))
    pad = np.pad(idx, 1, constant_values=-1)
    on = np.pad(skel, 1, constant_values=False)
    pairs = []
    i, j = pix[:, 0] + 1, pix[:, 1] + 1
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        other = pad[i + di, j + dj]
        m = other >= 0
        if di and dj:  # diagonal: drop when a 4-neighbour path exists
            m &= ~(on[i + di, j] | on[i, j + dj])
        pairs.append(np.stack([np.arange(len(pix))[m], other[m]], axis=1))
    return pix, np.concatenate(pairs)


def _path_length(path: np.ndarray, cell: float) -> float:
    return float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)) * cell) if len(path) > 1 \
        else 0.0


def _trace(pix: np.ndarray, pairs: np.ndarray, deg: np.ndarray) -> tuple[dict, list]:
    """Node clusters and pixel chains of a skeleton pixel graph."""
    n = len(pix)
    nbrs: list[list[int]] = [[] for _ in range(n)]
    for a, b in pairs:
        nbrs[a].append(b)
        nbrs[b].append(a)
    is_node = deg != 2
    # cluster adjacent node pixels
    node_pairs = pairs[is_node[pairs[:, 0]] & is_node[pairs[:, 1]]]
    g = coo_matrix((np.ones(len(node_pairs)), (node_pairs[:, 0], node_pairs[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    node_of = np.where(is_node, lab, -1)
    clusters: dict[int, list[int]] = {}
    for p in np.flatnonzero(is_node):
        clusters.setdefault(int(node_of[p]), []).append(int(p))
    seen = np.zeros(n, dtype=bool)
    chains: list[tuple[int, int, list[int]]] = []
    for c, members in clusters.items():
        for p in members:
            for q in nbrs[p]:
                if is_node[q] or seen[q]:
                    continue
                path, prev, cur = [p, q], p, q
                seen[q] = True
                while not is_node[cur]:
                    nxt = [r for r in nbrs[cur] if r != prev]
                    if not nxt:
                        break
                    prev, cur = cur, nxt[0]
                    if not is_node[cur]:
                        if seen[cur]:
                            break
                        seen[cur] = True
                    path.append(cur)
                end = int(node_of[cur]) if is_node[cur] else -1
                chains.append((c, end, path))
    # loops without any node (a ring drift): cut at an arbitrary pixel
    for p in np.flatnonzero(~is_node & ~seen):
        if seen[p]:
            continue
        path, prev, cur = [int(p)], -1, int(p)
        seen[p] = True
        while True:
            nxt = [r for r in nbrs[cur] if r != prev and not seen[r]]
            if not nxt:
                break
            prev, cur = cur, nxt[0]
            seen[cur] = True
            path.append(cur)
        cid = max(clusters, default=-1) + 1
        clusters[cid] = [int(p)]
        chains.append((cid, cid, path + [int(p)]))
    return clusters, chains


def skeleton_graph(
    grid: PlanGrid,
    *,
    min_branch_length: float = 3.0,
    through_angle_deg: float = 35.0,
) -> SkeletonGraph:
    """The simplified skeleton graph of a footprint (see the module notes, steps 4-6).

    Parameters
    ----------
    grid : PlanGrid
    min_branch_length : float
        A dead-end edge must reach this far beyond the wall of the drift it leaves, metres.
    through_angle_deg : float
        Two edges meeting within this angle of a straight line pass through their junction as
        one edge.

    Returns
    -------
    SkeletonGraph
        Edges with their pixel paths and a ``junctions`` map of node -> member edge indices.
    """
    from skimage.morphology import skeletonize

    skel = skeletonize(grid.footprint)
    pix, pairs = _pixel_graph(skel)
    if len(pix) < 2:
        raise NetworkError("the footprint's skeleton is empty; is the cloud a tunnel scan?")
    deg = np.bincount(pairs.ravel(), minlength=len(pix))
    clusters, chains = _trace(pix, pairs, deg)
    cell = grid.cell
    nodes = {c: pix[m].mean(axis=0) for c, m in clusters.items()}
    radius = {c: float(grid.half_width[tuple(pix[m[0]])]) for c, m in clusters.items()}
    edges = [
        SkeletonEdge([a, b], pix[path].astype(np.float64), _path_length(pix[path], cell))
        for a, b, path in chains
    ]
    edges = _simplify(edges, nodes, radius, grid, min_branch_length)
    graph = SkeletonGraph(nodes, radius, edges)
    _join_through(graph, cell, through_angle_deg)
    return graph


def _incidence(edges: list[SkeletonEdge]) -> dict[int, list[int]]:
    inc: dict[int, list[int]] = {}
    for k, e in enumerate(edges):
        for v in e.nodes:
            if v >= 0:
                inc.setdefault(v, []).append(k)
    return inc


def _simplify(
    edges: list[SkeletonEdge],
    nodes: dict[int, np.ndarray],
    radius: dict[int, float],
    grid: PlanGrid,
    min_branch: float,
) -> list[SkeletonEdge]:
    cell = grid.cell
    edges = [e for e in edges if len(e.path) >= 2]
    for _ in range(100):
        changed = False
        inc = _incidence(edges)
        # 1. prune spurs: a leaf edge (one end free or of degree one) that barely leaves the wall
        for k, e in enumerate(edges):
            a, b = e.nodes
            deg_a = len(inc.get(a, []))
            deg_b = len(inc.get(b, []))
            if a == b:
                continue
            leaf_b = deg_b <= 1 and deg_a >= 3
            leaf_a = deg_a <= 1 and deg_b >= 3
            if leaf_a or leaf_b:
                hub = b if leaf_a else a
                if e.length - radius.get(hub, 0.0) < min_branch:
                    edges.pop(k)
                    changed = True
                    break
        if changed:
            continue
        # 2. merge nodes joined by a short edge (within the drift's half-width), or by one up
        # to 2.5 half-widths long that continues no drift straight on (an oblique crossing's
        # medial axis splits into two forks a few metres apart, joined across the crossing)
        for k, e in enumerate(edges):
            a, b = e.nodes
            if a < 0 or b < 0 or a == b or len(inc[a]) < 3 or len(inc[b]) < 3:
                continue
            r = max(radius[a], radius[b])
            short = e.length <= r or (e.length <= 2.5 * r and (
                _crosses(edges, inc, k, cell, r) or not _continues(edges, inc, k, cell, r)))
            if short:
                edges.pop(k)
                w = np.array([len(inc[a]), len(inc[b])], dtype=np.float64)
                nodes[a] = (nodes[a] * w[0] + nodes[b] * w[1]) / w.sum()
                radius[a] = max(radius[a], radius[b])
                for f in edges:
                    f.nodes = [a if v == b else v for v in f.nodes]
                    if f.nodes[0] == a:
                        f.path = np.vstack([nodes[a][None], f.path[1:]])
                    if f.nodes[1] == a:
                        f.path = np.vstack([f.path[:-1], nodes[a][None]])
                changed = True
                break
        if changed:
            continue
        # 3. dissolve nodes of degree two
        for v, ks in inc.items():
            if len(ks) != 2 or ks[0] == ks[1]:
                continue
            e, f = edges[ks[0]], edges[ks[1]]
            pe = e.path if e.nodes[1] == v else e.path[::-1]
            pf = f.path if f.nodes[0] == v else f.path[::-1]
            ne = e.nodes[0] if e.nodes[1] == v else e.nodes[1]
            nf = f.nodes[1] if f.nodes[0] == v else f.nodes[0]
            merged = SkeletonEdge([ne, nf], np.vstack([pe, pf[1:]]))
            merged.length = _path_length(merged.path, cell)
            edges = [g for i, g in enumerate(edges) if i not in ks] + [merged]
            changed = True
            break
        if not changed:
            break
    return edges


def _leg(path: np.ndarray, from_start: bool, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """A point and the unit direction of a path's leg from ``reach`` to ``reach + 15`` cells
    away from its start (or end) node: the drift's own axis, beyond the junction."""
    p = path if from_start else path[::-1]
    d = np.linalg.norm(p - p[0], axis=1)
    far = p[(d >= reach) & (d <= reach + 15.0)]
    if len(far) < 2:
        far = p[len(p) // 2:] if len(p) >= 4 else p
    u = far[-1] - far[0]
    n = np.linalg.norm(u)
    return far.mean(axis=0), (u / n if n > 0 else u)


def _crosses(edges: list[SkeletonEdge], inc: dict[int, list[int]], k: int, cell: float,
             radius: float, angle_deg: float = 35.0) -> bool:
    """True when the link edge ``k`` joins the two forks of one crossing: an edge at one of
    its nodes and an edge at the other leave in opposite directions (within ``angle_deg``)
    along one line (their legs beyond the junction within half a drift width of each
    other's line). Two cross-cuts staggered along a drift leave along parallel lines a link
    apart."""
    a, b = edges[k].nodes
    reach = (radius + 2.0) / cell
    cos_lim = -np.cos(np.radians(angle_deg))

    def legs(v: int) -> list[tuple[np.ndarray, np.ndarray]]:
        out = []
        for f in inc.get(v, []):
            if f == k:
                continue
            g = edges[f]
            out += [_leg(g.path, end == 0, reach) for end in (0, 1) if g.nodes[end] == v]
        return out

    for pa, ua in legs(a):
        for pb, ub in legs(b):
            if float(ua @ ub) >= cos_lim:
                continue
            off = pb - pa
            gap = abs(float(off[0] * ua[1] - off[1] * ua[0]))  # distance from a's line, cells
            if gap * cell <= 0.5 * radius:
                return True
    return False


def _continues(edges: list[SkeletonEdge], inc: dict[int, list[int]], k: int, cell: float,
               radius: float, angle_deg: float = 15.0) -> bool:
    """True when the link edge ``k`` carries on another edge at either of its nodes straight
    on (within ``angle_deg``): a drift passing two junctions a few metres apart, which must
    stay two junctions."""
    link = edges[k]
    reach = (radius + 2.0) / cell
    cos_lim = -np.cos(np.radians(angle_deg))
    for side, v in enumerate(link.nodes):
        u = _direction(link.path, side == 0, reach)
        for f in inc.get(v, []):
            if f == k:
                continue
            g = edges[f]
            for end in (0, 1):
                if g.nodes[end] == v and float(u @ _direction(g.path, end == 0, reach)) < cos_lim:
                    return True
    return False


def _direction(path: np.ndarray, from_start: bool, reach: float) -> np.ndarray:
    """Unit plan direction of a path leaving its start (or end) node, measured ``reach``
    cells away (beyond the junction's disturbance)."""
    p = path if from_start else path[::-1]
    d = np.linalg.norm(p - p[0], axis=1)
    i = int(np.searchsorted(d, reach)) if d[-1] > reach else len(p) - 1
    v = p[i] - p[0]
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def _join_through(graph: SkeletonGraph, cell: float, angle_deg: float) -> None:
    """Join the most nearly straight pairs of edges at each junction into through edges and
    record each junction's member edges."""
    edges = graph.edges
    inc = _incidence(edges)
    cos_lim = -np.cos(np.radians(angle_deg))
    link: dict[tuple[int, int], tuple[int, int]] = {}
    for v, ks in inc.items():
        if len(ks) < 3:
            continue
        reach = (graph.radius[v] + 2.0) / cell
        ends = []
        for k in ks:
            e = edges[k]
            for side in (0, 1):
                if e.nodes[side] == v and (k, side) not in [x[:2] for x in ends]:
                    ends.append((k, side, _direction(e.path, side == 0, reach)))
        free = list(range(len(ends)))
        while len(free) >= 2:
            best, pair = cos_lim, None
            for ia in free:
                for ib in free:
                    if ib <= ia or ends[ia][0] == ends[ib][0]:
                        continue
                    c = float(ends[ia][2] @ ends[ib][2])
                    if c < best:
                        best, pair = c, (ia, ib)
            if pair is None:
                break
            a, b = ends[pair[0]], ends[pair[1]]
            link[(a[0], a[1])] = (b[0], b[1])
            link[(b[0], b[1])] = (a[0], a[1])
            free = [f for f in free if f not in pair]
    # follow the links into chains of edges
    used = np.zeros(len(edges), dtype=bool)
    out: list[SkeletonEdge] = []
    members: dict[int, list[int]] = {}

    def chain_from(k: int, side: int) -> SkeletonEdge:
        paths, nodes_seq = [], []
        cur, entry = k, side
        start_node = edges[k].nodes[side]
        while True:
            used[cur] = True
            e = edges[cur]
            p = e.path if entry == 0 else e.path[::-1]
            paths.append(p if not paths else p[1:])
            exit_side = 1 - entry
            v = e.nodes[exit_side]
            nxt = link.get((cur, exit_side))
            if nxt is None or used[nxt[0]]:
                end_node = v
                break
            nodes_seq.append(v)
            cur, entry = nxt
        path = np.vstack(paths)
        se = SkeletonEdge([start_node, end_node], path, _path_length(path, cell))
        se.through = nodes_seq  # type: ignore[attr-defined]
        return se

    for k in range(len(edges)):
        if used[k]:
            continue
        for side in (0, 1):
            if (k, side) not in link:
                out.append(chain_from(k, side))
                break
    for k in range(len(edges)):
        if not used[k]:  # a ring of through links: cut anywhere
            out.append(chain_from(k, 0))
    for i, e in enumerate(out):
        for v in list(e.nodes) + list(getattr(e, "through", [])):
            if v >= 0 and len(inc.get(v, [])) >= 3:
                members.setdefault(v, [])
                if i not in members[v]:
                    members[v].append(i)
    graph.edges = out
    graph.junctions = members


@dataclass(frozen=True)
class PlanTopology:
    """What the plan skeleton says an epoch is.

    Attributes
    ----------
    lengths : tuple of float
        Length of every drift (skeleton edge), metres, longest first; empty when the plan
        could not be read (``reason`` says why).
    junctions : int
        Nodes where drifts meet (0 for one drift, whatever its bends and niches).
    reason : str
        Why the plan says nothing ("" when it was read).
    corners : int
        Sharp turns of the drifts away from junctions (:func:`sharp_turns`) whose legs both
        reach ``network.min_branch_length`` beyond the other drift's wall: a walk round a
        corner, e.g. from a drift's end into a cross-cut (not a chamber at a drift's end).
    """

    lengths: tuple[float, ...]
    junctions: int
    reason: str = ""
    corners: int = 0

    def describe(self) -> str:
        """E.g. ``"3 drifts (40.2, 24.1, 12.0 m) meeting at 2 junctions"``."""
        if self.reason:
            return f"plan not read ({self.reason})"
        ls = ", ".join(f"{v:.1f}" for v in self.lengths)
        n = len(self.lengths)
        turns = (f", turning {self.corners} corner{'s' if self.corners != 1 else ''}"
                 if self.corners else "")
        if not self.junctions:
            return f"{n} drift{'s' if n != 1 else ''} ({ls} m), no junction{turns}"
        return (f"{n} drift{'s' if n != 1 else ''} ({ls} m) meeting at {self.junctions} "
                f"junction{'s' if self.junctions != 1 else ''}")


def plan_graph(xyz: np.ndarray, nc: NetworkConfig) -> tuple[PlanGrid, SkeletonGraph]:
    """The plan grid of points (N, 3) and its simplified skeleton graph, with the
    ``[network]`` parameters (raises :class:`~tunneldef.errors.NetworkError` on a plan that
    cannot be read)."""
    grid = plan_grid(xyz, cell=nc.cell, min_count=nc.min_count,
                     min_component_area=nc.min_component_area, max_hole_area=nc.max_hole_area,
                     max_cells=nc.max_cells, max_height_ratio=nc.max_height_ratio)
    graph = skeleton_graph(grid, min_branch_length=nc.min_branch_length,
                           through_angle_deg=nc.through_angle_deg)
    return grid, graph


def plan_topology(
    xyz: np.ndarray, network: NetworkConfig | None = None, *, max_points: int = 2_000_000
) -> PlanTopology:
    """How many drifts an epoch holds and where they meet, from the skeleton of its plan
    footprint (:func:`~tunneldef.centerline.plan.plan_grid`, :func:`skeleton_graph` with the
    ``[network]`` parameters), on at most ``max_points`` points drawn at random (seeded).

    A plan that cannot be read (drifts above one another, a footprint with no interior) is
    reported in ``reason``, not raised: this is a question asked before the real work.

    The answer is remembered for the same array (while it lives, and as long as a sample of
    its rows reads the same): ``detect`` asks it once to choose between one drift and a
    network, and again for its checks.
    """
    nc = network or NetworkConfig()
    key = _memo_key(xyz, nc, max_points)
    if key is not None:
        with _MEMO_LOCK:
            hit = _MEMO.get(id(xyz))
        if hit is not None and hit[0]() is xyz and hit[1] == key:
            return hit[2]
    topo = _plan_topology(xyz, nc, max_points)
    if key is not None:
        with _MEMO_LOCK:
            _MEMO[id(xyz)] = (weakref.ref(xyz), key, topo)
            while len(_MEMO) > _MEMO_SIZE:
                del _MEMO[next(iter(_MEMO))]
    return topo


# id(array) -> (weak reference to it, _memo_key, answer); a weak reference that no longer
# points at the array means the id was reused by another
_MEMO: dict[int, tuple[Any, tuple, PlanTopology]] = {}
_MEMO_LOCK = threading.Lock()
_MEMO_SIZE = 8
_MEMO_SAMPLE = 65_536  # rows read to tell an array changed in place


def _memo_key(xyz: Any, nc: NetworkConfig, max_points: int) -> tuple | None:
    """What :func:`plan_topology`'s answer for ``xyz`` depends on (``None``: not an array
    that can be remembered)."""
    if not isinstance(xyz, np.ndarray):
        return None
    step = max(1, len(xyz) // _MEMO_SAMPLE)
    sample = np.ascontiguousarray(xyz[::step]).tobytes()
    return (nc, max_points, xyz.shape, xyz.dtype.str, hash(sample))


def _plan_topology(xyz: np.ndarray, nc: NetworkConfig, max_points: int) -> PlanTopology:
    pts = np.asarray(xyz, dtype=np.float64)
    if len(pts) > max_points:
        pts = pts[random_keep(len(pts), max_points / len(pts))]
    try:
        grid, graph = plan_graph(pts, nc)
    except TunnelDefError as exc:
        return PlanTopology((), 0, str(exc).split(";")[0])
    lengths = tuple(sorted((float(e.length) for e in graph.edges), reverse=True))
    corners = 0
    if not graph.junctions:  # (a skeleton bends into a crossing's forks: junctions decide)
        for e in graph.edges:
            half = path_half_width(grid, e.path)
            # a free end's medial axis forks to the face's corners within a half-width
            # and an alcove at a drift's end bends it too, but reaches no farther than a niche
            corners += len(sharp_turns(grid.to_world(e.path), half, trim=half,
                                       min_leg=half + nc.min_branch_length))
    return PlanTopology(lengths, len(graph.junctions), corners=corners)
