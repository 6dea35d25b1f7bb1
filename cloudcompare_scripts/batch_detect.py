#!/usr/bin/env python3
"""Detect deformation with the tunneldef CLI, then colour/convert the result with CloudCompare.

For CloudCompare users without the Python plugin (any CloudCompare >= 2.11 command line,
e.g. Debian's headless ``CloudCompare``): the result opens with the deformation already shown
on a diverging scale.

Usage
-----
    python batch_detect.py REF CMP -o OUT.ply [--threshold 0.05] [--limit 0.03]
                           [--cloudcompare /usr/bin/CloudCompare] [--skip-detect]
                           [-- extra arguments for `tunneldef detect`]

Steps
-----
1. ``tunneldef detect REF CMP -o OUT.ply --summary OUT.json [--threshold T] [extra]``
   (skipped with ``--skip-detect``: OUT.ply must then exist, e.g. from an earlier run).
2. CloudCompare's command line, once (headless with ``QT_QPA_PLATFORM=offscreen``)::

       CloudCompare -SILENT -AUTO_SAVE OFF -O -GLOBAL_SHIFT AUTO OUT.ply
           -SET_ACTIVE_SF <index of deformation> -SF_COLOR_SCALE OUT_scale.xml
           -C_EXPORT_FMT BIN -SAVE_CLOUDS FILE OUT.bin
           -SF_CONVERT_TO_RGB FALSE
           -C_EXPORT_FMT PLY -PLY_EXPORT_FMT BINARY_LE -SAVE_CLOUDS FILE OUT_rgb.ply
           -C_EXPORT_FMT ASC -PREC 6 -ADD_HEADER -SAVE_CLOUDS FILE OUT.asc

   giving ``OUT.bin`` (CloudCompare's own format: all fields, ``deformation`` active on a
   Red>White>Blue scale saturated at +-limit), ``OUT_rgb.ply`` (the same colours baked into
   RGB, for any viewer) and ``OUT.asc`` (text, header line with the field names).

Notes (verified with CloudCompare 2.11.3): ``-SET_ACTIVE_SF`` takes an index, not a name; the
index is the position of the field among the PLY properties other than x/y/z, colours and
normals (CloudCompare loads every such property as a scalar field, ``scalar_`` prefix
removed). ``-SF_COLOR_SCALE`` reads a colour-scale XML file; an *absolute* scale from -limit
to +limit gives a diverging scale centred on 0 with symmetric saturation. ``-GLOBAL_SHIFT
AUTO`` keeps survey coordinates exact (without it CloudCompare stores them in float32).
Red = surface moved into the tunnel (negative: roof sag, wall bulge, floor heave), white = 0,
blue = outward: the project's convention (report figures, matplotlib ``RdBu``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

from tunneldef_cloudcompare.colours import color_scale_xml, symmetric_limit

#: PLY vertex properties CloudCompare does not load as scalar fields.
_STANDARD_PROPERTIES = {
    "x", "y", "z", "red", "green", "blue", "alpha", "r", "g", "b",
    "diffuse_red", "diffuse_green", "diffuse_blue", "nx", "ny", "nz",
}  # fmt: skip


def scalar_field_index(ply_path: str | os.PathLike, name: str) -> int:
    """Index CloudCompare gives to field ``name`` (``scalar_<name>`` or ``<name>``) of a PLY.

    Raises
    ------
    KeyError
        If the file has no such vertex property.
    """
    props = [p for p in _ply_header(ply_path) if p.lower() not in _STANDARD_PROPERTIES]
    for i, p in enumerate(props):
        if p in (name, f"scalar_{name}"):
            return i
    raise KeyError(f"{ply_path} has no vertex property {name!r} (has {props})")


def _ply_header(path: str | os.PathLike) -> list[str]:
    """Names of the vertex properties, read from the PLY header only."""
    names: list[str] = []
    element = None
    with open(path, "rb") as fh:
        for raw in fh:
            line = raw.decode("ascii", errors="replace").strip()
            if line.startswith("element"):
                element = line.split()[1]
            elif line.startswith("property") and element == "vertex":
                names.append(line.split()[-1])
            elif line == "end_header":
                break
    return names


#: Identity of the absolute scale written for the command line (the plugin's relative scale
#: has its own, :data:`tunneldef_cloudcompare.colours.SCALE_UUID`).
ABSOLUTE_SCALE_UUID = "{5b7c2f4e-1d0a-4f3e-9a61-7e2d8c3b9f01}"


def run_detect(
    ref: str,
    cmp: str,
    out: Path,
    *,
    threshold: float | None,
    extra: list[str],
    timeout: float | None = None,
) -> None:
    """Step 1: ``tunneldef detect`` (the console script, or ``python -m tunneldef.cli``)."""
    exe = shutil.which("tunneldef")
    cmd = [exe] if exe else [sys.executable, "-m", "tunneldef.cli"]
    cmd += ["detect", ref, cmp, "-o", str(out), "--summary", str(out.with_suffix(".json"))]
    if threshold is not None:
        cmd += ["--threshold", str(threshold)]
    cmd += extra
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, timeout=timeout)


def cloudcompare_command(cc: str, ply: Path, *, sf_index: int, scale_xml: Path) -> list[str]:
    """Step 2's CloudCompare command line (outputs next to ``ply``)."""
    stem = ply.with_suffix("")
    return [
        cc, "-SILENT", "-AUTO_SAVE", "OFF",
        "-O", "-GLOBAL_SHIFT", "AUTO", str(ply),
        "-SET_ACTIVE_SF", str(sf_index),
        "-SF_COLOR_SCALE", str(scale_xml),
        "-C_EXPORT_FMT", "BIN", "-SAVE_CLOUDS", "FILE", f"{stem}.bin",
        "-SF_CONVERT_TO_RGB", "FALSE",
        "-C_EXPORT_FMT", "PLY", "-PLY_EXPORT_FMT", "BINARY_LE",
        "-SAVE_CLOUDS", "FILE", f"{stem}_rgb.ply",
        "-C_EXPORT_FMT", "ASC", "-PREC", "6", "-ADD_HEADER",
        "-SAVE_CLOUDS", "FILE", f"{stem}.asc",
    ]  # fmt: skip


def run_cloudcompare(
    cc: str,
    ply: Path,
    *,
    threshold: float = 0.0,
    limit: float | None = None,
    timeout: float | None = 600,
) -> dict[str, Path]:
    """Step 2: colour ``deformation`` and export BIN / RGB PLY / ASC with CloudCompare.

    Returns the paths written: ``{"bin", "rgb_ply", "asc", "scale"}``.
    """
    if limit is None:
        from tunneldef.io import read

        limit = symmetric_limit(read(ply).fields["deformation"], threshold=threshold)
    stem = ply.with_suffix("")
    scale = Path(f"{stem}_scale.xml")
    xml = color_scale_xml(name="tunneldef deformation", uuid=ABSOLUTE_SCALE_UUID, limit=limit)
    scale.write_text(xml, encoding="utf-8")
    cmd = cloudcompare_command(
        cc, ply, sf_index=scalar_field_index(ply, "deformation"), scale_xml=scale
    )
    env = dict(os.environ)
    env.setdefault("QT_QPA_PLATFORM", "offscreen")
    print("+", " ".join(cmd), flush=True)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    outputs = {
        "bin": Path(f"{stem}.bin"),
        "rgb_ply": Path(f"{stem}_rgb.ply"),
        "asc": Path(f"{stem}.asc"),
        "scale": scale,
    }
    missing = [str(p) for p in outputs.values() if not p.is_file()]
    if proc.returncode != 0 or missing:
        raise RuntimeError(
            f"CloudCompare failed (exit {proc.returncode}; missing {missing}):\n"
            + proc.stdout[-2000:]
            + proc.stderr[-2000:]
        )
    print(f"colour scale: red = into the tunnel, blue = outward, saturated at +-{limit:.3f} m")
    return outputs


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, extra = argv[:cut], argv[cut + 1 :]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("reference", help="reference epoch (earlier scan)")
    ap.add_argument("compared", help="compared epoch (later scan)")
    ap.add_argument("-o", "--output", required=True, help="output PLY of tunneldef detect")
    ap.add_argument("--threshold", type=float, help="danger threshold, m (tunneldef default)")
    ap.add_argument("--limit", type=float, help="colour saturation, m (default: 98th pct)")
    ap.add_argument(
        "--cloudcompare",
        default=shutil.which("CloudCompare") or "CloudCompare",
        help="CloudCompare executable",
    )
    ap.add_argument("--skip-detect", action="store_true", help="OUT.ply exists: only colour it")
    args = ap.parse_args(argv)
    out = Path(args.output)
    if out.suffix.lower() != ".ply":
        ap.error("the output must be a .ply file (CloudCompare 2.11 has no LAS support here)")
    if not args.skip_detect:
        run_detect(args.reference, args.compared, out, threshold=args.threshold, extra=extra)
    elif not out.is_file():
        ap.error(f"--skip-detect: {out} does not exist")
    written = run_cloudcompare(
        args.cloudcompare, out, threshold=args.threshold or 0.0, limit=args.limit
    )
    for key, path in written.items():
        print(f"{key}: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
