"""The centreline as a densely sampled 3-D curve with chainage, and projection onto it.

A :class:`Centerline` is what every later stage uses: registration aligns two of them, the
deformation stage projects points onto one to get chainage ``s`` and the offsets across
(``lateral``, horizontal, positive to the left of the direction of increasing chainage) and
``vertical`` (in the plane normal to the curve, positive up). How the curve was fitted (NURBS,
paper §3.1.4) is :mod:`tunneldef.centerline.fit`'s business; this module only samples it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .cloud import check_points
from .curve_kernels import foot_points
from .errors import NotATunnelError
from .spatial import query_workers
from .transforms import apply_transform

__all__ = ["Centerline", "Projection"]


@dataclass(frozen=True)
class Projection:
    """Points expressed relative to a centreline (all arrays shape (N,), metres).

    Attributes
    ----------
    chainage : distance along the curve of the foot point (may be < 0 or > length beyond the
        ends, extrapolated along the end tangents).
    lateral : horizontal offset from the curve, positive to the left of increasing chainage.
    vertical : offset in the normal plane, perpendicular to ``lateral``, positive up.
    distance : sqrt(lateral**2 + vertical**2), the distance to the curve.
    inside : True where the foot point lies on the curve (0 <= chainage <= length).
    """

    chainage: np.ndarray
    lateral: np.ndarray
    vertical: np.ndarray
    distance: np.ndarray
    inside: np.ndarray


@dataclass(frozen=True)
class Centerline:
    """A tunnel centreline sampled at a fixed chainage step.

    Attributes
    ----------
    points : ndarray, shape (M, 3)
        World coordinates of the samples, metres, in order of increasing chainage.
    chainage : ndarray, shape (M,)
        Arc length of each sample from the first, metres (``chainage[0] == 0``).
    centres : ndarray, shape (K, 3)
        The slice centres the curve was fitted to (may be empty).
    meta : dict
        How it was made (method, degree, knots, per-slice records...), JSON-serialisable.
    """

    points: np.ndarray
    chainage: np.ndarray
    centres: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    meta: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_polyline(
        cls,
        vertices: np.ndarray,
        *,
        step: float = 0.05,
        centres: np.ndarray | None = None,
        meta: dict[str, Any] | None = None,
    ) -> Centerline:
        """Resample a polyline (e.g. an evaluated NURBS curve) at a uniform arc-length step.

        Parameters
        ----------
        vertices : ndarray, shape (V, 3)
            Ordered vertices, metres; at least 2 distinct.
        step : float
            Sampling step along the curve, metres.
        """
        v = check_points(vertices, name="centreline vertices", min_points=2)
        seg = np.linalg.norm(np.diff(v, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-9])
        v = v[keep]
        if v.shape[0] < 2:
            raise NotATunnelError("the centreline has fewer than two distinct vertices")
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(v, axis=0), axis=1))])
        n = max(int(np.ceil(s[-1] / step)), 1) + 1
        t = np.linspace(0.0, s[-1], n)
        pts = np.stack([np.interp(t, s, v[:, i]) for i in range(3)], axis=1)
        return cls(
            pts,
            t,
            np.empty((0, 3)) if centres is None else np.asarray(centres, float),
            dict(meta or {}),
        )

    @property
    def length(self) -> float:
        """Length of the curve, metres."""
        return float(self.chainage[-1])

    def _frames(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cache = self.__dict__.get("_frames_cache")
        if cache is None:
            p = self.points
            t = (
                np.gradient(p, self.chainage, axis=0)
                if len(p) > 2
                else np.repeat((p[1] - p[0])[None], len(p), axis=0)
            )
            t /= np.linalg.norm(t, axis=1, keepdims=True)
            up = np.array([0.0, 0.0, 1.0])
            lat = np.cross(up, t)
            norm = np.linalg.norm(lat, axis=1, keepdims=True)
            if np.any(norm < 1e-6):
                raise NotATunnelError("the centreline is vertical somewhere; a shaft, not a tunnel")
            lat /= norm
            ver = np.cross(t, lat)
            cache = (t, lat, ver)
            object.__setattr__(self, "_frames_cache", cache)
        return cache

    def _curvature(self) -> np.ndarray:
        """Curvature vectors dt/ds at the samples, (M, 3), pointing to the centre of curvature."""
        k = self.__dict__.get("_curvature_cache")
        if k is None:
            t = self._frames()[0]
            k = np.gradient(t, self.chainage, axis=0) if len(t) > 2 else np.zeros_like(t)
            object.__setattr__(self, "_curvature_cache", k)
        return k

    def _tree(self) -> cKDTree:
        tree = self.__dict__.get("_tree_cache")
        if tree is None:
            tree = cKDTree(self.points)
            object.__setattr__(self, "_tree_cache", tree)
        return tree

    def point_at(self, s: np.ndarray | float) -> np.ndarray:
        """World coordinates of the curve at chainage ``s`` (linear between samples; the end
        tangents extend the curve beyond its ends)."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        t, _, _ = self._frames()
        out = np.stack([np.interp(s, self.chainage, self.points[:, i]) for i in range(3)], axis=1)
        lo, hi = s < 0, s > self.length
        out[lo] = self.points[0] + s[lo, None] * t[0]
        out[hi] = self.points[-1] + (s[hi, None] - self.length) * t[-1]
        return out

    def frame_at(self, s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit tangent, lateral (left) and vertical (up) vectors at chainage ``s``, each (N, 3)."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        i = np.clip(
            np.round(np.interp(s, self.chainage, np.arange(len(self.chainage)))),
            0,
            len(self.chainage) - 1,
        ).astype(np.intp)
        t, lat, ver = self._frames()
        return t[i], lat[i], ver[i]

    def project(self, xyz: np.ndarray, *, workers: int = -1) -> Projection:
        """Chainage and offsets of points relative to the curve.

        Parameters
        ----------
        xyz : ndarray, shape (N, 3)
            World coordinates, metres.
        workers : int
            Threads for the nearest-sample query (-1: all cores).

        Notes
        -----
        Each point is matched to its nearest curve sample (KD-tree), then slid along that
        sample's tangent to its foot point, the slide scaled by ``1 / (1 - d . k)`` (``d`` the
        offset from the curve, ``k`` the curvature vector) so that points outside a bend get
        the chainage of their foot point, not of the tangent line; with samples every few
        centimetres the remaining error is of the order of ``step**2 * curvature``, far below a
        millimetre.
        """
        p = np.ascontiguousarray(xyz, dtype=np.float64)
        t, lat, ver = self._frames()
        _, i = self._tree().query(p, workers=query_workers(len(p), workers))
        # slide from the nearest sample to the foot point, re-anchor on the sample nearest to
        # it and measure the offsets there (one compiled pass, :mod:`.curve_kernels`)
        s, lateral, vertical = foot_points(
            p, np.asarray(i, dtype=np.int64), self.points, self.chainage, t, lat, ver,
            self._curvature(),
        )
        return Projection(
            chainage=s,
            lateral=lateral,
            vertical=vertical,
            distance=np.hypot(lateral, vertical),
            inside=(s >= 0.0) & (s <= self.length),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (points, chainage, centres, meta)."""
        return {
            "length_m": self.length,
            "points": self.points.tolist(),
            "chainage": self.chainage.tolist(),
            "centres": self.centres.tolist(),
            "meta": self.meta,
        }

    def transformed(self, transform: np.ndarray) -> Centerline:
        """The same curve mapped by a 4 x 4 rigid transform."""
        def f(a: np.ndarray) -> np.ndarray:
            return apply_transform(transform, a) if len(a) else a

        return Centerline(f(self.points), self.chainage.copy(), f(self.centres), dict(self.meta))
