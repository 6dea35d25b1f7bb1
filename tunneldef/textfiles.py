"""Text outputs (JSON summaries, CSV tables), each written atomically; JSON clean-up."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_text_atomic", "jsonable", "to_json", "write_json", "write_csv"]


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename.

    An existing file at ``path`` is replaced only once the new content is complete.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def jsonable(obj: Any) -> Any:
    """Plain JSON values, recursively: numpy arrays and scalars become lists and numbers,
    tuples lists, NaN and infinities None (not valid JSON)."""
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def to_json(obj: Any) -> str:
    """Indented, strictly valid JSON text: numpy arrays and scalars become lists and numbers,
    NaN and infinities become null."""
    return json.dumps(jsonable(obj), indent=2, default=_default, allow_nan=False) + "\n"


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as JSON, atomically."""
    return write_text_atomic(path, to_json(obj))


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.6g}"
    s = str(v)
    return '"' + s.replace('"', '""') + '"' if ("," in s or '"' in s or "\n" in s) else s


def write_csv(path: str | Path, rows: Sequence[dict[str, Any]]) -> Path:
    """Write dict rows as CSV (header from the first row's keys), atomically."""
    if not rows:
        raise ValueError("no rows to write")
    keys = list(rows[0].keys())
    lines = [",".join(keys)] + [",".join(_cell(r.get(k)) for k in keys) for r in rows]
    return write_text_atomic(path, "\n".join(lines) + "\n")
