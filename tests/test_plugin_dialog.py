"""The "Detect deformation" dialog logic against a minimal stand-in for Qt's widgets (only the
calls the dialog makes), and the no-Qt fallback. Real Qt is not installed here."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from tunneldef_cloudcompare import dialog
from tunneldef_cloudcompare.adapter import DetectParams


class _Signal:
    def __init__(self):
        self.slots = []

    def connect(self, slot):
        self.slots.append(slot)

    def emit(self):
        for slot in self.slots:
            slot()


class _Widget:
    def __init__(self, *args):
        self.args = args


class FakeQt:
    """Just enough of QtWidgets for dialog._qt_dialog; ``user(widgets)`` plays the user."""

    def __init__(self, user, accept=True):
        qt = self
        self.widgets = SimpleNamespace(
            labels=[], spins=[], ints=[], combos=[], checks=[], buttons=[]
        )
        self.messages = []

        class QApplication:
            @staticmethod
            def instance():
                return object()

        class QDialog(_Widget):
            def setWindowTitle(self, t):  # noqa: N802
                self.title = t

            def accept(self):
                self.result = 1

            def reject(self):
                self.result = 0

            def exec(self):
                user(qt.widgets)
                return 1 if accept else 0

        class QFormLayout(_Widget):
            def addRow(self, *args):  # noqa: N802
                pass

        class QLabel(_Widget):
            def __init__(self, *a):
                super().__init__(*a)
                self.text = ""
                qt.widgets.labels.append(self)

            def setText(self, t):  # noqa: N802
                self.text = t

        class QPushButton(_Widget):
            def __init__(self, *a):
                super().__init__(*a)
                self.clicked = _Signal()
                qt.widgets.buttons.append(self)

        class _Spin(_Widget):
            def setRange(self, lo, hi):  # noqa: N802
                self.range = (lo, hi)

            def setValue(self, v):  # noqa: N802
                self.v = v

            def value(self):
                return self.v

        class QDoubleSpinBox(_Spin):
            def __init__(self, *a):
                super().__init__(*a)
                qt.widgets.spins.append(self)

            def setDecimals(self, n):  # noqa: N802
                pass

            def setSingleStep(self, s):  # noqa: N802
                pass

            def setSuffix(self, s):  # noqa: N802
                pass

        class QSpinBox(_Spin):
            def __init__(self, *a):
                super().__init__(*a)
                qt.widgets.ints.append(self)

        class QComboBox(_Widget):
            def __init__(self, *a):
                super().__init__(*a)
                self.items, self.i = [], 0
                qt.widgets.combos.append(self)

            def addItems(self, items):  # noqa: N802
                self.items += items

            def setCurrentIndex(self, i):  # noqa: N802
                self.i = i

            def currentText(self):  # noqa: N802
                return self.items[self.i]

            def currentIndex(self):  # noqa: N802
                return self.i

        class QCheckBox(_Widget):
            def __init__(self, *a):
                super().__init__(*a)
                self.checked = False
                qt.widgets.checks.append(self)

            def setChecked(self, c):  # noqa: N802
                self.checked = c

            def isChecked(self):  # noqa: N802
                return self.checked

        class QDialogButtonBox(_Widget):
            class StandardButton:
                Ok, Cancel = 1, 2

            def __init__(self, *a):
                super().__init__(*a)
                self.accepted, self.rejected = _Signal(), _Signal()

        class QMessageBox:
            @staticmethod
            def critical(parent, title, text):
                qt.messages.append(("critical", text))

            @staticmethod
            def information(parent, title, text):
                qt.messages.append(("information", text))

        for cls in (
            QApplication,
            QDialog,
            QFormLayout,
            QLabel,
            QPushButton,
            QDoubleSpinBox,
            QSpinBox,
            QComboBox,
            QCheckBox,
            QDialogButtonBox,
            QMessageBox,
        ):
            setattr(self, cls.__name__, cls)


def test_dialog_states_reference_and_swaps(monkeypatch):
    def user(w):
        ref, cmp = w.labels[0].text, w.labels[1].text
        assert "epoch A" in ref and "earlier" in ref and "epoch B" in cmp
        w.buttons[0].clicked.emit()  # Swap
        assert "epoch B" in w.labels[0].text and "epoch A" in w.labels[1].text
        w.spins[0].setValue(0.025)
        w.ints[0].setValue(6)
        assert w.combos[0].currentText() == "robust"  # Config().deformation.method
        w.combos[0].setCurrentIndex(1)
        assert w.combos[1].currentText().startswith("auto")  # network: decided from the plan
        w.combos[1].setCurrentIndex(2)
        w.checks[0].setChecked(True)

    monkeypatch.setattr(dialog, "qt_widgets", lambda: FakeQt(user))
    p = dialog.ask_detect_params("epoch A", "epoch B", DetectParams(threshold=0.05, k=3))
    assert p == DetectParams(swap=True, threshold=0.025, k=6, method="knn", move_original=True,
                             network="network")


def test_dialog_cancel_returns_none(monkeypatch):
    monkeypatch.setattr(dialog, "qt_widgets", lambda: FakeQt(lambda w: None, accept=False))
    assert dialog.ask_detect_params("a", "b") is None


def test_without_qt_defaults_are_used(monkeypatch, caplog, capsys):
    monkeypatch.setattr(dialog, "qt_widgets", lambda: None)
    caplog.set_level("INFO")
    p = dialog.ask_detect_params("a", "b", DetectParams(k=5))
    assert p == DetectParams(k=5) and "reference = 'a'" in caplog.text
    dialog.show_message("select two clouds", error=True)
    assert "[tunneldef] select two clouds" in capsys.readouterr().out


def test_message_box_with_qt(monkeypatch):
    qt = FakeQt(lambda w: None)
    monkeypatch.setattr(dialog, "qt_widgets", lambda: qt)
    dialog.show_message("boom", error=True)
    dialog.show_message("done")
    assert qt.messages == [("critical", "boom"), ("information", "done")]


def test_qt_widgets_is_none_without_pyside():
    import importlib.util

    if any(importlib.util.find_spec(m) for m in ("PySide6", "PySide2")):
        pytest.skip("a Qt binding is installed here")
    assert dialog.qt_widgets() is None
