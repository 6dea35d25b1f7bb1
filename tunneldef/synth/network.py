"""Synthetic drift networks with ground truth per branch: two epochs of a handheld SLAM survey.

A network is a set of edges (branches): design centrelines given as 3-D polylines whose corners
are rounded by circular fillets (horizontal bends, vertical curves, or both), each with a design
section from :func:`tunneldef.synth.section_outline` (rectangle, arch, trapezoid, horseshoe), and
junction nodes where they meet. The tunnel surface is the union of the edges' tubes: every
point of a tube's surface that lies inside another tube is removed, so junctions are open (a
cross-cut's mouth is a hole in the main drift's wall, the main drift's interior has no
cross-cut walls). Dead-end edges end in a face.

An epoch covers a walk: an ordered tree of stretches (chainage ranges on edges, each after the
first starting where it branches off one walked before). Its points are drawn on the covered
surfaces at a density (points per m^2) with Gaussian noise, optional clutter (pipes and cables
on the walls, a conveyor with a coal load, as in :func:`tunneldef.synth.make_pair`, shadowing
the shell behind them) and outliers inside, then moved by the epoch's SLAM drift
(:mod:`tunneldef.synth.drift`: a smooth 6-DoF random walk of a few centimetres per 100 m, a
function of the path position), and stray points (one far point and a few small far clusters)
are added. The reference epoch stays in the design frame; the compared epoch is deformed and
moved by a rigid motion into a frame of its own.

Conventions are those of :mod:`tunneldef.synth`: section coordinates ``(u, v)``, ``u`` lateral,
positive to the left of increasing chainage, ``v`` up in the normal plane; the design axis is the
section centre; displacement sign negative = the shell moved into the tunnel; noise sigma
0.015 m (the scanner's ±3 cm read as 2 sigma).

One idea at this length: synthetic drift networks and their per-branch truth (geometry,
coverage, SLAM drift, strays); it reuses the single-tube sampler.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import Cloud
from ..config import check_positive
from ..curve import Centerline, Projection
from ..errors import ConfigError
from ..progress import ProgressCallback, notify, timed_stage
from .design import (
    _C_OUTLIER,
    _C_SHELL,
    LABEL_EQUIPMENT,
    LABEL_OUTLIER,
    LABEL_SHELL,
    SURFACE_NONE,
    DeformationSpec,
    Outline,
    SectionSpec,
    TunnelSpec,
    _check_deformations,
    _patch_centre,
    _rigid_motion,
    section_outline,
)
from .drift import DriftWalk, random_drift
from .sampling import _SHADOW_SEEN, _SHADOW_STEP, _Epoch, _intensity, write_epochs
from .scene import _draw_heaps, _make_scene, _relief, draw_relief

__all__ = [
    "SURFACE_FACE",
    "NO_BRANCH",
    "EdgeSpec",
    "JunctionSpec",
    "NetworkSpec",
    "BranchDeformation",
    "Stretch",
    "NetworkPairSpec",
    "Branch",
    "EpochTruth",
    "NetworkTruth",
    "NetworkPair",
    "build_branches",
    "make_network_pair",
    "write_network_pair",
    "network_250m",
    "network_250m_pair",
]

log = logging.getLogger(__name__)

#: Surface code of the face of a dead-end edge (the other codes are those of the outline).
SURFACE_FACE = 4
#: ``branch`` of points that belong to no edge (stray points).
NO_BRANCH = 65535

_CHUNK = 2_000_000  # shell candidates drawn at once
_STEP = 0.05  # m, sampling step of the design axes
_COINCIDE = 0.005  # m, surfaces of two edges closer than this are one surface


# --------------------------------------------------------------------------------------------
# specifications
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EdgeSpec:
    """One edge (branch) of a network: a design centreline and its section.

    Parameters
    ----------
    name : str
        Unique name.
    vertices : tuple of (x, y, z)
        Polyline of the design axis (section centre), m, in the reference (design) frame;
        chainage 0 at the first vertex. Interior corners are rounded by circular fillets.
    section : SectionSpec
        Design cross-section.
    bend_radius : float
        Radius of the fillet at each interior vertex, m (horizontal and vertical bends alike).
    faces : (bool, bool)
        A dead-end face at the start / the end of the edge (sampled when the walk reaches it).
    equipment : bool
        Pipes and cables on the walls (the placement of :func:`tunneldef.synth.make_pair`'s
        ``equipment``), when :attr:`NetworkPairSpec.equipment` is on.
    conveyor : bool
        A conveyor along the floor with a coal load (label 2, drawn anew in each epoch), on the
        ``conveyor_side``, when :attr:`NetworkPairSpec.equipment` is on.
    conveyor_side : {"left", "right"}
    """

    name: str
    vertices: tuple[tuple[float, float, float], ...]
    section: SectionSpec = field(default_factory=SectionSpec)
    bend_radius: float = 15.0
    faces: tuple[bool, bool] = (False, False)
    equipment: bool = False
    conveyor: bool = False
    conveyor_side: str = "right"

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 2 or not np.all(np.isfinite(v)):
            raise ConfigError(f"edge {self.name!r}: vertices must be at least 2 finite (x, y, z)")
        if np.any(np.linalg.norm(np.diff(v, axis=0), axis=1) < 1e-6):
            raise ConfigError(f"edge {self.name!r}: repeated vertex")
        object.__setattr__(self, "vertices", tuple(tuple(float(c) for c in p) for p in v))
        object.__setattr__(self, "faces", (bool(self.faces[0]), bool(self.faces[1])))
        if not isinstance(self.section, SectionSpec):
            raise ConfigError(f"edge {self.name!r}: section must be a SectionSpec")
        check_positive("bend_radius", self.bend_radius)
        if self.conveyor_side not in ("left", "right"):
            raise ConfigError(f"edge {self.name!r}: conveyor_side must be 'left' or 'right'")


@dataclass(frozen=True)
class JunctionSpec:
    """A junction node: where edges meet (for the truth; the geometry comes from the edges).

    Parameters
    ----------
    name : str
    position : (x, y, z)
        Node position, m (reference frame).
    edges : tuple of int
        Indices of the edges that meet there.
    """

    name: str
    position: tuple[float, float, float]
    edges: tuple[int, ...]

    def __post_init__(self) -> None:
        if np.shape(self.position) != (3,):
            raise ConfigError(f"junction {self.name!r}: position must be 3 numbers")
        object.__setattr__(self, "position", tuple(float(c) for c in self.position))
        object.__setattr__(self, "edges", tuple(int(e) for e in self.edges))


@dataclass(frozen=True)
class NetworkSpec:
    """A drift network: edges and junction nodes.

    Parameters
    ----------
    edges : tuple of EdgeSpec
        The branches; an edge's index is its ``branch`` id in the truth. Order matters for
        clutter only: an edge's clutter is cut where it enters an edge listed before it.
    junctions : tuple of JunctionSpec
        Junction nodes.
    name : str
    """

    edges: tuple[EdgeSpec, ...]
    junctions: tuple[JunctionSpec, ...] = ()
    name: str = "network"

    def __post_init__(self) -> None:
        object.__setattr__(self, "edges", tuple(self.edges))
        object.__setattr__(self, "junctions", tuple(self.junctions))
        if not self.edges or len(self.edges) >= NO_BRANCH:
            raise ConfigError(f"a network needs 1 to {NO_BRANCH - 1} edges")
        names = [e.name for e in self.edges]
        if len(set(names)) != len(names):
            raise ConfigError(f"edge names must be unique, got {names}")
        for j in self.junctions:
            if any(not 0 <= e < len(self.edges) for e in j.edges):
                raise ConfigError(f"junction {j.name!r} names an unknown edge: {j.edges}")


@dataclass(frozen=True)
class BranchDeformation:
    """A deformation patch (:class:`tunneldef.synth.DeformationSpec`) on one branch.

    Parameters
    ----------
    branch : int
        Edge index.
    deformation : DeformationSpec
        Its ``chainage`` is along that edge's design axis.
    """

    branch: int
    deformation: DeformationSpec

    @property
    def kind(self) -> str:
        """``roof_sag``, ``wall_bulge`` or ``floor_heave``."""
        return self.deformation.kind

    @property
    def chainage(self) -> float:
        """Centre chainage on the branch, m."""
        return float(self.deformation.chainage)

    @property
    def amplitude(self) -> float:
        """Peak movement into the tunnel, m (truth displacement ``-amplitude`` at the centre)."""
        return float(self.deformation.amplitude)


@dataclass(frozen=True)
class Stretch:
    """One walked stretch of an edge.

    Parameters
    ----------
    branch : int
        Edge index.
    start : float
        Chainage where the walk along it starts, m.
    end : float or None
        Chainage where it ends, m (None: the end of the edge); ``end < start`` walks backwards.
    """

    branch: int
    start: float = 0.0
    end: float | None = None


@dataclass(frozen=True)
class NetworkPairSpec:
    """Two epochs of a network survey.

    Parameters
    ----------
    network : NetworkSpec
    deformations : tuple of BranchDeformation
        Applied to the compared epoch only.
    ref_coverage, cmp_coverage : tuple of Stretch or None
        Each epoch's walk, in walking order; every stretch after the first starts on one walked
        before it (the drift branches off there). None: every edge in full.
    density : float
        Points per m^2 of shell.
    noise_sigma : float
        Gaussian noise on each of x, y, z, m (0.015: ±3 cm as 2 sigma).
    outlier_fraction : float
        Outliers inside the tunnels (label 3), as a fraction of the shell points.
    equipment : bool
        Clutter on the edges that ask for it (:attr:`EdgeSpec.equipment`,
        :attr:`EdgeSpec.conveyor`); off: bare tunnels.
    drift : float
        SLAM drift, m per square root of 100 m walked (see :class:`DriftWalk`); 0: none.
    drift_step : float
        Knot spacing of the drift along the walk, m.
    stray_distance : float
        Distance of the single far stray point from the nearest design axis, m (0: none).
    stray_clusters : int
        Small clusters (5-40 points, 0.3 m across) 40-200 m away from the network.
    roughness : float
        Standard deviation of a smooth static rock relief of every edge's shell about its
        design outline, m (the same rock in both epochs; 0: planar walls). Drawn from its own
        random stream, so a pair with roughness 0 is the pair drawn before it existed.
    yaw_deg : float or None
        Rotation about z of the compared epoch's frame, degrees (None: random).
    tilt_deg : float
        Tilt about a random horizontal axis, degrees.
    translation : (3,) float
        Translation of the compared epoch's frame, m.
    seed : int
    """

    network: NetworkSpec
    deformations: tuple[BranchDeformation, ...] = ()
    ref_coverage: tuple[Stretch, ...] | None = None
    cmp_coverage: tuple[Stretch, ...] | None = None
    density: float = 300.0
    noise_sigma: float = 0.015
    outlier_fraction: float = 0.001
    equipment: bool = True
    drift: float = 0.03
    drift_step: float = 10.0
    stray_distance: float = 130.0
    stray_clusters: int = 3
    roughness: float = 0.0
    yaw_deg: float | None = None
    tilt_deg: float = 2.0
    translation: tuple[float, float, float] = (350.0, -120.0, 15.0)
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.network, NetworkSpec):
            raise ConfigError("network must be a NetworkSpec")
        object.__setattr__(self, "deformations", tuple(self.deformations))
        for name in ("ref_coverage", "cmp_coverage"):
            cov = getattr(self, name)
            if cov is not None:
                cov = tuple(cov)
                if not cov or not all(isinstance(s, Stretch) for s in cov):
                    raise ConfigError(f"{name} must be a non-empty tuple of Stretch")
                object.__setattr__(self, name, cov)
        for d in self.deformations:
            if not isinstance(d, BranchDeformation):
                raise ConfigError(f"deformations must be BranchDeformation objects, got {d!r}")
        check_positive("density", self.density, unit="points per m^2")
        check_positive("drift_step", self.drift_step)
        if not np.isfinite(self.roughness) or not 0 <= self.roughness < 0.25:
            raise ConfigError(f"roughness must be in [0, 0.25) m, got {self.roughness!r}")
        for name in ("noise_sigma", "drift", "stray_distance"):
            val = getattr(self, name)
            if not np.isfinite(val) or val < 0:
                raise ConfigError(f"{name} must be >= 0, got {val!r}")
        if not 0 <= self.outlier_fraction < 0.5:
            raise ConfigError(f"outlier_fraction must be in [0, 0.5), got {self.outlier_fraction}")
        if int(self.stray_clusters) != self.stray_clusters or self.stray_clusters < 0:
            raise ConfigError("stray_clusters must be a non-negative integer")
        if np.shape(self.translation) != (3,):
            raise ConfigError(f"translation must be 3 numbers, got {self.translation!r}")


# --------------------------------------------------------------------------------------------
# geometry of a branch
# --------------------------------------------------------------------------------------------


def _fillet_pieces(v: np.ndarray, radius: float, name: str) -> list[tuple]:
    """The polyline ``v`` as straight pieces and circular fillets of ``radius`` at corners."""
    seg = np.diff(v, axis=0)
    seglen = np.linalg.norm(seg, axis=1)
    d = seg / seglen[:, None]
    nv = len(v)
    theta = np.zeros(nv)
    tlen = np.zeros(nv)
    for i in range(1, nv - 1):
        theta[i] = float(np.arccos(np.clip(d[i - 1] @ d[i], -1.0, 1.0)))
        if theta[i] > np.radians(170.0):
            raise ConfigError(f"edge {name!r}: a corner turns back by more than 170 degrees")
        tlen[i] = radius * np.tan(theta[i] / 2)
    for i in range(nv - 1):
        if tlen[i] + tlen[i + 1] > seglen[i] + 1e-9:
            raise ConfigError(
                f"edge {name!r}: segment {i} ({seglen[i]:.2f} m) is too short for bends of "
                f"radius {radius} m; use a smaller bend_radius"
            )
    pieces: list[tuple] = []
    cur = v[0]
    for i in range(nv - 1):
        end = v[i + 1] - d[i] * tlen[i + 1]
        length = float(np.linalg.norm(end - cur))
        if length > 1e-9:
            pieces.append(("line", cur, d[i], length))
        if i + 1 < nv - 1 and theta[i + 1] > 1e-9:
            n = d[i + 1] - (d[i + 1] @ d[i]) * d[i]
            n /= np.linalg.norm(n)
            pieces.append(("arc", end, d[i], n, radius, float(theta[i + 1])))
            cur = v[i + 1] + d[i + 1] * tlen[i + 1]
        else:
            cur = end
    return pieces


def _evaluate_pieces(pieces: list[tuple], s: np.ndarray) -> tuple[np.ndarray, ...]:
    """Point, unit tangent and curvature vector (dt/ds) of the filleted axis at ``s``."""
    lengths = np.array([p[3] if p[0] == "line" else p[4] * p[5] for p in pieces])
    starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    idx = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(pieces) - 1)
    loc = s - starts[idx]
    c = np.empty((s.shape[0], 3))
    t = np.empty_like(c)
    k = np.zeros_like(c)
    for j, p in enumerate(pieces):
        m = idx == j
        if not m.any():
            continue
        x = loc[m][:, None]
        if p[0] == "line":
            c[m] = p[1] + x * p[2]
            t[m] = p[2]
        else:
            _, a, d1, n, r, _ = p
            phi = x / r
            c[m] = a + r * (1.0 - np.cos(phi)) * n + r * np.sin(phi) * d1
            t[m] = np.cos(phi) * d1 + np.sin(phi) * n
            k[m] = (np.cos(phi) * n - np.sin(phi) * d1) / r
    return c, t, k


class Branch:
    """The built geometry of one edge: its design axis, moving frame and section outline.

    Attributes
    ----------
    index : int
        Edge index (the truth's ``branch``).
    spec : EdgeSpec
    outline : Outline
        Design section outline.
    length : float
        Length of the design axis, m.
    radius : float
        Largest distance of the outline from the axis, m.
    centerline : Centerline
        The design axis sampled every ~5 cm (reference frame), chainage 0 at the first vertex.
    """

    def __init__(self, index: int, spec: EdgeSpec, *, step: float = _STEP) -> None:
        self.index = int(index)
        self.spec = spec
        self.outline: Outline = section_outline(spec.section)
        pieces = _fillet_pieces(np.asarray(spec.vertices), spec.bend_radius, spec.name)
        self.length = float(sum(p[3] if p[0] == "line" else p[4] * p[5] for p in pieces))
        n = max(int(np.ceil(self.length / step)), 1) + 1
        self._s = np.linspace(0.0, self.length, n)
        self.step = self.length / (n - 1)
        c, t, k = _evaluate_pieces(pieces, self._s)
        lat = np.cross(np.array([0.0, 0.0, 1.0]), t)
        norm = np.linalg.norm(lat, axis=1)
        if np.any(norm < 0.3):
            raise ConfigError(f"edge {spec.name!r} is steeper than 72 degrees somewhere")
        lat /= norm[:, None]
        ver = np.cross(t, lat)
        self._c, self._t, self._lat, self._ver = c, t, lat, ver
        self._kl = np.einsum("ij,ij->i", k, lat)
        self._kv = np.einsum("ij,ij->i", k, ver)
        # steps to the next sample, for the linear interpolation
        self._d = {id(a): np.diff(a, axis=0) for a in (c, t, lat, ver, self._kl, self._kv)}
        p = self.outline.evaluate(np.linspace(0.0, self.outline.perimeter, 512))
        self.radius = float(np.max(np.hypot(p[0], p[1])))
        self.centerline = Centerline(
            c,
            self._s.copy(),
            meta={"method": "synthetic network edge", "edge": spec.name, "index": self.index},
        )
        self.tree = cKDTree(c)

    @property
    def name(self) -> str:
        """The edge's name."""
        return self.spec.name

    @property
    def max_curvature(self) -> float:
        """Largest curvature of the design axis, 1/m."""
        return float(np.max(np.hypot(self._kl, self._kv)))

    def _where(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.clip(s / self.step, 0.0, len(self._s) - 1.0)
        i = np.minimum(x.astype(np.intp), len(self._s) - 2)
        return i, x - i

    def _lerp(self, arr: np.ndarray, i: np.ndarray, f: np.ndarray) -> np.ndarray:
        out = arr[i]
        out += (f if arr.ndim == 1 else f[:, None]) * self._d[id(arr)][i]
        return out

    def _sweep(self, s: np.ndarray, u: np.ndarray, v: np.ndarray):
        """World point, unit tangent and sweep stretch (see :meth:`jacobian`) at (s, u, v)."""
        i, f = self._where(s)
        x = self._lerp(self._c, i, f)
        x += u[:, None] * self._lerp(self._lat, i, f)
        x += v[:, None] * self._lerp(self._ver, i, f)
        jac = 1.0 - self._lerp(self._kl, i, f) * u - self._lerp(self._kv, i, f) * v
        return x, self._lerp(self._t, i, f), jac

    def frames(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Axis point, unit tangent, lateral (left) and vertical vectors at chainages ``s``,
        each (N, 3) (linear between the 5 cm samples)."""
        i, f = self._where(np.atleast_1d(np.asarray(s, dtype=np.float64)))
        return tuple(self._lerp(a, i, f) for a in (self._c, self._t, self._lat, self._ver))

    def jacobian(self, s: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Along-axis stretch ``1 - k_lat u - k_ver v`` of the sweep at section point (u, v)."""
        i, f = self._where(np.atleast_1d(np.asarray(s, dtype=np.float64)))
        return 1.0 - self._lerp(self._kl, i, f) * u - self._lerp(self._kv, i, f) * v

    def to_world(self, s: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Reference-frame coordinates (N, 3) of section points ``(u, v)`` at chainage ``s``."""
        i, f = self._where(np.atleast_1d(np.asarray(s, dtype=np.float64)))
        c = self._lerp(self._c, i, f)
        c += np.asarray(u)[..., None] * self._lerp(self._lat, i, f)
        c += np.asarray(v)[..., None] * self._lerp(self._ver, i, f)
        return c

    def project(self, xyz: np.ndarray) -> Projection:
        """Chainage and section offsets of points relative to this edge's design axis.

        :meth:`Centerline.project` (nearest sample), then a Newton step on the foot-point
        condition with the interpolated frames: exact to about 0.01 mm where the sample
        frames alone are off by up to 0.7 mm (a 12 m bend on a 12 % grade, 3 m off the axis).
        Beyond the ends, the chainage is extrapolated along the end tangents.
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        s = self.centerline.project(xyz, workers=1).chainage
        for _ in range(2):
            sc = np.clip(s, 0.0, self.length)
            i, f = self._where(sc)
            d = xyz - self._lerp(self._c, i, f)
            along = np.einsum("ij,ij->i", d, self._lerp(self._t, i, f))
            lat = np.einsum("ij,ij->i", d, self._lerp(self._lat, i, f))
            ver = np.einsum("ij,ij->i", d, self._lerp(self._ver, i, f))
            jac = 1.0 - self._lerp(self._kl, i, f) * lat - self._lerp(self._kv, i, f) * ver
            s = sc + along / np.maximum(jac, 0.1)
        s = sc + along  # the last step's frames: a negligible slide inside, exact beyond the ends
        return Projection(
            chainage=s,
            lateral=lat,
            vertical=ver,
            distance=np.hypot(lat, ver),
            inside=(s >= 0.0) & (s <= self.length),
        )

    def signed_distance(self, xyz: np.ndarray) -> tuple[np.ndarray, Projection]:
        """Signed distance of points to this edge's design surface, m (negative inside), and
        their projection."""
        pr = self.project(xyz)
        return self.outline.signed_distance(pr.lateral, pr.vertical), pr

    def inside(self, xyz: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True for points inside this edge's tube (between its end sections, deeper than
        ``margin`` inside the outline)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        out = np.zeros(len(xyz), dtype=bool)
        if len(xyz) == 0:
            return out
        # only points near the axis can be inside: a cheap bounded nearest-sample query first
        reach = self.radius + max(0.0, -margin) + self.step
        near = np.flatnonzero(np.isfinite(self.tree.query(xyz, distance_upper_bound=reach)[0]))
        if near.size:
            sd, pr = self.signed_distance(xyz[near])
            out[near] = pr.inside & (sd < -margin)
        return out


def build_branches(network: NetworkSpec) -> tuple[Branch, ...]:
    """The :class:`Branch` geometry of every edge of a network."""
    return tuple(Branch(i, e) for i, e in enumerate(network.edges))


def _openings(branches: tuple[Branch, ...]) -> dict[int, list[tuple[int, float, float]]]:
    """Per edge, ``(other edge, s0, s1)``: chainage windows where the other tube may overlap."""
    out: dict[int, list[tuple[int, float, float]]] = {b.index: [] for b in branches}
    for b in branches:
        s = np.append(np.arange(0.0, b.length, 0.25), b.length)
        pts = b.to_world(s, np.zeros_like(s), np.zeros_like(s))
        for f in branches:
            if f is b:
                continue
            dist, _ = f.tree.query(pts)
            near = dist < b.radius + f.radius + 0.5
            if not near.any():
                continue
            edges = np.flatnonzero(np.diff(np.concatenate([[0], near.astype(np.int8), [0]])))
            for i0, i1 in zip(edges[::2], edges[1::2], strict=True):
                pad = f.radius + 0.5
                out[b.index].append(
                    (f.index, max(0.0, s[i0] - pad), min(b.length, s[i1 - 1] + pad))
                )
    return out


# --------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EpochTruth:
    """Ground truth of one epoch (arrays shape (N,), in the cloud's point order).

    Attributes
    ----------
    branch : uint16, edge index of the point (:data:`NO_BRANCH` for stray points).
    chainage : float64, m along that edge's design axis (of the noisy point, to first order;
        NaN for strays).
    label : uint8, 0 shell, 1 equipment, 2 dynamic (coal load), 3 outlier (inside a tunnel) or
        stray.
    surface : uint8, 0 roof, 1 left wall, 2 right wall, 3 floor, 4 dead-end face
        (:data:`SURFACE_FACE`), 255 not shell.
    displacement : float64, signed normal displacement of shell points, m (negative = into the
        tunnel); 0 elsewhere and in the reference epoch.
    stray : bool, True for stray points far from the network.
    path : float64, path position of the walk when the point was scanned, m (NaN for strays).
    stretch : uint16, index of the walked stretch (into ``coverage``; :data:`NO_BRANCH` for
        strays).
    xyz_ref : (N, 3) float64, true position of the point in the reference frame (noise and
        deformation included, no drift).
    coverage : the walked stretches (resolved: ``end`` is a number).
    drift : the epoch's :class:`DriftWalk`; the cloud holds ``drift.apply(xyz_ref, stretch,
        path)`` (then the rigid motion, for the compared epoch); strays are not drifted.
    """

    branch: np.ndarray
    chainage: np.ndarray
    label: np.ndarray
    surface: np.ndarray
    displacement: np.ndarray
    stray: np.ndarray
    path: np.ndarray
    stretch: np.ndarray
    xyz_ref: np.ndarray
    coverage: tuple[Stretch, ...]
    drift: DriftWalk

    @property
    def shell(self) -> np.ndarray:
        """True for shell points (walls, roof, floor, dead-end faces)."""
        return self.label == LABEL_SHELL

    def drift_offset(self) -> np.ndarray:
        """Per-point drift displacement (N, 3), m, in the reference frame (0 for strays)."""
        out = np.zeros_like(self.xyz_ref)
        m = ~self.stray
        out[m] = self.drift.offset(self.xyz_ref[m], self.stretch[m], self.path[m])
        return out


@dataclass(frozen=True)
class NetworkTruth:
    """Ground truth of a network pair.

    Attributes
    ----------
    ref, cmp : EpochTruth
    transform : (4, 4) float64, maps compared-epoch coordinates to the reference frame (the
        compared cloud mapped by it is ``cmp.xyz_ref`` plus the compared epoch's drift).
    branches : per edge, its :class:`Branch` (design axis, outline, ``project``).
    centerlines : per edge, the design axis in the reference frame.
    junctions : the network's junction nodes (reference frame).
    deformations : the applied deformations.
    yaw_deg, tilt_deg, tilt_axis : the rigid motion's rotation.
    """

    ref: EpochTruth
    cmp: EpochTruth
    transform: np.ndarray
    branches: tuple[Branch, ...]
    centerlines: tuple[Centerline, ...]
    junctions: tuple[JunctionSpec, ...]
    deformations: tuple[BranchDeformation, ...]
    yaw_deg: float
    tilt_deg: float
    tilt_axis: np.ndarray

    @property
    def junction_positions(self) -> np.ndarray:
        """(J, 3) junction node positions, m (reference frame)."""
        return np.array([j.position for j in self.junctions], dtype=np.float64).reshape(-1, 3)

    @property
    def branch_lengths(self) -> np.ndarray:
        """(E,) design axis length of every edge, m."""
        return np.array([b.length for b in self.branches])


@dataclass(frozen=True)
class NetworkPair:
    """A reference epoch, a compared epoch and their truth."""

    ref: Cloud
    cmp: Cloud
    truth: NetworkTruth
    spec: NetworkPairSpec


# --------------------------------------------------------------------------------------------
# the walk
# --------------------------------------------------------------------------------------------


def _resolve(coverage, branches) -> tuple[Stretch, ...]:
    out = []
    for st in coverage:
        if not 0 <= st.branch < len(branches):
            raise ConfigError(f"stretch on unknown branch {st.branch}")
        b = branches[st.branch]
        end = b.length if st.end is None else float(st.end)
        start = float(st.start)
        for x in (start, end):
            if not -1e-9 <= x <= b.length + 1e-9:
                raise ConfigError(f"stretch {st} leaves edge {b.name!r} (0 to {b.length:.2f} m)")
        if abs(end - start) < 0.5:
            raise ConfigError(f"stretch {st} is shorter than 0.5 m")
        out.append(Stretch(st.branch, min(max(start, 0.0), b.length), min(max(end, 0.0), b.length)))
    for i, a in enumerate(out):
        for b in out[:i]:
            if a.branch == b.branch:
                lo = max(min(a.start, a.end), min(b.start, b.end))
                hi = min(max(a.start, a.end), max(b.start, b.end))
                if hi - lo > 1e-9:
                    raise ConfigError(f"stretches {b} and {a} overlap")
    return tuple(out)


def _auto_coverage(branches: tuple[Branch, ...]) -> tuple[Stretch, ...]:
    """Every edge in full: the first from its start, each next one from its point nearest to
    the edges walked before it (split in two when that point is inside the edge)."""
    out = [Stretch(0, 0.0, branches[0].length)]
    walked = [branches[0].centerline.points]
    for b in branches[1:]:
        tree = cKDTree(np.concatenate(walked))
        s = np.append(np.arange(0.0, b.length, 0.25), b.length)
        dist, _ = tree.query(b.to_world(s, np.zeros_like(s), np.zeros_like(s)))
        s0 = float(s[int(np.argmin(dist))])
        if s0 < 1.0:
            out.append(Stretch(b.index, 0.0, b.length))
        elif s0 > b.length - 1.0:
            out.append(Stretch(b.index, b.length, 0.0))
        else:
            out += [Stretch(b.index, s0, 0.0), Stretch(b.index, s0, b.length)]
        walked.append(b.centerline.points)
    return tuple(out)


def _walk_tree(
    coverage: tuple[Stretch, ...], branches: tuple[Branch, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Parent stretch and branching chainage on it of every stretch after the first."""
    n = len(coverage)
    parent = np.full(n, -1, dtype=np.int64)
    at = np.zeros(n)
    for k in range(1, n):
        st = coverage[k]
        b = branches[st.branch]
        p = b.to_world(np.array([st.start]), np.zeros(1), np.zeros(1))
        best = (np.inf, -1, 0.0)
        for j in range(k):
            sj = coverage[j]
            bj = branches[sj.branch]
            s = float(np.clip(bj.project(p).chainage[0], *sorted((sj.start, sj.end))))
            d = float(np.linalg.norm(p[0] - bj.centerline.point_at(s)[0]))
            if d < best[0] - 1e-9:
                best = (d, j, s)
        d, j, s = best
        if d > b.radius + branches[coverage[j].branch].radius + 1.0:
            raise ConfigError(
                f"stretch {k} ({st}) does not start on the network walked before it "
                f"({d:.2f} m away)"
            )
        parent[k], at[k] = j, s
    return parent, at


# --------------------------------------------------------------------------------------------
# sampling
# --------------------------------------------------------------------------------------------


class _Sampler:
    """Draws one epoch's points on a network."""

    def __init__(self, branches, openings, scenes, spec: NetworkPairSpec, rng) -> None:
        self.branches, self.openings, self.scenes = branches, openings, scenes
        self.spec, self.rng = spec, rng
        # the rock: one relief per edge, from a stream of its own shared by both epochs
        self.reliefs = {
            b.index: draw_relief(
                np.random.default_rng([spec.seed, 0x7E11EF, b.index]),
                spec.roughness,
                b.outline.perimeter,
            )
            for b in branches
        } if spec.roughness > 0 else {}
        self.parts: list[dict[str, np.ndarray]] = []
        self._current: tuple[Branch, int, Stretch, float] | None = None

    def _emit(self, s, u, v, comp, label, surface, disp=None) -> None:
        """Map section samples of the current stretch to the reference frame with noise and
        record their truth (chainage of the noisy point to first order: the along-axis part of
        the noise over the sweep's stretch ``1 - k . (u, v)``)."""
        b, k, st, tau0 = self._current
        rng, sigma = self.rng, self.spec.noise_sigma
        n = s.shape[0]
        xyz, t, jac = b._sweep(s, np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
        chainage = s.copy()
        if sigma > 0 and n:
            noise = rng.normal(0.0, sigma, (n, 3))
            xyz += noise
            chainage += np.einsum("ij,ij->i", noise, t) / np.maximum(jac, 0.1)
        self.parts.append(
            {
                "xyz": xyz,
                "chainage": chainage,
                "path": tau0 + np.abs(s - st.start),
                "branch": np.full(n, b.index, np.uint16),
                "stretch": np.full(n, k, np.uint16),
                "label": np.full(n, label, np.uint8),
                "surface": np.full(n, surface, np.uint8) if np.isscalar(surface) else surface,
                "displacement": np.zeros(n) if disp is None else disp,
                "comp": np.full(n, comp, np.uint8) if np.isscalar(comp) else comp,
            }
        )

    def _sorted_uniform(self, n: int, a: float, b: float) -> np.ndarray:
        if n <= 0:
            return np.empty(0)
        gaps = self.rng.standard_exponential(n + 1)
        s = np.cumsum(gaps[:-1])
        s *= (b - a) / (s[-1] + gaps[-1])
        s += a
        return s

    def _cut(self, b: Branch, s, u, v, keep, before_only: bool = False) -> None:
        """Clear ``keep`` where the section point lies inside another edge's tube.

        Where two surfaces coincide (level floors meeting at a junction), the edge listed
        first keeps its points: a point is cut within 5 mm outside an earlier edge's surface,
        and only deeper than 5 mm inside a later one's. Clutter (``before_only``) is cut inside
        earlier edges only, so the main drift's pipes run on across a cross-cut's mouth (where
        they are not where the shell is, nothing is cut).
        """
        for f, w0, w1 in self.openings[b.index]:
            if before_only and f > b.index:
                continue
            margin = 0.0 if before_only else (-_COINCIDE if f < b.index else _COINCIDE)
            i, j = np.searchsorted(s, (w0, w1))
            if j > i:
                x = b.to_world(s[i:j], u[i:j], v[i:j])
                keep[i:j] &= ~self.branches[f].inside(x, margin)

    def stretch(self, k: int, st: Stretch, tau0: float, deformations) -> int:
        """Sample one stretch; returns its number of shell points."""
        b, rng, spec = self.branches[st.branch], self.rng, self.spec
        self._current = (b, k, st, tau0)
        out = b.outline
        a, e = sorted((st.start, st.end))
        per = out.perimeter
        jmax = 1.0 + b.max_curvature * b.radius
        n = int(round(spec.density * (e - a) * per * jmax))
        nk = max(1, -(-n // _CHUNK))
        cuts = np.linspace(a, e, nk + 1)
        n_shell = 0
        half = per / 2
        table = self._shadow_table(b)
        for c, nc in enumerate(rng.multinomial(n, np.full(nk, 1.0 / nk))):
            s = self._sorted_uniform(int(nc), cuts[c], cuts[c + 1])
            p = rng.uniform(0.0, per, s.shape[0])
            u, v, nu, nv, surf = out.evaluate(p)
            keep = rng.random(s.shape[0]) * jmax < b.jacobian(s, u, v)
            if table is not None:  # a moving handheld scanner still sees some of the shadow
                cell = np.minimum((p / _SHADOW_STEP).astype(np.intp), table.shape[0] - 1)
                keep &= ~table[cell] | (rng.random(s.shape[0]) < _SHADOW_SEEN)
            self._cut(b, s, u, v, keep)
            s, p, u, v, nu, nv, surf = (x[keep] for x in (s, p, u, v, nu, nv, surf))
            relief = self.reliefs.get(b.index)
            if relief is not None:  # static rock relief, outward positive
                off = _relief(relief, s, p)
                u -= off * nu
                v -= off * nv
            disp = np.zeros(s.shape[0])
            for d in deformations:
                pc = _patch_centre(out, d)
                i, j = np.searchsorted(s, (d.chainage - d.length / 2, d.chainage + d.length / 2))
                dp = np.mod(p[i:j] - pc + half, per) - half
                shift = d.amplitude * d.taper(s[i:j] - d.chainage, dp)
                u[i:j] += shift * nu[i:j]
                v[i:j] += shift * nv[i:j]
                disp[i:j] -= shift
            n_shell += s.shape[0]
            self._emit(s, u, v, _C_SHELL, LABEL_SHELL, surf, disp)
        # dead-end faces
        for at_end, s_face in ((0, 0.0), (1, b.length)):
            if b.spec.faces[at_end] and abs((a if at_end == 0 else e) - s_face) < 1e-6:
                u, v = self._inside_section(out, spec.density * _area(out), 0.0)
                s = np.full(u.shape[0], s_face)
                n_shell += u.shape[0]
                self._emit(s, u, v, _C_SHELL, LABEL_SHELL, SURFACE_FACE)
        # clutter: pipes, cables, conveyor and coal, drawn by the single-tube sampler in
        # section coordinates (no density correction on bends)
        scene = self.scenes[b.index]
        if scene is not None:
            ep = _Epoch(scene, a, e, rng)
            ep.equipment()
            if scene.conveyor is not None:
                ep.conveyor(_draw_heaps(rng, a, e))
            for part in ep.parts:
                order = np.argsort(part["s"], kind="stable")
                ps, pu, pv = part["s"][order], part["u"][order], part["v"][order]
                keep = np.ones(ps.shape[0], dtype=bool)
                self._cut(b, ps, pu, pv, keep, before_only=True)
                self._emit(
                    ps[keep],
                    pu[keep],
                    pv[keep],
                    part["comp"][order][keep],
                    int(part["label"][0]) if ps.shape[0] else LABEL_EQUIPMENT,
                    SURFACE_NONE,
                )
        # outliers inside the tunnel
        m = int(round(spec.outlier_fraction * n_shell))
        if m:
            u, v = self._inside_section(out, m, 0.05)
            s = rng.uniform(a, e, u.shape[0])
            self._emit(s, u, v, _C_OUTLIER, LABEL_OUTLIER, SURFACE_NONE)
        return n_shell

    def _shadow_table(self, b: Branch) -> np.ndarray | None:
        """Shell hidden behind the edge's clutter, on a grid around the outline (the scanner
        walks parallel to the axis: the shadow is the same in every section)."""
        scene = self.scenes[b.index]
        if scene is None:
            return None
        out = b.outline
        grid = (np.arange(int(np.ceil(out.perimeter / _SHADOW_STEP))) + 0.5) * _SHADOW_STEP
        gu, gv, *_ = out.evaluate(grid)
        return _Epoch(scene, 0.0, b.length, np.random.default_rng(0)).shadow(gu, gv)

    def _inside_section(self, out: Outline, n: float, margin: float):
        """About ``n`` uniform section points deeper than ``margin`` inside the outline."""
        n = int(round(n))
        pts = out.evaluate(np.linspace(0.0, out.perimeter, 256))
        lo = np.array([pts[0].min(), pts[1].min()])
        hi = np.array([pts[0].max(), pts[1].max()])
        got_u, got_v, total = [], [], 0
        while total < n:
            m = 2 * (n - total) + 16
            u = self.rng.uniform(lo[0], hi[0], m)
            v = self.rng.uniform(lo[1], hi[1], m)
            ok = out.signed_distance(u, v) < -margin
            got_u.append(u[ok])
            got_v.append(v[ok])
            total += int(ok.sum())
        return np.concatenate(got_u)[:n], np.concatenate(got_v)[:n]

    def finish(self) -> dict[str, np.ndarray]:
        parts = self.parts
        path = np.concatenate([p.pop("path") for p in parts])
        order = np.argsort(path, kind="stable")
        out = {"path": path[order]}
        for key in list(parts[0]):
            out[key] = np.concatenate([p.pop(key) for p in parts])[order]
        self.parts = []
        return out


def _clutter_scene(b: Branch, spec: NetworkPairSpec, rng: np.random.Generator):
    """The single-tube scene holding an edge's clutter (None: a bare edge)."""
    e = b.spec
    if not spec.equipment or not (e.equipment or e.conveyor):
        return None
    tunnel = TunnelSpec(
        length=b.length,
        section=e.section,
        density=spec.density,
        equipment=e.equipment,
        conveyor=e.conveyor,
        conveyor_side=e.conveyor_side,
        outlier_fraction=0.0,
    )
    return _make_scene(tunnel, rng)


def _area(out: Outline) -> float:
    u, v, *_ = out.evaluate(np.linspace(0.0, out.perimeter, 2049)[:-1])
    return float(0.5 * abs(np.sum(u * np.roll(v, -1) - np.roll(u, -1) * v)))


def _far_points(
    trees_pts: np.ndarray, tree: cKDTree, distance: float, rng: np.random.Generator
) -> np.ndarray:
    """A point ``distance`` from the nearest of ``trees_pts`` (the design axes), (3,)."""
    for _ in range(64):
        idx = rng.integers(0, len(trees_pts), 256)
        d = rng.normal(size=(256, 3))
        d[:, 2] *= 0.2  # mostly sideways, a little up or down
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        cand = trees_pts[idx] + distance * d
        dist, _ = tree.query(cand)
        ok = np.flatnonzero(dist >= distance * (1.0 - 1e-9))
        if ok.size:
            return cand[ok[0]]
    centre = trees_pts.mean(axis=0)
    reach = float(np.max(np.linalg.norm(trees_pts - centre, axis=1)))
    return centre + np.array([reach + distance, 0.0, 0.0])


def _strays(branches, spec: NetworkPairSpec, rng: np.random.Generator) -> np.ndarray:
    pts = np.concatenate([b.centerline.points[::4] for b in branches])
    tree = cKDTree(pts)
    out = []
    if spec.stray_distance > 0:
        out.append(_far_points(pts, tree, spec.stray_distance, rng)[None])
    for _ in range(int(spec.stray_clusters)):
        centre = _far_points(pts, tree, rng.uniform(40.0, 200.0), rng)
        n = int(rng.integers(5, 41))
        out.append(centre + rng.normal(0.0, 0.1, (n, 3)))
    return np.concatenate(out) if out else np.empty((0, 3))




def _apply(transform: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    out = np.einsum("ij,kj->ik", xyz, transform[:3, :3])
    out += transform[:3, 3]
    return out


# --------------------------------------------------------------------------------------------
# entry points
# --------------------------------------------------------------------------------------------


def _epoch(
    branches, openings, scenes, spec, coverage, deformations, g_sample, g_drift, g_stray
) -> tuple[np.ndarray, EpochTruth, np.ndarray]:
    parent, at = _walk_tree(coverage, branches)
    drift = random_drift(
        tuple(branches[st.branch].centerline for st in coverage),
        np.array([st.start for st in coverage]),
        np.array([st.end for st in coverage]),
        parent,
        at,
        spec.drift,
        g_drift,
        step=spec.drift_step,
    )
    sampler = _Sampler(branches, openings, scenes, spec, g_sample)
    by_branch: dict[int, list[DeformationSpec]] = {}
    for d in deformations:
        by_branch.setdefault(d.branch, []).append(d.deformation)
    for k, st in enumerate(coverage):
        sampler.stretch(k, st, float(drift.tau0[k]), tuple(by_branch.get(st.branch, ())))
    ep = sampler.finish()
    xyz_ref = ep.pop("xyz")
    seen = drift.apply(xyz_ref, ep["stretch"], ep["path"])
    far = _strays(branches, spec, g_stray)
    m = far.shape[0]
    if m:
        xyz_ref = np.concatenate([xyz_ref, far])
        seen = np.concatenate([seen, far])
        fill = {
            "path": np.nan,
            "chainage": np.nan,
            "branch": NO_BRANCH,
            "stretch": NO_BRANCH,
            "label": LABEL_OUTLIER,
            "surface": SURFACE_NONE,
            "displacement": 0.0,
            "comp": _C_OUTLIER,
        }
        for key, val in fill.items():
            ep[key] = np.concatenate([ep[key], np.full(m, val, ep[key].dtype)])
    stray = np.zeros(seen.shape[0], dtype=bool)
    stray[seen.shape[0] - m :] = True
    intensity = _intensity(ep.pop("comp"), g_sample)
    truth = EpochTruth(
        branch=ep["branch"],
        chainage=ep["chainage"],
        label=ep["label"],
        surface=ep["surface"],
        displacement=ep["displacement"],
        stray=stray,
        path=ep["path"],
        stretch=ep["stretch"],
        xyz_ref=xyz_ref,
        coverage=coverage,
        drift=drift,
    )
    return seen, truth, intensity


def make_network_pair(
    spec: NetworkPairSpec | None = None,
    *,
    progress: ProgressCallback | None = None,
    **changes,
) -> NetworkPair:
    """Two epochs of a synthetic drift network with ground truth per branch.

    Parameters
    ----------
    spec : NetworkPairSpec, optional
        The pair (default: :func:`network_250m_pair`); keyword arguments (any
        :class:`NetworkPairSpec` field, e.g. ``density=50, seed=3``) override it.
    progress : ProgressCallback, optional
        Called with ``("synthetic network", fraction)``.

    Returns
    -------
    NetworkPair
        ``ref`` in the design (reference) frame, drifted; ``cmp`` deformed, drifted (its own
        drift) and moved by a rigid motion; both with a ``uint16`` ``intensity`` field, points
        in walk order then the strays; ``truth`` (:class:`NetworkTruth`).

    Examples
    --------
    >>> pair = make_network_pair(density=50, seed=1)
    >>> t = pair.truth
    >>> ramp = t.cmp.shell & (t.cmp.branch == 4)  # the ramp's shell in the compared epoch
    >>> moved = t.cmp.displacement[ramp] < 0  # its roof sag (truth, m)
    >>> in_ref = pair.cmp.xyz @ t.transform[:3, :3].T + t.transform[:3, 3]
    >>> drift = in_ref - t.cmp.xyz_ref  # == t.cmp.drift_offset()
    """
    if spec is None:
        spec = network_250m_pair(**changes)
    elif changes:
        spec = dataclasses.replace(spec, **changes)
    branches = build_branches(spec.network)
    for d in spec.deformations:
        if not 0 <= d.branch < len(branches):
            raise ConfigError(f"deformation on unknown branch {d.branch}")
        b = branches[d.branch]
        if not 0 <= d.chainage <= b.length:
            raise ConfigError(
                f"deformation at chainage {d.chainage} m is off edge {b.name!r} "
                f"(0 to {b.length:.2f} m)"
            )
        _check_deformations(TunnelSpec(section=b.spec.section), (d.deformation,))
    g = [np.random.default_rng(c) for c in np.random.SeedSequence(spec.seed).spawn(8)]
    g_scene, g_ref, g_cmp, g_dref, g_dcmp, g_motion, g_sref, g_scmp = g
    scenes = {b.index: _clutter_scene(b, spec, g_scene) for b in branches}
    openings = _openings(branches)
    cov_ref = _resolve(spec.ref_coverage or _auto_coverage(branches), branches)
    cov_cmp = _resolve(spec.cmp_coverage or _auto_coverage(branches), branches)
    notify(progress, "synthetic network", 0.0)
    with timed_stage(log, "synthetic network reference epoch"):
        ref_xyz, ref_truth, ref_int = _epoch(
            branches, openings, scenes, spec, cov_ref, (), g_ref, g_dref, g_sref
        )
    notify(progress, "synthetic network", 0.5)
    with timed_stage(log, "synthetic network compared epoch"):
        cmp_seen, cmp_truth, cmp_int = _epoch(
            branches, openings, scenes, spec, cov_cmp, spec.deformations, g_cmp, g_dcmp, g_scmp
        )
    motion, transform, yaw, tilt_axis = _rigid_motion(
        g_motion, spec.yaw_deg, spec.tilt_deg, spec.translation
    )
    cmp_xyz = _apply(motion, cmp_seen)
    del cmp_seen
    meta = {"source": "tunneldef.synth.network", "network": spec.network.name, "seed": spec.seed}
    ref = Cloud(ref_xyz, {"intensity": ref_int}, {**meta, "epoch": "ref"})
    cmp = Cloud(cmp_xyz, {"intensity": cmp_int}, {**meta, "epoch": "cmp"})
    truth = NetworkTruth(
        ref=ref_truth,
        cmp=cmp_truth,
        transform=transform,
        branches=branches,
        centerlines=tuple(b.centerline for b in branches),
        junctions=spec.network.junctions,
        deformations=spec.deformations,
        yaw_deg=float(yaw),
        tilt_deg=float(spec.tilt_deg),
        tilt_axis=tilt_axis,
    )
    notify(progress, "synthetic network", 1.0)
    log.debug("synthetic network pair: %d reference, %d compared points", len(ref), len(cmp))
    return NetworkPair(ref, cmp, truth, spec)


def write_network_pair(
    pair: NetworkPair, out_dir: str | Path, *, fmt: str = "laz"
) -> dict[str, Path]:
    """Write ``ref.<fmt>``, ``cmp.<fmt>`` and ``truth.npz`` into ``out_dir``.

    Clouds go through :func:`tunneldef.io.write` (``intensity`` only). ``truth.npz`` holds, per
    epoch (prefix ``ref_`` / ``cmp_``), every per-point truth array and the walked stretches
    (rows branch, start, end); the 4 x 4 ``transform``; per edge ``centerline_<i>`` (M, 3);
    ``junctions`` (J, 3); ``deformations`` (rows branch, chainage, amplitude, length, width);
    and the specification as JSON in ``spec_json`` (``np.load`` reads it without pickle).

    Returns
    -------
    dict
        ``{"ref": path, "cmp": path, "truth": path}``.
    """
    paths = write_epochs(pair.ref, pair.cmp, out_dir, fmt)
    t = pair.truth
    arrays: dict[str, np.ndarray] = {"transform": t.transform, "junctions": t.junction_positions}
    for name, ep in (("ref", t.ref), ("cmp", t.cmp)):
        for key in (
            "branch",
            "chainage",
            "label",
            "surface",
            "displacement",
            "stray",
            "path",
            "stretch",
            "xyz_ref",
        ):
            arrays[f"{name}_{key}"] = getattr(ep, key)
        arrays[f"{name}_coverage"] = np.array([[s.branch, s.start, s.end] for s in ep.coverage])
    for b in t.branches:
        arrays[f"centerline_{b.index}"] = b.centerline.points
    arrays["deformations"] = np.array(
        [
            [d.branch, d.chainage, d.amplitude, d.deformation.length, d.deformation.width]
            for d in t.deformations
        ]
    ).reshape(-1, 5)
    arrays["spec_json"] = np.array(json.dumps(dataclasses.asdict(pair.spec)))
    np.savez_compressed(paths["truth"], **arrays)
    return paths


# --------------------------------------------------------------------------------------------
# preset
# --------------------------------------------------------------------------------------------


def network_250m() -> NetworkSpec:
    """A 250 m drift network (reference frame: x along the main drift, z up, floor at z = -1.6).

    - 0 ``main``: 110 m straight, rectangle 5.0 m x 3.2 m, pipes, cables and a conveyor with
      coal on the right;
    - 1 ``xc-through``: 40 m right-angle cross-cut through the main drift at x = 30 m (a 4-way
      crossing), arch 4.2 m x 3.2 m;
    - 2 ``xc-oblique``: 30 m cross-cut branching off to the right at 45 degrees at x = 60 m,
      trapezoid 4.0 m x 3.0 m (3.0 m at the roof);
    - 3 ``xc-dead-end``: 20 m right-angle cross-cut to the left at x = 85 m, horseshoe
      4.0 m x 3.2 m, ending in a face;
    - 4 ``ramp``: about 50 m from the end of the main drift: 8 m level, then a 12 % grade with a
      60 degree bend to the left (bend radius 12 m), rectangle 4.5 m x 3.0 m, pipes and cables.

    Floors are level with the main drift's at the junctions.
    """
    c45 = float(np.cos(np.radians(45.0)))
    g = 0.12
    z1 = -0.1 + 18.0 * g
    z2 = z1 + 24.0 * g
    c60, s60 = 0.5, float(np.sin(np.radians(60.0)))
    edges = (
        EdgeSpec(
            "main",
            ((0.0, 0.0, 0.0), (110.0, 0.0, 0.0)),
            SectionSpec("rectangle", 5.0, 3.2),
            equipment=True,
            conveyor=True,
        ),
        EdgeSpec(
            "xc-through", ((30.0, -20.0, 0.0), (30.0, 20.0, 0.0)), SectionSpec("arch", 4.2, 3.2)
        ),
        EdgeSpec(
            "xc-oblique",
            ((60.0, 0.0, -0.1), (60.0 + 30.0 * c45, -30.0 * c45, -0.1)),
            SectionSpec("trapezoid", 4.0, 3.0, top_width=3.0),
        ),
        EdgeSpec(
            "xc-dead-end",
            ((85.0, 0.0, 0.0), (85.0, 20.0, 0.0)),
            SectionSpec("horseshoe", 4.0, 3.2),
            faces=(False, True),
        ),
        EdgeSpec(
            "ramp",
            (
                (110.0, 0.0, -0.1),
                (118.0, 0.0, -0.1),
                (136.0, 0.0, z1),
                (136.0 + 24.0 * c60, 24.0 * s60, z2),
            ),
            SectionSpec("rectangle", 4.5, 3.0),
            bend_radius=12.0,
            equipment=True,
        ),
    )
    junctions = (
        JunctionSpec("crossing", (30.0, 0.0, 0.0), (0, 1)),
        JunctionSpec("oblique", (60.0, 0.0, 0.0), (0, 2)),
        JunctionSpec("dead-end tee", (85.0, 0.0, 0.0), (0, 3)),
        JunctionSpec("ramp portal", (110.0, 0.0, 0.0), (0, 4)),
    )
    return NetworkSpec(edges, junctions, name="network_250m")


def network_250m_pair(**changes) -> NetworkPairSpec:
    """The :func:`network_250m` pair: five deformations (10-60 mm, in the compared epoch), the
    reference walk and a later, longer compared walk starting 6 m further in.

    Deformations: main roof sag 40 mm at 15 m, main left-wall bulge 25 mm at 72 m, main floor
    heave 12 mm at 100 m, oblique cross-cut right-wall bulge 60 mm at 20 m, ramp roof sag 30 mm
    at 26 m (on the bend). Walks: reference main 0-110 m, the through cross-cut both ways from
    the crossing, 24 m of the oblique one, the dead-end to its face, 42 m of the ramp; compared
    main 6-110 m and everything else in full. Keyword arguments override any field.
    """
    defs = (
        BranchDeformation(0, DeformationSpec("roof_sag", 15.0, 6.0, 2.5, 0.040)),
        BranchDeformation(0, DeformationSpec("wall_bulge", 72.0, 5.0, 1.5, 0.025, "left")),
        BranchDeformation(0, DeformationSpec("floor_heave", 100.0, 6.0, 2.0, 0.012)),
        BranchDeformation(2, DeformationSpec("wall_bulge", 20.0, 4.0, 1.5, 0.060, "right")),
        BranchDeformation(4, DeformationSpec("roof_sag", 26.0, 6.0, 2.0, 0.030)),
    )
    ref = (
        Stretch(0, 0.0, 110.0),
        Stretch(1, 20.0, 0.0),
        Stretch(1, 20.0, 40.0),
        Stretch(2, 0.0, 24.0),
        Stretch(3, 0.0, None),
        Stretch(4, 0.0, 42.0),
    )
    cmp = (
        Stretch(0, 6.0, 110.0),
        Stretch(1, 20.0, 0.0),
        Stretch(1, 20.0, 40.0),
        Stretch(2, 0.0, None),
        Stretch(3, 0.0, None),
        Stretch(4, 0.0, None),
    )
    base = {
        "network": network_250m(),
        "deformations": defs,
        "ref_coverage": ref,
        "cmp_coverage": cmp,
    }
    base.update(changes)
    return NetworkPairSpec(**base)


def ramp_survey() -> NetworkSpec:
    """A network shaped like a real pair of handheld-SLAM surveys (reference frame: x along
    the main drift, z up, floor at z = -1.5).

    - 0 ``main``: 80 m straight, rectangle 4.8 m x 3.0 m, pipes, cables and a conveyor;
    - 1-3 ``xc1``-``xc3``: cross-cuts at right angles at x = 20 m (40 m to the right, open),
      45 m (15 m to the left, a dead end) and 70 m (18 m to the right, a dead end),
      rectangles 4.2 m x 2.8 m;
    - 4 ``ramp``: on from the end of the main drift, 8 m level, then 60 m at a 15 % grade and
      a 35 degree bend to the left (radius 15 m) into 70 m more at 15 %: about 20 m of climb;
    - 5-8 ``xc4``-``xc7``: four level dead ends of 12-15 m off the ramp (two on its straight,
      two beyond its bend, either side), rectangles 4.0-4.2 m x 2.8 m.
    """
    g = 0.15
    c, s = float(np.cos(np.radians(35.0))), float(np.sin(np.radians(35.0)))
    p0, p1 = (80.0, 0.0, 0.0), (88.0, 0.0, 0.0)
    p2 = (148.0, 0.0, 60.0 * g)
    p3 = (148.0 + 70.0 * c, 70.0 * s, 130.0 * g)

    def along(a: tuple, b: tuple, t: float) -> tuple[float, float, float]:
        return tuple(float(x + t * (y - x)) for x, y in zip(a, b, strict=True))

    j4, j5, j6, j7 = along(p1, p2, 0.3), along(p1, p2, 0.75), along(p2, p3, 0.5), along(p2, p3, 0.8)
    xc = SectionSpec("rectangle", 4.2, 2.8)
    xs = SectionSpec("rectangle", 4.0, 2.8)
    end = (False, True)
    edges = (
        EdgeSpec("main", ((0.0, 0.0, 0.0), p0), SectionSpec("rectangle", 4.8, 3.0),
                 equipment=True, conveyor=True),
        EdgeSpec("xc1", ((20.0, 0.0, 0.0), (20.0, -40.0, 0.0)), xc),
        EdgeSpec("xc2", ((45.0, 0.0, 0.0), (45.0, 15.0, 0.0)), xc, faces=end),
        EdgeSpec("xc3", ((70.0, 0.0, 0.0), (70.0, -18.0, 0.0)), xc, faces=end),
        EdgeSpec("ramp", (p0, p1, p2, p3), SectionSpec("rectangle", 4.8, 3.0), bend_radius=15.0,
                 equipment=True),
        EdgeSpec("xc4", (j4, (j4[0], -15.0, j4[2])), xs, faces=end),
        EdgeSpec("xc5", (j5, (j5[0], 15.0, j5[2])), xc, faces=end),
        EdgeSpec("xc6", (j6, (j6[0] + 12.0 * s, j6[1] - 12.0 * c, j6[2])), xs, faces=end),
        EdgeSpec("xc7", (j7, (j7[0] - 12.0 * s, j7[1] + 12.0 * c, j7[2])), xs, faces=end),
    )
    junctions = (
        JunctionSpec("xc1", (20.0, 0.0, 0.0), (0, 1)),
        JunctionSpec("xc2", (45.0, 0.0, 0.0), (0, 2)),
        JunctionSpec("xc3", (70.0, 0.0, 0.0), (0, 3)),
        JunctionSpec("ramp portal", p0, (0, 4)),
        JunctionSpec("xc4", j4, (4, 5)),
        JunctionSpec("xc5", j5, (4, 6)),
        JunctionSpec("xc6", j6, (4, 7)),
        JunctionSpec("xc7", j7, (4, 8)),
    )
    return NetworkSpec(edges, junctions, name="ramp_survey")


def ramp_survey_pair(**changes) -> NetworkPairSpec:
    """The :func:`ramp_survey` pair: the reference walks the main drift and its three
    cross-cuts; the later, compared walk also goes up the whole ramp and into its four dead
    ends (twice the points). 150 points/m^2 (0.08 m spacing), +-3 cm noise (sigma 1.5 cm),
    SLAM drift 5 cm per sqrt(100 m), a 3 degree tilt, each epoch in its own frame.

    Deformations: main roof sag 40 mm at 35 m, left-wall bulge 50 mm at 25 m of ``xc1``.
    Keyword arguments override any field."""
    defs = (
        BranchDeformation(0, DeformationSpec("roof_sag", 35.0, 6.0, 2.5, 0.040)),
        BranchDeformation(1, DeformationSpec("wall_bulge", 25.0, 5.0, 1.5, 0.050, "left")),
    )
    ref = tuple(Stretch(k, 0.0, 80.0 if k == 0 else None) for k in range(4))
    cmp = tuple(Stretch(k, 0.0, 80.0 if k == 0 else None) for k in range(9))
    base = {
        "network": ramp_survey(),
        "deformations": defs,
        "ref_coverage": ref,
        "cmp_coverage": cmp,
        "density": 150.0,
        "noise_sigma": 0.015,
        "drift": 0.05,
        "tilt_deg": 3.0,
        "translation": (1234.0, -567.0, 89.0),
    }
    base.update(changes)
    return NetworkPairSpec(**base)
