"""Wall lines of a slice from its top view (paper §3.1.3, Fig. 4, Fig. 14).

Steps (paper §3.1.3, with the guards a cluttered mine needs):

1. Keep the points in the band of heights where the section is wall (between the floor and roof
   lines and away from both), so the roof, floor, arch, roof bolts and pipes under the roof do
   not enter the top view.
2. Rasterise the top view (along-axis u, lateral v) into an n x n grid. Rows are lateral
   (left = +v at the top, as in the paper's Fig. 4), columns span the slice thickness, so the
   slice is magnified along the axis as in the paper.
3. Smooth the counts with the linear kernel K(x) = 1 - |x| (paper eq. 3), separably in both
   directions (``scipy.ndimage.convolve1d``).
4. Canny edges (``skimage.feature.canny``), then the Hough line transform
   (``skimage.transform.hough_line``) restricted to lines within ``max_angle_deg`` of the axis.
5. The first line from the top is the left wall, the last the right wall (outermost strong
   lines: equipment hangs inside the walls). Each is refined to the mode of the lateral offsets
   of the points near it (narrow kernel density), since Canny marks the *edge* of the wall's
   density ridge, a few centimetres outside the wall.
6. Leaning walls (a trapezoidal section) are a strip, not a line, from above: when the whole
   tunnel's walls lean (:func:`estimate_wall_leans`), the points are first moved along the lean
   to the middle of the wall band, where the wall is then measured.

If no Hough line qualifies at all (an image too sparse for edges), a 1-D density of the lateral
offsets gives the first and last significant peaks instead (method ``"fallback"``); if the lines
all belong to one wall, the other wall is missing and the slice is rejected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import convolve1d, gaussian_filter, sobel, uniform_filter1d
from scipy.signal import find_peaks
from scipy.stats import theilslopes
from skimage.feature import canny
from skimage.transform import hough_line, hough_line_peaks

from ..config import CenterlineConfig, SlicingConfig
from .roof_floor import kernel_density_1d, refine_peak, roof_floor_lines
from .slicing import slice_along_axis

__all__ = ["WallLines", "wall_lines", "wall_lean", "estimate_wall_leans", "linear_kernel_density"]

HOUGH = "hough"
FALLBACK = "fallback"
_MAX_PIXELS = 800


@dataclass(frozen=True)
class WallLines:
    """Left and right wall lines of one slice (lateral offsets at the station, metres).

    Attributes
    ----------
    left, right : float
        Lateral position of the left (+v) and right (-v) wall at the station; NaN if missing.
    left_slope, right_slope : float
        dv/du of each line (0 for an axis-parallel wall).
    method : str
        ``"hough"``, ``"fallback"`` or ``""`` (not found).
    reason : str
        Why the walls are missing ("" when found).
    image : ndarray, shape (n, n)
        Linear-kernel density of the top view (max 1), rows from +v (top) to -v.
    edges : ndarray of bool, shape (n, n)
        Canny edges of ``image``.
    extent : tuple of float
        (u_min, u_max, v_min, v_max) of the image, metres.
    lines : ndarray, shape (L, 2)
        Every accepted Hough line as (v at the station, slope), top first.
    """

    left: float
    right: float
    left_slope: float
    right_slope: float
    method: str
    reason: str
    image: np.ndarray
    edges: np.ndarray
    extent: tuple[float, float, float, float]
    lines: np.ndarray

    @property
    def ok(self) -> bool:
        return not self.reason


def _triangle(half_width: int) -> np.ndarray:
    """Linear kernel K(x) = 1 - |x| (paper eq. 3) sampled at integer offsets, |x| = i / h."""
    i = np.arange(-half_width, half_width + 1)
    k = 1.0 - np.abs(i) / (half_width + 1.0)
    return k / k.sum()


def _smooth(img: np.ndarray, half_width: int, axis: int) -> np.ndarray:
    m = half_width + 1
    if m % 2:  # odd box: two passes of a centred box of m pixels are exactly the triangle
        pad = [(0, 0), (0, 0)]
        pad[axis] = (m, m)
        out = uniform_filter1d(np.pad(img, pad), m, axis=axis, mode="constant")
        out = uniform_filter1d(out, m, axis=axis, mode="constant")
        return out[m:-m] if axis == 0 else out[:, m:-m]
    return convolve1d(img, _triangle(half_width), axis=axis, mode="constant")


def linear_kernel_density(counts: np.ndarray, *, half_widths: tuple[int, int]) -> np.ndarray:
    """2-D linear-kernel density of a count image, separable (rows, then columns).

    Parameters
    ----------
    counts : ndarray, shape (R, C)
        Points per pixel.
    half_widths : (int, int)
        Kernel half-widths in pixels along rows (axis 0) and columns (axis 1).

    Notes
    -----
    The triangle 1 - |i| / m is the convolution of two boxes of m pixels, so for odd m it is
    computed as two running means (cost independent of the kernel width).
    """
    img = _smooth(counts.astype(np.float64), half_widths[0], 0)
    return _smooth(img, half_widths[1], 1)


def _hough_lines(edges: np.ndarray, *, max_slope_px: float, peak_ratio: float) -> np.ndarray:
    """Near-horizontal Hough lines of an edge image as (row at the centre column, drow/dcol)."""
    n_rows, n_cols = edges.shape
    a = max(np.arctan(max_slope_px), 2.0 / n_cols)
    n_angles = int(np.clip(np.ceil(8 * a * n_cols) + 1, 9, 91))  # quarter-pixel steps
    theta = np.pi / 2 + np.linspace(-a, a, n_angles)
    h, angles, dists = hough_line(edges, theta=theta)
    if h.max() == 0:
        return np.empty((0, 2))
    _, ang, dist = hough_line_peaks(
        h,
        angles,
        dists,
        min_distance=2,
        min_angle=n_angles,
        threshold=peak_ratio * h.max(),
        num_peaks=40,
    )
    xc = (n_cols - 1) / 2.0
    rows = (dist - xc * np.cos(ang)) / np.sin(ang)
    slopes = -np.cos(ang) / np.sin(ang)
    out = np.stack([rows, slopes], axis=1)
    return out[np.argsort(out[:, 0])]


def wall_lean(v: np.ndarray, dz: np.ndarray, *, side: float, bin_height: float = 0.15) -> float:
    """Lean dv/dz of one wall from the points of its side of the wall band.

    Seen from above, a wall that leans (a trapezoidal section) is a strip, not a line, and which
    part of the strip is seen depends on what hides it (pipes, a conveyor). Per height bin the
    98th percentile of ``side * v`` traces the wall's outer envelope (equipment hangs inside the
    walls and hides most, not all, of the wall behind it); a Theil-Sen line through the bins
    gives the lean (NaN with fewer than four bins).

    Parameters
    ----------
    v, dz : ndarray, shape (N,)
        Lateral offsets and heights (relative to any reference) of one side's points, metres.
    side : float
        +1 for the left wall (+v), -1 for the right wall.
    """
    k = np.floor((dz - dz.min()) / bin_height).astype(np.intp)
    zs, env = [], []
    for b in np.unique(k):
        m = k == b
        if m.sum() >= 5:
            zs.append(float(np.mean(dz[m])))
            env.append(float(np.percentile(side * v[m], 98)))
    if len(zs) < 4:
        return np.nan
    return side * float(theilslopes(env, zs).slope)


def _fallback(v: np.ndarray, *, bandwidth: float, min_share: float) -> tuple[float, float] | None:
    grid, dens = kernel_density_1d(v, bandwidth=bandwidth)
    idx, _ = find_peaks(dens, prominence=0.05 * dens.max())
    if idx.size < 2:
        return None
    vs = np.sort(v)
    p = grid[idx]
    share = (np.searchsorted(vs, p + bandwidth) - np.searchsorted(vs, p - bandwidth)) / v.size
    p = p[share >= min_share]
    return (float(p[-1]), float(p[0])) if p.size >= 2 else None


def wall_lines(
    u: np.ndarray,
    v: np.ndarray,
    *,
    station: float,
    thickness: float,
    grid_cell: float = 0.02,
    kernel_half_width: float = 0.04,
    max_angle_deg: float = 20.0,
    peak_ratio: float = 0.3,
    refine_bandwidth: float = 0.02,
    min_width: float = 0.5,
    w: np.ndarray | None = None,
    w_ref: float = 0.0,
    leans: tuple[float, float] = (0.0, 0.0),
) -> WallLines:
    """Left and right wall lines of one slice from the top view of its wall band.

    Parameters
    ----------
    u, v : ndarray, shape (N,)
        Along-axis and lateral (positive left) coordinates of the slice's wall-band points,
        metres.
    station : float
        Along-axis position of the slice centre, metres.
    thickness : float
        Slice thickness, metres (the image spans ``station +- thickness / 2``).
    grid_cell : float
        Lateral pixel size, metres; the image is n x n with n = lateral extent / grid_cell.
    kernel_half_width : float
        Lateral half-width of the linear kernel (paper eq. 3), metres; along the axis the
        half-width is a quarter of the thickness.
    max_angle_deg : float
        Only lines within this angle of the axis are walls (real-space degrees).
    peak_ratio : float
        Hough peaks below this fraction of the strongest are ignored.
    refine_bandwidth : float
        Narrow kernel that refines each line to the mode of its points' lateral offsets, m.
    min_width : float
        Two lines closer than this are one wall seen twice (the other wall is missing), m.
    w : ndarray, shape (N,), optional
        Vertical coordinates of the points, metres (needed for leaning walls).
    w_ref : float
        Height at which leaning walls are measured, metres.
    leans : (float, float)
        Lean dv/dw of the left and right wall (:func:`wall_lean`; 0 = vertical). Seen from
        above a leaning wall is a strip whose visible part depends on what hides it, so its
        points are moved to ``w_ref`` along the lean before the line is refined.

    Returns
    -------
    WallLines
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    empty_img = np.zeros((0, 0))
    if v.size < 10:
        return WallLines(
            np.nan,
            np.nan,
            0.0,
            0.0,
            "",
            "too few points in the wall band",
            empty_img,
            empty_img.astype(bool),
            (0, 0, 0, 0),
            np.empty((0, 2)),
        )
    lo, hi = np.quantile(v, [0.001, 0.999])
    margin = 4 * kernel_half_width + 5 * grid_cell
    v_min, v_max = lo - margin, hi + margin
    cell = max(grid_cell, (v_max - v_min) / _MAX_PIXELS)
    n = int(np.ceil((v_max - v_min) / cell))
    v_max = v_min + n * cell
    u_min, u_max = station - thickness / 2, station + thickness / 2
    cell_u = thickness / n
    counts, _, _ = np.histogram2d(-v, u, bins=(n, n), range=((-v_max, -v_min), (u_min, u_max)))
    half = (2 * max(1, round(kernel_half_width / cell / 2)), 2 * max(1, n // 8))
    image = linear_kernel_density(counts, half_widths=half)
    image /= max(image.max(), 1e-300)
    smooth = gaussian_filter(image, 1.0)
    grad = np.hypot(sobel(smooth, 0), sobel(smooth, 1))
    gmax = float(grad.max())
    edges = canny(image, sigma=1.0, low_threshold=0.1 * gmax, high_threshold=0.25 * gmax)
    max_slope_px = np.tan(np.radians(max_angle_deg)) * cell_u / cell
    lines_px = _hough_lines(edges, max_slope_px=max_slope_px, peak_ratio=peak_ratio)
    # pixel (row, drow/dcol) -> (v at the station, dv/du)
    lines = (
        np.stack([v_max - (lines_px[:, 0] + 0.5) * cell, -lines_px[:, 1] * cell / cell_u], axis=1)
        if len(lines_px)
        else np.empty((0, 2))
    )
    extent = (u_min, u_max, v_min, v_max)
    window = kernel_half_width + 3 * cell
    if len(lines) >= 2:
        out = []
        mid = (lines[0, 0] + lines[-1, 0]) / 2
        for (v0, slope), side, lean in ((lines[0], 1.0, leans[0]), (lines[-1], -1.0, leans[1])):
            r = v - slope * (u - station)
            if w is not None and lean:
                # a leaning wall is measured at the reference height: its points are moved
                # there along the lean, and the search starts at their outer envelope
                r = r - lean * (w - w_ref)
                on_side = side * (r - mid) > 0
                if on_side.sum() >= 10:
                    v0 = side * float(np.percentile(side * r[on_side], 90))
            out.append((refine_peak(r, v0, window=window, bandwidth=refine_bandwidth), slope))
        (left, ls), (right, rs) = out
        if left - right >= min_width:
            return WallLines(left, right, ls, rs, HOUGH, "", image, edges, extent, lines)
    # Hough lines on one side only: that wall is missing (a hole, a chamber mouth); the density
    # fallback is for slices whose image gave no line at all (too sparse for edges)
    fb = None if len(lines) else _fallback(v, bandwidth=kernel_half_width, min_share=0.05)
    if fb is not None and fb[0] - fb[1] >= min_width:
        left = refine_peak(v, fb[0], window=window, bandwidth=refine_bandwidth)
        right = refine_peak(v, fb[1], window=window, bandwidth=refine_bandwidth)
        return WallLines(left, right, 0.0, 0.0, FALLBACK, "", image, edges, extent, lines)
    reason = "no wall line" if len(lines) == 0 else "only one wall found (the other is missing)"
    return WallLines(np.nan, np.nan, 0.0, 0.0, "", reason, image, edges, extent, lines)


def estimate_wall_leans(
    local: np.ndarray,
    slicing: SlicingConfig,
    settings: CenterlineConfig,
    *,
    min_lean: float = 0.05,
) -> tuple[float, float]:
    """Lean dv/dw of the left and right walls, common to the whole tunnel.

    ``local`` holds the points as (along, lateral, vertical), shape (N, 3), metres (section
    levelled); ``slicing`` and ``settings`` give the slicing, kernel and wall-band parameters.

    Every metre, the wall band of a slice is split at the middle of its lateral extent and each
    side's lean is measured (:func:`wall_lean`); the median over
    the slices is the wall's lean (a design section is the same along the tunnel; the median
    ignores slices where pipes or a conveyor hide the wall). The leans are used only when both
    walls lean by at least ``min_lean`` (2.9 deg), steadily along the tunnel (robust spread at
    most half the lean) and symmetrically (the section narrows or widens upwards on both
    sides); anything else (vertical walls, an arch springing inside the wall band, rough rock)
    is measured as vertical walls, as in the paper.
    """
    c = settings
    leans: list[tuple[float, float]] = []
    for sl in slice_along_axis(
        local[:, 0], step=max(slicing.step, 1.0), thickness=slicing.thickness
    ):
        if len(sl.index) < slicing.min_points:
            continue
        p = local[sl.index]
        rf = roof_floor_lines(p[:, 2], bandwidth=c.kde_bandwidth, min_share=c.min_peak_share)
        if not rf.ok:
            continue
        h = rf.roof - rf.floor
        q = p[
            (p[:, 2] > rf.floor + c.wall_band_low * h) & (p[:, 2] < rf.floor + c.wall_band_high * h)
        ]
        if len(q) < 40:
            continue
        mid = float(np.mean(np.percentile(q[:, 1], [2, 98])))
        w_ref = rf.floor + 0.5 * (c.wall_band_low + c.wall_band_high) * h
        pair = []
        for side in (1.0, -1.0):
            m = side * (q[:, 1] - mid) > 0
            pair.append(wall_lean(q[m, 1], q[m, 2] - w_ref, side=side) if m.sum() >= 20 else np.nan)
        leans.append((pair[0], pair[1]))
    if len(leans) < 3:
        return 0.0, 0.0
    cols = [col[np.isfinite(col)] for col in np.array(leans).T]
    med = np.array([np.median(col) if col.size >= 3 else np.nan for col in cols])
    spread = np.array(
        [
            1.4826 * np.median(np.abs(col - m)) if col.size >= 3 else np.nan
            for col, m in zip(cols, med, strict=True)
        ]
    )
    steady = np.isfinite(med) & (np.abs(med) >= min_lean) & (spread <= 0.5 * np.abs(med))
    if steady.all() and med[0] * med[1] < 0:
        return float(med[0]), float(med[1])
    return 0.0, 0.0
