"""Synthetic pairs too large to hold in memory, written stretch by stretch.

:func:`~tunneldef.synth.make_pair` holds both epochs and their per-point truth at once (about
14 GB for 350 m at the handheld scanner's density). :func:`write_large_pair` draws the same
kind of pair one stretch of chainage at a time and streams each epoch into a LAS/LAZ file,
so memory is bounded by a stretch whatever the length: this is how a 1 km (55 M + 55 M point)
pair is made for the scale benchmark.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.core import atomic_target
from ..progress import ProgressCallback, notify
from ..transforms import apply_transform
from .design import PairSpec, _rigid_motion
from .sampling import _sample_epoch
from .scene import _pair_scene

log = logging.getLogger(__name__)

FRESH_SCALE = 1e-4  # m: the quantum of the LAS coordinates written (0.1 mm)


def write_large_pair(
    spec: PairSpec,
    out_dir: str | Path,
    *,
    fmt: str = "laz",
    stretch: float = 50.0,
    progress: ProgressCallback | None = None,
) -> dict[str, Path]:
    """Write ``ref.<fmt>``, ``cmp.<fmt>`` and ``truth.json`` of a pair, stretch by stretch.

    Parameters
    ----------
    spec : PairSpec
        The pair, as for :func:`~tunneldef.synth.make_pair` (the scene, the deformations,
        ``cmp_shift``/``cmp_length`` and the rigid motion have the same meaning).
    out_dir : path-like
        Folder for the files (created).
    fmt : {"laz", "las"}
        Output format.
    stretch : float
        Chainage drawn at a time, m; memory grows with it, not with the tunnel's length.
    progress : ProgressCallback, optional
        Called with ``("synthetic pair", fraction)``.

    Returns
    -------
    dict
        ``{"ref", "cmp", "truth"}`` paths. ``truth.json`` holds the 4 x 4 transform taking the
        compared epoch into the reference frame, both chainage ranges and the specification;
        per-point truth is not kept (it would not fit either).

    Notes
    -----
    Each stretch is drawn with its own random stream, so the pair differs from
    :func:`~tunneldef.synth.make_pair`'s with the same seed, and the density modulation along
    the axis restarts at each stretch. The scene (section, axis, rock relief, chamber, pipes,
    coal heaps) is drawn once, so nothing else shows where two stretches meet.
    """
    import laspy

    fmt = fmt.lower().lstrip(".")
    if fmt not in ("las", "laz"):
        raise ConfigError(f"a large synthetic pair is written as LAS or LAZ, not {fmt!r}")
    if not stretch > 0:
        raise ConfigError(f"stretch must be positive, got {stretch!r}")
    seeds = np.random.SeedSequence(spec.seed).spawn(4)
    g_scene, g_motion, g_coal = (np.random.default_rng(s) for s in seeds[:3])
    scene, ref_range, cmp_range, heaps_ref, heaps_cmp = _pair_scene(spec, g_scene, g_coal)
    motion, transform, yaw, tilt_axis = _rigid_motion(
        g_motion, spec.yaw_deg, spec.tilt_deg, spec.translation
    )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"ref": out / f"ref.{fmt}", "cmp": out / f"cmp.{fmt}", "truth": out / "truth.json"}
    jobs = (("ref", ref_range, (), heaps_ref, np.eye(4)),
            ("cmp", cmp_range, spec.deformations, heaps_cmp, motion))
    total = sum(int(np.ceil((r[1] - r[0]) / stretch)) for _, r, *_ in jobs)
    done = 0
    counts = {}
    notify(progress, "synthetic pair", 0.0)
    for job, stream in zip(jobs, seeds[3].spawn(2), strict=True):
        epoch, (s0, s1), deformations, heaps, move = job
        edges = np.append(np.arange(s0, s1, stretch), s1)
        streams = stream.spawn(len(edges) - 1)
        header = laspy.LasHeader(version="1.4", point_format=6)
        header.scales = np.full(3, FRESH_SCALE)
        corner = apply_transform(move, np.array([[s0, 0.0, 0.0]]), blas=False)[0]
        header.offsets = np.floor(corner) - 1000.0  # every point within 1 km of the start
        n = 0
        with atomic_target(paths[epoch]) as tmp, laspy.open(
            tmp, mode="w", header=header, do_compress=fmt == "laz"
        ) as writer:
            for a, b, seq in zip(edges[:-1], edges[1:], streams, strict=True):
                ep = _sample_epoch(scene, float(a), float(b), np.random.default_rng(seq),
                                   deformations, heaps)
                xyz = apply_transform(move, ep["xyz"], blas=False)
                rec = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=header)
                q = np.rint((xyz - header.offsets) / header.scales).astype(np.int64)
                if np.abs(q).max(initial=0) > np.iinfo(np.int32).max:
                    raise ConfigError("a large synthetic pair must lie within 200 km of its start")
                for axis, dim in enumerate("XYZ"):
                    rec.array[dim] = q[:, axis].astype(np.int32)
                rec.array["intensity"] = ep["intensity"]
                writer.write_points(rec)
                n += len(xyz)
                done += 1
                notify(progress, "synthetic pair", done / total)
                log.debug("%s: %.0f-%.0f m, %d points", epoch, a, b, len(xyz))
        counts[epoch] = n
    truth = {
        "transform": transform.tolist(),
        "ref_range": list(ref_range),
        "cmp_range": list(cmp_range),
        "yaw_deg": float(yaw),
        "tilt_axis": np.asarray(tilt_axis).tolist(),
        "points": counts,
        "spec": dataclasses.asdict(spec),
    }
    with atomic_target(paths["truth"]) as tmp:
        tmp.write_text(json.dumps(truth, indent=1))
    log.info("large synthetic pair: %d reference, %d compared points", counts["ref"],
             counts["cmp"])
    return paths
