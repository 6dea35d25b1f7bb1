"""NURBS centreline through the slice centres (paper §3.1.4).

The paper makes every slice centre a control point of a cubic NURBS curve. A curve shaped by
its control points follows their noise (a few millimetres to centimetres per slice), so here the
centres are *data* and the curve is a least-squares cubic NURBS with fewer control points than
centres (The NURBS Book, 2nd ed., §9.4.1):

* parameters: the centres' along-axis stations, i.e. chord length along the axis (the chainage
  of the previous pass once the axis is curved), normalised to [0, 1];
* knots: averaged over the parameters (NURBS Book eq. 9.68-9.69,
  ``geomdl.fitting.compute_knot_vector2``), so they are non-uniform and every knot span holds
  data: where slices are missing (a chamber, a blind cone under a scanner) the span simply
  stretches across the gap instead of letting the curve wiggle in it;
* weights: each centre has a data weight, its "adhesion" in the paper's words, computed by
  iteratively reweighted least squares (Huber, then Tukey), so a bad centre that passed the
  per-slice checks cannot pull the curve; the control-point weights of the rational curve are 1 (a
  centreline has no conic sections that would need other weights) and are kept in the meta
  data with the knots and control points;
* the ends are free (not clamped to the first and last noisy centres).

The knots come from geomdl and a ``geomdl.NURBS.Curve`` is kept as the reference object, but
the curve is evaluated with :class:`scipy.interpolate.BSpline` (a rational B-spline is the
B-spline of the weighted control points divided by the B-spline of the weights), vectorised in
C, and resampled as a :class:`~tunneldef.curve.Centerline`. A station span or a
curve far longer than the path through the centres raises
:class:`~tunneldef.errors.ImplausibleExtentError` at once (stray points or a wrong unit)
instead of being sampled for minutes, and the number of evaluations is capped.

One idea at this length: one least-squares NURBS fit with its knots, banded solve, evaluation
and the plausibility bounds that guard it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from geomdl import NURBS
from geomdl.fitting import compute_knot_vector2
from scipy.interpolate import BSpline
from scipy.linalg import LinAlgError, solveh_banded
from scipy.sparse import csr_array

from ..curve import Centerline
from ..errors import ImplausibleExtentError, InvalidCloudError, NotATunnelError

__all__ = [
    "NurbsFit",
    "fit_nurbs",
    "fit_centerline",
    "fit_stiffest",
    "systematic_misfit",
    "fit_line",
    "fit_cubic_bspline",
    "nurbs_points",
    "check_curve_length",
    "MAX_EVAL_POINTS",
    "LENGTH_FACTOR",
    "LENGTH_MARGIN",
]

#: Most points one curve is evaluated at (50 km at the default 2.5 cm); past it the evaluation
#: step grows and the centreline's meta data say so (``eval_step_m``).
MAX_EVAL_POINTS = 2_000_000
#: A curve or station span may be at most ``LENGTH_FACTOR`` times the path through its centres
#: plus ``LENGTH_MARGIN`` metres (ours: a fitted centreline is as long as that path to within
#: centimetres; 1.5 x + 10 m leaves room for gaps in bends and slice noise, while a stray point
#: or a wrong unit makes it hundreds of times longer).
LENGTH_FACTOR = 1.5
LENGTH_MARGIN = 10.0


def nurbs_points(
    degree: int,
    knots: np.ndarray,
    ctrlpts: np.ndarray,
    weights: np.ndarray,
    params: np.ndarray,
) -> np.ndarray:
    """Points of a NURBS curve at many parameters, vectorised (scipy, in C).

    Parameters
    ----------
    degree : int
        Curve degree.
    knots : ndarray, shape (C + degree + 1,)
        Clamped, non-decreasing knot vector.
    ctrlpts : ndarray, shape (C, D)
        Control points (metres for a centreline).
    weights : ndarray, shape (C,)
        Positive control-point weights.
    params : ndarray, shape (M,)
        Parameters, clipped to ``[knots[degree], knots[-degree - 1]]``.

    Returns
    -------
    ndarray, shape (M, D)
        ``sum_i N_i(t) w_i P_i / sum_i N_i(t) w_i``; equals ``geomdl.NURBS.Curve`` evaluation
        to rounding (tested to 1e-9 m).
    """
    t = np.asarray(knots, dtype=np.float64)
    c = np.asarray(ctrlpts, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    u = np.clip(np.asarray(params, dtype=np.float64), t[degree], t[-degree - 1])
    h = BSpline(t, np.column_stack([c * w[:, None], w]), degree, extrapolate=False)(u)
    return h[:, :-1] / h[:, -1:]


def _check_max_length(lengths: dict[str, float], max_length: float | None) -> None:
    if max_length is None:
        return
    for what, length in lengths.items():
        if not length <= max_length:
            raise ImplausibleExtentError(
                f"{what} is {length:.4g} m but the cloud holds at most {max_length:.4g} m of "
                "tunnel; remove stray points (tunneldef.outliers.remove_strays) or check the units"
            )


def _path_length(q: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(q, axis=0), axis=1)))


def check_curve_length(length: float, path: float, what: str) -> None:
    """Raise if ``length`` is absurd against ``path``, the length of the path through the data.

    Parameters
    ----------
    length : float
        Length to check (a curve's arc length or a span of stations), metres.
    path : float
        Length of the polyline through the slice centres, metres.
    what : str
        What ``length`` is, for the message.

    Raises
    ------
    ImplausibleExtentError
        If ``length`` is not finite or exceeds ``LENGTH_FACTOR * path + LENGTH_MARGIN``.
    """
    limit = LENGTH_FACTOR * path + LENGTH_MARGIN
    if not np.isfinite(length) or length > limit:
        raise ImplausibleExtentError(
            f"{what} is {length:.4g} m but the slice centres lie along only {path:.4g} m "
            f"(limit {limit:.4g} m); remove stray points (tunneldef.outliers.remove_strays) "
            "or check the units"
        )


@dataclass(frozen=True)
class NurbsFit:
    """A least-squares NURBS curve through centres.

    Attributes
    ----------
    curve : geomdl.NURBS.Curve
        The fitted curve (parameter in [0, 1]).
    ctrlpts : ndarray, shape (C, 3)
    weights : ndarray, shape (C,)
        Control-point weights of the rational curve.
    knots : ndarray, shape (C + degree + 1,)
    params : ndarray, shape (K,)
        Parameter of each centre.
    data_weights : ndarray, shape (K,)
        Final robust weight of each centre (1 = fully trusted, -> 0 = ignored).
    residuals : ndarray, shape (K,)
        Distance of each centre from the curve at its parameter, metres.
    """

    curve: NURBS.Curve
    ctrlpts: np.ndarray
    weights: np.ndarray
    knots: np.ndarray
    params: np.ndarray
    data_weights: np.ndarray
    residuals: np.ndarray

    @property
    def degree(self) -> int:
        """Curve degree."""
        return len(self.knots) - len(self.ctrlpts) - 1

    def evaluate(self, params: np.ndarray) -> np.ndarray:
        """Curve points (M, 3) at parameters in [0, 1] (clipped), metres."""
        return nurbs_points(self.degree, self.knots, self.ctrlpts, self.weights, params)

    def arc_length(self, n: int | None = None) -> float:
        """Length of the curve, metres, from ``n`` evaluations (default 32 per control point,
        at least 1024, at most ``MAX_EVAL_POINTS``); a slight underestimate."""
        n = n or int(np.clip(32 * len(self.ctrlpts), 1024, MAX_EVAL_POINTS))
        return _path_length(self.evaluate(np.linspace(0.0, 1.0, n)))


def _design_matrix(degree: int, knots: list[float], n_ctrl: int, params: np.ndarray) -> csr_array:
    """B-spline basis values (K, C), sparse: degree + 1 non-zeros per row."""
    a = BSpline.design_matrix(params, np.asarray(knots, dtype=np.float64), degree)
    if a.shape[1] != n_ctrl:  # pragma: no cover - a knot vector of the wrong length
        raise ValueError(f"design matrix has {a.shape[1]} columns, expected {n_ctrl}")
    return csr_array(a)


def _weighted_lstsq(a: csr_array, q: np.ndarray, w: np.ndarray, degree: int) -> np.ndarray:
    """Control points minimising sum_k w_k |a_k P - q_k|^2.

    The normal matrix of a B-spline fit is banded (bandwidth ``degree``), so it is solved by a
    banded Cholesky factorisation in O(C); if a control point has (almost) no data weight, or
    the factorisation fails, the dense minimum-norm least-squares solution of the previous
    implementation is used instead.
    """
    aw = a.multiply(w[:, None]).tocsr()
    normal = (a.T @ aw).tocoo()
    rhs = aw.T @ q
    n = a.shape[1]
    upper = normal.row <= normal.col
    band = np.zeros((degree + 1, n))
    band[degree + normal.row[upper] - normal.col[upper], normal.col[upper]] = normal.data[upper]
    diag = band[degree]
    if diag.min() > 1e-9 * diag.max():  # every control point has data weight
        try:
            ctrl = solveh_banded(band, rhs, check_finite=False)
            if np.all(np.isfinite(ctrl)):
                return ctrl
        except LinAlgError:
            pass
    sw = np.sqrt(w)[:, None]
    ctrl, *_ = np.linalg.lstsq(a.toarray() * sw, q * sw, rcond=None)
    return ctrl


def fit_nurbs(
    centres: np.ndarray,
    *,
    params: np.ndarray | None = None,
    degree: int = 3,
    n_ctrl: int | None = None,
    weights: np.ndarray | None = None,
    robust: bool = True,
    iterations: int = 5,
) -> NurbsFit:
    """Weighted least-squares NURBS curve through ordered centres.

    Parameters
    ----------
    centres : ndarray, shape (K, 3)
        Ordered points, metres.
    params : ndarray, shape (K,), optional
        Increasing positions of the centres along the axis (any unit; normalised to [0, 1]);
        default: chord length.
    degree : int
        Curve degree (paper §3.1.4: 3).
    n_ctrl : int, optional
        Number of control points, degree + 1 <= n_ctrl <= K (default K // 2).
    weights : ndarray, shape (K,), optional
        Prior data weight of each centre (default 1).
    robust : bool
        Reweight the centres by their residuals for ``iterations`` rounds: two Huber rounds
        (threshold 2.5 robust sigmas, sigma at least 5 mm), then Tukey's biweight (4.685
        sigmas), which ignores gross outliers.

    Raises
    ------
    NotATunnelError
        If there are fewer than ``degree + 1`` centres.
    InvalidCloudError
        If centres or parameters are not finite, or the parameters decrease.
    """
    q = np.asarray(centres, dtype=np.float64)
    k = len(q)
    if q.ndim != 2 or q.shape[1] != 3 or not np.all(np.isfinite(q)):
        raise InvalidCloudError(f"centres must be a finite K x 3 array, got shape {q.shape}")
    if k < degree + 1:
        raise NotATunnelError(
            f"only {k} slice centres for a degree-{degree} centreline (need {degree + 1}); "
            "is the cloud a tunnel, and long enough? try a smaller slicing step"
        )
    if params is None:
        params = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    t = np.asarray(params, dtype=np.float64)
    if t.shape != (k,) or not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        raise InvalidCloudError("centre parameters must be K finite, non-decreasing values")
    t = (t - t[0]) / max(t[-1] - t[0], 1e-12)
    n_ctrl = int(np.clip(n_ctrl or k // 2, degree + 1, k))
    knots = compute_knot_vector2(degree, k, n_ctrl, list(t))
    a = _design_matrix(degree, knots, n_ctrl, t)
    prior = np.ones(k) if weights is None else np.asarray(weights, dtype=np.float64)
    w = prior.copy()
    for it in range(iterations if robust else 1):
        ctrl = _weighted_lstsq(a, q, w, degree)
        res = np.linalg.norm(a @ ctrl - q, axis=1)
        if not robust:
            break
        sigma = max(1.4826 * float(np.median(res)), 0.005)
        if it < 2:  # Huber first (convex, finds the bulk) ...
            c = 2.5 * sigma
            w = prior * np.where(res <= c, 1.0, c / np.maximum(res, 1e-12))
        else:  # ... then Tukey's biweight, which gives gross outliers no weight at all
            c = 4.685 * sigma
            w = prior * np.where(res < c, (1.0 - (res / c) ** 2) ** 2, 0.0)
    curve = NURBS.Curve()
    curve.degree = degree
    curve.ctrlpts = ctrl.tolist()
    curve.weights = [1.0] * n_ctrl
    curve.knotvector = knots
    return NurbsFit(curve, ctrl, np.ones(n_ctrl), np.asarray(knots), t, w, res)


def _from_vertices(
    vertices: np.ndarray, centres: np.ndarray, step: float, meta: dict
) -> Centerline:
    return Centerline.from_polyline(vertices, step=step, centres=centres, meta=meta)


def fit_centerline(
    centres: np.ndarray,
    *,
    params: np.ndarray | None = None,
    degree: int = 3,
    ctrl_spacing: float = 2.0,
    sample_step: float = 0.05,
    weights: np.ndarray | None = None,
    meta: dict | None = None,
    max_length: float | None = None,
) -> tuple[Centerline, NurbsFit]:
    """The NURBS centreline of slice centres, resampled every ``sample_step`` metres.

    Parameters
    ----------
    centres : ndarray, shape (K, 3)
        Slice centres in world coordinates, ordered along the tunnel, metres.
    params : ndarray, shape (K,), optional
        Stations of the centres along the axis, metres (default: chord length).
    degree : int
        Curve degree (paper §3.1.4: 3).
    ctrl_spacing : float
        About one control point per this many metres of tunnel (at least degree + 1, at most
        one per centre).
    sample_step : float
        Spacing of the output samples, metres.
    weights : ndarray, shape (K,), optional
        Prior data weights of the centres.
    meta : dict, optional
        Extra metadata stored in the centreline.
    max_length : float, optional
        Longest curve the cloud can hold, metres, e.g. from
        :func:`tunneldef.outliers.robust_extent` (``2 * extent.diagonal`` allows a 90 degree
        bend with room to spare). The station span, the path through the centres and the
        curve may not exceed it. Default: no bound but the centres' own path.

    Returns
    -------
    centerline : Centerline
    fit : NurbsFit

    Raises
    ------
    ImplausibleExtentError
        If the stations span, or the fitted curve is, longer than ``LENGTH_FACTOR`` times the
        path through the centres plus ``LENGTH_MARGIN`` metres (a stray point, a wrong unit),
        or any of them exceeds ``max_length``.

    Notes
    -----
    The curve is evaluated at one parameter per ``sample_step / 2`` metres of station span
    (the parameter is chord length, so about every ``sample_step / 2`` metres of arc; at most
    ``MAX_EVAL_POINTS`` times) and then resampled every ``sample_step`` metres. Both the span
    and the curve's arc length are checked against the path through the centres first, so the
    work is bounded by the data.
    """
    q = np.asarray(centres, dtype=np.float64)
    if params is None:
        params = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    if not sample_step > 0 or not ctrl_spacing > 0:
        raise ValueError("sample_step and ctrl_spacing must be positive")
    params = np.asarray(params, dtype=np.float64)
    path = _path_length(q)
    span = float(params[-1] - params[0])
    check_curve_length(span, path, "the span of the slice stations")
    _check_max_length(
        {"the span of the slice stations": span, "the centres' path": path}, max_length
    )
    n_ctrl = int(round(span / ctrl_spacing)) + degree
    fit = fit_nurbs(q, params=params, degree=degree, n_ctrl=min(n_ctrl, len(q)), weights=weights)
    length = fit.arc_length()
    check_curve_length(length, path, "the fitted centreline")
    _check_max_length({"the fitted centreline": length}, max_length)
    # as many parameters as half-steps along the stations (both checked against the data):
    # the parameter is chord length, so that is about one evaluation per sample_step / 2 of arc
    n_eval = int(np.clip(np.ceil(span / (sample_step / 2)) + 1, 2, MAX_EVAL_POINTS))
    pts = fit.evaluate(np.linspace(0.0, 1.0, n_eval))
    info = {
        "method": "nurbs_least_squares",
        "degree": degree,
        "knots": fit.knots.tolist(),
        "ctrlpts": fit.ctrlpts.tolist(),
        "ctrl_weights": fit.weights.tolist(),
        "centre_weights": fit.data_weights.tolist(),
        "centre_residual_rms_m": float(np.sqrt(np.mean(fit.residuals**2))),
        "eval_step_m": length / (n_eval - 1),
    }
    info.update(meta or {})
    return _from_vertices(pts, q, sample_step, info), fit


def systematic_misfit(
    cl: Centerline, centres: np.ndarray, stations: np.ndarray, window: float
) -> float:
    """Largest distance of the centres' running mean from a curve, metres.

    The centres' offsets from the curve (lateral, vertical) are averaged over every
    ``window`` metres of station (windows holding at least 5 centres); the largest length of
    that mean is what the curve misses systematically, e.g. a bend it cuts. Noise and waves
    shorter than the window average out.
    """
    if len(centres) < 5:
        return 0.0
    pr = cl.project(np.asarray(centres, dtype=np.float64))
    order = np.argsort(stations)
    st = np.asarray(stations, dtype=np.float64)[order]
    off = np.stack([pr.lateral, pr.vertical], axis=1)[order]
    csum = np.vstack([np.zeros((1, 2)), np.cumsum(off, axis=0)])
    lo = np.searchsorted(st, st - window / 2)
    hi = np.searchsorted(st, st + window / 2, side="right")
    n = hi - lo
    full = n >= 5
    if not full.any():
        return 0.0
    mean = (csum[hi[full]] - csum[lo[full]]) / n[full, None]
    return float(np.max(np.hypot(mean[:, 0], mean[:, 1])))


def fit_stiffest(
    centres: np.ndarray,
    *,
    params: np.ndarray,
    degree: int = 3,
    min_spacing: float = 2.0,
    max_spacing: float = 8.0,
    max_misfit: float = 0.01,
    sample_step: float = 0.05,
    meta: dict | None = None,
) -> tuple[Centerline, NurbsFit]:
    """The stiffest NURBS centreline that still follows the centres' course.

    Slice centres follow more than the design axis: rock relief, overbreak and a wall read
    on a pipe shift the midpoint of a section by centimetres over a few metres. A curve with
    a control point every 2 m follows those waves; on random synthetic pairs its p95
    distance from the design axis was 1.2-3.6 x that of a curve with one every 8 m (every
    one of 104 epochs better with 8 m). A stiff curve cuts tight bends, though (15 m radius
    fillets: its centres' running mean 15 mm off). So the spacings ``max_spacing``,
    ``max_spacing / 2``, ... down to ``min_spacing`` are tried, stiffest first, and the
    first whose :func:`systematic_misfit` (window ``max_spacing``) is within ``max_misfit``
    is kept; else the ``min_spacing`` curve.

    Parameters
    ----------
    centres : ndarray, shape (K, 3)
        Slice centres, ordered along the tunnel, metres.
    params : ndarray, shape (K,)
        Their stations along the axis, metres.
    degree : int
        Curve degree (paper §3.1.4: 3).
    min_spacing, max_spacing : float
        Most and least control points tried: one per this many metres.
    max_misfit : float
        Largest systematic misfit a stiffer curve may show, metres.
    sample_step : float
        Spacing of the output samples, metres.
    meta : dict, optional
        Extra metadata stored in the centreline.

    Returns
    -------
    centerline : Centerline
        Its ``meta`` holds ``ctrl_spacing_m``, ``systematic_misfit_m``,
        ``centre_scatter_p95_m`` (the p95 distance from the ``min_spacing`` curve of the
        centres its robust fit kept: their local scatter, the centreline's uncertainty
        figure) and ``centre_outliers`` (the centres it gave no weight).
    fit : NurbsFit
    """
    q = np.asarray(centres, dtype=np.float64)
    st = np.asarray(params, dtype=np.float64)
    spacings = [min_spacing]
    while max_spacing > min_spacing and spacings[-1] * 2 <= max_spacing + 1e-9:
        spacings.append(spacings[-1] * 2)
    flex, flex_fit = fit_centerline(q, params=st, degree=degree, ctrl_spacing=min_spacing,
                                    sample_step=sample_step)
    # the scatter of the centres that shaped the curve: a gross outlier (no weight in the
    # robust fit, e.g. one slice half in a niche 4.5 cm off) moves no curve, and on a short
    # branch of a dozen centres it alone would be the 95th percentile
    inliers = flex_fit.data_weights > 0
    dist = flex.project(q).distance
    scatter = float(np.percentile(dist[inliers] if inliers.sum() >= 3 else dist, 95))
    chosen, misfit = None, np.nan
    for spacing in reversed(spacings[1:]):
        try:
            cl, fit = fit_centerline(q, params=st, degree=degree, ctrl_spacing=spacing,
                                     sample_step=sample_step)
        except (ImplausibleExtentError, LinAlgError):
            # a stiff curve can shed a bend's centres as outliers (its reweighting) and then
            # swing wide over the span it lost: not a candidate
            continue
        misfit = systematic_misfit(cl, q, st, max_spacing)
        if misfit <= max_misfit:
            chosen = (cl, fit, spacing)
            break
    if chosen is None:
        misfit = systematic_misfit(flex, q, st, max_spacing)
        chosen = (flex, flex_fit, min_spacing)
    cl, fit, spacing = chosen
    cl.meta.update(meta or {})
    cl.meta.update({"ctrl_spacing_m": spacing, "systematic_misfit_m": misfit,
                    "centre_scatter_p95_m": scatter,
                    "centre_outliers": int(np.sum(~inliers))})
    return cl, fit


def fit_line(centres: np.ndarray, *, sample_step: float = 0.05) -> Centerline:
    """Least-squares straight line through centres (the paper's Fig. 16 blue line)."""
    q = np.asarray(centres, dtype=np.float64)
    c = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - c, full_matrices=False)
    d = vt[0] if vt[0] @ (q[-1] - q[0]) >= 0 else -vt[0]
    s = (q - c) @ d
    ends = c + np.array([s.min(), s.max()])[:, None] * d
    return _from_vertices(ends, q, sample_step, {"method": "least_squares_line"})


def fit_cubic_bspline(
    centres: np.ndarray, *, params: np.ndarray | None = None, sample_step: float = 0.05
) -> Centerline:
    """Plain cubic B-spline interpolating every centre (the paper's Fig. 16 green curve)."""
    from scipy.interpolate import make_interp_spline

    q = np.asarray(centres, dtype=np.float64)
    if params is None:
        params = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    t = np.asarray(params, dtype=np.float64)
    path = _path_length(q)
    check_curve_length(float(t[-1] - t[0]), path, "the span of the slice stations")
    spline = make_interp_spline(t, q, k=min(3, len(q) - 1), axis=0)
    length = _path_length(spline(np.linspace(t[0], t[-1], max(32 * len(q), 1024))))
    check_curve_length(length, path, "the cubic B-spline")
    n_eval = int(np.clip(np.ceil((t[-1] - t[0]) / (sample_step / 2)) + 1, 2, MAX_EVAL_POINTS))
    pts = spline(np.linspace(t[0], t[-1], n_eval))
    return _from_vertices(pts, q, sample_step, {"method": "cubic_bspline_interpolation"})
