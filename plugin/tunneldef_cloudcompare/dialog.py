"""The parameter dialog of "Detect deformation" and small message helpers.

CloudCompare's Python runtime ships a Qt binding (PySide2; newer Windows builds PySide6); it
is imported lazily here and never declared as a dependency of the package. Without Qt (or
without a running QApplication) the functions fall back to plain behaviour: the defaults are
used as they are and messages go to the log/console.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
from typing import Any

from .params import NETWORK_CHOICES, DetectParams

log = logging.getLogger(__name__)

__all__ = ["qt_widgets", "ask_detect_params", "show_message", "METHODS", "NETWORK_CHOICES"]

#: Deformation estimators offered in the dialog (``Config.deformation.method``): ``robust``
#: (local surface, per-point level of detection; the default) and ``knn`` (paper §3.3.1).
METHODS = ("robust", "knn")


def qt_widgets() -> Any:
    """``QtWidgets`` of PySide6 or PySide2 if usable now (module present and a QApplication
    running, i.e. CloudCompare's GUI), else None."""
    for binding in ("PySide6", "PySide2"):
        try:
            qtw = importlib.import_module(f"{binding}.QtWidgets")
        except ImportError:
            continue
        return qtw if qtw.QApplication.instance() is not None else None
    return None


def show_message(
    text: str, *, title: str = "tunneldef", error: bool = False, box: bool = True
) -> None:
    """A message box when Qt is available and ``box`` is true (there is a window to show it
    in); always also in the log (CloudCompare's console)."""
    (log.error if error else log.info)("%s", text)
    qw = qt_widgets() if box else None
    if qw is None:
        print(f"[{title}] {text}")  # noqa: T201 - CloudCompare's console is stdout
        return
    box = qw.QMessageBox.critical if error else qw.QMessageBox.information
    box(None, title, text)


def ask_detect_params(
    first_name: str, second_name: str, defaults: DetectParams | None = None
) -> DetectParams | None:
    """Ask which cloud is the reference and the detection parameters.

    Parameters
    ----------
    first_name, second_name : str
        Names of the two selected clouds, in selection order.
    defaults : DetectParams
        Initial values (``DetectParams.from_config()`` if None).

    Returns
    -------
    DetectParams or None
        None if the user pressed Cancel. Without Qt the defaults are returned unchanged
        (first selected cloud = reference) and that choice is logged.
    """
    params = defaults or DetectParams.from_config()
    qw = qt_widgets()
    if qw is None:
        ref, cmp = (second_name, first_name) if params.swap else (first_name, second_name)
        log.info("no Qt dialog available: reference = %r, compared = %r, %s", ref, cmp, params)
        return params
    return _qt_dialog(qw, first_name, second_name, params)


def _qt_dialog(qw: Any, first: str, second: str, params: DetectParams) -> DetectParams | None:
    dlg = qw.QDialog()
    dlg.setWindowTitle("tunneldef: detect deformation")
    form = qw.QFormLayout(dlg)

    state = {"swap": params.swap}
    ref_label, cmp_label = qw.QLabel(), qw.QLabel()

    def refresh() -> None:
        ref, cmp = (second, first) if state["swap"] else (first, second)
        ref_label.setText(f"<b>{ref}</b> (earlier epoch)")
        cmp_label.setText(f"<b>{cmp}</b> (later epoch; receives the fields)")

    def swap() -> None:
        state["swap"] = not state["swap"]
        refresh()

    refresh()
    swap_button = qw.QPushButton("Swap reference / compared")
    swap_button.clicked.connect(swap)
    form.addRow("Reference:", ref_label)
    form.addRow("Compared:", cmp_label)
    form.addRow("", swap_button)

    threshold = qw.QDoubleSpinBox()
    threshold.setDecimals(3)
    threshold.setRange(0.001, 10.0)
    threshold.setSingleStep(0.005)
    threshold.setSuffix(" m")
    threshold.setValue(params.threshold)
    form.addRow("Danger threshold |deformation|:", threshold)

    k = qw.QSpinBox()
    k.setRange(1, 100)
    k.setValue(params.k)
    form.addRow("k nearest neighbours (knn only):", k)

    method = qw.QComboBox()
    method.addItems(list(METHODS))
    if params.method in METHODS:
        method.setCurrentIndex(METHODS.index(params.method))
    form.addRow("Method:", method)

    network = qw.QComboBox()
    labels = {"auto": "auto (network if the plan shows junctions)", "single": "one drift",
              "network": "drift network (one centreline per branch)"}
    network.addItems([labels[c] for c in NETWORK_CHOICES])
    if params.network in NETWORK_CHOICES:
        network.setCurrentIndex(NETWORK_CHOICES.index(params.network))
    form.addRow("Tunnel:", network)

    move = qw.QCheckBox("Also move the original compared cloud into the reference frame")
    move.setChecked(params.move_original)
    form.addRow("", move)

    std = getattr(qw.QDialogButtonBox, "StandardButton", qw.QDialogButtonBox)
    buttons = qw.QDialogButtonBox(std.Ok | std.Cancel)
    buttons.accepted.connect(dlg.accept)
    buttons.rejected.connect(dlg.reject)
    form.addRow(buttons)

    run = getattr(dlg, "exec", None) or dlg.exec_  # PySide6 / PySide2
    if not run():
        return None
    return dataclasses.replace(
        params,
        swap=state["swap"],
        threshold=float(threshold.value()),
        k=int(k.value()),
        method=str(method.currentText()),
        move_original=bool(move.isChecked()),
        network=NETWORK_CHOICES[int(network.currentIndex())],
    )
