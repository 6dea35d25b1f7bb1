"""The field of core deformations on the shell (the robust estimator's last steps, :mod:`.robust`).

* :func:`_sharpen`: the smoothing bias of the cylinders taken out where they are dense
  (an unsharp mask, its strength from :func:`_sharpening`);
* :func:`_pool`: sparse cores pooled with their neighbours, bias-corrected (Richardson);
* :func:`_assign_cores` and :func:`_spread`: the core each compared point belongs to, and the
  Gaussian interpolation of the core values at every point, on its own surface only
  (:func:`_surface_weights`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .cylinders import _CHUNK, _COS_MAX_ANGLE, _RadiusIndex

_MAX_VARIATION = 0.02  # a plane with 2 cm noise at a 0.3 m radius: ~0.005; a corner: > 0.05
_K_SPREAD = 6  # cores interpolated at each point
# bias correction (an unsharp mask of the core field, see _sharpen): its full strength takes
# a noise-free 30 mm synthetic sag (1 m wide) from 6.4 % low at its peak to within 1 %; it
# amplifies a core's noise by about 1 + 0.4 beta (measured), so it is applied only as far as
# the core's standard error stays within 2 mm: fully at the handheld scanner's density
# (2,600 points/m^2, about 1.2 mm), not at all on sparse scans (400 points/m^2, about 3 mm)
_SHARPEN = 1.0
_SHARPEN_GAIN = 0.4
_SHARPEN_SE = 0.002
# pooling on sparse scans (see _pool): a core whose plain standard error exceeds _POOL_SE is
# blended, fully from _POOL_SE + _POOL_RAMP, into a bias-corrected Gaussian mean of the cores
# around it on its surface. On the synthetic pairs (+-3 cm noise, 15 mm sag, perfect
# registration, 8 seeds at 400 points/m^2) it takes the noise floor from 2.0 to 1.7 mm and
# recall at 10 mm from 0.80 to 0.89 (lowest seed 0.61 to 0.76); at 1,000 points/m^2 the
# lowest recall of 3 seeds from 0.86 to 0.90; at 2,600 points/m^2 it changes nothing that
# shows. Starting at 2 mm (where sharpening stops) left 1,000 points/m^2 between the two.
_POOL_SE = 0.0015
_POOL_RAMP = 0.0005
_POOL_SCALE = 1.0  # sigma of the finer pooled mean, in cylinder radii; 0.75 kept a 1.2 m wide
# bulge 3 mm deeper (30.8 against 27.9 mm of a true 35.8 mm) but the noise floor only to 1.95 mm
_SPREAD_SIGMA = 0.6  # of the core spacing: Gaussian weights of the interpolation
_SPREAD_PLANE = 0.1  # a core's plane must pass this close to a point to be interpolated, m
_K_ASSIGN = 8  # candidate planar cores for a point of a corner core


def _assign_cores(
    pts: np.ndarray,
    inverse: np.ndarray,
    cores: np.ndarray,
    normals: np.ndarray,
    variation: np.ndarray,
    valid: np.ndarray,
    *,
    reach: float,
    workers: int,
) -> np.ndarray:
    """Core whose value each compared point takes.

    A point keeps its voxel's core unless that core straddles two surfaces (surface variation
    above ``_MAX_VARIATION``, e.g. a voxel on a wall-roof corner, whose tilted cylinder mixes
    both): then it takes, among the ``_K_ASSIGN`` nearest planar cores within ``reach``, the one
    whose plane passes closest to it, if that plane passes within ``_SPREAD_PLANE`` of it (the
    test :func:`_spread` applies to its neighbours); otherwise it keeps its own core, whose
    value may be none. A plane farther off is another surface (the floor 0.65 m below the
    wall behind a row of pipes), and its value is not the point's.
    """
    planar = valid & (variation <= _MAX_VARIATION)
    corner = np.isfinite(variation) & (variation > _MAX_VARIATION)  # not: no reference near
    point_core = inverse.copy()
    move = np.flatnonzero(corner[inverse])
    if move.size == 0 or not planar.any():
        return point_core
    ids = np.flatnonzero(planar)
    k = min(_K_ASSIGN, ids.size)
    dist, j = cKDTree(cores[ids]).query(pts[move], k=k, distance_upper_bound=reach, workers=workers)
    dist, j = dist.reshape(len(move), k), j.reshape(len(move), k)
    found = np.isfinite(dist)
    jj = ids[np.where(found, j, 0)]
    res = np.abs(np.einsum("ijk,ijk->ij", pts[move][:, None, :] - cores[jj], normals[jj]))
    res[~found] = np.inf
    best = np.argmin(res, axis=1)
    ok = res[np.arange(len(move)), best] <= _SPREAD_PLANE
    point_core[move[ok]] = jj[ok, best[ok]]
    return point_core


def _surface_weights(
    q: np.ndarray,
    own: np.ndarray,
    cores: np.ndarray,
    normals: np.ndarray,
    ids: np.ndarray,
    *,
    spacing: float,
    k: int,
    workers: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian weights (sigma ``_SPREAD_SIGMA`` core spacings) of the cores ``ids`` among the
    ``k`` nearest within ``1.5 * spacing`` of each position ``q`` that lie on the surface of
    its own core ``own``: normals within ``_MAX_ANGLE_DEG``, plane within ``_SPREAD_PLANE`` of
    the position; the own core itself is left out.

    Returns the core indices ``jj`` (Q, k) and their weights ``w`` (Q, k), 0 where unused.
    """
    k = min(k, ids.size)
    dist, j = cKDTree(cores[ids]).query(q, k=k, distance_upper_bound=1.5 * spacing, workers=workers)
    dist, j = dist.reshape(len(q), k), j.reshape(len(q), k)
    found = np.isfinite(dist)
    jj = ids[np.where(found, j, 0)]
    # float32 products: normals are unit vectors and the plane offsets are taken about each
    # core (``q.n - c.n``, float64), so single precision loses nothing that matters
    n32 = normals.astype(np.float32)
    nj = n32[jj]
    same = np.einsum("ijk,ik->ij", nj, n32[own]) >= _COS_MAX_ANGLE
    cn = np.einsum("ij,ij->i", cores, normals)
    plane = np.abs(np.einsum("ijk,ik->ij", nj, q) - cn[jj])
    del nj
    use = found & same & (plane <= _SPREAD_PLANE) & (jj != own[:, None])
    inv2s2 = -0.5 / (_SPREAD_SIGMA * spacing) ** 2
    w = np.where(use, np.exp(inv2s2 * np.where(found, dist, 0.0) ** 2), 0.0)
    return jj, w


def _spread(
    pts: np.ndarray,
    point_core: np.ndarray,
    cores: np.ndarray,
    normals: np.ndarray,
    variation: np.ndarray,
    d_core: np.ndarray,
    lod_core: np.ndarray,
    *,
    spacing: float,
    workers: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Deformation and level of detection of every point from the cores around it.

    Each point takes a Gaussian-weighted mean (sigma ``_SPREAD_SIGMA`` spacings) of the valid
    planar cores among its ``_K_SPREAD`` nearest within ``1.5 * spacing`` that lie on its own
    core's surface (see :func:`_surface_weights`), its own core always included: neighbouring
    cylinders overlap, so this interpolates the smooth field between cores rather than copying
    one core's value over its voxel, and averages some of the noise. The level of detection
    is the same weighted mean of the cores' levels (conservative: it ignores the averaging).
    """
    d = d_core[point_core].copy()
    lod = lod_core[point_core].copy()
    valid = np.isfinite(d_core) & (variation <= _MAX_VARIATION)
    ids = np.flatnonzero(valid)
    todo = np.flatnonzero(np.isfinite(d))
    if ids.size < 2 or todo.size == 0:
        return d, lod
    p = pts[todo]
    own = point_core[todo]
    jj, w = _surface_weights(
        p, own, cores, normals, ids, spacing=spacing, k=_K_SPREAD, workers=workers
    )
    use = w > 0
    off = p - cores[own]
    w_own = np.exp(-0.5 * np.einsum("ij,ij->i", off, off) / (_SPREAD_SIGMA * spacing) ** 2)
    total = w.sum(axis=1) + w_own
    d[todo] = (np.einsum("ij,ij->i", w, np.where(use, d_core[jj], 0.0)) + w_own * d[todo]) / total
    lod[todo] = (
        np.einsum("ij,ij->i", w, np.where(use, lod_core[jj], 0.0)) + w_own * lod[todo]
    ) / total
    return d, lod


def _sharpening(se: np.ndarray) -> np.ndarray:
    """Strength ``beta`` of the bias correction of each core from its standard error ``se``:
    as much of ``_SHARPEN`` as keeps the amplified error ``se * (1 + _SHARPEN_GAIN * beta)``
    within ``_SHARPEN_SE``; 0 where the cylinders are too sparse (or ``se`` is NaN)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        beta = np.clip((_SHARPEN_SE / se - 1.0) / _SHARPEN_GAIN, 0.0, _SHARPEN)
    beta[~np.isfinite(beta)] = 0.0
    return beta


def _sharpen(
    cores: np.ndarray,
    normals: np.ndarray,
    variation: np.ndarray,
    d_core: np.ndarray,
    beta: np.ndarray,
    *,
    spacing: float,
    workers: int,
) -> np.ndarray:
    """Core deformations with the smoothing bias taken out (an unsharp mask).

    The cylinder mean and the interpolation between cores both average the field over a
    patch, which reads a curved field low by about half its Laplacian times the patch's second
    moment: 6 % at the peak of a 1 m wide sag. The difference between a core and the
    Gaussian mean of its planar neighbours on the same surface (:func:`_surface_weights`)
    is proportional to that Laplacian, so ``d + beta * (d - neighbours)`` removes the bias at
    ``beta`` near 1 (calibrated on a noise-free synthetic sag), at the price of amplifying
    the core's noise by about ``1 + _SHARPEN_GAIN * beta``.
    """
    out = d_core.copy()
    valid = np.isfinite(d_core) & (variation <= _MAX_VARIATION)
    ids = np.flatnonzero(valid & (beta > 0))
    nb_ids = np.flatnonzero(valid)
    if ids.size == 0 or nb_ids.size < 2:
        return out
    jj, w = _surface_weights(
        cores[ids],
        ids,
        cores,
        normals,
        nb_ids,
        spacing=spacing,
        k=_K_SPREAD + 1,
        workers=workers,
    )
    total = w.sum(axis=1)
    ok = total > 0
    nb = np.einsum("ij,ij->i", w, np.where(w > 0, d_core[jj], 0.0))[ok] / total[ok]
    i = ids[ok]
    out[i] = d_core[i] + beta[i] * (d_core[i] - nb)
    return out


def _pool(
    cores: np.ndarray,
    normals: np.ndarray,
    variation: np.ndarray,
    d_core: np.ndarray,
    se: np.ndarray,
    *,
    sigma: float,
    base: float,
    overlap: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Deformations of the sparse cores pooled with their neighbours, bias-corrected.

    Each valid planar core whose standard error ``se`` exceeds ``_POOL_SE`` gets
    ``2 S1 - S2``, where ``S1`` and ``S2`` are Gaussian-weighted means of the valid planar
    cores on its surface (normals within ``_MAX_ANGLE_DEG``, planes within ``_SPREAD_PLANE``
    of it; itself included) with sigmas ``sigma`` and ``sqrt(2 sigma^2 + base)``. ``base``
    is the variance of the smoothing the cylinder mean and the interpolation already apply,
    so the two smoothings' total variances are ``T^2`` and ``2 T^2`` and the combination
    cancels their bias to second order (Richardson extrapolation; about 3 % of a 1 m wide
    sag's depth is left). Its standard error is ``sqrt(overlap * sum_j c_j^2 se_j^2)`` over
    the combination's weights ``c_j``, where ``overlap`` (the cores each cylinder covers)
    accounts for neighbouring cylinders sharing points.

    Returns the pooled cores' indices, their blend weights ``lam`` (0 at ``_POOL_SE``, 1 from
    ``_POOL_SE + _POOL_RAMP``), pooled deformations and standard errors.
    """
    valid = np.isfinite(d_core) & np.isfinite(se) & (variation <= _MAX_VARIATION)
    with np.errstate(invalid="ignore"):
        lam = np.clip((se - _POOL_SE) / _POOL_RAMP, 0.0, 1.0)
    todo = np.flatnonzero(valid & (lam > 0))
    ids = np.flatnonzero(valid)
    d_out, se_out = np.empty(todo.size), np.empty(todo.size)
    if todo.size == 0 or ids.size < 2:
        return todo[:0], lam[todo[:0]], d_out[:0], se_out[:0]
    s2 = float(np.sqrt(2.0 * sigma**2 + base))
    reach = 3.0 * s2
    index = _RadiusIndex(cores[ids], reach)
    cn = np.einsum("ij,ij->i", cores, normals)
    for start in range(0, todo.size, _CHUNK):
        sl = slice(start, min(start + _CHUNK, todo.size))
        t = todo[sl]
        g, j, d2 = index.ball(cores[t], reach)
        j = ids[j]
        own = t[g]
        same = np.einsum("ij,ij->i", normals[j], normals[own]) >= _COS_MAX_ANGLE
        near = np.abs(np.einsum("ij,ij->i", normals[j], cores[own]) - cn[j]) <= _SPREAD_PLANE
        keep = same & near
        g, j, d2 = g[keep], j[keep], d2[keep].astype(np.float64)
        w1 = np.exp(-0.5 * d2 / sigma**2)
        w2 = np.exp(-0.5 * d2 / s2**2)
        w1 /= np.bincount(g, w1, len(t))[g]
        w2 /= np.bincount(g, w2, len(t))[g]
        c = 2.0 * w1 - w2
        d_out[sl] = np.bincount(g, c * d_core[j], len(t))
        se_p = np.sqrt(overlap * np.bincount(g, c**2 * se[j] ** 2, len(t)))
        se_out[sl] = np.minimum(se_p, se[t])
    return todo, lam[todo], d_out, se_out
