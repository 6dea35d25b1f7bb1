"""Chunked reading and writing give what the whole-cloud reader and writer give."""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef.cloud import Cloud
from tunneldef.errors import InvalidCloudError, MissingFileError
from tunneldef.io import ply, read, stream, write
from tunneldef.io.stream import read_points, write_with_fields
from tunneldef.transforms import apply_transform


@pytest.fixture
def small_chunks(monkeypatch):
    monkeypatch.setattr(stream, "CHUNK_POINTS", 997)


def _cloud(n: int = 5000, seed: int = 0) -> Cloud:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform([1000.0, 2000.0, 10.0], [1060.0, 2006.0, 13.0], size=(n, 3))
    fields = {"intensity": rng.integers(0, 65535, n).astype(np.uint16),
              "classification": rng.integers(0, 20, n).astype(np.uint8),
              "gps_time": rng.uniform(0, 1e5, n),
              "reflectance": rng.normal(size=n).astype(np.float32)}
    return Cloud(xyz, fields)


def _motion() -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    t[:3, 3] = [12.5, -3.25, 0.5]
    return t


@pytest.mark.parametrize("ext", [".las", ".laz", ".ply"])
def test_read_points_equals_read(tmp_path, small_chunks, ext) -> None:
    path = tmp_path / f"a{ext}"
    write(path, _cloud())
    xyz, keep = read_points(path)
    assert keep is None
    np.testing.assert_array_equal(xyz, read(path).xyz)


@pytest.mark.parametrize("src_ext,out_ext", [(".laz", ".laz"), (".las", ".laz"), (".laz", ".las"),
                                             (".ply", ".ply"), (".laz", ".ply")])
def test_chunked_output_equals_whole_cloud_output(tmp_path, small_chunks, src_ext,
                                                  out_ext) -> None:
    src = tmp_path / f"src{src_ext}"
    write(src, _cloud())
    xyz, keep = read_points(src)
    moved = apply_transform(_motion(), xyz)
    rng = np.random.default_rng(1)
    new = {"deformation": rng.normal(size=len(xyz)).astype(np.float32),
           "danger": (rng.random(len(xyz)) > 0.9).astype(np.uint8)}
    whole = read(src).transformed(_motion())
    whole.add_fields(new)
    write(tmp_path / f"whole{out_ext}", whole)
    write_with_fields(tmp_path / f"chunked{out_ext}", src, moved, new, keep=keep)
    a, b = read(tmp_path / f"chunked{out_ext}"), read(tmp_path / f"whole{out_ext}")
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert list(a.fields) == list(b.fields)
    for name in b.fields:
        np.testing.assert_array_equal(a.fields[name], b.fields[name], err_msg=name)
    if out_ext != ".ply":
        ha, hb = a.meta["las_header"], b.meta["las_header"]
        assert ha.point_count == hb.point_count == len(xyz)
        np.testing.assert_array_equal(ha.mins, hb.mins)
        np.testing.assert_array_equal(ha.maxs, hb.maxs)


def test_chunked_output_drops_the_points_the_reader_dropped(tmp_path, small_chunks) -> None:
    cloud = _cloud(3000)
    cloud.xyz[[5, 1500, 2999]] = np.nan
    src = tmp_path / "src.ply"
    ply.write(src, cloud.xyz, cloud.fields, {}, ext=".ply")  # the checked writer refuses NaN
    xyz, keep = read_points(src)
    assert keep is not None and int((~keep).sum()) == 3 and len(xyz) == 2997
    with pytest.raises(InvalidCloudError, match="NaN"):
        read_points(src, strict=True)
    write_with_fields(tmp_path / "out.ply", src, xyz, {"d": np.zeros(len(xyz), np.float32)},
                      keep=keep)
    assert len(read(tmp_path / "out.ply")) == 2997


def test_failed_write_leaves_no_file_and_keeps_the_old_one(tmp_path, small_chunks) -> None:
    src = tmp_path / "src.laz"
    write(src, _cloud())
    xyz, _ = read_points(src)
    out = tmp_path / "out.laz"
    out.write_bytes(b"old")
    short = {"deformation": np.zeros(len(xyz) - 10, np.float32)}  # too few values
    with pytest.raises(Exception):  # noqa: B017 - any failure, the point is what is left
        write_with_fields(out, src, xyz, short)
    assert out.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.laz", "src.laz"]


def test_missing_input_is_a_one_line_error(tmp_path) -> None:
    with pytest.raises(MissingFileError):
        read_points(tmp_path / "nope.laz")
