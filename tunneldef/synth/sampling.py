"""One synthetic epoch's points drawn from the scene: shell, clutter, noise, shadows, holes.

One idea at this length: drawing one epoch's points (surfaces, clutter, shadows, noise) from a
shared scene.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from .design import (
    _C_BELT,
    _C_CHAMBER,
    _C_COAL,
    _C_FRAME,
    _C_OUTLIER,
    _C_PERSON,
    _C_SHELL,
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
    _patch_centre,
)
from .scene import _heap_height, _relief, _Scene

log = logging.getLogger(__name__)

_SHADOW_SEEN = 0.2  # share of shadowed shell a handheld scanner still records
_SHELL_CHUNK = 4_000_000  # shell candidates drawn at once
_SHADOW_STEP = 0.0005  # m around the outline: resolution of the shadow look-up table


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


def write_epochs(ref: Any, cmp: Any, out_dir: str | Path, fmt: str) -> dict[str, Path]:
    """Write the two epochs as ``ref.<fmt>`` and ``cmp.<fmt>`` into ``out_dir`` (created)
    through :func:`tunneldef.io.write`; returns ``{"ref", "cmp", "truth"}`` paths, the last
    (``truth.npz``) for the caller to write."""
    from ..io import write as write_cloud

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fmt = fmt.lower().lstrip(".")
    paths = {"ref": out / f"ref.{fmt}", "cmp": out / f"cmp.{fmt}", "truth": out / "truth.npz"}
    write_cloud(paths["ref"], ref)
    write_cloud(paths["cmp"], cmp)
    return paths
