"""The three menu actions in CloudCompare's real window (under Xvfb), driven through the menu
*Plugins > Python Plugin > Plugins > tunneldef* by ``gui_harness``: detect (with "Also move the
original" ticked), extract centreline, register, and Cancel during a detection, on a
survey-coordinate pair opened with CloudCompare's global shift; compared with the core on the
same files."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from .checks import (
    MOVED_TOL,
    assert_fields_equal_core,
    assert_red_white_blue,
    assert_xyz,
    samples_inside,
)
from .conftest import load_run

pytestmark = pytest.mark.cloudcompare


@pytest.fixture(scope="module")
def gui(cc_runtime, cc_pair, tmp_path_factory):
    for tool in ("xvfb-run", "xauth"):
        if shutil.which(tool) is None:
            pytest.fail(f"{tool} is missing: apt-get install -y xvfb xauth")
    if not list(Path("/usr/lib/python3/dist-packages/PySide2").glob("QtWidgets*.so")):
        pytest.fail("the GUI harness needs PySide2: apt-get install -y python3-pyside2.qtwidgets")
    work = tmp_path_factory.mktemp("cc_gui")
    proc = cc_runtime.run_gui(list(cc_pair), workdir=work)
    return load_run(work, proc)


def _fields(arrays, step):
    prefix = f"{step}:field:"
    return {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}


def test_menu_runs_and_path(gui):
    assert gui.report.get("finished"), gui.log
    assert gui.report["errors"] == [], gui.report["errors"]
    assert gui.report["menu_path"] == ["Plugins", "Python Plugin", "Plugins", "tunneldef"]
    assert set(gui.report["steps"]) == {"detect", "centerline", "register", "cancel"}
    titles = [m["title"] for m in gui.report["modals"]]
    assert titles.count("tunneldef: detect deformation") == 2  # the plugin's dialog each time
    assert not [m for m in gui.report["modals"] if "text" in m], "an error box was shown"


def test_global_shift_and_detect_fields_equal_the_core(gui, core):
    for key, shift in gui.report["shifts"].items():
        assert np.abs(shift).max() > 1e5, f"{key}: no global shift ({shift})"
    step = gui.report["steps"]["detect"]
    assert step["selected"] == ["ref - Cloud", "cmp - Cloud"]  # click order: reference first
    assert_fields_equal_core(_fields(gui.arrays, "detect"), core.result)
    assert_xyz(gui.arrays["detect:registered"], core.result.cloud.xyz, "registered copy")


def test_colour_scale_and_polylines(gui, core):
    step = gui.report["steps"]["detect"]
    assert step["displayed"] == "deformation" and step["symmetrical"]
    lim = step["saturation_stop"]
    assert_red_white_blue(step["rgb"], samples_inside(core.result.cloud.fields["deformation"], lim))
    res = core.result
    assert_xyz(gui.arrays["detect:reference_centerline"], res.ref_centerline.points, "ref line")
    assert_xyz(gui.arrays["detect:compared_centerline"], res.cmp_centerline.points, "cmp line")
    assert any("red = into the tunnel" in line for line in step["console"] +
               gui.report["steps"]["centerline"]["console"])


def test_extract_centerline_and_register(gui, core):
    res = core.result
    assert gui.report["steps"]["centerline"]["new"] == ["ccPolyline: ref - Cloud centreline"]
    assert_xyz(gui.arrays["centerline"], res.ref_centerline.points, "Extract centerline")
    assert gui.report["steps"]["register"]["new"] == ["ccPointCloud: cmp - Cloud (registered)"]
    assert_xyz(gui.arrays["register:copy"], res.cloud.xyz, "Register to reference")


def test_cancel_changes_nothing(gui):
    step = gui.report["steps"]["cancel"]
    assert "cancel_pressed" in gui.report
    assert step["new"] == [] and step["deformation_unchanged"]
    assert step["cmp_fields_after"] == step["cmp_fields_before"]
    lines = [ln for ln in gui.report["console"] if "; nothing was changed" in ln]
    assert len(lines) == 1 and "Detect deformation: cancelled during '" in lines[0], lines
    stage = lines[0].split("cancelled during '")[1].split("'")[0]
    assert not stage.startswith(("deformation", "sections")), stage  # stopped early


def test_move_the_original(gui, core):
    assert any(m.get("ticked") == "move the original" for m in gui.report["modals"])
    assert_xyz(gui.arrays["detect:cmp_xyz"], core.result.cloud.xyz, "moved", tol=MOVED_TOL)
