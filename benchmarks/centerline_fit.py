"""Centreline fitting methods against synthetic truth (the paper's Fig. 16, measured).

For each synthetic tunnel (straight with a chamber and clutter, curved R = 120 m, arched
section) the slice centres are extracted once (paper §3.1: KDE roof/floor, linear-KDE + Canny +
Hough walls, re-slicing normal to the curve) and then fitted by

- ``nurbs``: the least-squares cubic NURBS of :mod:`tunneldef.centerline.fit` (ours);
- ``nurbs 1 pass``: the same, slicing only along the PCA axis as the paper does;
- ``lsq line``: a least-squares straight line through the centres (paper Fig. 16, blue);
- ``cubic b-spline``: a plain cubic B-spline through every centre (paper Fig. 16, green).

Widths of the trapezoid are measured at the middle of the wall band (not the floor width), so
its width error column is not meaningful.

Centre error = distance from the fitted curve to the design axis, over the interior (1 m from
each end), in millimetres. Time = slicing + fitting for the NURBS rows, fitting only for the
others (they reuse the NURBS rows' centres).

Run: ``python benchmarks/centerline_fit.py [--density 400] [--seed 0]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tunneldef.centerline import extract_centerline
from tunneldef.centerline.fit import fit_cubic_bspline, fit_line
from tunneldef.config import CenterlineConfig
from tunneldef.curve import Centerline
from tunneldef.synth import SectionSpec, TunnelSpec, make_tunnel


def _errors(cl: Centerline, truth: Centerline) -> np.ndarray:
    p = truth.project(cl.points)
    keep = (p.chainage > 1.0) & (p.chainage < truth.length - 1.0)
    return p.distance[keep] * 1000.0


def _note(res, spec: TunnelSpec, n: int) -> str:  # noqa: ANN001
    ok = res.accepted
    w = np.array([r.width for r in ok]) - spec.section.width
    h = np.array([r.height for r in ok]) - spec.section.height
    return (
        f"{len(ok)}/{len(res.slices)} slices, {res.passes} passes, {n / 1e3:.0f} k pts, "
        f"width/height err p95 {np.percentile(np.abs(w), 95) * 1000:.0f}/"
        f"{np.percentile(np.abs(h), 95) * 1000:.0f} mm"
    )


def _roll_about_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    m = np.eye(4)
    m[1:3, 1:3] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return m


def _cases(density: float) -> dict[str, TunnelSpec]:
    return {
        "straight+chamber+clutter": TunnelSpec(
            length=30.0,
            density=density,
            chamber=True,
            equipment=True,
            conveyor=True,
            holes=3,
            people=2,
        ),
        "curved R=120 m": TunnelSpec(length=60.0, radius=120.0, density=density, equipment=True),
        "arch section": TunnelSpec(
            length=30.0, section=SectionSpec(kind="arch"), density=density, equipment=True
        ),
        "trapezoid+conveyor": TunnelSpec(
            length=30.0,
            section=SectionSpec(kind="trapezoid"),
            density=density,
            equipment=True,
            conveyor=True,
        ),
        "rolled 3 deg (tilted scan)": TunnelSpec(length=30.0, density=density, equipment=True),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--density", type=float, default=400.0, help="points per m^2 of shell")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    header = f"{'tunnel':27s} {'method':16s} {'p50 mm':>8s} {'p95 mm':>8s} {'max mm':>8s} "
    header += f"{'time s':>7s}  notes"
    print(header)
    print("-" * len(header))
    for name, spec in _cases(args.density).items():
        cloud, truth = make_tunnel(spec, seed=args.seed)
        design = truth.centerline
        if name.startswith("rolled"):
            m = _roll_about_x(3.0)
            cloud, design = cloud.transformed(m), design.transformed(m)
        rows = []
        t0 = time.perf_counter()
        res = extract_centerline(cloud.xyz)
        t_nurbs = time.perf_counter() - t0
        ok = res.accepted
        centres = np.array([r.centre for r in ok])
        stations = np.array([r.station for r in ok])
        rows.append(("nurbs", res.centerline, t_nurbs, _note(res, spec, len(cloud.xyz))))
        t0 = time.perf_counter()
        single = extract_centerline(
            cloud.xyz, settings=CenterlineConfig(max_iterations=0)
        )
        dt = time.perf_counter() - t0
        rows.append(("nurbs 1 pass", single.centerline, dt, _note(single, spec, len(cloud.xyz))))
        t0 = time.perf_counter()
        line = fit_line(centres)
        rows.append(("lsq line", line, time.perf_counter() - t0, ""))
        t0 = time.perf_counter()
        spline = fit_cubic_bspline(centres, params=stations)
        rows.append(("cubic b-spline", spline, time.perf_counter() - t0, ""))
        for method, cl, dt, note in rows:
            e = _errors(cl, design)
            p50, p95, mx = np.percentile(e, 50), np.percentile(e, 95), e.max()
            print(f"{name:27s} {method:16s} {p50:8.1f} {p95:8.1f} {mx:8.1f} {dt:7.2f}  {note}")
        print()


if __name__ == "__main__":
    main()
