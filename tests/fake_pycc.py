"""A small stand-in for CloudCompare's ``pycc`` module, for testing the plugin adapter.

It implements exactly the calls the plugin and scripts use, as documented by the
CloudCompare-PythonRuntime bindings (``ccPointCloud``, ``ccScalarField``, ``ccPolyline``,
``ccGLMatrix``, ``ccProgressDialog``, ``ccColorScale``, ``ccColorScalesManager``, ``RunInThread``,
``GetInstance``/``GetCmdLineInstance``, ``PythonPluginInterface``, ``Action``) and nothing
more: an attribute the real module lacks is not here either, and a call the adapter makes that
is missing here fails the tests. It is NOT the real runtime: what passes here was verified
against the documented API only. Behaviour copied from the bindings:

* ``ccPointCloud(x, y, z)`` copies float32 local coordinates; ``points()`` is a read-only
  (N, 3) float32 view; ``getPoint(i)`` returns an object with ``.x .y .z``.
* ``addScalarField(name, values)`` raises RuntimeError if the name exists and ValueError on a
  length mismatch; ``getScalarFieldIndexByName`` gives -1 for a missing name.
* ``getGlobalShift()`` returns a vector with ``.x .y .z``; ``getGlobalScale()`` a float.
* ``ccGLMatrix().asArray()`` is a writable (4, 4) float32 view of column-major storage.

Switches for the known runtime quirks: ``STRIDE0_ARRAYS`` (a runtime built with pybind11 <
2.12 under numpy 2: every array it hands out has stride 0, so ``points()`` repeats point 0,
writes into ``ccGLMatrix.asArray()`` are lost and ``ScalarField.toArray()`` repeats the last
value) and ``SCALE_GETTER_BUG`` (``getGlobalScale`` bound to the setter in some builds).

``tests/test_plugin_runtime_api.py`` checks, inside the real CloudCompare, that every public
name faked here exists there with a compatible signature.
"""

from __future__ import annotations

import types
from typing import Any

import numpy as np

PointCoordinateType = np.float32
ScalarType = np.float32

STRIDE0_ARRAYS = False
SCALE_GETTER_BUG = False


def _stride0(array: np.ndarray, row: int = 0) -> np.ndarray:
    """What a stride-0 runtime hands out: every row (or element) is ``array[row]``."""
    return np.broadcast_to(array[row], array.shape)


class _Vector3d:
    """What ``getGlobalShift()``/``getPoint()`` return (``cccorelib._Vector3d``/``CCVector3``
    in the real runtime, not in ``pycc``): ``.x .y .z``."""

    def __init__(self, x: float = 0.0, y: float = 0.0, z: float = 0.0) -> None:
        self.x, self.y, self.z = float(x), float(y), float(z)


class Rgb:
    def __init__(self, r: int, g: int, b: int) -> None:
        self.r, self.g, self.b = r, g, b


class ccColorScale:  # noqa: N801 - the binding's name
    """``ccColorScale(name, uuid="")``; ``LoadFromXML`` gives a ``ccColorScale.Shared``.

    In the runtime ``Shared`` (``QSharedPointer<ccColorScale>``, what ``setColorScale`` takes
    and ``GetDefaultScale``/``LoadFromXML`` return) is opaque: no methods. The attributes of
    :class:`Shared` here (name, uuid, relative, steps) are for the tests' eyes only; the
    adapter must not use them.
    """

    class Shared:
        def __init__(self, name: str, uuid: str, relative: bool, steps: list) -> None:
            self.name, self.uuid, self.relative, self.steps = name, uuid, relative, steps

    def __init__(self, name: str, uuid: str = "") -> None:
        self.name, self.uuid = name, uuid

    @staticmethod
    def LoadFromXML(filename: str) -> ccColorScale.Shared:  # noqa: N802
        """Parse CloudCompare's colour-scale XML (same layout as ``ccColorScale::saveAsXML``)."""
        import xml.etree.ElementTree as ET

        root = ET.parse(filename).getroot()
        props = root.find("ColorScale/Properties")
        steps = [
            (int(s.get("r")), int(s.get("g")), int(s.get("b")), float(s.get("pos")))
            for s in root.iter("step")
        ]
        return ccColorScale.Shared(
            props.findtext("name"),
            props.findtext("uuid"),
            props.findtext("absolute", "0").strip() == "0",
            steps,
        )


_BWR_STEPS = [(0, 0, 255, 0.0), (255, 255, 255, 0.5), (255, 0, 0, 1.0)]


class ccColorScalesManager:  # noqa: N801
    """Default scales by enum value; ``GetUniqueInstance().addScale`` keyed by UUID."""

    BWR = "BWR"
    BGYR = "BGYR"
    _instance: ccColorScalesManager | None = None

    def __init__(self) -> None:
        self.scales: dict[str, ccColorScale.Shared] = {}

    @staticmethod
    def GetDefaultScale(scale: str = "BGYR") -> ccColorScale.Shared:  # noqa: N802
        steps = _BWR_STEPS if scale == "BWR" else []
        return ccColorScale.Shared(scale, scale, True, steps)

    @staticmethod
    def GetUniqueInstance() -> ccColorScalesManager:  # noqa: N802
        if ccColorScalesManager._instance is None:
            ccColorScalesManager._instance = ccColorScalesManager()
        return ccColorScalesManager._instance

    def addScale(self, scale: ccColorScale.Shared) -> None:  # noqa: N802
        self.scales[scale.uuid] = scale


class ccScalarField:  # noqa: N801
    def __init__(self, name: str, n: int) -> None:
        self._name = name
        self._values = np.zeros(n, dtype=np.float32)
        self._min = self._max = 0.0
        self.color_scale: ccColorScale.Shared | None = None
        self.symmetrical = False
        self.saturation = [None, None]
        self.displayed = [None, None]

    def getName(self) -> str:  # noqa: N802
        return self._name

    def computeMinAndMax(self) -> None:  # noqa: N802
        v = self._values[np.isfinite(self._values)]
        self._min, self._max = (float(v.min()), float(v.max())) if v.size else (0.0, 0.0)

    def getMin(self) -> float:  # noqa: N802
        return self._min

    def getMax(self) -> float:  # noqa: N802
        return self._max

    def toArray(self) -> np.ndarray:  # noqa: N802
        if STRIDE0_ARRAYS and self._values.size:
            return _stride0(self._values, -1)
        return self._values.copy()

    def setColorScale(self, scale: ccColorScale.Shared) -> None:  # noqa: N802
        self.color_scale = scale

    def setSymmetricalScale(self, state: bool) -> None:  # noqa: N802
        self.symmetrical = bool(state)

    def setSaturationStart(self, value: float) -> None:  # noqa: N802
        self.saturation[0] = float(value)

    def setSaturationStop(self, value: float) -> None:  # noqa: N802
        self.saturation[1] = float(value)

    def setMinDisplayed(self, value: float) -> None:  # noqa: N802
        self.displayed[0] = float(value)

    def setMaxDisplayed(self, value: float) -> None:  # noqa: N802
        self.displayed[1] = float(value)


class ccHObject:  # noqa: N801
    def __init__(self, name: str = "") -> None:
        self._name = name
        self._shift = np.zeros(3)
        self._scale = 1.0

    def getName(self) -> str:  # noqa: N802
        return self._name

    def setName(self, name: str) -> None:  # noqa: N802
        self._name = str(name)


class ccShiftedObject(ccHObject):  # noqa: N801
    """Entities with a global shift and scale (clouds, polylines)."""

    def getGlobalShift(self) -> _Vector3d:  # noqa: N802
        return _Vector3d(*self._shift)

    def setGlobalShift(self, x_: float, y: float, z: float) -> None:  # noqa: N802
        self._shift = np.array([x_, y, z], dtype=np.float64)

    def setGlobalScale(self, scale: float) -> None:  # noqa: N802
        self._scale = float(scale)

    def getGlobalScale(self, *args: Any) -> Any:  # noqa: N802
        if SCALE_GETTER_BUG:  # bound to the setter: needs an argument, returns None
            if len(args) != 1:
                raise TypeError("getGlobalScale(): incompatible function arguments")
            self._scale = float(args[0])
            return None
        if args:
            raise TypeError("getGlobalScale() takes no arguments")
        return self._scale

    def isShifted(self) -> bool:  # noqa: N802
        return bool(np.any(self._shift != 0) or self._scale != 1.0)

    def copyGlobalShiftAndScale(self, s: Any) -> None:  # noqa: N802
        self._shift = s._shift.copy()
        self._scale = s._scale


class ccGLMatrix:  # noqa: N801
    def __init__(self) -> None:
        self._data = np.eye(4, dtype=np.float32).ravel(order="F").copy()

    def asArray(self) -> np.ndarray:  # noqa: N802
        if STRIDE0_ARRAYS:  # a writable array whose writes never reach the matrix
            return np.repeat(self._data.reshape(4, 4)[:1], 4, axis=0)
        return self._data.reshape(4, 4)  # row i of this view = column i of the matrix

    def matrix(self) -> np.ndarray:
        """Test helper (not in the binding): the matrix in row-major form."""
        return self._data.reshape(4, 4).T.astype(np.float64)


class ccPointCloud(ccShiftedObject):  # noqa: N801
    def __init__(self, *args: Any) -> None:
        if len(args) == 3:
            super().__init__("")
            self._xyz = np.stack([np.asarray(a, dtype=np.float32) for a in args], axis=1)
        else:
            super().__init__(args[0] if args else "")
            self._xyz = np.empty((0, 3), dtype=np.float32)
        self._sfs: list[ccScalarField] = []
        self.displayed_sf = -1
        self.sf_shown = False
        self.sf_scale_shown = False

    def size(self) -> int:
        return int(self._xyz.shape[0])

    def __len__(self) -> int:
        return self.size()

    def points(self) -> np.ndarray:
        view = self._xyz.view()
        if STRIDE0_ARRAYS and len(view):
            view = _stride0(self._xyz)
        view = view.view()
        view.flags.writeable = False
        return view

    def getPoint(self, index: int) -> _Vector3d:  # noqa: N802
        return _Vector3d(*self._xyz[int(index)])

    def addScalarField(self, name: str, values: Any = None) -> int:  # noqa: N802
        if self.getScalarFieldIndexByName(name) >= 0:
            raise RuntimeError("Failed to add scalar field")
        sf = ccScalarField(name, self.size())
        if values is not None:
            v = np.asarray(values, dtype=ScalarType)
            if v.size != self.size():
                raise ValueError("value must have the same len as the point cloud size")
            sf._values[:] = v
        self._sfs.append(sf)
        return len(self._sfs) - 1

    def getNumberOfScalarFields(self) -> int:  # noqa: N802
        return len(self._sfs)

    def getScalarField(self, index: int) -> ccScalarField | None:  # noqa: N802
        return self._sfs[index] if 0 <= index < len(self._sfs) else None

    def getScalarFieldName(self, index: int) -> str:  # noqa: N802
        return self._sfs[index].getName()

    def getScalarFieldIndexByName(self, name: str) -> int:  # noqa: N802
        for i, sf in enumerate(self._sfs):
            if sf.getName() == name:
                return i
        return -1

    def deleteScalarField(self, index: int) -> None:  # noqa: N802
        del self._sfs[index]
        if self.displayed_sf == index:
            self.displayed_sf = -1

    def setCurrentDisplayedScalarField(self, index: int) -> None:  # noqa: N802
        self.displayed_sf = int(index)

    def getCurrentDisplayedScalarFieldIndex(self) -> int:  # noqa: N802
        return self.displayed_sf

    def showSF(self, state: bool) -> None:  # noqa: N802
        self.sf_shown = bool(state)

    def showSFColorsScale(self, state: bool) -> None:  # noqa: N802
        self.sf_scale_shown = bool(state)

    def applyGLTransformation_recursive(self, trans: ccGLMatrix) -> None:  # noqa: N802
        m = trans.matrix()
        xyz = self._xyz.astype(np.float64) @ m[:3, :3].T + m[:3, 3]
        self._xyz = xyz.astype(np.float32)


class ccPolyline(ccShiftedObject):  # noqa: N801
    def __init__(self, associatedCloud: ccPointCloud) -> None:  # noqa: N803
        super().__init__("")
        self.cloud = associatedCloud
        self.indices: list[int] = []
        self.closed = True
        self.colour: Rgb | None = None
        self.colours_shown = False

    def addPointIndex(self, firstIndex: int, lastIndex: int | None = None) -> None:  # noqa: N802, N803
        if lastIndex is None:
            self.indices.append(int(firstIndex))
        else:
            self.indices.extend(range(int(firstIndex), int(lastIndex)))

    def getAssociatedCloud(self) -> ccPointCloud:  # noqa: N802
        return self.cloud

    def size(self) -> int:
        return len(self.indices)

    def setClosed(self, state: bool) -> None:  # noqa: N802
        self.closed = bool(state)

    def setColor(self, col: Rgb) -> None:  # noqa: N802
        self.colour = col

    def showColors(self, state: bool) -> None:  # noqa: N802
        self.colours_shown = bool(state)


class ccProgressDialog:  # noqa: N801
    def __init__(self, cancelButton: bool = False) -> None:  # noqa: N803
        self.cancel_button = cancelButton
        self.values: list[float] = []
        self.started = self.stopped = False
        self.cancel_after: int | None = None  # test switch: press Cancel after n updates
        self.title = self.info = ""
        self.visible = False
        self.auto_closed = 0  # times the value reached the maximum and the dialog hid itself

    def start(self) -> None:
        self.started = self.visible = True

    def stop(self) -> None:
        self.stopped, self.visible = True, False

    def setMethodTitle(self, methodTitle: str) -> None:  # noqa: N802, N803
        self.title = methodTitle

    def setInfo(self, infoStr: str) -> None:  # noqa: N802, N803
        self.info = infoStr

    def update(self, percent: float) -> None:
        """As the real one: a QProgressDialog on 0-100 with autoClose and autoReset, so the
        maximum hides it (and clears its cancellation flag)."""
        self.values.append(float(percent))
        if int(percent) >= 100:
            self.visible = False
            self.auto_closed += 1

    def isCancelRequested(self) -> bool:  # noqa: N802
        return self.cancel_after is not None and len(self.values) >= self.cancel_after


def ProcessEvents() -> None:  # noqa: N802
    """The real one runs ``QCoreApplication::processEvents()``; counted here."""
    global PROCESSED_EVENTS
    PROCESSED_EVENTS += 1


PROCESSED_EVENTS = 0


def RunInThread(callable: Any, *args: Any, **kwargs: Any) -> Any:  # noqa: N802, A002
    """The real one runs ``func`` in a QtConcurrent thread and waits; same result here."""
    import threading

    out: dict[str, Any] = {}

    def run() -> None:
        out["value"] = callable(*args, **kwargs)

    t = threading.Thread(target=run)
    t.start()
    t.join()
    return out.get("value")


class ccPythonInstance:  # noqa: N801
    def __init__(self) -> None:
        self.selected: list[Any] = []
        self.db: list[Any] = []
        self.frozen: list[bool] = []
        self.redraws = 0

    def getSelectedEntities(self) -> list[Any]:  # noqa: N802
        return list(self.selected)

    def haveSelection(self) -> bool:  # noqa: N802
        return bool(self.selected)

    def addToDB(self, obj: Any, *args: Any, **kwargs: Any) -> None:  # noqa: N802
        self.db.append(obj)

    def updateUI(self) -> None:  # noqa: N802
        pass

    def redrawAll(self, only2D: bool = False) -> None:  # noqa: N802, N803
        self.redraws += 1

    def freezeUI(self, state: bool) -> None:  # noqa: N802
        self.frozen.append(bool(state))


class CLCloudDesc:
    def __init__(self, pc: ccPointCloud, path: str = "", basename: str = "") -> None:
        self.pc = pc
        self.path = path
        self.basename = basename


class ccCommandLineInterface:  # noqa: N801
    def __init__(self, clouds: list[CLCloudDesc] | None = None) -> None:
        self._clouds = clouds or []

    def clouds(self) -> list[CLCloudDesc]:
        return self._clouds


_GUI: ccPythonInstance | None = ccPythonInstance()
_CMDLINE: ccCommandLineInterface | None = None


def GetInstance() -> Any:  # noqa: N802
    return _GUI if _GUI is not None else _CMDLINE


def GetGUIInstance() -> ccPythonInstance | None:  # noqa: N802
    return _GUI


def GetCmdLineInstance() -> ccCommandLineInterface | None:  # noqa: N802
    return _CMDLINE


class PythonPluginInterface:
    def __init__(self) -> None:
        pass


class Action:
    def __init__(self, name: str, target: Any, icon: Any = None) -> None:
        self.name, self.target, self.icon = name, target, icon


class ccLog:  # noqa: N801
    messages: list[str] = []

    @staticmethod
    def Print(message: str) -> None:  # noqa: N802
        ccLog.messages.append(str(message))


def install() -> types.ModuleType:
    """Test helper: reset the module state and return it (to put into ``sys.modules``)."""
    import sys

    mod = sys.modules[__name__]
    mod.STRIDE0_ARRAYS = False
    mod.SCALE_GETTER_BUG = False
    mod.PROCESSED_EVENTS = 0
    from tunneldef_cloudcompare.runtime import reset_runtime_check

    reset_runtime_check()
    mod._GUI = ccPythonInstance()
    mod._CMDLINE = None
    mod.ccColorScalesManager._instance = None
    return mod
