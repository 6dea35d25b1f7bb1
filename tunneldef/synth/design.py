"""Design of synthetic tunnels (:mod:`tunneldef.synth`): the specifications, their checks, the
cross-section outlines and the deformation patches on them.

One idea at this length: the specifications of a synthetic pair and the section outlines they
are drawn on, validated in one place.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import check_positive
from ..errors import ConfigError
from ..surfaces import FLOOR, LEFT_WALL, NO_SURFACE, RIGHT_WALL, ROOF

LABEL_SHELL, LABEL_EQUIPMENT, LABEL_DYNAMIC, LABEL_OUTLIER = 0, 1, 2, 3
SURFACE_ROOF, SURFACE_LEFT, SURFACE_RIGHT, SURFACE_FLOOR, SURFACE_NONE = (
    ROOF, LEFT_WALL, RIGHT_WALL, FLOOR, NO_SURFACE
)

_SECTION_KINDS = ("rectangle", "arch", "trapezoid", "horseshoe")
_DEFORMATION_KINDS = ("roof_sag", "wall_bulge", "floor_heave")
_SIDES = ("left", "right")

# component codes (internal; they set the intensity model)
_C_SHELL, _C_PIPE, _C_CABLE, _C_BELT, _C_FRAME, _C_COAL = range(6)
_C_OUTLIER, _C_PERSON, _C_CHAMBER = range(6, 9)


@dataclass(frozen=True)
class SectionSpec:
    """Design cross-section.

    Parameters
    ----------
    kind : {"rectangle", "arch", "trapezoid", "horseshoe"}
        Rectangle (paper §4); arch = vertical walls and a circular roof; trapezoid = inclined
        walls, wider at the floor; horseshoe = a semicircular roof over curved walls (arcs of
        radius ``width``, centred on the far side of the springing line) and a flat floor.
    width : float
        Floor width, m (paper §4: 5.8 m); horseshoe: the span at the springing line (the floor
        is narrower), and ``height`` must stay below ``(1 + sqrt(3)) * width / 2``.
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
        check_positive("section width", self.width)
        check_positive("section height", self.height)
        if self.arch_rise is not None:
            check_positive("arch_rise", self.arch_rise)
            if self.arch_rise > self.width / 2 or self.arch_rise >= self.height:
                raise ConfigError(
                    f"arch_rise {self.arch_rise} m must be at most width/2 and below the height"
                )
        if self.top_width is not None:
            check_positive("top_width", self.top_width)
            if self.top_width > self.width:
                raise ConfigError(
                    f"top_width {self.top_width} m exceeds the floor width {self.width} m"
                )
        if self.kind == "horseshoe" and not (
            self.width / 2 < self.height < 0.95 * (1 + np.sqrt(3)) * self.width / 2
        ):
            raise ConfigError(
                f"a horseshoe section needs width/2 < height < 1.3 x width, got "
                f"{self.width} x {self.height} m"
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
        check_positive("tunnel length", self.length)
        check_positive("density", self.density, unit="points per m^2")
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
        check_positive("chamber_depth", self.chamber_depth)
        check_positive("chamber_length", self.chamber_length)
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
        check_positive("deformation length", self.length)
        check_positive("deformation width", self.width)
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
            check_positive("cmp_length", self.cmp_length)
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
            inside = (u - fu) * nu + (v - fv) * nv > 0
            # nearest to a corner shared with an earlier segment (a tie): inside only if on
            # the inner side of both (else obtuse corners, e.g. a trapezoid's, flip the sign)
            tie = np.abs(d - best) <= 1e-9
            better = (d < best) & ~tie
            best = np.where(better, d, best)
            sign = np.where(better, np.where(inside, -1.0, 1.0), np.where(tie & ~inside, 1.0, sign))
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
    elif section.kind == "horseshoe":
        r = w2  # roof radius; the walls are arcs of radius 2 r about the opposite springing
        vs = h2 - r
        b = float(np.arcsin((h2 + vs) / (2 * r)))  # wall arc angle from springing to floor
        uf = 2 * r * np.cos(b) - r  # half floor width
        segs = [
            ("line", (-uf, -h2), (uf, -h2), SURFACE_FLOOR),
            ("arc", (-r, vs), 2 * r, -b, 0.0, SURFACE_LEFT),
            ("arc", (0.0, vs), r, 0.0, np.pi, SURFACE_ROOF),
            ("arc", (r, vs), 2 * r, np.pi, np.pi + b, SURFACE_RIGHT),
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


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) by ``angle`` (radians) about ``axis`` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * (kx @ kx)


def _rigid_motion(
    g: np.random.Generator, yaw_deg: float | None, tilt_deg: float,
    translation: tuple[float, float, float],
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """The compared epoch's arbitrary frame: a yaw (random when None), a tilt about a random
    horizontal axis and a translation. Returns ``(motion, transform, yaw_deg, tilt_axis)``:
    ``motion`` maps the design frame into the compared epoch's, ``transform`` (its inverse)
    maps the compared epoch into the reference's."""
    yaw = g.uniform(0.0, 360.0) if yaw_deg is None else float(yaw_deg)
    phi = g.uniform(0.0, 2 * np.pi)
    tilt_axis = np.array([np.cos(phi), np.sin(phi), 0.0])
    rot = _rotation(np.array([0.0, 0.0, 1.0]), np.radians(yaw)) @ _rotation(
        tilt_axis, np.radians(tilt_deg)
    )
    motion = np.eye(4)
    motion[:3, :3] = rot
    motion[:3, 3] = np.asarray(translation, dtype=np.float64)
    transform = np.eye(4)
    transform[:3, :3] = rot.T
    transform[:3, 3] = -rot.T @ motion[:3, 3]
    return motion, transform, yaw, tilt_axis
