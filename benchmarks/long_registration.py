"""Registration of a long synthetic pair against the truth, with the independent check's figures.

A straight tunnel with one chamber (the paper's 5.8 m x 2.86 m section), the later epoch moved
by a known translation, optionally in survey coordinates rounded to a 2**-10 m grid as
CloudCompare hands them over. Prints the registration's RMS error over the compared points and
every registration check (figure, verdict, note).

Usage::

    python benchmarks/long_registration.py --length 350 --points 16e6 --survey
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from tunneldef.cloud import Cloud
from tunneldef.config import Config
from tunneldef.pipeline import register_epochs
from tunneldef.synth import DeformationSpec, PairSpec, TunnelSpec, make_pair
from tunneldef.transforms import apply_transform

SURVEY_OFFSET = np.array((512000.0, 5611000.0, 310.0))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--length", type=float, default=350.0, help="tunnel length, m")
    ap.add_argument("--points", type=float, default=16e6, help="points per epoch")
    ap.add_argument("--survey", action="store_true",
                    help="survey-sized coordinates on a 2**-10 m grid (as from CloudCompare)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    density = args.points / (2 * (5.8 + 2.86) * args.length)
    pair = make_pair(PairSpec(
        tunnel=TunnelSpec(length=args.length, chamber=True, density=density,
                          outlier_fraction=0.0),
        deformations=(DeformationSpec(kind="roof_sag", chainage=10.0, amplitude=0.05),),
        translation=(1.5, -0.8, 0.3), seed=0,
    ))
    offset = SURVEY_OFFSET if args.survey else np.zeros(3)
    ref = Cloud(np.round((pair.ref.xyz + offset) * 2**10) / 2**10 if args.survey
                else pair.ref.xyz)
    cmp = Cloud(np.round((pair.cmp.xyz + offset) * 2**10) / 2**10 if args.survey
                else pair.cmp.xyz)
    t = time.perf_counter()
    reg = register_epochs(ref, cmp, Config().replace(quality={"enforce": False}))
    seconds = time.perf_counter() - t
    sub = slice(None, None, 50)
    err = apply_transform(reg.registration.transform, cmp.xyz[sub]) - (
        pair.truth.cmp_xyz_in_ref[sub] + offset)
    rms = float(np.sqrt(np.mean(np.einsum("ij,ij->i", err, err))))
    print(f"{len(ref):,} + {len(cmp):,} points, {args.length:.0f} m"
          f"{', survey coordinates' if args.survey else ''}: centrelines + registration + check "
          f"{seconds:.0f} s; registration RMS error against the truth {1000 * rms:.1f} mm")
    print("| check | figure | verdict | note |")
    print("|---|---:|---|---|")
    for c in reg.quality.checks:
        if c.name.startswith("registration"):
            print(f"| {c.name} | {c.figure:.4g} | {'pass' if c.passed else 'FAIL'} | {c.note} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
