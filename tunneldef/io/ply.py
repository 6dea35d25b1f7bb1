"""PLY (ascii and binary) through plyfile, which keeps every numeric property type.

On read, each scalar vertex property other than x, y, z becomes a field; a ``scalar_`` prefix
(CloudCompare's convention for scalar fields) is removed from the field name and the original
property names are kept in ``meta["ply"]["names"]`` so they are written back unchanged. Fields
without a recorded name are written as ``scalar_<name>``, the only properties CloudCompare loads
as scalar fields. Coordinates are written as double when the source had doubles or when they
exceed 1e4 m (survey coordinates), float otherwise.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import plyfile

from ..cloud import Cloud
from ..errors import CorruptFileError
from ._common import coordinate_dtype, corrupt, safe_name, storable

__all__ = ["read", "write", "SCALAR_PREFIX"]

logger = logging.getLogger(__name__)

#: Prefix CloudCompare gives scalar-field properties (and the only ones it loads as such).
SCALAR_PREFIX = "scalar_"

_PLY_TYPES = ("i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8")


def read(path: Path) -> Cloud:
    """Read the vertex element of a PLY file (ascii, binary little or big endian)."""
    try:
        with open(path, "rb") as stream:
            ply = plyfile.PlyData.read(stream, mmap=False)
    except (plyfile.PlyParseError, UnicodeDecodeError, ValueError) as exc:
        raise corrupt(path, exc) from exc
    try:
        vertex = ply["vertex"]
    except KeyError:
        raise CorruptFileError(f"cannot read {path}: it has no 'vertex' element") from None
    data = vertex.data
    scalar = [p for p in vertex.properties if not isinstance(p, plyfile.PlyListProperty)]
    skipped = [p.name for p in vertex.properties if isinstance(p, plyfile.PlyListProperty)]
    if skipped:
        logger.warning("%s: list properties %s of 'vertex' are not read", path, skipped)
    others = [el.name for el in ply.elements if el.name != "vertex"]
    if others:
        logger.info("%s: elements %s besides 'vertex' are not read", path, others)
    prop_names = [p.name for p in scalar]
    if not all(c in prop_names for c in "xyz"):
        raise CorruptFileError(f"cannot read {path}: the vertex element has no x, y, z")
    xyz = np.column_stack([np.asarray(data[c], dtype=np.float64) for c in "xyz"])
    fields: dict[str, np.ndarray] = {}
    names: dict[str, str] = {}
    for prop in prop_names:
        if prop in ("x", "y", "z"):
            continue
        name = prop
        if prop.startswith(SCALAR_PREFIX) and len(prop) > len(SCALAR_PREFIX):
            name = prop[len(SCALAR_PREFIX) :]
            if name in prop_names or name in ("x", "y", "z"):
                name = prop
        values = np.asarray(data[prop])
        fields[name] = np.ascontiguousarray(values.astype(values.dtype.newbyteorder("=")))
        names[name] = prop
    meta = {
        "ply": {
            "text": bool(ply.text),
            "byte_order": ply.byte_order,
            "comments": list(ply.comments),
            "obj_info": list(ply.obj_info),
            "names": names,
            "xyz_dtype": np.dtype(data["x"].dtype).newbyteorder("=").str,
        }
    }
    return Cloud(xyz, fields, meta)


def write(
    path: Path, xyz: np.ndarray, fields: dict[str, np.ndarray], meta: dict[str, Any], *, ext: str
) -> None:
    """Write ``xyz`` (N, 3) metres and ``fields`` as the vertex element of a PLY file.

    Binary little endian unless the cloud was read from an ascii (or big-endian) PLY.
    """
    source = meta.get("ply") if isinstance(meta.get("ply"), dict) else {}
    names: dict[str, str] = dict(source.get("names", {}))
    coord = coordinate_dtype(xyz, source.get("xyz_dtype"))
    columns: list[tuple[str, np.ndarray]] = [(c, xyz[:, i]) for i, c in enumerate("xyz")]
    used = {"x", "y", "z"}
    for name, values in fields.items():
        prop = names.get(name) or SCALAR_PREFIX + safe_name(name)
        if prop in used:
            prop = SCALAR_PREFIX + safe_name(name)
        used.add(prop)
        columns.append((prop, storable(name, values, _PLY_TYPES)))
    dtype = [(c, coord) for c in "xyz"] + [(p, v.dtype) for p, v in columns[3:]]
    data = np.empty(len(xyz), dtype=dtype)
    for prop, values in columns:
        data[prop] = values
    element = plyfile.PlyElement.describe(data, "vertex")
    text = bool(source.get("text", False))
    byte_order = source.get("byte_order", "<") if not text else "="
    if byte_order == "=":
        byte_order = "<"
    ply = plyfile.PlyData(
        [element],
        text=text,
        byte_order=byte_order,
        comments=list(source.get("comments", [])),
        obj_info=list(source.get("obj_info", [])),
    )
    with open(path, "wb") as stream:
        ply.write(stream)
