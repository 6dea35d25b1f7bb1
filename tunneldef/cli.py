"""The ``tunneldef`` command.

Subcommands: ``info``, ``synth``, ``centerline``, ``register``, ``detect``, ``demo``, ``config``.
User mistakes (missing file, bad format, non-overlapping epochs...) print one line to stderr and
exit with code 2; ``--quiet`` silences progress. Heavy imports happen inside the commands.

One idea at this length: the command line, one subcommand per job, its argument checks and its
one-line errors.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from . import __version__
from .errors import ConfigError, TunnelDefError
from .progress import StageLogger
from .textfiles import to_json, write_csv, write_text_atomic

log = logging.getLogger("tunneldef")

EXIT_USER_ERROR = 2


# --------------------------------------------------------------------------- helpers


def _setup_logging(quiet: bool, verbose: bool) -> tuple[logging.Handler, int, bool]:
    """Send tunneldef's log to stderr; returns what :func:`_restore_logging` needs."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(message)s"))
    root = logging.getLogger("tunneldef")
    saved = (handler, root.level, root.propagate)
    root.addHandler(handler)
    root.setLevel(logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO)
    root.propagate = False
    return saved


def _restore_logging(saved: tuple[logging.Handler, int, bool]) -> None:
    handler, level, propagate = saved
    root = logging.getLogger("tunneldef")
    root.removeHandler(handler)
    root.setLevel(level)
    root.propagate = propagate


def _existing_file(path: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise TunnelDefError(f"input file not found: {p}")
    if p.is_dir():
        raise TunnelDefError(f"input is a folder, not a point cloud file: {p}")
    return p


def _check_output(out: Path, inputs: Sequence[Path]) -> None:
    """Refuse to overwrite an input and to write into a missing folder."""
    for src in inputs:
        if out.resolve() == src.resolve():
            raise TunnelDefError(
                f"output {out} is the same file as input {src}; choose another name"
            )
    if not out.parent.resolve().is_dir():
        raise TunnelDefError(f"output folder does not exist: {out.parent}")


def _load_config(args: argparse.Namespace):  # noqa: ANN202
    from .config import load_config

    return load_config(getattr(args, "config", None))


# --------------------------------------------------------------------------- commands


def cmd_info(args: argparse.Namespace) -> int:
    import numpy as np

    from .errors import NotATunnelError
    from .frame import principal_frame
    from .io import read

    cloud = read(_existing_file(args.file), strict=args.strict)
    lo, hi = cloud.bounds
    out = [
        f"file:       {args.file}",
        f"points:     {len(cloud):,}",
        f"bounds min: {lo[0]:.4f} {lo[1]:.4f} {lo[2]:.4f}",
        f"bounds max: {hi[0]:.4f} {hi[1]:.4f} {hi[2]:.4f}",
        f"extent:     {hi[0] - lo[0]:.3f} x {hi[1] - lo[1]:.3f} x {hi[2] - lo[2]:.3f} m",
    ]
    if cloud.meta.get("dropped_nonfinite"):
        out.append(f"dropped:    {cloud.meta['dropped_nonfinite']} points with NaN/inf coordinates")
    out.append(f"attributes: {len(cloud.fields)}")
    for name, values in cloud.fields.items():
        v = np.asarray(values)
        rng = f"{v.min():.6g} .. {v.max():.6g}" if v.size and v.dtype.kind in "biuf" else ""
        out.append(f"  {name:<24s} {str(v.dtype):<8s} {rng}")
    try:
        frame = principal_frame(cloud.xyz)
        local = frame.to_local(cloud.xyz)
        p = np.percentile(local, [0.5, 99.5], axis=0)
        azimuth = np.degrees(np.arctan2(frame.axes[0, 1], frame.axes[0, 0])) % 360.0
        out += [
            "tunnel axis (PCA guess):",
            f"  direction:  azimuth {azimuth:.2f} deg from +x (counter-clockwise), horizontal",
            f"  length:     {p[1, 0] - p[0, 0]:.2f} m (0.5-99.5 % extent along the axis)",
            f"  across:     {p[1, 1] - p[0, 1]:.2f} m wide x {p[1, 2] - p[0, 2]:.2f} m high "
            "(outer extent, includes chambers and clutter)",
        ]
    except NotATunnelError as exc:
        out.append(f"tunnel axis: none ({exc})")
    print("\n".join(out))
    return 0


#: Peak memory of :func:`tunneldef.synth.make_pair` and its writing per point of one epoch
#: (14.7 GB for 19.4 M points per epoch, measured at 350 m), bytes.
_SYNTH_BYTES_PER_POINT = 760


def _available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux's ``MemAvailable``: free memory
    and the page cache it may reclaim); None where the system does not say."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def cmd_synth(args: argparse.Namespace) -> int:
    from . import synth

    out_dir = Path(args.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    deformations = []
    if args.sag > 0:
        deformations.append(synth.DeformationSpec(kind="roof_sag", chainage=args.length / 2,
                                                  amplitude=args.sag))
    spec = synth.PairSpec(
        tunnel=synth.TunnelSpec(
            length=args.length,
            radius=args.radius,
            section=synth.SectionSpec(kind=args.section),
            density=args.density,
            noise_sigma=args.noise,
            chamber=args.chamber,
            equipment=args.equipment,
            conveyor=args.conveyor,
        ),
        deformations=tuple(deformations),
        seed=args.seed,
    )
    per_epoch = args.density * synth.section_outline(spec.tunnel.section).perimeter * args.length
    if args.stream:
        from .synth.large import write_large_pair

        log.info("generating a synthetic pair stretch by stretch (%s section, %.0f m)...",
                 args.section, args.length)
        paths = write_large_pair(spec, out_dir, fmt=args.format)
        for name, p in paths.items():
            log.info("wrote %-6s %s", name, p)
        return 0
    free = _available_memory()
    if free is not None and per_epoch * _SYNTH_BYTES_PER_POINT > free:
        raise ConfigError(
            f"a pair of about {per_epoch / 1e6:.0f} M points per epoch and its truth need "
            f"about {per_epoch * _SYNTH_BYTES_PER_POINT / 1e9:.0f} GB, more than the "
            f"{free / 1e9:.0f} GB available; add --stream (LAS/LAZ, written stretch by stretch)")
    log.info("generating a synthetic pair (%s section, %.0f m)...", args.section, args.length)
    pair = synth.make_pair(spec)
    paths = synth.write_pair(pair, out_dir, fmt=args.format)
    for name, p in paths.items():
        log.info("wrote %-6s %s", name, p)
    log.info("reference: %s points; compared: %s points", f"{len(pair.ref):,}",
             f"{len(pair.cmp):,}")
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    from .config import dump_config

    print(dump_config(_load_config(args)), end="")
    return 0


def cmd_centerline(args: argparse.Namespace) -> int:
    from .centerline import extract_centerline
    from .io import read

    src = _existing_file(args.input)
    out = Path(args.output)
    _check_output(out, [src])
    config = _load_config(args)
    cloud = read(src, strict=args.strict)
    progress = None if args.quiet else StageLogger(log)
    if _as_network(args, [cloud], config):
        return _centerline_network(cloud, config, out, progress)
    result = extract_centerline(
        cloud.xyz, slicing=config.slicing, settings=config.centerline, progress=progress
    )
    _write_centerline(result, out)
    ok = sum(1 for r in result.table() if r.get("ok", True))
    log.info("centreline: %.2f m, %d slices (%d usable) -> %s", result.centerline.length,
             len(result.slices), ok, out)
    if args.plots:
        from .report.centerline_plots import plot_centerline_diagnostics

        plot_dir = Path(args.plots)
        plot_dir.mkdir(parents=True, exist_ok=True)
        for p in plot_centerline_diagnostics(result, cloud.xyz, plot_dir):
            log.info("figure: %s", p)
    return 0


def _write_centerline(result: Any, out: Path) -> None:
    """CSV: one row per slice (chainage, centre, width, height, quality); PLY/LAS: curve samples."""
    import numpy as np

    from .cloud import Cloud
    from .io import write

    suffix = out.suffix.lower()
    if suffix == ".csv":
        rows = result.table()
        if not rows:
            raise TunnelDefError("no slice produced a centre; nothing to write")
        write_csv(out, rows)
    elif suffix == ".json":
        write_text_atomic(out, to_json({"centerline": result.centerline.to_dict(),
                                           "slices": result.table()}))
    else:
        cl = result.centerline
        cloud = Cloud(cl.points, {"chainage": cl.chainage.astype(np.float32)})
        write(out, cloud)


def _centerline_network(cloud: Any, config: Any, out: Path, progress: Any) -> int:
    """``tunneldef centerline --network``: the graph of a drift network.

    JSON: nodes (junctions) and edges (each with its curve) plus the slices; CSV: one row per
    slice with its ``edge``; PLY/LAS/LAZ: the curves' samples with ``edge`` and ``chainage``.
    """
    import numpy as np

    from .centerline.network import extract_network
    from .cloud import Cloud
    from .io import write

    result = extract_network(cloud.xyz, slicing=config.slicing, settings=config.centerline,
                             network=config.network, progress=progress)
    net = result.network
    suffix = out.suffix.lower()
    if suffix == ".csv":
        write_csv(out, result.table())
    elif suffix == ".json":
        write_text_atomic(out, to_json({**net.to_dict(), "slices": result.table()}))
    else:
        pts = np.concatenate([e.centerline.points for e in net.edges])
        fields = {
            "edge": np.concatenate([np.full(len(e.centerline.points), e.id, dtype=np.uint16)
                                    for e in net.edges]),
            "chainage": np.concatenate([e.centerline.chainage for e in net.edges]
                                       ).astype(np.float32),
            "junction": np.concatenate([e.in_zone(e.centerline.chainage) for e in net.edges]
                                       ).astype(np.uint8),
        }
        write(out, Cloud(pts, fields))
    for e in net.edges:
        log.info("edge %d: %.2f m, %d slices (%d usable), junctions %s", e.id, e.length,
                 len(e.slices), sum(r.ok for r in e.slices), [n for n in e.nodes if n >= 0])
    corners = len(net.meta.get("corners", []))
    log.info("network: %d edges, %d junctions%s, %.1f m -> %s", len(net.edges),
             len(net.junctions), f" ({corners} of them corners)" if corners else "",
             net.length, out)
    return 0


def cmd_register(args: argparse.Namespace) -> int:
    from .io import read, write
    from .pipeline import register_epochs

    ref_path, cmp_path = _existing_file(args.reference), _existing_file(args.compared)
    out = Path(args.output)
    _check_output(out, [ref_path, cmp_path])
    if args.transform:
        _check_output(Path(args.transform), [ref_path, cmp_path])
    config = _load_config(args)
    if args.method:
        config = config.replace(registration={"method": args.method})
    ref, cmp = read(ref_path, strict=args.strict), read(cmp_path, strict=args.strict)
    progress = None if args.quiet else StageLogger(log)
    reg = register_epochs(ref, cmp, config, progress=progress).registration
    moved = cmp.transformed(reg.transform)
    write(out, moved)
    if args.transform:
        write_text_atomic(Path(args.transform), to_json(reg.to_dict()))
    import numpy as np

    with np.printoptions(precision=6, suppress=True):
        log.info("transform (compared -> reference):\n%s", reg.transform)
    log.info("fitness (RMSE) %.4f m; axial uncertainty %.3f m; wrote %s", reg.fitness,
             reg.axial_uncertainty, out)
    return 0


def _add_kind(p: argparse.ArgumentParser, network_help: str, single_help: str) -> None:
    """``--network`` / ``--single``: which stages, when the plan should not decide."""
    kind = p.add_mutually_exclusive_group()
    kind.add_argument("--network", action="store_true", help=network_help)
    kind.add_argument("--single", action="store_true", help=single_help)


def _as_network(args: argparse.Namespace, clouds: list[Any], config: Any) -> bool:
    """``--network``, ``--single``, or else whether the plan of any epoch shows a junction
    or a corner."""
    from .pipeline import is_network

    if args.network or args.single:
        return bool(args.network)
    return is_network(clouds, config)


def cmd_detect(args: argparse.Namespace) -> int:
    from .cloud import Cloud
    from .engine import open_engine
    from .io.stream import read_points, write_with_fields
    from .pipeline import detect

    ref_path, cmp_path = _existing_file(args.reference), _existing_file(args.compared)
    if ref_path.resolve() == cmp_path.resolve():
        raise TunnelDefError("reference and compared are the same file; give two epochs")
    out = Path(args.output)
    extra = [Path(p) for p in (args.summary, args.sections) if p]
    for p in [out, *extra]:
        _check_output(p, [ref_path, cmp_path])
    config = _apply_overrides(_load_config(args), args)
    tile_dir = Path(args.tile_dir) if args.tile_dir else out.parent
    if not tile_dir.is_dir():
        raise TunnelDefError(f"tile folder does not exist: {tile_dir}; create it first")
    ref = Cloud(read_points(ref_path, strict=args.strict)[0])
    cmp_xyz, keep = read_points(cmp_path, strict=args.strict)
    cmp = Cloud(cmp_xyz)
    log.info("reference %s: %s points; compared %s: %s points", ref_path.name, f"{len(ref):,}",
             cmp_path.name, f"{len(cmp):,}")
    progress = None if args.quiet else StageLogger(log)
    network = _as_network(args, [ref, cmp], config)
    with open_engine(scheduler=args.scheduler, workers=args.workers,
                     memory_gb=args.memory) as engine:
        tiles = {"tile_length": args.tile_length, "memory_gb": engine.tile_memory_gb,
                 "engine": engine, "workdir": tile_dir}
        if args.no_drift_correction:
            config = config.replace(network={"drift_correction": False})
        if network:
            from .pipeline import detect_network

            result = detect_network(ref, cmp, config, progress=progress, tiles=tiles)
        else:
            result = detect(ref, cmp, config, progress=progress, tiles=tiles,
                            overwrite_compared=True)
    write_with_fields(out, cmp_path, result.cloud.xyz, result.cloud.fields, keep=keep,
                      strict=args.strict, note=result.cloud.meta.get("note"))
    summary = result.summary()
    summary["inputs"] = {"reference": str(ref_path), "compared": str(cmp_path), "output": str(out)}
    if args.summary:
        write_text_atomic(Path(args.summary), to_json(summary))
    if args.sections:
        from .deformation.sections import write_sections_csv

        write_sections_csv(result.sections, Path(args.sections))
    _log_result(summary)
    log.info("wrote %s", ", ".join(str(p) for p in [out, *extra]))
    return 0


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _apply_overrides(config: Any, args: argparse.Namespace) -> Any:
    danger: dict[str, Any] = {}
    deformation: dict[str, Any] = {}
    if getattr(args, "threshold", None) is not None:
        danger["threshold"] = float(args.threshold)
    if getattr(args, "rule", None):
        danger["rule"] = args.rule
    if getattr(args, "method", None):
        deformation["method"] = args.method
    if getattr(args, "k", None) is not None:
        deformation["k"] = int(args.k)
    changes = {k: v for k, v in (("danger", danger), ("deformation", deformation)) if v}
    if getattr(args, "registration", None):
        changes["registration"] = {"method": args.registration}
    if getattr(args, "force", False):
        changes["quality"] = {"enforce": False}
    return config.replace(**changes) if changes else config


def _log_result(summary: dict[str, Any]) -> None:
    stats = summary.get("statistics", {})
    if stats:
        log.info(
            "shell deformation: mean %+.1f mm, mean |d| %.1f mm, p95 |d| %.1f mm over %s points",
            1e3 * stats.get("mean", float("nan")), 1e3 * stats.get("mean_abs", float("nan")),
            1e3 * stats.get("p95_abs", float("nan")), f"{stats.get('count', 0):,}",
        )
    zones = summary.get("danger_zones", [])
    thr = summary.get("danger_threshold_m")
    if thr is not None:
        log.info("danger threshold %.1f mm: %d zone(s)", 1e3 * thr, len(zones))
    for z in zones[:10]:
        log.info("  chainage %7.2f-%7.2f m  %-5s peak %+.1f mm at %.2f m (%d points)",
                 z["start"], z["end"], z.get("surface", ""), 1e3 * z["peak"],
                 z.get("peak_chainage", float("nan")), z.get("n_points", 0))
    if len(zones) > 10:
        log.info("  ... %d more in the summary", len(zones) - 10)


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    run_demo(Path(args.out_dir), seed=args.seed, quick=args.quick,
             progress=None if args.quiet else StageLogger(log))
    return 0


# --------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                        help="only warnings and errors")
    common.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                        help="debug messages")
    reading = argparse.ArgumentParser(add_help=False)
    reading.add_argument("--strict", action="store_true",
                         help="refuse inputs with NaN/inf coordinates instead of dropping them")
    configured = argparse.ArgumentParser(add_help=False)
    configured.add_argument("--config", metavar="TOML",
                            help="parameter file (see `tunneldef config --dump`)")

    parser = argparse.ArgumentParser(
        prog="tunneldef",
        description="Tunnel deformation from two epochs of mobile laser scans "
        "(centreline registration, per-point and per-section deformation).",
        parents=[common],
    )
    parser.add_argument("--version", action="version", version=f"tunneldef {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("info", parents=[common, reading],
                       help="points, bounds, attributes and a guess of the tunnel axis",
                       description="Print points, bounds, attributes and a guess of the tunnel "
                       "axis and length of a cloud (PLY, LAS, LAZ, PCD, XYZ/TXT).")
    p.add_argument("file", help="point cloud file")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("synth", parents=[common],
                       help="write a synthetic epoch pair with ground truth",
                       description="Write a synthetic reference/compared pair (ref.*, cmp.*) "
                       "and its ground truth (truth.npz) into OUT_DIR.")
    p.add_argument("out_dir", help="output folder (created if missing)")
    p.add_argument("--length", type=float, default=30.0, help="tunnel length, m (default 30)")
    p.add_argument("--radius", type=float, default=None,
                   help="horizontal radius of a curved tunnel, m (default: straight)")
    p.add_argument("--section", choices=["rectangle", "arch", "trapezoid"], default="rectangle",
                   help="section shape (default rectangle, 5.8 x 2.86 m as in the paper)")
    p.add_argument("--density", type=float, default=400.0,
                   help="points per square metre of shell (default 400)")
    p.add_argument("--noise", type=float, default=0.015,
                   help="Gaussian noise sigma, m (default 0.015: the scanner's +-3 cm as 2 sigma)")
    p.add_argument("--sag", type=float, default=0.03,
                   help="roof sag amplitude at mid-length in the compared epoch, m (default 0.03)")
    p.add_argument("--chamber", action="store_true", help="add a side chamber")
    p.add_argument("--equipment", action="store_true", help="add pipes and cables on the walls")
    p.add_argument("--conveyor", action="store_true", help="add a conveyor with a coal load")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--format", choices=["ply", "las", "laz"], default="ply",
                   help="file format (default ply)")
    p.add_argument("--stream", action="store_true",
                   help="draw the pair stretch by stretch into LAS/LAZ, memory bounded whatever "
                   "the length (a 1 km survey); truth.json then holds the transform only")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("centerline", parents=[common, reading, configured],
                       help="extract the tunnel centreline (paper §3.1)",
                       description="Extract the centreline of one epoch: slices, roof/floor "
                       "lines by 1-D Gaussian KDE peaks, wall lines by 2-D linear-kernel density "
                       "+ Canny + Hough, NURBS fit. CSV output holds one row per slice; "
                       "PLY/LAS/LAZ output holds the curve's samples with a chainage field.")
    p.add_argument("input", help="point cloud file")
    p.add_argument("-o", "--output", required=True,
                   help="centerline.csv (slices), .json, or .ply/.las/.laz (curve points)")
    p.add_argument("--plots", metavar="DIR", help="write diagnostic figures into DIR")
    _add_kind(p, "a drift network: write the graph of edges and junctions (JSON: nodes and "
              "edges; CSV: slices with their edge; PLY/LAS/LAZ: curve points with an edge "
              "field); default: when the plan shows a junction or a corner",
              "one drift, even if the plan shows junctions")
    p.set_defaults(func=cmd_centerline)

    p = sub.add_parser("register", parents=[common, reading, configured],
                       help="register the compared epoch onto the reference (paper §3.2)",
                       description="Register CMP onto REF by their centrelines (default) or a "
                       "baseline (ICP, GICP, NDT) and write CMP moved into REF's frame.")
    p.add_argument("reference", help="reference epoch (earlier scan)")
    p.add_argument("compared", help="compared epoch (later scan)")
    p.add_argument("-o", "--output", required=True, help="registered copy of the compared epoch")
    p.add_argument("--transform", metavar="JSON", help="write the 4x4 transform and diagnostics")
    p.add_argument("--method", choices=["centerline", "icp_point", "icp_plane", "gicp", "ndt"],
                   help="registration method (default: centerline)")
    p.set_defaults(func=cmd_register)

    p = sub.add_parser("detect", parents=[common, reading, configured],
                       help="the main job: per-point and per-section deformation",
                       description="Register CMP onto REF and compute deformation. OUT holds "
                       "CMP's points in CMP's order with its attributes, coordinates in REF's "
                       "frame, and fields deformation, deformation_horizontal, "
                       "deformation_vertical, chainage (float32, m) and danger (uint8). "
                       "Negative deformation = the surface moved into the tunnel.")
    p.add_argument("reference", help="reference epoch (earlier scan)")
    p.add_argument("compared", help="compared epoch (later scan)")
    p.add_argument("-o", "--output", required=True, help="output cloud (.ply, .las, .laz, ...)")
    p.add_argument("--summary", metavar="JSON", help="write transform, centrelines, statistics")
    p.add_argument("--sections", metavar="CSV", help="write per-section statistics")
    p.add_argument("--threshold", type=float, metavar="M",
                   help="danger threshold on |deformation|, m")
    p.add_argument("--rule", choices=["absolute", "mean"],
                   help="danger rule: absolute threshold or the paper's mean |deformation|")
    p.add_argument("--method", choices=["knn", "robust"],
                   help="deformation estimator: the paper's KNN centroid or the robust one")
    p.add_argument("--k", type=int, help="neighbours of the KNN centroid (paper: 3)")
    p.add_argument("--registration",
                   choices=["centerline", "icp_point", "icp_plane", "gicp", "ndt"],
                   help="registration method (default: centerline)")
    _add_kind(p, "the epochs are drift networks: measure every point against its branch "
              "(adds the uint16 field 'branch'; sections and danger zones per branch); "
              "default: when either epoch's plan shows a junction or a corner",
              "one drift: refuse epochs whose plan shows junctions or corners")
    p.add_argument("--no-drift-correction", action="store_true",
                   help="no piecewise-rigid SLAM-drift correction along the reference "
                   "centreline (or each edge of a network) after the rigid registration")
    p.add_argument("--force", action="store_true",
                   help="write the result even if a quality check fails; the outputs (summary, "
                   "LAS/PLY header) are then marked UNVERIFIED")
    p.add_argument("--tile-length", type=_positive_float, metavar="M",
                   help="length of a chainage tile, m (default: from --memory)")
    p.add_argument("--memory", type=_positive_float, default=1.5, metavar="GB",
                   help="working memory of the tiles, GB (default 1.5): on this machine for "
                   "the tiles at once, on a cluster per worker; chooses the tile length")
    p.add_argument("--workers", type=int, metavar="N",
                   help="start a local Dask cluster of N worker processes (default: Dask's "
                   "threaded scheduler, as many tiles at once as --memory holds at 1.5 GB "
                   "each, at most one per core)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the tiles on an existing Dask cluster (tcp://host:port); its "
                   "workers must see --tile-dir")
    p.add_argument("--tile-dir", metavar="DIR",
                   help="folder for the tiles' temporary files, visible to every worker "
                   "(default: the output's folder)")
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser("demo", parents=[common],
                       help="run detect on a built-in synthetic pair and write figures",
                       description="Make a synthetic pair with a known roof sag, wall bulge "
                       "and floor heave, run detect, and write the outputs and PNG figures "
                       "into DIR, printing measured versus true deformation.")
    p.add_argument("out_dir", nargs="?", default="tunneldef_demo",
                   help="output folder (default ./tunneldef_demo)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--quick", action="store_true", help="a smaller pair (for a fast check)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("config", parents=[common, configured],
                       help="print every parameter with its default and source",
                       description="Print the configuration as TOML, every value with the "
                       "source of its default (the paper's section or ours).")
    p.add_argument("--dump", action="store_true", help="print the configuration (default action)")
    p.set_defaults(func=cmd_config)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``tunneldef`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.quiet = getattr(args, "quiet", False)
    args.verbose = getattr(args, "verbose", False)
    saved = _setup_logging(args.quiet, args.verbose)
    from .engine import limit_malloc_arenas

    limit_malloc_arenas()
    try:
        return int(args.func(args) or 0)
    except TunnelDefError as exc:
        print(f"tunneldef: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except PermissionError as exc:
        print(f"tunneldef: error: permission denied: {exc.filename}", file=sys.stderr)
        return EXIT_USER_ERROR
    except IsADirectoryError as exc:
        print(f"tunneldef: error: expected a file, got a folder: {exc.filename}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("tunneldef: interrupted", file=sys.stderr)
        return 130
    finally:
        _restore_logging(saved)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
