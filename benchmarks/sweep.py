"""Random synthetic pairs over the whole ``tunneldef.synth`` space: right, or refused, never
silently wrong.

Each case draws a tunnel (20-120 m, straight or curved with R >= 60 m, rectangle / arch /
trapezoid 2-7 m wide, chambers, pipes and cables, a conveyor with coal, occlusion holes,
200-3000 points/m^2, +-0.5 to +-3 cm noise, outliers, rough rock, any yaw, a tilt, survey-size
coordinates, the later epoch covering a stretch shifted by 0-10 m, 0-3 deformations of
10-60 mm), runs :func:`tunneldef.pipeline.detect` and sorts the outcome:

* ``correct``: exit 0, registration within 1 cm RMS of the truth over the compared points and
  both centrelines within 3 cm (p95, 1 m inside the ends) of the design axis;
* ``refused``: a :class:`~tunneldef.errors.TunnelDefError` with its one-line reason;
* ``WRONG``: exit 0 but not correct (a silent wrong answer: the failure this sweep exists for);
* ``CRASH``: any other exception.

A case "has an along-axis feature" when a chamber lies wholly inside the common stretch or the
rock is rough (relief >= 1 cm): something that fixes the position along the tunnel. A bend of
constant radius (all that ``synth`` draws) fixes nothing: the arc slides along itself. Pairs
without a feature should be refused.

Speed: by default the drawn density is thinned so that an epoch holds at most ``--budget``
points (250 000, but never below 130 points/m^2, which keeps >= 200 points in a 0.2 m slice);
a case then takes about 30-90 s on 2 shared cores, 200 cases a few hours. ``--budget 0`` uses
the drawn density.

Usage::

    python benchmarks/sweep.py --cases 200 --seed 1
    python benchmarks/sweep.py --replay 1000123      # one case by its printed seed
    python benchmarks/sweep.py --no-enforce --jsonl calib.jsonl   # every check's figure

``--no-enforce`` runs every case to the end with the checks recorded but not enforced: each
case is then sorted by the truth alone, and its JSON line lists the checks that would have
refused it (``failed``), so the checks' limits can be judged against the truth.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tunneldef.config import Config
from tunneldef.errors import ConfigError, TunnelDefError
from tunneldef.pipeline import detect
from tunneldef.synth import DeformationSpec, PairSpec, SectionSpec, TunnelSpec, make_pair
from tunneldef.transforms import apply_transform

REG_LIMIT = 0.01  # m RMS against the truth
CENTRE_LIMIT = 0.03  # m, p95 of the centreline's distance to the design axis
MIN_DENSITY = 130.0  # points/m^2: >= 200 points in a 0.2 m slice of an 8 m perimeter


@dataclass
class Case:
    """One drawn pair and what became of it."""

    seed: int
    spec: PairSpec
    drawn_density: float
    featured: bool
    outcome: str = ""
    reason: str = ""
    reg_rms: float = np.nan
    centre_p95: float = np.nan
    seconds: float = np.nan
    points: int = 0
    info: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> str:
        t = self.spec.tunnel
        shape = "straight" if t.radius is None else f"R{t.radius:+.0f}"
        extras = "".join(
            k for k, v in (("C", t.chamber), ("E", t.equipment), ("V", t.conveyor)) if v
        )
        return (
            f"{t.length:5.1f}m {shape:>6s} {t.section.kind[:4]} {t.section.width:.1f}x"
            f"{t.section.height:.1f} {extras or '-':3s} h{t.holes} {t.density:4.0f}/m2 "
            f"n{1000 * t.noise_sigma:4.1f}mm r{1000 * t.roughness:4.1f}mm "
            f"sh{self.spec.cmp_shift:4.1f} d{len(self.spec.deformations)}"
        )


def _perimeter(s: SectionSpec) -> float:
    return 2.0 * (s.width + s.height)


def draw(
    seed: int,
    budget: int = 250_000,
    lengths: tuple[float, float] = (20.0, 120.0),
    *,
    min_density: float = MIN_DENSITY,
    min_slice_points: float = 300.0,
) -> Case:
    """The pair of case ``seed`` (deterministic for given ``budget`` and ``lengths``).

    Parameters
    ----------
    seed : int
        Case seed (also the seed of :func:`tunneldef.synth.make_pair`).
    budget : int
        Most points per epoch: the drawn density is thinned to it, but never below
        ``min_density`` (points/m^2) nor below ``min_slice_points`` per 0.2 m slice of shell
        (0: the drawn density).
    lengths : (float, float)
        Range of the tunnel length, m.
    """
    rng = np.random.default_rng(seed)
    for _ in range(100):
        length = float(rng.uniform(*lengths))
        radius = None
        if rng.random() < 0.4:
            radius = float(rng.choice([-1.0, 1.0]) * rng.uniform(60.0, 400.0))
        kind = str(rng.choice(["rectangle", "arch", "trapezoid"]))
        width = float(rng.uniform(2.0, 7.0))
        height = float(rng.uniform(max(1.8, 0.35 * width), min(4.5, max(2.0, 0.9 * width))))
        section = SectionSpec(kind=kind, width=width, height=height)
        drawn = float(np.exp(rng.uniform(np.log(200.0), np.log(3000.0))))
        density = drawn
        if budget > 0:
            cap = budget / (length * _perimeter(section))
            floor = max(min_density, min_slice_points / (0.2 * _perimeter(section)))
            density = min(drawn, max(floor, cap))
        shift = float(rng.uniform(0.0, 10.0))
        chamber = bool(rng.random() < 0.5)
        roughness = float(rng.uniform(0.005, 0.03)) if rng.random() < 0.3 else 0.0
        try:
            tunnel = TunnelSpec(
                length=length,
                radius=radius,
                grade=float(rng.uniform(-0.03, 0.03)),
                section=section,
                density=density,
                noise_sigma=float(rng.uniform(0.005, 0.03)),
                outlier_fraction=float(rng.uniform(0.0, 0.005)),
                chamber=chamber,
                equipment=bool(rng.random() < 0.5),
                conveyor=bool(width >= 3.0 and rng.random() < 0.4),
                holes=int(rng.integers(0, 7)),
                roughness=roughness,
                chamber_side=str(rng.choice(["left", "right"])),
            )
            defs = []
            for _ in range(int(rng.integers(0, 4))):
                defs.append(
                    DeformationSpec(
                        kind=str(rng.choice(["roof_sag", "wall_bulge", "floor_heave"])),
                        chainage=float(rng.uniform(shift + 3.0, length - 3.0)),
                        length=float(rng.uniform(2.0, 5.0)),
                        width=float(rng.uniform(0.8, min(2.0, 0.5 * height))),
                        amplitude=float(rng.uniform(0.01, 0.06)),
                        side=str(rng.choice(["left", "right"])),
                    )
                )
            survey = rng.random() < 0.5
            translation = (
                (float(rng.uniform(4e5, 6e5)), float(rng.uniform(5.3e6, 5.5e6)),
                 float(rng.uniform(-500, 500)))
                if survey
                else tuple(float(v) for v in rng.uniform(-200, 200, 3))
            )
            spec = PairSpec(
                tunnel=tunnel,
                deformations=tuple(defs),
                cmp_shift=shift,
                yaw_deg=float(rng.uniform(0.0, 360.0)),
                tilt_deg=float(rng.uniform(0.0, 3.0)),
                translation=translation,
                seed=seed,
            )
        except ConfigError:
            continue
        c0 = length / 2  # the chamber's centre (synth default: mid-length)
        half = tunnel.chamber_length / 2
        # (a circular bend is no feature: sliding along a constant-radius arc changes nothing)
        featured = (chamber and c0 - half >= shift and c0 + half <= length) or roughness >= 0.01
        return Case(seed, spec, drawn, bool(featured))
    raise RuntimeError(f"case {seed}: no valid pair drawn")


def _centre_p95(cl: Any, truth: Any, margin: float = 1.0) -> float:
    p = truth.project(cl.points)
    keep = (p.chainage > margin) & (p.chainage < truth.length - margin)
    return float(np.percentile(p.distance[keep], 95)) if keep.any() else np.inf


def run_case(case: Case, config: Config | None = None) -> Case:
    """Run detect on the case's pair and sort the outcome (fills the case in place)."""
    pair = make_pair(case.spec)
    case.points = len(pair.ref) + len(pair.cmp)
    t0 = time.perf_counter()
    try:
        result = detect(pair.ref, pair.cmp, config or Config())
    except TunnelDefError as exc:
        case.outcome, case.reason = "refused", str(exc)
        report = getattr(exc, "report", None)  # a failed quality check: the figures so far
        if report is not None:
            case.info["quality"] = report.to_dict()
    except Exception as exc:  # noqa: BLE001 - a crash is an outcome of the sweep
        case.outcome, case.reason = "CRASH", f"{type(exc).__name__}: {exc}"
    else:
        moved = apply_transform(result.transform, pair.cmp.xyz)
        err = moved - pair.truth.cmp_xyz_in_ref
        case.reg_rms = float(np.sqrt(np.mean(np.einsum("ij,ij->i", err, err))))
        truth = pair.truth.centerline
        # the compared centreline over the common stretch only (truth: the reference's axis)
        case.centre_p95 = max(
            _centre_p95(result.ref_centerline, truth),
            _centre_p95(result.cmp_centerline, truth),
        )
        ok = case.reg_rms <= REG_LIMIT and case.centre_p95 <= CENTRE_LIMIT
        case.outcome = "correct" if ok else "WRONG"
        if result.quality is not None:
            case.info["quality"] = result.quality.to_dict()
    case.seconds = time.perf_counter() - t0
    return case


def table(cases: list[Case]) -> str:
    """The summary table (Markdown) and the list of refusals and failures."""
    out = []
    rows = [("with an along-axis feature", [c for c in cases if c.featured]),
            ("featureless", [c for c in cases if not c.featured]),
            ("all", cases)]
    out.append("| pairs | n | correct | refused | WRONG (exit 0) | crash |")
    out.append("|---|---:|---:|---:|---:|---:|")
    for name, cs in rows:
        n = len(cs)
        cnt = {k: sum(c.outcome == k for c in cs) for k in ("correct", "refused", "WRONG",
                                                              "CRASH")}
        pct = f" ({100 * cnt['correct'] / n:.0f} %)" if n else ""
        out.append(f"| {name} | {n} | {cnt['correct']}{pct} | {cnt['refused']} | "
                   f"{cnt['WRONG']} | {cnt['CRASH']} |")
    out.append("")
    for c in cases:
        if c.outcome != "correct":
            extra = (f" reg {1000 * c.reg_rms:.1f} mm, centre p95 {1000 * c.centre_p95:.1f} mm"
                     if c.outcome == "WRONG" else "")
            out.append(f"- seed {c.seed} [{c.outcome}{', featured' if c.featured else ''}] "
                       f"{c.describe()}: {c.reason}{extra}")
    return "\n".join(out)


def _record(c: Case) -> dict[str, Any]:
    """One case as JSON: what was drawn, the outcome, and every quality figure."""
    def num(v: float) -> float | None:
        return float(v) if np.isfinite(v) else None

    checks = c.info.get("quality", {}).get("checks", [])
    return {
        "seed": c.seed, "pair": c.describe(), "featured": c.featured,
        "drawn_density": c.drawn_density, "outcome": c.outcome, "reason": c.reason,
        "reg_rms": num(c.reg_rms), "centre_p95": num(c.centre_p95), "seconds": c.seconds,
        "checks": {k["check"]: k["figure"] for k in checks},
        "failed": [k["check"] for k in checks if k["verdict"] == "fail"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=200, help="number of random pairs (200)")
    ap.add_argument("--seed", type=int, default=1, help="sweep seed; case i has seed "
                    "seed * 1000000 + i, printed, so any case replays")
    ap.add_argument("--replay", type=int, nargs="*", help="run only these case seeds")
    ap.add_argument("--budget", type=int, default=250_000,
                    help="most points per epoch (thins the drawn density; 0: no thinning)")
    ap.add_argument("--jsonl", help="also write one JSON line per case (outcome, errors and "
                    "every quality check's figure) to this file")
    ap.add_argument("--no-enforce", action="store_true",
                    help="record the quality checks without enforcing them (each case is then "
                    "sorted by the truth; --jsonl lists the checks that would have refused it)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    config = Config().replace(quality={"enforce": False}) if args.no_enforce else Config()
    seeds = args.replay or [args.seed * 1_000_000 + i for i in range(args.cases)]
    cases = []
    print("| seed | pair (F: along-axis feature) | outcome | reg mm | centre p95 mm | s | reason |")
    print("|---|---|---|---:|---:|---:|---|")
    for s in seeds:
        c = run_case(draw(s, args.budget), config)
        cases.append(c)
        if args.jsonl:
            with open(args.jsonl, "a", encoding="utf-8") as f:
                f.write(json.dumps(_record(c)) + "\n")
        print(f"| {c.seed} | {c.describe()}{' F' if c.featured else ''} | {c.outcome} | "
              f"{1000 * c.reg_rms:.1f} | {1000 * c.centre_p95:.1f} | {c.seconds:.0f} | "
              f"{c.reason} |", flush=True)
    print()
    print(table(cases))
    wrong = sum(c.outcome in ("WRONG", "CRASH") for c in cases)
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main())
