"""Reading CloudCompare clouds: global float64 coordinates and :class:`tunneldef.Cloud`."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from .coords import local_to_global, shift_and_scale, vec3
from .runtime import check_array, entity_name, pycc_module

log = logging.getLogger(__name__)

__all__ = ["read_points", "entity_to_cloud", "point_clouds"]


def read_points(entity: Any) -> np.ndarray:
    """Global float64 coordinates of a ``ccPointCloud``, shape (N, 3), metres.

    Uses the ``points()`` view, copied once into the float64 result. If the view has the
    wrong shape (runtime issues #124/#142/#152) each point is read with ``getPoint(i)``
    instead (a Python loop: slow, but correct).

    Raises
    ------
    BrokenRuntimeError
        If ``points()`` has stride 0 (every row would be point 0).
    """
    n = int(entity.size())
    if n == 0:
        return np.empty((0, 3))
    local = check_array(entity.points(), f"points() of {entity_name(entity)!r}")
    if local.ndim == 1 and local.dtype.names is None and local.size == 3 * n:
        local = local.reshape(n, 3)
    if local.shape != (n, 3):
        log.warning("points() returned shape %s; reading %d points one by one", local.shape, n)
        local = np.array([vec3(entity.getPoint(i)) for i in range(n)], dtype=np.float64)
    shift, scale = shift_and_scale(entity)
    return local_to_global(local, shift, scale)


def entity_to_cloud(entity: Any) -> Any:
    """A :class:`tunneldef.Cloud` (global coordinates) for a ``ccPointCloud``.

    ``meta`` records the entity name, shift and scale. Scalar fields are not copied: the core
    does not need them and they stay on the entity.
    """
    from tunneldef.cloud import Cloud

    shift, scale = shift_and_scale(entity)
    return Cloud(
        read_points(entity),
        {},
        {"name": entity_name(entity), "global_shift": shift.tolist(), "global_scale": scale},
    )


def point_clouds(entities: Sequence[Any]) -> list[Any]:
    """The ``ccPointCloud`` entities of a selection, in the user's selection order."""
    cls = pycc_module().ccPointCloud
    return [e for e in entities if isinstance(e, cls)]
