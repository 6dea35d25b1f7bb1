"""Synthetic drift networks: the 250 m preset pair at survey densities (counts, time, memory).

Generates :func:`tunneldef.synth.network_250m_pair` (a main drift, three cross-cuts, a 4-way
crossing, a 12 % ramp with a bend; five deformations; SLAM drift; strays), or with
``--preset ramp-survey`` :func:`tunneldef.synth.ramp_survey_pair` (a pair shaped like a real
handheld-SLAM survey, tilted 3 degrees), at each density and
prints, per epoch, the points per branch (shell / equipment / coal / outliers), the strays,
the generation time and the memory; ``--out DIR`` also writes each pair (``ref``/``cmp`` clouds
through :func:`tunneldef.io.write`, ``truth.npz``) into ``DIR/d<density>/``.

Detection scoring against the truth (per branch and per deformation) plugs in through
:data:`SCORERS`: functions ``pair -> dict of name: value`` whose results are printed per pair.

With ``--detect`` every pair is also run through :func:`tunneldef.pipeline.detect_network`
(checks recorded, not enforced) and scored against the truth (:func:`score_detect`): the
quality verdict and every failed check, time and peak RSS, the noise floor on the unchanged
shell, and per deformation the branch it was measured on, how far the read peak lies from the
true one and the core median read against the truth.

Usage: ``python benchmarks/networks.py [--preset 250m|ramp-survey] [--densities 300,1000]
[--noise SIGMA] [--roughness SIGMA] [--seed 0] [--out DIR] [--fmt laz|las|ply] [--detect]``

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
    ramp_survey_pair,
    write_network_pair,
)

#: ``--preset`` name -> pair spec factory (keyword arguments: density, seed, ...)
PRESETS = {"250m": network_250m_pair, "ramp-survey": ramp_survey_pair}

#: Scorers run on every generated pair: ``pair -> {name: value}`` (``--detect`` adds
#: :func:`score_detect`).
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


def score_detect(pair: NetworkPair) -> dict[str, str]:
    """``detect_network`` on the pair (checks recorded, not enforced), scored against the
    truth; one line per figure.

    * noise floor: |deformation| on compared shell points whose truth displacement is 0, more
      than 5 m from any junction (mean / p95, mm) and the share beyond 10 mm;
    * registration error on those points: RMS of where they land against where their
      surface lies in the reference cloud (true place plus the reference epoch's own drift
      there), across the surface (along its normal: what a surface comparison sees) and in
      3-D (a slide along a plain drift, which no surface can fix, included), after the rigid
      motion and after the drift correction;
    * per deformation (its core: truth displacement beyond half the amplitude, on its branch
      and within its chainage span): the branch the
      core was measured on (right when that edge's curve runs within 0.3 m of the truth
      branch's axis there); where the change is found along the branch: the reading-weighted
      mean chainage of the shell points (as classified) reading beyond half the amplitude
      within 6 m of its chainage and 1 m of its place around the section (the same
      surface), against its true chainage (m); the core's median reading against its
      median truth, and the peak's (truth beyond 90 % of the amplitude) likewise.
    """
    from tunneldef.config import Config
    from tunneldef.pipeline import detect_network

    t = pair.truth
    start = time.perf_counter()
    r = detect_network(pair.ref, pair.cmp, Config().replace(quality={"enforce": False}))
    took = time.perf_counter() - start
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    f = r.cloud.fields
    dc = r.drift_correction
    shell = np.asarray(f["shell"], dtype=bool)
    d = np.asarray(f["deformation"], dtype=np.float64)
    branch = np.asarray(f["branch"])
    ep = t.cmp
    juncs = t.junction_positions
    far = np.min(np.linalg.norm(ep.xyz_ref[:, None, :2] - juncs[None, :, :2], axis=2), axis=1)
    stable = ep.shell & (ep.displacement == 0) & (far > 2.0 + 3.0) & np.isfinite(d)
    # registration error: where the compared stable shell lands against where that surface
    # lies in the reference cloud (its true place plus the reference epoch's own drift there,
    # taken from the nearest reference point in true coordinates), after the rigid motion
    # alone and after the drift correction
    from scipy.spatial import cKDTree

    on_ref = ~t.ref.stray
    nn = cKDTree(t.ref.xyz_ref[on_ref]).query(ep.xyz_ref[stable])[1]
    target = ep.xyz_ref[stable] + t.ref.drift_offset()[on_ref][nn]
    import open3d as o3d

    surf = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(t.ref.xyz_ref[on_ref]))
    surf.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    normal = np.asarray(surf.normals)[nn]
    rigid = pair.cmp.xyz[stable] @ r.transform[:3, :3].T + r.transform[:3, 3]

    def rms(err: np.ndarray) -> str:
        across = np.sum(err * normal, axis=1)
        return (f"{1e3 * np.sqrt(np.mean(across ** 2)):.1f} mm across the surface "
                f"({1e3 * np.sqrt(np.mean(np.sum(err ** 2, axis=1))):.1f} mm in 3-D)")
    out = {
        "detect_network": f"{took:.1f} s, process peak RSS {rss:.2f} GB, "
                          f"{'verified' if r.quality.verified else 'UNVERIFIED'}"
                          + (f" (failed: {', '.join(c.name for c in r.quality.failed)})"
                             if r.quality.failed else ""),
        "noise floor on unchanged shell (>5 m from junctions)":
            f"mean {1e3 * np.mean(np.abs(d[stable])):.2f} mm, p95 "
            f"{1e3 * np.percentile(np.abs(d[stable]), 95):.2f} mm, beyond 10 mm "
            f"{100 * np.mean(np.abs(d[stable]) > 0.01):.2f} %",
        "registration error on unchanged shell (>5 m from junctions)":
            f"RMS {rms(rigid - target)} after the rigid registration, "
            f"{rms(r.cloud.xyz[stable] - target)} after the drift correction",
        "drift correction": (f"used, residual {1e3 * dc['residual_rms_before_m']:.1f} -> "
                             f"{1e3 * dc['residual_rms_after_m']:.1f} mm RMS"
                             if dc.get("used") else "not used"),
    }
    for k, bd in enumerate(t.deformations):
        amp = bd.deformation.amplitude
        dspec = bd.deformation
        core = ((ep.branch == bd.branch) & (np.abs(ep.chainage - dspec.chainage)
                                             <= dspec.length / 2 + 0.5)
                & (ep.displacement < -0.5 * amp) & np.isfinite(d))
        if core.sum() < 10:
            out[f"deformation {k}"] = "core not scanned"
            continue
        ids, counts = np.unique(branch[core], return_counts=True)
        got = int(ids[np.argmax(counts)])
        centre = ep.xyz_ref[core].mean(axis=0)
        # right: the detected edge's curve there runs along the truth branch's axis (a ramp
        # that continues a drift straight on is one edge with it)
        curve = r.ref_network.edges[got].centerline
        foot = curve.point_at(curve.project(centre[None]).chainage)
        right = bool(t.centerlines[bd.branch].project(foot).distance[0] < 0.3)
        # where along the branch the change reads: the same surface (within 1 m of the core
        # around the section), within 6 m of its chainage; a 3-D centroid would mix in noise
        # readings on the other surfaces of the section
        on = ep.branch == bd.branch
        axis = t.centerlines[bd.branch]
        pr = axis.project(ep.xyz_ref[on])
        lat, ver = np.full(len(d), np.nan), np.full(len(d), np.nan)
        lat[on], ver[on] = pr.lateral, pr.vertical
        near = (on & (np.abs(ep.chainage - dspec.chainage) <= 6.0)
                & (np.hypot(lat - np.median(lat[core]), ver - np.median(ver[core])) < 1.0))
        read = near & shell & (d < -0.5 * amp)
        dist = (abs(float(np.sum(d[read] * ep.chainage[read]) / np.sum(d[read]))
                    - dspec.chainage) if read.sum() >= 10 else np.inf)
        med_read, med_true = float(np.median(d[core])), float(np.median(ep.displacement[core]))
        top = core & (ep.displacement < -0.9 * amp)
        peak_read, peak_true = float(np.median(d[top])), float(np.median(ep.displacement[top]))
        out[f"deformation {k} ({bd.deformation.kind} {1e3 * amp:.0f} mm, truth branch "
            f"{bd.branch})"] = (
            f"on detected branch {got} ({'right' if right else 'WRONG'} branch), found "
            f"{dist:.2f} m along the branch from its true chainage, core median "
            f"{1e3 * med_read:.1f} mm vs "
            f"{1e3 * med_true:.1f} mm ({100 * (med_read / med_true - 1):+.0f} %), peak "
            f"{1e3 * peak_read:.1f} mm vs {1e3 * peak_true:.1f} mm "
            f"({100 * (peak_read / peak_true - 1):+.0f} %)")
    return out


def run(density: float, seed: int, out: Path | None, fmt: str, preset: str = "250m",
        noise: float | None = None, roughness: float = 0.0) -> None:
    """Generate, report and optionally write one pair."""
    extra = {} if noise is None else {"noise_sigma": noise}
    if roughness:
        extra["roughness"] = roughness
    spec = PRESETS[preset](density=density, seed=seed, **extra)
    tracemalloc.start()
    start = time.perf_counter()
    pair = make_network_pair(spec)
    seconds = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    t = pair.truth
    print(f"\n## {preset}, density {density:g} points/m^2, noise sigma "
          f"{1e3 * spec.noise_sigma:g} mm, rock relief {1e3 * spec.roughness:g} mm, seed {seed}\n")
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
    ap.add_argument("--preset", default="250m", choices=sorted(PRESETS),
                    help="250m: network_250m_pair; ramp-survey: ramp_survey_pair (a pair shaped "
                         "like a real handheld-SLAM survey: the later epoch goes on up a ramp "
                         "with four dead ends)")
    ap.add_argument("--noise", type=float, default=None,
                    help="noise sigma per coordinate, m (default: the preset's)")
    ap.add_argument("--roughness", type=float, default=0.0,
                    help="standard deviation of the rock relief, m (default 0: planar walls)")
    ap.add_argument("--out", type=Path, default=None, help="write each pair into OUT/d<density>/")
    ap.add_argument("--fmt", default="laz", choices=["laz", "las", "ply"])
    ap.add_argument("--detect", action="store_true",
                    help="also run detect_network on each pair and score it against the truth")
    args = ap.parse_args()
    if args.detect:
        SCORERS.append(score_detect)
    for density in (float(d) for d in args.densities.split(",")):
        run(density, args.seed, args.out, args.fmt, args.preset, args.noise, args.roughness)


if __name__ == "__main__":
    main()
