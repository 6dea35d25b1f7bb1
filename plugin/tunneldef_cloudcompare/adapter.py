"""CloudCompare entities <-> numpy arrays and :class:`tunneldef.Cloud`; no algorithm code.

Everything CloudCompare-specific that the plugin and the scripts share lives here:

* coordinates: CloudCompare keeps float32 *local* coordinates and a per-entity global shift
  and scale; ``global = local / scale - shift`` (:func:`local_to_global`) and back
  (:func:`global_to_local`). The core always sees float64 global coordinates.
* reading points with the ``points()`` fallback (some runtime builds return N identical rows:
  then each point is read with ``getPoint(i)``), :func:`read_points`.
* writing scalar fields, replacing same-named ones (:func:`write_scalar_fields`), and showing
  ``deformation`` on a Red>White>Blue scale centred on 0, red = into the tunnel
  (:func:`red_white_blue_scale`, :func:`show_diverging`).
* new entities (clouds, polylines) that inherit the shift/scale of an existing one.
* the three jobs as three steps each: read (main thread) -> compute (worker thread, pure
  numpy, never touches an entity) -> apply (main thread: fields, new entities).

The module imports neither ``pycc`` nor Qt at import time. Functions that create entities get
the ``pycc`` module lazily from ``sys.modules``/import, so a stand-in module can be injected in
tests. Only the calls listed in the project's notes on the runtime are used.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "DEFORMATION_FIELDS",
    "OPTIONAL_FIELDS",
    "DetectParams",
    "Outcome",
    "ProgressBridge",
    "config_from_params",
    "local_to_global",
    "global_to_local",
    "local_transform",
    "shift_and_scale",
    "copy_shift_and_scale",
    "read_points",
    "entity_to_cloud",
    "point_clouds",
    "write_scalar_fields",
    "symmetric_limit",
    "SCALE_NAME",
    "SCALE_UUID",
    "color_scale_xml",
    "red_white_blue_scale",
    "show_diverging",
    "make_point_cloud",
    "make_polyline",
    "move_entity",
    "run_guarded",
    "compute_detect",
    "apply_detect",
    "compute_centerline",
    "apply_centerline",
    "compute_register",
    "apply_register",
    "format_matrix",
    "format_slice_table",
    "result_fields",
    "DetectEntities",
]

#: Fields every detection writes onto the compared cloud (DESIGN.md output contract).
DEFORMATION_FIELDS = (
    "deformation",
    "deformation_horizontal",
    "deformation_vertical",
    "chainage",
    "danger",
)
#: Fields written too when the estimator provides them (significance, classes).
OPTIONAL_FIELDS = ("significant", "lod95", "shell", "surface", "class")

#: Largest local coordinate (m) float32 holds to ~1 cm; beyond it a global shift is needed.
_FLOAT32_SAFE = 1.0e5

_CENTERLINE_COLOURS = {"reference": (0, 160, 0), "compared": (255, 140, 0)}


def _pycc() -> Any:
    """The ``pycc`` module (CloudCompare's, or a stand-in registered in ``sys.modules``)."""
    return importlib.import_module("pycc")


# --------------------------------------------------------------------------- parameters


def _config_default(section: str, name: str) -> Any:
    """A default of :class:`tunneldef.config.Config` (imported only when needed)."""
    from tunneldef.config import Config

    return getattr(getattr(Config(), section), name)


@dataclass(frozen=True)
class DetectParams:
    """What the "Detect deformation" dialog asks.

    Attributes
    ----------
    swap : bool
        False: the first selected cloud is the reference (earlier epoch), the second the
        compared one; True: the other way round.
    threshold : float
        Danger threshold on |deformation|, metres (``Config.danger.threshold``).
    k : int
        Nearest neighbours of the ``knn`` estimator only (``Config.deformation.k``, paper
        §4.3); ``robust`` ignores it.
    method : str
        Deformation estimator, ``"robust"`` (local surface, per-point level of detection) or
        ``"knn"`` (the paper's KNN centroid).

    Every default is the :class:`tunneldef.config.Config` default.
    move_original : bool
        Also move the original compared cloud into the reference frame (default: leave it).
    """

    swap: bool = False
    threshold: float = field(default_factory=lambda: float(_config_default("danger", "threshold")))
    k: int = field(default_factory=lambda: int(_config_default("deformation", "k")))
    method: str = field(default_factory=lambda: str(_config_default("deformation", "method")))
    move_original: bool = False

    @classmethod
    def from_config(cls, config: Any = None, **overrides: Any) -> DetectParams:
        """Defaults taken from a :class:`tunneldef.config.Config` (its defaults if None)."""
        if config is None:
            from tunneldef.config import Config

            config = Config()
        base = cls(
            threshold=float(config.danger.threshold),
            k=int(config.deformation.k),
            method=str(config.deformation.method),
        )
        return dataclasses.replace(base, **overrides)


def config_from_params(params: DetectParams, base: Any = None) -> Any:
    """The :class:`tunneldef.config.Config` for a run: ``base`` with the dialog's values."""
    if base is None:
        from tunneldef.config import Config

        base = Config()
    return base.replace(
        danger={"threshold": float(params.threshold)},
        deformation={"k": int(params.k), "method": str(params.method)},
    )


# --------------------------------------------------------------------------- coordinates


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
    local = np.asarray(local, dtype=np.float64).reshape(-1, 3)
    return local / float(scale) - np.asarray(shift, dtype=np.float64)


def global_to_local(xyz: np.ndarray, shift: np.ndarray, scale: float) -> np.ndarray:
    """CloudCompare local coordinates (float32) for global ones: ``(xyz + shift) * scale``.

    Logs a warning when a local coordinate exceeds 1e5 m (float32 then loses centimetres):
    give the entity a global shift.
    """
    local = (np.asarray(xyz, dtype=np.float64) + np.asarray(shift, dtype=np.float64)) * float(scale)
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


def _vec3(v: Any) -> np.ndarray:
    if hasattr(v, "x"):
        return np.array([float(v.x), float(v.y), float(v.z)])
    return np.asarray(v, dtype=np.float64).reshape(3)


def shift_and_scale(entity: Any) -> tuple[np.ndarray, float]:
    """``(shift (3,), scale)`` of an entity.

    Some runtime builds bound ``getGlobalScale`` to the setter (it then needs an argument and
    returns None): the scale is then taken as 1 and a warning logged.
    """
    shift = _vec3(entity.getGlobalShift()) if hasattr(entity, "getGlobalShift") else np.zeros(3)
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


# --------------------------------------------------------------------------- reading


def _points_look_broken(local: np.ndarray, n: int) -> bool:
    """``points()`` of some builds gives a wrong shape or N copies of one row."""
    if local.shape != (n, 3):
        return True
    return n > 1 and bool(np.all(local == local[0]))


def read_points(entity: Any) -> np.ndarray:
    """Global float64 coordinates of a ``ccPointCloud``, shape (N, 3), metres.

    Uses the ``points()`` view; if it is broken (all rows equal, runtime issues #124/#142/#152)
    each point is read with ``getPoint(i)`` instead (a Python loop: slow, but correct).
    """
    n = int(entity.size())
    if n == 0:
        return np.empty((0, 3))
    local = np.asarray(entity.points())
    if local.ndim == 1 and local.dtype.names is None and local.size == 3 * n:
        local = local.reshape(n, 3)
    if _points_look_broken(local, n):
        log.warning("points() returned unusable rows; reading %d points one by one", n)
        local = np.array([_vec3(entity.getPoint(i)) for i in range(n)], dtype=np.float64)
    shift, scale = shift_and_scale(entity)
    return local_to_global(local, shift, scale)


def _name(entity: Any) -> str:
    try:
        return str(entity.getName())
    except AttributeError:
        return "cloud"


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
        {"name": _name(entity), "global_shift": shift.tolist(), "global_scale": scale},
    )


def point_clouds(entities: Sequence[Any]) -> list[Any]:
    """The ``ccPointCloud`` entities of a selection, in the user's selection order."""
    cls = _pycc().ccPointCloud
    return [e for e in entities if isinstance(e, cls)]


# --------------------------------------------------------------------------- scalar fields


def _sf_index(entity: Any, name: str) -> int:
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
        old = _sf_index(entity, name)
        if old >= 0:
            entity.deleteScalarField(old)
        idx = entity.addScalarField(name, np.ascontiguousarray(values, dtype=np.float32))
        sf = entity.getScalarField(int(idx))
        if sf is not None:
            sf.computeMinAndMax()
    return {name: _sf_index(entity, name) for name in fields}


def symmetric_limit(
    values: np.ndarray,
    *,
    threshold: float = 0.0,
    percentile: float = 98.0,
) -> float:
    """Half-width of a colour scale centred on 0, metres.

    The ``percentile`` of |values| (so a few outliers do not wash out the colours), at least
    ``threshold`` (so the danger level is always inside the scale) and at least 1 mm.
    """
    v = np.abs(np.asarray(values, dtype=np.float64))
    v = v[np.isfinite(v)]
    lim = float(np.percentile(v, percentile)) if v.size else 0.0
    return max(lim, float(threshold), 1e-3)


def _try(obj: Any, method: str, *args: Any) -> bool:
    """Call ``obj.method(*args)`` if this runtime has it; False (and a debug log) if not."""
    fn = getattr(obj, method, None)
    if fn is None:
        log.debug("%s has no %s(); skipped", type(obj).__name__, method)
        return False
    fn(*args)
    return True


#: Name and fixed identity of the plugin's colour scale (a re-run replaces it, never duplicates).
SCALE_NAME = "tunneldef deformation (red = into the tunnel)"
SCALE_UUID = "{5b7c2f4e-1d0a-4f3e-9a61-7e2d8c3b9f02}"

#: What :func:`show_diverging` could set up (the plugin prints the matching legend).
SCALE_RED_IN = "red-white-blue"
SCALE_BLUE_IN = "blue-white-red"
SCALE_DEFAULT = "default"


def color_scale_xml(*, name: str = SCALE_NAME, uuid: str = SCALE_UUID) -> str:
    """CloudCompare colour-scale XML: a *relative* Red>White>Blue scale.

    Red at the low end (negative deformation: the surface moved into the tunnel), white in the
    middle, blue at the high end (outward). Relative, so that CloudCompare's symmetrical-scale
    and saturation settings centre it on 0 (an absolute scale would switch them off).
    """
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<CloudCompare>
    <ColorScale version="1">
        <Properties>
            <name>{name}</name>
            <uuid>{uuid}</uuid>
            <absolute>0</absolute>
        </Properties>
        <Data>
            <step r="255" g="0" b="0" pos="0"/>
            <step r="255" g="255" b="255" pos="0.5"/>
            <step r="0" g="0" b="255" pos="1"/>
        </Data>
    </ColorScale>
</CloudCompare>
"""


def red_white_blue_scale() -> Any:
    """The plugin's Red>White>Blue colour scale, or None if this runtime cannot build one.

    The runtime binds ``ccColorScale.Shared`` (what ``ccScalarField.setColorScale`` takes) as
    an opaque type: a scale built step by step in Python cannot be handed to a scalar field,
    but ``ccColorScale.LoadFromXML`` returns one. The XML (:func:`color_scale_xml`) is written
    to a temporary file and loaded; the scale is also registered with
    ``ccColorScalesManager.GetUniqueInstance().addScale`` (same UUID every time, so a re-run
    replaces it) so that it is listed in the scalar field's properties.
    """
    pycc = _pycc()
    load = getattr(getattr(pycc, "ccColorScale", None), "LoadFromXML", None)
    if load is None:
        log.info("this runtime has no ccColorScale.LoadFromXML; using the built-in scale")
        return None
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "tunneldef_deformation_scale.xml")
            with open(path, "w", encoding="utf-8") as fh:
                fh.write(color_scale_xml())
            scale = load(path)
    except Exception as exc:  # noqa: BLE001 - any runtime failure: fall back to built-in
        log.warning("could not build the Red>White>Blue scale (%s); using the built-in one", exc)
        return None
    if scale is None:
        return None
    manager = getattr(pycc, "ccColorScalesManager", None)
    if manager is not None and hasattr(manager, "GetUniqueInstance"):
        try:
            _try(manager.GetUniqueInstance(), "addScale", scale)
        except Exception as exc:  # noqa: BLE001 - listing the scale is a convenience only
            log.debug("addScale failed: %s", exc)
    return scale


def show_diverging(entity: Any, name: str, *, limit: float, scale: Any = None) -> str:
    """Display scalar field ``name`` on a diverging scale centred on 0.

    With ``scale`` (from :func:`red_white_blue_scale`): negative values (surface moved into
    the tunnel) red, white at 0, positive blue, the project's convention. Without it,
    CloudCompare's built-in Blue>White>Red scale (colours the other way round). Either way
    ``setSymmetricalScale(True)`` and saturation 0..``limit`` on |value|, so colours saturate
    at ``±limit`` metres. The display range is left at the field's min..max: CloudCompare
    hides values outside it, and the largest changes must stay visible. Each call is skipped
    if the runtime lacks it.

    Returns
    -------
    str
        ``"red-white-blue"`` (``scale`` set), ``"blue-white-red"`` (built-in scale set) or
        ``"default"`` (no scale could be set; CloudCompare's default scale shows).
    """
    pycc = _pycc()
    idx = _sf_index(entity, name)
    if idx < 0:
        raise ValueError(f"the cloud has no scalar field {name!r}")
    entity.setCurrentDisplayedScalarField(idx)
    sf = entity.getScalarField(idx)
    sf.computeMinAndMax()
    shown = SCALE_DEFAULT
    if scale is not None and _try(sf, "setColorScale", scale):
        shown = SCALE_RED_IN
    else:
        manager = getattr(pycc, "ccColorScalesManager", None)
        if manager is not None and hasattr(manager, "BWR"):
            if _try(sf, "setColorScale", manager.GetDefaultScale(manager.BWR)):
                shown = SCALE_BLUE_IN
    _try(sf, "setSymmetricalScale", True)
    _try(sf, "setSaturationStart", 0.0)
    _try(sf, "setSaturationStop", float(limit))
    entity.showSF(True)
    _try(entity, "showSFColorsScale", True)
    return shown


# --------------------------------------------------------------------------- new entities


def make_point_cloud(
    xyz: np.ndarray,
    *,
    like: Any = None,
    name: str = "cloud",
    fields: Mapping[str, np.ndarray] | None = None,
) -> Any:
    """A new ``ccPointCloud`` holding global coordinates ``xyz`` (N, 3), metres.

    With ``like`` the new cloud gets that entity's global shift and scale (so survey
    coordinates keep their precision); ``fields`` are written as scalar fields.
    """
    pycc = _pycc()
    shift, scale = shift_and_scale(like) if like is not None else (np.zeros(3), 1.0)
    local = global_to_local(xyz, shift, scale)
    pc = pycc.ccPointCloud(
        np.ascontiguousarray(local[:, 0]),
        np.ascontiguousarray(local[:, 1]),
        np.ascontiguousarray(local[:, 2]),
    )
    if like is not None:
        copy_shift_and_scale(pc, like)
    pc.setName(name)
    if fields:
        write_scalar_fields(pc, fields)
    return pc


def make_polyline(
    points: np.ndarray,
    *,
    like: Any = None,
    name: str = "centreline",
    colour: tuple[int, int, int] | None = None,
) -> tuple[Any, Any]:
    """An open ``ccPolyline`` through ``points`` (M, 3), global metres.

    Returns ``(polyline, vertices)``. The runtime exposes no ``addChild``: the caller must
    keep a Python reference to ``vertices`` for as long as the polyline lives (as the
    runtime's own polyline example does); only the polyline goes into the DB tree.
    """
    pycc = _pycc()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    vertices = make_point_cloud(pts, like=like, name=f"{name} vertices")
    poly = pycc.ccPolyline(vertices)
    poly.addPointIndex(0, int(len(pts)))
    _try(poly, "setClosed", False)
    if like is not None:
        copy_shift_and_scale(poly, like)
    poly.setName(name)
    if colour is not None and hasattr(pycc, "Rgb"):
        _try(poly, "setColor", pycc.Rgb(*colour))
        _try(poly, "showColors", True)
    return poly, vertices


def move_entity(entity: Any, transform: np.ndarray) -> None:
    """Apply a rigid global-coordinate transform to an entity's points in place.

    Uses ``ccGLMatrix`` (column-major storage, its ``asArray()`` view is the transpose) and
    ``applyGLTransformation_recursive``; the entity keeps its shift and scale.
    """
    pycc = _pycc()
    shift, scale = shift_and_scale(entity)
    lt = local_transform(transform, shift, scale)
    mat = pycc.ccGLMatrix()
    mat.asArray()[:, :] = lt.T.astype(np.float32)
    entity.applyGLTransformation_recursive(mat)


# --------------------------------------------------------------------------- threading


class ProgressBridge:
    """The core's ``progress(stage, fraction)`` callback, fed to a CloudCompare progress dialog.

    Runs in the worker thread, so it only calls the dialog's thread-safe ``update(percent)``
    and ``isCancelRequested()``; it raises :class:`tunneldef.progress.Cancelled` when the user
    pressed Cancel (or ``cancel()`` was called). Stage names are kept in ``stages`` for the
    log (setting the dialog's label from a worker thread is not safe).
    """

    def __init__(self, dialog: Any = None) -> None:
        self.dialog = dialog
        self.stages: list[str] = []
        self.last_fraction = 0.0
        self._cancelled = False

    def cancel(self) -> None:
        """Request cancellation (as the dialog's Cancel button does)."""
        self._cancelled = True

    @property
    def cancelled(self) -> bool:
        if self._cancelled:
            return True
        dlg = self.dialog
        return bool(dlg is not None and dlg.isCancelRequested())

    def __call__(self, stage: str, fraction: float) -> None:
        from tunneldef.progress import Cancelled

        if self.cancelled:
            raise Cancelled(f"cancelled during {stage!r}")
        if not self.stages or self.stages[-1] != stage:
            self.stages.append(stage)
        self.last_fraction = float(fraction)
        if self.dialog is not None:
            self.dialog.update(float(np.clip(100.0 * fraction, 0.0, 100.0)))


@dataclass
class Outcome:
    """What a worker-thread job gave: a value, or the exception it raised (never raised
    across the thread boundary)."""

    value: Any = None
    error: BaseException | None = None

    @property
    def cancelled(self) -> bool:
        from tunneldef.progress import Cancelled

        return isinstance(self.error, Cancelled)

    @property
    def ok(self) -> bool:
        return self.error is None

    def unwrap(self) -> Any:
        """The value, or raise the stored exception."""
        if self.error is not None:
            raise self.error
        return self.value


def run_guarded(func: Callable[..., Any], *args: Any, **kwargs: Any) -> Outcome:
    """Call ``func`` and capture its result or exception in an :class:`Outcome`."""
    try:
        return Outcome(value=func(*args, **kwargs))
    except Exception as exc:  # noqa: BLE001 - handed back to the main thread as data
        return Outcome(error=exc)


# --------------------------------------------------------------------------- detect


def compute_detect(ref: Any, cmp: Any, config: Any = None, *, progress: Any = None) -> Any:
    """Worker-thread part of "Detect deformation": :func:`tunneldef.pipeline.detect`."""
    from tunneldef.pipeline import detect

    return detect(ref, cmp, config, progress=progress)


def result_fields(cloud: Any) -> dict[str, np.ndarray]:
    """The fields of a detection result to write onto the compared cloud."""
    missing = [f for f in DEFORMATION_FIELDS if f not in cloud.fields]
    if missing:
        raise ValueError(f"the detection result lacks the fields {missing}")
    names = list(DEFORMATION_FIELDS) + [f for f in OPTIONAL_FIELDS if f in cloud.fields]
    return {name: np.asarray(cloud.fields[name]) for name in names}


@dataclass
class DetectEntities:
    """Entities the "Detect deformation" action created (to add to the DB tree)."""

    registered: Any
    ref_centerline: Any
    cmp_centerline: Any
    keep_alive: list[Any] = field(default_factory=list)
    limit: float = 0.0
    colours: str = SCALE_RED_IN

    def legend(self) -> str:
        """One line saying what the colours mean, for the console."""
        ends = {
            SCALE_RED_IN: "red = into the tunnel, white = 0, blue = outward",
            SCALE_BLUE_IN: "blue = into the tunnel, white = 0, red = outward (built-in scale; "
            "this runtime cannot load the Red>White>Blue one)",
        }.get(self.colours, "CloudCompare's default scale (no diverging scale available)")
        return f"colour scale: {ends}, saturated at ±{self.limit * 1000:.0f} mm"

    def new_entities(self) -> list[Any]:
        return [self.registered, self.ref_centerline, self.cmp_centerline]


def apply_detect(
    ref_entity: Any,
    cmp_entity: Any,
    result: Any,
    *,
    threshold: float,
    move_original: bool = False,
) -> DetectEntities:
    """Main-thread part of "Detect deformation": fields, colours and new entities.

    Writes the result fields onto ``cmp_entity`` (same points, same order; same-named fields
    replaced), shows ``deformation`` on a diverging scale (red = into the tunnel), builds a
    registered copy of the compared cloud (in the reference frame, reference shift/scale, with
    the fields) and both centrelines as polylines. ``cmp_entity``'s points move only if
    ``move_original``.
    """
    fields = result_fields(result.cloud)
    write_scalar_fields(cmp_entity, fields)
    limit = symmetric_limit(fields["deformation"], threshold=threshold)
    scale = red_white_blue_scale()
    colours = show_diverging(cmp_entity, "deformation", limit=limit, scale=scale)

    base = _name(cmp_entity)
    registered = make_point_cloud(
        result.cloud.xyz, like=ref_entity, name=f"{base} (registered)", fields=fields
    )
    show_diverging(registered, "deformation", limit=limit, scale=scale)
    ref_line, ref_v = make_polyline(
        result.ref_centerline.points,
        like=ref_entity,
        name="reference centreline",
        colour=_CENTERLINE_COLOURS["reference"],
    )
    cmp_line, cmp_v = make_polyline(
        result.cmp_centerline.points,
        like=ref_entity,
        name="compared centreline",
        colour=_CENTERLINE_COLOURS["compared"],
    )
    if move_original:
        move_entity(cmp_entity, result.transform)
    return DetectEntities(registered, ref_line, cmp_line, [ref_v, cmp_v], limit, colours)


# --------------------------------------------------------------------------- centreline


def compute_centerline(cloud: Any, config: Any = None, *, progress: Any = None) -> Any:
    """Worker-thread part of "Extract centerline": ``extract_centerline`` of the core."""
    from tunneldef.centerline import extract_centerline
    from tunneldef.config import Config

    cfg = config or Config()
    return extract_centerline(
        cloud.xyz, slicing=cfg.slicing, settings=cfg.centerline, progress=progress
    )


def apply_centerline(entity: Any, extraction: Any) -> tuple[Any, Any, str]:
    """Main-thread part: ``(polyline, vertices, table)`` for an extraction result."""
    poly, vertices = make_polyline(
        extraction.centerline.points,
        like=entity,
        name=f"{_name(entity)} centreline",
        colour=_CENTERLINE_COLOURS["reference"],
    )
    return poly, vertices, format_slice_table(extraction.slices)


# --------------------------------------------------------------------------- registration


def compute_register(ref: Any, cmp: Any, config: Any = None, *, progress: Any = None) -> Any:
    """Worker-thread part of "Register to reference": both centrelines and the registration,
    with the same checks as ``tunneldef detect`` (:func:`tunneldef.pipeline.register_epochs`)."""
    from tunneldef.pipeline import register_epochs

    return register_epochs(ref, cmp, config, progress=progress).registration


def apply_register(
    ref_entity: Any,
    cmp_entity: Any,
    cmp: Any,
    registration: Any,
) -> tuple[Any, str]:
    """Main-thread part: ``(registered copy, matrix text)``; the original is not moved."""
    t = np.asarray(registration.transform, dtype=np.float64)
    moved = cmp.xyz @ t[:3, :3].T + t[:3, 3]
    copy = make_point_cloud(moved, like=ref_entity, name=f"{_name(cmp_entity)} (registered)")
    return copy, format_matrix(t)


# --------------------------------------------------------------------------- text


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
