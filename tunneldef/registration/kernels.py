"""Compiled loops of the along-axis slide (Numba).

:func:`nearest_two` and :func:`slide_residuals` are the per-iteration work of
:func:`.axial.fine_shift`: the nearest two cached candidates of every sliding point, and the
point-to-plane residual of each matched point. In NumPy the same work is an ``argpartition``,
two gathers and a handful of whole-array temporaries per Gauss-Newton step; here it is one pass
over each point's own candidates. :func:`candidate_terms` draws the candidates' cached terms
without the (points, candidates, 3) offset arrays NumPy needs (1.5 M sliding points: 0.6 GB).
Distances are bit for bit those of the NumPy formulation; dot products equal NumPy's
``einsum`` to the last bits (NumPy does not fix the order of the three products);
``tests/test_kernels.py`` holds them to that. Compiled once per machine and cached beside the
module (``cache=True``); serial, so that it runs the same in Dask's threads and in
CloudCompare's.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["candidate_terms", "nearest_two", "slide_residuals"]


@numba.njit(cache=True, nogil=True)
def nearest_two(a, b, step):
    """Distances to the nearest and second-nearest candidate after a slide.

    Parameters
    ----------
    a, b : ndarray of float64, shape (M, K)
        Squared distance of each point to each candidate at the base slide (``inf`` where
        there is none), and ``2 t . (x0 - c)``.
    step : float
        Slide beyond the base, metres: squared distances are ``a + step * (b + step)``.

    Returns
    -------
    dmin, second : ndarray of float64, shape (M,)
        The two smallest distances (``sqrt`` of the squared ones clipped at 0), ascending.
    best : ndarray of int64, shape (M,)
        Column of the nearest candidate (0 where no candidate is finite).
    """
    m, k = a.shape
    dmin = np.empty(m)
    second = np.empty(m)
    best = np.zeros(m, dtype=np.int64)
    for i in range(m):
        m1 = np.inf
        m2 = np.inf
        k1 = 0
        for c in range(k):
            v = a[i, c] + step * (b[i, c] + step)
            if v < m1:
                m2 = m1
                m1 = v
                k1 = c
            elif v < m2:
                m2 = v
        dmin[i] = np.sqrt(max(m1, 0.0))
        second[i] = np.sqrt(max(m2, 0.0))
        best[i] = k1
    return dmin, second, best


@numba.njit(cache=True, nogil=True)
def slide_residuals(xyz, tangents, ref_pn, rows, j, delta):
    """Point-to-plane residuals of the matched sliding points.

    Parameters
    ----------
    xyz, tangents : ndarray of float64, shape (M, 3)
        Points and their unit slide directions.
    ref_pn : ndarray of float64, shape (N, 6)
        Reference points and unit normals side by side.
    rows : ndarray of int64, shape (P,)
        The matched points.
    j : ndarray of int64, shape (M,)
        Each point's reference match.
    delta : float
        Slide along the tangents, metres.

    Returns
    -------
    r, a : ndarray of float64, shape (P,)
        ``n . (x + delta t - p)`` and ``n . t`` of each matched point.
    """
    p = rows.shape[0]
    r = np.empty(p)
    a = np.empty(p)
    for q in range(p):
        i = rows[q]
        m = j[i]
        n0, n1, n2 = ref_pn[m, 3], ref_pn[m, 4], ref_pn[m, 5]
        t0, t1, t2 = tangents[i, 0], tangents[i, 1], tangents[i, 2]
        e0 = xyz[i, 0] + delta * t0 - ref_pn[m, 0]
        e1 = xyz[i, 1] + delta * t1 - ref_pn[m, 1]
        e2 = xyz[i, 2] + delta * t2 - ref_pn[m, 2]
        r[q] = n0 * e0 + n1 * e1 + n2 * e2
        a[q] = n0 * t0 + n1 * t1 + n2 * t2
    return r, a


@numba.njit(cache=True, nogil=True)
def candidate_terms(p, ref, j, d, tangents):
    """The cached terms of each point's candidates for :func:`nearest_two`.

    Parameters
    ----------
    p : ndarray of float64, shape (M, 3)
        Points at the base slide.
    ref : ndarray of float64, shape (N, 3)
        Reference points.
    j, d : ndarray, shape (M, K)
        The KD-tree's ``k`` nearest reference points of each point and their distances
        (``inf`` and index ``N`` where there are fewer within reach).
    tangents : ndarray of float64, shape (M, 3)
        Unit slide directions.

    Returns
    -------
    cand : ndarray of int64, shape (M, K)
        The candidates (0 where none).
    a, b : ndarray of float64, shape (M, K)
        ``|p - c|^2`` (``inf`` where none) and ``2 t . (p - c)``.
    """
    m, k = j.shape
    cand = np.zeros((m, k), dtype=np.int64)
    a = np.empty((m, k))
    b = np.empty((m, k))
    for i in range(m):
        for c in range(k):
            missing = not np.isfinite(d[i, c])
            q = 0 if missing else j[i, c]
            cand[i, c] = q
            o0 = p[i, 0] - ref[q, 0]
            o1 = p[i, 1] - ref[q, 1]
            o2 = p[i, 2] - ref[q, 2]
            a[i, c] = np.inf if missing else o0 * o0 + o1 * o1 + o2 * o2
            b[i, c] = 2.0 * (o0 * tangents[i, 0] + o1 * tangents[i, 1] + o2 * tangents[i, 2])
    return cand, a, b
