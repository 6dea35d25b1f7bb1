"""Tunnel shell versus everything in front of it, from the cross-section geometry.

Attached equipment (pipes, cables), the conveyor and its load, people and stray points all lie
*inside* the tunnel: seen from the centreline, the shell is the outermost surface in every
direction. :func:`classify_shell` cuts the cloud into chainage windows and angular sectors
around the centreline, takes an outer anchor in each (window, sector) bin, joins the anchors
on each window's convex hull into a closed outer envelope, refines it on the points near it,
and keeps as shell the points within a tolerance of that envelope.

Everything is vectorised over all bins at once (one sort of all points by (bin, radius), one
``np.searchsorted`` over the concatenated envelopes of all windows); there is no loop over
points or bins.

One idea at this length: the shell-versus-clutter decision (envelopes, their matching between
epochs, the mask) used by the estimator and the output field.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from ..cloud import check_points
from ..config import check_positive
from ..curve import Centerline, Projection
from ..errors import ConfigError, InvalidCloudError

__all__ = ["ShellEnvelope", "classify_shell", "outer_envelope", "shell_envelope", "shell_mask"]

logger = logging.getLogger(__name__)

_ANCHOR_QUANTILE = 0.75  # of the radii near the outer envelope, in each bin
_MATCH_REACH = 15  # sectors either side over which two envelopes' difference is averaged
_WINDOW_PERIOD = 20.0  # > 6 pi: angle axis offset per window in the concatenated envelopes


def _bins(window: np.ndarray, theta: np.ndarray, sectors: int) -> tuple[np.ndarray, np.ndarray]:
    """Dense window ids (N,) and (window, sector) bin ids (N,)."""
    wid = np.unique(window, return_inverse=True)[1].ravel().astype(np.int64)
    sec = np.clip(((theta + np.pi) / (2 * np.pi) * sectors).astype(np.int64), 0, sectors - 1)
    return wid, wid * sectors + sec


def _order_in_bins(bin_: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Permutation sorting points by bin, then by radius (one float sort instead of a
    two-key ``np.lexsort``; radii below 1 km keep about 1e-7 m of resolution in the key
    for up to a million bins)."""
    return np.argsort(bin_.astype(np.float64) * 1024.0 + np.clip(rho, 0.0, 1023.0))


def _ring(
    wid: np.ndarray,
    theta: np.ndarray,
    a_win: np.ndarray,
    a_theta: np.ndarray,
    a_rho: np.ndarray,
    ray: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Closed polygon of each window through its anchors (in order of angle), evaluated along
    each point's ray from the centreline.

    ``ray`` is ``(cos theta, sin theta)`` of the points when the caller has it. Returns the
    radius where the point's ray crosses its window's polygon and the obliquity
    ``1 / |cos(incidence)|`` of that polygon edge to the ray.
    """
    o = np.lexsort((a_theta, a_win))
    a_win, a_theta, a_rho = a_win[o], a_theta[o], a_rho[o]
    w_start = np.flatnonzero(np.r_[True, a_win[1:] != a_win[:-1]])
    w_end = np.r_[w_start[1:], len(a_win)] - 1
    x = np.concatenate([a_theta[w_end] - 2 * np.pi, a_theta, a_theta[w_start] + 2 * np.pi])
    y = np.concatenate([a_rho[w_end], a_rho, a_rho[w_start]])
    w = np.concatenate([a_win[w_end], a_win, a_win[w_start]])
    xo = x + _WINDOW_PERIOD * w
    oo = np.argsort(xo, kind="stable")
    xo, y = xo[oo], y[oo]
    px, py = y * np.cos(x[oo]), y * np.sin(x[oo])  # anchor vertices in the section plane
    ex_all, ey_all = np.diff(px), np.diff(py)  # polygon edges (between windows: unused)
    q = theta + _WINDOW_PERIOD * wid
    seg = np.clip(np.searchsorted(xo, q, side="right") - 1, 0, len(xo) - 2)
    ax, ay, ex, ey = px[seg], py[seg], ex_all[seg], ey_all[seg]
    dx, dy = (np.cos(theta), np.sin(theta)) if ray is None else ray
    den = dx * ey - dy * ex
    length = np.hypot(ex, ey)
    ok = np.abs(den) > 1e-9 * np.maximum(length, 1e-12)
    envelope = np.where(ok, (ax * ey - ay * ex) / np.where(ok, den, 1.0), 0.0)
    if not ok.all():
        envelope[~ok] = np.interp(q[~ok], xo, y)  # degenerate edges
    cos_inc = np.abs(den) / np.maximum(length, 1e-12)
    obliquity = np.where(ok, 1.0 / np.maximum(cos_inc, 1e-3), 1.0)
    return envelope, obliquity


def _hull_anchors(a_win: np.ndarray, a_theta: np.ndarray, a_rho: np.ndarray) -> np.ndarray:
    """Mask of the anchors on the convex hull of their window (section outlines are convex:
    objects in front of the shell dent the anchors inward and drop off the hull)."""
    keep = np.zeros(len(a_win), dtype=bool)
    order = np.argsort(a_win, kind="stable")
    bounds = np.flatnonzero(np.r_[True, a_win[order][1:] != a_win[order][:-1], True])
    pts = np.stack([a_rho * np.cos(a_theta), a_rho * np.sin(a_theta)], axis=1)
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):  # one hull per window
        idx = order[lo:hi]
        if len(idx) < 4:
            keep[idx] = True
            continue
        try:
            keep[idx[ConvexHull(pts[idx]).vertices]] = True
        except QhullError:
            keep[idx] = True
    return keep


def outer_envelope(
    window: np.ndarray,
    theta: np.ndarray,
    rho: np.ndarray,
    *,
    sectors: int = 360,
    rank: int = 1,
    hull: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Outer envelope radius at each point's own angle, and the envelope's obliquity there.

    Parameters
    ----------
    window : ndarray of int, shape (N,)
        Chainage window of each point (any integers).
    theta : ndarray, shape (N,)
        Angle around the centreline, radians in [-pi, pi].
    rho : ndarray, shape (N,)
        Distance from the centreline, metres.
    sectors : int
        Angular sectors per turn.
    rank : int
        The anchor of a (window, sector) bin is its ``rank``-th largest radius (0 = the
        largest), so that up to ``rank`` stray points beyond the shell do not move it.
    hull : bool
        Keep only the anchors on each window's convex hull (bridges over objects that hide
        the shell over several sectors, e.g. a conveyor and its load).

    Returns
    -------
    envelope : ndarray, shape (N,)
        Radius of the envelope of the point's window at the point's angle, metres.
    obliquity : ndarray, shape (N,)
        ``sqrt(1 + (d rho / d theta)^2 / rho^2)`` of the envelope there (1 where the shell
        faces the centreline; larger where it is seen at a grazing angle), so that a distance
        along the shell normal ``t`` is about ``t * obliquity`` along the radius.
    """
    wid, bin_ = _bins(window, theta, sectors)
    return _outer(wid, bin_, theta, rho, rank=rank, hull=hull)


def _outer(
    wid: np.ndarray,
    bin_: np.ndarray,
    theta: np.ndarray,
    rho: np.ndarray,
    *,
    rank: int,
    hull: bool,
    ray: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`outer_envelope` on precomputed window and bin ids (see :func:`_bins`)."""
    n = theta.shape[0]
    order = _order_in_bins(bin_, rho)
    b_sorted = bin_[order]
    starts = np.flatnonzero(np.r_[True, b_sorted[1:] != b_sorted[:-1]])
    ends = np.r_[starts[1:], n]
    pick = order[np.maximum(ends - 1 - rank, starts)]  # rank-th largest (or the smallest)
    a_win, a_theta, a_rho = wid[pick], theta[pick], rho[pick]
    if hull:
        on = _hull_anchors(a_win, a_theta, a_rho)
        a_win, a_theta, a_rho = a_win[on], a_theta[on], a_rho[on]
    return _ring(wid, theta, a_win, a_theta, a_rho, ray)


def _upper_anchors(
    wid: np.ndarray,
    bin_: np.ndarray,
    theta: np.ndarray,
    rho: np.ndarray,
    keep: np.ndarray,
    *,
    sectors: int,
    quantile: float = _ANCHOR_QUANTILE,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Anchors (window id, angle, radius) through the mean angle and the ``quantile`` of the
    radius of the ``keep`` points of each bin (an upper quantile: objects near the shell pull a
    mean inward); ``wid`` and ``bin_`` from :func:`_bins`."""
    kb, kt, kr = bin_[keep], theta[keep], rho[keep]
    order = _order_in_bins(kb, kr)
    kb, kt, kr = kb[order], kt[order], kr[order]
    starts = np.flatnonzero(np.r_[True, kb[1:] != kb[:-1]])
    cnt = np.diff(np.r_[starts, len(kb)])
    inv = np.repeat(np.arange(len(starts)), cnt)
    m_theta = np.bincount(inv, weights=kt) / cnt
    q_rho = kr[starts + np.floor(quantile * (cnt - 1)).astype(np.intp)]
    return kb[starts] // sectors, m_theta, q_rho


def _polar(proj: Projection) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Angle, radius and ray direction ``(cos, sin)`` of projected points around the axis."""
    theta = np.arctan2(proj.vertical, proj.lateral)
    rho = proj.distance
    safe = np.where(rho > 0.0, rho, 1.0)
    ray = (np.where(rho > 0.0, proj.lateral / safe, 1.0), proj.vertical / safe)
    return theta, rho, ray


@dataclass(frozen=True)
class ShellEnvelope:
    """The outer envelope of one epoch's shell: a closed polygon per chainage window.

    Built by :func:`shell_envelope`; :meth:`offset` evaluates it at any points projected on the
    same centreline, so that one epoch's points can be cut against another epoch's envelope.

    Attributes
    ----------
    window : float
        Length of the chainage windows, metres.
    sectors : int
        Angular sectors per turn.
    win : ndarray of int, shape (A,)
        Window index ``floor(chainage / window)`` of each anchor.
    theta, rho : ndarray, shape (A,)
        Angle (radians) and radius (metres) of each anchor around the centreline.
    max_obliquity : float
        Cap on the obliquity returned by :meth:`offset`.
    """

    window: float
    sectors: int
    win: np.ndarray
    theta: np.ndarray
    rho: np.ndarray
    max_obliquity: float

    def offset(self, projection: Projection) -> tuple[np.ndarray, np.ndarray]:
        """Radial offset of projected points from the envelope, and its capped obliquity.

        Parameters
        ----------
        projection : Projection
            The points projected on the centreline the envelope was built on.

        Returns
        -------
        offset : ndarray, shape (N,)
            ``rho - rho_envelope`` along each point's ray, metres (negative: inside); NaN in
            windows where the envelope has no anchor.
        obliquity : ndarray, shape (N,)
            ``1 / |cos(incidence)|`` of the envelope to the ray, capped at ``max_obliquity``
            (NaN with the offset).
        """
        return self._offset(projection)[:2]

    def _offset(
        self, projection: Projection
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`offset`, and the points' angles and window indices."""
        theta, rho, ray = _polar(projection)
        win = np.floor(projection.chainage / self.window).astype(np.int64)
        covered = np.isin(win, self.win)
        off = np.full(theta.shape, np.nan)
        obl = np.full(theta.shape, np.nan)
        if covered.any() and self.win.size >= 2:
            sel = (ray[0][covered], ray[1][covered])
            env, o = _ring(win[covered], theta[covered], self.win, self.theta, self.rho, sel)
            off[covered] = rho[covered] - env
            obl[covered] = np.minimum(o, self.max_obliquity)
        return off, obl, theta, win

    def matched_offset(
        self, projection: Projection, own_offset: np.ndarray, *, reach: int = _MATCH_REACH
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`offset`, less the local mean difference between this envelope and the points'
        own one.

        Parameters
        ----------
        projection : Projection
            The points projected on the centreline.
        own_offset : ndarray, shape (N,)
            The points' offsets from their own epoch's envelope.
        reach : int
            The mean is taken over the points of the same chainage window within this many
            angular sectors either side (15: a 31 degree arc, about 1.6 m of a 3 m radius).

        Returns
        -------
        offset, obliquity : ndarray, shape (N,)
            The offset is NaN where either envelope has no value (as is the obliquity where
            this one has none).

        Notes
        -----
        Where the shell moved between the epochs (or one epoch's envelope bridges something
        the other sees), the two envelopes differ by the motion; the local mean takes it out,
        and what is left is the envelopes' own noise, bin by bin.
        """
        off, obl, theta, win = self._offset(projection)
        delta = off - np.asarray(own_offset, dtype=np.float64)
        ok = np.isfinite(delta)
        shift = np.full(delta.shape, np.nan)
        if ok.any():
            uw, wi = np.unique(win[ok], return_inverse=True)
            sec = np.clip(
                ((theta[ok] + np.pi) / (2 * np.pi) * self.sectors).astype(np.int64),
                0,
                self.sectors - 1,
            )
            b = wi.ravel() * self.sectors + sec
            size = len(uw) * self.sectors
            total = np.bincount(b, weights=delta[ok], minlength=size).reshape(-1, self.sectors)
            count = np.bincount(b, minlength=size).reshape(-1, self.sectors).astype(np.float64)
            t_sum, c_sum = total.copy(), count.copy()
            for j in range(1, int(reach) + 1):  # circular box sum along the sectors
                t_sum += np.roll(total, j, axis=1) + np.roll(total, -j, axis=1)
                c_sum += np.roll(count, j, axis=1) + np.roll(count, -j, axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):  # empty arcs: unused
                shift[ok] = (t_sum / c_sum).ravel()[b]
        return off - shift, obl


def shell_envelope(
    xyz: np.ndarray,
    centerline: Centerline,
    *,
    window: float = 1.0,
    sectors: int = 360,
    search_tolerance: float = 0.12,
    max_obliquity: float = 4.0,
    projection: Projection | None = None,
    workers: int = -1,
) -> tuple[ShellEnvelope, np.ndarray, np.ndarray]:
    """The outer envelope of a cloud's shell, and the points' offsets from it.

    Parameters are those of :func:`classify_shell`.

    Returns
    -------
    envelope : ShellEnvelope
    offset, obliquity : ndarray, shape (N,)
        ``envelope.offset`` at the cloud's own points (computed on the way, at no extra cost).

    Raises
    ------
    InvalidCloudError, ConfigError
        As :func:`classify_shell`.
    """
    p = check_points(xyz, name="xyz")
    window = check_positive("window", window)
    max_obliquity = check_positive("max_obliquity", max_obliquity)
    if int(sectors) < 8:
        raise ConfigError(f"sectors must be an integer >= 8, got {sectors!r}")
    if projection is None:
        proj = centerline.project(p, workers=workers)
    elif np.shape(projection.chainage) != (p.shape[0],):
        raise InvalidCloudError(
            f"projection has {np.shape(projection.chainage)} rows, expected ({p.shape[0]},)"
        )
    else:
        proj = projection
    theta, rho, ray = _polar(proj)
    win = np.floor(proj.chainage / window).astype(np.int64)
    uniq, wid = np.unique(win, return_inverse=True)
    wid = wid.ravel().astype(np.int64)
    bin_ = _bins(wid, theta, int(sectors))[1]
    env, obl = _outer(wid, bin_, theta, rho, rank=1, hull=True, ray=ray)
    near = rho - env >= -search_tolerance * np.minimum(obl, max_obliquity)
    a_win, a_theta, a_rho = _upper_anchors(wid, bin_, theta, rho, near, sectors=int(sectors))
    env, obl = _ring(wid, theta, a_win, a_theta, a_rho, ray)
    envelope = ShellEnvelope(window, int(sectors), uniq[a_win], a_theta, a_rho, max_obliquity)
    return envelope, rho - env, np.minimum(obl, max_obliquity)


def shell_mask(
    offset: np.ndarray,
    obliquity: np.ndarray,
    *,
    inner_tolerance: float = 0.055,
    outer_tolerance: float = 0.1,
    other: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Shell points from their offsets to an envelope (see :func:`classify_shell`).

    Parameters
    ----------
    offset, obliquity : ndarray, shape (N,)
        From :func:`shell_envelope` (the points' own envelope).
    inner_tolerance, outer_tolerance : float
        As :func:`classify_shell`.
    other : (offset, obliquity), optional
        The same points' offsets to the other epoch's envelope, best with the two envelopes'
        local difference taken out (:meth:`ShellEnvelope.matched_offset`). A point is then
        inside if it is within ``inner_tolerance`` of either envelope, so both epochs are cut
        from the inner of the two. Two envelopes estimated from different points differ by
        their own noise, and the cut sits about two sigma into the noise of rough rock: cut
        each epoch from its own envelope and their means drift apart by millimetres, patch by
        patch (on two random halves of the real drift 9.5 % of the unchanged shell exceeded
        its LoD95, against 4.9 % with the common cut). NaN offsets (no envelope there) count
        as the own envelope.

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    inner_tolerance = check_positive("inner_tolerance", inner_tolerance)
    outer_tolerance = check_positive("outer_tolerance", outer_tolerance)
    with np.errstate(invalid="ignore"):
        inside = offset >= -inner_tolerance * obliquity
        if other is not None:
            inside |= other[0] >= -inner_tolerance * other[1]
        return inside & (offset <= outer_tolerance * obliquity)


def classify_shell(
    xyz: np.ndarray,
    centerline: Centerline,
    *,
    window: float = 1.0,
    sectors: int = 360,
    inner_tolerance: float = 0.055,
    outer_tolerance: float = 0.1,
    search_tolerance: float = 0.12,
    max_obliquity: float = 4.0,
    projection: Projection | None = None,
    workers: int = -1,
) -> np.ndarray:
    """Which points are the tunnel shell (True) rather than objects in front of it (False).

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Points, metres, in the centreline's frame.
    centerline : Centerline
        Tunnel axis.
    window : float
        Length of the chainage windows, metres.
    sectors : int
        Angular sectors per turn around the centreline (360: 1 degree, about 5 cm of a 3 m
        radius section).
    inner_tolerance : float
        Points more than this far inside the shell's envelope (along the shell normal, metres)
        are not shell. The envelope sits at the upper quartile of the shell's noise band, so
        0.055 m keeps the shell down to about 3 sigma of the scanner's +-3 cm (2 sigma) noise
        (paper §4, Table 1); pipes, the conveyor, coal and people stand further off the rock.
        Objects closer to the rock than the noise (cables) cannot be told from it.
    outer_tolerance : float
        Points more than this far beyond the envelope are not shell (stray returns), metres.
    search_tolerance : float
        Points within this distance inside the outer hull are the candidates from which the
        shell's envelope is estimated, metres.
    max_obliquity : float
        Cap on the radial stretch of the tolerances where the shell is seen at a grazing angle
        from the centreline (roof corners of a wide rectangular section).
    projection : Projection, optional
        ``centerline.project(xyz)`` when the caller already has it (saves a projection).
    workers : int
        Threads for the centreline projection.

    Returns
    -------
    ndarray of bool, shape (N,)
        True on the shell.

    Raises
    ------
    InvalidCloudError
        If ``xyz`` is not N x 3 finite coordinates, or ``projection`` has another length.
    ConfigError
        If a window, tolerance or sector count is not positive.

    Notes
    -----
    (1) Project the points on the centreline: chainage ``s``, angle ``theta`` and radius
    ``rho`` in the normal plane. (2) In each (window, sector) bin take the second-largest radius
    and its angle as an anchor; keep the anchors on the convex hull of each window (tunnel
    sections are convex: a conveyor or a pipe that hides the rock over several sectors dents
    the anchors inward and drops off the hull). (3) Candidates are the points within
    ``search_tolerance`` inside that hull; the shell's envelope joins, bin by bin, their mean
    angle and the upper quartile of their radii. Envelopes are closed polygons evaluated along
    each point's own ray, so they follow the section inside a sector (a flat roof seen
    obliquely). (4) A point is shell when ``-inner_tolerance * f <= rho - rho_env <=
    outer_tolerance * f``, ``f`` being the obliquity of the envelope to the ray (capped at
    ``max_obliquity``).

    Limits: a dent of the shell deeper than ``search_tolerance`` relative to the hull of its
    window (a large bulge, or a side recess such as a chamber, whose mouth the hull bridges) is
    taken for an object in front of the shell.
    """
    inner_tolerance = check_positive("inner_tolerance", inner_tolerance)
    outer_tolerance = check_positive("outer_tolerance", outer_tolerance)
    _, off, obl = shell_envelope(
        xyz,
        centerline,
        window=window,
        sectors=sectors,
        search_tolerance=search_tolerance,
        max_obliquity=max_obliquity,
        projection=projection,
        workers=workers,
    )
    shell = shell_mask(off, obl, inner_tolerance=inner_tolerance, outer_tolerance=outer_tolerance)
    logger.debug("shell: %d of %d points", int(shell.sum()), len(shell))
    return shell
