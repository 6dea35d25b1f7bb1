"""Synthetic drift networks: the 250 m preset pair at survey densities (counts, time, memory).

Generates :func:`tunneldef.synth.network_250m_pair` (a main drift, three cross-cuts, a 4-way
crossing, a 12 % ramp with a bend; five deformations; SLAM drift; strays) at each density and
prints, per epoch, the points per branch (shell / equipment / coal / outliers), the strays,
the generation time and the memory; ``--out DIR`` also writes each pair (``ref``/``cmp`` clouds
through :func:`tunneldef.io.write`, ``truth.npz``) into ``DIR/d<density>/``.

Detection scoring against the truth (per branch and per deformation) plugs in through
:data:`SCORERS`: functions ``pair -> dict of name: value`` whose results are printed per pair.

Usage: ``python benchmarks/networks.py [--densities 300,1000] [--seed 0] [--out DIR]
[--fmt laz|las|ply]``

Measured (one run, 2 cores shared with other work): 1.1 + 1.2 M points in 6-11 s at
300 points/m^2, 3.8 + 3.9 M points in 13-31 s at 1000 points/m^2 with 0.9 GB of arrays at the
peak; writing the 1000 points/m^2 pair as LAZ with its compressed truth takes about 40 s.
"""

from __future__ import annotations

import argparse
import resource
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np

from tunneldef.synth import LABEL_DYNAMIC, LABEL_EQUIPMENT, LABEL_OUTLIER, LABEL_SHELL
from tunneldef.synth.network import (
    NetworkPair,
    make_network_pair,
    network_250m_pair,
    write_network_pair,
)

#: Scorers run on every generated pair: ``pair -> {name: value}`` (none yet).
SCORERS: list[Callable[[NetworkPair], dict[str, float]]] = []


def branch_table(pair: NetworkPair) -> str:
    """A markdown table of the points per branch and epoch (shell, equipment, coal, outliers)."""
    t = pair.truth
    labels = (LABEL_SHELL, LABEL_EQUIPMENT, LABEL_DYNAMIC, LABEL_OUTLIER)
    head = [f"{e} {n}" for e in ("ref", "cmp") for n in ("shell", "equip.", "coal", "outl.")]
    rows = [
        "| branch | length m | section | " + " | ".join(head) + " |",
        "|---|---|---|" + "---|" * len(head),
    ]
    for b in t.branches:
        cells = [b.name, f"{b.length:.1f}", b.spec.section.kind]
        for ep in (t.ref, t.cmp):
            on = (ep.branch == b.index) & ~ep.stray
            cells += [f"{int(np.sum(on & (ep.label == lab))):,}" for lab in labels]
        rows.append("| " + " | ".join(cells) + " |")
    strays = ["", "", "", f"{int(t.ref.stray.sum())}", "", "", "", f"{int(t.cmp.stray.sum())}"]
    rows.append("| strays | | | " + " | ".join(strays) + " |")
    return "\n".join(rows)


def run(density: float, seed: int, out: Path | None, fmt: str) -> None:
    """Generate, report and optionally write one pair."""
    spec = network_250m_pair(density=density, seed=seed)
    tracemalloc.start()
    start = time.perf_counter()
    pair = make_network_pair(spec)
    seconds = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    t = pair.truth
    print(f"\n## density {density:g} points/m^2, seed {seed}\n")
    print(
        f"{len(pair.ref):,} reference + {len(pair.cmp):,} compared points in {seconds:.1f} s; "
        f"peak array memory {peak / 1024**3:.2f} GB (process peak RSS so far {rss:.2f} GB)"
    )
    for name, ep in (("ref", t.ref), ("cmp", t.cmp)):
        mag = np.linalg.norm(ep.drift_offset()[~ep.stray], axis=1)
        print(f"{name} drift: max {1e3 * mag.max():.1f} mm over {np.nanmax(ep.path):.0f} m walked")
    print()
    print(branch_table(pair))
    for scorer in SCORERS:
        for key, value in scorer(pair).items():
            print(f"{key}: {value}")
    if out is not None:
        start = time.perf_counter()
        paths = write_network_pair(pair, out / f"d{density:g}", fmt=fmt)
        took = time.perf_counter() - start
        print(f"\nwrote {', '.join(str(p) for p in paths.values())} in {took:.1f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--densities", default="300,1000", help="points per m^2, comma-separated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="write each pair into OUT/d<density>/")
    ap.add_argument("--fmt", default="laz", choices=["laz", "las", "ply"])
    args = ap.parse_args()
    for density in (float(d) for d in args.densities.split(",")):
        run(density, args.seed, args.out, args.fmt)


if __name__ == "__main__":
    main()
