"""The scene both epochs of a synthetic pair share: design axis, rock relief, pipes, heaps."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..curve import Centerline
from .design import (
    _C_CABLE,
    _C_PIPE,
    SURFACE_LEFT,
    SURFACE_RIGHT,
    Outline,
    TunnelSpec,
    _cos_taper,
    section_outline,
)


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
    relief = draw_relief(rng, tunnel.roughness, outline.perimeter)
    return _Scene(tunnel, outline, axis, tuple(pipes), conveyor, chamber, relief, scanner)


def draw_relief(rng: np.random.Generator, roughness: float, perimeter: float) -> np.ndarray | None:
    """A smooth static rock relief of standard deviation ``roughness`` (m): 32 waves 0.8-8 m
    long along the axis, periodic around an outline of ``perimeter`` metres; rows (amplitude,
    along wavenumber, around wavenumber, phase) for :func:`_relief`. None where
    ``roughness`` is 0."""
    if roughness <= 0:
        return None
    k = 32
    lam = rng.uniform(0.8, 8.0, k)
    harmonic = rng.integers(1, max(2, int(perimeter / 0.8)), k)
    relief = np.stack(
        [
            np.full(k, roughness * np.sqrt(2.0 / k)),
            2 * np.pi / lam * rng.choice([-1.0, 1.0], k),
            harmonic.astype(float),
            rng.uniform(0, 2 * np.pi, k),
        ],
        axis=1,
    )
    relief[:, 2] *= 2 * np.pi / perimeter  # periodic around the outline
    return relief


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



def _pair_scene(spec: Any, g_scene: np.random.Generator, g_coal: np.random.Generator) -> tuple:
    """A pair's scene, the chainage ranges of its two epochs and their coal heaps:
    ``(scene, ref_range, cmp_range, heaps_ref, heaps_cmp)`` (heaps None without a conveyor)."""
    tunnel = spec.tunnel
    scene = _make_scene(tunnel, g_scene)
    ref_range = (0.0, float(tunnel.length))
    c0 = float(spec.cmp_shift)
    cmp_range = (c0, c0 + float(tunnel.length if spec.cmp_length is None else spec.cmp_length))
    heaps_ref = heaps_cmp = None
    if tunnel.conveyor:
        heaps_ref = _draw_heaps(g_scene, *ref_range)
        heaps_cmp = _draw_heaps(g_coal, *cmp_range) if spec.coal_change else heaps_ref
    return scene, ref_range, cmp_range, heaps_ref, heaps_cmp
