"""Helpers for the scripts that run inside CloudCompare (``script_actions.py``,
``gui_harness.py``); imported there as a top-level module (their folder is on the path)."""

from __future__ import annotations

import numpy as np


def sf_array(entity, name: str) -> np.ndarray | None:
    """A scalar field's values, float64, or None if the entity has no such field."""
    idx = entity.getScalarFieldIndexByName(name)
    if idx is None or int(idx) < 0:
        return None
    return np.asarray(entity.getScalarField(int(idx)).toArray(), dtype=np.float64)
