"""The three jobs, each in two steps: compute (worker thread: the core on numpy arrays, never
an entity) and apply (main thread: scalar fields, colours, new entities).

An epoch whose plan shows junctions (cross-cuts, crossings) or turns a corner (the core's
:func:`~tunneldef.centerline.skeleton.plan_topology`) is a drift network: detection and
extraction then run the core's network stages and draw one polyline per edge."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .colours import (
    SCALE_BLUE_IN,
    SCALE_RED_IN,
    red_white_blue_scale,
    show_diverging,
    symmetric_limit,
)
from .entities import CENTERLINE_COLOURS, make_point_cloud, make_polyline, move_entity
from .fields import write_scalar_fields
from .params import NETWORK_CHOICES
from .runtime import entity_name
from .text import format_matrix, format_slice_table

__all__ = [
    "NETWORK_CHOICES",
    "is_network",
    "DEFORMATION_FIELDS",
    "OPTIONAL_FIELDS",
    "DetectEntities",
    "compute_detect",
    "result_fields",
    "apply_detect",
    "compute_centerline",
    "apply_centerline",
    "compute_register",
    "apply_register",
]

#: Optional fields written too when the estimator provides them (significance, classes;
#: ``branch``: the network edge a point is measured against).
OPTIONAL_FIELDS = ("significant", "lod95", "shell", "surface", "class", "branch")


def is_network(clouds: Any, config: Any = None) -> bool:
    """True if any of ``clouds`` (core :class:`~tunneldef.cloud.Cloud`) is a drift network:
    the core's :func:`tunneldef.pipeline.is_network`."""
    from tunneldef.pipeline import is_network as core_is_network

    return core_is_network(clouds, config)


def _wants_network(network: str, clouds: Any, config: Any) -> bool:
    if network not in NETWORK_CHOICES:
        raise ValueError(f"network must be one of {NETWORK_CHOICES}, not {network!r}")
    return network == "network" or (network == "auto" and is_network(clouds, config))


#: Fields every detection writes onto the compared cloud: the core's output contract,
#: ``tunneldef.pipeline.OUTPUT_FIELDS`` (kept here so that importing the plugin stays light).
DEFORMATION_FIELDS = (
    "deformation",
    "deformation_horizontal",
    "deformation_vertical",
    "chainage",
    "danger",
)


def compute_detect(
    ref: Any, cmp: Any, config: Any = None, *, progress: Any = None, memory_gb: float = 1.5,
    network: str = "auto",
) -> Any:
    """Worker-thread part of "Detect deformation": :func:`tunneldef.pipeline.detect`, or
    :func:`tunneldef.pipeline.detect_network` for a drift network (``network``: one of
    :data:`NETWORK_CHOICES`).

    A single drift's deformation stage runs in chainage tiles on Dask's local threaded
    scheduler, as ``tunneldef detect`` does, so its working memory is bounded by
    ``memory_gb`` (GB) and not by the survey; the tiles' temporary files go to the system's
    temporary folder.
    """
    import tempfile

    from tunneldef.engine import open_engine
    from tunneldef.pipeline import detect, detect_network

    if _wants_network(network, (ref, cmp), config):
        return detect_network(ref, cmp, config, progress=progress)

    with open_engine(memory_gb=memory_gb) as engine:
        tiles = {"memory_gb": engine.tile_memory_gb, "engine": engine,
                 "workdir": tempfile.gettempdir()}
        return detect(ref, cmp, config, progress=progress, tiles=tiles)


def result_fields(cloud: Any) -> dict[str, np.ndarray]:
    """The fields of a detection result to write onto the compared cloud."""
    missing = [f for f in DEFORMATION_FIELDS if f not in cloud.fields]
    if missing:
        raise ValueError(f"the detection result lacks the fields {missing}")
    names = list(DEFORMATION_FIELDS) + [f for f in OPTIONAL_FIELDS if f in cloud.fields]
    return {name: np.asarray(cloud.fields[name]) for name in names}


@dataclass
class DetectEntities:
    """Entities the "Detect deformation" action created (to add to the DB tree): the
    registered copy and the centrelines as polylines, one per edge of each epoch (one each
    for a single drift)."""

    registered: Any
    ref_lines: list[Any] = field(default_factory=list)
    cmp_lines: list[Any] = field(default_factory=list)
    keep_alive: list[Any] = field(default_factory=list)
    limit: float = 0.0
    colours: str = SCALE_RED_IN

    @property
    def ref_centerline(self) -> Any:
        """The reference centreline's (first) polyline."""
        return self.ref_lines[0] if self.ref_lines else None

    @property
    def cmp_centerline(self) -> Any:
        """The compared centreline's (first) polyline."""
        return self.cmp_lines[0] if self.cmp_lines else None

    def legend(self) -> str:
        """One line saying what the colours mean, for the console."""
        ends = {
            SCALE_RED_IN: "red = into the tunnel, white = 0, blue = outward",
            SCALE_BLUE_IN: "blue = into the tunnel, white = 0, red = outward (built-in scale; "
            "this runtime cannot load the Red>White>Blue one)",
        }.get(self.colours, "CloudCompare's default scale (no diverging scale available)")
        return f"colour scale: {ends}, saturated at ±{self.limit * 1000:.0f} mm"

    def new_entities(self) -> list[Any]:
        return [self.registered, *self.ref_lines, *self.cmp_lines]


def apply_detect(
    ref_entity: Any,
    cmp_entity: Any,
    result: Any,
    *,
    threshold: float,
    move_original: bool = False,
) -> DetectEntities:
    """Main-thread part of "Detect deformation": fields, colours and new entities.

    Writes the result fields onto ``cmp_entity`` (same points, same order; same-named fields
    replaced), shows ``deformation`` on a diverging scale (red = into the tunnel), builds a
    registered copy of the compared cloud (in the reference frame, reference shift/scale, with
    the fields) and both centrelines as polylines. ``cmp_entity``'s points move only if
    ``move_original``.
    """
    fields = result_fields(result.cloud)
    write_scalar_fields(cmp_entity, fields)
    limit = symmetric_limit(fields["deformation"], threshold=threshold)
    scale = red_white_blue_scale()
    colours = show_diverging(cmp_entity, "deformation", limit=limit, scale=scale)

    base = entity_name(cmp_entity)
    registered = make_point_cloud(
        result.cloud.xyz, like=ref_entity, name=f"{base} (registered)", fields=fields
    )
    show_diverging(registered, "deformation", limit=limit, scale=scale)
    ref_lines, ref_v = _lines(result, "reference", like=ref_entity)
    cmp_lines, cmp_v = _lines(result, "compared", like=ref_entity)
    if move_original:
        move_entity(cmp_entity, result.transform)
    return DetectEntities(registered, ref_lines, cmp_lines, ref_v + cmp_v, limit, colours)


def _edge_name(prefix: str, edge: Any) -> str:
    return f"{prefix}: edge {edge.id} {edge.name} ({edge.centerline.length:.1f} m)"


def _lines(result: Any, epoch: str, *, like: Any) -> tuple[list[Any], list[Any]]:
    """Polylines (and their vertex clouds to keep alive) of one epoch's centreline, or of
    every edge of its network."""
    network = getattr(result, "ref_network" if epoch == "reference" else "cmp_network", None)
    if network is not None:
        curves = [(_edge_name(f"{epoch} centreline", e), e.centerline.points)
                  for e in network.edges]
    else:
        cl = result.ref_centerline if epoch == "reference" else result.cmp_centerline
        curves = [(f"{epoch} centreline", cl.points)]
    lines, vertices = [], []
    for name, points in curves:
        line, v = make_polyline(points, like=like, name=name,
                                colour=CENTERLINE_COLOURS[epoch])
        lines.append(line)
        vertices.append(v)
    return lines, vertices


# --------------------------------------------------------------------------- centreline


def compute_centerline(
    cloud: Any, config: Any = None, *, progress: Any = None, network: str = "auto"
) -> Any:
    """Worker-thread part of "Extract centerline": ``extract_centerline`` of the core, or
    ``extract_network`` for a drift network (``network``: one of :data:`NETWORK_CHOICES`)."""
    from tunneldef.centerline import extract_centerline
    from tunneldef.centerline.network import extract_network
    from tunneldef.config import Config

    cfg = config or Config()
    if _wants_network(network, (cloud,), cfg):
        return extract_network(cloud.xyz, slicing=cfg.slicing, settings=cfg.centerline,
                               network=cfg.network, progress=progress)
    return extract_centerline(
        cloud.xyz, slicing=cfg.slicing, settings=cfg.centerline, progress=progress
    )


def apply_centerline(entity: Any, extraction: Any) -> tuple[list[Any], list[Any], str]:
    """Main-thread part: ``(polylines, vertices, text)`` for an extraction result: one
    polyline and the per-slice table for a drift, one polyline per edge and a line per edge
    for a network."""
    base = f"{entity_name(entity)} centreline"
    network = getattr(extraction, "network", None)
    if network is None:
        curves = [(base, extraction.centerline.points)]
        text = format_slice_table(extraction.slices)
    else:
        curves = [(_edge_name(base, e), e.centerline.points) for e in network.edges]
        rows = []
        for e in network.edges:
            used = sum(1 for r in e.slices if r.ok)
            rows.append(f"edge {e.id} {e.name}: {e.centerline.length:.2f} m, nodes "
                        f"{e.nodes[0]} -> {e.nodes[1]}, {used} of {len(e.slices)} slices used")
        text = (f"{len(network.edges)} edges, {len(network.junctions)} junctions\n"
                + "\n".join(rows))
    polys, vertices = [], []
    for name, points in curves:
        poly, v = make_polyline(points, like=entity, name=name,
                                colour=CENTERLINE_COLOURS["reference"])
        polys.append(poly)
        vertices.append(v)
    return polys, vertices, text


# --------------------------------------------------------------------------- registration


def compute_register(ref: Any, cmp: Any, config: Any = None, *, progress: Any = None) -> Any:
    """Worker-thread part of "Register to reference": :func:`tunneldef.pipeline.register_epochs`
    (the CLI's checks and refusals: epoch sizes and units, axial uncertainty), its
    ``registration``."""
    from tunneldef.pipeline import register_epochs

    return register_epochs(ref, cmp, config, progress=progress).registration


def apply_register(
    ref_entity: Any,
    cmp_entity: Any,
    cmp: Any,
    registration: Any,
) -> tuple[Any, str]:
    """Main-thread part: ``(registered copy, matrix text)``; the original is not moved."""
    from tunneldef.transforms import apply_transform

    t = np.asarray(registration.transform, dtype=np.float64)
    moved = apply_transform(t, cmp.xyz)
    copy = make_point_cloud(moved, like=ref_entity, name=f"{entity_name(cmp_entity)} (registered)")
    return copy, format_matrix(t)


