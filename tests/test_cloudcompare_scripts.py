"""cloudcompare_scripts/: the in-CloudCompare script (stand-in pycc), the Open3D/matplotlib
viewer (non-GUI path), and round trips through the real CloudCompare 2.11 command line."""

from __future__ import annotations

import importlib
import json
import os
import runpy
import shutil
import subprocess
import sys
import types
import xml.etree.ElementTree as ET
from pathlib import Path
from types import SimpleNamespace

import fake_pycc
import numpy as np
import pytest
from conftest import REPO

from tunneldef.cloud import Cloud
from tunneldef.config import DeformationConfig

SCRIPTS = REPO / "cloudcompare_scripts"
CLOUDCOMPARE = shutil.which("CloudCompare")
needs_cc = pytest.mark.skipif(CLOUDCOMPARE is None, reason="CloudCompare binary not installed")
CC_TIMEOUT = 120


def _script(name):
    return SimpleNamespace(**runpy.run_path(str(SCRIPTS / name), run_name=f"cc_{name[:-3]}"))


def _write(path, cloud):
    from tunneldef.io import write

    write(path, cloud)


def _cloudcompare(*args, cwd):
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    r = subprocess.run(
        [CLOUDCOMPARE, "-SILENT", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=CC_TIMEOUT,
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return r.stdout


def _read_asc(path):
    with open(path) as fh:
        header = fh.readline().lstrip("/").split()
    return header, np.loadtxt(path, skiprows=1, ndmin=2)


def _result_cloud(n=3000, seed=0):
    """A result-like cloud in survey coordinates with the contract's fields."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 10, (n, 3)) + [512345.0, 5612345.0, 312.0]
    d = rng.normal(0, 0.01, n)
    d[:50] = -0.08  # a sag
    fields = {
        "intensity": rng.integers(0, 4000, n).astype(np.uint16),  # an original attribute
        "deformation": d.astype(np.float32),
        "deformation_horizontal": (0.3 * d).astype(np.float32),
        "deformation_vertical": (0.9 * d).astype(np.float32),
        "chainage": (xyz[:, 0] - 512345.0).astype(np.float32),
        "danger": (np.abs(d) > 0.05).astype(np.uint8),
    }
    return Cloud(xyz, fields)


# --------------------------------------------------------------------------- viewer


def test_viewer_colours_are_diverging():
    view = _script("view_deformation.py")
    rgb = view.colours(np.array([-0.1, 0.0, 0.1, np.nan]), 0.05)
    # matplotlib RdBu ends (as the report figures): dark red, near-white, dark blue
    np.testing.assert_allclose(rgb[0], [0.404, 0.0, 0.122], atol=0.01)  # into the tunnel: red
    np.testing.assert_allclose(rgb[1], [0.969, 0.969, 0.969], atol=0.01)  # no change: white
    np.testing.assert_allclose(rgb[2], [0.020, 0.188, 0.380], atol=0.01)  # outward: blue
    np.testing.assert_allclose(rgb[3], [0.6, 0.6, 0.6])


@pytest.mark.parametrize("heading", [0.0, 200.0])
def test_viewer_unrolls_roof_walls_floor(heading):
    """A 6 x 3 m box along a heading: roof at 0 deg, left wall +90, right wall -90, floor
    +-180, with 'left' taken looking towards increasing chainage."""
    view = _script("view_deformation.py")
    rng = np.random.default_rng(2)
    n = 4000
    s = rng.uniform(0, 30, n)
    side = rng.integers(0, 4, n)  # 0 roof, 1 left, 2 right, 3 floor
    u = rng.uniform(-0.8, 0.8, n)
    y = np.select([side == 1, side == 2], [3.0, -3.0], 3.0 * u)
    z = np.select([side == 0, side == 3], [1.5, -1.5], 1.5 * u)
    a = np.deg2rad(heading)
    xyz = np.stack([s * np.cos(a) - y * np.sin(a), s * np.sin(a) + y * np.cos(a), z], axis=1)
    along, angle, height = view.unrolled(xyz + [4.0e5, 5.6e6, 300.0], chainage=s)
    np.testing.assert_allclose(along, s)
    # a 6 x 3 m box seen from its centre: roof within +-58 deg, walls 68-112, floor >= 122
    assert np.all(np.abs(angle[side == 0]) < 60)
    assert np.all((angle[side == 1] > 65) & (angle[side == 1] < 115))
    assert np.all((angle[side == 2] < -65) & (angle[side == 2] > -115))
    assert np.all(np.abs(angle[side == 3]) > 120)
    assert np.allclose(height[side == 0], 1.5, atol=0.01)


def test_viewer_writes_png_without_display(tmp_path, monkeypatch):
    view = _script("view_deformation.py")
    ply = tmp_path / "out.ply"
    _write(ply, _result_cloud())
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    assert not view.has_display()
    assert view.main([str(ply)]) == 0  # no display: falls back to a PNG next to the input
    png = tmp_path / "out.png"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert view.main([str(ply), "--png", str(tmp_path / "v.png"), "--field", "danger"]) == 0
    with pytest.raises(SystemExit, match="no field 'nope'"):
        view.main([str(ply), "--png", str(tmp_path / "x.png"), "--field", "nope"])


# --------------------------------------------------------------------------- in-CC script


@pytest.fixture
def pycc_cli(monkeypatch):
    mod = fake_pycc.install()
    monkeypatch.setitem(sys.modules, "pycc", mod)
    mod._GUI = None
    return mod


def _entity(pycc, xyz, name, shift):
    local = (xyz + shift).astype(np.float32)
    pc = pycc.ccPointCloud(local[:, 0], local[:, 1], local[:, 2])
    pc.setGlobalShift(*shift)
    pc.setName(name)
    return pc


def _fake_detect(result):
    def detect(ref, cmp, config=None, *, progress=None, tiles=None):
        assert tiles is not None and tiles["engine"] is not None  # as `tunneldef detect` runs
        progress("deformation", 1.0)
        assert len(cmp) == len(result.cloud)
        return result

    return detect


def test_detect_script_command_line_mode(pycc_cli, monkeypatch, tmp_path, capsys):
    from tunneldef.io import read

    res_cloud = _result_cloud(500)
    shift = -np.round(res_cloud.xyz.mean(axis=0))
    result = SimpleNamespace(
        cloud=res_cloud,
        transform=np.eye(4),
        summary=lambda: {"transform_compared_to_reference": np.eye(4).tolist()},
    )
    try:
        pipeline = importlib.import_module("tunneldef.pipeline")
    except ImportError:
        pipeline = types.ModuleType("tunneldef.pipeline")
        monkeypatch.setitem(sys.modules, "tunneldef.pipeline", pipeline)
    monkeypatch.setattr(pipeline, "detect", _fake_detect(result), raising=False)

    ref_e = _entity(pycc_cli, res_cloud.xyz + 0.5, "ref", shift)
    cmp_e = _entity(pycc_cli, res_cloud.xyz - 0.5, "cmp", shift)
    cmp_e.addScalarField("deformation", np.zeros(500))  # from an earlier run: replaced
    pycc_cli._CMDLINE = pycc_cli.ccCommandLineInterface(
        [
            pycc_cli.CLCloudDesc(ref_e, str(tmp_path), "ref"),
            pycc_cli.CLCloudDesc(cmp_e, str(tmp_path), "cmp"),
        ]
    )
    script = _script("detect_in_cloudcompare.py")
    assert script.main(["--threshold", "0.02"]) == 0

    out = tmp_path / "cmp_deformation.ply"
    back = read(out)
    assert np.abs(back.xyz - res_cloud.xyz).max() < 1e-9
    np.testing.assert_array_equal(back.fields["deformation"], res_cloud.fields["deformation"])
    idx = cmp_e.getScalarFieldIndexByName("deformation")
    np.testing.assert_array_equal(
        cmp_e.getScalarField(idx).toArray(), res_cloud.fields["deformation"]
    )
    assert cmp_e.getNumberOfScalarFields() == 5  # replaced, not duplicated
    text = capsys.readouterr().out
    assert "compared -> reference transform" in text and str(out) in text
    summary = json.loads((tmp_path / "cmp_deformation.json").read_text())
    assert summary["transform_compared_to_reference"] == np.eye(4).tolist()

    pycc_cli._CMDLINE = pycc_cli.ccCommandLineInterface([pycc_cli.CLCloudDesc(ref_e)])
    assert script.main([]) == 2
    assert "load exactly two clouds" in capsys.readouterr().out


# --------------------------------------------------------------------------- batch helpers


def test_scalar_field_index_and_colour_scale(tmp_path):
    batch = _script("batch_detect.py")
    ply = tmp_path / "r.ply"
    _write(ply, _result_cloud(100))
    assert batch.scalar_field_index(ply, "intensity") == 0
    assert batch.scalar_field_index(ply, "deformation") == 1
    with pytest.raises(KeyError, match="no vertex property 'nope'"):
        batch.scalar_field_index(ply, "nope")
    root = ET.fromstring(batch.color_scale_xml(limit=0.025))
    props = root.find("ColorScale/Properties")
    assert float(props.findtext("minValue")) == -0.025 and float(props.findtext("range")) == 0.05
    steps = [(s.get("r"), s.get("g"), s.get("b"), float(s.get("pos"))) for s in root.iter("step")]
    # red at -limit (into the tunnel), white at 0, blue at +limit (outward)
    assert steps == [("255", "0", "0", 0.0), ("255", "255", "255", 0.5), ("0", "0", "255", 1.0)]


# --------------------------------------------------------------------------- real CloudCompare


@needs_cc
def test_cloudcompare_loads_our_ply_fields_by_name_and_value(tmp_path):
    cloud = _result_cloud()
    _write(tmp_path / "out.ply", cloud)
    _cloudcompare(
        "-AUTO_SAVE",
        "OFF",
        "-O",
        "-GLOBAL_SHIFT",
        "AUTO",
        "out.ply",
        "-C_EXPORT_FMT",
        "ASC",
        "-PREC",
        "8",
        "-ADD_HEADER",
        "-SAVE_CLOUDS",
        "FILE",
        "out.asc",
        cwd=tmp_path,
    )
    header, data = _read_asc(tmp_path / "out.asc")
    names = [
        "intensity",
        "deformation",
        "deformation_horizontal",
        "deformation_vertical",
        "chainage",
        "danger",
    ]
    assert header == ["X", "Y", "Z", *names]
    assert np.abs(data[:, :3] - cloud.xyz).max() < 2e-5  # survey coordinates kept (shifted)
    for i, name in enumerate(names):
        np.testing.assert_allclose(data[:, 3 + i], cloud.fields[name], atol=1e-7, err_msg=name)


@needs_cc
def test_batch_colours_with_cloudcompare(tmp_path):
    from plyfile import PlyData

    batch = _script("batch_detect.py")
    cloud = _result_cloud()
    ply = tmp_path / "res.ply"
    _write(ply, cloud)
    assert (
        batch.main(
            [
                str(tmp_path / "a"),
                str(tmp_path / "b"),
                "-o",
                str(ply),
                "--skip-detect",
                "--limit",
                "0.02",
                "--cloudcompare",
                CLOUDCOMPARE,
            ]
        )
        == 0
    )
    v = PlyData.read(str(tmp_path / "res_rgb.ply"))["vertex"]
    d = np.asarray(v["scalar_deformation"])
    rgb = np.stack([np.asarray(v[c]) for c in ("red", "green", "blue")], axis=1).astype(int)
    blue, red = [0, 0, 255], [255, 0, 0]
    assert np.abs(rgb[d < -0.02] - red).max() <= 2 and np.abs(rgb[d > 0.02] - blue).max() <= 2
    near0 = np.abs(d) < 0.0005
    assert near0.any() and rgb[near0].min() >= 240  # white at 0
    assert np.abs(np.stack([v["x"], v["y"], v["z"]], 1) - cloud.xyz).max() < 2e-5
    header, data = _read_asc(tmp_path / "res.asc")
    assert header[:6] == ["X", "Y", "Z", "R", "G", "B"] and "deformation" in header
    # the BIN (CloudCompare's format) holds the fields and the shift: reload and export
    _cloudcompare(
        "-AUTO_SAVE",
        "OFF",
        "-O",
        "res.bin",
        "-C_EXPORT_FMT",
        "ASC",
        "-PREC",
        "8",
        "-ADD_HEADER",
        "-SAVE_CLOUDS",
        "FILE",
        "bin.asc",
        cwd=tmp_path,
    )
    header, data = _read_asc(tmp_path / "bin.asc")
    col = header.index("deformation")
    np.testing.assert_allclose(data[:, col], cloud.fields["deformation"], atol=1e-7)
    assert np.abs(data[:, :3] - cloud.xyz).max() < 2e-5


def _registered_pair():
    """A small synthetic pair registered with the TRUE transform, and our (paper KNN)
    deformation of its compared epoch: C2C and tunneldef then measure the same geometry."""
    synth = pytest.importorskip("tunneldef.synth")
    try:
        from tunneldef.deformation import compute_deformation
    except ImportError as exc:
        pytest.skip(f"no deformation stage yet: {exc}")
    pair = synth.make_pair(
        synth.PairSpec(
            tunnel=synth.TunnelSpec(length=12.0, density=400.0, outlier_fraction=0.0),
            deformations=(synth.DeformationSpec(kind="roof_sag", chainage=6.0, amplitude=0.05),),
            seed=4,
        )
    )
    cmp_xyz = pair.truth.cmp_xyz_in_ref
    d = compute_deformation(
        pair.ref.xyz, cmp_xyz, pair.truth.centerline, settings=DeformationConfig(method="knn")
    )
    return pair, cmp_xyz, np.asarray(d.deformation, dtype=np.float64)


def _c2c(tmp_path, *model):
    for f in tmp_path.glob("*C2C*"):
        f.unlink()
    _cloudcompare(
        "-NO_TIMESTAMP",
        "-C_EXPORT_FMT",
        "ASC",
        "-PREC",
        "8",
        "-ADD_HEADER",
        "-O",
        "-GLOBAL_SHIFT",
        "AUTO",
        "cmp.ply",
        "-O",
        "-GLOBAL_SHIFT",
        "FIRST",
        "ref.ply",
        "-C2C_DIST",
        *model,
        cwd=tmp_path,
    )
    header, data = _read_asc(tmp_path / "cmp_C2C_DIST.asc")
    col = next(i for i, name in enumerate(header) if name.startswith("C2C"))
    return header, data, data[:, col]


@needs_cc
def test_cloudcompare_c2c_agrees_with_unsigned_deformation_on_unchanged_shell(tmp_path):
    """CloudCompare's C2C on the registered pair against our |deformation|.

    C2C to the nearest reference point sits above the paper's 3-NN-centroid distance (the
    nearest single point is farther from the surface than the centroid of three); C2C with a
    local plane (``-MODEL LS KNN 6``) sits below it (a fitted plane removes the along-surface
    offset). Measured here, 400 pts/m2, 15 mm noise: 16 mm < 27 mm < 33 mm (medians).
    """
    pair, cmp_xyz, d = _registered_pair()
    _write(tmp_path / "ref.ply", Cloud(pair.ref.xyz))
    _write(tmp_path / "cmp.ply", Cloud(cmp_xyz, {"deformation": d.astype(np.float32)}))
    header, data, c2c = _c2c(tmp_path)
    np.testing.assert_allclose(data[:, header.index("deformation")], d, atol=1e-7)
    _, _, c2c_plane = _c2c(tmp_path, "-MODEL", "LS", "KNN", "6")

    overlap = (pair.truth.chainage > 0.5) & (pair.truth.chainage < 11.5)  # both epochs there
    unchanged = (pair.truth.label == 0) & (np.abs(pair.truth.displacement) < 1e-9)
    unchanged &= overlap & np.isfinite(d)
    ours = np.median(np.abs(d[unchanged]))
    nearest, plane = np.median(c2c[unchanged]), np.median(c2c_plane[unchanged])
    print(
        f"median on unchanged shell: C2C plane {plane * 1000:.1f} mm, |deformation| "
        f"{ours * 1000:.1f} mm, C2C nearest {nearest * 1000:.1f} mm"
    )
    assert plane < ours < nearest
    assert nearest - ours < 0.008  # within 8 mm of CloudCompare's plain C2C
    sag = (pair.truth.label == 0) & (pair.truth.displacement < -0.04) & np.isfinite(d)
    for dist in (c2c, c2c_plane, np.abs(d)):  # all three see the 5 cm roof sag
        assert np.median(dist[sag]) > np.median(dist[unchanged]) + 0.012


_STUB_CLI = """#!{python}
# stands in for the `tunneldef` console script: records its arguments, writes a result
import json, sys
import numpy as np
from tunneldef.io import read, write
args = sys.argv[1:]
assert args[0] == "detect", args
out, summary = args[args.index("-o") + 1], args[args.index("--summary") + 1]
cloud = read(args[2])
z = cloud.xyz[:, 2]
d = np.where(z > np.percentile(z, 90), -0.04, 0.0).astype(np.float32)
cloud.add_fields({{"deformation": d, "deformation_horizontal": 0 * d,
                  "deformation_vertical": d, "chainage": cloud.xyz[:, 0].astype(np.float32),
                  "danger": (d < -0.03).astype(np.uint8)}})
write(out, cloud)
json.dump({{"argv": args}}, open(summary, "w"))
"""


@needs_cc
def test_plugin_scale_xml_loads_in_cloudcompare(tmp_path):
    """The plugin's relative Red>White>Blue XML through CloudCompare 2.11's own
    ``ccColorScale::LoadFromXML`` (``-SF_COLOR_SCALE``, the call the plugin makes through the
    runtime): minimum red, maximum blue, white half-way."""
    from plyfile import PlyData
    from tunneldef_cloudcompare.adapter import color_scale_xml

    cloud = _result_cloud(2000)
    cloud.fields["deformation"] = np.linspace(-0.04, 0.04, 2000).astype(np.float32)
    _write(tmp_path / "r.ply", cloud)
    (tmp_path / "scale.xml").write_text(color_scale_xml(), encoding="utf-8")
    sf = _script("batch_detect.py").scalar_field_index(tmp_path / "r.ply", "deformation")
    _cloudcompare(
        "-AUTO_SAVE", "OFF", "-O", "-GLOBAL_SHIFT", "AUTO", "r.ply",
        "-SET_ACTIVE_SF", str(sf), "-SF_COLOR_SCALE", "scale.xml",
        "-SF_CONVERT_TO_RGB", "FALSE",
        "-C_EXPORT_FMT", "PLY", "-SAVE_CLOUDS", "FILE", "rgb.ply",
        cwd=tmp_path,
    )  # fmt: skip
    v = PlyData.read(str(tmp_path / "rgb.ply"))["vertex"]
    d = np.asarray(v["scalar_deformation"])
    rgb = np.stack([np.asarray(v[c]) for c in ("red", "green", "blue")], axis=1).astype(int)
    assert np.abs(rgb[np.argmin(d)] - [255, 0, 0]).max() <= 2  # into the tunnel: red
    assert np.abs(rgb[np.argmax(d)] - [0, 0, 255]).max() <= 2  # outward: blue
    assert rgb[np.argmin(np.abs(d))].min() >= 240  # white at 0 (symmetric data)


@needs_cc
def test_batch_full_chain(tmp_path, monkeypatch):
    """REF CMP -> `tunneldef detect` (a stub with the CLI's interface: the real pipeline runs
    in the plugin tests) -> CloudCompare colours and exports."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    stub = bindir / "tunneldef"
    stub.write_text(_STUB_CLI.format(python=sys.executable))
    stub.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bindir}{os.pathsep}{os.environ['PATH']}")
    cmp_cloud = _result_cloud(2000)
    cmp_cloud.fields.clear()
    _write(tmp_path / "cmp.ply", cmp_cloud)
    batch = _script("batch_detect.py")
    out = tmp_path / "out.ply"
    argv = [
        str(tmp_path / "ref.ply"),
        str(tmp_path / "cmp.ply"),
        "-o",
        str(out),
        "--threshold",
        "0.03",
        "--cloudcompare",
        CLOUDCOMPARE,
        "--",
        "--k",
        "5",
    ]
    assert batch.main(argv) == 0
    recorded = json.loads((tmp_path / "out.json").read_text())["argv"]
    assert recorded == [
        "detect",
        str(tmp_path / "ref.ply"),
        str(tmp_path / "cmp.ply"),
        "-o",
        str(out),
        "--summary",
        str(tmp_path / "out.json"),
        "--threshold",
        "0.03",
        "--k",
        "5",
    ]
    for name in ("out.bin", "out_rgb.ply", "out.asc", "out_scale.xml"):
        assert (tmp_path / name).is_file(), name
    header, data = _read_asc(tmp_path / "out.asc")
    assert {"deformation", "chainage", "danger"} <= set(header) and len(data) == 2000
    d = data[:, header.index("deformation")]
    red = data[:, header.index("R")] - data[:, header.index("B")]
    assert np.all(red[d < -0.035] > 200)  # the -4 cm roof band (into the tunnel) is red
    with pytest.raises(SystemExit):
        batch.main([str(tmp_path / "ref.ply"), str(tmp_path / "cmp.ply"), "-o", "x.las"])


def test_scripts_have_usage_headers():
    for name in ("detect_in_cloudcompare.py", "batch_detect.py", "view_deformation.py"):
        doc = (SCRIPTS / name).read_text().split('"""')[1]
        assert "Usage" in doc, name
    assert Path(SCRIPTS / "batch_detect.py").stat().st_mode & 0o111  # executable
