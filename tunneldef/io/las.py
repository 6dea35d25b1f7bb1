"""LAS / LAZ through laspy (LAZ via lazrs).

Reading keeps every dimension as a field under laspy's names (``intensity``, ``classification``,
``return_number``, ``gps_time``, ``red`` ...) plus the extra bytes, and the laspy header (version,
point format, scales, offsets, VLRs, EVLRs, extra-bytes descriptions) in ``meta["las_header"]``.
Writing a cloud that carries such a header reuses it; any other cloud is written as LAS 1.4,
point format 6 (7 with red/green/blue), scale 0.1 mm, offset = floor of the minimum corner.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import Any

import laspy
import numpy as np
from laspy.point.dims import DimensionInfo, DimensionKind

from ..cloud import Cloud
from ..errors import InvalidCloudError
from ._common import corrupt

__all__ = ["read", "write", "FRESH_SCALE", "FIELD_DESCRIPTIONS"]

logger = logging.getLogger(__name__)

#: Coordinate resolution (m) of LAS files written from clouds that did not come from LAS.
FRESH_SCALE = 1.0e-4

#: Descriptions (at most 32 characters) of tunneldef's output fields in LAS extra bytes;
#: other fields use ``meta["field_descriptions"][name]`` or their own name.
FIELD_DESCRIPTIONS: dict[str, str] = {
    "deformation": "signed deformation, m",
    "deformation_horizontal": "horizontal deformation, m",
    "deformation_vertical": "vertical deformation, m",
    "chainage": "chainage along centreline, m",
    "danger": "1 = beyond danger threshold",
    "significant": "1 = change beyond LoD95",
    "shell": "1 = tunnel shell point",
}

_INT32 = np.iinfo(np.int32)
_EXTRA_TYPES = ("u1", "i1", "u2", "i2", "u4", "i4", "u8", "i8", "f4", "f8")

# laspy raises these for damaged headers / point data; lazrs and numpy add their own.
try:  # pragma: no cover - lazrs is a declared dependency
    from lazrs import LazrsError as _LazrsError
except ImportError:  # pragma: no cover
    _LazrsError = laspy.errors.LaspyException
_READ_ERRORS = (laspy.errors.LaspyException, _LazrsError, ValueError, EOFError, IndexError)


def read(path: Path) -> Cloud:
    """Read a LAS/LAZ file (any version 1.0-1.4, any point format) into a Cloud."""
    try:
        las = laspy.read(path)
    except _READ_ERRORS as exc:
        raise corrupt(path, exc) from exc
    header = las.header
    points = las.points
    n = len(points)
    if n < header.point_count:
        raise corrupt(path, f"the header announces {header.point_count} points, only {n} are there")
    xyz = np.empty((n, 3), dtype=np.float64)
    for axis, dim in enumerate("XYZ"):
        np.multiply(points.array[dim], header.scales[axis], out=xyz[:, axis])
        xyz[:, axis] += header.offsets[axis]
    fields: dict[str, np.ndarray] = {}
    for dim in las.point_format.dimensions:
        if dim.name in ("X", "Y", "Z"):
            continue
        if dim.num_elements != 1:
            logger.warning(
                "%s: extra dimension %r has %d values per point; not read",
                path,
                dim.name,
                dim.num_elements,
            )
            continue
        fields[dim.name] = np.ascontiguousarray(las[dim.name])
    return Cloud(xyz, fields, {"las_header": header})


def write(
    path: Path, xyz: np.ndarray, fields: dict[str, np.ndarray], meta: dict[str, Any], *, ext: str
) -> None:
    """Write ``xyz`` (N, 3) metres and ``fields`` to a LAS (``ext == ".las"``) or LAZ file."""
    source = meta.get("las_header")
    if isinstance(source, laspy.LasHeader):
        header, targets = _header_from_source(source, fields, meta)
    else:
        header, targets = _fresh_header(xyz, fields, meta)
    _fit_offsets(header, xyz)
    if meta.get("note"):
        # a run whose quality checks failed says so in words (tunneldef.quality.UNVERIFIED)
        note = str(meta["note"])
        header.vlrs.append(laspy.VLR(user_id="tunneldef", record_id=1,
                                     description=note.encode()[:32].decode(errors="ignore"),
                                     record_data=note.encode()))
    las = laspy.LasData(header, laspy.ScaleAwarePointRecord.zeros(len(xyz), header=header))
    quantised = np.rint((xyz - header.offsets) / header.scales)
    for axis, dim in enumerate("XYZ"):
        las.points.array[dim] = quantised[:, axis].astype(np.int32)
    for name, target in targets.items():
        dim = header.point_format.dimension_by_name(target)
        las[target] = _cast(name, fields[name], dim)
    with open(path, "wb") as stream:
        las.write(stream, do_compress=ext == ".laz")


def _header_from_source(
    source: laspy.LasHeader, fields: dict[str, np.ndarray], meta: dict[str, Any]
) -> tuple[laspy.LasHeader, dict[str, str]]:
    """Copy the source header (version, point format, scales, offsets, VLRs, EVLRs); the extra
    bytes are rebuilt for the fields written, keeping the source's type and description."""
    header = copy.deepcopy(source)
    old_extra = {dim.name: dim for dim in source.point_format.extra_dimensions}
    header.point_format = laspy.PointFormat(source.point_format.id)
    standard = set(header.point_format.dimension_names)
    targets: dict[str, str] = {}
    params = []
    for name, values in fields.items():
        targets[name] = name
        if name in standard:
            continue
        old = old_extra.get(name)
        if old is not None and _fits(values, old):
            params.append(
                laspy.ExtraBytesParams(
                    name, old.dtype, old.description, old.offsets, old.scales, old.no_data
                )
            )
        else:
            targets[name] = _extra_name(name, standard)
            params.append(_new_extra(targets[name], name, values, meta))
    if params:
        header.add_extra_dims(params)
    return header, targets


def _fresh_header(
    xyz: np.ndarray, fields: dict[str, np.ndarray], meta: dict[str, Any]
) -> tuple[laspy.LasHeader, dict[str, str]]:
    """LAS 1.4, point format 6 (7 with colour), 0.1 mm scale, offset at the floored minimum."""
    has_rgb = all(c in fields for c in ("red", "green", "blue"))
    header = laspy.LasHeader(version="1.4", point_format=7 if has_rgb else 6)
    header.scales = np.full(3, FRESH_SCALE)
    header.offsets = np.floor(xyz.min(axis=0))
    standard = set(header.point_format.dimension_names)
    targets: dict[str, str] = {}
    params = []
    for name, values in fields.items():
        if name in standard and _fits(values, header.point_format.dimension_by_name(name)):
            targets[name] = name
            continue
        targets[name] = _extra_name(name, standard)
        params.append(_new_extra(targets[name], name, values, meta))
    if params:
        header.add_extra_dims(params)
    return header, targets


def _extra_name(name: str, standard: set[str]) -> str:
    """Extra-bytes name for a field: its own unless that is a standard dimension's name."""
    extra = name
    if name in standard or name.lower() in ("x", "y", "z"):
        extra = f"{name}_value"
        logger.warning(
            "field %r does not fit the LAS dimension of that name; written as extra bytes %r",
            name,
            extra,
        )
    if len(extra.encode()) > 32:
        raise InvalidCloudError(
            f"field name {extra!r} is longer than the 32 bytes LAS extra bytes allow; rename it"
        )
    return extra


def _new_extra(
    extra: str, name: str, values: np.ndarray, meta: dict[str, Any]
) -> laspy.ExtraBytesParams:
    """Extra bytes for a new field: bool as uint8, float16 as float32, others keep their type."""
    dt = values.dtype
    if dt.kind == "b":
        dtype = np.dtype(np.uint8)
    elif dt.kind == "f":
        dtype = np.dtype(np.float32 if dt.itemsize <= 4 else np.float64)
    elif dt.kind in "ui":
        dtype = dt.newbyteorder("=")
    else:
        raise InvalidCloudError(
            f"field {name!r} has dtype {dt}; only numeric or bool fields can be written to LAS"
        )
    descriptions = meta.get("field_descriptions") or {}
    description = str(descriptions.get(name) or FIELD_DESCRIPTIONS.get(name) or name)
    description = description.encode()[:32].decode(errors="ignore")
    return laspy.ExtraBytesParams(extra, dtype, description)


def _bounds(dim: DimensionInfo) -> tuple[float, float] | None:
    """Value range of a dimension as stored (None for floats and scaled dimensions)."""
    if dim.is_scaled or dim.kind == DimensionKind.FloatingPoint:
        return None
    return float(dim.min), float(dim.max)


def _fits(values: np.ndarray, dim: DimensionInfo) -> bool:
    """Whether ``values`` can be stored in ``dim`` without change."""
    if dim.num_elements != 1:
        return False
    bounds = _bounds(dim)
    if bounds is None:
        if dim.is_scaled:
            return values.dtype.kind in "uifb"
        return values.dtype.kind in "uifb" and (
            values.dtype.kind != "f" or values.dtype.itemsize <= dim.num_bytes
        )
    if values.dtype.kind not in "uifb":
        return False
    if values.size == 0:
        return True
    if values.dtype.kind == "f" and not np.array_equal(values, np.rint(values)):
        return False
    return bounds[0] <= float(values.min()) and float(values.max()) <= bounds[1]


def _cast(name: str, values: np.ndarray, dim: DimensionInfo) -> np.ndarray:
    """``values`` in the dimension's storage type, refusing values it cannot hold."""
    if dim.is_scaled:
        return values.astype(np.float64)
    if not _fits(values, dim):
        lo, hi = _bounds(dim) or (None, None)
        raise InvalidCloudError(
            f"field {name!r} has values outside LAS dimension {dim.name!r} "
            f"(range {lo}..{hi}); change the values or write the field under another name"
        )
    dtype = dim.dtype if dim.dtype is not None else np.dtype(np.uint8)
    return values.astype(dtype)


def _fit_offsets(header: laspy.LasHeader, xyz: np.ndarray) -> None:
    """Keep scale and offset if the coordinates fit int32; else a fresh offset per axis."""
    lo = (xyz.min(axis=0) - header.offsets) / header.scales
    hi = (xyz.max(axis=0) - header.offsets) / header.scales
    overflow = (lo < _INT32.min + 1) | (hi > _INT32.max - 1)
    if overflow.any():
        offsets = np.array(header.offsets, dtype=np.float64)
        offsets[overflow] = np.floor(xyz.min(axis=0)[overflow])
        logger.info("LAS offsets %s do not fit the coordinates; using %s", header.offsets, offsets)
        header.offsets = offsets
        span = (xyz.max(axis=0) - offsets) / header.scales
        if (span > _INT32.max - 1).any():
            raise InvalidCloudError(
                f"the cloud spans {np.ptp(xyz, axis=0).max():.0f} m, too much for LAS scale "
                f"{header.scales.tolist()}; write it as PLY or reduce the extent"
            )
