"""Helpers shared by the format modules: field dtypes, names and error wrapping."""

from __future__ import annotations

import io
import logging
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CorruptFileError, InvalidCloudError

logger = logging.getLogger(__name__)

#: Largest absolute coordinate (m) written as float32 in PLY/PCD; beyond it float32 rounding
#: exceeds ~0.5 mm, so survey coordinates are written as float64.
FLOAT32_COORD_LIMIT = 1.0e4

_WHITESPACE = re.compile(r"\s+")


def corrupt(path: Path, problem: object) -> CorruptFileError:
    """A :class:`CorruptFileError` naming the file, on one line."""
    text = _WHITESPACE.sub(" ", str(problem)).strip() or type(problem).__name__
    return CorruptFileError(
        f"cannot read {path}: {text} (the file is damaged, truncated or not in its format)"
    )


def coordinate_dtype(xyz: np.ndarray, source_dtype: object | None = None) -> np.dtype:
    """float64 when the source stored doubles or coordinates exceed float32's mm precision."""
    if source_dtype is not None and np.dtype(source_dtype) == np.float64:
        return np.dtype(np.float64)
    if xyz.size and float(np.abs(xyz).max()) > FLOAT32_COORD_LIMIT:
        return np.dtype(np.float64)
    return np.dtype(np.float32)


def storable(name: str, values: np.ndarray, allowed: tuple[str, ...]) -> np.ndarray:
    """Convert ``values`` to a dtype a file format can hold, losslessly where possible.

    Parameters
    ----------
    name : str
        Field name (for messages).
    values : ndarray, shape (N,)
        Field values of any numeric or bool dtype.
    allowed : tuple of str
        numpy dtype strings the format supports (e.g. ``("u1", "i4", "f4", "f8")``).

    Returns
    -------
    ndarray, shape (N,)
        ``values`` itself when its dtype is allowed; bool as uint8; float16 as float32; a
        64-bit integer as 32-bit when all values fit, else float64.
    """
    dt = values.dtype
    if dt.kind == "b":
        return values.astype(np.uint8)
    if dt.kind not in "uif":
        raise InvalidCloudError(
            f"field {name!r} has dtype {dt}; only numeric or bool fields can be written"
        )
    if dt.newbyteorder("=").str[1:] in allowed:
        return values.astype(dt.newbyteorder("="), copy=False)
    if dt.kind == "f":
        return values.astype(np.float32 if dt.itemsize < 4 else np.float64)
    lo = int(values.min()) if values.size else 0
    hi = int(values.max()) if values.size else 0
    for cand in ("i4", "u4") if dt.kind == "i" else ("u4", "i4"):
        info = np.iinfo(cand)
        if cand in allowed and info.min <= lo and hi <= info.max:
            return values.astype(cand)
    logger.warning("field %r (%s) does not fit the format's integers; written as float64", name, dt)
    return values.astype(np.float64)


def safe_name(name: str) -> str:
    """A field name usable in a whitespace-separated header (spaces become underscores)."""
    clean = _WHITESPACE.sub("_", name.strip())
    if not clean:
        raise InvalidCloudError("a field has an empty name; give every field a name")
    if clean != name:
        logger.warning(
            "field name %r written as %r (no spaces allowed in this format)", name, clean
        )
    return clean


def text_format(values: np.ndarray) -> str:
    """printf format that writes ``values`` exactly as text (ints, float32, float64)."""
    if values.dtype.kind in "uib":
        return "%d"
    if values.dtype == np.float32:
        return "%.9g"
    return "%.17g"


def write_table(
    stream: Any, columns: list[np.ndarray], fmt: list[str], delimiter: str, *, chunk: int = 200_000
) -> None:
    """Write (N,) columns of mixed types as text rows, exact for ints, float32 and float64.

    Rows are formatted in chunks with one printf per row (about 3x faster than
    ``np.savetxt`` on mixed columns).
    """
    row = delimiter.join(fmt)
    n = columns[0].shape[0]
    for start in range(0, n, chunk):
        parts = [c[start : start + chunk].tolist() for c in columns]
        text = "\n".join([row % values for values in zip(*parts, strict=True)]) + "\n"
        stream.write(text if isinstance(stream, io.TextIOBase) else text.encode("ascii"))
