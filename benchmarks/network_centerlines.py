"""Centreline networks against the truth of the synthetic 250 m drift network.

For the reference epoch of :func:`tunneldef.synth.network.network_250m_pair` (main drift, three
cross-cuts, a 4-way crossing, a 12 % ramp with a bend; SLAM drift; strays) this extracts the
centreline network and prints, per truth branch, how much of it an edge covers and the centre
error (distance from the truth axis, moved by the epoch's own SLAM drift, to the nearest edge
curve), every 0.25 m, 1 m inside the scanned ends and away from the junctions: 2 m beyond
where another drift's tube cuts the section.

Usage: ``python benchmarks/network_centerlines.py [--density 300] [--seed 0]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial import cKDTree

from tunneldef.centerline.network import extract_network
from tunneldef.synth.network import make_network_pair


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--density", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    pair = make_network_pair(density=args.density, seed=args.seed)
    truth = pair.truth
    t0 = time.perf_counter()
    net = extract_network(pair.ref.xyz).network
    took = time.perf_counter() - t0
    print(f"{len(pair.ref):,} points: {len(net.edges)} edges, {len(net.junctions)} junctions, "
          f"{net.length:.1f} m in {took:.1f} s")
    for e in net.edges:
        zones = [tuple(float(v) for v in np.round(z, 1)) for z in e.zones]
        print(f"  edge {e.id}: {e.length:6.1f} m, {sum(r.ok for r in e.slices)} of "
              f"{len(e.slices)} slices fitted, junction zones {zones}")
    tr = truth.ref
    drift = tr.drift_offset()
    print("branch  length  scanned        covered  p95 (mm)  max (mm)  samples")
    for b, branch in enumerate(truth.branches):
        m = tr.branch == b
        if not m.any():
            continue
        s0, s1 = float(np.nanmin(tr.chainage[m])), float(np.nanmax(tr.chainage[m]))
        s = np.arange(max(s0, 0.0) + 1.0, min(s1, branch.length) - 1.0, 0.25)
        p = branch.centerline.point_at(s)
        order = np.argsort(tr.chainage[m])
        cs, dr = tr.chainage[m][order], drift[m][order]
        lo, hi = np.searchsorted(cs, s - 0.5), np.searchsorted(cs, s + 0.5)
        p += np.array([np.median(dr[a:c], axis=0) if c > a else np.zeros(3)
                       for a, c in zip(lo, hi, strict=True)])
        # at a junction where another drift's tube cuts this one's section, and 2 m either side
        cut = np.zeros(len(p), dtype=bool)
        for o in truth.branches:
            if o is not branch:
                d, _ = cKDTree(o.centerline.points[:, :2]).query(p[:, :2])
                cut |= d < o.radius + branch.radius
        pad = int(round(2.0 / 0.25))
        away = ~np.convolve(cut, np.ones(2 * pad + 1), mode="same").astype(bool)
        pr = net.project(p[away])
        err = np.where(pr.inside, pr.distance, np.inf)
        hit = err < 0.5
        print(f"{branch.name:12s} {branch.length:6.1f}  {s0:5.1f}-{s1:5.1f}  {hit.mean():7.3f}  "
              f"{1e3 * np.percentile(err[hit], 95):8.1f}  {1e3 * err[hit].max():8.1f}  "
              f"{hit.sum()}")


if __name__ == "__main__":
    main()
