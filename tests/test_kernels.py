"""The compiled cylinder statistics equal their NumPy formulation bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef.deformation import cylinders
from tunneldef.deformation.kernels import cylinder_stats


def _moments(group, values, keep, ngroups):
    w = keep.astype(np.float64)
    n = np.bincount(group, weights=w, minlength=ngroups)
    mean = np.bincount(group, weights=w * values, minlength=ngroups) / np.maximum(n, 1.0)
    dev = values - mean[group]
    var = np.bincount(group, weights=w * dev * dev, minlength=ngroups) / np.maximum(n - 1.0, 1.0)
    return n, mean, np.sqrt(var), dev


def _numpy_stats(pts, pt_normals, cores, normals, splits, idx, d2, radius, depth, trim_z):
    """The statistics as whole-array NumPy passes over the flat (core, point) pairs."""
    group = np.repeat(np.arange(len(cores)), np.diff(splits))
    cn = normals[group]
    a = np.einsum("ij,ij->i", pts[idx] - cores[group], cn)
    inside = (np.abs(a) <= depth) & (d2 - a * a <= radius * radius)
    group, idx, a, cn = group[inside], idx[inside], a[inside], cn[inside]
    same = np.einsum("ij,ij->i", pt_normals[idx], cn) >= cylinders._COS_MAX_ANGLE
    group, idx, a, cn = group[same], idx[same], a[same], cn[same]
    values, ng, k, floor = a.astype(np.float64), len(cores), 3.0, 0.005
    keep = np.ones(values.shape[0], dtype=bool)
    _, _, std, dev = _moments(group, values, keep, ng)
    keep = np.abs(dev) <= np.maximum(k * std[group], floor)
    _, mean, spread, dev = _moments(group, values, keep, ng)
    keep = np.abs(dev) <= np.maximum(k * spread[group], floor)
    if trim_z > 0:
        keep &= dev >= -trim_z * spread[group]
    _, _, std, dev = _moments(group, values, keep, ng)
    keep &= np.abs(dev) <= np.maximum(k * std[group], floor)
    n, mean, _, _ = _moments(group, values, keep, ng)
    mean[n < 1] = np.nan
    spread[n < 1] = np.nan
    g, w = group[keep], np.maximum(n, 1.0)
    across = pts[idx[keep]] - cores[g] - a[keep, None] * cn[keep]
    centre = np.stack([np.bincount(g, weights=across[:, i], minlength=ng) / w
                       for i in range(3)], axis=1)
    centre[n < 1] = np.nan
    return mean, spread, n.astype(np.int32), centre


def _scene(seed: int):
    """A rough wall with pipes in front of it, stray returns and a few far cores."""
    rng = np.random.default_rng(seed)
    m = 60_000
    pts = np.c_[rng.uniform(0, 4, m), rng.uniform(0, 3, m), rng.normal(0, 0.012, m)]
    pipe = rng.random(m) < 0.08
    pts[pipe, 2] -= rng.uniform(0.05, 0.25, pipe.sum())  # in front of the rock
    stray = rng.random(m) < 0.01
    pts[stray, 2] += rng.normal(0, 0.2, stray.sum())
    pt_normals = np.tile([0.0, 0.0, 1.0], (m, 1)) + rng.normal(0, 0.2, (m, 3))
    pt_normals[rng.random(m) < 0.05] *= -1  # another surface's points
    pt_normals /= np.linalg.norm(pt_normals, axis=1, keepdims=True)
    cores = np.c_[rng.uniform(0, 4, 900), rng.uniform(0, 3, 900), rng.normal(0, 0.01, 900)]
    cores[:7] += [0.0, 0.0, 5.0]  # nothing within reach
    cores[7:20, 0] = -0.1  # at the edge of the scan: one-sided cylinders
    normals = np.tile([0.0, 0.0, 1.0], (900, 1)) + rng.normal(0, 0.05, (900, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return (pts.astype(np.float32), pt_normals.astype(np.float32), cores.astype(np.float32),
            normals.astype(np.float32))


@pytest.mark.parametrize(("seed", "trim_z"), [(0, 0.0), (1, 0.0), (2, 0.84)])
def test_cylinder_stats_equal_the_numpy_formulation(seed: int, trim_z: float) -> None:
    pts, pt_normals, cores, normals = _scene(seed)
    radius, depth = 0.2, 0.3
    epoch = cylinders._Epoch(pts, pt_normals, float(np.hypot(radius, depth)))
    splits, idx, d2 = epoch.ball_csr(cores, float(np.hypot(radius, depth)))
    got = cylinder_stats(pts, pt_normals, cores, normals, splits, idx, d2, radius, depth,
                         cylinders._COS_MAX_ANGLE, 3.0, 0.005, trim_z)
    want = _numpy_stats(pts, pt_normals, cores, normals, splits, idx.astype(np.intp), d2,
                        radius, depth, trim_z)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)
    mean, spread, count, centre = got
    assert np.all(count[:7] == 0) and np.isnan(mean[:7]).all() and np.isnan(centre[:7]).all()
    ok = count > 0
    assert ok.sum() > 850
    # the rock's surface at 0 within the noise, pipes and strays clipped away
    assert abs(float(np.median(mean[ok]))) < 0.003
    assert 0.008 < float(np.median(spread[ok])) < 0.04  # the noise, widened by pipe backs
    # cylinders at the scan's edge are covered on one side only
    assert float(np.median(centre[7:20, 0])) > 0.05
    if trim_z == 0.0:  # what _epoch_stats gives is the kernel's
        via = cylinders._epoch_stats(epoch, cores, normals, radius, depth)
        for g, w in zip(via, got, strict=True):
            np.testing.assert_array_equal(g, w)


def test_slide_kernels_equal_the_numpy_formulation() -> None:
    # the along-axis slide's two compiled loops give what an argpartition over the candidates
    # (bit for bit) and the gathered point-to-plane residuals (to the last bits) give
    from tunneldef.registration.kernels import nearest_two, slide_residuals

    rng = np.random.default_rng(3)
    m, k, n = 5_000, 8, 3_000
    a = rng.uniform(0.0, 0.09, (m, k))
    a[rng.random((m, k)) < 0.1] = np.inf  # candidates out of reach
    a[:50] = np.inf  # points with none at all
    a[50:60, 1] = a[50:60, 0]  # exact ties
    b = rng.normal(0.0, 0.2, (m, k))
    for step in (0.0, 0.0031, -0.02):
        dmin, second, best = nearest_two(a, b, step)
        d2 = a + step * (b + step)
        order = np.argpartition(d2, 1, axis=1)[:, :2]
        two = np.sqrt(np.maximum(np.take_along_axis(d2, order, axis=1), 0.0))
        np.testing.assert_array_equal(dmin, two[:, 0])
        np.testing.assert_array_equal(second, two[:, 1])
        finite = np.isfinite(dmin)
        # the chosen column holds the smallest value (which of tied columns is immaterial)
        np.testing.assert_array_equal(d2[np.arange(m), best][finite], d2.min(axis=1)[finite])
    assert np.isinf(dmin[:50]).all() and (best[:50] == 0).all()

    xyz, tan = rng.normal(size=(m, 3)), rng.normal(size=(m, 3))
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    ref = rng.normal(size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    ref_pn = np.hstack([ref, nrm])
    j = rng.integers(0, n, m)
    ok = rng.random(m) < 0.7
    delta = 0.0123
    r, a_n = slide_residuals(xyz, tan, ref_pn, np.flatnonzero(ok), j, delta)
    matched = ref_pn[j[ok]]
    want_r = np.einsum("ij,ij->i", matched[:, 3:], xyz[ok] + delta * tan[ok] - matched[:, :3])
    want_a = np.einsum("ij,ij->i", matched[:, 3:], tan[ok])
    # einsum's own order of the three products is unspecified: equal to the last bits
    np.testing.assert_allclose(r, want_r, rtol=4e-16, atol=4e-16)
    np.testing.assert_allclose(a_n, want_a, rtol=4e-16, atol=4e-16)


def _numpy_project(cl, p):
    """The foot points as whole-array NumPy passes (the formulation the kernel replaced)."""
    t, lat, ver = cl._frames()
    _, i = cl._tree().query(p)
    u = np.einsum("ij,ij->i", p - cl.points[i], t[i])
    s = cl.chainage[i] + u
    j = np.clip(np.round(np.interp(s, cl.chainage, np.arange(len(cl.chainage)))), 0,
                len(cl.chainage) - 1).astype(np.intp)
    d = p - cl.points[j]
    u = np.einsum("ij,ij->i", d, t[j])
    d -= u[:, None] * t[j]
    scale = 1.0 - np.einsum("ij,ij->i", d, cl._curvature()[j])
    beyond = ((j == 0) & (u < 0)) | ((j == len(cl.chainage) - 1) & (u > 0))
    scale[beyond] = 1.0
    s = cl.chainage[j] + u / np.maximum(scale, 0.1)
    return s, np.einsum("ij,ij->i", d, lat[j]), np.einsum("ij,ij->i", d, ver[j]), j


def test_projection_kernel_equals_the_numpy_formulation() -> None:
    # a bend, points around it and beyond both ends, some exactly on samples and half-way
    # between two (where the rounding to the nearest sample must match NumPy's)
    from tunneldef.curve import Centerline
    from tunneldef.curve_kernels import _sample_index

    a = np.linspace(0.0, np.pi / 2, 400)
    cl = Centerline.from_polyline(np.c_[30 * np.sin(a), 30 * (1 - np.cos(a)), 0.02 * a * 30],
                                  step=0.05)
    rng = np.random.default_rng(5)
    s0 = rng.uniform(-3.0, cl.length + 3.0, 20_000)
    pts = cl.point_at(s0) + rng.normal(0.0, 1.5, (20_000, 3))
    pts[:50] = cl.points[rng.integers(0, len(cl.points), 50)]
    got = cl.project(pts)
    s, lateral, vertical, j = _numpy_project(cl, pts)
    np.testing.assert_allclose(got.chainage, s, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.lateral, lateral, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.vertical, vertical, rtol=0, atol=1e-12)
    ch = cl.chainage
    probe = np.r_[ch[[0, 1, -2, -1]], 0.5 * (ch[:-1] + ch[1:]), -1.0, ch[-1] + 1.0,
                  rng.uniform(0.0, cl.length, 2000)]
    want = np.clip(np.round(np.interp(probe, ch, np.arange(len(ch)))), 0, len(ch) - 1)
    assert [_sample_index(x, ch) for x in probe] == want.astype(int).tolist()


def test_candidate_terms_equal_the_numpy_formulation() -> None:
    # the sliding points' cached candidate terms, without the (M, K, 3) offsets NumPy needs
    from scipy.spatial import cKDTree

    from tunneldef.registration.kernels import candidate_terms

    rng = np.random.default_rng(4)
    ref = rng.uniform(0.0, 2.0, (4_000, 3))
    p = rng.uniform(-0.5, 2.5, (3_000, 3))  # some beyond the reference: fewer candidates
    tan = rng.normal(size=(3_000, 3))
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    d, j = cKDTree(ref).query(p, k=8, distance_upper_bound=0.2)
    missing = ~np.isfinite(d)
    assert missing.any() and (~missing).any()
    cand, a, b = candidate_terms(p, ref, j.astype(np.int64), d, tan)
    want_cand = np.where(missing, 0, j)
    off = p[:, None, :] - ref[want_cand]
    want_a = np.where(missing, np.inf, np.einsum("ijk,ijk->ij", off, off))
    want_b = 2.0 * np.einsum("ijk,ik->ij", off, tan)
    np.testing.assert_array_equal(cand, want_cand)
    np.testing.assert_array_equal(np.isinf(a), missing)
    np.testing.assert_allclose(a[~missing], want_a[~missing], rtol=4e-16, atol=4e-16)
    np.testing.assert_allclose(b, want_b, rtol=4e-16, atol=1e-15)


def test_slides_run_side_by_side_only_within_their_memory_budget() -> None:
    from tunneldef.registration.axial import (
        _SLIDE_BYTES_PER_POINT,
        SLIDE_MEMORY_BUDGET,
        concurrent_slides,
    )

    assert concurrent_slides(90_000, 2) == 2  # a 60 m survey's slides
    assert concurrent_slides(525_000, 2) == 2  # 350 m
    assert concurrent_slides(1_500_000, 2) == 1  # 1 km: one at a time
    assert concurrent_slides(10, 1) == 1 and concurrent_slides(10**9, 8) == 1
    for n in (60_000, 525_000, 1_500_000):
        k = concurrent_slides(n, 64)
        assert k == 1 or k * n * _SLIDE_BYTES_PER_POINT <= SLIDE_MEMORY_BUDGET
