"""PCD (Point Cloud Library), ascii and binary, parsed with numpy; binary_compressed via Open3D.

Every field of the header becomes a cloud field with its own type. A packed ``rgb`` / ``rgba``
field is split into ``red``, ``green``, ``blue`` (and ``alpha``) uint8 fields and packed again on
write; a field with COUNT k > 1 becomes ``name_0`` ... ``name_{k-1}``; ``_`` padding is skipped.
Organized clouds (HEIGHT > 1) are read as a flat list. Files are written as binary unless the
cloud was read from an ascii PCD.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..cloud import Cloud
from ..errors import UnsupportedFormatError
from ._common import (
    coordinate_dtype,
    corrupt,
    safe_name,
    storable,
    text_format,
    write_table,
)

__all__ = ["read", "write"]

logger = logging.getLogger(__name__)

_TYPES = {("F", 4): "f4", ("F", 8): "f8"}
_TYPES.update({("I", k): f"i{k}" for k in (1, 2, 4, 8)})
_TYPES.update({("U", k): f"u{k}" for k in (1, 2, 4, 8)})
_PCD_TYPES = tuple(_TYPES.values())
_MAX_HEADER_LINES = 64


def _parse_header(path: Path, raw: bytes) -> tuple[dict[str, list[str]], int]:
    """Header entries (key -> tokens) and the byte offset of the data."""
    header: dict[str, list[str]] = {}
    pos = 0
    for _ in range(_MAX_HEADER_LINES):
        end = raw.find(b"\n", pos)
        if end < 0:
            raise corrupt(path, "the header has no DATA line")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, pos
    raise corrupt(path, "the header has no DATA line")


def _layout(path: Path, header: dict[str, list[str]]) -> tuple[list[str], list[str], list[int]]:
    """Field names, numpy type strings and counts from FIELDS/SIZE/TYPE/COUNT."""
    names = header.get("FIELDS") or header.get("COLUMNS")
    if not names:
        raise corrupt(path, "the header has no FIELDS line")
    sizes = header.get("SIZE", [])
    kinds = header.get("TYPE", [])
    counts = header.get("COUNT", ["1"] * len(names))
    if not (len(sizes) == len(kinds) == len(counts) == len(names)):
        raise corrupt(path, "FIELDS, SIZE, TYPE and COUNT have different lengths")
    try:
        types = [_TYPES[(k.upper(), int(s))] for k, s in zip(kinds, sizes, strict=True)]
        count_values = [int(c) for c in counts]
    except (KeyError, ValueError) as exc:
        raise corrupt(path, f"bad SIZE/TYPE/COUNT entry {exc}") from exc
    return names, types, count_values


def _point_count(path: Path, header: dict[str, list[str]]) -> int:
    try:
        if "POINTS" in header:
            return int(header["POINTS"][0])
        return int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0])
    except (KeyError, IndexError, ValueError) as exc:
        raise corrupt(path, "the header has no valid POINTS or WIDTH/HEIGHT") from exc


def read(path: Path) -> Cloud:
    """Read a PCD file (v0.5-0.7; ascii, binary or binary_compressed)."""
    raw = path.read_bytes()
    header, start = _parse_header(path, raw)
    names, types, counts = _layout(path, header)
    n = _point_count(path, header)
    mode = (header.get("DATA") or ["?"])[0].lower()
    meta: dict[str, Any] = {
        "data": mode,
        "viewpoint": header.get("VIEWPOINT", ["0", "0", "0", "1", "0", "0", "0"]),
        "version": (header.get("VERSION") or ["0.7"])[0],
    }
    if mode == "binary_compressed":
        packed = [
            (name, typ) for name, typ in zip(names, types, strict=True) if name in ("rgb", "rgba")
        ]
        if packed:
            meta["packed_rgb"] = list(packed[0])
        return _read_compressed(path, names, meta)
    columns: dict[str, np.ndarray] = {}
    if mode == "ascii":
        width = sum(counts)
        try:
            lines = raw[start:].decode("ascii").splitlines()
            table = np.loadtxt(lines, dtype=np.float64, ndmin=2) if n else np.empty((0, width))
        except (ValueError, UnicodeDecodeError) as exc:
            raise corrupt(path, exc) from exc
        if table.shape[0] != n or (n and table.shape[1] != width):
            raise corrupt(path, f"expected {n} rows of {width} values, found {table.shape}")
        col = 0
        for name, typ, count in zip(names, types, counts, strict=True):
            block = table[:, col : col + count]
            col += count
            if name == "rgb" or name == "rgba":
                block = block.astype(np.float64)
                columns[name] = _ascii_packed(block[:, 0], typ)
            elif count == 1:
                columns[name] = block[:, 0].astype(typ)
            else:
                columns[name] = block.astype(typ)
    elif mode == "binary":
        dtype = np.dtype(
            [
                (f"f{i}", "<" + typ, (count,)) if count > 1 else (f"f{i}", "<" + typ)
                for i, (typ, count) in enumerate(zip(types, counts, strict=True))
            ]
        )
        if len(raw) - start < n * dtype.itemsize:
            raise corrupt(
                path, f"{n} points need {n * dtype.itemsize} data bytes, found {len(raw) - start}"
            )
        data = np.frombuffer(raw, dtype=dtype, count=n, offset=start)
        for i, name in enumerate(names):
            columns[name] = data[f"f{i}"].astype(data[f"f{i}"].dtype.base.newbyteorder("="))
    else:
        raise UnsupportedFormatError(
            f"{path}: PCD DATA {mode!r} is not supported; use ascii, binary or binary_compressed"
        )
    return _to_cloud(path, columns, types, names, meta)


def _ascii_packed(values: np.ndarray, typ: str) -> np.ndarray:
    """A packed colour written as text: float bit pattern (TYPE F) or integer (TYPE U/I)."""
    if typ == "f4":
        return values.astype(np.float32).view(np.uint32)
    return values.astype(np.uint32)


def _to_cloud(
    path: Path,
    columns: dict[str, np.ndarray],
    types: list[str],
    names: list[str],
    meta: dict[str, Any],
) -> Cloud:
    if not all(c in columns for c in "xyz"):
        raise corrupt(path, "the PCD has no x, y, z fields")
    xyz = np.column_stack([columns[c].astype(np.float64).ravel() for c in "xyz"])
    fields: dict[str, np.ndarray] = {}
    groups: dict[str, int] = {}
    for name, typ in zip(names, types, strict=True):
        if name in ("x", "y", "z") or name == "_":
            continue
        values = columns[name]
        if name in ("rgb", "rgba") and typ in ("f4", "u4", "i4"):
            bits = values.view(np.uint32) if values.dtype.itemsize == 4 else values
            bits = np.asarray(bits, dtype=np.uint32)
            fields["red"] = ((bits >> 16) & 0xFF).astype(np.uint8)
            fields["green"] = ((bits >> 8) & 0xFF).astype(np.uint8)
            fields["blue"] = (bits & 0xFF).astype(np.uint8)
            if name == "rgba":
                fields["alpha"] = ((bits >> 24) & 0xFF).astype(np.uint8)
            meta["packed_rgb"] = [name, typ]
        elif values.ndim == 2:
            groups[name] = values.shape[1]
            for k in range(values.shape[1]):
                fields[f"{name}_{k}"] = np.ascontiguousarray(values[:, k])
        else:
            fields[name] = np.ascontiguousarray(values)
    meta["groups"] = groups
    meta["xyz_dtype"] = columns["x"].dtype.str[1:]
    return Cloud(xyz, fields, {"pcd": meta})


def _read_compressed(path: Path, names: list[str], meta: dict[str, Any]) -> Cloud:
    """binary_compressed (LZF) through Open3D's tensor reader, which keeps custom fields."""
    import open3d as o3d

    try:
        pcd = o3d.t.io.read_point_cloud(str(path))
    except RuntimeError as exc:
        raise corrupt(path, exc) from exc
    attrs = {key: pcd.point[key].numpy() for key in pcd.point}
    if "positions" not in attrs or len(attrs["positions"]) == 0:
        raise corrupt(path, "Open3D found no points in this binary_compressed PCD")
    columns: dict[str, np.ndarray] = {}
    types: list[str] = []
    order: list[str] = []
    for key, values in attrs.items():
        if key == "positions":
            parts = dict(zip("xyz", values.T, strict=True))
        elif key == "normals":
            parts = dict(zip(("normal_x", "normal_y", "normal_z"), values.T, strict=True))
        elif key == "colors":
            rgb = values if values.dtype == np.uint8 else np.clip(values * 255, 0, 255)
            parts = dict(zip(("red", "green", "blue"), rgb.astype(np.uint8).T, strict=True))
        elif values.ndim == 2 and values.shape[1] == 1:
            parts = {key: values[:, 0]}
        else:
            parts = {f"{key}_{k}": values[:, k] for k in range(values.shape[1])}
        for name, column in parts.items():
            columns[name] = np.ascontiguousarray(column)
            types.append(column.dtype.str[1:])
            order.append(name)
    ranked = {name: i for i, name in enumerate(names)}
    index = sorted(range(len(order)), key=lambda i: ranked.get(order[i], len(ranked) + i))
    meta["data"] = "binary"
    if "alpha" not in columns and meta.get("packed_rgb", [""])[0] == "rgba":
        meta["packed_rgb"] = ["rgb", meta["packed_rgb"][1]]
    return _to_cloud(path, columns, [types[i] for i in index], [order[i] for i in index], meta)


def write(
    path: Path, xyz: np.ndarray, fields: dict[str, np.ndarray], meta: dict[str, Any], *, ext: str
) -> None:
    """Write ``xyz`` (N, 3) metres and ``fields`` as a PCD v0.7 file (binary or ascii)."""
    source = meta.get("pcd") if isinstance(meta.get("pcd"), dict) else {}
    ascii_mode = source.get("data") == "ascii"
    coord = coordinate_dtype(xyz, source.get("xyz_dtype"))
    columns: list[tuple[str, np.ndarray]] = [
        (c, xyz[:, i].astype(coord)) for i, c in enumerate("xyz")
    ]
    remaining = dict(fields)
    packed = source.get("packed_rgb")
    groups: dict[str, int] = dict(source.get("groups", {}))
    for name in list(fields):
        if name not in remaining:
            continue
        if packed and name in ("red", "green", "blue", "alpha"):
            column = _pack_rgb(remaining, packed, ascii_mode)
            if column is not None:
                columns.append(column)
                continue
        group = _group_of(name, groups, remaining)
        if group is not None:
            columns.append(group)
            continue
        values = remaining.pop(name)
        columns.append((safe_name(name), storable(name, values, _PCD_TYPES)))
    n = len(xyz)
    header = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(name for name, _ in columns),
        "SIZE " + " ".join(str(v.dtype.itemsize) for _, v in columns),
        "TYPE " + " ".join(v.dtype.kind.upper() for _, v in columns),
        "COUNT " + " ".join(str(v.shape[1] if v.ndim == 2 else 1) for _, v in columns),
        f"WIDTH {n}",
        "HEIGHT 1",
        "VIEWPOINT " + " ".join(source.get("viewpoint", ["0", "0", "0", "1", "0", "0", "0"])),
        f"POINTS {n}",
        f"DATA {'ascii' if ascii_mode else 'binary'}",
    ]
    with open(path, "wb") as stream:
        stream.write(("\n".join(header) + "\n").encode("ascii"))
        if ascii_mode:
            flat = [
                block[:, k]
                for block in (v if v.ndim == 2 else v[:, None] for _, v in columns)
                for k in range(block.shape[1])
            ]
            write_table(stream, flat, [text_format(v) for v in flat], " ")
        else:
            dtype = np.dtype(
                [
                    (f"f{i}", v.dtype.newbyteorder("<"), (v.shape[1],))
                    if v.ndim == 2
                    else (f"f{i}", v.dtype.newbyteorder("<"))
                    for i, (_, v) in enumerate(columns)
                ]
            )
            data = np.empty(n, dtype=dtype)
            for i, (_, values) in enumerate(columns):
                data[f"f{i}"] = values
            stream.write(data.tobytes())


def _pack_rgb(
    remaining: dict[str, np.ndarray], packed: list[str], ascii_mode: bool
) -> tuple[str, np.ndarray] | None:
    """Pack red/green/blue(/alpha) back into the source's rgb/rgba field if they fit uint8."""
    name, typ = packed
    parts = ["red", "green", "blue"] + (["alpha"] if name == "rgba" else [])
    if not all(p in remaining for p in parts):
        return None
    values = [remaining[p] for p in parts]
    if not all(v.dtype.kind in "uib" and v.min() >= 0 and v.max() <= 255 for v in values):
        return None
    for p in parts:
        remaining.pop(p)
    r, g, b = (v.astype(np.uint32) for v in values[:3])
    bits = (r << 16) | (g << 8) | b
    if name == "rgba":
        bits |= values[3].astype(np.uint32) << 24
    if typ == "f4" and not ascii_mode:
        return name, bits.view(np.float32)
    return name, bits.astype(np.uint32)


def _group_of(
    name: str, groups: dict[str, int], remaining: dict[str, np.ndarray]
) -> tuple[str, np.ndarray] | None:
    """Join ``base_0 .. base_{k-1}`` back into one COUNT k field when all parts are there."""
    for base, count in groups.items():
        parts = [f"{base}_{k}" for k in range(count)]
        if name in parts and all(p in remaining for p in parts):
            values = [remaining[p] for p in parts]
            if len({v.dtype for v in values}) != 1:
                return None
            for p in parts:
                remaining.pop(p)
            return base, np.column_stack(values)
    return None
