"""End-to-end speed of `detect` on a synthetic pair of a given size (stage timings, memory).

Usage: python benchmarks/detect_speed.py [--points 1000000] [--length 60] [--method robust|knn]
(the handheld scanner's full scan: ``--points 16e6 --length 350``, 2,600 points/m^2 of shell,
19.4 M points per epoch with the chamber, equipment and conveyor; about 7 minutes, 15 GB)

Prints one table row per run: points per epoch, time per stage, total, peak memory (RSS), and the
registration error and noise floor against the synthetic truth.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from tunneldef import synth
from tunneldef.config import Config
from tunneldef.pipeline import detect


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=1e6, help="points per epoch (default 1e6)")
    ap.add_argument("--length", type=float, default=60.0, help="tunnel length, m (default 60)")
    ap.add_argument("--method", choices=["robust", "knn"], default="robust")
    args = ap.parse_args()

    perimeter = 2 * (5.8 + 2.86)
    density = args.points / (perimeter * args.length)
    spec = synth.PairSpec(
        tunnel=synth.TunnelSpec(length=args.length, density=density, chamber=True,
                                equipment=True, conveyor=True, roughness=0.02),
        deformations=(synth.DeformationSpec(kind="roof_sag", chainage=args.length / 2,
                                            amplitude=0.03),),
        cmp_shift=1.0, yaw_deg=140.0, seed=11,
    )
    t = time.perf_counter()
    pair = synth.make_pair(spec)
    t_synth = time.perf_counter() - t
    config = Config().replace(deformation={"method": args.method})
    t = time.perf_counter()
    res = detect(pair.ref, pair.cmp, config)
    total = time.perf_counter() - t
    err = np.sqrt(np.mean(np.sum((res.cloud.xyz - pair.truth.cmp_xyz_in_ref) ** 2, axis=1)))
    d = res.cloud.fields["deformation"]
    still = (pair.truth.label == 0) & (pair.truth.displacement == 0) & np.isfinite(d)
    rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    print("| points/epoch | synth s | centrelines+registration s | deformation s | "
          "sections+danger s | detect total s | peak RSS GB | reg. RMS mm | "
          "noise floor mean/p95 mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    tm = res.timings
    print(f"| {len(pair.ref):,} / {len(pair.cmp):,} | {t_synth:.1f} | "
          f"{tm['centrelines_and_registration']:.1f} | {tm['deformation']:.1f} | "
          f"{tm['sections_and_danger']:.1f} | {total:.1f} | {rss_gb:.1f} | {1e3 * err:.1f} | "
          f"{1e3 * np.mean(np.abs(d[still])):.1f} / "
          f"{1e3 * np.percentile(np.abs(d[still]), 95):.1f} |")


if __name__ == "__main__":
    main()
