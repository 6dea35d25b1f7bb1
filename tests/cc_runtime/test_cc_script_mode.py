"""The plugin's three jobs in the real CloudCompare, command-line mode (``-PYTHON_SCRIPT``):
centreline, registration and detection on a small survey-coordinate pair loaded with a global
shift, compared with the core on the same files."""

from __future__ import annotations

import numpy as np
import pytest

from .checks import assert_fields_equal_core, assert_xyz
from .conftest import load_run
from .runner import HERE

pytestmark = pytest.mark.cloudcompare


@pytest.fixture(scope="module")
def run(cc_runtime, cc_pair, tmp_path_factory):
    work = tmp_path_factory.mktemp("cc_script")
    proc = cc_runtime.run_script(
        HERE / "script_actions.py", list(cc_pair), workdir=work, env_extra={"TDCC_OUT": str(work)}
    )
    return load_run(work, proc)


def test_runs_the_three_jobs_without_error(run):
    assert run.proc.returncode == 0, run.log
    assert run.report.get("finished") and run.report["errors"] == [], run.report["errors"]
    assert [a["action"] for a in run.report["actions"]] == ["centerline", "register", "detect"]
    assert run.report["runtime_check"] == "passed"
    assert 0 not in run.report["points_strides"]


def test_survey_coordinates_come_through_the_global_shift(run, core):
    for key in ("ref", "cmp"):
        shift = np.array(run.report["shifts"][key])
        assert np.abs(shift).max() > 1e5, f"{key}: no global shift applied ({shift})"
    # on a 2**-10 m grid the float32 local coordinates are exact: the core's input is the file's
    assert_xyz(run.arrays["ref_xyz"], core.ref.xyz, "reference", tol=1e-9)
    assert_xyz(run.arrays["cmp_xyz"], core.cmp.xyz, "compared", tol=1e-9)


def test_detect_fields_equal_the_core(run, core):
    fields = {k.split(":", 1)[1]: v for k, v in run.arrays.items() if k.startswith("field:")}
    assert_fields_equal_core(fields, core.result)
    np.testing.assert_allclose(
        run.arrays["registered_deformation"], fields["deformation"], atol=0, equal_nan=True
    )


def test_new_entities_and_the_original_left_in_place(run, core):
    res = core.result
    assert_xyz(run.arrays["registered"], res.cloud.xyz, "registered copy (detect)")
    assert_xyz(run.arrays["registered_copy"], res.cloud.xyz, "registered copy (register)")
    assert_xyz(run.arrays["cmp_after"], core.cmp.xyz, "original left in place", tol=1e-9)
    assert_xyz(run.arrays["ref_centerline"], res.ref_centerline.points, "reference centreline")
    assert_xyz(run.arrays["cmp_centerline"], res.cmp_centerline.points, "compared centreline")
    assert_xyz(run.arrays["centerline"], res.ref_centerline.points, "Extract centerline")
    detect = run.report["actions"][-1]
    assert detect["polylines"] == ["reference centreline", "compared centreline"]
    assert np.allclose(detect["registered_shift"], run.report["shifts"]["ref"])


def test_colour_scale_red_white_blue_centred_on_zero(run, core):
    from tunneldef_cloudcompare.colours import symmetric_limit

    detect = run.report["actions"][-1]
    limit = symmetric_limit(core.result.cloud.fields["deformation"], threshold=0.05)
    assert detect["limit"] == pytest.approx(limit, rel=1e-9)
    assert detect["colours"] == "red-white-blue"
    scale = detect["scale"]
    assert scale["displayed"] and scale["symmetrical"]
    # CloudCompare clamps the saturation to the field's largest |value|
    d = np.asarray(core.result.cloud.fields["deformation"], dtype=np.float32)
    shown = min(limit, float(np.nanmax(np.abs(d))))
    assert scale["saturation"] == pytest.approx([0.0, shown], rel=1e-6)


def test_a_refused_detection_returns_with_one_line_instead_of_a_modal_box(cc_runtime, tmp_path):
    """In command-line mode nobody can close a message box: a refusal (here two clouds that
    are no tunnel) must come back as a console line and a None, not wait for ever."""
    import subprocess

    from tunneldef.cloud import Cloud
    from tunneldef.io import write

    rng = np.random.default_rng(0)
    paths = []
    for name in ("a", "b"):
        path = tmp_path / f"{name}.ply"
        write(path, Cloud(np.round(rng.uniform(0.0, 5.0, (20_000, 3)) * 2**10) / 2**10))
        paths.append(path)
    work = tmp_path / "run"
    work.mkdir()
    try:
        proc = cc_runtime.run_script(
            HERE / "script_actions.py", paths, workdir=work, timeout=120,
            env_extra={"TDCC_OUT": str(work), "TDCC_ACTIONS": "detect"},
        )
    except subprocess.TimeoutExpired:
        pytest.fail("CloudCompare hung on a refused detection (a modal message box?)")
    run = load_run(work, proc)
    assert run.report.get("finished"), run.log
    assert len(run.report["errors"]) == 1 and "returned None" in run.report["errors"][0]
    assert "Detect deformation: " in proc.stdout and "tunnel" in proc.stdout
