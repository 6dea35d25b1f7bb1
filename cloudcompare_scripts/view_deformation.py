#!/usr/bin/env python3
"""Show a tunneldef result coloured by ``deformation`` on a diverging scale centred on 0.

Usage
-----
    python view_deformation.py OUT.ply                 # a window (Open3D) if a display exists
    python view_deformation.py OUT.ply --png view.png  # no window: a PNG (matplotlib)
    python view_deformation.py OUT.ply --limit 0.03 --field deformation_vertical

Colours: red = the surface moved into the tunnel (negative: roof sag, wall bulge, floor
heave), white = no change, blue = outward; saturated symmetrically at +-limit (default: the
98th percentile of |deformation|, at least 1 mm). matplotlib's ``RdBu``, as in the report
figures; the CloudCompare plugin and ``batch_detect.py`` use the same Red>White>Blue order.
Points without a value (NaN) are grey.

Without a display (or with ``--png``) the PNG shows the tunnel surface unrolled around its
main axis (along x angle: roof, walls, floor) and a side view, with the colour bar; it needs
only matplotlib.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
from tunneldef_cloudcompare.colours import symmetric_limit

_GREY = np.array([0.6, 0.6, 0.6])
#: Diverging colour map: red = negative (into the tunnel), blue = positive (report figures).
CMAP = "RdBu"


def load(
    path: str | os.PathLike, field: str = "deformation"
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(xyz (N,3), values (N,), chainage (N,) or None)`` of a result file (float64)."""
    from tunneldef.io import read

    cloud = read(path)
    if field not in cloud.fields:
        raise SystemExit(f"{path} has no field {field!r}; fields: {sorted(cloud.fields)}")
    ch = cloud.fields.get("chainage")
    return (
        cloud.xyz,
        np.asarray(cloud.fields[field], dtype=np.float64),
        None if ch is None else np.asarray(ch, dtype=np.float64),
    )


def colours(values: np.ndarray, limit: float) -> np.ndarray:
    """RGB in [0, 1], shape (N, 3): matplotlib's ``RdBu`` over [-limit, +limit] (red =
    negative = into the tunnel), NaN grey."""
    from matplotlib import colormaps

    t = np.clip((np.asarray(values, dtype=np.float64) / limit + 1.0) / 2.0, 0.0, 1.0)
    rgb = colormaps[CMAP](np.nan_to_num(t, nan=0.5))[:, :3]
    rgb[~np.isfinite(values)] = _GREY
    return rgb


def has_display() -> bool:
    """True if a window can be opened (X11/Wayland on Linux; always on Windows/macOS)."""
    if sys.platform.startswith(("win", "darwin")):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def show_window(xyz: np.ndarray, rgb: np.ndarray, title: str) -> None:
    """An Open3D window (coordinates recentred: survey coordinates exceed float32)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz - xyz.mean(axis=0)))
    pcd.colors = o3d.utility.Vector3dVector(rgb)
    o3d.visualization.draw_geometries([pcd], window_name=title)


def _main_axes(xyz: np.ndarray) -> np.ndarray:
    """Horizontal main axis (unit, z = 0) of the cloud, from a PCA of x, y."""
    xy = xyz[:, :2] - xyz[:, :2].mean(axis=0)
    w, v = np.linalg.eigh(np.cov(xy[:: max(1, len(xy) // 50000)].T))
    return np.array([*v[:, np.argmax(w)], 0.0])


def unrolled(
    xyz: np.ndarray, chainage: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(along, angle_deg, height)`` of points around the tunnel's main horizontal axis.

    ``along``: position along the axis (m); ``angle_deg``: direction from the section centre
    (0 = roof, 90 = left wall, -90 = right wall, +-180 = floor); ``height`` above the
    section centre (m). A straight-axis approximation: good enough for a picture. With the
    ``chainage`` field the axis points towards increasing chainage (so "left" is left when
    looking that way) and ``along`` is the chainage itself.
    """
    p = xyz - xyz.mean(axis=0)
    axis = _main_axes(p)
    along = p @ axis
    if chainage is not None:
        ok = np.isfinite(chainage)
        if ok.sum() > 2 and np.corrcoef(along[ok], chainage[ok])[0, 1] < 0:
            axis, along = -axis, -along
        along = np.where(ok, chainage, along)
    across = p @ np.array([-axis[1], axis[0], 0.0])
    z = p[:, 2]
    yc = 0.5 * (np.percentile(across, 1) + np.percentile(across, 99))
    zc = 0.5 * (np.percentile(z, 1) + np.percentile(z, 99))
    angle = np.degrees(np.arctan2(across - yc, z - zc))
    return along, angle, z - zc


def save_png(
    xyz: np.ndarray,
    values: np.ndarray,
    limit: float,
    out: str | os.PathLike,
    *,
    title: str = "deformation",
    chainage: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
    cmap: Any = CMAP,
    max_points: int = 80_000,
    dpi: int = 80,
) -> Path:
    """The tunnel surface unrolled (along x angle) and a side view, coloured by ``values``
    (or by the given ``rgb`` (N, 3) in [0, 1], e.g. colours computed by CloudCompare; then
    pass the matching ``cmap`` (name or Colormap) for the colour bar)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize

    rng = np.random.default_rng(0)
    idx = np.arange(len(xyz))
    if len(idx) > max_points:
        idx = np.sort(rng.choice(idx, max_points, replace=False))
    v = values[idx]
    along, angle, height = unrolled(xyz[idx], None if chainage is None else chainage[idx])
    order = np.argsort(np.abs(np.nan_to_num(v)))  # largest changes drawn on top
    rgb = colours(v, limit) if rgb is None else np.asarray(rgb, dtype=np.float64)[idx]

    fig, (ax1, ax2) = plt.subplots(
        2, 1, figsize=(9, 5.6), sharex=True, gridspec_kw={"hspace": 0.3, "height_ratios": [1.6, 1]}
    )
    ax1.scatter(along[order], angle[order], c=rgb[order], s=2, linewidths=0, rasterized=True)
    ax1.set_ylim(-180, 180)
    ax1.set_yticks([-180, -90, 0, 90, 180])
    ax1.set_yticklabels(["floor", "right wall", "roof", "left wall", "floor"])
    ax1.set_title(f"{title}: tunnel surface unrolled around its axis")
    ax2.scatter(along[order], height[order], c=rgb[order], s=2, linewidths=0, rasterized=True)
    ax2.set_xlabel("chainage (m)" if chainage is not None else "along the tunnel (m)")
    ax2.set_ylabel("height (m)")
    ax2.set_title("side view")
    sm = plt.cm.ScalarMappable(norm=Normalize(-limit * 1000, limit * 1000), cmap=cmap)
    cb = fig.colorbar(sm, ax=[ax1, ax2], shrink=0.9)
    cb.set_label("mm  (red: into the tunnel, blue: outward)")
    out = Path(out)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("result", help="output of `tunneldef detect` (PLY, LAS, LAZ, ...)")
    ap.add_argument("--field", default="deformation", help="field to show (default deformation)")
    ap.add_argument("--limit", type=float, help="colour saturation, m (default: 98th pct)")
    ap.add_argument("--png", help="write this PNG instead of opening a window")
    args = ap.parse_args(argv)
    xyz, values, chainage = load(args.result, args.field)
    limit = args.limit if args.limit else symmetric_limit(values)
    if args.png or not has_display():
        png = args.png or str(Path(args.result).with_suffix(".png"))
        out = save_png(xyz, values, limit, png, title=args.field, chainage=chainage)
        print(f"wrote {out}")
    else:
        show_window(xyz, colours(values, limit), f"{args.field} (+-{limit * 1000:.0f} mm)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
