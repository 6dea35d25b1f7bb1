"""New CloudCompare entities (clouds, polylines) in survey coordinates, and moving one."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .coords import copy_shift_and_scale, global_to_local, local_transform, shift_and_scale
from .fields import write_scalar_fields
from .runtime import BrokenRuntimeError, check_array, pycc_module, try_call

__all__ = ["CENTERLINE_COLOURS", "make_point_cloud", "make_polyline", "move_entity"]

#: Polyline colours (RGB 0-255) of the reference and the compared centreline.
CENTERLINE_COLOURS = {"reference": (0, 160, 0), "compared": (255, 140, 0)}


def _local_columns(xyz: np.ndarray, shift: np.ndarray, scale: float) -> list[np.ndarray]:
    """Contiguous float32 local x, y, z columns (one column at a time: little extra memory)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return [np.ascontiguousarray(global_to_local(xyz[:, i], shift[i], scale)) for i in range(3)]


def make_point_cloud(
    xyz: np.ndarray,
    *,
    like: Any = None,
    name: str = "cloud",
    fields: Mapping[str, np.ndarray] | None = None,
) -> Any:
    """A new ``ccPointCloud`` holding global coordinates ``xyz`` (N, 3), metres.

    With ``like`` the new cloud gets that entity's global shift and scale (so survey
    coordinates keep their precision); ``fields`` are written as scalar fields.
    """
    pycc = pycc_module()
    shift, scale = shift_and_scale(like) if like is not None else (np.zeros(3), 1.0)
    pc = pycc.ccPointCloud(*_local_columns(xyz, shift, scale))
    if like is not None:
        copy_shift_and_scale(pc, like)
    pc.setName(name)
    if fields:
        write_scalar_fields(pc, fields)
    return pc


def make_polyline(
    points: np.ndarray,
    *,
    like: Any = None,
    name: str = "centreline",
    colour: tuple[int, int, int] | None = None,
) -> tuple[Any, Any]:
    """An open ``ccPolyline`` through ``points`` (M, 3), global metres.

    Returns ``(polyline, vertices)``. The runtime exposes no ``addChild``: the caller must
    keep a Python reference to ``vertices`` for as long as the polyline lives (as the
    runtime's own polyline example does); only the polyline goes into the DB tree.
    """
    pycc = pycc_module()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    vertices = make_point_cloud(pts, like=like, name=f"{name} vertices")
    poly = pycc.ccPolyline(vertices)
    poly.addPointIndex(0, int(len(pts)))
    try_call(poly, "setClosed", False)
    if like is not None:
        copy_shift_and_scale(poly, like)
    poly.setName(name)
    if colour is not None and hasattr(pycc, "Rgb"):
        try_call(poly, "setColor", pycc.Rgb(*colour))
        try_call(poly, "showColors", True)
    return poly, vertices


def move_entity(entity: Any, transform: np.ndarray) -> None:
    """Apply a rigid global-coordinate transform to an entity's points in place.

    Uses ``ccGLMatrix`` (column-major storage, its ``asArray()`` view is the transpose) and
    ``applyGLTransformation_recursive``; the entity keeps its shift and scale.

    Raises
    ------
    BrokenRuntimeError
        If the matrix written into ``asArray()`` does not read back (the entity is then not
        moved at all).
    """
    pycc = pycc_module()
    shift, scale = shift_and_scale(entity)
    lt = local_transform(transform, shift, scale).T.astype(np.float32)
    mat = pycc.ccGLMatrix()
    check_array(mat.asArray(), "ccGLMatrix.asArray()")[:, :] = lt
    if not np.allclose(np.asarray(mat.asArray()), lt, rtol=0, atol=0):
        raise BrokenRuntimeError(
            "this CloudCompare Python runtime loses writes into ccGLMatrix.asArray(); the "
            "original cloud was not moved (rebuild the runtime with pybind11 >= 2.13)"
        )
    entity.applyGLTransformation_recursive(mat)
