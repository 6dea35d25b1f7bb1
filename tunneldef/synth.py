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
:class:`tunneldef.centerline.curve.Centerline`. Deformation sign (the paper's, §3.3.2):
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
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .centerline.curve import Centerline
from .cloud import Cloud
from .errors import ConfigError
from .progress import ProgressCallback, report, timed_stage

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
]

log = logging.getLogger(__name__)

LABEL_SHELL, LABEL_EQUIPMENT, LABEL_DYNAMIC, LABEL_OUTLIER = 0, 1, 2, 3
SURFACE_ROOF, SURFACE_LEFT, SURFACE_RIGHT, SURFACE_FLOOR, SURFACE_NONE = 0, 1, 2, 3, 255

_SECTION_KINDS = ("rectangle", "arch", "trapezoid")
_DEFORMATION_KINDS = ("roof_sag", "wall_bulge", "floor_heave")
_SIDES = ("left", "right")

# component codes (internal; they set the intensity model)
_C_SHELL, _C_PIPE, _C_CABLE, _C_BELT, _C_FRAME, _C_COAL = range(6)
_C_OUTLIER, _C_PERSON, _C_CHAMBER = range(6, 9)
_SHADOW_SEEN = 0.2  # share of shadowed shell a handheld scanner still records
_SHELL_CHUNK = 4_000_000  # shell candidates drawn at once
_SHADOW_STEP = 0.0005  # m around the outline: resolution of the shadow look-up table


# --------------------------------------------------------------------------------------------
# specifications
# --------------------------------------------------------------------------------------------


def _positive(name: str, value: float, unit: str = "m") -> None:
    try:
        ok = bool(np.isfinite(value) and value > 0)
    except TypeError:
        ok = False
    if not ok:
        raise ConfigError(f"{name} must be a positive number ({unit}), got {value!r}")


@dataclass(frozen=True)
class SectionSpec:
    """Design cross-section.

    Parameters
    ----------
    kind : {"rectangle", "arch", "trapezoid"}
        Rectangle (paper §4); arch = vertical walls and a circular roof; trapezoid = inclined
        walls, wider at the floor.
    width : float
        Floor width, m (paper §4: 5.8 m).
    height : float
        Floor to roof (or crown) height, m (paper §4: 2.86 m).
    arch_rise : float or None
        Arch only: rise of the roof arch above the springing line, m. None: semicircular
        (``width / 2``) when that is at most half the height, else ``height / 2`` (segmental).
    top_width : float or None
        Trapezoid only: roof width, m. None: ``0.75 * width``.
    """

    kind: str = "rectangle"
    width: float = 5.8
    height: float = 2.86
    arch_rise: float | None = None
    top_width: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in _SECTION_KINDS:
            raise ConfigError(
                f"unknown section kind {self.kind!r}; use one of {', '.join(_SECTION_KINDS)}"
            )
        _positive("section width", self.width)
        _positive("section height", self.height)
        if self.arch_rise is not None:
            _positive("arch_rise", self.arch_rise)
            if self.arch_rise > self.width / 2 or self.arch_rise >= self.height:
                raise ConfigError(
                    f"arch_rise {self.arch_rise} m must be at most width/2 and below the height"
                )
        if self.top_width is not None:
            _positive("top_width", self.top_width)
            if self.top_width > self.width:
                raise ConfigError(
                    f"top_width {self.top_width} m exceeds the floor width {self.width} m"
                )

    @property
    def rise(self) -> float:
        """Arch rise actually used, m (0 for other kinds)."""
        if self.kind != "arch":
            return 0.0
        if self.arch_rise is not None:
            return float(self.arch_rise)
        return float(min(self.width / 2, self.height / 2))


@dataclass(frozen=True)
class TunnelSpec:
    """A synthetic tunnel and how one epoch of it is scanned.

    Parameters
    ----------
    length : float
        Length of the (reference) stretch along the design axis, m.
    radius : float or None
        Horizontal radius of the axis, m; > 0 turns left, < 0 right; None = straight.
    grade : float
        Constant grade of the axis, rise over horizontal run (0.02 = 2 %).
    section : SectionSpec
        Design cross-section.
    density : float
        Points per m^2 of shell (equipment and coal are sampled at the same density).
    noise_sigma : float
        Standard deviation of the Gaussian noise on each of x, y, z, m. Default 0.015 m: the
        scanner's stated accuracy of ±3 cm (paper §4, Table 1) taken as 2 sigma.
    outlier_fraction : float
        Outliers (label 3) scattered inside the tunnel volume, as a fraction of the other points.
    chamber : bool
        Add a side chamber (a recess in one wall).
    equipment : bool
        Add pipes and cables on the walls (label 1). They shadow the wall behind them, as seen
        from the walking line (80 % of the shadowed shell is dropped).
    conveyor : bool
        Add a conveyor belt along the floor (label 1; frame, legs, return belt; its belt
        surface 0.9 m above the floor, shadowing the floor and wall below) with a coal load
        (label 2).
    holes : int
        Number of occlusion holes (random patches of shell removed) per epoch.
    people : int
        People standing in the walkway per epoch (label 2, dynamic), placed anew each epoch.
    uneven_density : float
        Amplitude in [0, 1) of a smooth multiplicative modulation of density along chainage.
    roughness : float
        Standard deviation of a smooth static relief of the shell about the design outline, m
        (wavelengths 0.8-8 m; the same in both epochs, so it is not a displacement).
    chamber_chainage, chamber_depth, chamber_length, chamber_side
        Centre chainage (None: mid-length), depth into the wall, length along the axis (m) and
        side of the chamber.
    conveyor_side : {"left", "right"}
        Wall the conveyor runs along.
    """

    length: float = 30.0
    radius: float | None = None
    grade: float = 0.0
    section: SectionSpec = field(default_factory=SectionSpec)
    density: float = 400.0
    noise_sigma: float = 0.015
    outlier_fraction: float = 0.002
    chamber: bool = False
    equipment: bool = False
    conveyor: bool = False
    holes: int = 0
    people: int = 0
    uneven_density: float = 0.0
    roughness: float = 0.0
    chamber_chainage: float | None = None
    chamber_depth: float = 2.0
    chamber_length: float = 4.0
    chamber_side: str = "left"
    conveyor_side: str = "right"

    def __post_init__(self) -> None:
        if not isinstance(self.section, SectionSpec):
            raise ConfigError("section must be a SectionSpec")
        _positive("tunnel length", self.length)
        _positive("density", self.density, "points per m^2")
        if self.radius is not None:
            if not np.isfinite(self.radius) or abs(self.radius) < 2 * self.section.width:
                raise ConfigError(
                    f"radius {self.radius!r} m is too tight for a {self.section.width} m wide "
                    "section; use |radius| >= 2 x width or None for a straight tunnel"
                )
        if not np.isfinite(self.grade) or abs(self.grade) > 0.5:
            raise ConfigError(f"grade {self.grade!r} must be a ratio within [-0.5, 0.5]")
        if not np.isfinite(self.noise_sigma) or self.noise_sigma < 0:
            raise ConfigError(f"noise_sigma must be >= 0 m, got {self.noise_sigma!r}")
        if not 0 <= self.outlier_fraction < 0.5:
            raise ConfigError(
                f"outlier_fraction must be in [0, 0.5), got {self.outlier_fraction!r}"
            )
        if int(self.holes) != self.holes or self.holes < 0:
            raise ConfigError(f"holes must be a non-negative integer, got {self.holes!r}")
        if not 0 <= self.uneven_density < 1:
            raise ConfigError(f"uneven_density must be in [0, 1), got {self.uneven_density!r}")
        for name in ("chamber_side", "conveyor_side"):
            if getattr(self, name) not in _SIDES:
                raise ConfigError(f"{name} must be 'left' or 'right', got {getattr(self, name)!r}")
        _positive("chamber_depth", self.chamber_depth)
        _positive("chamber_length", self.chamber_length)
        if not np.isfinite(self.roughness) or not 0 <= self.roughness < 0.25:
            raise ConfigError(f"roughness must be in [0, 0.25) m, got {self.roughness!r}")
        if int(self.people) != self.people or self.people < 0:
            raise ConfigError(f"people must be a non-negative integer, got {self.people!r}")


@dataclass(frozen=True)
class DeformationSpec:
    """A smooth local deformation of the shell (cosine taper along and across).

    Parameters
    ----------
    kind : {"roof_sag", "wall_bulge", "floor_heave"}
        Centred on the roof midline, the mid-height of a wall, or the floor midline.
    chainage : float
        Centre, m along the reference design axis.
    length : float
        Full extent along the axis, m (the taper is zero at ``chainage +- length / 2``).
    width : float
        Full extent across, measured along the section outline, m.
    amplitude : float
        Peak movement, m; > 0 moves the shell INTO the tunnel (truth displacement
        ``-amplitude`` at the centre, the paper's sign); < 0 moves it outward.
    side : {"left", "right"}
        Wall of a ``wall_bulge`` (ignored otherwise).
    """

    kind: str = "roof_sag"
    chainage: float = 15.0
    length: float = 4.0
    width: float = 2.0
    amplitude: float = 0.03
    side: str = "left"

    def __post_init__(self) -> None:
        if self.kind not in _DEFORMATION_KINDS:
            raise ConfigError(
                f"unknown deformation kind {self.kind!r}; use one of "
                f"{', '.join(_DEFORMATION_KINDS)}"
            )
        if self.side not in _SIDES:
            raise ConfigError(f"deformation side must be 'left' or 'right', got {self.side!r}")
        _positive("deformation length", self.length)
        _positive("deformation width", self.width)
        if not np.isfinite(self.chainage) or not np.isfinite(self.amplitude):
            raise ConfigError("deformation chainage and amplitude must be finite numbers")

    def taper(self, along: np.ndarray, across: np.ndarray) -> np.ndarray:
        """Cosine taper in [0, 1] at offsets ``along`` / ``across`` from the centre (m)."""
        return _cos_taper(along, self.length) * _cos_taper(across, self.width)


@dataclass(frozen=True)
class PairSpec:
    """Two epochs of one tunnel.

    Parameters
    ----------
    tunnel : TunnelSpec
        The tunnel and scanning parameters (both epochs).
    deformations : tuple of DeformationSpec
        Applied to the compared epoch only.
    cmp_shift : float
        Chainage where the compared stretch starts, m (the reference starts at 0).
    cmp_length : float or None
        Length of the compared stretch, m (None: the reference length).
    yaw_deg : float or None
        Rotation about z of the compared epoch, degrees (None: random in [0, 360)).
    tilt_deg : float
        Tilt about a random horizontal axis, degrees.
    translation : (3,) float
        Translation of the compared epoch, m.
    coal_change : bool
        Draw a new coal load for the compared epoch (else the same heaps).
    seed : int
        Seed of everything (``np.random.default_rng``).
    """

    tunnel: TunnelSpec = field(default_factory=TunnelSpec)
    deformations: tuple[DeformationSpec, ...] = ()
    cmp_shift: float = 2.0
    cmp_length: float | None = None
    yaw_deg: float | None = None
    tilt_deg: float = 2.0
    translation: tuple[float, float, float] = (350.0, -120.0, 15.0)
    coal_change: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "deformations", tuple(self.deformations))
        for d in self.deformations:
            if not isinstance(d, DeformationSpec):
                raise ConfigError(f"deformations must be DeformationSpec objects, got {d!r}")
        if not np.isfinite(self.cmp_shift):
            raise ConfigError(f"cmp_shift must be finite, got {self.cmp_shift!r}")
        if self.cmp_length is not None:
            _positive("cmp_length", self.cmp_length)
        if np.shape(self.translation) != (3,):
            raise ConfigError(f"translation must be 3 numbers, got {self.translation!r}")
        _check_deformations(self.tunnel, self.deformations)


# --------------------------------------------------------------------------------------------
# section outline
# --------------------------------------------------------------------------------------------


class Outline:
    """A closed, convex section outline made of line segments and circular arcs.

    Segments run counter-clockwise in the ``(u, v)`` plane (``u`` left, ``v`` up), so the
    inward normal is the tangent turned by +90 degrees. Each segment carries a surface code
    (0 roof, 1 left wall, 2 right wall, 3 floor).
    """

    def __init__(self, segments: list[tuple]) -> None:
        # ("line", (u0, v0), (u1, v1), surface) or ("arc", (cu, cv), radius, a0, a1, surface)
        self.segments = segments
        lengths = []
        for seg in segments:
            if seg[0] == "line":
                lengths.append(float(np.hypot(seg[2][0] - seg[1][0], seg[2][1] - seg[1][1])))
            else:
                lengths.append(float(seg[2] * (seg[4] - seg[3])))
        self.lengths = np.array(lengths)
        self.starts = np.concatenate([[0.0], np.cumsum(self.lengths)[:-1]])
        self.perimeter = float(self.lengths.sum())

    def evaluate(self, p: np.ndarray) -> tuple[np.ndarray, ...]:
        """Point, inward normal and surface at perimeter positions ``p`` (m, any real).

        Returns ``(u, v, nu, nv, surface)``, each shape (N,).
        """
        p = np.mod(np.asarray(p, dtype=np.float64), self.perimeter)
        idx = np.searchsorted(self.starts, p, side="right") - 1
        np.clip(idx, 0, len(self.segments) - 1, out=idx)
        t = p - self.starts[idx]
        # straight segments by table look-up, then arcs overwritten where there are any
        tab = np.zeros((len(self.segments), 4))
        for k, seg in enumerate(self.segments):
            if seg[0] == "line":
                (u0, v0), (u1, v1) = seg[1], seg[2]
                tab[k] = u0, v0, (u1 - u0) / self.lengths[k], (v1 - v0) / self.lengths[k]
        du, dv = tab[idx, 2], tab[idx, 3]
        u = tab[idx, 0] + t * du
        v = tab[idx, 1] + t * dv
        nu, nv = -dv, du
        surface = np.array([seg[-1] for seg in self.segments], dtype=np.uint8)[idx]
        for k, seg in enumerate(self.segments):
            if seg[0] == "arc":
                m = idx == k
                (cu, cv), r, a0 = seg[1], seg[2], seg[3]
                a = a0 + t[m] / r
                ca, sa = np.cos(a), np.sin(a)
                u[m] = cu + r * ca
                v[m] = cv + r * sa
                nu[m], nv[m] = -ca, -sa
        return u, v, nu, nv, surface

    def signed_distance(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Signed distance of section points to the outline, m: negative inside the tunnel
        (the paper's sign: a shell point moved into the tunnel by ``d`` gives ``-d``)."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        best = np.full(u.shape, np.inf)
        sign = np.ones(u.shape)
        for k, seg in enumerate(self.segments):
            if seg[0] == "line":
                (u0, v0), (u1, v1) = seg[1], seg[2]
                du, dv = (u1 - u0) / self.lengths[k], (v1 - v0) / self.lengths[k]
                t = np.clip((u - u0) * du + (v - v0) * dv, 0.0, self.lengths[k])
                fu, fv = u0 + t * du, v0 + t * dv
                nu, nv = -dv, du
            else:
                (cu, cv), r, a0, a1 = seg[1], seg[2], seg[3], seg[4]
                a = np.arctan2(v - cv, u - cu)
                a = np.where(a < a0 - np.pi / 2, a + 2 * np.pi, a)
                a = np.clip(a, a0, a1)
                fu, fv = cu + r * np.cos(a), cv + r * np.sin(a)
                nu, nv = -np.cos(a), -np.sin(a)
            d = np.hypot(u - fu, v - fv)
            better = d < best
            best = np.where(better, d, best)
            inside = (u - fu) * nu + (v - fv) * nv > 0
            sign = np.where(better, np.where(inside, -1.0, 1.0), sign)
        return sign * best

    def half_width(self, v: np.ndarray | float) -> np.ndarray:
        """Half the clear width at height ``v`` (m), for these symmetric outlines."""
        v = np.atleast_1d(np.asarray(v, dtype=np.float64))
        # the left half is the part with u >= 0: intersect a horizontal line with it
        pts = self.evaluate(np.linspace(0.0, self.perimeter, 4001))
        left = pts[0] >= -1e-12
        uu, vv = pts[0][left], pts[1][left]
        order = np.argsort(vv)
        return np.interp(v, vv[order], uu[order])

    def surface_span(self, surface: int) -> tuple[float, float]:
        """(start, end) perimeter positions of the segments with this surface code."""
        ks = [k for k, seg in enumerate(self.segments) if seg[-1] == surface]
        return float(self.starts[ks[0]]), float(self.starts[ks[-1]] + self.lengths[ks[-1]])


def section_outline(section: SectionSpec) -> Outline:
    """The :class:`Outline` of a design section, centred on the design axis (m)."""
    w2, h2 = section.width / 2, section.height / 2
    if section.kind == "rectangle":
        segs = [
            ("line", (-w2, -h2), (w2, -h2), SURFACE_FLOOR),
            ("line", (w2, -h2), (w2, h2), SURFACE_LEFT),
            ("line", (w2, h2), (-w2, h2), SURFACE_ROOF),
            ("line", (-w2, h2), (-w2, -h2), SURFACE_RIGHT),
        ]
    elif section.kind == "trapezoid":
        t2 = (section.top_width if section.top_width is not None else 0.75 * section.width) / 2
        segs = [
            ("line", (-w2, -h2), (w2, -h2), SURFACE_FLOOR),
            ("line", (w2, -h2), (t2, h2), SURFACE_LEFT),
            ("line", (t2, h2), (-t2, h2), SURFACE_ROOF),
            ("line", (-t2, h2), (-w2, -h2), SURFACE_RIGHT),
        ]
    else:
        f = section.rise
        vs = h2 - f  # springing line
        rho = (f * f + w2 * w2) / (2 * f)
        cv = h2 - rho
        a0 = float(np.arctan2(vs - cv, w2))
        segs = [
            ("line", (-w2, -h2), (w2, -h2), SURFACE_FLOOR),
            ("line", (w2, -h2), (w2, vs), SURFACE_LEFT),
            ("arc", (0.0, cv), rho, a0, np.pi - a0, SURFACE_ROOF),
            ("line", (-w2, vs), (-w2, -h2), SURFACE_RIGHT),
        ]
    return Outline(segs)


def _cos_taper(x: np.ndarray, full: float) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return np.where(np.abs(x) < full / 2, 0.5 * (1.0 + np.cos(2.0 * np.pi * x / full)), 0.0)


def _patch_centre(outline: Outline, d: DeformationSpec) -> float:
    """Perimeter position of the centre of a deformation patch."""
    if d.kind == "roof_sag":
        a, b = outline.surface_span(SURFACE_ROOF)
    elif d.kind == "floor_heave":
        a, b = outline.surface_span(SURFACE_FLOOR)
    else:
        a, b = outline.surface_span(SURFACE_LEFT if d.side == "left" else SURFACE_RIGHT)
    return 0.5 * (a + b)


def _check_deformations(tunnel: TunnelSpec, deformations: tuple[DeformationSpec, ...]) -> None:
    sec = tunnel.section
    half = 0.5 * min(sec.width, sec.height)
    outline = section_outline(sec)
    for d in deformations:
        if abs(d.amplitude) >= half:
            raise ConfigError(
                f"deformation amplitude {d.amplitude} m is larger than half the section "
                f"({half:.3f} m); use a smaller amplitude"
            )
        if d.width >= outline.perimeter / 2:
            raise ConfigError(
                f"deformation width {d.width} m exceeds half the section perimeter "
                f"({outline.perimeter / 2:.2f} m)"
            )


# --------------------------------------------------------------------------------------------
# design axis
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Axis:
    radius: float | None
    grade: float

    @property
    def cos_a(self) -> float:
        return float(1.0 / np.sqrt(1.0 + self.grade**2))

    @property
    def sin_a(self) -> float:
        return float(self.grade / np.sqrt(1.0 + self.grade**2))

    @property
    def kappa(self) -> float:
        """Curvature of the axis towards +lateral (left), 1/m."""
        return 0.0 if self.radius is None else self.cos_a**2 / self.radius

    def frames(self, s: np.ndarray) -> tuple[np.ndarray, ...]:
        """Axis point, tangent, lateral (left) and vertical unit vectors at chainage ``s``."""
        s = np.asarray(s, dtype=np.float64)
        ca, sa = self.cos_a, self.sin_a
        h = s * ca
        if self.radius is None:
            phi = np.zeros_like(s)
            c = np.stack([h, np.zeros_like(s), s * sa], axis=-1)
        else:
            r = self.radius
            phi = h / r
            c = np.stack([r * np.sin(phi), r * (1.0 - np.cos(phi)), s * sa], axis=-1)
        cp, sp = np.cos(phi), np.sin(phi)
        t = np.stack([ca * cp, ca * sp, np.full_like(s, sa)], axis=-1)
        lat = np.stack([-sp, cp, np.zeros_like(s)], axis=-1)
        ver = np.stack([-sa * cp, -sa * sp, np.full_like(s, ca)], axis=-1)
        return c, t, lat, ver

    def centerline(self, s0: float, s1: float, *, step: float = 0.05) -> Centerline:
        n = max(int(np.ceil((s1 - s0) / step)), 1) + 1
        s = np.linspace(s0, s1, n)
        c = self.frames(s)[0]
        return Centerline(
            c,
            s - s0,
            meta={"method": "synthetic design axis", "radius": self.radius, "grade": self.grade},
        )


# --------------------------------------------------------------------------------------------
# scene (shared by both epochs) and epoch sampling
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Scene:
    tunnel: TunnelSpec
    outline: Outline
    axis: _Axis
    pipes: tuple[tuple[float, float, float, int], ...]  # (u, v, radius, component)
    conveyor: dict | None
    chamber: dict | None
    relief: np.ndarray | None  # rows (amplitude, along wavenumber, around wavenumber, phase)
    scanner: tuple[float, float]  # (u, v) of the walking line


def _side_sign(side: str) -> float:
    return 1.0 if side == "left" else -1.0


def _make_scene(tunnel: TunnelSpec, rng: np.random.Generator) -> _Scene:
    sec = tunnel.section
    outline = section_outline(sec)
    axis = _Axis(tunnel.radius, tunnel.grade)
    w2, h2 = sec.width / 2, sec.height / 2
    pipes: list[tuple[float, float, float, int]] = []
    if tunnel.equipment:
        # (wall, radius range, fraction range along the wall span, component)
        plan = [
            (SURFACE_LEFT, (0.05, 0.15), (0.25, 0.45), _C_PIPE),
            (SURFACE_LEFT, (0.03, 0.08), (0.55, 0.7), _C_PIPE),
            (SURFACE_RIGHT, (0.04, 0.08), (0.08, 0.2), _C_PIPE),
        ] + [
            (SURFACE_LEFT, (0.008, 0.02), (0.8 + 0.04 * k, 0.8 + 0.04 * k), _C_CABLE)
            for k in range(3)
        ]
        for surf, (r0, r1), (f0, f1), comp in plan:
            a, b = outline.surface_span(surf)
            r = rng.uniform(r0, r1)
            gap = rng.uniform(0.02, 0.08)
            p = a + rng.uniform(f0, f1) * (b - a)
            u, v, nu, nv, _ = outline.evaluate(np.array([p]))
            pipes.append(
                (float(u[0] + (gap + r) * nu[0]), float(v[0] + (gap + r) * nv[0]), float(r), comp)
            )
    conveyor = None
    if tunnel.conveyor:
        sg = _side_sign(tunnel.conveyor_side)
        v_belt = -h2 + min(0.9, 0.5 * sec.height)
        wall = float(outline.half_width(v_belt)[0])
        conveyor = {
            "sign": sg,
            "v_belt": v_belt,
            "u_out": sg * (wall - 0.5),
            "u_in": sg * (wall - 1.5),
            "u_c": sg * (wall - 1.0),
            "coal_width": 0.8,
        }
    chamber = None
    if tunnel.chamber:
        sg = _side_sign(tunnel.chamber_side)
        c = tunnel.length / 2 if tunnel.chamber_chainage is None else tunnel.chamber_chainage
        a, b = outline.surface_span(SURFACE_LEFT if sg > 0 else SURFACE_RIGHT)
        top = outline.evaluate(np.array([b if sg > 0 else a]))  # upper end of the wall
        chamber = {
            "sign": sg,
            "s0": c - tunnel.chamber_length / 2,
            "s1": c + tunnel.chamber_length / 2,
            "v_top": float(top[1][0]),
            "u_top": float(abs(top[0][0])),
            "u_back": w2 + tunnel.chamber_depth,
        }
    # the surveyor walks off the conveyor's side, the scanner held at about 1.5 m
    walk = 0.0 if conveyor is None else -0.6 * conveyor["sign"]
    scanner = (walk, -h2 + min(1.5, 0.6 * sec.height))
    relief = None
    if tunnel.roughness > 0:
        k = 32
        lam = rng.uniform(0.8, 8.0, k)
        harmonic = rng.integers(1, max(2, int(outline.perimeter / 0.8)), k)
        relief = np.stack(
            [
                np.full(k, tunnel.roughness * np.sqrt(2.0 / k)),
                2 * np.pi / lam * rng.choice([-1.0, 1.0], k),
                harmonic.astype(float),
                rng.uniform(0, 2 * np.pi, k),
            ],
            axis=1,
        )
        relief[:, 2] *= 2 * np.pi / outline.perimeter  # periodic around the outline
    return _Scene(tunnel, outline, axis, tuple(pipes), conveyor, chamber, relief, scanner)


def _relief(relief: np.ndarray, s: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Static shell relief (outward offset, m) at chainage ``s`` and perimeter position ``p``."""
    out = np.zeros_like(s)
    for amp, ks, kp, ph in relief:
        out += amp * np.cos(ks * s + kp * p + ph)
    return out


def _draw_heaps(rng: np.random.Generator, s0: float, s1: float) -> np.ndarray:
    """Coal heaps on the belt: rows of (centre chainage, length, peak height), m."""
    n = max(2, int(round((s1 - s0) / 10.0)))
    lo, hi = s0 + min(1.0, 0.1 * (s1 - s0)), s1 - min(1.0, 0.1 * (s1 - s0))
    return np.stack(
        [rng.uniform(lo, hi, n), rng.uniform(2.0, 6.0, n), rng.uniform(0.1, 0.3, n)], axis=1
    )


def _heap_height(heaps: np.ndarray, s: np.ndarray) -> np.ndarray:
    h = np.zeros_like(s)
    for c, length, peak in heaps:
        np.maximum(h, peak * _cos_taper(s - c, length), out=h)
    return h


class _Epoch:
    """Accumulates section-coordinate samples of one epoch."""

    def __init__(self, scene: _Scene, s0: float, s1: float, rng: np.random.Generator) -> None:
        self.scene, self.s0, self.s1, self.rng = scene, s0, s1, rng
        t = scene.tunnel
        self.density = t.density
        self.a = t.uneven_density
        # smooth density modulation along chainage: normalised sum of three sinusoids
        self.waves = np.stack(
            [rng.uniform(5.0, 25.0, 3), rng.uniform(0, 2 * np.pi, 3), rng.uniform(0.5, 1.0, 3)],
            axis=1,
        )
        self.kappa = scene.axis.kappa
        self.parts: list[dict[str, np.ndarray]] = []

    def modulation(self, s: np.ndarray) -> np.ndarray:
        if self.a == 0:
            return np.ones_like(s)
        g = np.zeros_like(s)
        for lam, ph, amp in self.waves:
            g += amp * np.sin(2 * np.pi * s / lam + ph)
        return 1.0 + self.a * g / self.waves[:, 2].sum()

    def chainages(self, n: int, s0: float | None = None, s1: float | None = None) -> np.ndarray:
        """``n`` uniform chainages in [s0, s1], drawn already sorted (uniform spacings)."""
        s0 = self.s0 if s0 is None else s0
        s1 = self.s1 if s1 is None else s1
        if n <= 0:
            return np.empty(0)
        gaps = self.rng.standard_exponential(n + 1)
        s = np.cumsum(gaps[:-1])
        s *= (s1 - s0) / (s[-1] + gaps[-1])
        s += s0
        return s

    def keep(self, s: np.ndarray, u: np.ndarray, umax: float) -> np.ndarray:
        """Thinning mask for uneven density and the along-axis stretch of a curved sweep."""
        jmax = 1.0 + abs(self.kappa) * umax
        prob = self.modulation(s) * (1.0 - self.kappa * u) / ((1.0 + self.a) * jmax)
        return self.rng.random(s.shape[0]) < prob

    def n_candidates(self, area: float, umax: float) -> int:
        return int(round(self.density * area * (1.0 + self.a) * (1.0 + abs(self.kappa) * umax)))

    def add(self, s, u, v, comp, label, surface, disp=None) -> None:
        n = s.shape[0]
        self.parts.append(
            {
                "s": s,
                "u": u,
                "v": v,
                "comp": np.full(n, comp, np.uint8) if np.isscalar(comp) else comp,
                "label": np.full(n, label, np.uint8),
                "surface": np.full(n, surface, np.uint8) if np.isscalar(surface) else surface,
                "disp": np.zeros(n) if disp is None else disp,
            }
        )

    # -- components -------------------------------------------------------------------------

    def shell(self, deformations: tuple[DeformationSpec, ...]) -> None:
        """The design outline swept along the axis, with holes, shadows, relief, deformations.

        Drawn in consecutive stretches of at most ``_SHELL_CHUNK`` candidates (bounded memory);
        the counts per stretch are multinomial, so the union is one uniform sample.
        """
        sc, rng = self.scene, self.rng
        out = sc.outline
        umax = float(np.max(np.abs(out.evaluate(np.linspace(0, out.perimeter, 64))[0])))
        n = self.n_candidates((self.s1 - self.s0) * out.perimeter, umax)
        holes = np.stack(
            [
                rng.uniform(self.s0, self.s1, sc.tunnel.holes),
                rng.uniform(0, out.perimeter, sc.tunnel.holes),
                rng.uniform(0.3, 1.0, sc.tunnel.holes),
            ],
            axis=1,
        )
        table = None
        if sc.pipes or sc.conveyor is not None:
            # the shadow depends on the position around the outline only: a look-up table
            grid = (np.arange(int(np.ceil(out.perimeter / _SHADOW_STEP))) + 0.5) * _SHADOW_STEP
            gu, gv, *_ = out.evaluate(grid)
            table = self.shadow(gu, gv)
        k = max(1, -(-n // _SHELL_CHUNK))
        edges = np.linspace(self.s0, self.s1, k + 1)
        for c, nc in enumerate(rng.multinomial(n, np.full(k, 1.0 / k))):
            self._shell_stretch(edges[c], edges[c + 1], int(nc), umax, holes, table, deformations)

    def _shell_stretch(self, s0, s1, n, umax, holes, table, deformations) -> None:
        sc, rng, out = self.scene, self.rng, self.scene.outline
        s = self.chainages(n, s0, s1)
        p = rng.uniform(0.0, out.perimeter, n)
        u, v, nu, nv, surface = out.evaluate(p)
        m = self.keep(s, u, umax)
        half = out.perimeter / 2
        for cs, cp, r in holes:
            i, j = np.searchsorted(s, (cs - r, cs + r))
            dp = np.mod(p[i:j] - cp + half, out.perimeter) - half
            m[i:j] &= (s[i:j] - cs) ** 2 + dp**2 > r * r
        ch = sc.chamber
        if ch is not None:
            wall = SURFACE_LEFT if ch["sign"] > 0 else SURFACE_RIGHT
            i, j = np.searchsorted(s, (ch["s0"], ch["s1"]))
            m[i:j] &= surface[i:j] != wall
        if table is not None:  # a moving handheld scanner still sees some of the shadow
            cell = np.minimum((p / _SHADOW_STEP).astype(np.intp), table.shape[0] - 1)
            m &= ~table[cell] | (rng.random(n) < _SHADOW_SEEN)
            del cell
        s, p, u, v, nu, nv, surface = (a[m] for a in (s, p, u, v, nu, nv, surface))
        if sc.relief is not None:  # static rock relief, outward positive
            off = _relief(sc.relief, s, p)
            u -= off * nu
            v -= off * nv
            del off
        disp = np.zeros(s.shape[0])
        for d in deformations:
            pc = _patch_centre(out, d)
            i, j = np.searchsorted(s, (d.chainage - d.length / 2, d.chainage + d.length / 2))
            dp = np.mod(p[i:j] - pc + half, out.perimeter) - half
            shift = d.amplitude * d.taper(s[i:j] - d.chainage, dp)
            u[i:j] += shift * nu[i:j]
            v[i:j] += shift * nv[i:j]
            disp[i:j] -= shift
        self.add(s, u, v, _C_SHELL, LABEL_SHELL, surface, disp)

    def sweep(self, ua, va, ub, vb, comp, label, surface, s0=None, s1=None) -> None:
        """A straight section segment (ua, va)-(ub, vb) swept along the axis."""
        s0 = self.s0 if s0 is None else max(s0, self.s0)
        s1 = self.s1 if s1 is None else min(s1, self.s1)
        if s1 <= s0:
            return
        length = float(np.hypot(ub - ua, vb - va))
        umax = max(abs(ua), abs(ub))
        n = self.n_candidates((s1 - s0) * length, umax)
        s = self.chainages(n, s0, s1)
        f = self.rng.random(n)
        u, v = ua + f * (ub - ua), va + f * (vb - va)
        m = self.keep(s, u, umax)
        self.add(s[m], u[m], v[m], comp, label, surface)

    def tube(self, uc, vc, r, comp, label) -> None:
        """A cylinder of radius r parallel to the axis."""
        umax = abs(uc) + r
        n = self.n_candidates((self.s1 - self.s0) * 2 * np.pi * r, umax)
        s = self.chainages(n)
        a = self.rng.uniform(0, 2 * np.pi, n)
        u, v = uc + r * np.cos(a), vc + r * np.sin(a)
        m = self.keep(s, u, umax)
        self.add(s[m], u[m], v[m], comp, label, SURFACE_NONE)

    def cross(self, s_at, ua, ub, va, vb, comp, label, surface, reject=None) -> None:
        """A rectangle in the section plane at chainage ``s_at`` (optionally clipped)."""
        if not self.s0 <= s_at <= self.s1:
            return
        n = int(round(self.density * abs(ub - ua) * abs(vb - va) * (1 + self.a)))
        u = self.rng.uniform(min(ua, ub), max(ua, ub), n)
        v = self.rng.uniform(min(va, vb), max(va, vb), n)
        s = np.full(n, float(s_at))
        m = self.rng.random(n) < self.modulation(s) / (1 + self.a)
        if reject is not None:
            m &= ~reject(u, v)
        self.add(s[m], u[m], v[m], comp, label, surface)

    def chamber(self) -> None:
        ch, out = self.scene.chamber, self.scene.outline
        if ch is None:
            return
        sg, h2 = ch["sign"], self.scene.tunnel.section.height / 2
        wall = SURFACE_LEFT if sg > 0 else SURFACE_RIGHT
        w2 = self.scene.tunnel.section.width / 2
        ub, vt = sg * ch["u_back"], ch["v_top"]
        kw = {"s0": ch["s0"], "s1": ch["s1"]}
        self.sweep(ub, -h2, ub, vt, _C_CHAMBER, LABEL_SHELL, wall, **kw)  # back wall
        self.sweep(sg * w2, -h2, ub, -h2, _C_CHAMBER, LABEL_SHELL, SURFACE_FLOOR, **kw)
        self.sweep(sg * ch["u_top"], vt, ub, vt, _C_CHAMBER, LABEL_SHELL, SURFACE_ROOF, **kw)

        def inside(u, v):
            return np.abs(u) < out.half_width(v)

        for s_end in (ch["s0"], ch["s1"]):
            self.cross(
                s_end,
                sg * min(ch["u_top"], w2),
                ub,
                -h2,
                vt,
                _C_CHAMBER,
                LABEL_SHELL,
                wall,
                reject=inside,
            )

    def shadow(self, u: np.ndarray, v: np.ndarray) -> np.ndarray | None:
        """Shell points hidden from the walking line by pipes and the conveyor belt.

        The scanner walks parallel to the axis and so do the occluders, so each casts the same
        2-D shadow in every section: an angular interval seen from the scanner's position.
        """
        sc = self.scene
        if not sc.pipes and sc.conveyor is None:
            return None
        us, vs = sc.scanner
        ang = np.arctan2(v - vs, u - us)
        dist = np.hypot(u - us, v - vs)
        hidden = np.zeros(u.shape[0], dtype=bool)
        for uc, vc, r, _ in sc.pipes:
            dc = float(np.hypot(uc - us, vc - vs))
            half = float(np.arcsin(min(r / dc, 1.0)))
            da = np.angle(np.exp(1j * (ang - np.arctan2(vc - vs, uc - us))))
            hidden |= (np.abs(da) < half) & (dist > dc)
        cv = sc.conveyor
        if cv is not None:  # the belt: a segment (u_out, v_belt)-(u_in, v_belt)
            vb = cv["v_belt"]
            a0, a1 = sorted(
                (np.arctan2(vb - vs, cv["u_out"] - us), np.arctan2(vb - vs, cv["u_in"] - us))
            )
            if a1 - a0 <= np.pi:  # the walking line is not right above the belt
                below = (v - vb) * np.sign(vs - vb) < 0
                hidden |= (ang > a0) & (ang < a1) & below
        return hidden

    def equipment(self) -> None:
        for uc, vc, r, comp in self.scene.pipes:
            self.tube(uc, vc, r, comp, LABEL_EQUIPMENT)

    def people(self, count: int) -> None:
        """People standing in the walkway: vertical cylinders (label 2, dynamic)."""
        if count == 0:
            return
        sc = self.scene
        h2 = sc.tunnel.section.height / 2
        r, tall = 0.2, min(1.75, sc.tunnel.section.height - 0.2)
        where = self.rng.uniform(self.s0 + 0.5, self.s1 - 0.5, count)
        across = sc.scanner[0] + self.rng.uniform(-0.6, 0.6, count)
        n = int(round(self.density * count * 2 * np.pi * r * tall))
        k = self.rng.integers(0, count, n)
        a = self.rng.uniform(0, 2 * np.pi, n)
        s = where[k] + r * np.cos(a)
        order = np.argsort(s)
        u = (across[k] + r * np.sin(a))[order]
        v = self.rng.uniform(-h2, -h2 + tall, n)[order]
        self.add(s[order], u, v, _C_PERSON, LABEL_DYNAMIC, SURFACE_NONE)

    def conveyor(self, heaps: np.ndarray) -> None:
        cv = self.scene.conveyor
        if cv is None:
            return
        h2 = self.scene.tunnel.section.height / 2
        vb, uo, ui, uc = cv["v_belt"], cv["u_out"], cv["u_in"], cv["u_c"]
        before = len(self.parts)
        self.sweep(uo, vb, ui, vb, _C_BELT, LABEL_EQUIPMENT, SURFACE_NONE)  # belt surface
        belt = self.parts[before:]
        # the coal hides the belt under it
        wc = cv["coal_width"]
        for part in belt:
            hidden = (np.abs(part["u"] - uc) < wc / 2) & (_heap_height(heaps, part["s"]) > 0.01)
            for k in part:
                part[k] = part[k][~hidden]
        self.sweep(
            uo - 0.05 * cv["sign"],
            -h2 + 0.3,
            ui + 0.05 * cv["sign"],
            -h2 + 0.3,
            _C_BELT,
            LABEL_EQUIPMENT,
            SURFACE_NONE,
        )  # return belt
        for ue in (uo, ui):
            self.tube(ue, vb - 0.1, 0.04, _C_FRAME, LABEL_EQUIPMENT)  # stringers
        # legs: vertical posts every 1.5 m at both edges
        posts = np.arange(np.ceil(self.s0 / 1.5) * 1.5, self.s1, 1.5)
        r, hgt = 0.03, vb - 0.1 - (-h2)
        if posts.size:
            n = int(round(self.density * posts.size * 2 * 2 * np.pi * r * hgt))
            k = self.rng.integers(0, posts.size, n)
            e = np.where(self.rng.random(n) < 0.5, uo, ui)
            a = self.rng.uniform(0, 2 * np.pi, n)
            s = posts[k] + r * np.cos(a)
            ok = (s >= self.s0) & (s <= self.s1)
            self.add(
                s[ok],
                (e + r * np.sin(a))[ok],
                self.rng.uniform(-h2, vb - 0.1, n)[ok],
                _C_FRAME,
                LABEL_EQUIPMENT,
                SURFACE_NONE,
            )
        # coal load: parabolic heaps on the belt
        n = int(round(self.density * (self.s1 - self.s0) * wc * 1.15 * (1 + self.a)))
        s = self.chainages(n)
        x = self.rng.uniform(-wc / 2, wc / 2, n)
        h = _heap_height(heaps, s) * (1.0 - (2.0 * x / wc) ** 2)
        m = (h > 0.005) & self.keep(s, uc + x, abs(uc) + wc)
        self.add(s[m], (uc + x)[m], (vb + 0.005 + h)[m], _C_COAL, LABEL_DYNAMIC, SURFACE_NONE)

    def outliers(self) -> None:
        f = self.scene.tunnel.outlier_fraction
        n_other = sum(p["s"].shape[0] for p in self.parts)
        n = int(round(f * n_other))
        if n == 0:
            return
        sec, out = self.scene.tunnel.section, self.scene.outline
        m = 3 * n + 16
        s = self.rng.uniform(self.s0, self.s1, m)
        u = self.rng.uniform(-sec.width / 2, sec.width / 2, m)
        v = self.rng.uniform(-sec.height / 2, sec.height / 2, m)
        ok = np.flatnonzero(out.signed_distance(u, v) < -0.05)[:n]
        self.add(s[ok], u[ok], v[ok], _C_OUTLIER, LABEL_OUTLIER, SURFACE_NONE)

    # -- assembly -----------------------------------------------------------------------------

    def finish(self, *, chunk: int = 2_000_000) -> dict[str, np.ndarray]:
        """Concatenate, sort along the walk (chainage), add noise, map to the design frame."""
        parts = self.parts
        s = np.concatenate([p.pop("s") for p in parts])
        order = np.argsort(s, kind="stable")
        s = s[order]
        self.parts = []
        cat = {}
        for k in [k for k in parts[0] if k != "s"]:  # key by key, freeing the parts as we go
            cat[k] = np.concatenate([p.pop(k) for p in parts])[order]
        del order, parts
        n = s.shape[0]
        sigma = self.scene.tunnel.noise_sigma
        xyz = np.empty((n, 3))
        chainage = s.copy()
        axis = self.scene.axis
        ca, sa = axis.cos_a, axis.sin_a
        for i in range(0, n, chunk):
            j = min(i + chunk, n)
            si, ui, vi = s[i:j], cat["u"][i:j], cat["v"][i:j]
            if axis.radius is None:
                cp, sp = np.ones_like(si), np.zeros_like(si)
                cx, cy = si * ca, np.zeros_like(si)
            else:
                phi = si * (ca / axis.radius)
                cp, sp = np.cos(phi), np.sin(phi)
                cx, cy = axis.radius * sp, axis.radius * (1.0 - cp)
            # x = c + u * lateral + v * vertical, component by component (see _Axis.frames)
            out = xyz[i:j]
            out[:, 0] = cx - ui * sp - vi * sa * cp
            out[:, 1] = cy + ui * cp - vi * sa * sp
            out[:, 2] = si * sa + vi * ca
            if sigma > 0:
                noise = self.rng.normal(0.0, sigma, (j - i, 3))
                out += noise
                # chainage of the noisy point, exact to first order (curved sweep stretch)
                along = noise[:, 0] * (ca * cp) + noise[:, 1] * (ca * sp) + noise[:, 2] * sa
                chainage[i:j] += along / (1.0 - self.kappa * ui)
        intensity = _intensity(cat["comp"], self.rng)
        return {
            "xyz": xyz,
            "chainage": chainage,
            "displacement": cat["disp"],
            "label": cat["label"],
            "surface": cat["surface"],
            "chamber": cat["comp"] == _C_CHAMBER,
            "intensity": intensity,
        }


# base intensity and log-normal spread per component: rock/coal-face shell, pipes (painted
# metal), cables, rubber belt, steel frame, coal (dark), outliers (dust, people: anything)
_INTENSITY_BASE = np.array([1400.0, 2600.0, 1800.0, 600.0, 2800.0, 350.0, 1500.0, 900.0, 1400.0])
_INTENSITY_SPREAD = np.array([0.25, 0.2, 0.2, 0.25, 0.2, 0.35, 0.8, 0.5, 0.25])


def _intensity(comp: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    z = rng.standard_normal(comp.shape[0]).astype(np.float32)
    val = _INTENSITY_BASE.astype(np.float32)[comp] * np.exp(
        _INTENSITY_SPREAD.astype(np.float32)[comp] * z
    )
    return np.clip(val, 1, 65535).astype(np.uint16)


def _sample_epoch(
    scene: _Scene,
    s0: float,
    s1: float,
    rng: np.random.Generator,
    deformations: tuple[DeformationSpec, ...],
    heaps: np.ndarray | None,
) -> dict[str, np.ndarray]:
    ep = _Epoch(scene, s0, s1, rng)
    ep.shell(deformations)
    ep.chamber()
    ep.equipment()
    ep.people(scene.tunnel.people)
    if heaps is not None:
        ep.conveyor(heaps)
    ep.outliers()
    return ep.finish()


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
    report(progress, "synthetic epoch", 0.0)
    with timed_stage(log, "synthetic epoch"):
        ep = _sample_epoch(scene, 0.0, tunnel.length, g_ref, deformations, heaps)
    report(progress, "synthetic epoch", 1.0)
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


def _apply(transform: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """``xyz`` (N, 3) mapped by a 4 x 4 rigid transform (einsum: no BLAS threads)."""
    out = np.einsum("ij,kj->ik", xyz, transform[:3, :3])
    out += transform[:3, 3]
    return out


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * (kx @ kx)


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
    tunnel = spec.tunnel
    g_scene, g_ref, g_cmp, g_motion, g_coal = _streams(spec.seed)
    scene = _make_scene(tunnel, g_scene)
    ref_range = (0.0, float(tunnel.length))
    c0 = float(spec.cmp_shift)
    cmp_range = (c0, c0 + float(tunnel.length if spec.cmp_length is None else spec.cmp_length))
    heaps_ref = heaps_cmp = None
    if tunnel.conveyor:
        heaps_ref = _draw_heaps(g_scene, *ref_range)
        heaps_cmp = _draw_heaps(g_coal, *cmp_range) if spec.coal_change else heaps_ref
    report(progress, "synthetic pair", 0.0)
    with timed_stage(log, "synthetic reference epoch"):
        ref = _sample_epoch(scene, *ref_range, g_ref, (), heaps_ref)
    report(progress, "synthetic pair", 0.5)
    with timed_stage(log, "synthetic compared epoch"):
        cmp = _sample_epoch(scene, *cmp_range, g_cmp, spec.deformations, heaps_cmp)
    report(progress, "synthetic pair", 0.95)

    yaw = g_motion.uniform(0.0, 360.0) if spec.yaw_deg is None else float(spec.yaw_deg)
    phi = g_motion.uniform(0.0, 2 * np.pi)
    tilt_axis = np.array([np.cos(phi), np.sin(phi), 0.0])
    rot = _rotation(np.array([0.0, 0.0, 1.0]), np.radians(yaw)) @ _rotation(
        tilt_axis, np.radians(spec.tilt_deg)
    )
    motion = np.eye(4)
    motion[:3, :3] = rot
    motion[:3, 3] = np.asarray(spec.translation, dtype=np.float64)
    transform = np.eye(4)
    transform[:3, :3] = rot.T
    transform[:3, 3] = -rot.T @ motion[:3, 3]

    local = cmp.pop("xyz")
    cmp_xyz = _apply(motion, local)
    del local
    in_ref = _apply(transform, cmp_xyz)

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
    report(progress, "synthetic pair", 1.0)
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
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fmt = fmt.lower().lstrip(".")
    paths = {"ref": out / f"ref.{fmt}", "cmp": out / f"cmp.{fmt}", "truth": out / "truth.npz"}
    try:
        from .io import write as io_write
    except ImportError:
        io_write = None
    for key, cloud in (("ref", pair.ref), ("cmp", pair.cmp)):
        if io_write is not None:
            io_write(paths[key], cloud)
        elif fmt == "ply":
            _write_ply(paths[key], cloud)
        else:
            raise ConfigError(f"cannot write {fmt!r} without tunneldef.io; use fmt='ply'")
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


def _write_ply(path: Path, cloud: Cloud) -> None:
    from plyfile import PlyData, PlyElement

    n = len(cloud)
    dt = [("x", "f8"), ("y", "f8"), ("z", "f8")] + [
        (f"scalar_{k}", v.dtype.str) for k, v in cloud.fields.items()
    ]
    arr = np.empty(n, dtype=dt)
    arr["x"], arr["y"], arr["z"] = cloud.xyz.T
    for k, v in cloud.fields.items():
        arr[f"scalar_{k}"] = v
    PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(path))
