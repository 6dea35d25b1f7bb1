"""Drives tunneldef's real menu inside CloudCompare's window (under Xvfb) for the tests.

Loaded by CloudCompare's Python runtime at start-up as a plugin (entry point
``cloudcompare.plugins``, written by the test into a temporary ``.dist-info``), when
``TDCC_GUI=1``. On the main thread it opens the clouds listed in ``TDCC_CLOUDS`` (names
containing ``ref`` and ``cmp``; any global-shift dialog is accepted), waits for the plugin's
three menu actions, then, through
PySide2 (Debian's ``python3-pyside2``; the harness needs it, the plugin does not):

1. selects the reference in the DB tree and triggers *Extract centerline*;
2. selects reference then compared and triggers *Register to reference*;
3. triggers *Detect deformation*, ticking "Also move the original" in the plugin's dialog;
4. triggers *Detect deformation* again and presses Cancel on the progress dialog as soon as it
   is shown, or ``TDCC_CANCEL_AFTER`` seconds after the trigger (default 0: a fixed delay
   lets a fast machine reach the last stages first);
5. optionally (``TDCC_SCREENSHOT=path.png``) shows the compared cloud's colours and grabs the
   screen with ImageMagick's ``import -window root``.

What landed in CloudCompare goes to ``$TDCC_OUT/report.json`` and ``$TDCC_OUT/arrays.npz``;
then CloudCompare exits (``os._exit``).
"""

from __future__ import annotations

import json
import os
import subprocess
import time
import traceback

import numpy as np
import pycc
from inside import sf_array

OUT = os.environ.get("TDCC_OUT", ".")
ACTIONS = ("Detect deformation", "Extract centerline", "Register to reference")
REPORT: dict = {"steps": {}, "errors": [], "modals": []}
ARRAYS: dict[str, np.ndarray] = {}


class HarnessPlugin(pycc.PythonPluginInterface):
    """A do-nothing plugin: the entry point only serves to import this module at start-up (one
    action: with none, CloudCompare 2.13 crashes while building the plugin menu)."""

    def __init__(self) -> None:
        pycc.PythonPluginInterface.__init__(self)

    def getActions(self) -> list:  # noqa: N802 - the runtime's API name
        return [pycc.Action(name="(test harness)", target=_nothing)]


def _nothing() -> None:
    """The harness plugin's menu entry does nothing."""


def save() -> None:
    with open(os.path.join(OUT, "report.json"), "w", encoding="utf-8") as fh:
        json.dump(REPORT, fh, indent=1, default=str)


def _walk(obj, out):
    for i in range(obj.getChildrenNumber()):
        child = obj.getChild(i)
        out.append(child)
        _walk(child, out)
    return out


def entities() -> list:
    return _walk(pycc.GetInstance().dbRootObject(), [])


def sf_names(entity) -> list[str]:
    return [entity.getScalarFieldName(i) for i in range(entity.getNumberOfScalarFields())]


class Driver:
    """A state machine on CloudCompare's main thread, stepped by QTimer callbacks."""

    def __init__(self) -> None:
        from PySide2 import QtCore, QtWidgets

        self.QtCore, self.QtWidgets = QtCore, QtWidgets
        self.app = QtWidgets.QApplication
        self.t0 = time.time()
        self.cancel_at: float | None = None
        self.tick_move = False
        self.keep: list = []
        self.queue: list = []
        self._widgets: dict = {}

    # ---- Qt helpers
    def later(self, ms: int, fn) -> None:
        def run() -> None:
            try:
                fn()
            except Exception:  # noqa: BLE001 - recorded, then finish
                REPORT["errors"].append(traceback.format_exc())
                self.finish()

        self.QtCore.QTimer.singleShot(ms, run)

    def scan(self, keep, top_level: bool = False) -> list:
        """The widgets (all, or top-level) for which ``keep(widget)`` is true; the PySide2
        wrappers of all the others are invalidated (see :meth:`watch`)."""
        import shiboken2

        widgets = self.app.topLevelWidgets() if top_level else self.app.allWidgets()
        cached = [id(w) for w in self._widgets.values()]
        out = []
        for w in widgets:
            if keep(w):
                out.append(w)
            elif id(w) not in cached:
                shiboken2.invalidate(w)
        return out

    def menu_actions(self) -> dict:
        """The plugin's three QActions: ``{text: (menu title, action)}``."""

        def ours(w) -> bool:
            return isinstance(w, self.QtWidgets.QMenu) and any(
                a.text() in ACTIONS for a in w.actions()
            )

        found = {}
        for menu in self.scan(ours):
            for a in menu.actions():
                if a.text() in ACTIONS:
                    found.setdefault(a.text(), (menu.title(), a))
        return found

    def menu_path(self) -> list[str]:
        """Titles from the menu bar down to the tunneldef submenu holding the actions."""
        _, action = self.acts[ACTIONS[0]]
        path: list[str] = []
        menu = action.associatedWidgets()[0] if action.associatedWidgets() else None
        while isinstance(menu, self.QtWidgets.QMenu):
            path.insert(0, menu.title().replace("&", ""))
            parent_action = menu.menuAction()
            owners = [w for w in parent_action.associatedWidgets() if w is not menu]
            menu = owners[0] if owners else None
        return path

    def console(self) -> list[str]:
        w = self.widget(self.QtWidgets.QListWidget, "consoleWidget")
        return [w.item(i).text() for i in range(w.count())]

    def widget(self, cls, name: str):
        """A long-lived widget of CloudCompare's window by class and object name (cached, so
        that ``allWidgets()`` is not wrapped again while transient widgets come and go)."""
        key = (cls.__name__, name)
        if key not in self._widgets:
            self._widgets[key] = self.scan(
                lambda w: isinstance(w, cls) and w.objectName() == name
            )[0]
        return self._widgets[key]

    def tree_rows(self) -> tuple:
        """CloudCompare's DB tree view and the model index of every row in it."""
        tree = self.widget(self.QtWidgets.QTreeView, "dbTreeView")
        model, rows = tree.model(), []

        def walk(parent) -> None:
            for r in range(model.rowCount(parent)):
                idx = model.index(r, 0, parent)
                rows.append(idx)
                walk(idx)

        walk(self.QtCore.QModelIndex())
        return tree, rows

    def select(self, ents: list) -> None:
        """Select ``ents`` in this order in the DB tree, as Ctrl+clicks would."""
        QtCore = self.QtCore
        tree, rows = self.tree_rows()
        sm = tree.selectionModel()
        by_name = {}
        for idx in rows:
            by_name.setdefault(idx.data(), idx)
        sm.clearSelection()
        flags = QtCore.QItemSelectionModel.Select | QtCore.QItemSelectionModel.Rows
        for e in ents:
            sm.select(by_name[e.getName()], flags)

    def watch(self) -> None:
        """Answer the plugin's dialog and message boxes; press Cancel when asked to.

        Widgets that CloudCompare creates and deletes itself (its progress dialog, its
        global-shift dialog) are wrapped by PySide2 only here, and their wrappers are
        invalidated at once: PySide2 does not see C++ deletions of objects it did not create,
        and a stale wrapper whose address is reused crashes CloudCompare."""
        import shiboken2

        QtWidgets = self.QtWidgets
        if self.cancel_at is not None and time.time() > self.cancel_at:
            shown = self.scan(
                lambda w: isinstance(w, QtWidgets.QProgressDialog) and w.isVisible(),
                top_level=True,
            )
            for w in shown:
                w.cancel()
                REPORT["cancel_pressed"] = round(time.time() - self.t0, 1)
                self.cancel_at = None
                shiboken2.invalidate(w)
        w = self.app.activeModalWidget()
        if isinstance(w, QtWidgets.QProgressDialog):
            shiboken2.invalidate(w)
        elif w is not None:
            title = w.windowTitle()
            rec = {"t": round(time.time() - self.t0, 1), "title": title}
            if isinstance(w, QtWidgets.QMessageBox):
                rec["text"] = w.text()
            if title == "tunneldef: detect deformation" and self.tick_move:
                for cb in w.findChildren(QtWidgets.QCheckBox):
                    cb.setChecked(True)
                rec["ticked"] = "move the original"
            REPORT["modals"].append(rec)
            w.accept() if hasattr(w, "accept") else w.close()
            if not title.startswith("tunneldef"):  # CloudCompare's own dialog
                shiboken2.invalidate(w)
        self.QtCore.QTimer.singleShot(200, self.watch)

    # ---- sequence
    def start(self) -> None:
        self.watch()
        self.later(300, self.load)

    def load(self) -> None:
        """Open the clouds of ``TDCC_CLOUDS`` as File > Open would (after start-up: clouds given
        on CloudCompare's command line load while the runtime is still starting, and a global
        shift dialog at that moment crashes CloudCompare 2.13)."""
        cc = pycc.GetInstance()
        loaded = []
        for path in filter(None, os.environ.get("TDCC_CLOUDS", "").split(os.pathsep)):
            params = pycc.FileIOFilter.LoadParameters()
            for name, value in (("alwaysDisplayLoadDialog", False),):
                if hasattr(params, name):
                    setattr(params, name, value)
            obj = cc.loadFile(path, params)
            loaded.append(None if obj is None else obj.getName())
        REPORT["loaded"] = loaded
        self.later(300, self.wait_ready)

    def wait_ready(self) -> None:
        clouds = [e for e in entities() if isinstance(e, pycc.ccPointCloud)]
        self.acts = self.menu_actions()
        named = {k: next((c for c in clouds if k in c.getName().lower()), None)
                 for k in ("ref", "cmp")}
        if (None in named.values() or len(self.acts) < 3) and time.time() - self.t0 < 120:
            self.later(300, self.wait_ready)
            return
        if None in named.values() or len(self.acts) < 3:
            raise RuntimeError(f"clouds {named} or actions {list(self.acts)} missing")
        self.ref, self.cmp = named["ref"], named["cmp"]
        REPORT["menu_path"] = self.menu_path()
        REPORT["shifts"] = {k: [c.getGlobalShift().x, c.getGlobalShift().y,
                                c.getGlobalShift().z] for k, c in named.items()}
        self.queue = [
            ("centerline", [self.ref], ACTIONS[1]),
            ("register", [self.ref, self.cmp], ACTIONS[2]),
            ("detect", [self.ref, self.cmp], ACTIONS[0]),
            ("cancel", [self.ref, self.cmp], ACTIONS[0]),
        ]
        self.next()

    def next(self) -> None:
        if not self.queue:
            self.finish()
            return
        step, sel, name = self.queue.pop(0)
        self.before = {
            "ids": {e.getUniqueID() for e in entities()},
            "console": len(self.console()),
            "cmp_fields": sf_names(self.cmp),
            "cmp_deformation": sf_array(self.cmp, "deformation"),
        }
        self.tick_move = step == "detect"
        self.select(sel)
        self.later(300, lambda: self.trigger(step, name))

    def trigger(self, step: str, name: str) -> None:
        selected = [e.getName() for e in pycc.GetInstance().getSelectedEntities()]
        _, action = self.acts[name]
        t_start = time.time()
        if step == "cancel":
            self.cancel_at = t_start + float(os.environ.get("TDCC_CANCEL_AFTER", "0"))

        def done(*_args) -> None:  # runs after the runtime's own slot returned
            action.triggered.disconnect(done)
            rec = {"selected": selected, "seconds": round(time.time() - t_start, 2)}
            # CloudCompare's console widget shows new lines on a timer: wait for them
            self.later(1200, lambda: self.check(step, rec))

        action.triggered.connect(done)
        self.keep.append(done)
        self.QtCore.QMetaObject.invokeMethod(action, "trigger", self.QtCore.Qt.QueuedConnection)

    def new_entities(self) -> list:
        return [e for e in entities() if e.getUniqueID() not in self.before["ids"]]

    def check(self, step: str, rec: dict) -> None:
        from tunneldef_cloudcompare import adapter

        rec["console"] = self.console()[self.before["console"]:]
        new = self.new_entities()
        rec["new"] = [f"{type(e).__name__}: {e.getName()}" for e in new]
        if step == "detect":
            rec["cmp_fields"] = sf_names(self.cmp)
            for f in rec["cmp_fields"]:
                ARRAYS[f"{step}:field:{f}"] = sf_array(self.cmp, f)
            ARRAYS[f"{step}:cmp_xyz"] = adapter.read_points(self.cmp)
            reg = [e for e in new if e.getName().endswith("(registered)")]
            if reg:
                ARRAYS[f"{step}:registered"] = adapter.read_points(reg[0])
            for e in new:
                if isinstance(e, pycc.ccPolyline):
                    key = e.getName().split()[0]  # "reference" / "compared"
                    ARRAYS[f"{step}:{key}_centerline"] = adapter.read_points(
                        e.getAssociatedCloud()
                    )
            sf = self.cmp.getScalarField(self.cmp.getCurrentDisplayedScalarFieldIndex())
            rec["displayed"] = sf.getName()
            rec["symmetrical"] = bool(sf.symmetricalScale())
            lim = float(sf.saturationRange().stop())
            rec["saturation_stop"] = lim
            rec["rgb"] = {f"{v:+.1f}": [int(c.r), int(c.g), int(c.b)] for v, c in (
                (v, sf.getColor(v * lim)) for v in (-1.0, -0.5, 0.0, 0.5, 1.0))}
        elif step == "centerline":
            poly = [e for e in new if isinstance(e, pycc.ccPolyline)]
            if poly:
                ARRAYS["centerline"] = adapter.read_points(poly[0].getAssociatedCloud())
        elif step == "register":
            reg = [e for e in new if isinstance(e, pycc.ccPointCloud)]
            if reg:
                ARRAYS["register:copy"] = adapter.read_points(reg[0])
        elif step == "cancel":
            rec["cmp_fields_before"] = self.before["cmp_fields"]
            rec["cmp_fields_after"] = sf_names(self.cmp)
            after = sf_array(self.cmp, "deformation")
            rec["deformation_unchanged"] = bool(
                np.array_equal(after, self.before["cmp_deformation"], equal_nan=True)
            )
        REPORT["steps"][step] = rec
        save()
        if step == "cancel" and os.environ.get("TDCC_SCREENSHOT"):
            self.later(200, self.screenshot)
            return
        self.next()

    def screenshot(self) -> None:
        """Show the compared cloud (and the centrelines) alone with its deformation colours,
        CloudCompare's window over the whole screen, an oblique view; then grab the screen."""
        QtCore, QtWidgets = self.QtCore, self.QtWidgets
        tree, rows = self.tree_rows()
        model = tree.model()
        keep = {self.cmp.getName(), "reference centreline", "compared centreline"}
        for idx in rows:
            if model.rowCount(idx) == 0 and idx.data() not in keep:
                model.setData(idx, QtCore.Qt.Unchecked, QtCore.Qt.CheckStateRole)
        views = os.environ.get("TDCC_VIEW_ACTIONS", "actionSetViewIso1,actionZoomAndCenter")
        wanted = views.split(",")
        main = self.scan(lambda w: isinstance(w, QtWidgets.QMainWindow), top_level=True)
        for w in main:
            if "CloudCompare" in w.windowTitle():
                screen = self.app.primaryScreen().geometry()
                w.setGeometry(screen)
                names = [a.objectName() for a in w.findChildren(QtWidgets.QAction)]
                REPORT["view_action_names"] = [n for n in names if "View" in n or "Zoom" in n]
                for a in w.findChildren(QtWidgets.QAction):
                    if a.objectName() in wanted:
                        a.trigger()
                        REPORT.setdefault("view_actions", []).append(a.objectName())
        if hasattr(self.cmp, "setPointSize"):
            self.cmp.setPointSize(int(os.environ.get("TDCC_POINT_SIZE", "3")))
        self.select([self.cmp])
        pycc.GetInstance().redrawAll()
        self.later(6000, self._grab)  # after CloudCompare's "New size" overlay has gone

    def _grab(self) -> None:
        path = os.environ["TDCC_SCREENSHOT"]
        r = subprocess.run(["import", "-window", "root", path], capture_output=True, text=True)
        REPORT["screenshot"] = {"path": path, "rc": r.returncode, "stderr": r.stderr[-500:]}
        self.next()

    def finish(self) -> None:
        try:
            REPORT["console"] = self.console()
            np.savez(os.path.join(OUT, "arrays.npz"), **ARRAYS)
            REPORT["finished"] = True
        except Exception:  # noqa: BLE001
            REPORT["errors"].append(traceback.format_exc())
        finally:
            save()
            os._exit(0)


_KEEP: list = []


def _bootstrap() -> None:
    """Plugins are imported off the main thread: hop onto it with a queued call."""
    from PySide2 import QtCore

    class Boot(QtCore.QObject):
        @QtCore.Slot()
        def go(self) -> None:
            driver = Driver()
            _KEEP.append(driver)
            driver.later(1000, driver.start)

    boot = Boot()
    boot.moveToThread(QtCore.QCoreApplication.instance().thread())
    _KEEP.append(boot)
    QtCore.QMetaObject.invokeMethod(boot, "go", QtCore.Qt.QueuedConnection)


if os.environ.get("TDCC_GUI"):
    _bootstrap()
