"""The built-in demonstration: a synthetic pair with known deformation, run end to end.

``tunneldef demo DIR`` makes a rectangular tunnel (the paper's 5.8 m x 2.86 m section) with
pipes, a conveyor whose coal load changes, a side chamber, rough rock and scanner noise of
+-3 cm; the
compared epoch has a roof sag, a wall bulge and a floor heave of known size and is moved by an
arbitrary rigid motion. It runs :func:`tunneldef.pipeline.detect`, writes the outputs and the
figures, and logs measured against true deformation.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from .config import Config
from .progress import ProgressCallback
from .transforms import apply_transform

__all__ = ["demo_spec", "run_demo"]

log = logging.getLogger(__name__)

#: a deformation's core is read well when its median is within this share of the truth's, %
TOLERANCE_PCT = 10.0


def demo_spec(*, seed: int = 0, quick: bool = False) -> Any:
    """The demo's :class:`tunneldef.synth.PairSpec` (``quick``: a shorter, sparser tunnel)."""
    from . import synth

    length = 24.0 if quick else 40.0
    return synth.PairSpec(
        tunnel=synth.TunnelSpec(
            length=length,
            section=synth.SectionSpec(kind="rectangle"),
            density=150.0 if quick else 400.0,
            noise_sigma=0.015,
            chamber=True,
            chamber_chainage=0.65 * length,
            equipment=True,
            conveyor=True,
            roughness=0.02,
        ),
        deformations=(
            synth.DeformationSpec(kind="roof_sag", chainage=0.5 * length, length=4.0,
                                  width=2.0, amplitude=0.03),
            synth.DeformationSpec(kind="wall_bulge", chainage=0.25 * length, length=3.0,
                                  width=1.2, amplitude=0.04, side="left"),
            synth.DeformationSpec(kind="floor_heave", chainage=0.75 * length, length=3.0,
                                  width=2.0, amplitude=0.05),
        ),
        cmp_shift=1.5,
        seed=seed,
    )


def measured_vs_truth(result: Any, truth: Any, spec: Any) -> list[dict[str, Any]]:
    """For each true deformation: its amplitude and chainage, and what the result measured.

    Over the core of each patch (the compared shell points whose true displacement exceeds 80 %
    of the amplitude), the true and the measured values are the medians of the true
    displacement and of the measured deformation; the chainage is that of the 0.5 m section
    with the most negative measured median there. ``error_pct`` is the measured median's
    error relative to the true one, and ``within_tolerance`` whether it is within
    ``TOLERANCE_PCT`` (of the size: positive when the change reads larger than it is).
    """
    d = np.asarray(result.cloud.fields["deformation"], float)
    s = np.asarray(result.cloud.fields["chainage"], float)
    rows = []
    for dspec in spec.deformations:
        near = np.abs(truth.chainage - dspec.chainage) < dspec.length
        core = near & (truth.displacement <= -0.8 * dspec.amplitude) & (truth.label == 0)
        if not core.any():
            continue
        med = float(np.nanmedian(d[core]))
        bins = np.round(s[core] / 0.5) * 0.5
        ub = np.unique(bins)
        per = np.array([np.nanmedian(d[core][bins == b]) for b in ub])
        rows.append({
            "kind": dspec.kind,
            "amplitude_mm": -1e3 * dspec.amplitude,
            "true_mm": 1e3 * float(np.median(truth.displacement[core])),
            "measured_mm": 1e3 * med,
            "true_chainage_m": float(np.median(truth.chainage[core])),
            "measured_chainage_m": float(ub[np.argmin(per)]),
            "points": int(core.sum()),
        })
        true = rows[-1]["true_mm"]
        # of the size: > 0 reads the change larger than it is, < 0 smaller
        rows[-1]["error_pct"] = 100.0 * (abs(rows[-1]["measured_mm"]) - abs(true)) / abs(true)
        rows[-1]["within_tolerance"] = bool(abs(rows[-1]["error_pct"]) <= TOLERANCE_PCT)
    return rows


def run_demo(
    out_dir: Path, *, seed: int = 0, quick: bool = False,
    config: Config | None = None, progress: ProgressCallback | None = None,
) -> dict[str, Any]:
    """Make the demo pair, run detect, write outputs and figures into ``out_dir``.

    Returns
    -------
    dict
        Paths written and the measured-versus-true table.
    """
    from . import synth
    from .deformation.sections import write_sections_csv
    from .io import write
    from .pipeline import detect
    from .report.figures import plot_cross_section, plot_danger_map, plot_deformation_map
    from .textfiles import write_json

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    spec = demo_spec(seed=seed, quick=quick)
    log.info("making a synthetic pair (%.0f m rectangular tunnel, noise sigma 15 mm)...",
             spec.tunnel.length)
    pair = synth.make_pair(spec)
    paths: dict[str, Path] = dict(synth.write_pair(pair, out_dir, fmt="ply"))
    log.info("reference: %s points, compared: %s points", f"{len(pair.ref):,}",
             f"{len(pair.cmp):,}")

    # the demo's sags are 30-50 mm: flag from 20 mm so that the danger map has something to show
    config = config or Config().replace(danger={"threshold": 0.02})
    result = detect(pair.ref, pair.cmp, config, progress=progress)
    paths["result"] = out_dir / "result.ply"
    write(paths["result"], result.cloud)
    summary = result.summary()
    table = measured_vs_truth(result, pair.truth, spec)
    summary["demo_truth"] = table
    paths["summary"] = out_dir / "summary.json"
    write_json(paths["summary"], summary)
    paths["sections"] = out_dir / "sections.csv"
    write_sections_csv(result.sections, paths["sections"])

    f = result.cloud.fields
    shell = np.asarray(f.get("shell", np.ones(len(result.cloud), bool)), bool)
    paths["deformation_map"] = plot_deformation_map(
        result.cloud.xyz, f["deformation"], result.ref_centerline,
        out_dir / "deformation_map.png", shell=shell, limit=0.06)
    paths["danger_map"] = plot_danger_map(
        result.cloud.xyz, f["danger"], result.ref_centerline, out_dir / "danger_map.png",
        shell=shell, threshold=result.danger_threshold)
    sag = next((r for r in table if r["kind"] == "roof_sag"), None)
    at = sag["measured_chainage_m"] if sag else 0.5 * result.ref_centerline.length
    paths["cross_section"] = plot_cross_section(
        pair.ref.xyz, result.cloud.xyz, f["deformation"], result.ref_centerline, at,
        out_dir / "cross_section.png", limit=0.06)

    err = _registration_error(result.transform, pair.truth)
    log.info("registration: point error vs truth %.1f mm RMS", 1e3 * err)
    log.info("%-12s %10s %10s %10s %7s %11s %13s", "deformation", "amplitude", "true core",
             "measured", "error", "true s (m)", "measured s")
    for r in table:
        log.info("%-12s %7.1f mm %7.1f mm %7.1f mm %+6.1f%% %11.2f %13.2f  %s", r["kind"],
                 r["amplitude_mm"], r["true_mm"], r["measured_mm"], r["error_pct"],
                 r["true_chainage_m"], r["measured_chainage_m"],
                 f"within {TOLERANCE_PCT:.0f} % of the true core" if r["within_tolerance"]
                 else f"NOT within {TOLERANCE_PCT:.0f} % of the true core")
    for name, p in paths.items():
        log.info("wrote %-16s %s", name, p)
    return {"paths": paths, "table": table, "registration_rms_m": err, "result": result}


def _registration_error(transform: np.ndarray, truth: Any) -> float:
    """RMS distance between compared points mapped by ``transform`` and by the true motion."""
    x = truth.cmp_xyz_in_ref
    t = np.asarray(truth.transform, float)
    src = (x - t[:3, 3]) @ t[:3, :3]  # back to the compared frame
    est = apply_transform(transform, src)
    return float(np.sqrt(np.mean(np.sum((est - x) ** 2, axis=1))))
