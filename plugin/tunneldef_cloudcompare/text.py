"""Text for CloudCompare's console: a 4 x 4 matrix, a per-slice table."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["format_matrix", "format_slice_table"]


def format_matrix(transform: np.ndarray) -> str:
    """A 4 x 4 matrix as four lines of numbers, the way CloudCompare prints transforms."""
    t = np.asarray(transform, dtype=np.float64).reshape(4, 4)
    return "\n".join(" ".join(f"{v: .8f}" for v in row) for row in t)


def _record_dict(record: Any) -> dict[str, Any]:
    if dataclasses.is_dataclass(record):
        return {f.name: getattr(record, f.name) for f in dataclasses.fields(record)}
    if isinstance(record, Mapping):
        return dict(record)
    return dict(vars(record))


def format_slice_table(slices: Sequence[Any]) -> str:
    """Per-slice chainage, width and height (m) as a fixed-width text table.

    Takes whichever of the columns ``chainage``/``s``, ``width``, ``height``, ``n_points``,
    ``ok`` each record has (dataclass, mapping or object).
    """
    wanted = [("chainage", "s"), ("width",), ("height",), ("n_points", "points"), ("ok",)]
    rows = [_record_dict(r) for r in slices]
    cols: list[tuple[str, str]] = []
    for alts in wanted:
        key = next((a for a in alts if rows and a in rows[0]), None)
        if key is not None:
            cols.append((alts[0], key))
    header = " ".join(f"{title:>10}" for title, _ in cols)
    lines = [header]
    for row in rows:
        cells = []
        for _, key in cols:
            v = row.get(key)
            if isinstance(v, (bool, np.bool_)):
                cells.append(f"{('yes' if v else 'no'):>10}")
            elif isinstance(v, (int, np.integer)):
                cells.append(f"{int(v):>10d}")
            elif isinstance(v, (float, np.floating)):
                cells.append(f"{float(v):>10.3f}")
            else:
                cells.append(f"{str(v):>10}")
        lines.append(" ".join(cells))
    return "\n".join(lines)
