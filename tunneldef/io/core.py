"""``read`` / ``write``: pick the format module from the extension, validate, write atomically."""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from types import ModuleType

import numpy as np

from ..cloud import Cloud, check_points
from ..errors import InvalidCloudError, MissingFileError, UnsupportedFormatError

__all__ = ["read", "write", "supported_extensions"]

logger = logging.getLogger(__name__)

#: extension -> module of tunneldef.io that reads and writes it
_FAMILIES: dict[str, str] = {
    ".las": "las",
    ".laz": "las",
    ".ply": "ply",
    ".pcd": "pcd",
    ".xyz": "xyz",
    ".txt": "xyz",
    ".asc": "xyz",
    ".csv": "xyz",
}


def supported_extensions() -> tuple[str, ...]:
    """File extensions :func:`read` and :func:`write` understand (lower case, with the dot)."""
    return tuple(_FAMILIES)


def _family(path: Path) -> tuple[str, ModuleType]:
    ext = path.suffix.lower()
    name = _FAMILIES.get(ext)
    if name is None:
        raise UnsupportedFormatError(
            f"{path}: unsupported extension {ext or '(none)'!r}; use one of "
            f"{', '.join(supported_extensions())}"
        )
    return name, importlib.import_module(f"{__package__}.{name}")


def read(path: str | os.PathLike[str], *, strict: bool = False) -> Cloud:
    """Read a point cloud file into a :class:`~tunneldef.cloud.Cloud`.

    Parameters
    ----------
    path : str or path-like
        A ``.las``, ``.laz``, ``.ply``, ``.pcd``, ``.xyz``, ``.txt``, ``.asc`` or ``.csv`` file.
    strict : bool
        If True, points with NaN or infinite coordinates raise; by default they are dropped
        with a warning and their count is stored in ``meta["dropped_nonfinite"]``.

    Returns
    -------
    Cloud
        ``xyz`` (N, 3) float64 in metres, every per-point attribute of the file in ``fields``
        (names as the file gives them; PLY ``scalar_`` prefixes removed) and what is needed to
        write the file back faithfully in ``meta`` (``meta["path"]``, ``meta["format"]`` and a
        format entry such as ``meta["las_header"]``).

    Raises
    ------
    MissingFileError
        The file does not exist or is not a regular file.
    UnsupportedFormatError
        The extension is not one of :func:`supported_extensions`, or the variant is unknown.
    CorruptFileError
        The file cannot be parsed.
    InvalidCloudError
        The file holds no points, or (``strict``) some coordinates are not finite.
    """
    p = Path(path)
    if not p.exists():
        raise MissingFileError(f"input file not found: {p}")
    if not p.is_file():
        raise MissingFileError(f"input path is not a file: {p}")
    family, module = _family(p)
    start = time.perf_counter()
    cloud: Cloud = module.read(p)
    cloud.meta["path"] = str(p)
    cloud.meta["format"] = family
    cloud = _drop_nonfinite(cloud, p, strict=strict)
    if len(cloud) == 0:
        raise InvalidCloudError(f"{p} holds no points; choose a file with a point cloud in it")
    logger.info(
        "read %s: %d points, %d fields in %.2f s",
        p,
        len(cloud),
        len(cloud.fields),
        time.perf_counter() - start,
    )
    return cloud


def _drop_nonfinite(cloud: Cloud, path: Path, *, strict: bool) -> Cloud:
    finite = np.isfinite(cloud.xyz).all(axis=1)
    bad = int(finite.size - np.count_nonzero(finite))
    if bad == 0:
        return cloud
    if strict:
        raise InvalidCloudError(
            f"{path} has {bad} points with NaN or infinite coordinates; read with strict=False "
            "to drop them"
        )
    logger.warning("%s: dropped %d points with NaN or infinite coordinates", path, bad)
    kept = cloud[finite]
    kept.meta["dropped_nonfinite"] = bad
    return kept


def _selected_fields(cloud: Cloud, fields: Iterable[str] | None) -> dict[str, np.ndarray]:
    n = len(cloud)
    if isinstance(fields, str):
        fields = [fields]
    names = list(cloud.fields) if fields is None else list(dict.fromkeys(fields))
    missing = [name for name in names if name not in cloud.fields]
    if missing:
        raise InvalidCloudError(
            f"fields {missing} are not in the cloud; available: {sorted(cloud.fields)}"
        )
    out: dict[str, np.ndarray] = {}
    for name in names:
        values = np.asarray(cloud.fields[name])
        if values.shape != (n,):
            raise InvalidCloudError(
                f"field {name!r} has shape {values.shape} for {n} points; each field needs "
                "one value per point"
            )
        out[name] = values
    return out



@contextlib.contextmanager
def atomic_target(path: Path):  # noqa: ANN201 - a context manager yielding a Path
    """A temporary file beside ``path`` to write into; renamed onto ``path`` when the block
    ends without error, removed otherwise (an existing ``path`` is never left half written).

    Raises
    ------
    MissingFileError
        The target folder does not exist.
    """
    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise MissingFileError(f"output folder does not exist: {folder}; create it first")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{p.name}.", suffix=f".tmp{p.suffix}", dir=folder)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        _set_mode(tmp, p)
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise

def write(
    path: str | os.PathLike[str],
    cloud: Cloud,
    *,
    fields: Iterable[str] | None = None,
) -> None:
    """Write a cloud to a file, atomically (temporary file in the same folder, then rename).

    Parameters
    ----------
    path : str or path-like
        Target file; its extension chooses the format (see :func:`supported_extensions`).
    cloud : Cloud
        Points (metres) and fields. A cloud read from the same format family is written back
        with its source layout (LAS header, point format, scales, VLRs; PLY property names and
        encoding; PCD and text layout).
    fields : iterable of str, optional
        Fields to write besides x, y, z; all of them when None.

    Raises
    ------
    UnsupportedFormatError
        Unknown extension.
    InvalidCloudError
        Empty cloud, non-finite coordinates, an unknown field name or a field of the wrong
        length.
    MissingFileError
        The target folder does not exist.

    Notes
    -----
    On any failure the temporary file is removed and an existing target is left untouched.
    """
    p = Path(path)
    _, module = _family(p)
    if not isinstance(cloud, Cloud):
        raise InvalidCloudError(f"write expects a Cloud, got {type(cloud).__name__}")
    xyz = check_points(cloud.xyz, name="cloud coordinates")
    selected = _selected_fields(cloud, fields)
    start = time.perf_counter()
    with atomic_target(p) as tmp:
        module.write(tmp, xyz, selected, cloud.meta, ext=p.suffix.lower())
    logger.info(
        "wrote %s: %d points, %d fields in %.2f s",
        p,
        len(xyz),
        len(selected),
        time.perf_counter() - start,
    )


def _set_mode(tmp: Path, target: Path) -> None:
    """Give the temporary file the target's permissions (or the umask default)."""
    try:
        mode = target.stat().st_mode & 0o7777
    except FileNotFoundError:
        mode = 0o666 & ~_umask()
    os.chmod(tmp, mode)


def _umask() -> int:
    """The process umask, read without changing it where the system allows."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    umask = os.umask(0o022)
    os.umask(umask)
    return umask
