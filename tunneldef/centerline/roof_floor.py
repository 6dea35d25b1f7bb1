"""Roof and floor lines of a slice from the density of its heights (paper §3.1.2, §4.1).

The heights of a slice's points are counted in a fine histogram and smoothed with a 1-D Gaussian
kernel (paper eq. 1-2; a binned kernel density estimate, window 0.1 m after §4.1 and Fig. 13).
Roof and floor are flat, so each gathers many points at one height and makes a density peak;
walls spread their points evenly over the height and make none. The floor is the first and the
roof the last *significant* peak: one holding at least ``min_share`` of the slice's points within
one window, so scattered outliers, cables and small equipment never win (a plain min/max of z
would). Each peak is then refined with a narrow kernel around it, which removes the pull of the
walls' points on the wide window's peak (about ``B h^2 / A`` for wall density B per metre and A
floor points, ~1 cm in a 2 m drift).

:func:`estimate_roll` measures the cross-slope shared by floors and roofs (a scan rolled about
the tunnel axis), which the caller removes before looking for level lines.

One idea at this length: everything read from the heights of a slice (the density peaks, the crown,
the cross slopes and the section's roll), which share the 1-D kernel density.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks

from ..config import CenterlineConfig, SlicingConfig
from .slicing import slice_along_axis

__all__ = [
    "RoofFloor",
    "roof_floor_lines",
    "kernel_density_1d",
    "refine_peak",
    "cover_beyond",
    "Crown",
    "crown_height",
    "estimate_roll",
]

KDE_PEAK = "kde_peak"


@dataclass(frozen=True)
class RoofFloor:
    """Floor and roof lines of one slice (heights in the slice's vertical coordinate, metres).

    Attributes
    ----------
    floor, roof : float
        Line heights, NaN when not found.
    method : str
        ``"kde_peak"`` when both were found, ``""`` otherwise.
    reason : str
        Why a line is missing ("" when both were found).
    grid, density : ndarray, shape (M,)
        Heights and the Gaussian kernel density there (integrates to 1), for diagnostics.
    peaks : ndarray, shape (P,)
        Heights of all density peaks.
    shares : ndarray, shape (P,)
        Share of the slice's points within one window of each peak.
    crown : Crown or None
        The trimmed parabola through the roof points (:func:`crown_height`), when fitted.
    """

    floor: float
    roof: float
    method: str
    reason: str
    grid: np.ndarray
    density: np.ndarray
    peaks: np.ndarray
    shares: np.ndarray
    crown: Crown | None = None

    @property
    def ok(self) -> bool:
        return not self.reason


def kernel_density_1d(
    values: np.ndarray, *, bandwidth: float, bin_width: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Binned Gaussian kernel density of 1-D values.

    Parameters
    ----------
    values : ndarray, shape (N,)
        Samples, metres.
    bandwidth : float
        Standard deviation of the Gaussian kernel ``h`` (paper eq. 1-2), metres.
    bin_width : float, optional
        Histogram bin, metres (default ``bandwidth / 10``).

    Returns
    -------
    grid, density : ndarray, shape (M,)
        Bin centres and the density there (integrates to 1).
    """
    v = np.asarray(values, dtype=np.float64)
    bw = bin_width or bandwidth / 10.0
    lo, hi = v.min() - 4 * bandwidth, v.max() + 4 * bandwidth
    nbins = max(int(np.ceil((hi - lo) / bw)), 1)
    counts, edges = np.histogram(v, bins=nbins, range=(lo, lo + nbins * bw))
    density = gaussian_filter1d(counts.astype(np.float64), bandwidth / bw, mode="constant")
    density /= max(density.sum() * bw, 1e-300)
    return (edges[:-1] + edges[1:]) / 2, density


def refine_peak(values: np.ndarray, centre: float, *, window: float, bandwidth: float) -> float:
    """Mode of ``values`` within ``centre +- window`` by a narrow Gaussian kernel density.

    The mode is taken with sub-bin (parabolic) interpolation; if the window holds fewer than 5
    values the centre is returned unchanged.
    """
    v = values[np.abs(values - centre) <= window]
    if v.size < 5:
        return float(centre)
    bw = bandwidth / 8.0
    grid, dens = kernel_density_1d(v, bandwidth=bandwidth, bin_width=bw)
    inside = np.abs(grid - centre) <= window
    idx = np.flatnonzero(inside)
    i = idx[np.argmax(dens[idx])]
    if 0 < i < len(dens) - 1:
        a, b, c = dens[i - 1], dens[i], dens[i + 1]
        den = a - 2 * b + c
        if den < 0:
            return float(grid[i] + 0.5 * (a - c) / den * bw)
    return float(grid[i])


def cover_beyond(
    z: np.ndarray, lateral: np.ndarray, floor: float, roof: float, *, gap: float,
    cell: float = 0.05,
) -> tuple[float, float]:
    """Share of the section's width holding points more than ``gap`` below the floor line and
    more than ``gap`` above the roof line.

    The width is the 1-99 % range of ``lateral`` cut into ``cell``-wide bins; a bin counts
    when it holds at least one such point. Noise, outliers and a drain cover a few bins; the
    true floor or roof, where the line was read on something inside the section (a clump on
    a wall, a support, a pipe), covers most of them, however few points it holds.

    Returns
    -------
    below, above : float
        Covered shares, 0 to 1.
    """
    lo, hi = np.quantile(lateral, [0.01, 0.99])
    nbins = max(int(np.ceil((hi - lo) / cell)), 1)
    bins = np.clip(((lateral - lo) / cell).astype(np.int64), 0, nbins - 1)
    below = np.unique(bins[z < floor - gap]).size / nbins
    above = np.unique(bins[z > roof + gap]).size / nbins
    return below, above


def roof_floor_lines(
    z: np.ndarray,
    *,
    bandwidth: float = 0.1,
    min_share: float = 0.05,
    refine_bandwidth: float | None = 0.02,
    lateral: np.ndarray | None = None,
    beyond_gap: float = 0.15,
    max_beyond_cover: float = 0.6,
) -> RoofFloor:
    """Floor and roof heights of one slice: first and last significant density peaks of z.

    Parameters
    ----------
    z : ndarray, shape (N,)
        Vertical coordinate of the slice's points, metres.
    bandwidth : float
        Gaussian kernel window, metres (paper §4.1: 0.1 m).
    min_share : float
        Smallest share of the slice's points within ``+-bandwidth`` of a peak for it to count.
    refine_bandwidth : float or None
        Narrow kernel used to refine each line (None: keep the wide window's peak).
    lateral : ndarray, shape (N,), optional
        Lateral coordinate of the points, metres. When given, a line with points more than
        ``beyond_gap`` beyond it over ``max_beyond_cover`` of the section's width
        (:func:`cover_beyond`) was read inside the section and the slice gets a reason: a
        terrestrial scanner's far roof can hold fewer points than a clump on a wall close to
        the scanner, and such a slice would be 0.2-0.3 m too low.
    beyond_gap, max_beyond_cover : float
        See ``lateral`` (metres, share of the width).

    Returns
    -------
    RoofFloor
    """
    z = np.asarray(z, dtype=np.float64)
    empty = np.empty(0)
    if z.size < 10:
        return RoofFloor(
            np.nan, np.nan, "", "too few points for a height density", empty, empty, empty, empty
        )
    grid, dens = kernel_density_1d(z, bandwidth=bandwidth)
    idx, _ = find_peaks(dens, prominence=0.02 * dens.max())
    peaks = grid[idx]
    zs = np.sort(z)
    within = np.searchsorted(zs, peaks + bandwidth, side="right") - np.searchsorted(
        zs, peaks - bandwidth, side="left"
    )
    shares = within / z.size
    sig = peaks[shares >= min_share]
    if sig.size < 2:
        reason = (
            "no significant height density peak"
            if sig.size == 0
            else "only one significant height density peak (floor or roof missing)"
        )
        return RoofFloor(np.nan, np.nan, "", reason, grid, dens, peaks, shares)
    floor, roof = float(sig[0]), float(sig[-1])
    if refine_bandwidth:
        floor = refine_peak(z, floor, window=bandwidth, bandwidth=refine_bandwidth)
        roof = refine_peak(z, roof, window=bandwidth, bandwidth=refine_bandwidth)
    reason = ""
    if lateral is not None:
        below, above = cover_beyond(z, np.asarray(lateral, dtype=np.float64), floor, roof,
                                    gap=beyond_gap)
        for name, cover, where in (("roof", above, "above"), ("floor", below, "below")):
            if cover >= max_beyond_cover:
                reason = (f"{name} read inside the section: points {beyond_gap:.2f} m {where} "
                          f"it span {100 * cover:.0f} % of the width")
                break
    return RoofFloor(floor, roof, KDE_PEAK, reason, grid, dens, peaks, shares)


@dataclass(frozen=True)
class Crown:
    """A trimmed parabola ``v = a + b u + c u^2`` through a slice's roof points
    (:func:`crown_height`).

    Attributes
    ----------
    height : float
        The parabola at the section's middle, metres (NaN when too few points).
    curvature : float
        ``c``, 1/m (negative: the roof curves down towards the walls).
    sigma : float
        Robust sigma of the points about the parabola, metres.
    """

    height: float
    curvature: float
    sigma: float

    def lift(self, peak: float) -> float:
        """How far to raise a roof density ``peak`` to this crown: only what the peak gets
        wrong is corrected. On a roof curving down to the walls the peak lies below the
        crown, by less than the points' own scatter about it; a crown above the peak by
        more, below it, or a parabola opening upwards (ledges, clutter, a roof that is no
        single curve: the real Freiberg drift) gives 0."""
        d = self.height - peak
        ok = self.curvature < 0 and 0.0 < d <= 3.0 * max(self.sigma, 0.005)
        return float(d) if ok else 0.0


def crown_height(
    lateral: np.ndarray,
    vertical: np.ndarray,
    roof: float,
    centre: float,
    half_width: float,
    *,
    window: float = 0.25,
    iterations: int = 5,
    min_points: int = 30,
) -> Crown:
    """The crown of a slice's roof, unbiased on a curved roof.

    The kernel density peak of the heights (paper §3.1.2) marks a flat roof exactly, but on an
    arch the heights crowd towards the crown (density ~ 1/sqrt(crown - v)); smoothed by noise
    and relief that peak lies below the crown by a good part of their sigma (synthetic arches,
    +-1.5-2.5 cm noise: centrelines 10-18 mm low). Here a parabola ``v = a + b u + c u^2`` is
    fitted by least squares to the points near the peak across the middle of the section and
    trimmed to its own residuals (2.5 robust sigmas), and read at the middle: on an arch the
    crown, on a flat roof about the peak; clutter below the roof falls outside the trimmed
    band. :meth:`Crown.lift` says how much of it to take.

    Parameters
    ----------
    lateral, vertical : ndarray, shape (N,)
        The slice's points across and up the section, metres.
    roof : float
        The density peak of the roof, metres.
    centre, half_width : float
        Lateral middle of the section and half its width (from the walls), metres.
    window : float
        Points within this height of ``roof`` start the fit, metres.

    Returns
    -------
    Crown
        NaN figures when fewer than ``min_points`` points support the fit.
    """
    none = Crown(np.nan, np.nan, np.nan)
    u = np.asarray(lateral, dtype=np.float64) - centre
    v = np.asarray(vertical, dtype=np.float64)
    near = (np.abs(u) < 0.6 * half_width) & (np.abs(v - roof) < window)
    u, v = u[near], v[near]
    if u.size < min_points:
        return none
    keep = np.ones(u.size, dtype=bool)
    coef, sigma = None, np.nan
    for _ in range(iterations):
        if keep.sum() < min_points:
            return none
        coef = np.polyfit(u[keep], v[keep], 2)
        res = v - np.polyval(coef, u)
        sigma = 1.4826 * float(np.median(np.abs(res[keep])))
        keep = np.abs(res) < max(2.5 * sigma, 0.01)
    return Crown(float(np.polyval(coef, 0.0)), float(coef[0]), float(sigma))


def cross_slopes(
    local: np.ndarray, slicing: SlicingConfig, settings: CenterlineConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Cross-slopes of floor and roof, every metre along the axis.

    ``local`` holds the points as (along, lateral, vertical), shape (N, 3), metres. Every metre
    a slice's floor and roof peaks are found (wide window only); the points within two windows
    of each are fitted with a line across the tunnel (inner 80 % of their lateral range, so
    wall corners do not count; one 3-MAD trim).

    Returns
    -------
    stations, angles : ndarray
        Where along the axis (m) and the slope's angle (radians; positive: rising to the left),
        one per floor or roof line found.
    """
    c = settings
    stations, slopes = [], []
    for sl in slice_along_axis(
        local[:, 0], step=max(slicing.step, 1.0), thickness=slicing.thickness
    ):
        if len(sl.index) < slicing.min_points:
            continue
        p = local[sl.index]
        rf = roof_floor_lines(
            p[:, 2], bandwidth=c.kde_bandwidth, min_share=c.min_peak_share, refine_bandwidth=None
        )
        if not rf.ok:
            continue
        for z0 in (rf.floor, rf.roof):
            q = p[np.abs(p[:, 2] - z0) < 2 * c.kde_bandwidth]
            if len(q) < 30:
                continue
            lo, hi = np.quantile(q[:, 1], [0.1, 0.9])
            q = q[(q[:, 1] >= lo) & (q[:, 1] <= hi)]
            if len(q) < 30 or hi - lo < 0.5:
                continue
            b, a = np.polyfit(q[:, 1], q[:, 2], 1)
            r = q[:, 2] - (a + b * q[:, 1])
            keep = np.abs(r - np.median(r)) <= 3 * 1.4826 * np.median(np.abs(r - np.median(r)))
            if keep.sum() >= 30:
                b, a = np.polyfit(q[keep, 1], q[keep, 2], 1)
            stations.append(sl.station)
            slopes.append(b)
    return np.asarray(stations, dtype=np.float64), np.arctan(np.asarray(slopes, dtype=np.float64))


def _common_roll(angles: np.ndarray) -> float:
    """The median angle; 0 below 0.1 degree (a levelled scan is left untouched), with fewer
    than 3 angles, or when they disagree by more than 1 degree (robust spread: a rough floor,
    not a rolled scan)."""
    if angles.size < 3:
        return 0.0
    spread = 1.4826 * float(np.median(np.abs(angles - np.median(angles))))
    if spread > np.radians(1.0):
        return 0.0  # rough floor/roof, no common cross-slope: nothing to level
    roll = float(np.median(angles))
    return roll if abs(roll) >= np.radians(0.1) else 0.0


def estimate_roll(
    local: np.ndarray, slicing: SlicingConfig, settings: CenterlineConfig
) -> float:
    """Roll of the section about the axis (radians) from the cross-slopes of floor and roof.

    ``local`` holds the points as (along, lateral, vertical), shape (N, 3), metres;
    ``slicing`` and ``settings`` give the slicing and kernel parameters. Positive: the floor
    rises to the left.

    The median of :func:`cross_slopes`. It is taken as 0 below 0.1 degree (a levelled scan is
    left untouched) and when the slopes disagree by more than 1 degree (robust spread: a rough
    floor, not a rolled scan).
    """
    return _common_roll(cross_slopes(local, slicing, settings)[1])


def roll_profile(
    local: np.ndarray, slicing: SlicingConfig, settings: CenterlineConfig, window: float
) -> tuple[np.ndarray, np.ndarray]:
    """The section's roll along the axis: :func:`estimate_roll`'s rule on the cross-slopes
    within ``window`` m either side of each metre (the whole axis' where fewer than three
    slopes lie within it).

    A drift network's edge turns (a ramp's bend, a drift that follows the seam), and a tilted
    scan rolls each direction's section by its own angle: one roll per edge does not fit
    both sides of a bend. Returns ``(stations, angles)`` (m, radians), empty when no slope was
    found; between and beyond stations the roll is interpolated (:func:`numpy.interp`).
    """
    st, ang = cross_slopes(local, slicing, settings)
    if st.size == 0:
        return st, ang
    at = np.unique(st)
    whole = _common_roll(ang)
    roll = np.empty(at.size)
    for k, s in enumerate(at):
        near = ang[np.abs(st - s) <= window]
        roll[k] = _common_roll(near) if near.size >= 3 else whole
    return at, roll
