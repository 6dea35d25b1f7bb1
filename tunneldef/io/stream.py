"""Large clouds without whole-file copies: coordinates read in chunks, outputs written in chunks.

* :func:`read_points`: the coordinates only (float64 metres, exactly as :func:`~.core.read`
  gives them), LAS/LAZ through laspy's chunk iterator (LAZ decompressed by lazrs on every
  core), PLY through plyfile's memory map; other formats through :func:`~.core.read`.
* :func:`write_with_fields`: the compared cloud written again with new coordinates and new
  fields, in its own order with every attribute. LAS/LAZ to LAS/LAZ goes chunk by chunk
  through laspy's chunked writer (the source's records are copied byte for byte, only X, Y, Z
  and the new fields are set); other pairs of formats through :func:`~.core.write`. Either
  way the file is written to a temporary name beside the target and renamed.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..cloud import Cloud
from ..errors import InvalidCloudError, MissingFileError
from .core import _family, atomic_target, read, write

__all__ = ["read_points", "write_with_fields", "CHUNK_POINTS"]

logger = logging.getLogger(__name__)

#: Points per chunk read or written.
CHUNK_POINTS = 1_000_000


def _laz_backend() -> Any:
    import laspy

    for name in ("LazrsParallel", "Lazrs"):
        backend = getattr(laspy.LazBackend, name, None)
        if backend is not None and backend.is_available():
            return backend
    return None


def _existing(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    if not p.exists():
        raise MissingFileError(f"input file not found: {p}")
    if not p.is_file():
        raise MissingFileError(f"input path is not a file: {p}")
    return p


def read_points(
    path: str | os.PathLike[str], *, strict: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    """Coordinates of a point cloud file.

    Parameters
    ----------
    path : path-like
        Any format :func:`~.core.read` reads.
    strict : bool
        Refuse NaN/inf coordinates instead of dropping them with a warning.

    Returns
    -------
    xyz : ndarray, shape (N, 3), float64
        Finite coordinates, metres, in file order.
    keep : ndarray of bool or None
        Which of the file's points ``xyz`` holds (None: all).

    Raises
    ------
    MissingFileError, UnsupportedFormatError, CorruptFileError, InvalidCloudError
        As :func:`~.core.read`.
    """
    p = _existing(path)
    family, _ = _family(p)
    start = time.perf_counter()
    if family == "las":
        xyz = _read_las_xyz(p)
    elif family == "ply":
        xyz = _read_ply_xyz(p)
    else:
        return read(p, strict=strict).xyz, None
    finite = np.isfinite(xyz).all(axis=1)
    keep = None
    if not finite.all():
        bad = int((~finite).sum())
        if strict:
            raise InvalidCloudError(
                f"{p} has {bad} points with NaN or infinite coordinates; read with strict=False "
                "to drop them"
            )
        logger.warning("%s: dropped %d points with NaN or infinite coordinates", p, bad)
        keep, xyz = finite, xyz[finite]
    if len(xyz) == 0:
        raise InvalidCloudError(f"{p} holds no points; choose a file with a point cloud in it")
    logger.info("read %s: %d points (coordinates) in %.2f s", p, len(xyz),
                time.perf_counter() - start)
    return xyz, keep


def _read_las_xyz(path: Path) -> np.ndarray:
    import laspy

    from ._common import corrupt
    from .las import _READ_ERRORS

    try:
        with laspy.open(path, laz_backend=_laz_backend()) as reader:
            header = reader.header
            n = int(header.point_count)
            xyz = np.empty((n, 3), dtype=np.float64)
            done = 0
            for chunk in reader.chunk_iterator(CHUNK_POINTS):
                m = len(chunk)
                if done + m > n:
                    raise ValueError(f"more points than the {n} the header announces")
                for axis, dim in enumerate("XYZ"):
                    out = xyz[done:done + m, axis]
                    np.multiply(chunk.array[dim], header.scales[axis], out=out)
                    out += header.offsets[axis]
                done += m
    except _READ_ERRORS as exc:
        raise corrupt(path, exc) from exc
    if done < n:
        raise corrupt(path, f"the header announces {n} points, only {done} are there")
    return xyz


def _read_ply_xyz(path: Path) -> np.ndarray:
    import plyfile

    from ..errors import CorruptFileError
    from ._common import corrupt

    with open(path, "rb") as head:
        if b"format ascii" in head.read(4096):
            return read(path).xyz  # text: parsed in bulk by the PLY module
    try:
        ply = plyfile.PlyData.read(str(path), mmap="r")  # binary: a memory map of the file
        vertex = ply["vertex"]
        return np.column_stack([np.asarray(vertex.data[c], dtype=np.float64) for c in "xyz"])
    except KeyError:
        raise CorruptFileError(f"cannot read {path}: it has no 'vertex' element with x, y, z"
                               ) from None
    except (plyfile.PlyParseError, UnicodeDecodeError, ValueError) as exc:
        raise corrupt(path, exc) from exc


def write_with_fields(
    path: str | os.PathLike[str],
    source: str | os.PathLike[str],
    xyz: np.ndarray,
    fields: dict[str, np.ndarray],
    *,
    keep: np.ndarray | None = None,
    strict: bool = False,
    note: str | None = None,
) -> None:
    """Write ``source``'s points (those in ``keep``) with coordinates ``xyz`` and ``fields``
    added to its attributes, atomically.

    Parameters
    ----------
    path : path-like
        Target file; its extension chooses the format.
    source : path-like
        The file the points were read from (its attributes and layout are kept).
    xyz : ndarray, shape (N, 3)
        New coordinates of the kept points, metres.
    fields : dict of str to ndarray, shape (N,)
        Fields added (or replacing the source's of the same name).
    keep : ndarray of bool, optional
        Which of the source's points are written (from :func:`read_points`).
    strict : bool
        As :func:`read_points` (for formats written through :func:`~.core.write`).
    note : str, optional
        Words for the file's header (a run whose quality checks failed is marked
        ``tunneldef.quality.UNVERIFIED``).
    """
    p, src = Path(path), _existing(source)
    out_family, _ = _family(p)
    src_family, _ = _family(src)
    if not (out_family == "las" and src_family == "las"):
        cloud = read(src, strict=strict)
        if len(cloud) != len(xyz):
            raise InvalidCloudError(f"{len(xyz)} coordinates for the {len(cloud)} points of {src}")
        meta = dict(cloud.meta)
        if note:
            meta["note"] = note
        cloud = Cloud(xyz, {**cloud.fields, **fields}, meta)
        write(p, cloud)
        return
    start = time.perf_counter()
    with atomic_target(p) as tmp:
        _write_las_chunks(tmp, src, xyz, fields, keep, compress=p.suffix.lower() == ".laz",
                          note=note)
    logger.info("wrote %s: %d points in chunks in %.2f s", p, len(xyz),
                time.perf_counter() - start)


def _write_las_chunks(
    tmp: Path, src: Path, xyz: np.ndarray, fields: dict[str, np.ndarray],
    keep: np.ndarray | None, *, compress: bool, note: str | None = None,
) -> None:
    import laspy

    from .las import _cast, _fit_offsets, _header_from_source

    backend = _laz_backend()
    with laspy.open(src, laz_backend=backend) as reader:
        source = reader.header
        # the fields in the order the whole-cloud path has them: the source's, then the new
        spec: dict[str, np.ndarray] = {}
        for dim in source.point_format.dimensions:
            if dim.name not in ("X", "Y", "Z") and dim.num_elements == 1:
                spec[dim.name] = np.zeros(0, dtype=dim.dtype or np.uint8)
        spec.update(fields)
        header, targets = _header_from_source(source, spec, {})
        _fit_offsets(header, xyz)
        if note:
            header.vlrs.append(laspy.VLR(user_id="tunneldef", record_id=1,
                                         description=note.encode()[:32].decode(errors="ignore"),
                                         record_data=note.encode()))
        raw = set(header.point_format.dtype().names) - {"X", "Y", "Z"}
        done = read_rows = 0
        with laspy.open(tmp, mode="w", header=header, do_compress=compress,
                        laz_backend=backend if compress else None) as writer:
            for chunk in reader.chunk_iterator(CHUNK_POINTS):
                rows = np.arange(read_rows, read_rows + len(chunk))
                read_rows += len(chunk)
                arr = chunk.array if keep is None else chunk.array[keep[rows]]
                m = len(arr)
                rec = laspy.ScaleAwarePointRecord.zeros(m, header=header)
                for name in raw & set(arr.dtype.names):
                    rec.array[name] = arr[name]
                q = np.rint((xyz[done:done + m] - header.offsets) / header.scales)
                for axis, dim in enumerate("XYZ"):
                    rec.array[dim] = q[:, axis].astype(np.int32)
                for name, values in fields.items():
                    target = targets[name]
                    rec[target] = _cast(name, values[done:done + m],
                                        header.point_format.dimension_by_name(target))
                writer.write_points(rec)
                done += m
    if done != len(xyz):
        raise InvalidCloudError(f"{len(xyz)} coordinates for the {done} points of {src}")
