"""The centreline of a drift network: edges (each a :class:`~tunneldef.curve.Centerline` with
its own chainage) joined at junction nodes, and the assignment of points to edges.

An edge is a main drift, a cross-cut, a ramp or a dead end. Where a straight-on drift crosses
or passes a junction it stays one edge, so its chainage runs on through the junction; an edge
that ends at a junction starts (or ends) there. Along each edge the stretches around its
junctions are *junction zones*: there the section is no tunnel section (a mouth in the wall, a
crossing), no slice was fitted, and the curve bridges them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .curve import Centerline
from .transforms import apply_transform

__all__ = ["NO_BRANCH", "Junction", "NetworkEdge", "NetworkProjection", "CenterlineNetwork"]

#: ``branch`` of points that belong to no edge.
NO_BRANCH = 65535
#: How near one of its ends a junction must list an edge for the edge to leave from that end
#: (the tolerance :meth:`CenterlineNetwork.without` counts branch ends with), m.
END_REACH = 1.0


@dataclass(frozen=True)
class Junction:
    """A junction node.

    Attributes
    ----------
    id : int
    position : ndarray, shape (3,)
        World coordinates, metres (on the centreline of the first member edge).
    edges : tuple of int
        Member edges (those that end here and those that pass through).
    chainages : tuple of float
        Chainage of the junction on each member edge, metres.
    """

    id: int
    position: np.ndarray
    edges: tuple[int, ...]
    chainages: tuple[float, ...]

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        return {
            "id": self.id,
            "position": np.asarray(self.position).tolist(),
            "edges": list(self.edges),
            "chainages_m": list(self.chainages),
        }


@dataclass(frozen=True)
class NetworkEdge:
    """One edge (branch) of a network.

    Attributes
    ----------
    id : int
        The ``branch`` value of its points.
    name : str
    centerline : Centerline
        The edge's curve; chainage 0 at its start.
    zones : tuple of (float, float)
        Chainage intervals at junctions (no fitted slices; the curve is bridged there).
    nodes : (int, int)
        Junction id at the start and the end (-1: a free end, e.g. a face or the scan's end).
    slices : list
        Per-slice records of the last pass (:class:`~tunneldef.centerline.SliceRecord`).
    """

    id: int
    name: str
    centerline: Centerline
    zones: tuple[tuple[float, float], ...] = ()
    nodes: tuple[int, int] = (-1, -1)
    slices: list[Any] = field(default_factory=list)

    @property
    def length(self) -> float:
        """Length of the edge's curve, metres."""
        return self.centerline.length

    def section_size(self) -> tuple[float, float, int]:
        """Median width and height of the edge's fitted slices, metres, and their count
        (NaN, NaN, 0 when none was fitted): the drift's size as a surveyor quotes it."""
        ok = [r for r in self.slices if getattr(r, "ok", False)]
        if not ok:
            return np.nan, np.nan, 0
        return (float(np.median([r.width for r in ok])),
                float(np.median([r.height for r in ok])), len(ok))

    def in_zone(self, chainage: np.ndarray) -> np.ndarray:
        """True where a chainage lies in one of the edge's junction zones."""
        s = np.asarray(chainage, dtype=np.float64)
        out = np.zeros(s.shape, dtype=bool)
        for a, b in self.zones:
            out |= (s >= a) & (s <= b)
        return out

    def to_dict(self, *, curve: bool = True) -> dict[str, Any]:
        """JSON-serialisable form (``curve=False`` leaves out the curve samples)."""
        out: dict[str, Any] = {
            "id": self.id,
            "name": self.name,
            "length_m": self.length,
            "nodes": list(self.nodes),
            "junction_zones_m": [list(z) for z in self.zones],
        }
        width, height, fitted = self.section_size()
        if fitted:
            out.update({"width_m": width, "height_m": height, "fitted_slices": fitted})
        if curve:
            out["centerline"] = self.centerline.to_dict()
        return out


@dataclass(frozen=True)
class NetworkProjection:
    """Points expressed relative to the edge each belongs to (arrays shape (N,)).

    Attributes
    ----------
    branch : uint16, edge id (:data:`NO_BRANCH` where no edge is within reach).
    chainage, lateral, vertical, distance : float64, metres on that edge (see
        :class:`~tunneldef.curve.Projection`).
    inside : bool, the foot point lies on the edge's curve.
    junction : bool, the foot point lies in one of the edge's junction zones.
    """

    branch: np.ndarray
    chainage: np.ndarray
    lateral: np.ndarray
    vertical: np.ndarray
    distance: np.ndarray
    inside: np.ndarray
    junction: np.ndarray


@dataclass(frozen=True)
class CenterlineNetwork:
    """Edges and junctions of a drift network.

    Attributes
    ----------
    edges : tuple of NetworkEdge
        ``edges[i].id == i``.
    junctions : tuple of Junction
    meta : dict
        How it was made (grid, timings, parameters), JSON-serialisable; ``meta["corners"]``
        lists the junctions that are corners (two drifts meeting at an angle, where a walker
        turned from one into the other).
    """

    edges: tuple[NetworkEdge, ...]
    junctions: tuple[Junction, ...] = ()
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def lengths(self) -> np.ndarray:
        """(E,) edge lengths, metres."""
        return np.array([e.length for e in self.edges])

    @property
    def length(self) -> float:
        """Total length of all edges, metres."""
        return float(self.lengths.sum())

    def project(self, xyz: np.ndarray, *, max_distance: float = np.inf) -> NetworkProjection:
        """Assign each point to the nearest edge and express it on that edge.

        The distance to an edge is the distance to its curve (beyond an end: to the end
        point), so a point in a junction goes to the drift whose axis it is nearest.

        Parameters
        ----------
        xyz : ndarray, shape (N, 3)
            World coordinates, metres.
        max_distance : float
            Points farther than this from every edge get :data:`NO_BRANCH` and NaN, metres.
        """
        p = np.asarray(xyz, dtype=np.float64)
        n = len(p)
        best = np.full(n, np.inf)
        out = {k: np.full(n, np.nan) for k in ("chainage", "lateral", "vertical", "distance")}
        branch = np.full(n, NO_BRANCH, dtype=np.uint16)
        for e in self.edges:
            pr = e.centerline.project(p)
            over = np.maximum(np.maximum(-pr.chainage, pr.chainage - e.length), 0.0)
            d = np.hypot(pr.distance, over)
            m = (d < best) & (d <= max_distance)
            best[m] = d[m]
            branch[m] = e.id
            for k in out:
                out[k][m] = getattr(pr, k)[m]
        inside = np.zeros(n, dtype=bool)
        junction = np.zeros(n, dtype=bool)
        for e in self.edges:
            m = branch == e.id
            inside[m] = (out["chainage"][m] >= 0) & (out["chainage"][m] <= e.length)
            junction[m] = e.in_zone(out["chainage"][m])
        return NetworkProjection(branch, out["chainage"], out["lateral"], out["vertical"],
                                 out["distance"], inside, junction)

    def branches(
        self, xyz: np.ndarray, *, max_distance: float = np.inf, chunk: int = 2_000_000
    ) -> np.ndarray:
        """``project(xyz, max_distance=...).branch``, projected ``chunk`` points at a time (a
        point's edge depends on that point alone), so that a large cloud needs no full-size
        projection arrays."""
        out = np.empty(len(xyz), dtype=np.uint16)
        for a in range(0, len(xyz), chunk):
            out[a:a + chunk] = self.project(xyz[a:a + chunk], max_distance=max_distance).branch
        return out

    def transformed(self, transform: np.ndarray) -> CenterlineNetwork:
        """The same network mapped by a 4 x 4 rigid transform."""
        edges = tuple(
            NetworkEdge(e.id, e.name, e.centerline.transformed(transform), e.zones, e.nodes,
                        e.slices)
            for e in self.edges
        )
        junctions = tuple(
            Junction(j.id, apply_transform(transform, j.position[None])[0], j.edges, j.chainages)
            for j in self.junctions
        )
        return CenterlineNetwork(edges, junctions, dict(self.meta))

    def is_dead_end(self, edge_id: int) -> bool:
        """True when the edge leaves the network at one end only and ends free (a face, a
        stub, the end of the scan), so that nothing else hangs on it; False for an edge
        between junctions and for one that drifts pass through (a main drift whose both ends
        are free, with junctions along it).

        The end it leaves from is a junction node, or a junction that lists the edge with a
        chainage within ``END_REACH`` of (or beyond) one of its ends: a stub whose curve
        kept only its readable slices ends short of the junction it leaves.
        """
        e = self.edges[edge_id]
        a, b = e.nodes
        if a >= 0 and b >= 0:
            return False
        touched = {end for end, node in enumerate((a, b)) if node >= 0}
        for j in self.junctions:
            if j.id in (a, b):
                continue
            for k, s in zip(j.edges, j.chainages, strict=True):
                if k != edge_id:
                    continue
                if s <= END_REACH:
                    touched.add(0)
                elif s >= e.length - END_REACH:
                    touched.add(1)
                else:
                    return False
        return len(touched) == 1

    def without(self, reasons: dict[int, str]) -> CenterlineNetwork:
        """The network without the edges in ``reasons`` (edge id -> why it is left out).

        The remaining edges are renumbered in order (``edges[i].id == i`` again); a junction
        keeps its remaining members and is dropped when fewer than three branch ends meet
        there (an edge passing through counts twice), or, at a corner, when one of its two
        drifts is left out: the mouth of a left-out stub on a main drift is no junction,
        though the main drift keeps its junction zone there (its section has a hole in the
        wall). ``meta["left_out"]`` lists what was left out and
        why.
        """
        if not reasons:
            return self
        keep = [e for e in self.edges if e.id not in reasons]
        new_id = {e.id: i for i, e in enumerate(keep)}
        corners = set(self.meta.get("corners", []))
        junctions, new_j = [], {}
        for j in self.junctions:
            members = [(new_id[k], s) for k, s in zip(j.edges, j.chainages, strict=True)
                       if k in new_id]
            ends = sum(1 if min(s, keep[k].length - s) <= END_REACH else 2 for k, s in members)
            if ends >= 3 or (j.id in corners and len(members) == 2):
                new_j[j.id] = len(junctions)
                junctions.append(Junction(len(junctions), j.position,
                                          tuple(k for k, _ in members),
                                          tuple(s for _, s in members)))
        for e in keep:
            e.centerline.meta["edge"] = new_id[e.id]
        edges = tuple(
            NetworkEdge(new_id[e.id], f"edge-{new_id[e.id]}", e.centerline, e.zones,
                        tuple(new_j.get(v, -1) for v in e.nodes), e.slices)
            for e in keep
        )
        left = list(self.meta.get("left_out", []))
        left += [{"edge": self.edges[k].name, "length_m": self.edges[k].length, "reason": r}
                 for k, r in sorted(reasons.items())]
        meta = {**self.meta, "left_out": left}
        if "corners" in meta:
            meta["corners"] = sorted(new_j[v] for v in corners if v in new_j)
        return CenterlineNetwork(edges, tuple(junctions), meta)

    def to_dict(self, *, curves: bool = True) -> dict[str, Any]:
        """JSON-serialisable form: nodes (junctions) and edges."""
        return {
            "kind": "centerline_network",
            "length_m": self.length,
            "nodes": [j.to_dict() for j in self.junctions],
            "edges": [e.to_dict(curve=curves) for e in self.edges],
            "meta": self.meta,
        }
