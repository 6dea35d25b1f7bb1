"""Running the core off CloudCompare's GUI thread without touching the runtime's thread pool.

``pycc.RunInThread`` runs a Python callable on a QtConcurrent thread; when the call's Python
objects are released there without the GIL, CloudCompare aborts (``Fatal Python error:
PyThreadState_Get``; seen in 3 of 4 command-line runs of CloudCompare 2.13 + PythonRuntime).
:func:`run_in_worker` uses a plain :class:`threading.Thread` instead, so every Python object is
created and freed under the interpreter's own rules, and keeps CloudCompare's window alive from
the main thread with ``pycc.ProcessEvents()`` while it waits. The worker never calls ``pycc``:
it only records progress in :class:`ProgressBridge`; the main thread moves the progress bar and
reads the dialog's Cancel button.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ProgressBridge", "Outcome", "run_guarded", "run_in_worker"]

#: the highest value the bar is moved to while a job runs (see :meth:`ProgressBridge.pump`)
MAX_PERCENT = 99.0


class ProgressBridge:
    """The core's ``progress(stage, fraction)`` callback, shown in a CloudCompare progress dialog.

    Called from the worker thread it only records the stage and fraction, and raises
    :class:`tunneldef.progress.Cancelled` once Cancel was seen; :meth:`pump` (main thread)
    moves the dialog's bar and reads its Cancel button. (CloudCompare 2.13's ``update`` and
    ``setInfo`` call ``QCoreApplication::processEvents`` themselves: on the main thread only,
    and the text is set once, before the run.) Called from the main thread (no
    worker) it does both at once. Stage names are kept in ``stages`` for the log.
    """

    def __init__(self, dialog: Any = None) -> None:
        self.dialog = dialog
        self.stages: list[str] = []
        self.last_fraction = 0.0
        self._cancelled = False
        self._shown: tuple[str, float] | None = None

    def cancel(self) -> None:
        """Request cancellation (as the dialog's Cancel button does)."""
        self._cancelled = True

    @property
    def cancelled(self) -> bool:
        """True once cancellation was requested (flag or, on the main thread, the dialog)."""
        if not self._cancelled and threading.current_thread() is threading.main_thread():
            dlg = self.dialog
            if dlg is not None and dlg.isCancelRequested():
                self._cancelled = True
        return self._cancelled

    def pump(self) -> None:
        """Main thread only: show the latest progress and read the Cancel button."""
        _ = self.cancelled
        dlg = self.dialog
        if dlg is None or not self.stages:
            return
        now = (self.stages[-1], self.last_fraction)
        if now != self._shown:
            self._shown = now
            # at most 99 %: CloudCompare's dialog is a QProgressDialog with autoClose and
            # autoReset on a 0-100 range, so 100 would hide it (and clear a Cancel already
            # pressed) for the rest of the run, which goes on to its next stage
            dlg.update(float(np.clip(100.0 * now[1], 0.0, MAX_PERCENT)))

    def __call__(self, stage: str, fraction: float) -> None:
        from tunneldef.progress import Cancelled

        if self.cancelled:
            raise Cancelled(f"cancelled during {stage!r}")
        if not self.stages or self.stages[-1] != stage:
            self.stages.append(stage)
        self.last_fraction = float(fraction)
        if threading.current_thread() is threading.main_thread():
            self.pump()


@dataclass
class Outcome:
    """What a worker-thread job gave: a value, or the exception it raised (never raised
    across the thread boundary)."""

    value: Any = None
    error: BaseException | None = None

    @property
    def cancelled(self) -> bool:
        """True if the job stopped because the user cancelled it."""
        from tunneldef.progress import Cancelled

        return isinstance(self.error, Cancelled)

    @property
    def ok(self) -> bool:
        """True if the job returned a value."""
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


def run_in_worker(
    func: Callable[..., Any],
    *args: Any,
    bridge: ProgressBridge,
    process_events: Callable[[], None] | None = None,
    poll: float = 0.05,
    **kwargs: Any,
) -> Outcome:
    """``func(*args, progress=bridge, **kwargs)`` on a worker thread; the caller waits.

    While waiting, the calling (main) thread wakes every ``poll`` seconds to call
    ``bridge.pump()`` and ``process_events()`` (``pycc.ProcessEvents``: repaint, Cancel
    button). The worker's result or exception comes back as an :class:`Outcome`; nothing is
    raised across threads and no ``pycc`` call happens on the worker.
    """
    box: dict[str, Outcome] = {}

    def target() -> None:
        box["outcome"] = run_guarded(func, *args, progress=bridge, **kwargs)

    worker = threading.Thread(target=target, name="tunneldef-worker", daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(poll)  # releases the GIL while waiting
        bridge.pump()
        if process_events is not None:
            process_events()
    bridge.pump()
    return box.get("outcome") or Outcome(error=RuntimeError("the worker thread returned nothing"))
