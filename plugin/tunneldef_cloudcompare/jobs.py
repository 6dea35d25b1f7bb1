"""The three jobs, each in two steps: compute (worker thread: the core on numpy arrays, never
an entity) and apply (main thread: scalar fields, colours, new entities)."""

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
from .runtime import entity_name
from .text import format_matrix, format_slice_table

__all__ = [
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

#: Optional fields written too when the estimator provides them (significance, classes).
OPTIONAL_FIELDS = ("significant", "lod95", "shell", "surface", "class")


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
    ref: Any, cmp: Any, config: Any = None, *, progress: Any = None, memory_gb: float = 1.5
) -> Any:
    """Worker-thread part of "Detect deformation": :func:`tunneldef.pipeline.detect`.

    The deformation stage runs in chainage tiles on Dask's local threaded scheduler, as
    ``tunneldef detect`` does, so its working memory is bounded by ``memory_gb`` (GB) and not
    by the survey; the tiles' temporary files go to the system's temporary folder.
    """
    import tempfile

    from tunneldef.engine import open_engine
    from tunneldef.pipeline import detect

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
    """Entities the "Detect deformation" action created (to add to the DB tree)."""

    registered: Any
    ref_centerline: Any
    cmp_centerline: Any
    keep_alive: list[Any] = field(default_factory=list)
    limit: float = 0.0
    colours: str = SCALE_RED_IN

    def legend(self) -> str:
        """One line saying what the colours mean, for the console."""
        ends = {
            SCALE_RED_IN: "red = into the tunnel, white = 0, blue = outward",
            SCALE_BLUE_IN: "blue = into the tunnel, white = 0, red = outward (built-in scale; "
            "this runtime cannot load the Red>White>Blue one)",
        }.get(self.colours, "CloudCompare's default scale (no diverging scale available)")
        return f"colour scale: {ends}, saturated at ±{self.limit * 1000:.0f} mm"

    def new_entities(self) -> list[Any]:
        return [self.registered, self.ref_centerline, self.cmp_centerline]


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
    ref_line, ref_v = make_polyline(
        result.ref_centerline.points,
        like=ref_entity,
        name="reference centreline",
        colour=CENTERLINE_COLOURS["reference"],
    )
    cmp_line, cmp_v = make_polyline(
        result.cmp_centerline.points,
        like=ref_entity,
        name="compared centreline",
        colour=CENTERLINE_COLOURS["compared"],
    )
    if move_original:
        move_entity(cmp_entity, result.transform)
    return DetectEntities(registered, ref_line, cmp_line, [ref_v, cmp_v], limit, colours)


# --------------------------------------------------------------------------- centreline


def compute_centerline(cloud: Any, config: Any = None, *, progress: Any = None) -> Any:
    """Worker-thread part of "Extract centerline": ``extract_centerline`` of the core."""
    from tunneldef.centerline import extract_centerline
    from tunneldef.config import Config

    cfg = config or Config()
    return extract_centerline(
        cloud.xyz, slicing=cfg.slicing, settings=cfg.centerline, progress=progress
    )


def apply_centerline(entity: Any, extraction: Any) -> tuple[Any, Any, str]:
    """Main-thread part: ``(polyline, vertices, table)`` for an extraction result."""
    poly, vertices = make_polyline(
        extraction.centerline.points,
        like=entity,
        name=f"{entity_name(entity)} centreline",
        colour=CENTERLINE_COLOURS["reference"],
    )
    return poly, vertices, format_slice_table(extraction.slices)


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


