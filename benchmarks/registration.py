"""Registration benchmark: the paper's Table 2 analogue, with known motion and deformation.

Pairs (each compared epoch moved by a known rigid motion with any heading, a few degrees of tilt
and hundreds of metres of translation, and carrying a 3 cm roof sag):

* synth ``straight``, ``curved`` (radius 80 m), ``arched`` (arch section), 30 m, with a chamber
  and wall equipment, the compared stretch shifted by 2 m, the sag 10 m long and 4 m wide;
* ``drift``: the real Freiberg drift (``../shared/data/freiberg_mine_drift_tls.laz``),
  subsampled and split at random into two halves, the second moved and sagged.

For each method: the fitness score (paper §4.2, RMSE of nearest-neighbour distances, m), the
rotation error (deg), the translation error at the compared centroid (m), the RMS point error
against the truth (m), the sag absorbed (mean registration error along the roof's inward normal
over the sagged zone, mm: how much of the deformation the registration explained away), the
reported axial uncertainty and the run time (s).

Run: ``python benchmarks/registration.py [--quick] [--no-drift] [--methods a,b]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from tunneldef.config import Config
from tunneldef.errors import TunnelDefError
from tunneldef.frame import principal_frame
from tunneldef.registration import METHODS, register
from tunneldef.registration.metrics import (
    apply_transform,
    point_rms_error,
    rotation_error_deg,
    translation_error,
)
from tunneldef.synth import DeformationSpec, PairSpec, SectionSpec, TunnelSpec, make_pair

DRIFT = (
    Path(__file__).resolve().parents[1].parent / "shared" / "data" / "freiberg_mine_drift_tls.laz"
)


def synth_case(name: str, density: float, seed: int):
    tunnel = {
        "straight": TunnelSpec(length=30, density=density, chamber=True, equipment=True),
        "curved": TunnelSpec(length=30, radius=80.0, density=density, chamber=True, equipment=True),
        "arched": TunnelSpec(
            length=30,
            section=SectionSpec(kind="arch"),
            density=density,
            chamber=True,
            equipment=True,
        ),
    }[name]
    yaw = {"straight": 37.0, "curved": 211.0, "arched": 123.0}[name]
    pair = make_pair(
        PairSpec(
            tunnel=tunnel,
            yaw_deg=yaw,
            seed=seed,
            deformations=(
                DeformationSpec(
                    kind="roof_sag", chainage=15.0, length=10.0, width=4.0, amplitude=0.03
                ),
            ),
        )
    )
    t = pair.truth
    sag = t.displacement < -0.005
    return pair.ref.xyz, pair.cmp.xyz, t.transform, sag, t.label == 0


def drift_case(n_points: int, seed: int):
    """The real drift split in two at random; the second half sagged and moved."""
    from tunneldef.io import read

    xyz = read(DRIFT).xyz
    rng = np.random.default_rng(seed)
    xyz = xyz[rng.choice(len(xyz), min(n_points, len(xyz)), replace=False)]
    half = rng.random(len(xyz)) < 0.5
    ref, cmp_true = xyz[half], xyz[~half].copy()
    # roof sag: 3 cm Gaussian bump (sigma 1 m along, 0.4 m across) in the roof 3 m from the
    # scanner along the drift axis
    c = ref.mean(axis=0)
    _, v = np.linalg.eigh(np.cov((ref - c)[:, :2].T))
    ax = np.r_[v[:, 1], 0.0]
    lat = np.cross([0, 0, 1.0], ax)
    s = (cmp_true - c) @ ax
    u = (cmp_true - c) @ lat
    roof = cmp_true[:, 2] > np.percentile(cmp_true[:, 2], 80)
    amp = 0.03 * np.exp(-0.5 * ((s - 3.0) / 1.0) ** 2 - 0.5 * (u / 0.4) ** 2) * roof
    cmp_true[:, 2] -= amp
    rot = Rotation.from_euler("zyx", [143.0, 1.5, -2.0], degrees=True).as_matrix()
    motion = np.eye(4)
    motion[:3, :3] = rot
    motion[:3, 3] = [412.0, -233.0, 17.0]
    cmp = apply_transform(motion, cmp_true)
    return ref, cmp, np.linalg.inv(motion), amp > 0.005, np.ones(len(cmp), dtype=bool)


def run(case: str, ref, cmp, truth, sag, shell, methods, config) -> list[dict]:
    rows = []
    centre = cmp[shell].mean(axis=0)
    axis = principal_frame(ref).axes[0]
    cls = None
    for method in methods:
        cfg = config
        label = method
        if method == "centerline-norefine":
            cfg = config.replace(registration={"refine": False})
            method = "centerline"
        elif method == "centerline-forcerefine":
            cfg = config.replace(
                registration={"refine_keep": "thresholds", "refine_min_angle_deg": 0.0,
                              "refine_min_shift": 0.0}
            )
            method = "centerline"
        t0 = time.perf_counter()
        try:
            if method == "centerline" and cls is not None:
                reg = register(
                    ref, cmp, cls[0].centerline, cls[1].centerline, method=method,
                    settings=cfg.registration,
                )
                dt = time.perf_counter() - t0 + cls[2]
            else:
                if method == "centerline":
                    from tunneldef.centerline import extract_centerline

                    te = time.perf_counter()
                    lines = {"slicing": cfg.slicing, "settings": cfg.centerline}
                    cls = (extract_centerline(ref, **lines), extract_centerline(cmp, **lines))
                    cls = (*cls, time.perf_counter() - te)
                    reg = register(
                        ref, cmp, cls[0].centerline, cls[1].centerline, method=method,
                        settings=cfg.registration,
                    )
                else:
                    reg = register(ref, cmp, method=method, settings=cfg.registration)
                dt = time.perf_counter() - t0
        except TunnelDefError as exc:
            rows.append({"case": case, "method": label, "error": str(exc)})
            continue
        err = apply_transform(reg.transform, cmp[sag]) - apply_transform(truth, cmp[sag])
        rows.append(
            {
                "case": case,
                "method": label,
                "fitness": reg.fitness,
                "rot_deg": rotation_error_deg(reg.transform, truth),
                "trans_m": translation_error(reg.transform, truth, at=centre),
                "axial_m": float(
                    (
                        apply_transform(reg.transform, centre[None])
                        - apply_transform(truth, centre[None])
                    )[0]
                    @ axis
                ),
                "rms_m": point_rms_error(reg.transform, truth, cmp[shell]),
                "sag_absorbed_mm": 1000 * float(err[:, 2].mean()) if sag.any() else float("nan"),
                "axial_sigma_m": reg.axial_uncertainty,
                "slices": [d["fitness"] for d in reg.slice_fitness],
                "time_s": dt,
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="straight pair only, low density")
    ap.add_argument("--no-drift", action="store_true", help="skip the real drift")
    ap.add_argument(
        "--methods", default="centerline,centerline-norefine,icp_point,icp_plane,gicp,ndt"
    )
    ap.add_argument("--density", type=float, default=100.0)
    ap.add_argument("--drift-points", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    methods = args.methods.split(",")
    for m in methods:
        if m not in METHODS and m not in ("centerline-norefine", "centerline-forcerefine"):
            ap.error(f"unknown method {m}")
    config = Config()
    cases = ["straight"] if args.quick else ["straight", "curved", "arched"]
    rows = []
    for case in cases:
        rows += run(case, *synth_case(case, args.density, args.seed), methods, config)
    if not args.no_drift and not args.quick:
        if DRIFT.is_file():
            rows += run("drift", *drift_case(args.drift_points, args.seed), methods, config)
        else:
            print(f"(real drift not found at {DRIFT}; skipped)", file=sys.stderr)
    head = (
        f"{'case':9} {'method':20} {'fitness m':>9} {'rot deg':>8} {'trans m':>8} "
        f"{'rms m':>8} {'sag abs mm':>10} {'axial err':>9} {'axial sd':>9} {'time s':>7}  "
        "slice fitness m"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        if "error" in r:
            print(f"{r['case']:9} {r['method']:20} failed: {r['error']}")
            continue
        sl = " ".join(f"{v:.4f}" for v in r["slices"])
        print(
            f"{r['case']:9} {r['method']:20} {r['fitness']:9.4f} {r['rot_deg']:8.4f} "
            f"{r['trans_m']:8.4f} {r['rms_m']:8.4f} {r['sag_absorbed_mm']:10.2f} "
            f"{r['axial_m']:9.4f} {r['axial_sigma_m']:9.4f} {r['time_s']:7.1f}  {sl}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
