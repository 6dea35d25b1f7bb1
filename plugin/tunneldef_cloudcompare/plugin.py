"""The CloudCompare Python-runtime plugin: three menu actions over the tunneldef core.

Found by CloudCompare through the entry point ``cloudcompare.plugins: tunneldef =
tunneldef_cloudcompare.plugin:TunnelDefPlugin``. Only ``pycc`` and numpy are imported at module
level (an import error would silently drop the plugin); the core, Open3D and Qt are imported
inside the actions. Each action: check that the runtime's arrays are sound -> read the
selection on the main thread -> run the core on a Python worker thread while the main thread
keeps CloudCompare responsive (``pycc.ProcessEvents``) and shows a cancellable
``ccProgressDialog`` -> write fields / add entities on the main thread. ``pycc.RunInThread``
is not used: it can abort CloudCompare (see :mod:`.worker`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np  # noqa: F401 - the plugin's only other top-level dependency
import pycc

from . import adapter
from .params import DetectParams
from .worker import Outcome, ProgressBridge

log = logging.getLogger(__name__)

__all__ = [
    "TunnelDefPlugin",
    "detect_deformation",
    "extract_centerline",
    "register_to_reference",
    "detect_on",
    "centerline_on",
    "register_on",
]


def _console(text: str) -> None:
    """Print to CloudCompare's console (the runtime redirects stdout there)."""
    print(text)  # noqa: T201 - host code: this is the user-facing console


def _has_window() -> bool:
    """True in CloudCompare's window; False in ``-PYTHON_SCRIPT`` (command-line) mode, where
    the instance has no selection and nobody can close a message box."""
    return hasattr(pycc.GetInstance(), "getSelectedEntities")


def _error(text: str) -> None:
    from .dialog import show_message

    # a modal box in command-line mode (often offscreen) would wait for ever
    show_message(text, error=True, box=_has_window())


def _run_with_progress(
    title: str,
    func: Callable[..., Any],
    *args: Any,
    **kwargs: Any,
) -> tuple[Outcome, ProgressBridge]:
    """Run ``func(*args, progress=bridge, **kwargs)`` in a worker thread with a cancellable
    progress dialog; the UI is frozen meanwhile. Exceptions come back in the Outcome."""
    cc = pycc.GetInstance()
    process_events = getattr(pycc, "ProcessEvents", None)
    dialog = pycc.ccProgressDialog(cancelButton=True)
    dialog.setMethodTitle(title)
    dialog.setInfo("working... (Cancel stops at the next step)")
    bridge = ProgressBridge(dialog)
    dialog.start()
    freeze = getattr(cc, "freezeUI", None)  # the command-line instance has no UI to freeze
    if freeze is not None:
        freeze(True)
    try:
        outcome = adapter.run_in_worker(
            func, *args, bridge=bridge, process_events=process_events, **kwargs
        )
    finally:
        if freeze is not None:
            freeze(False)
        dialog.stop()
    return outcome, bridge


def _report_failure(action: str, outcome: Outcome) -> None:
    from tunneldef.errors import TunnelDefError

    if outcome.cancelled:
        _console(f"[tunneldef] {action}: {outcome.error}; nothing was changed")
    elif isinstance(outcome.error, TunnelDefError):
        _error(f"{action}: {outcome.error}")
    else:
        log.error("%s failed", action, exc_info=outcome.error)
        _error(f"{action} failed: {type(outcome.error).__name__}: {outcome.error}")


def _runtime_ok(action: str) -> bool:
    """False (after a one-line message) if this runtime hands out wrong arrays."""
    try:
        adapter.check_runtime(pycc)
    except adapter.BrokenRuntimeError as exc:
        _error(f"{action}: {exc}")
        return False
    return True


def _selected_clouds(count: int, action: str) -> list[Any] | None:
    """The selected clouds if there are ``count``, else None (after a one-line message)."""
    cc = pycc.GetInstance()
    if not _has_window():  # -PYTHON_SCRIPT mode: no window, no selection
        _error(
            f"{action}: needs CloudCompare's window (no selection in command-line mode); "
            "use cloudcompare_scripts/detect_in_cloudcompare.py there"
        )
        return None
    clouds = adapter.point_clouds(cc.getSelectedEntities())
    if len(clouds) != count:
        what = "one point cloud" if count == 1 else f"{count} point clouds"
        _error(f"{action}: select exactly {what} (selected: {len(clouds)})")
        return None
    return clouds


def _add(entities: list[Any]) -> None:
    """Add entities to the DB tree (GUI); in command-line mode keep them alive instead."""
    cc = pycc.GetInstance()
    if not hasattr(cc, "addToDB"):
        _keep(entities)
        return
    for e in entities:
        cc.addToDB(e)
    cc.updateUI()
    cc.redrawAll()


# --------------------------------------------------------------------------- actions


def detect_deformation(params: DetectParams | None = None, *, ask: bool = True) -> Any:
    """Menu action *Detect deformation* on two selected clouds.

    The first selected cloud is the reference unless swapped in the dialog. Returns the
    :class:`adapter.DetectEntities` or None."""
    action = "Detect deformation"
    clouds = _selected_clouds(2, action)
    if clouds is None:
        return None
    params = params or DetectParams.from_config()
    if ask:
        from .dialog import ask_detect_params

        names = [adapter.entity_name(c) for c in clouds]
        params = ask_detect_params(names[0], names[1], params)
        if params is None:
            return None
    ref_e, cmp_e = (clouds[1], clouds[0]) if params.swap else (clouds[0], clouds[1])
    return detect_on(ref_e, cmp_e, params)


def detect_on(ref_e: Any, cmp_e: Any, params: DetectParams | None = None) -> Any:
    """*Detect deformation* on two given clouds (``ref_e`` = reference), no dialog.

    What the menu action does after the selection and the dialog; usable from scripts,
    including ``-PYTHON_SCRIPT`` mode. Returns the :class:`adapter.DetectEntities` or None
    (after a one-line message)."""
    action = "Detect deformation"
    if not _runtime_ok(action):
        return None
    params = params or DetectParams.from_config()
    config = adapter.config_from_params(params)
    ref, cmp = adapter.entity_to_cloud(ref_e), adapter.entity_to_cloud(cmp_e)
    _console(
        f"[tunneldef] reference: {ref.meta['name']} ({len(ref)} points); "
        f"compared: {cmp.meta['name']} ({len(cmp)} points); {params}"
    )

    outcome, bridge = _run_with_progress(action, adapter.compute_detect, ref, cmp, config,
                                         network=params.network)
    if not outcome.ok:
        _report_failure(action, outcome)
        return None
    result = outcome.value
    made = adapter.apply_detect(
        ref_e, cmp_e, result, threshold=params.threshold, move_original=params.move_original
    )
    _keep(made.keep_alive)
    _add(made.new_entities())
    _console(f"[tunneldef] stages: {', '.join(bridge.stages)}")
    _console(
        "[tunneldef] compared -> reference transform:\n" + adapter.format_matrix(result.transform)
    )
    stats = result.statistics() if hasattr(result, "statistics") else {}
    if stats:
        _console(
            "[tunneldef] "
            + ", ".join(
                f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in stats.items()
            )
        )
    _console(f"[tunneldef] {made.legend()}")
    # what the run warns of without stopping (e.g. a reference whose z may not point up)
    for check in getattr(getattr(result, "quality", None), "warnings", ()):
        _console(f"[tunneldef] warning: {check.reason()}")
    return made


def extract_centerline(*, config: Any = None) -> Any:
    """Menu action *Extract centerline*: one selected cloud -> a polyline (one per edge for
    a drift network).

    Per-slice width/height (per-edge lengths for a network) are printed in the console.
    Returns what :func:`centerline_on` returns."""
    clouds = _selected_clouds(1, "Extract centerline")
    return None if clouds is None else centerline_on(clouds[0], config=config)


def centerline_on(entity: Any, *, config: Any = None, network: str = "auto") -> Any:
    """*Extract centerline* on a given cloud (no selection needed).

    Returns the polyline of a drift, the list of per-edge polylines of a drift network
    (``network``: ``"auto"`` decides from the cloud's plan, ``"single"``, ``"network"``), or
    None (after a one-line message)."""
    action = "Extract centerline"
    if not _runtime_ok(action):
        return None
    cloud = adapter.entity_to_cloud(entity)
    outcome, _ = _run_with_progress(action, adapter.compute_centerline, cloud, config,
                                    network=network)
    if not outcome.ok:
        _report_failure(action, outcome)
        return None
    polys, vertices, text = adapter.apply_centerline(entity, outcome.value)
    _keep(vertices)
    _add(polys)
    if getattr(outcome.value, "network", None) is None:
        _console(
            f"[tunneldef] centreline of {cloud.meta['name']}: "
            f"{outcome.value.centerline.length:.2f} m\n{text}"
        )
        return polys[0]
    _console(f"[tunneldef] centreline network of {cloud.meta['name']}: {text}")
    return polys


def register_to_reference(*, config: Any = None) -> Any:
    """Menu action *Register to reference* on two selected clouds (first = reference).

    Adds a registered copy of the second and prints the 4 x 4 matrix. Returns the copy or
    None."""
    clouds = _selected_clouds(2, "Register to reference")
    return None if clouds is None else register_on(clouds[0], clouds[1], config=config)


def register_on(ref_e: Any, cmp_e: Any, *, config: Any = None) -> Any:
    """*Register to reference* on two given clouds (``ref_e`` = reference); the copy or None."""
    action = "Register to reference"
    if not _runtime_ok(action):
        return None
    ref, cmp = adapter.entity_to_cloud(ref_e), adapter.entity_to_cloud(cmp_e)
    outcome, _ = _run_with_progress(action, adapter.compute_register, ref, cmp, config)
    if not outcome.ok:
        _report_failure(action, outcome)
        return None
    reg = outcome.value
    copy, matrix = adapter.apply_register(ref_e, cmp_e, cmp, reg)
    _add([copy])
    fitness = getattr(reg, "fitness", float("nan"))
    _console(
        f"[tunneldef] {cmp.meta['name']} -> {ref.meta['name']} "
        f"(method {getattr(reg, 'method', '?')}, RMSE {fitness:.4f} m):\n{matrix}"
    )
    return copy


_KEEP_ALIVE: list[Any] = []


def _keep(objects: list[Any]) -> None:
    """Hold Python references to vertex clouds CloudCompare does not own yet."""
    _KEEP_ALIVE.extend(objects)


class TunnelDefPlugin(pycc.PythonPluginInterface):
    """tunneldef's menu in CloudCompare (*Plugins > Python Plugin > Plugins > tunneldef*)."""

    def __init__(self) -> None:
        pycc.PythonPluginInterface.__init__(self)

    def getActions(self) -> list[Any]:  # noqa: N802 - CloudCompare's API name
        return [
            pycc.Action(name="Detect deformation", target=_action(detect_deformation)),
            pycc.Action(name="Extract centerline", target=_action(extract_centerline)),
            pycc.Action(name="Register to reference", target=_action(register_to_reference)),
        ]


def _action(func: Callable[[], Any]) -> Callable[[], None]:
    """A menu target: runs ``func`` and turns any escaping exception into a message."""

    def target() -> None:
        try:
            func()
        except Exception as exc:  # noqa: BLE001 - last resort: never crash CloudCompare
            log.exception("tunneldef action failed")
            _error(f"{type(exc).__name__}: {exc}")

    target.__name__ = func.__name__
    return target
