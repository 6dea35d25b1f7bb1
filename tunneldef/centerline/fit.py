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

The curve is evaluated with ``geomdl.NURBS.Curve`` and resampled as a
:class:`~tunneldef.curve.Centerline`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from geomdl import NURBS, helpers
from geomdl.fitting import compute_knot_vector2

from ..curve import Centerline
from ..errors import NotATunnelError

__all__ = ["NurbsFit", "fit_nurbs", "fit_centerline", "fit_line", "fit_cubic_bspline"]


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

    def evaluate(self, params: np.ndarray) -> np.ndarray:
        """Curve points (M, 3) at parameters in [0, 1]."""
        return np.asarray(self.curve.evaluate_list([float(t) for t in np.clip(params, 0, 1)]))


def _design_matrix(degree: int, knots: list[float], n_ctrl: int, params: np.ndarray) -> np.ndarray:
    a = np.zeros((len(params), n_ctrl))
    for k, t in enumerate(params):
        span = helpers.find_span_linear(degree, knots, n_ctrl, float(t))
        a[k, span - degree : span + 1] = helpers.basis_function(degree, knots, span, float(t))
    return a


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
    """
    q = np.asarray(centres, dtype=np.float64)
    k = len(q)
    if k < degree + 1:
        raise NotATunnelError(
            f"only {k} slice centres for a degree-{degree} centreline (need {degree + 1}); "
            "is the cloud a tunnel, and long enough? try a smaller slicing step"
        )
    if params is None:
        params = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    t = np.asarray(params, dtype=np.float64)
    t = (t - t[0]) / max(t[-1] - t[0], 1e-12)
    n_ctrl = int(np.clip(n_ctrl or k // 2, degree + 1, k))
    knots = compute_knot_vector2(degree, k, n_ctrl, list(t))
    a = _design_matrix(degree, knots, n_ctrl, t)
    prior = np.ones(k) if weights is None else np.asarray(weights, dtype=np.float64)
    w = prior.copy()
    for it in range(iterations if robust else 1):
        sw = np.sqrt(w)[:, None]
        ctrl, *_ = np.linalg.lstsq(a * sw, q * sw, rcond=None)
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

    Returns
    -------
    centerline : Centerline
    fit : NurbsFit
    """
    q = np.asarray(centres, dtype=np.float64)
    if params is None:
        params = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    span = float(params[-1] - params[0])
    n_ctrl = int(round(span / ctrl_spacing)) + degree
    fit = fit_nurbs(q, params=params, degree=degree, n_ctrl=min(n_ctrl, len(q)), weights=weights)
    n_eval = max(int(np.ceil(span / (sample_step / 2))) + 1, 2)
    pts = fit.evaluate(np.linspace(0.0, 1.0, n_eval))
    info = {
        "method": "nurbs_least_squares",
        "degree": degree,
        "knots": fit.knots.tolist(),
        "ctrlpts": fit.ctrlpts.tolist(),
        "ctrl_weights": fit.weights.tolist(),
        "centre_weights": fit.data_weights.tolist(),
        "centre_residual_rms_m": float(np.sqrt(np.mean(fit.residuals**2))),
    }
    info.update(meta or {})
    return _from_vertices(pts, q, sample_step, info), fit


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
    spline = make_interp_spline(t, q, k=min(3, len(q) - 1), axis=0)
    n_eval = max(int(np.ceil((t[-1] - t[0]) / (sample_step / 2))) + 1, 2)
    pts = spline(np.linspace(t[0], t[-1], n_eval))
    return _from_vertices(pts, q, sample_step, {"method": "cubic_bspline_interpolation"})
