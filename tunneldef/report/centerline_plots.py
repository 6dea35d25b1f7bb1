"""Diagnostic figures of a centreline extraction (PNG analogues of the paper's Fig. 3, 4, 12, 15
and 16; matplotlib, Agg backend).

- ``centerline_fig03_roof_floor.png``: one slice's cross-section with the floor (red) and roof
  (green) lines, beside the Gaussian kernel density of its heights with the two peaks;
- ``centerline_fig04_walls.png``: the slice's top view with the wall lines, its linear-kernel
  density image, and the Canny edges with the Hough lines (first = left in red, last = right in
  green);
- ``centerline_fig12_slices.png``: cross-sections and height densities of several slices;
- ``centerline_fig15_wall_lines.png``: plan view of the wall points of every accepted slice and
  the NURBS lines through them;
- ``centerline_fig16_fit_comparison.png``: the NURBS centreline against a least-squares straight
  line and a plain interpolating cubic B-spline, in plan and as lateral offsets from the line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..centerline import CenterlineResult, SliceRecord, analyse_slice
from ..centerline.fit import fit_centerline, fit_cubic_bspline, fit_line
from ._figures import figures

__all__ = ["plot_centerline_diagnostics"]

_MAX_SCATTER = 150_000


def _pick(result: CenterlineResult, k: int) -> list[SliceRecord]:
    ok = result.accepted
    if not ok:
        return []
    idx = np.unique(np.round(np.linspace(0, len(ok) - 1, k + 2)[1:-1]).astype(int))
    return [ok[i] for i in idx]


def _slice_points(result: CenterlineResult, local: np.ndarray, rec: SliceRecord) -> np.ndarray:
    half = result.slicing.thickness / 2
    return local[np.abs(local[:, 0] - rec.station) <= half]


def _section_and_kde(ax_sec, ax_kde, pts: np.ndarray, rec: SliceRecord, result) -> None:  # noqa: ANN001
    rf, walls, band = analyse_slice(
        pts, rec.station, slicing=result.slicing, settings=result.settings
    )
    ax_sec.scatter(pts[:, 1], pts[:, 2], s=1, c="0.4", lw=0)
    ax_sec.scatter(pts[band, 1], pts[band, 2], s=1, c="tab:blue", lw=0)
    if rf.ok:
        ax_sec.axhline(rf.floor, color="red", lw=1.2, label=f"floor {rf.floor:+.3f} m")
        ax_sec.axhline(rf.roof, color="green", lw=1.2, label=f"roof {rf.roof:+.3f} m")
    if walls is not None and walls.ok:
        ax_sec.axvline(walls.left, color="red", ls="--", lw=1)
        ax_sec.axvline(walls.right, color="green", ls="--", lw=1)
    ax_sec.set_aspect("equal")
    ax_sec.invert_xaxis()  # looking along increasing chainage: left wall on the left
    ax_sec.set_xlabel("lateral (m, + left)")
    ax_sec.set_ylabel("vertical (m)")
    ax_sec.set_title(f"slice at chainage {rec.chainage:.2f} m")
    ax_sec.legend(loc="upper right", fontsize=7)
    if rf.grid.size:
        ax_kde.plot(rf.grid, rf.density, color="tab:blue", lw=1)
        dens_at = np.interp(rf.peaks, rf.grid, rf.density)
        ax_kde.scatter(rf.peaks, dens_at, s=12, c="0.5", zorder=3, label="peaks")
        if rf.ok:
            for z, colour in ((rf.floor, "red"), (rf.roof, "green")):
                ax_kde.scatter([z], [np.interp(z, rf.grid, rf.density)], s=40, c=colour, zorder=4)
    ax_kde.set_xlabel("vertical (m)")
    ax_kde.set_ylabel("density")
    ax_kde.set_title("Gaussian KDE of heights")


def _fig03(plt, result, local, rec, path: Path) -> Path:  # noqa: ANN001
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    _section_and_kde(a, b, _slice_points(result, local, rec), rec, result)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fig04(plt, result, local, rec, path: Path) -> Path:  # noqa: ANN001
    pts = _slice_points(result, local, rec)
    _, walls, band = analyse_slice(
        pts, rec.station, slicing=result.slicing, settings=result.settings
    )
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    bp = pts[band]
    axes[0].scatter(bp[:, 0], bp[:, 1], s=2, c="0.3", lw=0)
    if walls is not None and walls.ok:
        u = np.array([walls.extent[0], walls.extent[1]])
        axes[0].plot(u, walls.left + walls.left_slope * (u - rec.station), "r-", lw=1.5)
        axes[0].plot(u, walls.right + walls.right_slope * (u - rec.station), "g-", lw=1.5)
    axes[0].set_xlabel("along axis (m)")
    axes[0].set_ylabel("lateral (m, + left)")
    axes[0].set_title("top view of the wall band")
    if walls is not None and walls.image.size:
        u0, u1, v0, v1 = walls.extent
        extent = (u0, u1, v0, v1)
        axes[1].imshow(walls.image, extent=extent, aspect="auto", cmap="Blues")
        axes[1].scatter(bp[:, 0], bp[:, 1], s=1, c="red", lw=0)
        axes[1].set_title("linear-kernel density (eq. 3)")
        axes[2].imshow(walls.edges, extent=extent, aspect="auto", cmap="gray")
        u = np.array([u0, u1])
        for i, (v, slope) in enumerate(walls.lines):
            colour = "red" if i == 0 else "lime" if i == len(walls.lines) - 1 else "0.6"
            axes[2].plot(u, v + slope * (u - rec.station), color=colour, lw=1.2)
        axes[2].set_title(f"Canny + Hough ({len(walls.lines)} lines)")
        for ax in axes[1:]:
            ax.set_xlabel("along axis (m)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fig12(plt, result, local, recs, path: Path) -> Path:  # noqa: ANN001
    fig, axes = plt.subplots(len(recs), 2, figsize=(11, 3.6 * len(recs)), squeeze=False)
    for (a, b), rec in zip(axes, recs, strict=True):
        _section_and_kde(a, b, _slice_points(result, local, rec), rec, result)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _plan(result, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    p = result.frame.to_local(xyz)
    return p[:, 0], p[:, 1]


def _plan_background(ax, result, xyz: np.ndarray) -> None:  # noqa: ANN001
    step = max(1, len(xyz) // _MAX_SCATTER)
    p = result.frame.to_local(xyz[::step])
    ax.scatter(p[:, 0], p[:, 1], s=0.3, c="0.8", lw=0, rasterized=True)
    ax.set_xlabel("x along the PCA axis (m)")
    ax.set_ylabel("y across (m, + left)")


def _fig15(plt, result, xyz, path: Path) -> Path:  # noqa: ANN001
    ok = result.accepted
    mid = np.array([(r.floor + r.roof) / 2 for r in ok])
    st = np.array([r.station for r in ok])
    left = result.to_world(np.stack([st, [r.left for r in ok], mid], axis=1))
    right = result.to_world(np.stack([st, [r.right for r in ok], mid], axis=1))
    fig, ax = plt.subplots(figsize=(12, 5))
    _plan_background(ax, result, xyz)
    c = result.settings
    for pts, colour, name in ((left, "red", "left"), (right, "green", "right")):
        ax.scatter(*_plan(result, pts), s=10, c=colour, label=f"{name} wall lines (slices)")
        if len(pts) > c.degree:
            cl, fit = fit_centerline(
                pts,
                params=st,
                degree=c.degree,
                ctrl_spacing=c.ctrl_spacing,
                sample_step=c.sample_step,
            )
            ax.plot(*_plan(result, cl.points), "k-", lw=1)
            ax.scatter(*_plan(result, fit.ctrlpts), s=12, c="tab:blue", marker="s")
    cl = result.centerline
    ax.plot(*_plan(result, cl.points), "k--", lw=1, label="centreline")
    ax.set_title("wall lines along the tunnel, NURBS fits (black) and control points (blue)")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fig16(plt, result, xyz, path: Path) -> Path:  # noqa: ANN001
    ok = result.accepted
    centres = np.array([r.centre for r in ok])
    st = np.array([r.station for r in ok])
    nurbs = result.centerline
    line = fit_line(centres)
    bspline = fit_cubic_bspline(centres, params=st)
    fig, (a, b) = plt.subplots(2, 1, figsize=(12, 8), height_ratios=(1.2, 1))
    _plan_background(a, result, xyz)
    curves = (
        (nurbs, "red", "NURBS (least squares, cubic)"),
        (line, "tab:blue", "least-squares straight line"),
        (bspline, "green", "cubic B-spline through centres"),
    )
    for cl, colour, name in curves:
        a.plot(*_plan(result, cl.points), color=colour, lw=1.2, label=name)
    a.scatter(*_plan(result, centres), s=8, c="k", label="slice centres", zorder=3)
    a.legend(fontsize=7)
    a.set_title("centreline fitting methods (paper Fig. 16)")
    ref = line.project(centres)
    b.scatter(ref.chainage, ref.lateral * 100, s=8, c="k", label="slice centres")
    for cl, colour, name in curves:
        p = line.project(cl.points)
        b.plot(p.chainage, p.lateral * 100, color=colour, lw=1.2, label=name)
    b.set_xlabel("distance along the straight line (m)")
    b.set_ylabel("lateral offset from the line (cm)")
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_centerline_diagnostics(
    result: CenterlineResult, xyz: np.ndarray, out_dir: str | Path, *, slices: int = 3
) -> list[Path]:
    """Write the centreline diagnostic figures as PNG files.

    Parameters
    ----------
    result : CenterlineResult
        Output of :func:`tunneldef.centerline.extract_centerline` for ``xyz``.
    xyz : ndarray, shape (N, 3)
        The cloud the centreline was extracted from, world coordinates, metres.
    out_dir : str or Path
        Directory for the figures (created if missing).
    slices : int
        Number of slices shown in the multi-slice figure (Fig. 12 analogue).

    Returns
    -------
    list of Path
        The files written (Fig. 3, 4, 12, 15, 16 analogues; 3, 4 and 12 need an accepted slice).
    """
    plt = figures()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    xyz = np.asarray(xyz, dtype=np.float64)
    local = result.slice_coordinates(xyz)
    picks = _pick(result, max(int(slices), 1))
    written = []
    if picks:
        mid = picks[len(picks) // 2]
        written.append(_fig03(plt, result, local, mid, out / "centerline_fig03_roof_floor.png"))
        written.append(_fig04(plt, result, local, mid, out / "centerline_fig04_walls.png"))
        written.append(_fig12(plt, result, local, picks, out / "centerline_fig12_slices.png"))
    if len(result.accepted) > result.settings.degree:
        written.append(_fig15(plt, result, xyz, out / "centerline_fig15_wall_lines.png"))
        written.append(_fig16(plt, result, xyz, out / "centerline_fig16_fit_comparison.png"))
    return written
