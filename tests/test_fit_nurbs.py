"""NURBS evaluation with scipy against geomdl, and the bounds on what a centreline may cost."""

from __future__ import annotations

import time

import numpy as np
import pytest
from geomdl import NURBS, helpers

from tunneldef.centerline.fit import (
    LENGTH_FACTOR,
    LENGTH_MARGIN,
    MAX_EVAL_POINTS,
    _design_matrix,
    _weighted_lstsq,
    fit_centerline,
    fit_cubic_bspline,
    fit_nurbs,
    fit_stiffest,
    nurbs_points,
)
from tunneldef.errors import ImplausibleExtentError, InvalidCloudError, TunnelDefError


def _random_curve(rng: np.random.Generator, degree: int, n_ctrl: int) -> NURBS.Curve:
    inner = np.sort(rng.random(n_ctrl - degree - 1))
    knots = np.concatenate([np.zeros(degree + 1), inner, np.ones(degree + 1)])  # clamped
    curve = NURBS.Curve()
    curve.degree = degree
    curve.ctrlpts = (rng.normal(0.0, 50.0, (n_ctrl, 3)) + [4.5e5, 5.6e6, 400.0]).tolist()
    curve.weights = rng.uniform(0.3, 3.0, n_ctrl).tolist()  # rational: weights not all 1
    curve.knotvector = knots.tolist()
    return curve


@pytest.mark.parametrize(
    ("degree", "n_ctrl", "seed"), [(2, 7, 0), (3, 12, 1), (3, 30, 2), (4, 9, 3)]
)
def test_scipy_evaluation_equals_geomdl(degree: int, n_ctrl: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    curve = _random_curve(rng, degree, n_ctrl)
    u = np.concatenate([[0.0, 1.0], rng.random(200), np.unique(curve.knotvector)])
    ref = np.array(curve.evaluate_list(u.tolist()))
    got = nurbs_points(
        degree,
        np.array(curve.knotvector),
        np.array(curve.ctrlpts),  # cartesian; geomdl keeps P * w in ctrlptsw
        np.array(curve.weights),
        u,
    )
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


def test_design_matrix_equals_geomdl_basis() -> None:
    rng = np.random.default_rng(4)
    degree, n_ctrl = 3, 15
    curve = _random_curve(rng, degree, n_ctrl)
    knots = list(curve.knotvector)
    t = np.concatenate([[0.0, 1.0], rng.random(100)])
    ref = np.zeros((len(t), n_ctrl))
    for k, x in enumerate(t):
        span = helpers.find_span_linear(degree, knots, n_ctrl, float(x))
        ref[k, span - degree : span + 1] = helpers.basis_function(degree, knots, span, float(x))
    got = _design_matrix(degree, knots, n_ctrl, t).toarray()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


def test_fit_keeps_geomdl_reference_curve() -> None:
    rng = np.random.default_rng(5)
    s = np.arange(0.0, 40.0, 0.5)
    q = np.c_[s, 0.01 * s**1.5, np.zeros_like(s)] + rng.normal(0, 0.005, (len(s), 3))
    fit = fit_nurbs(q, params=s, n_ctrl=12)
    u = np.linspace(0.0, 1.0, 57)
    np.testing.assert_allclose(
        fit.evaluate(u), np.array(fit.curve.evaluate_list(u.tolist())), rtol=0, atol=1e-9
    )
    assert fit.degree == 3


def _arc(s: np.ndarray, radius: float = 150.0) -> np.ndarray:
    th = s / radius
    return np.c_[radius * np.sin(th), radius * (1 - np.cos(th)), 0.02 * s]


def test_300_m_centreline_is_fast_and_sampled_by_its_own_length() -> None:
    rng = np.random.default_rng(6)
    s = np.arange(0.0, 300.0001, 0.5)
    q = _arc(s) + rng.normal(0, 0.01, (len(s), 3))
    start = time.perf_counter()
    cl, fit = fit_centerline(q, params=s, ctrl_spacing=2.0, sample_step=0.05)
    assert time.perf_counter() - start < 2.0  # 0.2-0.6 s before (geomdl), 6 ms now
    true_length = float(
        np.sum(np.linalg.norm(np.diff(_arc(np.linspace(0, 300, 30001)), axis=0), axis=1))
    )
    assert cl.length == pytest.approx(true_length, abs=0.1)
    assert len(cl.points) == int(np.ceil(cl.length / 0.05)) + 1
    assert cl.meta["eval_step_m"] == pytest.approx(0.025, rel=1e-2)
    assert fit.arc_length() == pytest.approx(cl.length, abs=1e-3)


def test_absurd_station_span_raises_at_once() -> None:
    # one slice 1.4e6 m down the axis (a stray point and an oversized extent): refuse, fast
    s = np.arange(0.0, 300.0001, 0.5)
    q = _arc(s)
    s_bad = s.copy()
    s_bad[-1] = 1.4e6
    start = time.perf_counter()
    with pytest.raises(ImplausibleExtentError, match="span of the slice stations") as info:
        fit_centerline(q, params=s_bad)
    assert time.perf_counter() - start < 0.5
    assert "\n" not in str(info.value)
    assert isinstance(info.value, TunnelDefError)
    with pytest.raises(ImplausibleExtentError):
        fit_cubic_bspline(q, params=s_bad)


def test_length_limit_is_factor_times_path_plus_margin() -> None:
    s = np.linspace(0.0, 20.0, 41)
    q = np.c_[s, np.zeros((41, 2))]
    limit = LENGTH_FACTOR * 20.0 + LENGTH_MARGIN
    fit_centerline(q, params=s * (limit - 0.01) / 20.0)  # just inside
    with pytest.raises(ImplausibleExtentError, match=f"limit {limit:.4g} m"):
        fit_centerline(q, params=s * (limit + 0.01) / 20.0)


def test_evaluation_count_is_capped() -> None:
    s = np.linspace(0.0, 300.0, 601)
    q = np.c_[s, np.zeros((601, 2))]
    cl, _ = fit_centerline(q, params=s, sample_step=300.0 / MAX_EVAL_POINTS)
    assert cl.meta["eval_step_m"] == pytest.approx(300.0 / (MAX_EVAL_POINTS - 1), rel=1e-3)


def test_non_finite_centres_are_refused() -> None:
    q = np.c_[np.arange(10.0), np.zeros((10, 2))]
    q[3, 1] = np.nan
    with pytest.raises(InvalidCloudError, match="finite"):
        fit_nurbs(q)
    with pytest.raises(InvalidCloudError, match="non-decreasing"):
        fit_nurbs(np.nan_to_num(q), params=np.arange(10.0)[::-1])


def test_banded_solution_equals_dense_least_squares() -> None:
    rng = np.random.default_rng(7)
    s = np.sort(rng.uniform(0.0, 80.0, 160))
    q = _arc(s) + rng.normal(0, 0.01, (160, 3))
    w = rng.uniform(0.0, 1.0, 160)
    knots = [0.0] * 4 + list(np.linspace(0, 1, 32)[1:-1]) + [1.0] * 4
    t = (s - s[0]) / (s[-1] - s[0])
    a = _design_matrix(3, knots, 34, t)
    sw = np.sqrt(w)[:, None]
    dense, *_ = np.linalg.lstsq(a.toarray() * sw, q * sw, rcond=None)
    np.testing.assert_allclose(_weighted_lstsq(a, q, w, 3), dense, rtol=0, atol=1e-8)
    w[(s > 30) & (s < 45)] = 0.0  # control points without data: the dense fallback
    sw = np.sqrt(w)[:, None]
    dense, *_ = np.linalg.lstsq(a.toarray() * sw, q * sw, rcond=None)
    np.testing.assert_allclose(_weighted_lstsq(a, q, w, 3), dense, rtol=0, atol=1e-8)


def test_max_length_from_the_cloud() -> None:
    s = np.arange(0.0, 100.0001, 0.5)
    q = _arc(s)
    cl, _ = fit_centerline(q, params=s, max_length=101.0)
    assert cl.length == pytest.approx(100.0, abs=0.05)
    with pytest.raises(ImplausibleExtentError, match="at most 99 m"):
        fit_centerline(q, params=s, max_length=99.0)
    far = q.copy()
    far[-1] += [0.0, 0.0, 300.0]  # one centre 300 m off: its path is too long for the cloud
    with pytest.raises(ImplausibleExtentError, match="the centres' path"):
        fit_centerline(far, params=s, max_length=150.0)


# --------------------------------------------------------------------------- stiffest fit


def _fillet_path(s: np.ndarray, radius: float = 15.0, straight: float = 30.0) -> np.ndarray:
    """Points at arc length ``s`` on a straight, a 90 degree fillet of ``radius``, a straight."""
    arc = 0.5 * np.pi * radius
    out = np.zeros((len(s), 3))
    a = s < straight
    out[a, 0] = s[a]
    b = (s >= straight) & (s < straight + arc)
    t = (s[b] - straight) / radius
    out[b, 0] = straight + radius * np.sin(t)
    out[b, 1] = radius * (1 - np.cos(t))
    c = s >= straight + arc
    out[c, 0] = straight + radius
    out[c, 1] = radius + (s[c] - straight - arc)
    return out


def test_the_stiffest_fit_averages_relief_but_keeps_a_bend() -> None:
    rng = np.random.default_rng(3)
    # a straight drift whose centres follow +-12 mm of rock relief (6 m waves) and 8 mm noise
    s = np.arange(0.0, 80.0, 0.5)
    wave = 0.012 * np.sin(2 * np.pi * s / 6.0)
    centres = np.stack([s, wave + rng.normal(0, 0.008, len(s)), np.zeros(len(s))], axis=1)
    cl, _ = fit_stiffest(centres, params=s)
    flex, _ = fit_centerline(centres, params=s, ctrl_spacing=2.0)
    assert cl.meta["ctrl_spacing_m"] == 8.0
    off = np.abs(cl.points[:, 1][(cl.points[:, 0] > 2) & (cl.points[:, 0] < 78)])
    off_flex = np.abs(flex.points[:, 1][(flex.points[:, 0] > 2) & (flex.points[:, 0] < 78)])
    assert np.percentile(off, 95) < 0.006 < np.percentile(off_flex, 95)
    # the uncertainty figure is the centres' local scatter about the flexible curve
    assert cl.meta["centre_scatter_p95_m"] == pytest.approx(
        np.percentile(flex.project(centres).distance, 95))
    # a 15 m radius bend: an 8 m curve would cut it by about 15 mm, so a flexible one is kept
    s = np.arange(0.0, 30.0 + 0.5 * np.pi * 15.0 + 30.0, 0.5)
    centres = _fillet_path(s) + rng.normal(0, 0.005, (len(s), 3)) * [1, 1, 0]
    cl, _ = fit_stiffest(centres, params=s)
    assert cl.meta["ctrl_spacing_m"] < 8.0 and cl.meta["systematic_misfit_m"] <= 0.01
    truth = _fillet_path(np.arange(1.0, s[-1] - 1.0, 0.1))
    assert np.percentile(cl.project(truth).distance, 95) < 0.01
