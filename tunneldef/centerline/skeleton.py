"""The topology of a drift network from its plan view: occupancy, skeleton, graph.

Mine drifts are near-horizontal (ramps climb at 10-15 %), so seen from above the floor and roof
points of a drift fill its footprint, and the footprint's medial axis (skeleton) is the plan
view of the network's centrelines. This module turns a point cloud into that skeleton graph:

1. Robust extent: points are counted in coarse (1 m) plan cells; cells with fewer than
   ``min_coarse_count`` points are dropped and so are connected groups of cells smaller than
   ``min_component_area``, so a stray point or a small far cluster neither creates an edge nor
   stretches the grid. The fine grid is allocated over what is left, and refused beyond
   ``max_cells`` cells.
2. Footprint: fine cells (``cell``) with at least ``min_count`` points, closed by a small disk
   (sparse scans leave empty cells between points), holes smaller than ``max_hole_area``
   filled (the blind cone under a static scanner, a missing patch of floor); larger holes are
   pillars between drifts and stay.
3. Heights: per cell the 5th and 95th percentiles of z (floor and roof over the interior).
   A cell whose span is far larger than the footprint's typical height shows two drifts above
   one another (or a shaft); the plan view cannot separate them and
   :class:`~tunneldef.errors.NetworkError` is raised.
4. Skeleton (scikit-image) and its pixel graph: nodes are skeleton pixels with other than two
   neighbours (clusters of adjacent ones merged), edges the pixel chains between them.
5. Simplification: spurs (leaf edges protruding less than ``min_branch_length`` beyond the
   tunnel wall at their node: the corners of a drift's end, niches) are pruned, nodes of
   degree two are dissolved, and nodes closer than the tunnel's half-width are merged (a
   four-way crossing often skeletonises as two three-way nodes).
6. Through edges: at each junction the two most nearly opposite edges (within
   ``through_angle_deg`` of a straight line) are joined into one edge that passes the junction,
   so the main drift keeps one chainage through its cross-cuts and a through cross-cut is one
   branch; what remains ends at the junction.

Why the plan view rather than a 3-D skeleton: a handheld scan samples the shell, not the
volume; filling the inside of a 3-D occupancy grid needs the same "between floor and roof"
rule per plan column that the plan view uses, at 1/100 of the memory (a 250 m network at
0.2 m: 0.1 M plan cells against 10 M voxels). Its limit is drifts above one another, which is
detected and refused, not silently merged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import NetworkError

__all__ = ["PlanGrid", "SkeletonEdge", "SkeletonGraph", "plan_grid", "skeleton_graph"]


@dataclass
class PlanGrid:
    """The footprint of a network on a plan grid.

    Attributes
    ----------
    origin : ndarray, shape (2,)
        World x, y of the corner of cell (0, 0), metres.
    cell : float
        Cell size, metres.
    footprint : ndarray of bool, shape (nx, ny)
        Cells inside a drift.
    z_low, z_high : ndarray, shape (nx, ny)
        5th / 95th percentile of z per cell (NaN where no points).
    half_width : ndarray, shape (nx, ny)
        Distance to the nearest cell outside the footprint, metres (the medial axis's radius).
    keep : ndarray of bool, shape (N,)
        Points that lie in the retained extent (False: strays).
    height : float
        Median floor-to-roof span over the footprint's interior, metres.
    """

    origin: np.ndarray
    cell: float
    footprint: np.ndarray
    z_low: np.ndarray
    z_high: np.ndarray
    half_width: np.ndarray
    keep: np.ndarray
    height: float

    def to_world(self, ij: np.ndarray) -> np.ndarray:
        """World x, y (K, 2) of cell centres ``ij`` (K, 2)."""
        return self.origin + (np.asarray(ij, dtype=np.float64) + 0.5) * self.cell


def _components(keys: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected components of integer plan cells ``keys`` (K, 2)."""
    pairs = cKDTree(keys).query_pairs(1.5, output_type="ndarray")
    n = len(keys)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    ncomp, labels = connected_components(g, directed=False)
    return labels, ncomp


def plan_grid(
    xyz: np.ndarray,
    *,
    cell: float = 0.2,
    min_count: int = 2,
    coarse: float = 1.0,
    min_coarse_count: int = 20,
    min_component_area: float = 20.0,
    max_hole_area: float = 16.0,
    max_cells: int = 20_000_000,
    max_height_ratio: float = 1.8,
    max_stacked_area: float = 2.0,
) -> PlanGrid:
    """Plan-view occupancy, heights and half-widths of a network cloud.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Points, metres, z up.
    cell : float
        Fine cell size, metres.
    min_count : int
        Least points for a fine cell to be occupied.
    coarse, min_coarse_count, min_component_area :
        Coarse cell size (m), least points per coarse cell, least area (m^2) of a connected
        group of coarse cells: what fails these is stray.
    max_hole_area : float
        Holes of the footprint smaller than this are filled, m^2.
    max_cells : int
        Largest fine grid allocated.
    max_height_ratio, max_stacked_area :
        Cells whose z span exceeds ``max_height_ratio`` times the median span, over more than
        ``max_stacked_area`` m^2, mean drifts above one another.

    Raises
    ------
    NetworkError
        No dense part, an extent too large for the grid, or drifts above one another.
    """
    from skimage.morphology import disk, remove_small_holes, remove_small_objects

    xy = xyz[:, :2]
    ck = np.floor(xy / coarse).astype(np.int64)
    key = (ck[:, 0] + 2**31) * 2**32 + (ck[:, 1] + 2**31)
    ukey, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    uk = np.stack([ukey // 2**32 - 2**31, ukey % 2**32 - 2**31], axis=1)
    dense = cnt >= min_coarse_count
    if not dense.any():
        raise NetworkError(
            f"no part of the cloud holds {min_coarse_count} points per {coarse:g} m plan cell; "
            "is it a tunnel scan in metres?"
        )
    labels, ncomp = _components(uk[dense])
    area = np.bincount(labels, minlength=ncomp) * coarse**2
    good_comp = area >= min_component_area
    if not good_comp.any():
        raise NetworkError(
            f"the cloud's largest dense part covers {area.max():.1f} m^2 of plan, less than "
            f"{min_component_area:g} m^2; is it a tunnel scan in metres?"
        )
    good_cell = np.zeros(len(uk), dtype=bool)
    good_cell[np.flatnonzero(dense)[good_comp[labels]]] = True
    keep = good_cell[inv]
    p = xyz[keep]
    lo = p[:, :2].min(axis=0) - 2 * cell
    hi = p[:, :2].max(axis=0) + 2 * cell
    shape = np.ceil((hi - lo) / cell).astype(np.int64) + 1
    if shape[0] * shape[1] > max_cells:
        raise NetworkError(
            f"the network's plan extent ({hi[0] - lo[0]:.0f} m x {hi[1] - lo[1]:.0f} m) needs "
            f"{shape[0] * shape[1]:,} cells of {cell} m, more than {max_cells:,}; raise the "
            "network cell size"
        )
    ij = np.floor((p[:, :2] - lo) / cell).astype(np.int64)
    lin = ij[:, 0] * shape[1] + ij[:, 1]
    counts = np.bincount(lin, minlength=shape[0] * shape[1]).reshape(shape)
    occ = counts >= min_count
    occ = ndimage.binary_closing(occ, structure=disk(2), border_value=0)
    occ = remove_small_holes(occ, max_size=max(int(max_hole_area / cell**2), 1))
    occ = remove_small_objects(occ, max_size=max(int(min_component_area / cell**2), 1))
    # per-cell z percentiles: sort by (cell, z), pick by rank
    order = np.lexsort((p[:, 2], lin))
    ls, zs = lin[order], p[order, 2]
    starts = np.flatnonzero(np.concatenate([[True], ls[1:] != ls[:-1]]))
    n = np.diff(np.append(starts, len(ls)))
    z_low = np.full(shape[0] * shape[1], np.nan)
    z_high = np.full_like(z_low, np.nan)
    z_low[ls[starts]] = zs[starts + np.floor(0.05 * (n - 1)).astype(np.int64)]
    z_high[ls[starts]] = zs[starts + np.ceil(0.95 * (n - 1)).astype(np.int64)]
    z_low, z_high = z_low.reshape(shape), z_high.reshape(shape)
    half_width = ndimage.distance_transform_edt(occ) * cell
    interior = occ & (half_width > 3 * cell) & (counts >= 4)
    spans = (z_high - z_low)[interior]
    if spans.size == 0:
        raise NetworkError("the cloud's footprint has no interior; is it a tunnel scan?")
    height = float(np.median(spans))
    tall = interior & (z_high - z_low > max_height_ratio * height)
    if tall.sum() * cell**2 > max_stacked_area:
        where = lo + (np.argwhere(tall).mean(axis=0) + 0.5) * cell
        raise NetworkError(
            f"{tall.sum() * cell**2:.0f} m^2 of the plan span more than {max_height_ratio:g} x "
            f"the drifts' {height:.2f} m height (around x={where[0]:.1f}, y={where[1]:.1f}): "
            "drifts above one another or a shaft, which the plan-view network cannot separate"
        )
    return PlanGrid(lo, cell, occ, z_low, z_high, half_width, keep, height)


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
        # 2. merge nodes joined by a short edge (within the drift's half-width)
        for k, e in enumerate(edges):
            a, b = e.nodes
            if a < 0 or b < 0 or a == b:
                continue
            if e.length <= max(radius[a], radius[b]) and len(inc[a]) >= 3 and len(inc[b]) >= 3:
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
