"""Scalar fields on CloudCompare clouds: write (replacing same-named ones) and look up."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["sf_index", "write_scalar_fields"]


def sf_index(entity: Any, name: str) -> int:
    """Index of scalar field ``name`` on ``entity``, -1 if it has none."""
    idx = entity.getScalarFieldIndexByName(name)
    return -1 if idx is None else int(idx)


def write_scalar_fields(entity: Any, fields: Mapping[str, np.ndarray]) -> dict[str, int]:
    """Add per-point scalar fields to a cloud, replacing fields of the same name.

    Parameters
    ----------
    entity : ccPointCloud
    fields : mapping of str to ndarray, shape (N,)
        Values (any numeric or bool dtype; stored as float32, CloudCompare's ScalarType).

    Returns
    -------
    dict of str to int
        Final index of each written field.

    Raises
    ------
    ValueError
        If a field's length differs from the number of points.
    """
    n = int(entity.size())
    for name, values in fields.items():
        values = np.asarray(values)
        if values.shape != (n,):
            raise ValueError(f"field {name!r} has shape {values.shape}; the cloud has {n} points")
    for name, values in fields.items():
        old = sf_index(entity, name)
        if old >= 0:
            entity.deleteScalarField(old)
        idx = entity.addScalarField(name, np.ascontiguousarray(values, dtype=np.float32))
        sf = entity.getScalarField(int(idx))
        if sf is not None:
            sf.computeMinAndMax()
    return {name: sf_index(entity, name) for name in fields}

