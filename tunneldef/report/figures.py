"""Figures of a deformation result (matplotlib, Agg backend, PNG files).

- :func:`plot_deformation_map`: the shell unrolled (chainage x position around the section),
  coloured by signed deformation on a diverging scale centred on 0;
- :func:`plot_danger_map`: the same unrolled view, shell points over the danger threshold in red;
- :func:`plot_cross_section`: one section of both epochs overlaid, compared points coloured by
  deformation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.stats import binned_statistic_2d

from ..curve import Centerline
from ._figures import figures

__all__ = ["unrolled_angle", "plot_deformation_map", "plot_danger_map", "plot_cross_section"]


def unrolled_angle(lateral: np.ndarray, vertical: np.ndarray) -> np.ndarray:
    """Position around the section in degrees: 0 floor, 90 left wall, 180 roof, 270 right wall."""
    return (np.degrees(np.arctan2(vertical, lateral)) + 90.0) % 360.0


def _unrolled(xyz: np.ndarray, centerline: Centerline) -> tuple[np.ndarray, np.ndarray]:
    pr = centerline.project(xyz)
    return pr.chainage, unrolled_angle(pr.lateral, pr.vertical)


def _bins(chainage: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.nanpercentile(chainage, [0.1, 99.9])
    n = int(np.clip((hi - lo) / 0.1, 10, 1500))
    return np.linspace(lo, hi, n + 1), np.linspace(0.0, 360.0, 181)


def _decorate_unrolled(ax, title: str) -> None:  # noqa: ANN001
    ax.set_xlabel("chainage along the reference centreline (m)")
    ax.set_ylabel("position around the section")
    ax.set_yticks([0, 90, 180, 270, 360], ["floor", "left wall", "roof", "right wall", "floor"])
    ax.set_title(title)


def plot_deformation_map(
    xyz: np.ndarray, deformation: np.ndarray, centerline: Centerline, path: Path, *,
    shell: np.ndarray | None = None, limit: float | None = None,
) -> Path:
    """Unrolled map of the median signed deformation per 0.1 m x 2 deg cell.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        Registered compared points (reference frame), metres.
    deformation : ndarray, shape (N,)
        Signed deformation, metres (negative = into the tunnel).
    limit : float, optional
        Colour saturation, metres (default: the 99th percentile of |deformation|).
    """
    plt = figures()
    s, a = _unrolled(xyz, centerline)
    keep = np.isfinite(deformation) & (np.ones(len(s), bool) if shell is None else shell)
    sb, ab = _bins(s[keep])
    stat = binned_statistic_2d(s[keep], a[keep], deformation[keep] * 1e3, "median",
                               bins=[sb, ab]).statistic
    lim = 1e3 * (limit or float(np.nanpercentile(np.abs(deformation[keep]), 99)) or 1.0)
    fig, ax = plt.subplots(figsize=(11, 4.2), constrained_layout=True)
    im = ax.pcolormesh(sb, ab, stat.T, cmap="RdBu", vmin=-lim, vmax=lim, shading="flat")
    fig.colorbar(im, ax=ax, label="deformation (mm); red: into the tunnel")
    _decorate_unrolled(ax, "Deformation of the tunnel shell, unrolled")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_danger_map(
    xyz: np.ndarray, danger: np.ndarray, centerline: Centerline, path: Path, *,
    shell: np.ndarray | None = None, threshold: float | None = None,
) -> Path:
    """Unrolled map: cells holding points over the danger threshold red, the rest green."""
    plt = figures()
    from matplotlib.colors import ListedColormap

    s, a = _unrolled(xyz, centerline)
    sb, ab = _bins(s)
    keep = np.ones(len(s), bool) if shell is None else np.asarray(shell, bool)
    frac = binned_statistic_2d(s[keep], a[keep], np.asarray(danger, float)[keep], "mean",
                               bins=[sb, ab]).statistic
    cls = np.where(np.isnan(frac), np.nan, (frac >= 0.5).astype(float))
    fig, ax = plt.subplots(figsize=(11, 4.2), constrained_layout=True)
    ax.pcolormesh(sb, ab, cls.T, cmap=ListedColormap(["#3a9d3a", "#d62728"]), vmin=0, vmax=1,
                  shading="flat")
    label = f" (|deformation| > {1e3 * threshold:.0f} mm)" if threshold else ""
    _decorate_unrolled(ax, f"Danger zones{label}: red = over the threshold, green = safe")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_cross_section(
    ref_xyz: np.ndarray, cmp_xyz: np.ndarray, deformation: np.ndarray,
    centerline: Centerline, chainage: float, path: Path, *, thickness: float = 0.2,
    limit: float | None = None,
) -> Path:
    """Both epochs' points within ``thickness`` of one chainage, in the section plane."""
    plt = figures()
    pr_r, pr_c = centerline.project(ref_xyz), centerline.project(cmp_xyz)
    mr = np.abs(pr_r.chainage - chainage) <= thickness / 2
    mc = np.abs(pr_c.chainage - chainage) <= thickness / 2
    fig, ax = plt.subplots(figsize=(7, 5), constrained_layout=True)
    ax.scatter(-pr_r.lateral[mr], pr_r.vertical[mr], s=1, c="0.6", label="reference")
    d = deformation[mc] * 1e3
    ok = np.isfinite(d)
    lim = 1e3 * limit if limit else (float(np.nanpercentile(np.abs(d), 99)) if ok.any() else 1.0)
    if (~ok).any():
        ax.scatter(-pr_c.lateral[mc][~ok], pr_c.vertical[mc][~ok], s=1, c="k",
                   label="compared, no value (no reference surface)")
    sc = ax.scatter(-pr_c.lateral[mc][ok], pr_c.vertical[mc][ok], s=2, c=d[ok], cmap="RdBu",
                    vmin=-lim, vmax=lim, label="compared (registered)")
    fig.colorbar(sc, ax=ax, label="deformation (mm)")
    ax.set_aspect("equal")
    ax.set_xlabel("across the tunnel, looking along increasing chainage (m; right +)")
    ax.set_ylabel("vertical offset from the centreline (m)")
    ax.set_title(f"Cross-section at chainage {chainage:.2f} m (+-{thickness / 2:.2f} m)")
    ax.legend(loc="upper right", markerscale=6, fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
