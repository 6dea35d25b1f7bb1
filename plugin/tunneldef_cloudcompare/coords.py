"""CloudCompare's local coordinates and per-entity global shift/scale <-> survey coordinates.

CloudCompare keeps float32 *local* coordinates and a per-entity global shift and scale;
``global = local / scale - shift`` (:func:`local_to_global`) and back (:func:`global_to_local`).
The core always sees float64 global coordinates.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "local_to_global",
    "global_to_local",
    "local_transform",
    "shift_and_scale",
    "copy_shift_and_scale",
]

#: Largest local coordinate (m) float32 holds to ~1 cm; beyond it a global shift is needed.
_FLOAT32_SAFE = 1.0e5


def local_to_global(local: np.ndarray, shift: np.ndarray, scale: float) -> np.ndarray:
    """Global (survey) coordinates from CloudCompare's local ones.

    Parameters
    ----------
    local : ndarray, shape (N, 3)
        Local coordinates as stored by CloudCompare (float32), metres x scale.
    shift : ndarray, shape (3,)
        The entity's global shift (``getGlobalShift()``), metres.
    scale : float
        The entity's global scale (``getGlobalScale()``), usually 1.

    Returns
    -------
    ndarray, shape (N, 3), float64
        ``local / scale - shift``.
    """
    out = np.array(local, dtype=np.float64).reshape(-1, 3)  # the one float64 copy
    if float(scale) != 1.0:
        out /= float(scale)
    out -= np.asarray(shift, dtype=np.float64)
    return out


def global_to_local(xyz: np.ndarray, shift: np.ndarray, scale: float) -> np.ndarray:
    """CloudCompare local coordinates (float32) for global ones: ``(xyz + shift) * scale``.

    ``xyz`` (N, 3) with ``shift`` (3,), or one column (N,) with its scalar shift.

    Logs a warning when a local coordinate exceeds 1e5 m (float32 then loses centimetres):
    give the entity a global shift.
    """
    local = np.asarray(xyz, dtype=np.float64) + np.asarray(shift, dtype=np.float64)
    if float(scale) != 1.0:
        local *= float(scale)
    if local.size and np.abs(local).max() > _FLOAT32_SAFE:
        log.warning(
            "local coordinates up to %.3g m lose precision in float32; use a global shift",
            float(np.abs(local).max()),
        )
    return local.astype(np.float32)


def local_transform(transform: np.ndarray, shift: np.ndarray, scale: float) -> np.ndarray:
    """The 4 x 4 rigid transform in an entity's local coordinates.

    ``transform`` maps global coordinates (``g = l / scale - shift``); the result ``L`` maps
    local ones so that the moved entity keeps its shift and scale:
    ``L = [R, scale * (t + shift - R @ shift)]``.
    """
    t = np.asarray(transform, dtype=np.float64)
    s = np.asarray(shift, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = t[:3, :3]
    out[:3, 3] = float(scale) * (t[:3, 3] + s - t[:3, :3] @ s)
    return out


def vec3(v: Any) -> np.ndarray:
    """A ``CCVector3``-like object (``.x .y .z``) or a sequence as a float64 (3,) array."""
    if hasattr(v, "x"):
        return np.array([float(v.x), float(v.y), float(v.z)])
    return np.asarray(v, dtype=np.float64).reshape(3)


def shift_and_scale(entity: Any) -> tuple[np.ndarray, float]:
    """``(shift (3,), scale)`` of an entity.

    Some runtime builds bound ``getGlobalScale`` to the setter (it then needs an argument and
    returns None): the scale is then taken as 1 and a warning logged.
    """
    shift = vec3(entity.getGlobalShift()) if hasattr(entity, "getGlobalShift") else np.zeros(3)
    scale = 1.0
    try:
        value = entity.getGlobalScale()
        if value is not None:
            scale = float(value)
    except (TypeError, AttributeError):
        log.warning("this runtime cannot read the global scale of %r; assuming 1", entity)
    if not np.isfinite(scale) or scale <= 0:
        log.warning("invalid global scale %r; assuming 1", scale)
        scale = 1.0
    return shift, scale


def copy_shift_and_scale(dst: Any, src: Any) -> None:
    """Give ``dst`` the global shift and scale of ``src`` (``copyGlobalShiftAndScale`` where
    the runtime has it, else the setters)."""
    if hasattr(dst, "copyGlobalShiftAndScale"):
        dst.copyGlobalShiftAndScale(src)
        return
    shift, scale = shift_and_scale(src)
    dst.setGlobalShift(float(shift[0]), float(shift[1]), float(shift[2]))
    dst.setGlobalScale(float(scale))

