"""Whole-process time and peak memory of `tunneldef detect` against CloudCompare's C2C.

Usage: python benchmarks/scale.py [--rows 60,350,1000] [--keep DIR [--reuse]]
       [--cloudcompare EXE] [-- detect options]

Each row: a synthetic pair (``tunneldef.synth``: chamber, equipment, conveyor, rough rock, a
30 mm roof sag; the compared epoch moved by a rigid motion) of the given length at the
handheld scanner's density, written in the row's format. ``tunneldef detect REF CMP -o OUT``
runs as its own process; then CloudCompare's C2C (k = 1; Debian's 2.11, or the build
given by ``--cloudcompare``, e.g. the 2.13 one of ``../shared/cloudcompare-python``) runs on
the same pair, aligned (the compared epoch in the reference frame, the synthetic truth), as
binary PLY:
``CloudCompare -SILENT -AUTO_SAVE OFF -O ref.ply -O cmp.ply -C2C_DIST``. Wall time and peak
RSS are those of each whole process (``os.wait4``). Rows:

* ``60``: 60 m, 1.15 M + 1.14 M points, PLY in and out;
* ``350``: 350 m, 16 M + 16 M points, LAZ in and out;
* ``1000``: 1 km, 55 M + 55 M points, LAZ in and out. A pair this large does not fit in
  memory with its truth: it is drawn stretch by stretch
  (:func:`tunneldef.synth.large.write_large_pair`) and C2C, which needs the aligned copy, is
  not run on it.

Prints one Markdown table. Other work on the machine slows both programs; the load average
at the start of each row is printed with it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROWS = {  # length m -> (points per epoch without clutter, format)
    60: (0.93e6, "ply"),
    350: (13.2e6, "laz"),
    1000: (45.4e6, "laz"),
}
PERIMETER = 2 * (5.8 + 2.86)
LARGE = 20e6  # points per epoch beyond which the pair is written stretch by stretch


def _run(
    cmd: list[str], env: dict[str, str] | None = None, timeout: float | None = None
) -> tuple[float, float, int, str]:
    """Wall time (s), peak RSS (GiB, 2**30 bytes), exit code and the last lines of stderr of a
    process (killed after ``timeout`` seconds, exit code -9)."""
    import threading

    t = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
        timer = threading.Timer(timeout, proc.kill) if timeout else None
        if timer is not None:
            timer.start()
        _, status, usage = os.wait4(proc.pid, 0)
        if timer is not None:
            timer.cancel()
        wall = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        tail = err.read().decode(errors="replace").strip().splitlines()[-3:]
    return wall, usage.ru_maxrss / 1024**2, proc.returncode, " | ".join(tail)


def _count(folder: Path, fmt: str) -> tuple[int, int]:
    """Points of the kept pair's two epochs."""
    from tunneldef.io.stream import read_points

    return tuple(len(read_points(folder / f"{e}.{fmt}")[0]) for e in ("ref", "cmp"))


def _pair(length: float, points: float, fmt: str, folder: Path) -> tuple[int, int]:
    from tunneldef import synth
    from tunneldef.cloud import Cloud
    from tunneldef.io import write

    spec = synth.PairSpec(
        tunnel=synth.TunnelSpec(length=length, density=points / (PERIMETER * length),
                                chamber=True, chamber_chainage=0.4 * length, equipment=True,
                                conveyor=True, roughness=0.02),
        deformations=(synth.DeformationSpec(kind="roof_sag", chainage=length / 2,
                                            amplitude=0.03),),
        cmp_shift=1.0, yaw_deg=140.0, seed=11,
    )
    if points > LARGE:
        # too large to hold with its truth: drawn stretch by stretch, no aligned copy for C2C
        from tunneldef.synth.large import write_large_pair

        got = json.loads(write_large_pair(spec, folder, fmt=fmt)["truth"].read_text())["points"]
        return got["ref"], got["cmp"]
    pair = synth.make_pair(spec)
    write(folder / f"ref.{fmt}", pair.ref)
    write(folder / f"cmp.{fmt}", pair.cmp)
    # the aligned pair for C2C, binary PLY, coordinates only
    write(folder / "c2c_ref.ply", Cloud(pair.ref.xyz))
    write(folder / "c2c_cmp.ply", Cloud(pair.truth.cmp_xyz_in_ref))
    return len(pair.ref), len(pair.cmp)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", default="60,350", help="lengths to run, m (60, 350, 1000)")
    ap.add_argument("--keep", help="keep the pairs and outputs in this folder")
    ap.add_argument("--reuse", action="store_true",
                    help="reuse the pairs already in --keep")
    ap.add_argument("--cloudcompare", default=None,
                    help="CloudCompare executable for C2C (default: CloudCompare on PATH, "
                         "Debian's 2.11); a build unpacked as in ../shared/cloudcompare-python "
                         "(e.g. /opt/cloudcompare-m3c2/bin/CloudCompare, 2.13) gets its "
                         "lib/cloudcompare on LD_LIBRARY_PATH")
    ap.add_argument("--c2c-timeout", type=float, default=3600.0,
                    help="stop C2C after this many seconds and print it as not finished")
    ap.add_argument("detect_args", nargs="*", help="extra options for tunneldef detect")
    args = ap.parse_args()
    # the pairs are drawn (or counted) in a helper process: a child forked from a parent that
    # holds a 350 m pair starts with the parent's resident pages, and getrusage's peak keeps
    # them across exec (detect and C2C both read 3.13 GB that way, the parent's size)
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    helper = ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn"))
    cc = args.cloudcompare or shutil.which("CloudCompare")
    cc_env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    if args.cloudcompare:
        libs = Path(args.cloudcompare).resolve().parent.parent / "lib" / "cloudcompare"
        if libs.is_dir():
            cc_env["LD_LIBRARY_PATH"] = str(libs)
    lines = ["| points (ref + cmp) | length | format | detect wall s | detect peak RSS GiB | "
             "C2C wall s | C2C peak RSS GiB | detect / C2C time | load avg |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in args.rows.split(","):
        length = int(row)
        points, fmt = ROWS[length]
        base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="scale-"))
        folder = base / f"{length}m"
        folder.mkdir(parents=True, exist_ok=True)
        try:
            t = time.perf_counter()
            if args.reuse and (folder / f"cmp.{fmt}").exists():
                n_ref, n_cmp = helper.submit(_count, folder, fmt).result()
            else:
                n_ref, n_cmp = helper.submit(_pair, length, points, fmt, folder).result()
            print(f"{length} m: pair ready in {time.perf_counter() - t:.0f} s", file=sys.stderr)
            load = os.getloadavg()[0]
            cmd = [sys.executable, "-c", "import sys; from tunneldef.cli import main; "
                   "sys.exit(main())", "detect", str(folder / f"ref.{fmt}"),
                   str(folder / f"cmp.{fmt}"), "-o", str(folder / f"out.{fmt}"), "--quiet",
                   *args.detect_args]
            d_wall, d_rss, code, tail = _run(cmd)
            if code != 0:
                print(f"detect failed ({code}): {tail}", file=sys.stderr)
            c_wall = c_rss = float("nan")
            if cc and (folder / "c2c_cmp.ply").exists():
                c_wall, c_rss, c_code, c_tail = _run(
                    [cc, "-SILENT", "-AUTO_SAVE", "OFF", "-O", str(folder / "c2c_ref.ply"),
                     "-O", str(folder / "c2c_cmp.ply"), "-C2C_DIST"], cc_env,
                    timeout=args.c2c_timeout)
                if c_code != 0:
                    print(f"CloudCompare failed ({c_code}): {c_tail}", file=sys.stderr)
                    c_wall = c_rss = float("nan")
            ratio = d_wall / c_wall if np.isfinite(c_wall) else float("nan")
            status = "" if code == 0 else " (failed)"
            lines.append(f"| {n_ref / 1e6:.2f} M + {n_cmp / 1e6:.2f} M | {length} m | {fmt} | "
                         f"{d_wall:.1f}{status} | {d_rss:.2f} | {c_wall:.1f} | {c_rss:.2f} | "
                         f"{ratio:.1f}x | {load:.1f} |")
            print(lines[-1], file=sys.stderr)
        finally:
            if not args.keep:
                shutil.rmtree(base, ignore_errors=True)
    helper.shutdown()
    print("\n".join(lines))


if __name__ == "__main__":
    main()
