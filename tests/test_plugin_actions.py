"""The plugin's menu actions end to end against the stand-in ``pycc`` (tests/fake_pycc.py).

The core is replaced by small fakes with known output here (selection -> arrays -> core ->
fields and entities); ``test_detect_action_with_real_core`` runs the real pipeline on a small
synthetic pair when the core is importable.
"""

from __future__ import annotations

import importlib
import subprocess
import sys
import types
from types import SimpleNamespace

import fake_pycc
import numpy as np
import pytest

from tunneldef.cloud import Cloud
from tunneldef.curve import Centerline
from tunneldef.errors import NotATunnelError

SHIFT = np.array([-420000.0, -5650000.0, -250.0])


@pytest.fixture
def pycc(monkeypatch):
    mod = fake_pycc.install()
    monkeypatch.setitem(sys.modules, "pycc", mod)
    return mod


@pytest.fixture
def plugin(pycc):
    import tunneldef_cloudcompare.plugin as plugin

    return importlib.reload(plugin)  # bind to this test's stand-in


def _entity(pycc, xyz, name, shift=SHIFT):
    local = (xyz + shift).astype(np.float32)
    pc = pycc.ccPointCloud(local[:, 0], local[:, 1], local[:, 2])
    pc.setGlobalShift(*shift)
    pc.setName(name)
    return pc


def _box_shell(n, seed, length=12.0):
    """Points on the walls/roof/floor of a 5.8 x 2.9 m box along x, in survey coordinates."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0, length, n)
    u = rng.uniform(0, 1, n)
    side = rng.integers(0, 4, n)
    y = np.where(side < 2, u * 5.8 - 2.9, np.where(side == 2, -2.9, 2.9))
    z = np.where(side == 0, 0.0, np.where(side == 1, 2.9, u * 2.9))
    return np.stack([s, y, z], axis=1) - SHIFT


def _rigid(deg, t):
    a = np.deg2rad(deg)
    m = np.eye(4)
    m[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    m[:3, 3] = t
    return m


@pytest.fixture
def pair():
    ref = _box_shell(3000, 0)
    cmp_ref_frame = _box_shell(2500, 1)
    to_ref = _rigid(2.0, [0.0, 0.0, 0.0])
    centre = cmp_ref_frame.mean(axis=0)
    to_ref[:3, 3] = centre - to_ref[:3, :3] @ centre  # rotation about the data centre
    inv = np.linalg.inv(to_ref)
    cmp = cmp_ref_frame @ inv[:3, :3].T + inv[:3, 3]
    deformation = np.where(cmp_ref_frame[:, 2] + SHIFT[2] > 2.8, -0.03, 0.001)
    return SimpleNamespace(
        ref=ref, cmp=cmp, cmp_in_ref=cmp_ref_frame, transform=to_ref, deformation=deformation
    )


class FakeCore:
    """Stands in for tunneldef.pipeline.detect: reports progress, returns the known answer."""

    def __init__(self, pair, error=None):
        self.pair, self.error, self.calls = pair, error, []
        self.quality = None

    def detect(self, ref, cmp, config=None, *, progress=None, tiles=None):
        self.calls.append(SimpleNamespace(ref=ref, cmp=cmp, config=config, tiles=tiles))
        for i in range(5):
            if progress is not None:
                progress("reference centreline" if i < 3 else "deformation", i / 4)
        if self.error is not None:
            raise self.error
        p = self.pair
        n = len(p.cmp)
        fields = {
            "deformation": p.deformation.astype(np.float32),
            "deformation_horizontal": np.zeros(n, np.float32),
            "deformation_vertical": p.deformation.astype(np.float32),
            "chainage": (p.cmp_in_ref[:, 0] + SHIFT[0]).astype(np.float32),
            "danger": (np.abs(p.deformation) > config.danger.threshold).astype(np.uint8),
            "shell": np.ones(n, np.uint8),
        }
        axis = np.array([[0.0, 0.0, 1.45], [12.0, 0.0, 1.45]]) - SHIFT
        return SimpleNamespace(
            cloud=Cloud(p.cmp_in_ref, fields),
            transform=p.transform,
            ref_centerline=Centerline.from_polyline(axis, step=0.5),
            cmp_centerline=Centerline.from_polyline(axis + [0, 0.01, 0], step=0.5),
            statistics=lambda: {"count": n, "mean": float(p.deformation.mean())},
            quality=self.quality,
        )


def _patch_core(monkeypatch, name, attr, func):
    """Replace ``name.attr`` (a core function) even if that module does not import yet."""
    try:
        mod = importlib.import_module(name)
    except ImportError:
        mod = types.ModuleType(name)
        monkeypatch.setitem(sys.modules, name, mod)
    monkeypatch.setattr(mod, attr, func, raising=False)


@pytest.fixture
def core(monkeypatch, pair):
    fake = FakeCore(pair)
    _patch_core(monkeypatch, "tunneldef.pipeline", "detect", fake.detect)
    return fake


def _select(pycc, pair):
    ref_e = _entity(pycc, pair.ref, "epoch 1")
    cmp_e = _entity(pycc, pair.cmp, "epoch 2")
    pycc.GetInstance().selected = [ref_e, cmp_e]
    return ref_e, cmp_e


def _fields(entity):
    return {
        entity.getScalarFieldName(i): entity.getScalarField(i).toArray()
        for i in range(entity.getNumberOfScalarFields())
    }


def test_detect_writes_fields_and_adds_entities(pycc, plugin, core, pair):
    from tunneldef_cloudcompare import adapter

    ref_e, cmp_e = _select(pycc, pair)
    before = np.asarray(cmp_e.points()).copy()
    params = adapter.DetectParams(threshold=0.02, k=4)
    made = plugin.detect_deformation(params, ask=False)

    call = core.calls[0]  # the core got global float64 coordinates, first selected = ref
    assert np.abs(call.ref.xyz - pair.ref).max() < 1e-5
    assert np.abs(call.cmp.xyz - pair.cmp).max() < 1e-5
    assert call.config.deformation.k == 4 and call.config.danger.threshold == 0.02
    # the deformation stage runs in chainage tiles, as `tunneldef detect` does
    assert call.tiles is not None and call.tiles["engine"] is not None
    assert call.tiles["memory_gb"] > 0

    f = _fields(cmp_e)
    assert set(f) == {
        "deformation",
        "deformation_horizontal",
        "deformation_vertical",
        "chainage",
        "danger",
        "shell",
    }
    np.testing.assert_allclose(f["deformation"], pair.deformation, atol=1e-7)
    assert f["danger"].sum() == np.sum(np.abs(pair.deformation) > 0.02)
    np.testing.assert_array_equal(np.asarray(cmp_e.points()), before)  # original not moved
    sf = cmp_e.getScalarField(cmp_e.getCurrentDisplayedScalarFieldIndex())
    assert sf.getName() == "deformation" and sf.symmetrical
    assert sf.color_scale.name == adapter.SCALE_NAME and sf.color_scale.steps[0][:3] == (255, 0, 0)
    assert sf.saturation == [0.0, made.limit] and made.colours == "red-white-blue"
    reg_sf = made.registered.getScalarField(made.registered.getCurrentDisplayedScalarFieldIndex())
    assert reg_sf.color_scale is sf.color_scale  # one scale for both clouds

    db = pycc.GetInstance().db
    assert db == [made.registered, made.ref_centerline, made.cmp_centerline]
    assert made.registered.getName() == "epoch 2 (registered)"
    assert np.abs(adapter.read_points(made.registered) - pair.cmp_in_ref).max() < 1e-5
    assert set(_fields(made.registered)) == set(f)
    assert made.ref_centerline.size() == 25 and not made.ref_centerline.closed
    assert pycc.GetInstance().frozen == [True, False]


def test_detect_prints_the_advisory_warnings(pycc, plugin, core, pair, capsys):
    """A warning the run does not stop for (a cloud that may lie on its side) reaches
    CloudCompare's console, not only the Python log."""
    from tunneldef.config import QualityConfig
    from tunneldef.quality import QualityReport, upright_check

    tall = SimpleNamespace(slices=[SimpleNamespace(ok=True, width=2.9, height=5.8)] * 9)
    core.quality = QualityReport(enforced=True)
    core.quality.add([upright_check(tall, QualityConfig())])
    _select(pycc, pair)
    assert plugin.detect_deformation(ask=False) is not None
    out = capsys.readouterr().out
    assert "[tunneldef] warning: reference_section.upright 2 > limit 1.5" in out
    assert "z points up" in out


def test_detect_rerun_replaces_fields(pycc, plugin, core, pair):
    from tunneldef_cloudcompare import adapter

    _, cmp_e = _select(pycc, pair)
    cmp_e.addScalarField("intensity", np.ones(len(pair.cmp)))
    plugin.detect_deformation(adapter.DetectParams(), ask=False)
    plugin.detect_deformation(adapter.DetectParams(threshold=0.001), ask=False)
    names = [cmp_e.getScalarFieldName(i) for i in range(cmp_e.getNumberOfScalarFields())]
    assert sorted(names) == sorted(set(names)) and len(names) == 7
    assert _fields(cmp_e)["danger"].sum() == np.sum(np.abs(pair.deformation) > 0.001)


def test_detect_swap_makes_second_selected_the_reference(pycc, plugin, core, pair):
    from tunneldef_cloudcompare import adapter

    ref_e, cmp_e = _select(pycc, pair)
    pycc.GetInstance().selected = [cmp_e, ref_e]  # user clicked the later epoch first
    plugin.detect_deformation(adapter.DetectParams(swap=True), ask=False)
    assert np.abs(core.calls[0].ref.xyz - pair.ref).max() < 1e-5
    assert cmp_e.getScalarFieldIndexByName("deformation") >= 0
    assert ref_e.getNumberOfScalarFields() == 0


def test_detect_move_original(pycc, plugin, core, pair):
    from tunneldef_cloudcompare import adapter

    _, cmp_e = _select(pycc, pair)
    plugin.detect_deformation(adapter.DetectParams(move_original=True), ask=False)
    assert np.abs(adapter.read_points(cmp_e) - pair.cmp_in_ref).max() < 1e-4


class SlowCore(FakeCore):
    """A core that keeps reporting progress (a long computation) until it is cancelled."""

    def detect(self, ref, cmp, config=None, *, progress=None, tiles=None):
        import time

        self.calls.append(SimpleNamespace(ref=ref, cmp=cmp, config=config, tiles=tiles))
        for i in range(500):  # at most 5 s
            progress("deformation", i / 500)
            time.sleep(0.01)
        raise AssertionError("the worker was never cancelled")


def test_detect_cancel_changes_nothing(pycc, plugin, monkeypatch, pair, capsys):
    from tunneldef_cloudcompare import adapter

    class CancelAfterTwo(pycc.ccProgressDialog):
        def __init__(self, cancelButton=False):  # noqa: N803
            super().__init__(cancelButton)
            self.cancel_after = 2

    monkeypatch.setattr(pycc, "ccProgressDialog", CancelAfterTwo)
    slow = SlowCore(pair)
    _patch_core(monkeypatch, "tunneldef.pipeline", "detect", slow.detect)
    _, cmp_e = _select(pycc, pair)
    assert plugin.detect_deformation(adapter.DetectParams(), ask=False) is None
    assert len(slow.calls) == 1  # the core ran on the worker and stopped at Cancel
    assert cmp_e.getNumberOfScalarFields() == 0 and pycc.GetInstance().db == []
    assert "Detect deformation: cancelled during 'deformation'; nothing was changed" in (
        capsys.readouterr().out
    )
    assert pycc.GetInstance().frozen == [True, False]  # UI unfrozen after cancel
    assert pycc.PROCESSED_EVENTS >= 2  # the GUI was kept alive while waiting


def test_actions_refuse_a_stride0_runtime(pycc, plugin, core, pair, capsys):
    from tunneldef_cloudcompare import adapter

    _, cmp_e = _select(pycc, pair)
    pycc.STRIDE0_ARRAYS = True
    assert plugin.detect_deformation(adapter.DetectParams(), ask=False) is None
    assert plugin.register_to_reference() is None
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 2 and all("stride-0 numpy arrays" in line for line in out)
    assert out[0].startswith("[tunneldef] Detect deformation: this CloudCompare Python runtime")
    assert core.calls == [] and cmp_e.getNumberOfScalarFields() == 0
    assert pycc.GetInstance().db == []


def test_actions_in_command_line_mode_say_they_need_the_window(pycc, plugin, core, capsys):
    pycc._GUI = None
    pycc._CMDLINE = pycc.ccCommandLineInterface([])
    assert plugin.detect_deformation(ask=False) is None
    out = capsys.readouterr().out
    assert "needs CloudCompare's window" in out and core.calls == []


def test_detect_core_error_is_reported(pycc, plugin, monkeypatch, pair, capsys):
    from tunneldef_cloudcompare import adapter

    fake = FakeCore(pair, error=NotATunnelError("no tunnel axis found; is this a tunnel?"))
    _patch_core(monkeypatch, "tunneldef.pipeline", "detect", fake.detect)
    _, cmp_e = _select(pycc, pair)
    assert plugin.detect_deformation(adapter.DetectParams(), ask=False) is None
    assert "Detect deformation: no tunnel axis found" in capsys.readouterr().out
    assert cmp_e.getNumberOfScalarFields() == 0


def test_detect_needs_two_clouds(pycc, plugin, core, pair, capsys):
    ref_e, _ = _select(pycc, pair)
    pycc.GetInstance().selected = [ref_e, object()]  # a non-cloud entity is ignored
    assert plugin.detect_deformation(ask=False) is None
    assert "select exactly 2 point clouds (selected: 1)" in capsys.readouterr().out
    assert core.calls == []


def test_detect_dialog_without_qt_uses_defaults(pycc, plugin, core, pair, monkeypatch):
    from tunneldef_cloudcompare import dialog

    monkeypatch.setattr(dialog, "qt_widgets", lambda: None)
    _, cmp_e = _select(pycc, pair)
    made = plugin.detect_deformation()  # asks: no Qt -> defaults, first selected = reference
    assert made is not None and core.calls[0].config.danger.threshold == 0.05


def test_extract_centerline_action(pycc, plugin, monkeypatch, pair, capsys):
    axis = np.array([[0.0, 0.0, 1.45], [12.0, 0.0, 1.45]]) - SHIFT
    slices = [
        SimpleNamespace(chainage=s, width=5.8, height=2.9, n_points=300, ok=True)
        for s in (0.5, 1.0)
    ]
    extraction = SimpleNamespace(centerline=Centerline.from_polyline(axis, step=0.5), slices=slices)
    seen = {}

    def fake_extract(xyz, *, slicing=None, settings=None, progress=None):
        seen["xyz"] = xyz
        progress("slices", 1.0)
        return extraction

    _patch_core(monkeypatch, "tunneldef.centerline", "extract_centerline", fake_extract)
    e = _entity(pycc, pair.ref, "epoch 1")
    pycc.GetInstance().selected = [e]
    poly = plugin.extract_centerline()
    assert np.abs(seen["xyz"] - pair.ref).max() < 1e-5
    assert pycc.GetInstance().db == [poly] and poly.getName() == "epoch 1 centreline"
    out = capsys.readouterr().out
    assert "12.00 m" in out and "chainage" in out and "5.800" in out


def test_register_action_prints_matrix(pycc, plugin, monkeypatch, pair, capsys):
    from tunneldef_cloudcompare import adapter

    def fake_register_epochs(ref, cmp, config=None, *, progress=None):
        reg = SimpleNamespace(transform=pair.transform, method="centerline", fitness=0.012)
        return SimpleNamespace(registration=reg)

    _patch_core(monkeypatch, "tunneldef.pipeline", "register_epochs", fake_register_epochs)
    ref_e, cmp_e = _select(pycc, pair)
    before = np.asarray(cmp_e.points()).copy()
    copy = plugin.register_to_reference()
    assert np.abs(adapter.read_points(copy) - pair.cmp_in_ref).max() < 1e-4
    np.testing.assert_array_equal(np.asarray(cmp_e.points()), before)
    out = capsys.readouterr().out
    assert "RMSE 0.0120 m" in out
    rows = [line.split() for line in out.splitlines()[-4:]]
    np.testing.assert_allclose(np.array(rows, float), pair.transform, atol=1e-8)


def test_plugin_actions_and_error_guard(pycc, plugin, monkeypatch, capsys):
    p = plugin.TunnelDefPlugin()
    actions = p.getActions()
    assert [a.name for a in actions] == [
        "Detect deformation",
        "Extract centerline",
        "Register to reference",
    ]

    def broken():
        raise RuntimeError("boom")

    plugin._action(broken)()  # must not raise into CloudCompare
    assert "RuntimeError: boom" in capsys.readouterr().out


def test_imports_stay_light():
    code = (
        "import sys, tunneldef\n"
        "assert 'pycc' not in sys.modules\n"
        "import tunneldef_cloudcompare.adapter\n"
        "assert 'pycc' not in sys.modules\n"
        "try:\n"
        "    import tunneldef_cloudcompare.plugin\n"
        "except ImportError as e:\n"
        "    assert 'pycc' in str(e)\n"
        "else:\n"
        "    raise SystemExit('plugin imported without pycc')\n"
        "sys.path.insert(0, 'tests'); import fake_pycc; sys.modules['pycc'] = fake_pycc\n"
        "import tunneldef_cloudcompare.plugin\n"
        "heavy = [m for m in ('open3d', 'PySide2', 'tunneldef.pipeline', 'scipy',\n"
        "                     'matplotlib') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    from conftest import REPO

    r = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr


@pytest.mark.slow
def test_detect_action_with_real_core(pycc, plugin, monkeypatch):
    """The real pipeline on a small synthetic pair in survey coordinates, through the adapter:
    what lands on the entities must be exactly what the core returned (the core's accuracy
    is tested with the core)."""
    try:
        import tunneldef.pipeline as pipeline
        from tunneldef.synth import DeformationSpec, PairSpec, TunnelSpec, make_pair
    except ImportError as exc:
        pytest.skip(f"core not available yet: {exc}")
    from tunneldef_cloudcompare import adapter

    seen = {}
    real_detect = pipeline.detect

    def spy(ref, cmp, config=None, *, progress=None, tiles=None):
        seen["result"] = real_detect(ref, cmp, config, progress=progress, tiles=tiles)
        seen["ref"], seen["cmp"] = ref, cmp
        return seen["result"]

    monkeypatch.setattr(pipeline, "detect", spy)
    pair = make_pair(
        PairSpec(
            # a chamber: in a featureless drift the axial position is undetermined
            tunnel=TunnelSpec(length=20.0, chamber=True, density=60.0, outlier_fraction=0.0),
            deformations=(DeformationSpec(kind="roof_sag", chainage=10.0, amplitude=0.05),),
            translation=(512000.0, 5611000.0, 310.0),  # survey-sized coordinates
            seed=0,
        )
    )
    # on a 2**-16 m grid the float32 local coordinates (|x| < 256 m) are exact, so the core
    # sees exactly these coordinates
    ref_xyz, cmp_xyz = (np.round(c.xyz * 2**16) / 2**16 for c in (pair.ref, pair.cmp))
    ref_e = _entity(pycc, ref_xyz, "ref", shift=-np.round(ref_xyz.mean(axis=0)))
    cmp_e = _entity(pycc, cmp_xyz, "cmp", shift=-np.round(cmp_xyz.mean(axis=0)))
    pycc.GetInstance().selected = [ref_e, cmp_e]
    made = plugin.detect_deformation(adapter.DetectParams(threshold=0.02), ask=False)
    assert made is not None, "the core failed on a clean synthetic pair"
    res = seen["result"]
    np.testing.assert_array_equal(seen["ref"].xyz, ref_xyz)  # global coordinates in, exact
    np.testing.assert_array_equal(seen["cmp"].xyz, cmp_xyz)
    f = _fields(cmp_e)
    extra = [n for n in adapter.OPTIONAL_FIELDS if n in res.cloud.fields]
    assert {"significant", "lod95"} <= set(extra)  # the default (robust) estimator's fields
    assert set(f) == set(adapter.DEFORMATION_FIELDS) | set(extra)
    for name in (*adapter.DEFORMATION_FIELDS, *extra):
        np.testing.assert_allclose(
            f[name], np.asarray(res.cloud.fields[name], np.float32), atol=0, err_msg=name
        )
    assert np.abs(adapter.read_points(made.registered) - res.cloud.xyz).max() < 1e-4
    ref_line = adapter.read_points(made.ref_centerline.getAssociatedCloud())
    assert np.abs(ref_line - res.ref_centerline.points).max() < 1e-4
    assert res.ref_centerline.length > 15.0  # a 20 m tunnel (the overlap of both scans)


@pytest.mark.slow
def test_extract_centerline_action_with_real_core(pycc, plugin, monkeypatch, capsys):
    """The real centreline extraction through the action: polyline = the result's curve, and
    the console table = the result's slices."""
    try:
        import tunneldef.centerline as centerline
        from tunneldef.synth import TunnelSpec, make_tunnel
    except ImportError as exc:
        pytest.skip(f"core not available yet: {exc}")
    from tunneldef_cloudcompare import adapter

    seen = {}
    real = centerline.extract_centerline

    def spy(xyz, **kwargs):
        seen["res"] = real(xyz, **kwargs)
        return seen["res"]

    monkeypatch.setattr(centerline, "extract_centerline", spy)
    cloud, _ = make_tunnel(TunnelSpec(length=16.0, density=60.0, outlier_fraction=0.0), seed=1)
    xyz = np.round((cloud.xyz + [512000.0, 5611000.0, 310.0]) * 2**16) / 2**16
    e = _entity(pycc, xyz, "drift", shift=-np.round(xyz.mean(axis=0)))
    pycc.GetInstance().selected = [e]
    poly = plugin.extract_centerline()
    assert poly is not None
    res = seen["res"]
    line = adapter.read_points(poly.getAssociatedCloud())
    assert np.abs(line - res.centerline.points).max() < 1e-4
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    start = next(i for i, r in enumerate(rows) if r[:3] == ["chainage", "width", "height"])
    table = rows[start + 1 : start + 1 + len(res.slices)]
    assert len(table) == len(res.slices)
    widths = np.array([float(r[1]) for r in table])
    expected = np.array([s.width for s in res.slices])
    np.testing.assert_allclose(widths, expected, atol=5e-4, equal_nan=True)
    assert 5.5 < np.nanmedian(widths) < 6.1  # the synthetic section is 5.8 m wide


# --------------------------------------------------------------------------- drift networks


def _fake_network(points_per_edge):
    """A stand-in CenterlineNetwork: edges with ids, names, curves, nodes and slices."""
    edges = tuple(
        SimpleNamespace(id=k, name=f"e{k}", centerline=Centerline.from_polyline(p, step=0.5),
                        nodes=(-1, 0), slices=[SimpleNamespace(ok=True)])
        for k, p in enumerate(points_per_edge)
    )
    return SimpleNamespace(edges=edges, junctions=(SimpleNamespace(id=0),))


def test_detect_on_a_network_draws_one_polyline_per_edge_and_writes_branch(
    pycc, plugin, monkeypatch, pair
):
    from tunneldef_cloudcompare import adapter

    main = np.array([[0.0, 0.0, 1.45], [12.0, 0.0, 1.45]]) - SHIFT
    xc = np.array([[6.0, -4.0, 1.45], [6.0, 4.0, 1.45]]) - SHIFT
    seen = {}

    def fake_detect_network(ref, cmp, config=None, *, progress=None):
        seen["called"] = True
        base = FakeCore(pair).detect(ref, cmp, config)
        base.cloud.fields["branch"] = np.where(pair.cmp_in_ref[:, 1] + SHIFT[1] > 0, 1,
                                               0).astype(np.uint16)
        base.ref_network = _fake_network([main, xc])
        base.cmp_network = _fake_network([main + [0, 0.01, 0], xc + [0, 0.01, 0]])
        return base

    _patch_core(monkeypatch, "tunneldef.pipeline", "detect_network", fake_detect_network)
    from tunneldef_cloudcompare import jobs

    monkeypatch.setattr(jobs, "is_network", lambda clouds, config=None: True)
    ref_e, cmp_e = _select(pycc, pair)
    made = plugin.detect_on(ref_e, cmp_e)  # auto: the plan says network
    assert seen["called"] and len(made.ref_lines) == 2 and len(made.cmp_lines) == 2
    assert pycc.GetInstance().db == [made.registered, *made.ref_lines, *made.cmp_lines]
    names = [line.getName() for line in made.ref_lines + made.cmp_lines]
    assert names[0] == "reference centreline: edge 0 e0 (12.0 m)"
    assert names[3] == "compared centreline: edge 1 e1 (8.0 m)"
    xyz = adapter.read_points(made.ref_lines[1].getAssociatedCloud())
    assert np.abs(xyz - Centerline.from_polyline(xc, step=0.5).points).max() < 1e-4
    branch = _fields(cmp_e)["branch"]
    assert set(np.unique(branch)) == {0.0, 1.0}


def test_network_choice_single_keeps_the_single_drift_stage(pycc, plugin, core, pair,
                                                             monkeypatch):
    from tunneldef_cloudcompare import jobs
    from tunneldef_cloudcompare.params import DetectParams

    monkeypatch.setattr(jobs, "is_network", lambda clouds, config=None: pytest.fail("asked"))
    ref_e, cmp_e = _select(pycc, pair)
    made = plugin.detect_on(ref_e, cmp_e, DetectParams(network="single"))
    assert len(core.calls) == 1 and len(made.ref_lines) == 1
    with pytest.raises(ValueError, match="network must be one of"):
        jobs.compute_detect(None, None, network="maybe")


@pytest.mark.slow
def test_extract_centerline_on_a_network_with_real_core(pycc, plugin, capsys):
    """A synthetic drift network (a crossing and a tee): one polyline per edge, equal to the
    core's edge curves; the console lists the edges."""
    from test_network import small_network
    from tunneldef_cloudcompare import adapter

    from tunneldef.centerline.network import extract_network
    from tunneldef.synth.network import make_network_pair

    p = make_network_pair(network=small_network(), deformations=(), ref_coverage=None,
                          cmp_coverage=None, density=80.0, drift=0.0, equipment=False, seed=4)
    xyz = p.ref.xyz + [512000.0, 5611000.0, 310.0]
    e = _entity(pycc, xyz, "net", shift=-np.round(xyz.mean(axis=0)))
    polys = plugin.centerline_on(e)
    net = extract_network(adapter.entity_to_cloud(e).xyz).network
    assert isinstance(polys, list) and len(polys) == len(net.edges) == 3
    for poly, edge in zip(polys, net.edges, strict=True):
        assert np.abs(adapter.read_points(poly.getAssociatedCloud())
                      - edge.centerline.points).max() < 1e-3
        assert f"edge {edge.id}" in poly.getName()
    assert "3 edges, 2 junctions" in capsys.readouterr().out
