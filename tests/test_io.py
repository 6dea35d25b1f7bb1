"""Round trips, layout preservation and error messages of tunneldef.io (all formats)."""

from __future__ import annotations

import logging
import os
import stat
import time
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pytest
from conftest import CHAMBER_POINTS, DRIFT_POINTS
from laspy.vlrs.vlrlist import VLRList

import tunneldef
import tunneldef.io.ply
from tunneldef.cloud import Cloud
from tunneldef.errors import (
    CorruptFileError,
    InvalidCloudError,
    MissingFileError,
    UnsupportedFormatError,
)
from tunneldef.io import read, supported_extensions, write

ORIGIN = np.array([450000.0, 5600000.0, 300.0])
COORD_TOL = 1e-4  # m: the required round-trip accuracy (0.1 mm)
DTYPES = ("u1", "u2", "u4", "i4", "f4", "f8")
WKT = (
    'PROJCS["ETRS89 / UTM zone 33N",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_'
    'System_1989",SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],'
    'UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
    'PARAMETER["central_meridian",15],UNIT["metre",1],AUTHORITY["EPSG","25833"]]'
)


def _values(rng: np.random.Generator, dtype: str, n: int) -> np.ndarray:
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return (rng.normal(size=n) * 10).astype(dt)
    info = np.iinfo(dt)
    return rng.integers(info.min, info.max, size=n, endpoint=True, dtype=dt)


def survey_cloud(n: int = 2000, seed: int = 0) -> Cloud:
    """A 30 m x 6 m x 3 m box at survey coordinates with one field of each dtype."""
    rng = np.random.default_rng(seed)
    xyz = ORIGIN + rng.random((n, 3)) * [30.0, 6.0, 3.0]
    fields = {f"f_{dt}": _values(rng, dt, n) for dt in DTYPES}
    return Cloud(xyz, fields)


def assert_round_trip(back: Cloud, orig: Cloud, *, typed: bool = True) -> None:
    """Coordinates within 0.1 mm; every field present with exactly the same values.

    ``typed`` formats keep the dtype; text formats give float64 holding the same numbers
    (float32 fields to float32 precision).
    """
    assert len(back) == len(orig)
    assert np.abs(back.xyz - orig.xyz).max() < COORD_TOL
    for name, values in orig.fields.items():
        assert name in back.fields, name
        got = back.fields[name]
        if typed:
            assert got.dtype == values.dtype, (name, got.dtype, values.dtype)
            np.testing.assert_array_equal(got, values, err_msg=name)
        elif values.dtype == np.float32:
            np.testing.assert_array_equal(got.astype(np.float32), values, err_msg=name)
        else:
            np.testing.assert_array_equal(got, values.astype(np.float64), err_msg=name)


# --------------------------------------------------------------------------- round trips

VARIANTS = {
    "ply_binary": ("cloud.ply", {}, True),
    "ply_ascii": ("cloud.ply", {"ply": {"text": True}}, True),
    "las_14": ("cloud.las", {}, True),
    "laz_14": ("cloud.laz", {}, True),
    "pcd_binary": ("cloud.pcd", {}, True),
    "pcd_ascii": ("cloud.pcd", {"pcd": {"data": "ascii"}}, True),
    "xyz_header": ("cloud.xyz", {}, False),
    "csv_header": ("cloud.csv", {}, False),
    "txt_semicolon": ("cloud.txt", {"xyz": {"separator": ";", "style": "//"}}, False),
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_round_trip_keeps_coordinates_and_fields(tmp_path: Path, variant: str) -> None:
    name, meta, typed = VARIANTS[variant]
    cloud = survey_cloud()
    cloud.meta.update(meta)
    path = tmp_path / name
    write(path, cloud)
    back = read(path)
    assert_round_trip(back, cloud, typed=typed)
    # second generation: the file read back writes the same content again
    write(tmp_path / ("again_" + name), back)
    again = read(tmp_path / ("again_" + name))
    assert_round_trip(again, back, typed=True)
    assert sorted(again.fields) == sorted(back.fields)


def test_las_12_source_keeps_version_format_scale_vlrs_and_extra_bytes(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    n = 1500
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales = np.array([0.001, 0.001, 0.0005])
    header.offsets = np.array([449000.0, 5599000.0, 0.0])
    header.add_extra_dims(
        [
            laspy.ExtraBytesParams("range", np.uint16, "range, mm"),
            laspy.ExtraBytesParams("quality", np.float32, "fit quality"),
            laspy.ExtraBytesParams(
                "temp", np.int16, "scaled temperature", scales=[0.01], offsets=[20.0]
            ),
        ]
    )
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(WKT))
    las = laspy.LasData(header)
    las.x = ORIGIN[0] + rng.random(n) * 30
    las.y = ORIGIN[1] + rng.random(n) * 6
    las.z = ORIGIN[2] + rng.random(n) * 3
    las.intensity = rng.integers(0, 65535, n, dtype=np.uint16)
    las.classification = rng.integers(0, 31, n, dtype=np.uint8)
    las.return_number = rng.integers(1, 5, n, dtype=np.uint8)
    las.gps_time = rng.random(n) * 1e5
    las.red = rng.integers(0, 65535, n, dtype=np.uint16)
    las["range"] = rng.integers(0, 65535, n, dtype=np.uint16)
    las["quality"] = rng.random(n).astype(np.float32)
    las["temp"] = np.round(rng.normal(20, 5, n), 2)
    src = tmp_path / "src.las"
    las.write(src)

    cloud = read(src)
    for name in (
        "intensity",
        "classification",
        "return_number",
        "gps_time",
        "red",
        "range",
        "quality",
        "temp",
    ):
        assert name in cloud.fields
    np.testing.assert_allclose(cloud.fields["temp"], las["temp"], atol=1e-9)
    cloud.add_field("deformation", rng.normal(0, 0.01, n).astype(np.float32))
    cloud.add_field("danger", rng.random(n) > 0.9)
    out = tmp_path / "out.las"
    write(out, cloud)

    got = laspy.read(out)
    assert str(got.header.version) == "1.2"
    assert got.header.point_format.id == 3
    np.testing.assert_array_equal(got.header.scales, header.scales)
    np.testing.assert_array_equal(got.header.offsets, header.offsets)
    wkt = got.header.vlrs.get("WktCoordinateSystemVlr")
    assert len(wkt) == 1 and wkt[0].string.strip("\0") == WKT
    # integer coordinates are bit-identical: nothing moved, nothing was re-quantised
    for dim in "XYZ":
        np.testing.assert_array_equal(got[dim], las[dim])
    for name in (
        "intensity",
        "classification",
        "return_number",
        "gps_time",
        "red",
        "range",
        "quality",
    ):
        np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(las[name]), name)
    np.testing.assert_array_equal(got.points.array["temp"], las.points.array["temp"])
    extra = {d.name: d for d in got.point_format.extra_dimensions}
    assert extra["range"].description == "range, mm"
    assert extra["temp"].scales[0] == pytest.approx(0.01)
    assert extra["deformation"].dtype == np.float32
    assert extra["deformation"].description == "signed deformation, m"
    assert extra["danger"].dtype == np.uint8
    np.testing.assert_array_equal(got["deformation"], cloud.fields["deformation"])
    np.testing.assert_array_equal(got["danger"], cloud.fields["danger"].astype(np.uint8))


def test_las_14_laz_keeps_evlrs_and_moves_offset_when_it_would_overflow(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    n = 1000
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.zeros(3)
    header.add_extra_dims([laspy.ExtraBytesParams("sigma", np.float64, "1-sigma, m")])
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(WKT))
    las = laspy.LasData(header)
    las.xyz = rng.random((n, 3)) * [30, 6, 3]  # local frame, near the origin
    las["sigma"] = rng.random(n) * 0.01
    las.evlrs = VLRList([laspy.VLR("tunneldef", 42, "test evlr", b"\x01\x02\x03" * 100)])
    src = tmp_path / "local.laz"
    las.write(src)

    cloud = read(src)
    assert cloud.meta["las_header"].version.minor == 4
    moved = cloud.transformed(
        np.array([[1, 0, 0, ORIGIN[0]], [0, 1, 0, ORIGIN[1]], [0, 0, 1, ORIGIN[2]], [0, 0, 0, 1.0]])
    )
    out = tmp_path / "moved.laz"
    write(out, moved)
    got = laspy.read(out)
    assert got.header.are_points_compressed
    assert got.header.point_format.id == 6 and got.header.version.minor == 4
    np.testing.assert_array_equal(got.header.scales, header.scales)  # scale kept
    # only y (5.6e9 mm) overflows int32 at 1 mm; x and z keep their offset
    np.testing.assert_array_equal(got.header.offsets, [0.0, np.floor(moved.xyz[:, 1].min()), 0.0])
    assert np.abs(got.xyz - moved.xyz).max() <= 0.0005 + 1e-9  # half the 1 mm scale
    assert len(got.header.vlrs.get("WktCoordinateSystemVlr")) == 1
    assert len(got.evlrs) == 1 and got.evlrs[0].record_data == b"\x01\x02\x03" * 100
    np.testing.assert_array_equal(got["sigma"], las["sigma"])


def test_fresh_las_layout(tmp_path: Path) -> None:
    cloud = survey_cloud(500, seed=3)
    rng = np.random.default_rng(3)
    cloud.add_fields(
        {
            "intensity": rng.integers(0, 65535, 500, dtype=np.uint16),
            "classification": rng.integers(0, 255, 500).astype(np.float64),  # integral floats
            "red": rng.integers(0, 255, 500, dtype=np.uint8),
            "green": rng.integers(0, 255, 500, dtype=np.uint8),
            "blue": rng.integers(0, 255, 500, dtype=np.uint8),
            "flag": rng.random(500) > 0.5,
        }
    )
    write(tmp_path / "fresh.las", cloud)
    got = laspy.read(tmp_path / "fresh.las")
    assert (got.header.version.major, got.header.version.minor) == (1, 4)
    assert got.header.point_format.id == 7
    np.testing.assert_allclose(got.header.scales, 1e-4)
    np.testing.assert_array_equal(got.header.offsets, np.floor(cloud.xyz.min(axis=0)))
    np.testing.assert_array_equal(got.intensity, cloud.fields["intensity"])
    np.testing.assert_array_equal(got.classification, cloud.fields["classification"])
    np.testing.assert_array_equal(got.red, cloud.fields["red"])
    extra = {d.name: d.dtype for d in got.point_format.extra_dimensions}
    assert extra == {
        "f_u1": np.uint8,
        "f_u2": np.uint16,
        "f_u4": np.uint32,
        "f_i4": np.int32,
        "f_f4": np.float32,
        "f_f8": np.float64,
        "flag": np.uint8,
    }
    # a non-integral "intensity" cannot be a LAS intensity: kept as extra bytes instead
    cloud.add_field("intensity", rng.random(500))
    write(tmp_path / "float_intensity.las", cloud)
    back = read(tmp_path / "float_intensity.las")
    np.testing.assert_array_equal(back.fields["intensity_value"], cloud.fields["intensity"])


def test_ply_keeps_property_names_and_types(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    n = 300
    vertex = np.empty(
        n,
        dtype=[
            ("x", "f4"),
            ("y", "f4"),
            ("z", "f4"),
            ("intensity", "u4"),
            ("scalar_Range", "u2"),
            ("scalar_C2C_absolute_distances", "f4"),
            ("red", "u1"),
        ],
    )
    for c in "xyz":
        vertex[c] = rng.random(n) * 10
    vertex["intensity"] = rng.integers(0, 2**32 - 1, n, dtype=np.uint32)
    vertex["scalar_Range"] = rng.integers(0, 2**16 - 1, n, dtype=np.uint16)
    vertex["scalar_C2C_absolute_distances"] = rng.random(n).astype(np.float32)
    vertex["red"] = rng.integers(0, 255, n, dtype=np.uint8)
    src = tmp_path / "cc.ply"
    plyfile.PlyData(
        [plyfile.PlyElement.describe(vertex, "vertex")], text=True, comments=["made by a scanner"]
    ).write(str(src))

    cloud = read(src)
    assert sorted(cloud.fields) == ["C2C_absolute_distances", "Range", "intensity", "red"]
    assert cloud.fields["Range"].dtype == np.uint16
    assert cloud.fields["intensity"].dtype == np.uint32
    cloud.add_field("deformation", rng.normal(size=n).astype(np.float32))
    out = tmp_path / "out.ply"
    write(out, cloud)
    ply = plyfile.PlyData.read(str(out))
    assert ply.text  # source was ascii
    assert ply.comments == ["made by a scanner"]
    props = {p.name: p.val_dtype for p in ply["vertex"].properties}
    assert list(props) == [
        "x",
        "y",
        "z",
        "intensity",
        "scalar_Range",
        "scalar_C2C_absolute_distances",
        "red",
        "scalar_deformation",
    ]
    assert np.dtype(props["x"]) == np.float32  # small coordinates, float source
    assert np.dtype(props["intensity"]) == np.uint32
    assert np.dtype(props["scalar_Range"]) == np.uint16
    for prop in ("intensity", "scalar_Range", "scalar_C2C_absolute_distances", "red"):
        np.testing.assert_array_equal(ply["vertex"][prop], vertex[prop])
    np.testing.assert_array_equal(ply["vertex"]["scalar_deformation"], cloud.fields["deformation"])


def test_ply_coordinates_double_when_large(tmp_path: Path) -> None:
    small = Cloud(np.random.default_rng(5).random((50, 3)) * 100)
    write(tmp_path / "small.ply", small)
    assert plyfile.PlyData.read(str(tmp_path / "small.ply"))["vertex"]["x"].dtype == np.float32
    big = Cloud(small.xyz + ORIGIN)
    write(tmp_path / "big.ply", big)
    data = plyfile.PlyData.read(str(tmp_path / "big.ply"))["vertex"]
    assert data["x"].dtype == np.float64
    np.testing.assert_array_equal(data["y"], big.xyz[:, 1])


def test_pcd_packed_rgb_and_compressed(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    n = 200
    xyz = rng.random((n, 3)).astype(np.float32) * 5
    rgb = rng.integers(0, 255, (n, 3), dtype=np.uint8)
    packed = (
        (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2]
    ).view(np.float32)
    body = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    body["x"], body["y"], body["z"], body["rgb"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], packed
    head = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\n"
        f"COUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    src = tmp_path / "pcl.pcd"
    src.write_bytes(head.encode() + body.tobytes())
    cloud = read(src)
    for k, c in enumerate(("red", "green", "blue")):
        np.testing.assert_array_equal(cloud.fields[c], rgb[:, k])
    write(tmp_path / "back.pcd", cloud)
    assert (tmp_path / "back.pcd").read_bytes() == src.read_bytes().replace(
        b"# .PCD v0.7\n", b"# .PCD v0.7 - Point Cloud Data file format\n"
    )

    o3d = pytest.importorskip("open3d")
    tpc = o3d.t.geometry.PointCloud()
    tpc.point.positions = o3d.core.Tensor(xyz.astype(np.float64) + ORIGIN)
    tpc.point.range = o3d.core.Tensor(rng.integers(0, 60000, (n, 1), dtype=np.uint16))
    tpc.point.sigma = o3d.core.Tensor(rng.random((n, 1)).astype(np.float32))
    comp = tmp_path / "compressed.pcd"
    assert o3d.t.io.write_point_cloud(str(comp), tpc, write_ascii=False, compressed=True)
    assert b"DATA binary_compressed" in comp.read_bytes()[:400]
    got = read(comp)
    np.testing.assert_array_equal(got.xyz, xyz.astype(np.float64) + ORIGIN)
    assert got.fields["range"].dtype == np.uint16
    np.testing.assert_array_equal(got.fields["range"], tpc.point.range.numpy()[:, 0])
    np.testing.assert_array_equal(got.fields["sigma"], tpc.point.sigma.numpy()[:, 0])


def test_text_without_header_and_cloudcompare_header(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    table = np.column_stack(
        [
            np.round(ORIGIN + rng.random((100, 3)) * 10, 4),
            rng.integers(0, 255, 100),
            np.round(rng.random(100), 4),
        ]
    )
    plain = tmp_path / "plain.xyz"
    np.savetxt(plain, table, fmt=["%.4f", "%.4f", "%.4f", "%d", "%.4f"])
    cloud = read(plain)
    assert sorted(cloud.fields) == ["column_4", "column_5"]
    np.testing.assert_allclose(cloud.xyz, table[:, :3], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(cloud.fields["column_4"], table[:, 3])
    write(tmp_path / "plain_back.xyz", cloud)
    first = (tmp_path / "plain_back.xyz").read_text().splitlines()[0]
    assert first.split()[3] == str(int(table[0, 3]))  # no header line added
    assert_round_trip(read(tmp_path / "plain_back.xyz"), cloud)

    cc = tmp_path / "cc.asc"
    cc.write_text("//X;Y;Z;Scalar field;R\n1.5;2.5;3.5;0.25;7\n4;5;6;-1;8\n")
    got = read(cc)
    np.testing.assert_array_equal(got.xyz, [[1.5, 2.5, 3.5], [4, 5, 6]])
    np.testing.assert_array_equal(got.fields["Scalar field"], [0.25, -1])
    np.testing.assert_array_equal(got.fields["R"], [7, 8])
    reordered = tmp_path / "reordered.csv"
    reordered.write_text("intensity,X,Y,Z\n5,1,2,3\n6,4,5,6\n")
    got = read(reordered)
    np.testing.assert_array_equal(got.xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(got.fields["intensity"], [5, 6])


def test_ply_with_faces_and_big_endian(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    vertex = np.empty(4, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("scalar_d", "f4")])
    for c in "xyz":
        vertex[c] = ORIGIN["xyz".index(c)] + rng.random(4)
    vertex["scalar_d"] = rng.random(4).astype(np.float32)
    faces = np.array([([0, 1, 2],), ([1, 2, 3],)], dtype=[("vertex_indices", "i4", (3,))])
    mesh = tmp_path / "mesh.ply"
    plyfile.PlyData(
        [plyfile.PlyElement.describe(vertex, "vertex"), plyfile.PlyElement.describe(faces, "face")],
        text=True,
    ).write(str(mesh))
    cloud = read(mesh)  # plyfile's own parser (faces are not read)
    np.testing.assert_array_equal(cloud.xyz, np.column_stack([vertex[c] for c in "xyz"]))
    np.testing.assert_array_equal(cloud.fields["d"], vertex["scalar_d"])

    big = tmp_path / "big_endian.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], byte_order=">").write(str(big))
    cloud = read(big)
    assert cloud.fields["d"].dtype == np.float32
    write(tmp_path / "again.ply", cloud)
    again = plyfile.PlyData.read(str(tmp_path / "again.ply"))
    assert again.byte_order == ">"
    np.testing.assert_array_equal(again["vertex"]["scalar_d"], vertex["scalar_d"])


def test_text_comment_line_is_not_a_header(tmp_path: Path) -> None:
    path = tmp_path / "commented.txt"
    path.write_text("# exported by a scanner, units m\n1 2 3 9\n4 5 6 8\n")
    cloud = read(path)
    np.testing.assert_array_equal(cloud.xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(cloud.fields["column_4"], [9, 8])


def test_synthetic_epoch_with_truth_fields(tmp_path: Path) -> None:
    from tunneldef.synth import TunnelSpec, make_tunnel

    cloud, truth = make_tunnel(TunnelSpec(length=6.0, density=60.0), seed=3)
    cloud = cloud.transformed(np.vstack([np.column_stack([np.eye(3), ORIGIN]), [0, 0, 0, 1]]))
    cloud.add_fields({"label": truth.label, "surface": truth.surface, "chainage": truth.chainage})
    for name in ("epoch.laz", "epoch.ply", "epoch.pcd"):
        write(tmp_path / name, cloud)
        assert_round_trip(read(tmp_path / name), cloud)


def test_fields_selection(tmp_path: Path) -> None:
    cloud = survey_cloud(100)
    for name in ("sel.ply", "sel.las", "sel.pcd", "sel.xyz"):
        write(tmp_path / name, cloud, fields=["f_f4", "f_u2"])
        back = read(tmp_path / name)
        user = {k for k in back.fields if k.startswith("f_")}
        assert user == {"f_f4", "f_u2"}, name
    write(tmp_path / "none.ply", cloud, fields=[])
    assert read(tmp_path / "none.ply").fields == {}


def test_nonfinite_points_dropped_or_refused(tmp_path: Path, caplog) -> None:
    cloud = survey_cloud(50)
    xyz = cloud.xyz.copy()
    xyz[[3, 10, 20], [0, 1, 2]] = [np.nan, np.inf, -np.inf]
    vertex = np.empty(50, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("scalar_v", "u2")])
    vertex["x"], vertex["y"], vertex["z"] = xyz.T
    vertex["scalar_v"] = np.arange(50)
    path = tmp_path / "nan.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(path))
    with caplog.at_level(logging.WARNING, logger="tunneldef.io"):
        got = read(path)
    assert len(got) == 47
    assert got.meta["dropped_nonfinite"] == 3
    np.testing.assert_array_equal(got.fields["v"], np.delete(np.arange(50), [3, 10, 20]))
    assert "dropped 3 points" in caplog.text
    with pytest.raises(InvalidCloudError, match="3 points with NaN or infinite"):
        read(path, strict=True)


def test_package_level_read_write_and_extensions(tmp_path: Path) -> None:
    exts = supported_extensions()
    assert set(exts) == {".las", ".laz", ".ply", ".pcd", ".xyz", ".txt", ".asc", ".csv"}
    cloud = survey_cloud(20)
    tunneldef.write(tmp_path / "pkg.PLY", cloud)  # extension case does not matter
    assert_round_trip(tunneldef.read(tmp_path / "pkg.PLY"), cloud)


# --------------------------------------------------------------------------- atomic writes


def test_failed_write_leaves_target_untouched(tmp_path: Path, monkeypatch) -> None:
    target = tmp_path / "result.ply"
    write(target, survey_cloud(100, seed=1))
    os.chmod(target, 0o640)
    before = target.read_bytes()

    bad = survey_cloud(100, seed=2)
    bad.fields["f_u1"] = bad.fields["f_u1"][:50]  # wrong length (Cloud no longer checks)
    with pytest.raises(InvalidCloudError, match="'f_u1' has shape \\(50,\\) for 100 points"):
        write(target, bad)

    def broken(path, xyz, fields, meta, *, ext):  # writes half a file, then fails
        Path(path).write_bytes(b"ply\nformat binary_little_endian 1.0\n")
        raise OSError("disk full")

    monkeypatch.setattr(tunneldef.io.ply, "write", broken)
    with pytest.raises(OSError, match="disk full"):
        write(target, survey_cloud(100, seed=3))
    monkeypatch.undo()

    las_target = tmp_path / "result.las"
    write(las_target, survey_cloud(100, seed=1))
    las_before = las_target.read_bytes()
    src = read(las_target)
    src.fields["classification"] = np.full(100, 400)  # does not fit the LAS dimension
    with pytest.raises(InvalidCloudError, match="'classification' has values outside"):
        write(las_target, src)

    assert target.read_bytes() == before
    assert las_target.read_bytes() == las_before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.las", "result.ply"]
    write(target, survey_cloud(100, seed=4))  # a good write replaces it, keeping the mode
    assert target.read_bytes() != before
    assert stat.S_IMODE(target.stat().st_mode) == 0o640


# --------------------------------------------------------------------------- errors


def test_missing_and_unsupported(tmp_path: Path) -> None:
    with pytest.raises(MissingFileError, match="input file not found: .*nope.las"):
        read(tmp_path / "nope.las")
    with pytest.raises(MissingFileError, match="not a file"):
        read(tmp_path)
    (tmp_path / "scan.e57").write_bytes(b"x")
    with pytest.raises(UnsupportedFormatError, match=r"'\.e57'; use one of \.las, \.laz, \.ply"):
        read(tmp_path / "scan.e57")
    with pytest.raises(UnsupportedFormatError, match="unsupported extension '.obj'"):
        write(tmp_path / "out.obj", survey_cloud(10))
    with pytest.raises(MissingFileError, match="output folder does not exist"):
        write(tmp_path / "no" / "such" / "out.ply", survey_cloud(10))
    pcd = tmp_path / "odd.pcd"
    pcd.write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        "WIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_zstd\n"
    )
    with pytest.raises(UnsupportedFormatError, match="PCD DATA 'binary_zstd' is not supported"):
        read(pcd)


def test_empty_files(tmp_path: Path) -> None:
    empty_ply = tmp_path / "empty.ply"
    vertex = np.empty(0, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(empty_ply))
    (tmp_path / "empty.xyz").write_text("")
    (tmp_path / "header_only.csv").write_text("x,y,z\n")
    las = laspy.LasData(laspy.LasHeader(version="1.4", point_format=6))
    las.write(tmp_path / "empty.las")
    for name in ("empty.ply", "empty.xyz", "header_only.csv", "empty.las"):
        with pytest.raises(InvalidCloudError, match=f"{name} holds no points"):
            read(tmp_path / name)
    with pytest.raises(InvalidCloudError, match="has 0 points"):
        write(tmp_path / "out.ply", Cloud(np.empty((0, 3))))


def test_bad_clouds_refused_on_write(tmp_path: Path) -> None:
    cloud = survey_cloud(10)
    cloud.xyz[2, 1] = np.nan
    with pytest.raises(InvalidCloudError, match="1 points with NaN or infinite"):
        write(tmp_path / "out.las", cloud)
    with pytest.raises(InvalidCloudError, match=r"fields \['nope'\] are not in the cloud"):
        write(tmp_path / "out.ply", survey_cloud(10), fields=["nope"])
    odd = survey_cloud(10)
    odd.fields["text"] = np.array(["a"] * 10)
    with pytest.raises(InvalidCloudError, match="'text' has dtype <U1"):
        write(tmp_path / "out.ply", odd)
    with pytest.raises(InvalidCloudError, match="expects a Cloud, got ndarray"):
        write(tmp_path / "out.ply", np.zeros((3, 3)))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("name", "cut"),
    [("c.ply", 0.6), ("c.las", 0.6), ("c.laz", 0.5), ("c.pcd", 0.6), ("c.las", 0.02)],
)
def test_truncated_files_are_corrupt(tmp_path: Path, name: str, cut: float) -> None:
    path = tmp_path / name
    write(path, survey_cloud(500))
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * cut)])
    with pytest.raises(CorruptFileError, match=f"cannot read .*{name}: "):
        read(path)


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("g.las", b"this is not a LAS file at all, just some text" * 10),
        ("g.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n"),
        ("g.ply", b"ply\nformat ascii 1.0\nelement face 0\nend_header\n"),
        ("g.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nDATA ascii\n"),
        ("g.pcd", b"VERSION 0.7\nFIELDS a b\nSIZE 4 4\nTYPE F F\nPOINTS 1\nDATA ascii\n1 2\n"),
        ("g.xyz", b"1 2 3\n4 5\n"),
        ("g.xyz", b"1 2\n3 4\n"),
        ("g.csv", b"x,y,z\n1,2,three\n"),
        ("g.xyz", b"\xff\xfe\x00garbage"),
    ],
)
def test_malformed_files_are_corrupt(tmp_path: Path, name: str, content: bytes) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(CorruptFileError, match=f"cannot read .*{name}: .+"):
        read(path)


# --------------------------------------------------------------------------- real scans


def test_real_drift_reads(drift_path: Path) -> None:
    start = time.perf_counter()
    cloud = read(drift_path)
    elapsed = time.perf_counter() - start
    assert len(cloud) == DRIFT_POINTS
    assert cloud.xyz.dtype == np.float64 and np.isfinite(cloud.xyz).all()
    assert {"intensity", "classification", "return_number", "point_source_id"} <= set(cloud.fields)
    extent = np.ptp(cloud.xyz, axis=0)
    assert 10.0 < extent[1] < 20.0  # ~13 m of drift along y (README)
    assert elapsed < 30.0  # a few seconds on 2 cores; generous bound for a busy machine


def test_real_chamber_reads_and_writes_back_exactly(chamber_path: Path, tmp_path: Path) -> None:
    cloud = read(chamber_path)
    assert len(cloud) == CHAMBER_POINTS
    out = tmp_path / "chamber.laz"
    write(out, cloud)
    header = cloud.meta["las_header"]
    got = laspy.read(out)
    assert got.header.point_format.id == header.point_format.id
    np.testing.assert_array_equal(got.header.offsets, header.offsets)
    for axis, dim in enumerate("XYZ"):
        expected = np.rint((cloud.xyz[:, axis] - header.offsets[axis]) / header.scales[axis])
        np.testing.assert_array_equal(got[dim], expected)
    np.testing.assert_array_equal(got.intensity, cloud.fields["intensity"])
