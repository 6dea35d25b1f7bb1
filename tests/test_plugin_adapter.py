"""The CloudCompare adapter against the stand-in ``pycc`` (tests/fake_pycc.py).

What is checked here is our side of the documented runtime API (shift/scale arithmetic, the
points() fallback, field replacement, colour-scale calls, threading/cancel plumbing). That the
real runtime behaves as documented is not checked here (no runtime on this machine).
"""

from __future__ import annotations

import sys
from types import SimpleNamespace

import fake_pycc  # noqa: I001 - tests/ is on sys.path (rootdir conftest)
import numpy as np
import pytest


@pytest.fixture
def pycc(monkeypatch):
    mod = fake_pycc.install()
    monkeypatch.setitem(sys.modules, "pycc", mod)
    return mod


@pytest.fixture
def adapter(pycc):
    from tunneldef_cloudcompare import adapter

    return adapter


SHIFT = np.array([-500000.0, -5600000.0, -300.0])  # survey coordinates: E ~5e5, N ~5.6e6


def _survey_points(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    local = rng.uniform(-20, 20, size=(n, 3))
    return local - SHIFT  # global = local - shift


def _entity(pycc, global_xyz, *, shift=SHIFT, scale=1.0, name="scan"):
    local = ((global_xyz + shift) * scale).astype(np.float32)
    pc = pycc.ccPointCloud(local[:, 0], local[:, 1], local[:, 2])
    pc.setGlobalShift(*shift)
    pc.setGlobalScale(scale)
    pc.setName(name)
    return pc


def test_local_global_round_trip_keeps_survey_precision(adapter):
    xyz = _survey_points()
    local = adapter.global_to_local(xyz, SHIFT, 1.0)
    assert local.dtype == np.float32
    back = adapter.local_to_global(local, SHIFT, 1.0)
    assert np.abs(back - xyz).max() < 1e-5  # float32 of |local| <= 35 m: ~4 um


def test_scale_is_applied_both_ways(adapter):
    xyz = _survey_points(100)
    local = adapter.global_to_local(xyz, SHIFT, 1000.0)  # millimetre local units
    np.testing.assert_allclose(local, (xyz + SHIFT) * 1000.0, atol=0.01)
    np.testing.assert_allclose(adapter.local_to_global(local, SHIFT, 1000.0), xyz, atol=1e-5)


def test_large_local_coordinates_warn(adapter, caplog):
    adapter.global_to_local(np.array([[5e5, 5.6e6, 0.0]]), np.zeros(3), 1.0)
    assert "lose precision" in caplog.text


def test_read_points_applies_shift_and_scale(pycc, adapter):
    xyz = _survey_points()
    e = _entity(pycc, xyz, scale=2.0)
    got = adapter.read_points(e)
    assert got.dtype == np.float64 and got.shape == xyz.shape
    assert np.abs(got - xyz).max() < 1e-5


def test_read_points_refuses_stride0_points(pycc, adapter):
    xyz = _survey_points(300)
    e = _entity(pycc, xyz)
    pycc.STRIDE0_ARRAYS = True
    assert np.all(np.asarray(e.points()) == np.asarray(e.points())[0])  # the quirk is on
    with pytest.raises(adapter.BrokenRuntimeError, match=r"stride-0 .*strides \(0, 4\)"):
        adapter.read_points(e)


def test_runtime_check_passes_on_a_sound_runtime_and_refuses_stride0(pycc, adapter):
    adapter.check_runtime(pycc)  # sound: no error
    from tunneldef_cloudcompare.runtime import reset_runtime_check

    reset_runtime_check()
    pycc.STRIDE0_ARRAYS = True
    with pytest.raises(adapter.BrokenRuntimeError) as info:
        adapter.check_runtime(pycc)
    message = str(info.value)
    assert "\n" not in message and "stride-0" in message and "pybind11 >= 2.13" in message


def test_move_entity_refuses_lost_matrix_writes(pycc, adapter):
    xyz = _survey_points(50)
    e = _entity(pycc, xyz)
    before = np.asarray(e.points()).copy()
    pycc.STRIDE0_ARRAYS = True
    t = np.eye(4)
    t[:3, 3] = [1.0, 2.0, 3.0]
    with pytest.raises(adapter.BrokenRuntimeError, match="ccGLMatrix.asArray"):
        adapter.move_entity(e, t)
    pycc.STRIDE0_ARRAYS = False
    np.testing.assert_array_equal(np.asarray(e.points()), before)  # not moved at all


def test_scale_getter_bug_assumes_unit_scale(pycc, adapter, caplog):
    xyz = _survey_points(50)
    e = _entity(pycc, xyz)
    pycc.SCALE_GETTER_BUG = True
    shift, scale = adapter.shift_and_scale(e)
    assert scale == 1.0 and np.allclose(shift, SHIFT)
    assert "cannot read the global scale" in caplog.text


def test_entity_to_cloud_meta(pycc, adapter):
    e = _entity(pycc, _survey_points(10), name="epoch 1")
    c = adapter.entity_to_cloud(e)
    assert c.meta["name"] == "epoch 1" and c.meta["global_shift"] == SHIFT.tolist()
    assert len(c) == 10 and c.fields == {}


def test_write_scalar_fields_replaces_same_name(pycc, adapter):
    e = _entity(pycc, _survey_points(100))
    e.addScalarField("intensity", np.arange(100))
    adapter.write_scalar_fields(e, {"deformation": np.full(100, 0.01), "danger": np.zeros(100)})
    idx = adapter.write_scalar_fields(e, {"deformation": np.full(100, -0.02)})
    assert e.getNumberOfScalarFields() == 3  # intensity, danger, deformation: no duplicate
    names = [e.getScalarFieldName(i) for i in range(3)]
    assert sorted(names) == ["danger", "deformation", "intensity"]
    sf = e.getScalarField(idx["deformation"])
    np.testing.assert_allclose(sf.toArray(), -0.02, rtol=1e-6)
    assert sf.getMin() == pytest.approx(-0.02) and sf.getMax() == pytest.approx(-0.02)
    np.testing.assert_array_equal(e.getScalarField(0).toArray(), np.arange(100))  # untouched


def test_write_scalar_fields_rejects_wrong_length(pycc, adapter):
    e = _entity(pycc, _survey_points(10))
    with pytest.raises(ValueError, match="has shape \\(9,\\); the cloud has 10 points"):
        adapter.write_scalar_fields(e, {"deformation": np.zeros(9)})
    assert e.getNumberOfScalarFields() == 0  # checked before anything is written


def test_symmetric_limit():
    from tunneldef_cloudcompare.adapter import symmetric_limit

    rng = np.random.default_rng(1)
    d = rng.normal(0, 0.01, 10000)
    d[:10] = 5.0  # outliers do not set the scale
    lim = symmetric_limit(d, threshold=0.005)
    assert 0.018 < lim < 0.026  # 98th percentile of |N(0, 1 cm)| = 2.33 cm
    assert symmetric_limit(d, threshold=0.1) == 0.1
    assert symmetric_limit(np.full(5, np.nan)) == 1e-3


RED, WHITE, BLUE = (255, 0, 0), (255, 255, 255), (0, 0, 255)


def test_red_white_blue_scale_from_xml(pycc, adapter):
    scale = adapter.red_white_blue_scale()
    assert isinstance(scale, pycc.ccColorScale.Shared)  # what setColorScale takes
    assert scale.relative and scale.uuid == adapter.SCALE_UUID
    assert [s[:3] for s in scale.steps] == [RED, WHITE, BLUE]  # low (into the tunnel) = red
    assert [s[3] for s in scale.steps] == [0.0, 0.5, 1.0]
    adapter.red_white_blue_scale()  # listed once in the scale manager, replaced on a re-run
    assert list(pycc.ccColorScalesManager.GetUniqueInstance().scales) == [adapter.SCALE_UUID]


def _deformation_entity(pycc, adapter):
    e = _entity(pycc, _survey_points(100))
    adapter.write_scalar_fields(
        e, {"chainage": np.arange(100.0), "deformation": np.linspace(-0.03, 0.01, 100)}
    )
    return e


def test_show_diverging_centres_on_zero(pycc, adapter):
    e = _deformation_entity(pycc, adapter)
    scale = adapter.red_white_blue_scale()
    assert adapter.show_diverging(e, "deformation", limit=0.03, scale=scale) == "red-white-blue"
    idx = e.getScalarFieldIndexByName("deformation")
    sf = e.getScalarField(idx)
    assert e.getCurrentDisplayedScalarFieldIndex() == idx and e.sf_shown and e.sf_scale_shown
    assert sf.color_scale is scale and sf.symmetrical
    assert sf.saturation == [0.0, 0.03]
    assert sf.displayed == [None, None]  # display range untouched: nothing gets hidden
    with pytest.raises(ValueError, match="no scalar field 'nope'"):
        adapter.show_diverging(e, "nope", limit=0.03)


def test_show_diverging_falls_back_to_builtin_scale(pycc, adapter, monkeypatch):
    monkeypatch.delattr(pycc.ccColorScale, "LoadFromXML")  # a runtime without it
    e = _deformation_entity(pycc, adapter)
    assert adapter.red_white_blue_scale() is None
    shown = adapter.show_diverging(e, "deformation", limit=0.03, scale=None)
    sf = e.getScalarField(e.getScalarFieldIndexByName("deformation"))
    assert shown == "blue-white-red" and sf.color_scale.name == "BWR" and sf.symmetrical
    made = adapter.DetectEntities(None, limit=0.03, colours=shown)
    assert made.legend().startswith("colour scale: blue = into the tunnel")
    monkeypatch.delattr(pycc.ccScalarField, "setColorScale")
    assert adapter.show_diverging(e, "deformation", limit=0.03) == "default"


def test_scale_load_failure_falls_back(pycc, adapter, monkeypatch):
    def broken(filename):
        raise RuntimeError("cannot parse")

    monkeypatch.setattr(pycc.ccColorScale, "LoadFromXML", staticmethod(broken))
    assert adapter.red_white_blue_scale() is None


def test_make_point_cloud_inherits_shift(pycc, adapter):
    ref = _entity(pycc, _survey_points(10), scale=1.0)
    xyz = _survey_points(50, seed=3)
    pc = adapter.make_point_cloud(xyz, like=ref, name="copy", fields={"a": np.ones(50)})
    assert pc.getName() == "copy" and pc.getScalarFieldIndexByName("a") == 0
    assert np.abs(np.asarray(pc.points())).max() < 40  # small local coordinates
    assert np.abs(adapter.read_points(pc) - xyz).max() < 1e-5


def test_copy_shift_without_copy_method(pycc, adapter, monkeypatch):
    ref = _entity(pycc, _survey_points(10), scale=4.0)
    monkeypatch.delattr(pycc.ccShiftedObject, "copyGlobalShiftAndScale")
    dst = pycc.ccPointCloud("x")
    adapter.copy_shift_and_scale(dst, ref)
    shift, scale = adapter.shift_and_scale(dst)
    assert np.allclose(shift, SHIFT) and scale == 4.0


def test_make_polyline(pycc, adapter):
    ref = _entity(pycc, _survey_points(10))
    pts = _survey_points(7, seed=5)
    poly, vertices = adapter.make_polyline(pts, like=ref, name="axis", colour=(0, 255, 0))
    assert poly.indices == list(range(7)) and not poly.closed and poly.getName() == "axis"
    assert poly.cloud is vertices and vertices.getName() == "axis vertices"
    assert poly.colour.g == 255 and poly.colours_shown
    assert np.abs(adapter.read_points(poly.getAssociatedCloud()) - pts).max() < 1e-5
    shift, _ = adapter.shift_and_scale(poly)
    assert np.allclose(shift, SHIFT)


@pytest.mark.parametrize("scale", [1.0, 100.0])
def test_move_entity_applies_global_transform(pycc, adapter, scale):
    xyz = _survey_points(200)
    e = _entity(pycc, xyz, scale=scale)
    a = np.deg2rad(3.0)
    t = np.eye(4)
    t[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    centre = xyz.mean(axis=0)
    t[:3, 3] = centre - t[:3, :3] @ centre + [0.5, -0.2, 0.1]  # rotate about the data
    adapter.move_entity(e, t)
    expected = xyz @ t[:3, :3].T + t[:3, 3]
    assert np.abs(adapter.read_points(e) - expected).max() < 2e-5 * max(1.0, 1.0 / scale) + 1e-4


def test_local_transform_identity_with_zero_shift(adapter):
    t = np.eye(4)
    t[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(adapter.local_transform(t, np.zeros(3), 1.0), t)


def test_config_from_params(adapter):
    from tunneldef.config import Config

    p = adapter.DetectParams.from_config(Config(), threshold=0.02, k=5, method="robust")
    cfg = adapter.config_from_params(p)
    assert cfg.danger.threshold == 0.02 and cfg.deformation.k == 5
    assert cfg.deformation.method == "robust"
    d, c = adapter.DetectParams.from_config(), Config()
    assert (d.threshold, d.k, d.method, d.swap) == (
        c.danger.threshold,
        c.deformation.k,
        c.deformation.method,
        False,
    )
    assert d.method == "robust"  # the project default estimator
    assert adapter.DetectParams() == d  # plain defaults follow Config too


def test_progress_bridge_updates_and_cancels(pycc, adapter):
    from tunneldef.progress import Cancelled

    dlg = pycc.ccProgressDialog(cancelButton=True)
    bridge = adapter.ProgressBridge(dlg)
    dlg.start()
    bridge("centreline", 0.5)
    bridge("centreline", 1.0)
    bridge("registration", 0.25)
    assert dlg.values == [50.0, 99.0, 25.0] and bridge.stages == ["centreline", "registration"]
    # a stage that ends does not end the dialog: its Cancel button stays on screen
    assert dlg.visible and dlg.auto_closed == 0
    dlg.cancel_after = 3
    with pytest.raises(Cancelled, match="registration"):
        bridge("registration", 0.5)


def test_run_guarded_captures_errors(adapter):
    from tunneldef.errors import NotATunnelError
    from tunneldef.progress import Cancelled

    assert adapter.run_guarded(lambda x: x + 1, 1).value == 2

    def boom():
        raise NotATunnelError("no axis")

    out = adapter.run_guarded(boom)
    assert not out.ok and not out.cancelled and isinstance(out.error, NotATunnelError)
    with pytest.raises(NotATunnelError, match="no axis"):
        out.unwrap()

    def stop():
        raise Cancelled("stop")

    assert adapter.run_guarded(stop).cancelled


def test_format_matrix_and_slice_table(adapter):
    text = adapter.format_matrix(np.eye(4))
    assert text.splitlines()[0].split() == ["1.00000000", "0.00000000", "0.00000000", "0.00000000"]
    rec = [
        SimpleNamespace(chainage=0.5, width=5.8, height=2.86, n_points=1200, ok=True),
        {"chainage": 1.0, "width": 5.75, "height": 2.9, "n_points": 1100, "ok": False},
    ]
    table = adapter.format_slice_table(rec).splitlines()
    assert table[0].split() == ["chainage", "width", "height", "n_points", "ok"]
    assert table[1].split() == ["0.500", "5.800", "2.860", "1200", "yes"]
    assert table[2].split()[-1] == "no"
