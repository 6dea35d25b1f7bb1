"""The CloudCompare plugin in the real CloudCompare 2.13 + PythonRuntime: crashes over repeated
runs, and detection on large clouds.

Usage
-----
    python benchmarks/plugin_runtime.py crashes [--runs 50] [--worker plugin|runinthread]
    python benchmarks/plugin_runtime.py large [--points 16e6] [--length 350]
    python benchmarks/plugin_runtime.py screenshot docs/img/cloudcompare_plugin.png

``crashes``: ``--runs`` CloudCompare processes (``-PYTHON_SCRIPT``, offscreen), each running
the plugin's three jobs (Extract centerline, Register to reference, Detect deformation) on a
small synthetic pair (22 k points per epoch); a process that dies before its last job is a
crash, charged to the job it was in. ``--worker runinthread`` computes through
``pycc.RunInThread`` instead of the plugin's worker thread (the way the plugin ran before),
for comparison. Prints one row per job: runs, completed, crashed, errors, mean seconds.

``large``: a synthetic pair of ``--points`` per epoch (PLY files), loaded by CloudCompare and
given to *Detect deformation* (``plugin.detect_on``), then the same files through the core
alone (``tunneldef.pipeline.detect`` in a plain Python process, in chainage tiles as the
plugin and ``tunneldef detect`` run it). Prints wall time and peak
resident memory of the whole CloudCompare process and of the core-alone process, and
CloudCompare's memory once the clouds are loaded.

``screenshot``: CloudCompare's window (Xvfb) after the menu actions on a 30 m synthetic pair
with an 80 mm roof sag and a 60 mm wall bulge, the compared cloud shown alone with its
``deformation`` colours (ImageMagick's ``import``).

Needs the build described in ``tests/cc_runtime/runner.py`` (found or unpacked from
``../shared/cloudcompare-python/``).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from cc_runtime.runner import HERE, find_runtime, write_pair  # noqa: E402

JOBS = ("centerline", "register", "detect")


def crashes(
    runs: int, worker: str, jobs: tuple[str, ...] = JOBS, keep: Path | None = None
) -> dict[str, dict[str, float]]:
    """Run ``jobs`` in ``runs`` CloudCompare processes; per-job counts and mean time."""
    rt = find_runtime()
    top = Path(tempfile.mkdtemp(prefix="tdcc-crash-")) if keep is None else keep
    ref, cmp = write_pair(top / "pair")
    stats = {j: {"runs": 0, "completed": 0, "crashed": 0, "errors": 0, "seconds": 0.0}
             for j in jobs}
    exit_codes = []
    for i in range(runs):
        work = top / f"run{i:03d}"
        work.mkdir(parents=True, exist_ok=True)
        env = {"TDCC_OUT": str(work), "TDCC_WORKER": worker, "TDCC_NO_ARRAYS": "1",
               "TDCC_ACTIONS": ",".join(jobs)}
        proc = rt.run_script(HERE / "script_actions.py", [ref, cmp], workdir=work,
                             env_extra=env, timeout=600)
        exit_codes.append(proc.returncode)
        (work / "cloudcompare.log").write_text(proc.stdout + proc.stderr, encoding="utf-8")
        report_path = work / "report.json"
        try:
            report = json.loads(report_path.read_text())
        except (OSError, ValueError):  # none: died before the first job ended
            report = {}
        done = {a["action"]: a for a in report.get("actions", [])}
        finished = bool(report.get("finished")) and proc.returncode == 0
        for job in jobs:
            s = stats[job]
            if job in done:
                s["runs"] += 1
                s["completed"] += 1
                s["errors"] += int("error" in done[job])
                s["seconds"] += done[job]["seconds"]
            elif not finished and job == next(j for j in jobs if j not in done):
                s["runs"] += 1
                s["crashed"] += 1  # died inside this job
        fatal = [ln for ln in (proc.stdout + proc.stderr).splitlines() if "Fatal" in ln]
        tail = "" if finished else f" (exit {proc.returncode}) {fatal[:1]}"
        print(f"run {i + 1}/{runs}: {'ok' if finished else 'CRASHED'}{tail}", flush=True)
    for s in stats.values():
        s["seconds"] = s["seconds"] / max(s["completed"], 1)
    return {"jobs": stats, "exit_codes": exit_codes}


def _child_peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2


_CORE_ALONE = """
import resource, sys, tempfile, time
from tunneldef.engine import open_engine
from tunneldef.io import read
from tunneldef.pipeline import detect
t = time.perf_counter()
ref, cmp = read(sys.argv[1]), read(sys.argv[2])
t_read = time.perf_counter() - t
t = time.perf_counter()
with open_engine() as engine:  # the tiles of `tunneldef detect` and of the plugin
    res = detect(ref, cmp, tiles={"memory_gb": engine.tile_memory_gb, "engine": engine,
                                  "workdir": tempfile.gettempdir()})
t_detect = time.perf_counter() - t
print(t_read, t_detect, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2)
"""


def large(points: float, length: float, workdir: Path) -> dict[str, float]:
    """Detect on two ``points``-point clouds inside CloudCompare and with the core alone."""
    rt = find_runtime()
    perimeter = 2 * (5.8 + 2.86)
    density = points / (perimeter * length)
    t = time.perf_counter()
    ref, cmp = write_pair(workdir / "pair", length=length, density=density)
    t_write = time.perf_counter() - t
    out = {"synth_and_write_s": t_write}

    work = workdir / "cc"
    work.mkdir(parents=True, exist_ok=True)
    env = {"TDCC_OUT": str(work), "TDCC_ACTIONS": "detect", "TDCC_NO_ARRAYS": "1"}
    t = time.perf_counter()
    proc = rt.run_script(HERE / "script_actions.py", [ref, cmp], workdir=work, env_extra=env,
                         timeout=7200)
    out["cc_wall_s"] = time.perf_counter() - t
    out["cc_peak_gb"] = _child_peak_gb()
    if proc.returncode != 0:
        raise SystemExit(f"CloudCompare exited {proc.returncode}:\n{proc.stdout[-3000:]}")
    report = json.loads((work / "report.json").read_text())
    det = report["actions"][-1]
    if "error" in det:
        said = [ln for ln in proc.stdout.splitlines() if "Detect deformation" in ln]
        raise SystemExit(det["error"] + "\n".join(said[-3:]))
    out["points_ref"], out["points_cmp"] = report["sizes"]
    out["cc_detect_s"] = det["seconds"]
    out["cc_loaded_gb"] = report["memory_loaded"]["VmRSS"]
    out["cc_peak_in_process_gb"] = det["memory_after"]["VmHWM"]

    t = time.perf_counter()
    core = subprocess.run([sys.executable, "-c", _CORE_ALONE, str(ref), str(cmp)],
                          capture_output=True, text=True, check=True)
    out["core_wall_s"] = time.perf_counter() - t
    t_read, t_detect, peak = (float(v) for v in core.stdout.split()[-3:])
    out.update(core_read_s=t_read, core_detect_s=t_detect, core_peak_gb=peak)
    return out


def screenshot(png: Path) -> Path:
    """The window after the menu actions, the compared cloud coloured by ``deformation``."""
    from tunneldef.synth import DeformationSpec

    rt = find_runtime()
    work = Path(tempfile.mkdtemp(prefix="tdcc-shot-"))
    deformations = (
        DeformationSpec(kind="roof_sag", chainage=9.0, amplitude=0.08, length=5.0, width=3.0),
        DeformationSpec(kind="wall_bulge", chainage=21.0, amplitude=0.06, length=4.0),
    )
    ref, cmp = write_pair(work / "pair", length=30.0, density=150.0, deformations=deformations)
    env = {"TDCC_SCREENSHOT": str(png.resolve())}
    proc = rt.run_gui([ref, cmp], workdir=work, env_extra=env, timeout=900)
    report = json.loads((work / "report.json").read_text())
    if not png.is_file() or report.get("errors"):
        raise SystemExit(f"no screenshot ({proc.returncode}): {report.get('errors')}")
    return png


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("crashes", help="repeated runs of the three jobs; count crashes")
    c.add_argument("--runs", type=int, default=50)
    c.add_argument("--worker", choices=["plugin", "runinthread"], default="plugin")
    c.add_argument("--jobs", default=",".join(JOBS), help="comma list (default: all three)")
    c.add_argument("--max-crashes", type=int, default=None,
                   help="exit 1 when more processes crashed (CI: 0)")
    g = sub.add_parser("large", help="detect on two large clouds inside CloudCompare")
    g.add_argument("--points", type=float, default=16e6, help="points per epoch")
    g.add_argument("--length", type=float, default=350.0, help="tunnel length, m")
    g.add_argument("--workdir", type=Path, default=None)
    h = sub.add_parser("screenshot", help="PNG of CloudCompare's window showing the colours")
    h.add_argument("png", type=Path)
    args = ap.parse_args(argv)

    if args.cmd == "screenshot":
        print(screenshot(args.png))
        return 0
    if args.cmd == "crashes":
        res = crashes(args.runs, args.worker, tuple(args.jobs.split(",")))
        print(f"\nworker: {args.worker}; {args.runs} CloudCompare processes")
        print("| job | runs | completed | crashed | errors | mean s |")
        print("|---|---|---|---|---|---|")
        for job, s in res["jobs"].items():
            print(f"| {job} | {s['runs']} | {s['completed']} | {s['crashed']} | {s['errors']} | "
                  f"{s['seconds']:.1f} |")
        n_crashed = sum(s["crashed"] for s in res["jobs"].values())
        errors = sum(s["errors"] for s in res["jobs"].values())
        print(f"processes crashed: {n_crashed}; jobs with an error: {errors}")
        if args.max_crashes is not None and (n_crashed > args.max_crashes or errors):
            return 1
        return 0

    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="tdcc-large-"))
    r = large(args.points, args.length, workdir)
    print("| points/epoch | CloudCompare: whole process s / peak GB (clouds loaded GB) | "
          "in it, Detect deformation s | core alone: read + detect s / peak GB |")
    print("|---|---|---|---|")
    print(f"| {r['points_ref']:,} / {r['points_cmp']:,} | {r['cc_wall_s']:.1f} / "
          f"{r['cc_peak_gb']:.2f} ({r['cc_loaded_gb']:.2f}) | {r['cc_detect_s']:.1f} | "
          f"{r['core_read_s']:.1f} + {r['core_detect_s']:.1f} / {r['core_peak_gb']:.2f} |")
    print(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
