"""Detect tunnel deformation inside CloudCompare (Python runtime), without the menu plugin.

Usage
-----
From CloudCompare's Python console / script editor (GUI): select two point clouds, the
reference (earlier epoch) FIRST, then run this file. It does what the menu action
"Detect deformation" does (same adapter; the dialog lets you swap the two).

From CloudCompare's command line (the Python runtime plugin must be installed)::

    CloudCompare -SILENT -O ref.las -O cmp.las -PYTHON_SCRIPT detect_in_cloudcompare.py \
        [OUT.ply] [--threshold 0.05] [--method robust|knn] [--k 3]
        [--network auto|single|network]

The FIRST loaded cloud is the reference. Put ``-PYTHON_SCRIPT`` last: the runtime hands every
argument after the script name to the script. OUT (default: ``<compared>_deformation.ply``
next to the compared file) is written with tunneldef's writer: the compared points in the
reference frame with all fields (the ``tunneldef detect`` output contract), plus
``OUT.json`` with the summary (transform, centrelines, sections). The loaded compared cloud
also receives the scalar fields (``deformation``, ``deformation_horizontal``,
``deformation_vertical``, ``chainage``, ``danger``, ...; same-named fields replaced); its
coordinates are left as loaded. The 4 x 4 transform is printed. A drift network (the plan
shows junctions; ``--network auto``, the default) runs the network stages: every point also
gets ``branch``, the edge it is measured against.

Requires ``tunneldef`` installed in CloudCompare's Python (see docs/cloudcompare.md).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any


def _parse(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="detect_in_cloudcompare.py")
    ap.add_argument("output", nargs="?", help="result file (default <compared>_deformation.ply)")
    ap.add_argument("--threshold", type=float, help="danger threshold |deformation|, m")
    ap.add_argument("--k", type=int, help="nearest neighbours, --method knn only (paper: 3)")
    ap.add_argument(
        "--method", choices=["robust", "knn"], help="deformation estimator (default: Config's)"
    )
    ap.add_argument(
        "--network", choices=["auto", "single", "network"], default="auto",
        help="drift network (one centreline per branch) if the plan shows junctions (auto), "
        "never (single) or always (network)"
    )
    args, unknown = ap.parse_known_args(argv)
    if unknown:
        print(f"[tunneldef] ignoring arguments {unknown}")
    return args


def _default_output(desc: Any) -> str:
    folder = getattr(desc, "path", "") or "."
    if os.path.isfile(folder):  # some builds give the file path itself
        folder = os.path.dirname(folder)
    base = getattr(desc, "basename", "") or "compared"
    return os.path.join(folder, f"{base}_deformation.ply")


def run_command_line(cli: Any, argv: list[str]) -> int:
    """Command-line mode: ``cli.clouds()`` = loaded clouds, first = reference."""
    from tunneldef_cloudcompare import adapter

    from tunneldef.io import write

    args = _parse(argv)
    descs = list(cli.clouds())
    if len(descs) != 2:
        print(f"[tunneldef] load exactly two clouds with -O (reference first); got {len(descs)}")
        return 2
    overrides = {
        k: getattr(args, k) for k in ("threshold", "k", "method") if getattr(args, k) is not None
    }
    params = adapter.DetectParams.from_config(**overrides)
    try:
        adapter.check_runtime()
    except adapter.BrokenRuntimeError as exc:
        print(f"[tunneldef] error: {exc}")
        return 2
    ref_e, cmp_e = descs[0].pc, descs[1].pc
    ref, cmp = adapter.entity_to_cloud(ref_e), adapter.entity_to_cloud(cmp_e)
    print(
        f"[tunneldef] reference {ref.meta['name']} ({len(ref)} points), "
        f"compared {cmp.meta['name']} ({len(cmp)} points)"
    )

    def progress(stage: str, fraction: float) -> None:
        if fraction >= 1.0:
            print(f"[tunneldef] {stage}: done")

    from tunneldef.errors import TunnelDefError

    try:
        result = adapter.compute_detect(
            ref, cmp, adapter.config_from_params(params), progress=progress,
            network=args.network,
        )
    except TunnelDefError as exc:
        print(f"[tunneldef] error: {exc}")
        return 2
    adapter.write_scalar_fields(cmp_e, adapter.result_fields(result.cloud))
    out = args.output or _default_output(descs[1])
    write(out, result.cloud)
    if hasattr(result, "summary"):
        import json

        summary = os.path.splitext(out)[0] + ".json"
        with open(summary, "w", encoding="utf-8") as fh:
            json.dump(result.summary(), fh, indent=1)
        print(f"[tunneldef] wrote {summary}")
    print(
        "[tunneldef] compared -> reference transform:\n" + adapter.format_matrix(result.transform)
    )
    print(f"[tunneldef] wrote {out}")
    return 0


def run_gui() -> int:
    """GUI mode: the plugin's "Detect deformation" on the current selection."""
    from tunneldef_cloudcompare.plugin import detect_deformation

    return 0 if detect_deformation() is not None else 1


def main(argv: list[str] | None = None) -> int:
    import pycc

    argv = list(sys.argv[1:] if argv is None else argv)
    get_cli = getattr(pycc, "GetCmdLineInstance", None)
    cli = get_cli() if get_cli is not None else None
    if cli is not None:
        return run_command_line(cli, argv)
    return run_gui()


if __name__ == "__main__":
    # no sys.exit(): a SystemExit would end CloudCompare's embedded interpreter session
    main()
