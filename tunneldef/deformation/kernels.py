"""Compiled loops of the robust estimator (Numba).

:func:`cylinder_stats` is the inner loop of :func:`.cylinders._epoch_stats`: for every core, the
points of one epoch in its cylinder, their positions along the core's normal, three passes of
sigma clipping and the mean offset across the normal. In NumPy the same work takes a dozen
passes over flat (core, point) pair arrays, each as long as all neighbourhoods together; here it
is one pass over each core's own neighbours, with the same float32 and float64 arithmetic in the
same order, so the values are bit for bit those of the NumPy formulation
(``tests/test_kernels.py`` holds it to that). Compiled once per machine and cached beside the
module (``cache=True``); serial, so that it runs the same in Dask's threads and in
CloudCompare's.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["cylinder_stats"]


@numba.njit(cache=True, nogil=True)
def _moments(vals: np.ndarray, keep: np.ndarray, q: int) -> tuple[float, float, float]:
    """Count, mean and standard deviation (n - 1) of the kept values, summed in order."""
    n = 0.0
    total = 0.0
    for i in range(q):
        if keep[i]:
            n += 1.0
            total += vals[i]
    mean = total / max(n, 1.0)
    var = 0.0
    for i in range(q):
        if keep[i]:
            dev = vals[i] - mean
            var += dev * dev
    return n, mean, np.sqrt(var / max(n - 1.0, 1.0))


@numba.njit(cache=True, nogil=True)
def cylinder_stats(
    pts, pt_normals, cores, normals, splits, idx, d2, radius, depth, cos_max, k, floor, trim_z,
):
    """Clipped statistics of the points in each core's cylinder.

    Parameters
    ----------
    pts, pt_normals : ndarray of float32, shape (M, 3)
        The epoch's points (offsets from a local origin) and the normal of each point's core.
    cores : ndarray of float32, shape (C, 3)
        Core points, same origin.
    normals : ndarray of float32, shape (C, 3)
        Unit normal of each core.
    splits, idx, d2 : ndarray
        The points within ``hypot(radius, depth)`` of each core as Open3D's fixed-radius
        search gives them: core ``c``'s are ``idx[splits[c]:splits[c + 1]]`` with squared
        distances ``d2`` (float32).
    radius, depth : float
        Cylinder radius about the normal and half-length along it, metres.
    cos_max : float
        A point counts when its own normal is within this cosine of the core's.
    k, floor : float
        Clipping at ``max(k * std, floor)`` from the mean.
    trim_z : float
        Values below ``mean - trim_z * spread`` are dropped after the second pass (0: off).

    Returns
    -------
    mean, spread : ndarray of float64, shape (C,)
        Mean of the last survivors along the normal and the spread of the second pass's
        survivors (NaN without points).
    count : ndarray of int32, shape (C,)
        Survivors.
    centre : ndarray of float64, shape (C, 3)
        Mean offset of the survivors across the normal from the cylinder's axis (NaN without).
    """
    n_cores = cores.shape[0]
    mean = np.full(n_cores, np.nan)
    spread = np.full(n_cores, np.nan)
    count = np.zeros(n_cores, np.int32)
    centre = np.full((n_cores, 3), np.nan)
    r2 = np.float32(radius * radius)
    dep = np.float32(depth)
    cmax = np.float32(cos_max)
    for c in range(n_cores):
        a0, a1 = splits[c], splits[c + 1]
        vals = np.empty(a1 - a0, np.float64)
        along = np.empty(a1 - a0, np.float32)
        point = np.empty(a1 - a0, np.int64)
        cx, cy, cz = cores[c, 0], cores[c, 1], cores[c, 2]
        nx, ny, nz = normals[c, 0], normals[c, 1], normals[c, 2]
        q = 0
        for j in range(a0, a1):
            p = idx[j]
            a = (pts[p, 0] - cx) * nx + (pts[p, 1] - cy) * ny + (pts[p, 2] - cz) * nz
            if abs(a) <= dep and d2[j] - a * a <= r2:
                if pt_normals[p, 0] * nx + pt_normals[p, 1] * ny + pt_normals[p, 2] * nz >= cmax:
                    vals[q] = a
                    along[q] = a
                    point[q] = p
                    q += 1
        if q == 0:
            continue
        keep = np.ones(q, np.bool_)
        _, mu, sd = _moments(vals, keep, q)
        lim = max(k * sd, floor)
        for i in range(q):
            keep[i] = abs(vals[i] - mu) <= lim
        _, mu, sp = _moments(vals, keep, q)
        lim = max(k * sp, floor)
        for i in range(q):
            keep[i] = abs(vals[i] - mu) <= lim
            if trim_z > 0.0:
                keep[i] = keep[i] and vals[i] - mu >= -trim_z * sp
        _, mu, sd = _moments(vals, keep, q)
        lim = max(k * sd, floor)
        for i in range(q):
            keep[i] = keep[i] and abs(vals[i] - mu) <= lim
        n, mu, _ = _moments(vals, keep, q)
        if n < 1.0:
            continue
        mean[c], spread[c], count[c] = mu, sp, np.int32(n)
        sx = sy = sz = 0.0
        for i in range(q):
            if keep[i]:
                p, a = point[i], along[i]
                sx += np.float64((pts[p, 0] - cx) - a * nx)
                sy += np.float64((pts[p, 1] - cy) - a * ny)
                sz += np.float64((pts[p, 2] - cz) - a * nz)
        centre[c, 0], centre[c, 1], centre[c, 2] = sx / n, sy / n, sz / n
    return mean, spread, count, centre
