"""The ``pycc`` module, small call helpers, and the check that this runtime's arrays are sound.

CloudCompare-PythonRuntime builds made with pybind11 < 2.12 against numpy 2 hand out numpy
arrays with stride 0: ``points()`` repeats point 0, writes into ``ccGLMatrix.asArray()`` are
lost and ``ScalarField.toArray()`` repeats one value. The plugin would then compute on, and
write back, wrong data without any error. :func:`check_runtime` builds a known 2-point cloud,
a known matrix and a known scalar field, reads them back, and raises
:class:`BrokenRuntimeError` (a one-line message naming the cause) when they differ.
"""

from __future__ import annotations

import importlib
import logging
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "BrokenRuntimeError",
    "pycc_module",
    "try_call",
    "entity_name",
    "check_array",
    "check_runtime",
    "reset_runtime_check",
]

_FIX = "rebuild CloudCompare-PythonRuntime with pybind11 >= 2.13 (or use numpy < 2 with it)"


class BrokenRuntimeError(RuntimeError):
    """This CloudCompare Python runtime returns wrong arrays; nothing was computed or written."""


def pycc_module() -> Any:
    """The ``pycc`` module (CloudCompare's, or a stand-in registered in ``sys.modules``)."""
    return importlib.import_module("pycc")


def try_call(obj: Any, method: str, *args: Any) -> bool:
    """Call ``obj.method(*args)`` if this runtime has it; False (and a debug log) if not."""
    fn = getattr(obj, method, None)
    if fn is None:
        log.debug("%s has no %s(); skipped", type(obj).__name__, method)
        return False
    fn(*args)
    return True


def entity_name(entity: Any) -> str:
    """An entity's name (``"cloud"`` if it has none)."""
    try:
        return str(entity.getName())
    except AttributeError:
        return "cloud"


def check_array(array: Any, what: str) -> np.ndarray:
    """``array`` as an ndarray; :class:`BrokenRuntimeError` if a dimension of length > 1 has
    stride 0 (the signature of a pybind11 < 2.12 build under numpy 2)."""
    arr = np.asarray(array)
    for length, stride in zip(arr.shape, arr.strides, strict=True):
        if length > 1 and stride == 0:
            raise BrokenRuntimeError(
                f"this CloudCompare Python runtime returns stride-0 numpy arrays ({what} has "
                f"strides {tuple(arr.strides)}): {_FIX}"
            )
    return arr


_CHECKED: list[str] = []


def reset_runtime_check() -> None:
    """Forget an earlier successful :func:`check_runtime` (tests swap runtimes)."""
    _CHECKED.clear()


def check_runtime(pycc: Any = None) -> None:
    """Refuse a runtime whose numpy views are wrong; cheap, done once per process.

    Checks: ``points()`` of a known 2-point cloud (strides and values), a matrix written into
    ``ccGLMatrix.asArray()`` and read back, and a 2-value scalar field read back with
    ``toArray()``.

    Raises
    ------
    BrokenRuntimeError
        With a one-line message naming what came back wrong.
    """
    if _CHECKED:
        return
    pycc = pycc or pycc_module()
    x = np.array([1.0, 4.0], np.float32)
    y = np.array([2.0, 5.0], np.float32)
    z = np.array([3.0, 6.0], np.float32)
    pc = pycc.ccPointCloud(x, y, z)
    pts = check_array(pc.points(), "points() of a 2-point cloud")
    if pts.shape != (2, 3) or not np.array_equal(pts, np.stack([x, y, z], axis=1)):
        raise BrokenRuntimeError(
            f"this CloudCompare Python runtime's points() returned {pts.tolist()} for the cloud "
            f"[[1, 2, 3], [4, 5, 6]]: {_FIX}"
        )
    mat = pycc.ccGLMatrix()
    view = check_array(mat.asArray(), "ccGLMatrix.asArray()")
    known = np.arange(16, dtype=np.float32).reshape(4, 4)
    view[:, :] = known
    back = np.asarray(mat.asArray())
    if not np.array_equal(back, known):
        raise BrokenRuntimeError(
            f"this CloudCompare Python runtime loses writes into ccGLMatrix.asArray() (read back "
            f"{back.ravel()[:4].tolist()}... for 0, 1, 2, 3...): {_FIX}"
        )
    idx = pc.addScalarField("tunneldef runtime check", np.array([7.0, 8.0], np.float32))
    sf = pc.getScalarField(int(idx))
    values = check_array(sf.toArray(), "ScalarField.toArray()")
    if not np.array_equal(values, [7.0, 8.0]):
        raise BrokenRuntimeError(
            f"this CloudCompare Python runtime's ScalarField.toArray() returned "
            f"{values.tolist()} for [7, 8]: {_FIX}"
        )
    _CHECKED.append("ok")
