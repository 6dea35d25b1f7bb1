"""Plain-text clouds: .xyz, .txt, .asc, .csv (whitespace, comma or semicolon separated).

An optional first line names the columns, plain (``x,y,z,intensity``) or commented as
CloudCompare writes it (``//X Y Z deformation``). Columns named x, y, z (any case) are the
coordinates, otherwise the first three; every other column becomes a float64 field named by the
header, or ``column_<k>`` (1-based) without one. Written files use the source's separator and
header style when the cloud came from such a file; otherwise comma with a plain header for
``.csv`` and a space with a CloudCompare ``//X Y Z ...`` header for the others (no header when
there are no fields).
"""

from __future__ import annotations

import logging
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..cloud import Cloud
from ._common import corrupt, safe_name, text_format, write_table

__all__ = ["read", "write"]

logger = logging.getLogger(__name__)

_AUTO_NAME = re.compile(r"column_\d+")
_COORD_FORMAT = "%.6f"  # 1 micrometre
_SCAN_LINES = 50


def _split(line: str, sep: str | None) -> list[str]:
    return [t.strip() for t in line.split(sep)] if sep else line.split()


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read(path: Path) -> Cloud:
    """Read a text cloud (see the module notes for the accepted layouts)."""
    try:
        with open(path, encoding="utf-8-sig") as stream:
            head = [stream.readline() for _ in range(_SCAN_LINES)]
    except UnicodeDecodeError as exc:
        raise corrupt(path, exc) from exc
    first = next((i for i, line in enumerate(head) if line.strip()), None)
    if first is None:
        return Cloud(np.empty((0, 3)))
    header_line: str | None = None
    style = ""
    line = head[first].strip()
    if line.startswith(("//", "#")):
        style = "//" if line.startswith("//") else "#"
        header_line = line.lstrip("/#").strip()
    data_lines = [x.strip() for x in head[first + 1 :] if x.strip()]
    if header_line is None:
        if not all(_is_number(t) for t in re.split(r"[\s,;]+", line) if t):
            header_line = line
        else:
            data_lines.insert(0, line)
    sample = next((x for x in data_lines if not x.startswith(("#", "//"))), header_line or "")
    sep = "," if "," in sample else (";" if ";" in sample else None)
    skip = first + 1 if header_line is not None else first
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            table = np.loadtxt(
                path,
                delimiter=sep,
                comments=("#", "//"),
                skiprows=skip,
                ndmin=2,
                dtype=np.float64,
                encoding="utf-8-sig",
            )
    except (ValueError, UnicodeDecodeError) as exc:
        raise corrupt(path, exc) from exc
    if table.shape[0] == 0:
        return Cloud(np.empty((0, 3)))
    ncol = table.shape[1]
    if ncol < 3:
        raise corrupt(path, f"rows have {ncol} values; x, y, z need at least 3")
    if style == "#" and header_line is not None and len(_split(header_line, sep)) != ncol:
        header_line, style = None, ""  # a comment, not column names
    names = _column_names(path, header_line, sep, ncol)
    lower = [name.lower() for name in names]
    if all(c in lower for c in "xyz"):
        coords = [lower.index(c) for c in "xyz"]
    else:
        coords = [0, 1, 2]
    xyz = np.ascontiguousarray(table[:, coords])
    fields = {names[k]: np.ascontiguousarray(table[:, k]) for k in range(ncol) if k not in coords}
    meta = {
        "xyz": {
            "separator": sep,
            "header": header_line is not None,
            "style": style,
            "xyz_names": [names[k] for k in coords] if header_line is not None else None,
        }
    }
    return Cloud(xyz, fields, meta)


def _column_names(path: Path, header: str | None, sep: str | None, ncol: int) -> list[str]:
    """Header names (unique, non-empty), or ``column_<k>`` where there is none."""
    given = _split(header, sep) if header is not None else []
    if header is not None and len(given) != ncol:
        logger.warning(
            "%s: header names %d columns but rows have %d; unnamed ones are column_<k>",
            path,
            len(given),
            ncol,
        )
    names: list[str] = []
    for k in range(ncol):
        name = given[k] if k < len(given) else ""
        if not name or name in names:
            name = f"column_{k + 1}"
        names.append(name)
    return names


def write(
    path: Path, xyz: np.ndarray, fields: dict[str, np.ndarray], meta: dict[str, Any], *, ext: str
) -> None:
    """Write ``xyz`` (N, 3) metres and ``fields`` as text rows (coordinates to 1 micrometre)."""
    source = meta.get("xyz") if isinstance(meta.get("xyz"), dict) else None
    if ext == ".csv":
        sep = ","
    elif source is not None:
        sep = source.get("separator") or " "
    else:
        sep = " "
    if source is not None:
        auto = all(_AUTO_NAME.fullmatch(name) for name in fields)
        with_header = bool(source.get("header")) or (bool(fields) and not auto)
        style = source.get("style", "")
    else:
        with_header = bool(fields)
        style = "" if ext == ".csv" else "//"
    columns = [xyz[:, 0], xyz[:, 1], xyz[:, 2], *fields.values()]
    fmt = [_COORD_FORMAT] * 3 + [text_format(v) for v in fields.values()]
    with open(path, "w", encoding="utf-8", newline="\n") as stream:
        if with_header:
            xyz_names = (source or {}).get("xyz_names") or (
                ["X", "Y", "Z"] if style == "//" else ["x", "y", "z"]
            )
            names = [*xyz_names, *(safe_name(n) if sep == " " else n for n in fields)]
            stream.write(style + sep.join(names) + "\n")
        write_table(stream, columns, fmt, sep)
