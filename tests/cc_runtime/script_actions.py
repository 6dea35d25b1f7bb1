"""Run inside CloudCompare: ``CloudCompare -SILENT -O ref.ply -O cmp.ply -PYTHON_SCRIPT
script_actions.py`` (first loaded cloud = reference).

Runs the code path of each menu action below the selection (``plugin.centerline_on``,
``plugin.register_on``, ``plugin.detect_on``: runtime check, reading the entities, the core on
the worker thread with ``pycc.ProcessEvents``, the progress dialog, writing fields and making
entities) and saves what landed in CloudCompare for the tests to compare with the core:

* ``$TDCC_OUT/report.json``: per action, seconds, names, counts, colours, shifts;
* ``$TDCC_OUT/arrays.npz``: fields, coordinates of new clouds and polylines (global, float64).

Environment: ``TDCC_ACTIONS`` (comma list of ``centerline,register,detect``; default all),
``TDCC_REPEAT`` (runs of each action in this process; default 1), ``TDCC_WORKER``
(``plugin``, the default, or ``runinthread``: the compute step through ``pycc.RunInThread``,
as older versions of the plugin did, to count its crashes), ``TDCC_NO_ARRAYS=1`` (save no
arrays: for benchmarks on large clouds). Each action's record holds the process's resident
memory (``VmRSS``) and its peak so far (``VmHWM``) before and after it, GB.
"""

from __future__ import annotations

import json
import os
import time
import traceback

import numpy as np
from inside import sf_array

OUT = os.environ.get("TDCC_OUT", ".")
REPORT: dict = {"actions": [], "errors": []}
ARRAYS: dict[str, np.ndarray] = {}


def memory() -> dict[str, float]:
    """This process's resident memory now and at its peak, GB (Linux ``/proc``)."""
    out = {}
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line.split(":")[0]] = int(line.split()[1]) / 1024**2
    return out


def save() -> None:
    """Write the report (after every step, so a crash leaves what was done)."""
    path = os.path.join(OUT, "report.json")
    with open(path + ".tmp", "w", encoding="utf-8") as fh:
        json.dump(REPORT, fh, indent=1, default=str)
    os.replace(path + ".tmp", path)  # a crash never leaves half a report


def colours_of(entity, name: str, values: list[float]) -> dict:
    """The RGB CloudCompare gives to ``values`` on field ``name``'s current scale."""
    sf = entity.getScalarField(int(entity.getScalarFieldIndexByName(name)))
    out = {}
    for v in values:
        c = sf.getColor(float(v))
        out[f"{v:.6f}"] = None if c is None else [int(c.r), int(c.g), int(c.b)]
    sat = sf.saturationRange()
    return {
        "rgb": out,
        "symmetrical": bool(sf.symmetricalScale()),
        "saturation": [float(sat.start()), float(sat.stop())],
        "displayed": int(entity.getCurrentDisplayedScalarFieldIndex())
        == int(entity.getScalarFieldIndexByName(name)),
    }


def run_in_runinthread(plugin, adapter) -> None:
    """Make the plugin compute through ``pycc.RunInThread`` (the old way) for crash counting."""
    import pycc

    def old_way(func, *args, bridge, process_events=None, **kwargs):
        out = pycc.RunInThread(adapter.run_guarded, func, *args, progress=bridge, **kwargs)
        return out if out is not None else adapter.Outcome(error=RuntimeError("no result"))

    plugin.adapter.run_in_worker = old_way


def main() -> None:
    import pycc
    from tunneldef_cloudcompare import adapter, plugin

    if os.environ.get("TDCC_WORKER") == "runinthread":
        run_in_runinthread(plugin, adapter)
    adapter.check_runtime(pycc)
    REPORT["runtime_check"] = "passed"
    cli = pycc.GetCmdLineInstance()
    descs = list(cli.clouds())
    ref_e, cmp_e = descs[0].pc, descs[1].pc
    REPORT["shifts"] = {
        "ref": adapter.shift_and_scale(ref_e)[0].tolist(),
        "cmp": adapter.shift_and_scale(cmp_e)[0].tolist(),
    }
    REPORT["points_strides"] = list(np.asarray(ref_e.points()).strides)
    REPORT["sizes"] = [int(ref_e.size()), int(cmp_e.size())]
    REPORT["memory_loaded"] = memory()
    if not os.environ.get("TDCC_NO_ARRAYS"):
        ARRAYS["ref_xyz"] = adapter.read_points(ref_e)
        ARRAYS["cmp_xyz"] = adapter.read_points(cmp_e)
    actions = os.environ.get("TDCC_ACTIONS", "centerline,register,detect").split(",")
    repeat = int(os.environ.get("TDCC_REPEAT", "1"))
    for i in range(repeat):
        for action in actions:
            t0 = time.perf_counter()
            rec: dict = {"action": action, "run": i, "memory_before": memory()}
            try:
                rec.update(ACTIONS[action](plugin, adapter, ref_e, cmp_e, last=i == repeat - 1))
            except Exception:  # noqa: BLE001 - recorded for the test to show
                rec["error"] = traceback.format_exc()
                REPORT["errors"].append(rec["error"])
            rec["seconds"] = round(time.perf_counter() - t0, 3)
            rec["memory_after"] = memory()
            REPORT["actions"].append(rec)
            save()
    np.savez(os.path.join(OUT, "arrays.npz"), **ARRAYS)
    REPORT["finished"] = True
    save()


def do_centerline(plugin, adapter, ref_e, cmp_e, *, last: bool) -> dict:
    poly = plugin.centerline_on(ref_e)
    if poly is None:
        raise RuntimeError("centerline_on returned None")
    if isinstance(poly, list):  # a drift network: one polyline per edge
        if last and not os.environ.get("TDCC_NO_ARRAYS"):
            for k, p in enumerate(poly):
                ARRAYS[f"centerline:{k}"] = adapter.read_points(p.getAssociatedCloud())
        return {"names": [p.getName() for p in poly], "sizes": [int(p.size()) for p in poly]}
    if last and not os.environ.get("TDCC_NO_ARRAYS"):
        ARRAYS["centerline"] = adapter.read_points(poly.getAssociatedCloud())
    return {"name": poly.getName(), "size": int(poly.size())}


def do_register(plugin, adapter, ref_e, cmp_e, *, last: bool) -> dict:
    copy = plugin.register_on(ref_e, cmp_e)
    if copy is None:
        raise RuntimeError("register_on returned None")
    if last and not os.environ.get("TDCC_NO_ARRAYS"):
        ARRAYS["registered_copy"] = adapter.read_points(copy)
    return {"name": copy.getName(), "size": int(copy.size())}


def do_detect(plugin, adapter, ref_e, cmp_e, *, last: bool) -> dict:
    params = adapter.DetectParams.from_config()
    made = plugin.detect_on(ref_e, cmp_e, params)
    if made is None:
        raise RuntimeError("detect_on returned None")
    rec = {"limit": made.limit, "colours": made.colours, "legend": made.legend()}
    if last and not os.environ.get("TDCC_NO_ARRAYS"):
        names = [cmp_e.getScalarFieldName(i) for i in range(cmp_e.getNumberOfScalarFields())]
        rec["cmp_fields"] = names
        for name in names:
            ARRAYS[f"field:{name}"] = sf_array(cmp_e, name)
        ARRAYS["cmp_after"] = adapter.read_points(cmp_e)
        ARRAYS["registered"] = adapter.read_points(made.registered)
        ARRAYS["registered_deformation"] = sf_array(made.registered, "deformation")
        ARRAYS["ref_centerline"] = adapter.read_points(made.ref_centerline.getAssociatedCloud())
        ARRAYS["cmp_centerline"] = adapter.read_points(made.cmp_centerline.getAssociatedCloud())
        for key, lines in (("ref", made.ref_lines), ("cmp", made.cmp_lines)):
            for k, line in enumerate(lines):
                ARRAYS[f"{key}_line:{k}"] = adapter.read_points(line.getAssociatedCloud())
        lim = made.limit
        rec["scale"] = colours_of(cmp_e, "deformation", [-lim, -lim / 2, 0.0, lim / 2, lim])
        rec["registered_shift"] = adapter.shift_and_scale(made.registered)[0].tolist()
        rec["polylines"] = [line.getName() for line in made.ref_lines + made.cmp_lines]
    return rec


ACTIONS = {"centerline": do_centerline, "register": do_register, "detect": do_detect}

main()
