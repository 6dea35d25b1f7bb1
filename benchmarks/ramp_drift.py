"""A single drift that runs flat and then goes on up a ramp, straight in plan: which way round
the registration keeps it, and how far off along the drift it ends.

Turned end for end and tipped by the grade, such a drift lies on itself, so the direction
candidates fit alike and only the tilt of levelled scans tells them apart; along it, only the
ramp's floor and roof fix the position. Each pair is run through ``detect`` with the checks
recorded but not enforced, and scored against the truth:

* ``tilt kept / other``: how far the kept and the other direction tip the compared epoch's
  vertical (degrees; blank when one direction fitted clearly better);
* ``along / off axis``: the registration's mean error along the drift, and the RMS of its
  error's other two components, on the unchanged shell (mm, against the truth);
* ``claimed``: the registration's along-axis uncertainty (m);
* ``translation left / rigid spread``: the two checks of the position along the drift, the
  translation an independent point-to-plane fit still finds and how far apart a rigid fit
  ends from the pose and 2 cm either side of it (mm; limits 10 mm each);
* ``verified`` and the checks that failed.

Pairs: a 120 m rectangle (60 m flat, 60 m at 12 %, 300 points/m^2, +-1.5 cm noise, own frames
tipped 2 degrees) and three 50-70 m ones (25-35 m flat, then 12 %, 100-150 points/m^2,
+-8 mm, tipped 1.5 degrees).

Run: ``python benchmarks/ramp_drift.py [--quick]`` (``--quick``: the three short pairs only).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tunneldef.config import Config
from tunneldef.errors import TunnelDefError
from tunneldef.pipeline import detect
from tunneldef.synth import SectionSpec
from tunneldef.synth.network import (
    EdgeSpec,
    NetworkPairSpec,
    NetworkSpec,
    Stretch,
    make_network_pair,
)
from tunneldef.transforms import apply_transform

GRADE = 0.12


def pair_spec(flat: float, density: float, noise: float, tilt: float, seed: int,
              yaw: float | None, height: float) -> NetworkPairSpec:
    """``flat`` m level, then as far again up the ramp; the compared walk 3 m shorter at the
    start and 2 m at the end."""
    edge = EdgeSpec("drift", ((0.0, 0.0, 0.0), (flat, 0.0, 0.0), (2 * flat, 0.0, GRADE * flat)),
                    SectionSpec("rectangle", 4.5, height), bend_radius=15.0)
    return NetworkPairSpec(NetworkSpec((edge,), (), name="flat then ramp"),
                           ref_coverage=(Stretch(0, 0.0, 2 * flat),),
                           cmp_coverage=(Stretch(0, 3.0, 2 * flat - 2.0),), density=density,
                           noise_sigma=noise, drift=0.0, stray_distance=0.0, stray_clusters=0,
                           yaw_deg=yaw, tilt_deg=tilt, seed=seed)


PAIRS = {
    "120 m, 300/m2, 1.5 cm": dict(flat=60.0, density=300.0, noise=0.015, tilt=2.0, seed=2,
                                  yaw=None, height=3.2),
    "50 m, 100/m2, 8 mm": dict(flat=25.0, density=100.0, noise=0.008, tilt=1.5, seed=2,
                               yaw=140.0, height=3.0),
    "70 m, 120/m2, 8 mm": dict(flat=35.0, density=120.0, noise=0.008, tilt=1.5, seed=1,
                               yaw=140.0, height=3.0),
    "60 m, 150/m2, 8 mm": dict(flat=30.0, density=150.0, noise=0.008, tilt=1.5, seed=3,
                               yaw=140.0, height=3.0),
}


def run(name: str, **kw) -> str:
    """One pair through ``detect`` (checks not enforced), one table row."""
    pair = make_network_pair(pair_spec(**kw))
    t0 = time.perf_counter()
    try:
        res = detect(pair.ref, pair.cmp, Config().replace(quality={"enforce": False}))
    except TunnelDefError as exc:
        return f"| {name} | refused: {exc} |"
    seconds = time.perf_counter() - t0
    reg, ep = res.registration, pair.truth.cmp
    keep = ep.shell & (ep.displacement == 0) & ~ep.stray
    err = res.cloud.xyz[keep] - apply_transform(pair.truth.transform, pair.cmp.xyz[keep])
    # the drift runs along the reference (design) frame's x axis
    along = float(np.mean(err[:, 0]))
    off = float(np.sqrt(np.mean(err[:, 1] ** 2 + err[:, 2] ** 2)))
    tilts = reg.info.get("direction_tilts_deg")
    tilt = f"{tilts[0]:.1f} / {tilts[1]:.1f}" if tilts else ""
    failed = ", ".join(c.name for c in res.quality.failed) or "-"
    figures = {c.name: c.figure for c in res.quality.checks}
    held = [1e3 * figures.get(k, np.nan) for k in ("registration.translation_residual",
                                                   "registration.rigid_convergence")]
    return (f"| {name} | {tilt} | {1e3 * along:+.1f} | {1e3 * off:.1f} | "
            f"{reg.axial_uncertainty:.3f} | {held[0]:.1f} / {held[1]:.1f} | "
            f"{res.quality.verified} | {failed} | {seconds:.0f} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the three short pairs only")
    args = ap.parse_args(argv)
    print("| pair | tilt kept / other (deg) | along (mm) | off axis (mm) | claimed (m) | "
          "translation left / rigid spread (mm) | verified | failed checks | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, kw in PAIRS.items():
        if args.quick and kw["flat"] >= 60.0:
            continue
        print(run(name, **kw), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
