"""Sensitivity of the paper's KNN-centroid deformation to k (paper §4.3, Table 3 analogue).

A synthetic pair with perfect registration (the compared points mapped by the true transform)
and the true centreline; for k = 1..8 it prints, on shell that did not move, the mean and
standard deviation of |deformation| (the paper's Table 3 columns: 0.0305 m and 0.0424 m for
k = 3 on its data) and the mean signed value, and in the roof sag (points where the sag reaches
80 % of its amplitude) the error of the median deformation and of the median vertical
component against the true displacement, and the error of the danger zone's robust peak
against the amplitude. A second table shows how the zone peak reads sags of 15-100 mm.

With ``--speed N`` it also times the KNN query on two tunnels of N points each, with and
without the Morton sort.

Run: ``python benchmarks/deformation_k.py [--seed 0] [--noise 0.015] [--speed 2000000]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial import cKDTree

from tunneldef.config import DeformationConfig
from tunneldef.deformation import compute_deformation, danger_zones
from tunneldef.deformation.knn import knn_counterparts
from tunneldef.synth import DeformationSpec, PairSpec, TunnelSpec, make_pair

AMP, SAG = 0.03, 10.0


def k_table(seed: int, noise: float, density: float) -> None:
    pair = make_pair(
        PairSpec(
            tunnel=TunnelSpec(length=20.0, noise_sigma=noise, density=density),
            deformations=(DeformationSpec(kind="roof_sag", chainage=SAG, amplitude=AMP),),
            cmp_shift=1.0,
            cmp_length=18.0,
            seed=seed,
        )
    )
    t = pair.truth
    shell = t.label == 0
    still = shell & (t.displacement == 0)
    core = shell & (t.surface == 0) & (t.displacement <= -0.8 * AMP)
    truth = t.displacement[core].mean()
    print(
        f"synthetic pair: {len(pair.ref)} ref / {len(pair.cmp)} cmp points, noise sigma "
        f"{1000 * noise:.0f} mm, {density:.0f} pts/m^2, {1000 * AMP:.0f} mm roof sag "
        f"({core.sum()} points at >= 80 %, mean truth {1000 * truth:.1f} mm); mm below"
    )
    head = (
        f"{'k':>2} {'|d| mean':>9} {'|d| std':>8} {'d mean':>7} | {'sag d err':>9} "
        f"{'sag dv err':>10} {'peak err':>8} {'peak s':>6} {'time s':>6}"
    )
    print(head)
    print("-" * len(head))
    for k in range(1, 9):
        t0 = time.perf_counter()
        d = compute_deformation(
            pair.ref.xyz,
            t.cmp_xyz_in_ref,
            t.centerline,
            settings=DeformationConfig(method="knn", k=k),
            shell=shell,
        )
        el = time.perf_counter() - t0
        a = np.abs(d.deformation[still])
        _, zones = danger_zones(d, threshold=0.02)
        roof = [z for z in zones if z["surface"] == "roof"]
        peak = min(roof, key=lambda z: z["peak"]) if roof else None
        peak_err = f"{1000 * (peak['peak'] + AMP):8.1f}" if peak else f"{'-':>8}"
        peak_s = f"{peak['peak_chainage']:6.2f}" if peak else f"{'-':>6}"
        print(
            f"{k:>2} {1000 * a.mean():9.1f} {1000 * a.std():8.1f} "
            f"{1000 * d.deformation[still].mean():7.1f} | "
            f"{1000 * (np.median(d.deformation[core]) - truth):9.1f} "
            f"{1000 * (np.median(d.vertical[core]) - truth):10.1f} {peak_err} {peak_s} {el:6.2f}"
        )
    print(
        "sag d err / sag dv err: median deformation / vertical component in the sag minus the "
        "truth (negative = more than the truth);\npeak err: danger zone peak (threshold 20 mm) "
        f"minus -{1000 * AMP:.0f} mm; peak s: its chainage (truth {SAG:.1f} m)"
    )


def amplitude_table(seed: int, noise: float, density: float) -> None:
    """How the robust zone peak reads sags of other amplitudes (k = 3)."""
    print("\nroof sag amplitude sweep, k = 3 (danger threshold min(20 mm, 0.6 amplitude)); mm")
    head = f"{'amp':>5} {'peak':>7} {'peak_normal':>11} {'peak s':>6}"
    print(head)
    print("-" * len(head))
    for amp in (0.015, 0.03, 0.06, 0.1):
        pair = make_pair(
            PairSpec(
                tunnel=TunnelSpec(length=20.0, noise_sigma=noise, density=density),
                deformations=(DeformationSpec(kind="roof_sag", chainage=SAG, amplitude=amp),),
                cmp_shift=1.0,
                cmp_length=18.0,
                seed=seed,
            )
        )
        t = pair.truth
        d = compute_deformation(pair.ref.xyz, t.cmp_xyz_in_ref, t.centerline, shell=t.label == 0)
        _, zones = danger_zones(d, threshold=min(0.02, 0.6 * amp))
        roof = [z for z in zones if z["surface"] == "roof"]
        if not roof:
            print(f"{1000 * amp:5.0f} {'-':>7} {'-':>11} {'-':>6}")
            continue
        z = min(roof, key=lambda z: z["peak"])
        print(
            f"{1000 * amp:5.0f} {1000 * z['peak']:7.1f} {1000 * z['peak_normal']:11.1f} "
            f"{z['peak_chainage']:6.2f}"
        )


def _tube(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on a 5.8 x 2.86 m rectangular tube along x, in random order."""
    s = rng.uniform(0, n / 17.3 / 400, n)
    t = rng.uniform(0, 17.32, n)
    y = np.where(t < 5.8, t - 2.9, np.where(t < 8.66, 2.9, np.where(t < 14.46, 11.56 - t, -2.9)))
    z = np.where(t < 5.8, 1.43, np.where(t < 8.66, 7.23 - t, np.where(t < 14.46, -1.43, t - 15.89)))
    return np.c_[s, y, z] + rng.normal(0, 0.015, (n, 3))


def speed(n: int) -> None:
    rng = np.random.default_rng(0)
    ref, cmp = _tube(rng, n), _tube(rng, n)
    t0 = time.perf_counter()
    knn_counterparts(ref, cmp, k=3)
    fast = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, idx = cKDTree(ref).query(cmp, k=3, workers=-1)
    ref[idx].mean(axis=1)
    plain = time.perf_counter() - t0
    print(
        f"k=3 counterparts, {n} vs {n} points: Morton-sorted {fast:.1f} s, file order {plain:.1f} s"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--noise", type=float, default=0.015, help="noise sigma, m")
    ap.add_argument("--density", type=float, default=400.0, help="points per m^2")
    ap.add_argument("--speed", type=int, default=0, help="also time N vs N points")
    args = ap.parse_args()
    k_table(args.seed, args.noise, args.density)
    amplitude_table(args.seed, args.noise, args.density)
    if args.speed:
        speed(args.speed)


if __name__ == "__main__":
    main()
