"""Compiled loop of :meth:`.curve.Centerline.project` (Numba).

Once each point's nearest curve sample is known (a KD-tree query), the foot point, chainage and
offsets are a few dot products per point. In NumPy that is about twenty whole-array passes
and (N, 3) temporaries over every point of a survey, several times per run; here it is one
pass. The sample index comes from the same interpolation and rounding as ``np.interp`` and
``np.round`` (bit for bit), the dot products agree with NumPy's ``einsum`` to the last bits
(NumPy does not fix the order of the three products); ``tests/test_kernels.py`` holds it to
that. Compiled once per machine and cached beside the module (``cache=True``); serial, so that
it runs the same in Dask's threads and in CloudCompare's.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["foot_points"]


@numba.njit(cache=True, nogil=True)
def _sample_index(s, chainage):
    """``clip(round(interp(s, chainage, arange(n))), 0, n - 1)`` for one value."""
    n = chainage.shape[0]
    if not s > chainage[0]:  # (NaN goes to the first sample, as NumPy's cast then clip does)
        return 0
    if s >= chainage[n - 1]:
        return n - 1
    lo, hi = 0, n - 1  # chainage[lo] <= s < chainage[hi]
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if chainage[mid] <= s:
            lo = mid
        else:
            hi = mid
    slope = 1.0 / (chainage[lo + 1] - chainage[lo])
    return int(np.rint(slope * (s - chainage[lo]) + lo))


@numba.njit(cache=True, nogil=True)
def foot_points(p, nearest, points, chainage, t, lat, ver, curvature):
    """Chainage and offsets of points from their nearest curve sample.

    Parameters
    ----------
    p : ndarray of float64, shape (N, 3)
        Points, metres.
    nearest : ndarray of int64, shape (N,)
        Index of each point's nearest curve sample.
    points, t, lat, ver, curvature : ndarray of float64, shape (M, 3)
        Curve samples, their unit tangent, lateral and vertical vectors and curvature vectors.
    chainage : ndarray of float64, shape (M,)
        Chainage of the samples, increasing.

    Returns
    -------
    s, lateral, vertical : ndarray of float64, shape (N,)
        As :meth:`.curve.Centerline.project` documents them.
    """
    n = p.shape[0]
    m = chainage.shape[0]
    s_out = np.empty(n)
    lat_out = np.empty(n)
    ver_out = np.empty(n)
    for q in range(n):
        i = nearest[q]
        d0 = p[q, 0] - points[i, 0]
        d1 = p[q, 1] - points[i, 1]
        d2 = p[q, 2] - points[i, 2]
        s = chainage[i] + (d0 * t[i, 0] + d1 * t[i, 1] + d2 * t[i, 2])
        # re-anchor on the sample nearest to the foot point, then measure offsets there
        j = _sample_index(s, chainage)
        d0 = p[q, 0] - points[j, 0]
        d1 = p[q, 1] - points[j, 1]
        d2 = p[q, 2] - points[j, 2]
        u = d0 * t[j, 0] + d1 * t[j, 1] + d2 * t[j, 2]
        d0 = d0 - u * t[j, 0]
        d1 = d1 - u * t[j, 1]
        d2 = d2 - u * t[j, 2]
        scale = 1.0 - (d0 * curvature[j, 0] + d1 * curvature[j, 1] + d2 * curvature[j, 2])
        if (j == 0 and u < 0) or (j == m - 1 and u > 0):
            scale = 1.0  # beyond the ends the curve goes on straight
        s_out[q] = chainage[j] + u / max(scale, 0.1)
        lat_out[q] = d0 * lat[j, 0] + d1 * lat[j, 1] + d2 * lat[j, 2]
        ver_out[q] = d0 * ver[j, 0] + d1 * ver[j, 1] + d2 * ver[j, 2]
    return s_out, lat_out, ver_out
