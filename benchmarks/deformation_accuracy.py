"""Deformation accuracy and speed: the paper's KNN centroid against the robust estimator and peers.

Every method runs on the same registered pairs and is scored against the same truth:

* synthetic pairs (``tunneldef.synth``, 20 m, rough rock, equipment + conveyor with a new coal
  load) with noise sigma 0.015 m (the scanner's +-3 cm) and 0.012 m, and a 15 mm (the paper's
  Table 5 roof deformation) or 30 mm roof sag; registration perfect (the true transform), then a
  second block registered by ``tunneldef.registration.register``. Each block runs at two shell
  densities: 2,600 points/m^2, the handheld SLAM scanner's (16 M points per 350 m of tunnel,
  a 17.3 m section perimeter), and 400 points/m^2, a sparse scan (a 0.2 m cylinder then holds
  about 50 points per epoch, and +-3 cm noise alone gives each cylinder's deformation a
  standard error of about 3 mm);
* the real drift scan (``../shared/data/freiberg_mine_drift_tls.laz``, subsampled), its points
  split at random into two epochs, a 15 mm roof sag injected into the second.

Methods: ``knn`` (the paper's KNN centroid, k = 3, §3.3.1), ``robust`` (both through
``tunneldef.deformation.compute_deformation``, shell classification included in the time),
``cc-c2c`` (CloudCompare's cloud-to-cloud distance, nearest neighbour, unsigned: its values are
scored as if every change were inward) and ``py4dgeo-m3c2`` (M3C2 on the robust estimator's
core points, cylinder 0.2 m, normal radius 0.3 m; its normals oriented outward afterwards).
CloudCompare or py4dgeo are skipped with a message when absent.

Scores (mm unless stated), on points labelled shell by the truth:
  noise mean / p95 : mean and 95th percentile of |d| on shell that did not move;
  peak             : median of d within 0.3 m of the sag's centre (truth: the same median of the
                     true displacement);
  core mean        : mean of d where the truth is at least half the amplitude (truth likewise);
  recall@10        : fraction of the sag core (truth >= 80 % of the amplitude) with d < -10 mm;
  FA@10 %          : fraction of the unchanged shell with |d| > 10 mm;
  time s           : wall time of the method on the pair.
A last block, in a fresh process, times the robust estimator on a compared cloud of one million
points (median of three runs, after a small pair has taken the one-time start-up).

The surveyor's blocks (issue 17; ``--survey-only``) score the field as a surveyor thresholds
it: 16 m pairs (rectangular and arched sections; 400, 900 and 2,600 points/m^2; noise sigma
12 mm, "+-1.2 cm", and 15 mm, the scanner's "+-3 cm" taken as 2 sigma) with a side chamber,
pipes, a conveyor with a changing coal load, four occlusion holes and rough rock, 15 mm and
30 mm roof sags and a 40 mm wall bulge 1.2 m wide, the compared epoch moved by our own
registration (``tunneldef.pipeline.register_epochs``; ``--cache DIR`` keeps the registered
pairs). Per point on the true unchanged shell: the share beyond 10 mm (either sign) of the
points with a value, the noise floor, the share without a value, the side chamber's share;
and the median read over each change's core against the truth's. Then the noise floor of
the arched pair at 900 points/m^2 and sigma 18 mm, and the real drift's random halves with
a 19 mm sag, registered by us, over the same seeds. ``cc-m3c2`` rows run CloudCompare 2.13's
M3C2 plugin (``/opt/cloudcompare-m3c2``, skipped with a message where absent) on the same
registered pairs.

Run: ``python benchmarks/deformation_accuracy.py [--quick] [--no-cc] [--no-m3c2]
[--densities 2600,400] [--speed-points 1000000] [--drift-points 600000]`` (default: about
25 minutes on 2 cores, most of it at the scanner's density; ``--quick``: one sparse pair).
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tunneldef.config import Config, DeformationConfig
from tunneldef.curve import Centerline
from tunneldef.deformation import compute_deformation
from tunneldef.deformation.local_surface import robust_deformation, voxel_cores
from tunneldef.deformation.shell import classify_shell
from tunneldef.errors import TunnelDefError
from tunneldef.synth import DeformationSpec, PairSpec, TunnelSpec, make_pair

#: the shared data folder: next to the checkout, or one level up (from a worktree)
SHARED = next(
    (p / "shared" for p in Path(__file__).resolve().parents[2:4] if (p / "shared").is_dir()),
    Path(__file__).resolve().parents[1].parent / "shared",
)
DRIFT = SHARED / "data" / "freiberg_mine_drift_tls.laz"
THRESHOLD = 0.010
LENGTH, SAG_AT = 20.0, 10.0
SCANNER_DENSITY = 2600.0  # points/m^2: 16 M points per 350 m over a 17.3 m section perimeter
# targets on the registered pairs: noise mean / p95, peak error (mm), recall, false alarms (%)
TARGETS = {"mean": 3.0, "p95": 8.0, "peak": 2.0, "recall": 0.9, "fa": 0.5}


# --------------------------------------------------------------------------- methods


#: the raw registration, its along-axis uncertainty reported rather than refused
ANY_AXIAL = Config().replace(registration={"max_axial_uncertainty": float("inf")})

def run_knn(ref, cmp_, line, ctx):
    return compute_deformation(
        ref, cmp_, line, settings=DeformationConfig(method="knn")
    ).deformation


def run_robust(ref, cmp_, line, ctx):
    return compute_deformation(
        ref, cmp_, line, settings=DeformationConfig(method="robust")
    ).deformation


def run_c2c(ref, cmp_, line, ctx):
    exe = shutil.which("CloudCompare")
    if exe is None:
        raise RuntimeError("CloudCompare not found")
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        o = ref.mean(axis=0)  # local origin: CloudCompare stores float32 coordinates
        np.savetxt(t / "cmp.xyz", cmp_ - o, fmt="%.5f")
        np.savetxt(t / "ref.xyz", ref - o, fmt="%.5f")
        env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
        cmd = [
            exe,
            "-SILENT",
            "-AUTO_SAVE",
            "OFF",
            "-C_EXPORT_FMT",
            "ASC",
            "-O",
            "cmp.xyz",
            "-O",
            "ref.xyz",
            "-C2C_DIST",
            "-SAVE_CLOUDS",
            "FILE",
            "out_cmp.asc out_ref.asc",
        ]
        subprocess.run(cmd, cwd=t, env=env, check=True, capture_output=True, timeout=600)
        out = np.loadtxt(t / "out_cmp.asc")
    if out.shape[0] != cmp_.shape[0] or not np.allclose(out[:, :3], cmp_ - o, atol=1e-3):
        raise RuntimeError("CloudCompare changed the point order")
    return -np.abs(out[:, 3])  # unsigned: scored as inward


def run_m3c2(ref, cmp_, line, ctx):
    import py4dgeo

    logging.getLogger("py4dgeo").setLevel(logging.WARNING)
    o = ref.mean(axis=0)
    cores, inverse = voxel_cores(cmp_ - o, 0.2)
    m = py4dgeo.M3C2(
        epochs=(py4dgeo.Epoch(ref - o), py4dgeo.Epoch(cmp_ - o)),
        corepoints=cores,
        cyl_radius=0.2,
        normal_radii=[0.3],
        max_distance=0.3,
    )
    dist, _ = m.run()
    normals = m.directions()
    proj = line.project(cores + o)
    _, lat, ver = line.frame_at(proj.chainage)
    outward = proj.lateral[:, None] * lat + proj.vertical[:, None] * ver
    flip = np.einsum("ij,ij->i", normals, outward) < 0
    dist = np.where(flip, -dist, dist)
    return dist[inverse]


METHODS = {"knn": run_knn, "robust": run_robust, "cc-c2c": run_c2c, "py4dgeo-m3c2": run_m3c2}
METHODS["cc-m3c2"] = lambda *a: run_cc_m3c2(*a)


# --------------------------------------------------------------------------- scoring


def score(d, truth, shell, unchanged, xyz, amp):
    """Scores of one method on one pair (see the module docstring)."""
    d = np.asarray(d, dtype=np.float64)
    du = np.abs(d[unchanged])
    ok = np.isfinite(du)
    centre = np.argmin(np.where(shell, truth, np.inf))
    disc = shell & (np.linalg.norm(xyz - xyz[centre], axis=1) < 0.3)
    half = shell & (truth <= -0.5 * amp)
    core = shell & (truth <= -0.8 * amp)
    with np.errstate(invalid="ignore"):
        return {
            "mean": 1e3 * np.mean(du[ok]),
            "p95": 1e3 * np.percentile(du[ok], 95),
            "peak": 1e3 * np.nanmedian(d[disc]),
            "peak_t": 1e3 * np.median(truth[disc]),
            "core": 1e3 * np.nanmean(d[half]),
            "core_t": 1e3 * np.mean(truth[half]),
            "recall": float(np.mean(d[core] < -THRESHOLD)),
            "fa": 100.0 * float(np.mean(du[ok] > THRESHOLD)),
            "nan": 100.0 * float(np.mean(~ok)),
        }


HEADER = (
    f"{'pair':<28} {'method':<13} {'mean':>6} {'p95':>6} {'peak/truth':>13} "
    f"{'core/truth':>13} {'rec@10':>6} {'FA@10%':>7} {'NaN%':>5} {'time s':>7}"
)


def row(pair_name, method, s, seconds):
    return (
        f"{pair_name:<28} {method:<13} {s['mean']:6.1f} {s['p95']:6.1f} "
        f"{s['peak']:6.1f}/{s['peak_t']:<6.1f} {s['core']:6.1f}/{s['core_t']:<6.1f} "
        f"{s['recall']:6.2f} {s['fa']:7.2f} {s['nan']:5.1f} {seconds:7.1f}"
    )


def run_methods(name, ref, cmp_, line, truth, shell, unchanged, amp, methods, *, show=True):
    """Scores and times of every method on one pair ({method: (scores, seconds)})."""
    out = {}
    for mname in methods:
        t0 = time.perf_counter()
        try:
            d = METHODS[mname](ref, cmp_, line, None)
        except Exception as exc:  # a peer that is missing or fails is reported, not fatal
            print(f"{name:<28} {mname:<13} skipped: {type(exc).__name__}: {exc}"[:150])
            continue
        seconds = time.perf_counter() - t0
        out[mname] = (score(d, truth, shell, unchanged, cmp_, amp), seconds)
        if show:
            print(row(name, mname, *out[mname]), flush=True)
    return out


def print_mean(name, runs, methods):
    """One row per method: each score averaged over the runs (seeds)."""
    for mname in methods:
        got = [r[mname] for r in runs if mname in r]
        if not got:
            continue
        s = {k: float(np.mean([g[0][k] for g in got])) for k in got[0][0]}
        print(row(name, mname, s, float(np.mean([g[1] for g in got]))), flush=True)
    if runs and "robust" in runs[0]:
        worst = max(abs(r["robust"][0]["peak"] - r["robust"][0]["peak_t"]) for r in runs)
        low = min(r["robust"][0]["recall"] for r in runs)
        print(
            f"{'':<28} robust over {len(runs)} seeds: worst peak error {worst:.1f} mm, "
            f"lowest recall@10 {low:.2f}"
        )


# --------------------------------------------------------------------------- pairs


def synth_pair(noise, amp, seed, density=400.0):
    return make_pair(
        PairSpec(
            # rough rock (static, the same in both epochs) as in real drifts: it is what fixes the
            # position along the axis for the registered block
            tunnel=TunnelSpec(
                length=LENGTH,
                noise_sigma=noise,
                equipment=True,
                conveyor=True,
                roughness=0.02,
                density=density,
            ),
            deformations=(DeformationSpec(kind="roof_sag", chainage=SAG_AT, amplitude=amp),),
            cmp_shift=1.0,
            seed=seed,
        )
    )


def synth_masks(pair):
    tr = pair.truth
    shell = tr.label == 0
    inside = (tr.chainage > 0.5) & (tr.chainage < LENGTH - 0.5)  # where both epochs exist
    return shell & inside, shell & inside & (tr.displacement == 0.0)


def synth_block(methods, quick, seeds, density):
    cases = [(0.015, 0.015), (0.015, 0.030), (0.012, 0.015), (0.012, 0.030)]
    if quick:
        cases = cases[:1]
    print(
        f"\nSynthetic pairs at {density:.0f} points/m^2, perfect registration (truth transform); "
        f"mean of seeds {seeds}"
    )
    print(HEADER)
    for noise, amp in cases:
        runs = []
        name = f"s={noise * 1e3:.0f}mm sag={amp * 1e3:.0f}mm {density:.0f}/m2"
        for seed in seeds:
            pair = synth_pair(noise, amp, seed, density)
            tr = pair.truth
            shell, unchanged = synth_masks(pair)
            runs.append(
                run_methods(
                    name,
                    pair.ref.xyz,
                    tr.cmp_xyz_in_ref,
                    tr.centerline,
                    tr.displacement,
                    shell,
                    unchanged,
                    amp,
                    methods,
                    show=False,
                )
            )
        print_mean(name, runs, methods)


def registration_block(methods, seeds, density):
    """The s = 15 mm, 15 mm sag pair of every seed, registered by our own registration."""
    try:
        from tunneldef.pipeline import register_epochs
    except ImportError as exc:
        print(f"\n(registration block skipped: {exc})")
        return
    print(
        f"\nSynthetic pairs s=15mm sag=15mm at {density:.0f} points/m^2, registered by "
        f"tunneldef.registration.register; seeds {seeds}"
    )
    print(HEADER)
    name = f"s=15mm sag=15mm {density:.0f}/m2 reg"
    runs = []
    for seed in seeds:
        pair = synth_pair(0.015, 0.015, seed, density)
        tr = pair.truth
        t0 = time.perf_counter()
        try:
            reg = register_epochs(pair.ref, pair.cmp, ANY_AXIAL).registration
        except Exception as exc:
            print(f"(seed {seed}: registration failed: {type(exc).__name__}: {exc})")
            continue
        t = reg.transform
        cmp_reg = pair.cmp.xyz @ t[:3, :3].T + t[:3, 3]
        err = np.linalg.norm(cmp_reg - tr.cmp_xyz_in_ref, axis=1)
        print(
            f"seed {seed}: registration ({reg.method}) {time.perf_counter() - t0:.1f} s; point "
            f"error vs truth mean {1e3 * err.mean():.1f} mm, max {1e3 * err.max():.1f} mm"
        )
        shell, unchanged = synth_masks(pair)
        runs.append(
            run_methods(
                f"{name} seed {seed}",
                pair.ref.xyz,
                cmp_reg,
                tr.centerline,
                tr.displacement,
                shell,
                unchanged,
                0.015,
                methods,
            )
        )
    print_mean(f"{name} mean", runs, methods)
    got = [r["robust"][0] for r in runs if "robust" in r]
    if got:
        worst = {
            "mean": max(g["mean"] for g in got),
            "p95": max(g["p95"] for g in got),
            "peak": max(abs(g["peak"] - g["peak_t"]) for g in got),
            "recall": min(g["recall"] for g in got),
            "fa": max(g["fa"] for g in got),
        }
        met = {
            k: (v >= TARGETS[k]) if k == "recall" else (v <= TARGETS[k]) for k, v in worst.items()
        }
        print(
            f"robust, worst seed against the targets: noise mean {worst['mean']:.1f} mm "
            f"(<= {TARGETS['mean']:.0f}: {_yes(met['mean'])}), p95 {worst['p95']:.1f} mm "
            f"(<= {TARGETS['p95']:.0f}: {_yes(met['p95'])}), peak error {worst['peak']:.1f} mm "
            f"(<= {TARGETS['peak']:.0f}: {_yes(met['peak'])}), recall@10 {worst['recall']:.2f} "
            f"(>= {TARGETS['recall']}: {_yes(met['recall'])}), false alarms {worst['fa']:.2f} % "
            f"(<= {TARGETS['fa']}: {_yes(met['fa'])})"
        )


def _yes(ok):
    return "met" if ok else "MISSED"


def _taper(x, full):
    return np.where(np.abs(x) < full / 2, 0.5 * (1.0 + np.cos(2.0 * np.pi * x / full)), 0.0)


def drift_halves(n_points, seed, amp, *, registered=False):
    """The real drift's points (a random subsample) split at random into two epochs, a roof
    sag of ``amp`` (2 m along, 1 m across, cosine tapers) injected into the second, which is
    moved by our own registration when ``registered``. Returns ``(ref, cmp, line, truth,
    shell, unchanged, note)``, or None without the data."""
    if not DRIFT.is_file():
        return None
    from tunneldef.io import read

    rng = np.random.default_rng(seed)
    xyz = read(DRIFT).xyz
    xyz = xyz[rng.choice(len(xyz), min(n_points, len(xyz)), replace=False)]
    half = rng.random(len(xyz)) < 0.5
    ref, cmp_ = xyz[half], xyz[~half].copy()
    try:
        from tunneldef.centerline import extract_centerline

        line = extract_centerline(ref).centerline
        how = "extract_centerline"
    except Exception as exc:  # fall back to a straight axis along the drift
        lo, hi = np.percentile(ref, [1, 99], axis=0)
        mid = 0.5 * (lo + hi)
        line = Centerline.from_polyline(
            np.array([[mid[0], lo[1], mid[2]], [mid[0], hi[1], mid[2]]])
        )
        how = f"straight axis ({type(exc).__name__})"
    p = line.project(cmp_)
    top = np.percentile(p.vertical, 99)
    roof = (p.vertical > 0.6 * top) & (np.abs(p.lateral) < 0.7)
    # the sag 2 m along the drift and 1 m across, where the roof is seen (3 m from the
    # scanner: no blind cone)
    s0 = float(line.project(np.array([[0.0, 3.0, 0.0]])).chainage[0])
    truth = np.where(roof, -amp * _taper(p.chainage - s0, 2.0) * _taper(p.lateral, 1.0), 0.0)
    cmp_[:, 2] += truth  # the roof moves down, into the drift
    shell_c = classify_shell(cmp_, line)
    inside = (p.chainage > 0.5) & (p.chainage < line.length - 0.5)
    shell = shell_c & inside
    unchanged = shell & (truth == 0.0)
    note = f"centreline by {how}, sag at chainage {s0:.1f} m, {int((truth < 0).sum())} moved"
    if registered:
        from tunneldef.cloud import Cloud
        from tunneldef.pipeline import register_epochs

        t = register_epochs(Cloud(ref), Cloud(cmp_), ANY_AXIAL).registration.transform
        moved = cmp_ @ t[:3, :3].T + t[:3, 3]
        note += f"; our registration moved the points by {1e3 * np.abs(moved - cmp_).max():.1f} mm"
        cmp_ = moved
    return ref, cmp_, line, truth, shell, unchanged, note


def drift_block(methods, n_points, seed, amp=0.015, *, registered=False, seeds=None):
    """The real drift halves (:func:`drift_halves`) for each seed: the scores of
    :func:`score`, plus the median read over the sag's core against the truth's."""
    seeds = [seed] if seeds is None else seeds
    print(
        f"\nReal drift ({DRIFT.name}): {n_points} points split at random into two halves, "
        f"a {amp * 1e3:.0f} mm roof sag injected; "
        f"{'our registration' if registered else 'perfect registration'}; shell = "
        "classify_shell; core = points moved by >= 80 % of the sag, median"
    )
    print(HEADER + f" {'core t/r':>11}")
    worst = {}
    for sd in seeds:
        try:
            got = drift_halves(n_points, sd, amp, registered=registered)
        except TunnelDefError as exc:  # a refusal is a result, not a crash
            print(f"drift halves seed {sd}: refused: {exc}"[:200])
            continue
        if got is None:
            print(f"(real drift block skipped: {DRIFT} not found)")
            return
        ref, cmp_, line, truth, shell, unchanged, note = got
        print(f"seed {sd}: {len(ref)} + {len(cmp_)} points; {note}")
        core = shell & (truth <= -0.8 * amp)
        for mname in methods:
            t0 = time.perf_counter()
            try:
                d = METHODS[mname](ref, cmp_, line, None)
            except Exception as exc:  # a peer that is missing or fails is reported
                print(f"{'drift halves':<28} {mname:<13} skipped: {exc}"[:150])
                continue
            s = score(d, truth, shell, unchanged, cmp_, amp)
            t_core, r_core = 1e3 * np.median(truth[core]), 1e3 * np.nanmedian(d[core])
            print(
                row(f"drift halves seed {sd}", mname, s, time.perf_counter() - t0)
                + f" {t_core:5.1f}/{r_core:<5.1f}",
                flush=True,
            )
            w = worst.setdefault(mname, [0.0, 0.0])
            w[0], w[1] = max(w[0], s["fa"]), max(w[1], abs(r_core - t_core))
    for mname, (fa, err) in worst.items():
        print(
            f"  {mname}, worst seed: FA {fa:.2f} % (<= 0.5: {_yes(fa <= SURVEY_TARGETS['fa'])}), "
            f"sag core error {err:.1f} mm (<= 2: {_yes(err <= SURVEY_TARGETS['drift_peak'])})"
        )


def _speed_pair(length, seed):
    pair = make_pair(
        PairSpec(
            tunnel=TunnelSpec(length=length, equipment=True, conveyor=True),
            deformations=(DeformationSpec(kind="roof_sag", chainage=length / 2, amplitude=0.015),),
            cmp_shift=0.0,
            seed=seed,
        )
    )
    return pair.ref.xyz, pair.truth.cmp_xyz_in_ref, pair.truth.centerline


def speed_block(n_points, seed, repeats=3):
    """Times on a compared cloud of ``n_points``, in this (fresh) process: a 10 m pair first
    takes the one-time start-up (imports, Open3D's and SciPy's thread pools), then each
    function runs ``repeats`` times; the median is the figure."""
    per_metre = 8_300.0  # points per metre of a 5.8 x 2.86 m section at 400 points/m^2
    length = max(10.0, n_points / per_metre)
    small = _speed_pair(10.0, seed)
    w0 = time.perf_counter()
    compute_deformation(*small, settings=DeformationConfig(method="robust"))
    warm = time.perf_counter() - w0
    ref, cmp_, line = _speed_pair(length, seed)
    print(
        f"\nSpeed: {len(cmp_)} compared vs {len(ref)} reference points ({length:.0f} m), "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; start-up (a 10 m "
        f"pair, {len(small[1])} points, run first) {warm:.1f} s; wall times of {repeats} runs"
    )
    for label, fn in (
        ("robust_deformation", lambda: robust_deformation(ref, cmp_, line)),
        ("classify_shell (compared)", lambda: classify_shell(cmp_, line)),
        (
            "compute_deformation robust",
            lambda: compute_deformation(
                ref, cmp_, line, settings=DeformationConfig(method="robust")
            ),
        ),
        (
            "compute_deformation knn",
            lambda: compute_deformation(ref, cmp_, line, settings=DeformationConfig(method="knn")),
        ),
    ):
        walls, cpus = [], []
        for _ in range(repeats):
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
        runs = " ".join(f"{w:.1f}" for w in walls)
        print(
            f"  {label:<28} median wall {np.median(walls):6.1f} s ({runs})   "
            f"cpu {np.median(cpus):6.1f} s",
            flush=True,
        )


# --------------------------------------------------------------------------- surveyor block
# issue 17: the field as a surveyor thresholds it, per point on the true unchanged shell, with
# our own registration, on pairs with a side chamber, pipes, a conveyor and occlusion holes

SURVEY_LENGTH = 16.0
#: (kind, chainage, side, amplitude, width across, length along), m
SURVEY_CHANGES = (
    ("roof_sag", 3.5, "left", 0.015, 2.0, 3.0),
    ("wall_bulge", 6.5, "right", 0.040, 1.2, 3.0),
    ("roof_sag", 9.5, "left", 0.030, 2.0, 3.0),
)
#: noise sigma per label: "+-1.2 cm", "+-1.8 cm" as the issue names sigma 0.012 / 0.018 m (the
#: benchmark's s=12mm pair), "+-3 cm" the scanner's stated accuracy taken as 2 sigma (synth)
SURVEY_NOISE = {"+-1.2cm": 0.012, "+-1.8cm": 0.018, "+-3cm": 0.015}
SURVEY_TARGETS = {"fa": 0.5, "mean": 3.0, "p95": 8.0, "peak": 0.10, "drift_peak": 2.0}


def survey_spec(section, density, noise, seed):
    """A 16 m pair with a chamber (13 m), pipes, conveyor, 4 holes, rough rock and three
    changes: 15 mm and 30 mm roof sags, a 40 mm wall bulge 1.2 m wide."""
    from tunneldef.synth import SectionSpec

    return PairSpec(
        tunnel=TunnelSpec(
            length=SURVEY_LENGTH,
            section=SectionSpec(kind=section),
            noise_sigma=noise,
            density=density,
            chamber=True,
            chamber_chainage=13.0,
            chamber_length=3.0,
            equipment=True,
            conveyor=True,
            holes=4,
            roughness=0.02,
        ),
        deformations=tuple(
            DeformationSpec(kind=k, chainage=s, side=side, amplitude=a, width=w, length=ln)
            for k, s, side, a, w, ln in SURVEY_CHANGES
        ),
        cmp_shift=1.0,
        seed=seed,
    )


def registered_pair(spec, cache, cached_only=False):
    """The pair of ``spec`` and the compared epoch moved by our own registration
    (``tunneldef.pipeline.register_epochs``); kept in ``cache`` (a directory) when given.
    ``cached_only``: None when the pair is not in the cache yet."""
    import hashlib
    import pickle

    from tunneldef.pipeline import register_epochs

    key = hashlib.sha1(repr(spec).encode()).hexdigest()[:16]
    path = None if cache is None else Path(cache) / f"pair_{key}.pkl"
    if path is not None and path.is_file():
        with open(path, "rb") as fh:
            return pickle.load(fh)
    if cached_only:
        return None
    pair = make_pair(spec)
    t0 = time.perf_counter()
    rp = register_epochs(pair.ref, pair.cmp, ANY_AXIAL)
    t = rp.registration.transform
    cmp_reg = pair.cmp.xyz @ t[:3, :3].T + t[:3, 3]
    err = np.linalg.norm(cmp_reg - pair.truth.cmp_xyz_in_ref, axis=1)
    tr = pair.truth
    out = {
        "ref": pair.ref.xyz,
        "cmp": cmp_reg,
        "line": rp.ref_extraction.centerline,
        "displacement": tr.displacement,
        "label": tr.label,
        "chainage": tr.chainage,
        "chamber": tr.chamber,
        "ref_range": tr.ref_range,
        "reg_error_mm": 1e3 * float(err.mean()),
        "reg_seconds": time.perf_counter() - t0,
    }
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            pickle.dump(out, fh)
    return out


def survey_scores(d, pr, changes):
    """Per-point scores on the true unchanged shell inside the reference's stretch, and the
    median read over each change's core (truth beyond 80 % of its amplitude)."""
    d = np.asarray(d, dtype=np.float64)
    shell = (pr["label"] == 0) & (pr["chainage"] > pr["ref_range"][0] + 0.5)
    shell &= pr["chainage"] < pr["ref_range"][1] - 0.5
    unchanged = shell & (pr["displacement"] == 0.0)
    du = np.abs(d[unchanged])
    ok = np.isfinite(du)
    out = {
        "fa": 100.0 * float(np.mean(du[ok] > THRESHOLD)),
        "mean": 1e3 * float(np.mean(du[ok])),
        "p95": 1e3 * float(np.percentile(du[ok], 95)),
        "nan": 100.0 * float(np.mean(~ok)),
        "chamber_fa": 100.0 * float(np.mean(np.abs(d[unchanged & pr["chamber"]]) > THRESHOLD)),
    }
    for i, (_, s, _, amp, _, ln) in enumerate(changes):
        # the change's own patch (``ln`` is its whole length): the three patches touch, and a
        # window of +-ln took the bulge's points into both sags' cores
        own = np.abs(pr["chainage"] - s) < 0.5 * ln
        core = shell & own & (pr["displacement"] <= -0.8 * amp)
        out[f"true{i}"] = 1e3 * float(np.median(pr["displacement"][core]))
        out[f"read{i}"] = 1e3 * float(np.nanmedian(d[core]))
    return out


SURVEY_HEADER = (
    f"{'pair':<34} {'method':<9} {'FA@10%':>6} {'mean':>5} {'p95':>5} {'NaN%':>5} "
    f"{'chmbFA':>6} {'sag15 t/r':>11} {'bulge40 t/r':>11} {'sag30 t/r':>11} {'s':>5}"
)


def survey_row(name, method, s, seconds):
    peaks = " ".join(
        f"{s[f'true{i}']:5.1f}/{s[f'read{i}']:<5.1f}" for i in range(len(SURVEY_CHANGES))
    )
    return (
        f"{name:<34} {method:<9} {s['fa']:6.2f} {s['mean']:5.1f} {s['p95']:5.1f} "
        f"{s['nan']:5.1f} {s['chamber_fa']:6.2f} {peaks} {seconds:5.1f}"
    )


def survey_block(seeds, cache, *, sections, densities, noises, cc=False, cached_only=False):
    """Every (section, density, noise) pair over ``seeds``, our registration, scored with
    :func:`survey_scores`; the mean over the seeds and the worst seed against the targets."""
    print(
        f"\nSurveyor's field (issue 17): {SURVEY_LENGTH:.0f} m pairs with chamber, pipes, "
        f"conveyor, 4 holes, rough rock; our registration; seeds {seeds}. Scores per point on "
        "the true unchanged shell (FA@10% = share beyond 10 mm either sign, of the points with "
        "a value; NaN% = share without); t/r = true / read median over each change's core, mm"
    )
    print(SURVEY_HEADER)
    verdicts = []
    for section in sections:
        for density in densities:
            for label in noises:
                name = f"{section} {density:.0f}/m2 {label}"
                runs = {}
                used = []
                for seed in seeds:
                    try:
                        pr = registered_pair(
                            survey_spec(section, density, SURVEY_NOISE[label], seed), cache,
                            cached_only,
                        )
                    except TunnelDefError as exc:  # a refusal is a result, not a crash
                        print(f"{name} s{seed}: refused: {exc}"[:200])
                        continue
                    if pr is None:
                        continue
                    used.append(seed)
                    for method in ("robust", "cc-m3c2") if cc else ("robust",):
                        t0 = time.perf_counter()
                        try:
                            run = run_robust if method == "robust" else run_cc_m3c2
                            d = run(pr["ref"], pr["cmp"], pr["line"], None)
                        except Exception as exc:  # a missing peer is reported, not fatal
                            print(f"{name:<34} {method:<9} skipped: {exc}"[:150])
                            continue
                        runs.setdefault(method, []).append(
                            (survey_scores(d, pr, SURVEY_CHANGES), time.perf_counter() - t0)
                        )
                if not used:
                    print(f"{name:<34} (no pair in the cache)")
                    continue
                name = f"{name} s{','.join(map(str, used))}"
                for method, got in runs.items():
                    mean = {k: float(np.mean([g[0][k] for g in got])) for k in got[0][0]}
                    print(survey_row(name, method, mean, float(np.mean([g[1] for g in got]))))
                    if method == "robust":
                        verdicts.append((name, [g[0] for g in got], used))
    print("robust, worst seed against the targets (FA <= 0.5 %; peaks within 10 % at >= 400/m2):")
    for name, got, used in verdicts:
        fas = [g["fa"] for g in got]
        peaks = [
            max(abs(g[f"read{i}"] - g[f"true{i}"]) / abs(g[f"true{i}"])
                for i in range(len(SURVEY_CHANGES)))
            for g in got
        ]
        fa, peak = max(fas), max(peaks)
        print(
            f"  {name:<34} FA {fa:5.2f} % (s{used[int(np.argmax(fas))]}, "
            f"{_yes(fa <= SURVEY_TARGETS['fa'])}), worst peak error {100 * peak:4.1f} % "
            f"(s{used[int(np.argmax(peaks))]}, {_yes(peak <= SURVEY_TARGETS['peak'])})"
        )


def floor_block(seeds, cache, cached_only=False):
    """Noise floor, arched section, 900 points/m^2, sigma 18 mm, our registration."""
    got = []
    used = []
    for seed in seeds:
        spec = survey_spec("arch", 900.0, SURVEY_NOISE["+-1.8cm"], seed)
        pr = registered_pair(spec, cache, cached_only)
        if pr is None:
            continue
        used.append(seed)
        d = compute_deformation(pr["ref"], pr["cmp"], pr["line"]).deformation
        got.append(survey_scores(d, pr, SURVEY_CHANGES))
    print(f"\nNoise floor, arched, 900 points/m^2, +-1.8 cm (sigma 18 mm); seeds {used}")
    if not got:
        return
    mean = max(g["mean"] for g in got)
    p95 = max(g["p95"] for g in got)
    print(
        f"  worst seed: mean {mean:.1f} mm (<= 3: {_yes(mean <= 3.0)}), p95 {p95:.1f} mm "
        f"(<= 8: {_yes(p95 <= 8.0)}), FA {max(g['fa'] for g in got):.2f} %"
    )


CC_M3C2 = Path("/opt/cloudcompare-m3c2")
CC_M3C2_PARAMS = SHARED / "cloudcompare-python"


def run_cc_m3c2(ref, cmp_, line, ctx):
    """CloudCompare 2.13's M3C2 plugin (the prebuilt command-line build in
    ``/opt/cloudcompare-m3c2``), every compared point a core point, with the parameter file
    of ``../shared/cloudcompare-python/m3c2_params.txt`` (normal radius 0.3 m, cylinder
    radius 0.2 m, depth 0.3 m, normals away from the barycentre: negative = into the
    tunnel)."""
    exe = CC_M3C2 / "bin" / "CloudCompare"
    params = CC_M3C2_PARAMS / "m3c2_params.txt"
    if not exe.is_file():
        raise RuntimeError(f"CloudCompare M3C2 not found ({exe}; unpack the tarball to /opt)")
    if not params.is_file():
        raise RuntimeError(f"M3C2 parameter file not found ({params}: ../shared beside the "
                           "checkout)")
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        o = ref.mean(axis=0)  # local origin: CloudCompare stores float32 coordinates
        np.savetxt(t / "ref.xyz", ref - o, fmt="%.5f")
        np.savetxt(t / "cmp.xyz", cmp_ - o, fmt="%.5f")
        env = dict(
            os.environ,
            QT_QPA_PLATFORM="offscreen",
            LD_LIBRARY_PATH=str(CC_M3C2 / "lib" / "cloudcompare"),
            XDG_CONFIG_HOME=str(t),
        )
        cmd = [
            str(exe), "-SILENT", "-NO_TIMESTAMP", "-AUTO_SAVE", "ON", "-C_EXPORT_FMT", "ASC",
            "-PREC", "6", "-SEP", "SPACE", "-ADD_HEADER", "-O", "ref.xyz", "-O", "cmp.xyz",
            "-O", "cmp.xyz", "-M3C2", str(params),
        ]
        subprocess.run(cmd, cwd=t, env=env, check=True, capture_output=True, timeout=1800)
        found = sorted(t.glob("*M3C2*.asc"))
        if not found:
            raise RuntimeError("CloudCompare wrote no M3C2 output")
        head = found[0].read_text().splitlines()[0].lstrip("/").split()
        out = np.loadtxt(found[0], skiprows=1)
    if out.shape[0] != cmp_.shape[0] or not np.allclose(out[:, :3], cmp_ - o, atol=1e-3):
        raise RuntimeError("CloudCompare M3C2 changed the point order")
    col = [i for i, h in enumerate(head) if h.lower().startswith("m3c2") and "dist" in h.lower()]
    return out[:, col[0] if col else 3]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one synthetic pair, no speed block")
    ap.add_argument("--no-cc", action="store_true", help="skip CloudCompare C2C")
    ap.add_argument("--no-m3c2", action="store_true", help="skip py4dgeo M3C2")
    ap.add_argument("--seed", type=int, default=0, help="first seed")
    ap.add_argument("--seeds", type=int, default=3, help="synthetic pairs per case")
    ap.add_argument(
        "--densities",
        default=f"{SCANNER_DENSITY:.0f},400",
        help="shell densities of the synthetic pairs, points/m^2, comma-separated",
    )
    ap.add_argument("--speed-points", type=int, default=1_000_000)
    ap.add_argument("--drift-points", type=int, default=600_000)
    ap.add_argument("--speed-only", action="store_true", help="only the speed block")
    ap.add_argument(
        "--survey-only", action="store_true", help="only the surveyor's blocks (issue 17)"
    )
    ap.add_argument(
        "--survey-densities", default="400,900,2600", help="densities of the surveyor's block"
    )
    ap.add_argument("--survey-sections", default="rectangle,arch")
    ap.add_argument("--survey-noises", default=",".join(k for k in SURVEY_NOISE if "1.8" not in k))
    ap.add_argument(
        "--cache", default=None, help="directory keeping registered pairs between runs"
    )
    ap.add_argument(
        "--cached-only", action="store_true", help="surveyor's blocks: only pairs in --cache"
    )
    ap.add_argument("--no-drift", action="store_true", help="skip the real drift block")
    args = ap.parse_args()
    if args.speed_only:
        speed_block(args.speed_points, args.seed)
        return
    seeds = list(range(args.seed, args.seed + args.seeds))
    if args.survey_only:
        survey_block(
            seeds,
            args.cache,
            sections=args.survey_sections.split(","),
            densities=[float(x) for x in args.survey_densities.split(",")],
            noises=args.survey_noises.split(","),
            cc=not args.no_cc,
            cached_only=args.cached_only,
        )
        floor_block(seeds, args.cache, args.cached_only)
        if not args.no_drift:
            drift_block(["robust"] + ([] if args.no_cc else ["cc-m3c2"]), args.drift_points,
                        args.seed, amp=0.019, registered=True, seeds=seeds)
        return
    methods = ["knn", "robust"]
    if not args.no_cc:
        methods.append("cc-c2c")
    if not args.no_m3c2:
        try:
            import py4dgeo  # noqa: F401

            methods.append("py4dgeo-m3c2")
        except ImportError:
            print("py4dgeo not installed (pip install py4dgeo): M3C2 rows skipped")
    t0 = time.perf_counter()
    seeds = list(range(args.seed, args.seed + (1 if args.quick else args.seeds)))
    densities = [400.0] if args.quick else [float(x) for x in args.densities.split(",")]
    for density in densities:
        synth_block(methods, args.quick, seeds, density)
        registration_block(methods, seeds, density)
    drift_block(methods, args.drift_points, args.seed)
    if not args.quick and args.speed_points > 0:
        # a fresh process: the peers run before it leave thread pools and memory behind that
        # slowed the same code by 20-40 %
        cmd = [sys.executable, __file__, "--speed-only", "--speed-points", str(args.speed_points)]
        subprocess.run([*cmd, "--seed", str(args.seed)], check=True)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
