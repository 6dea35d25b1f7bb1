"""SLAM drift of a synthetic survey walk (:mod:`tunneldef.synth.network`).

A handheld SLAM scanner's map is locally rigid but its pose error grows along the walk. Here the
error at path position ``tau`` (metres walked from the start of the survey, measured along the
walked centrelines) is a small rigid motion about the walker's position ``c(tau)``::

    x' = x + d(tau) + omega(tau) x (x - c(tau))

``d`` (m) is the displacement of the walked centreline point and ``omega`` (rad) a small
rotation vector. Both are random walks sampled at knots a few metres apart and joined by natural
cubic splines (smooth in ``tau``); a rotation error displaces everything walked after it by its
lever arm, as in a real SLAM map. A walk is a tree of stretches: each stretch after the first
branches off one walked before it, starting from that stretch's pose at the branching point, so
the drift is continuous across junctions and independent in each branch.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline

from ..curve import Centerline

__all__ = ["DriftWalk", "random_drift"]


@dataclass(frozen=True)
class DriftWalk:
    """The SLAM drift of one epoch: a smooth 6-DoF pose error along a tree of walked stretches.

    Attributes
    ----------
    centerlines : tuple of Centerline
        Per stretch, the walked design axis (reference frame).
    starts, ends : (K,) float64
        Chainage on that axis where the stretch's walk starts and ends (``end < start``: walked
        backwards), m.
    tau0 : (K,) float64
        Path position at each stretch's start, m.
    parent : (K,) int64
        Stretch each stretch branches off (-1 for the first).
    knots : tuple of (M, 7) float64
        Per stretch, rows ``(tau, d_x, d_y, d_z, omega_x, omega_y, omega_z)`` (m, rad).
    rate : float
        Root-mean-square over all knots after the start of ``|d| / sqrt(tau / 100 m)``, m: the
        drift of the walked centreline, in metres per square root of 100 m walked.
    """

    centerlines: tuple[Centerline, ...]
    starts: np.ndarray
    ends: np.ndarray
    tau0: np.ndarray
    parent: np.ndarray
    knots: tuple[np.ndarray, ...]
    rate: float
    _splines: dict = field(default_factory=dict, repr=False, compare=False)

    def _spline(self, k: int) -> CubicSpline:
        sp = self._splines.get(k)
        if sp is None:
            kn = self.knots[k]
            sp = CubicSpline(kn[:, 0], kn[:, 1:], axis=0, bc_type="natural", extrapolate=True)
            self._splines[k] = sp
        return sp

    def centre(self, stretch: int, tau: np.ndarray) -> np.ndarray:
        """Walked centreline point (reference frame) at path positions ``tau`` of a stretch."""
        tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
        sign = 1.0 if self.ends[stretch] >= self.starts[stretch] else -1.0
        s = self.starts[stretch] + sign * (tau - self.tau0[stretch])
        return self.centerlines[stretch].point_at(s)

    def pose(self, stretch: int, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(d, omega)``, each (N, 3): the centreline displacement (m) and rotation vector
        (rad) at path positions ``tau`` of one stretch."""
        tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
        val = self._spline(stretch)(tau)
        return val[:, :3], val[:, 3:]

    def offset(self, xyz: np.ndarray, stretch: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Drift displacement (N, 3), m, of true points ``xyz`` (reference frame) scanned on
        stretches ``stretch`` (N,) at path positions ``tau`` (N,)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        stretch = np.asarray(stretch)
        tau = np.asarray(tau, dtype=np.float64)
        out = np.zeros_like(xyz)
        for k in np.unique(stretch):
            m = np.flatnonzero(stretch == k)
            d, w = self.pose(int(k), tau[m])
            out[m] = d + np.cross(w, xyz[m] - self.centre(int(k), tau[m]))
        return out

    def apply(self, xyz: np.ndarray, stretch: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """``xyz`` as the drifting SLAM map records them (``xyz + offset``)."""
        return np.asarray(xyz, dtype=np.float64) + self.offset(xyz, stretch, tau)

    def remove(self, xyz: np.ndarray, stretch: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Undo :meth:`apply` (two fixed-point steps: exact to ``|omega|**2``, sub-micrometre)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        est = xyz - self.offset(xyz, stretch, tau)
        return xyz - self.offset(est, stretch, tau)


def random_drift(
    centerlines: tuple[Centerline, ...],
    starts: np.ndarray,
    ends: np.ndarray,
    parent: np.ndarray,
    parent_chainage: np.ndarray,
    rate: float,
    rng: np.random.Generator,
    *,
    step: float = 10.0,
    rotation_share: float = 0.015,
) -> DriftWalk:
    """Draw a drift along a tree of walked stretches.

    Parameters
    ----------
    centerlines, starts, ends, parent
        See :class:`DriftWalk`; ``parent[k] < k`` for ``k > 0``.
    parent_chainage : (K,) float64
        Chainage on the parent stretch's axis where stretch ``k`` branches off (ignored for 0).
    rate : float
        Drift in metres per square root of 100 m walked (see :attr:`DriftWalk.rate`); the draw is
        scaled to it exactly. 0 gives no drift.
    rng : numpy.random.Generator
    step : float
        Knot spacing along the walk, m.
    rotation_share : float
        Standard deviation of the rotation increments (rad) per metre of the translation
        increments' before scaling: 0.015 makes the lever-arm part of the drift about as large as
        the translation part over 100 m.

    Returns
    -------
    DriftWalk
    """
    n = len(centerlines)
    starts = np.asarray(starts, dtype=np.float64)
    ends = np.asarray(ends, dtype=np.float64)
    parent = np.asarray(parent, dtype=np.int64)
    tau0 = np.zeros(n)
    knots: list[np.ndarray] = []
    for k in range(n):
        length = abs(ends[k] - starts[k])
        m = max(2, int(np.ceil(length / step)) + 1)
        if k == 0 or parent[k] < 0:
            d0, w0 = np.zeros(3), np.zeros(3)
        else:
            j = int(parent[k])
            sj = float(parent_chainage[k])
            tj = tau0[j] + abs(sj - starts[j])
            pj = centerlines[j].point_at(sj)[0]
            here = centerlines[k].point_at(starts[k])[0]
            kn = np.asarray(knots[j])
            sp = CubicSpline(kn[:, 0], kn[:, 1:], axis=0, bc_type="natural")(tj)
            w0 = sp[3:]
            d0 = sp[:3] + np.cross(w0, here - pj)
            tau0[k] = tj + float(np.linalg.norm(here - pj))
        tau = tau0[k] + np.linspace(0.0, length, m)
        sign = 1.0 if ends[k] >= starts[k] else -1.0
        c = centerlines[k].point_at(starts[k] + sign * (tau - tau0[k]))
        dt = np.diff(tau)[:, None]
        eps = rng.normal(0.0, 1.0, (m - 1, 3)) * np.sqrt(dt / 3.0)
        eta = rng.normal(0.0, rotation_share, (m - 1, 3)) * np.sqrt(dt / 3.0)
        d = np.empty((m, 3))
        w = np.empty((m, 3))
        d[0], w[0] = d0, w0
        for i in range(1, m):
            w[i] = w[i - 1] + eta[i - 1]
            d[i] = d[i - 1] + np.cross(w[i - 1], c[i] - c[i - 1]) + eps[i - 1]
        knots.append(np.column_stack([tau, d, w]))
    # scale to the rate: the drift is linear in the increments
    tau_all = np.concatenate([kn[:, 0] for kn in knots])
    d_all = np.concatenate([np.linalg.norm(kn[:, 1:4], axis=1) for kn in knots])
    use = tau_all > 1e-9
    raw = float(np.sqrt(np.mean(d_all[use] ** 2 / (tau_all[use] / 100.0)))) if use.any() else 0.0
    scale = rate / raw if raw > 0 else 0.0
    scaled = []
    for kn in knots:
        kn = kn.copy()
        kn[:, 1:] *= scale
        scaled.append(kn)
    return DriftWalk(tuple(centerlines), starts, ends, tau0, parent, tuple(scaled), float(rate))
