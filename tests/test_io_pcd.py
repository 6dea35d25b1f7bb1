"""binary_compressed PCD: every field as in the same file written uncompressed, both decoders.

Compressed files are written here as PCL writes them (one LZF stream holding one block per
field) with a small LZF encoder of our own, so layouts Open3D does not write (COUNT > 1, rgba,
padding, mixed types) are covered; the truth is the same columns written as DATA binary.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from tunneldef.errors import CorruptFileError
from tunneldef.io import pcd as pcd_module
from tunneldef.io import read, write
from tunneldef.io.pcd import lzf_decompress

ORIGIN = np.array([4.5e5, 5.6e6, 310.0])


def lzf_compress(data: bytes) -> bytes:
    """Greedy LZF encoder (liblzf stream format), for writing test files only."""
    out = bytearray()
    literal = bytearray()
    last: dict[bytes, int] = {}
    i, n = 0, len(data)

    def flush() -> None:
        while literal:
            chunk = literal[:32]
            del literal[:32]
            out.append(len(chunk) - 1)
            out.extend(chunk)

    while i < n:
        key = data[i : i + 3]
        ref = last.get(key) if len(key) == 3 else None
        last[key] = i
        if ref is not None and i - ref - 1 < 8192:
            length = 3
            while i + length < n and length < 264 and data[ref + length] == data[i + length]:
                length += 1
            flush()
            off, run = i - ref - 1, length - 2
            if run < 7:
                out.append((run << 5) | (off >> 8))
            else:
                out += bytes([(7 << 5) | (off >> 8), run - 7])
            out.append(off & 0xFF)
            i += length
        else:
            literal.append(data[i])
            i += 1
    flush()
    return bytes(out)


def _header(names, types, counts, n, *, height=1, data="binary") -> bytes:  # noqa: ANN001
    kinds = [np.dtype(t).kind.upper() for t in types]
    return (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(names)}\n"
        f"SIZE {' '.join(str(np.dtype(t).itemsize) for t in types)}\n"
        f"TYPE {' '.join(kinds)}\nCOUNT {' '.join(map(str, counts))}\n"
        f"WIDTH {n // height}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        f"DATA {data}\n"
    ).encode()


def write_pair(tmp: Path, name: str, columns: list[tuple[str, np.ndarray]], *, height=1):  # noqa: ANN001, ANN201
    """The same columns as DATA binary and DATA binary_compressed; returns both paths."""
    names = [c for c, _ in columns]
    types = [v.dtype.str[1:] for _, v in columns]
    counts = [v.shape[1] if v.ndim == 2 else 1 for _, v in columns]
    n = len(columns[0][1])
    rows = np.empty(
        n,
        dtype=[
            (f"f{i}", "<" + t, (c,)) if c > 1 else (f"f{i}", "<" + t)
            for i, (t, c) in enumerate(zip(types, counts, strict=True))
        ],
    )
    for i, (_, v) in enumerate(columns):
        rows[f"f{i}"] = v
    plain = tmp / f"{name}_binary.pcd"
    plain.write_bytes(_header(names, types, counts, n, height=height) + rows.tobytes())
    body = b"".join(
        np.ascontiguousarray(v).astype(v.dtype.newbyteorder("<")).tobytes() for _, v in columns
    )
    packed = lzf_compress(body)
    comp = tmp / f"{name}_compressed.pcd"
    comp.write_bytes(
        _header(names, types, counts, n, height=height, data="binary_compressed")
        + struct.pack("<II", len(packed), len(body))
        + packed
    )
    return plain, comp


def _layouts(rng: np.random.Generator, n: int) -> dict[str, list[tuple[str, np.ndarray]]]:
    xyz = (rng.random((n, 3)) * [40, 4, 3]).round(3).astype(np.float32)
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint32)
    packed = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    f = [("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])]
    return {
        # a handheld SLAM export as PCL writes it: alpha 255 in the top byte of a float rgb,
        # so every colour with red >= 128 is a NaN bit pattern
        "slam": f
        + [
            ("intensity", rng.random(n).astype(np.float32)),
            ("rgb", (packed | np.uint32(0xFF000000)).view(np.float32)),
        ],
        "rgba_and_count": f
        + [
            ("rgba", packed | (rng.integers(0, 256, n).astype(np.uint32) << 24)),
            ("hist", rng.random((n, 3)).astype(np.float32)),
        ],
        "padding_and_ints": f
        + [
            ("_", np.zeros((n, 4), np.uint8)),
            ("ring", rng.integers(0, 64, n).astype(np.uint16)),
            ("t", rng.integers(-(10**12), 10**12, n).astype(np.int64)),
            ("cls", rng.integers(0, 255, n).astype(np.uint8)),
            ("rgb", packed),
        ],
        "doubles": [
            ("x", ORIGIN[0] + xyz[:, 0].astype(np.float64)),
            ("y", ORIGIN[1] + xyz[:, 1].astype(np.float64)),
            ("z", xyz[:, 2].astype(np.float64)),
            ("normal_x", rng.random(n)),
            ("curvature", rng.random(n).astype(np.float32)),
        ],
        # x, y, z of different types: Open3D cannot be used, numpy decodes
        "mixed_xyz": [
            ("x", ORIGIN[0] + xyz[:, 0].astype(np.float64)),
            ("y", xyz[:, 1]),
            ("z", xyz[:, 2]),
            ("i", rng.integers(0, 9, n).astype(np.int8)),
        ],
    }


def _same(a, b) -> None:  # noqa: ANN001
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert list(a.fields) == list(b.fields)
    for name in a.fields:
        assert a.fields[name].dtype == b.fields[name].dtype, name
        np.testing.assert_array_equal(a.fields[name], b.fields[name], err_msg=name)


@pytest.mark.parametrize(
    "layout", ["slam", "rgba_and_count", "padding_and_ints", "doubles", "mixed_xyz"]
)
@pytest.mark.parametrize("decoder", ["open3d", "numpy"])
def test_compressed_equals_binary(tmp_path: Path, layout: str, decoder: str, monkeypatch) -> None:  # noqa: ANN001
    if decoder == "numpy":
        monkeypatch.setattr(pcd_module, "_decompress_open3d", lambda *a: None)
    elif layout != "mixed_xyz":  # Open3D must do it: no silent fallback to the slow decoder

        def refuse(*args: object) -> None:
            raise AssertionError("numpy LZF decoder used")

        monkeypatch.setattr(pcd_module, "lzf_decompress", refuse)
    rng = np.random.default_rng(1)
    plain, comp = write_pair(tmp_path, layout, _layouts(rng, 700)[layout])
    want, got = read(plain), read(comp)
    _same(got, want)
    assert got.meta["pcd"].get("packed_rgb") == want.meta["pcd"].get("packed_rgb")
    if layout == "rgba_and_count":
        assert {"red", "green", "blue", "alpha", "hist_0", "hist_1", "hist_2"} <= set(got.fields)
    # written back (as binary) and read again: every field survives
    write(tmp_path / "back.pcd", got)
    _same(read(tmp_path / "back.pcd"), got)


def test_organized_cloud_with_nan_points(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    xyz = rng.random((40 * 5, 3)).astype(np.float32)
    xyz[::7] = np.nan  # no return: organized clouds keep the pixel as NaN
    cols = [
        ("x", xyz[:, 0]),
        ("y", xyz[:, 1]),
        ("z", xyz[:, 2]),
        ("range", rng.integers(0, 9999, 200).astype(np.uint16)),
    ]
    plain, comp = write_pair(tmp_path, "organized", cols, height=5)
    got = read(comp)
    _same(got, read(plain))
    assert len(got) == 200 - 29
    assert got.meta["dropped_nonfinite"] == 29


def test_open3d_written_file(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(3)
    n = 500
    tpc = o3d.t.geometry.PointCloud()
    xyz = rng.random((n, 3)).astype(np.float32)
    tpc.point.positions = o3d.core.Tensor(xyz)
    tpc.point.colors = o3d.core.Tensor(rng.integers(0, 256, (n, 3)).astype(np.uint8))
    tpc.point.intensity = o3d.core.Tensor(rng.random((n, 1)).astype(np.float32))
    path = tmp_path / "o3d.pcd"
    assert o3d.t.io.write_point_cloud(str(path), tpc, write_ascii=False, compressed=True)
    got = read(path)
    np.testing.assert_array_equal(got.xyz, xyz.astype(np.float64))
    for k, c in enumerate(("red", "green", "blue")):
        np.testing.assert_array_equal(got.fields[c], tpc.point.colors.numpy()[:, k])
    np.testing.assert_array_equal(got.fields["intensity"], tpc.point.intensity.numpy()[:, 0])


@pytest.mark.parametrize(
    "data",
    [
        b"a",
        b"abc" * 1000,  # long back-references (length byte)
        bytes(5000),  # one overlapping run copied from 1 byte back
        bytes(range(256)) * 3,
        np.random.default_rng(4).integers(0, 4, 20000, dtype=np.uint8).tobytes(),
        np.random.default_rng(5).integers(0, 256, 3000, dtype=np.uint8).tobytes(),  # literals
        np.arange(30000, dtype=np.float32).tobytes(),  # references up to 8 KiB back
    ],
)
def test_lzf_decompress_round_trip(data: bytes) -> None:
    assert lzf_decompress(lzf_compress(data), len(data)).tobytes() == data


def test_lzf_decompress_hand_made_tokens() -> None:
    # 3 literals "abc", then copy 7 bytes from 3 back (overlapping): "abcabcabca"
    stream = bytes([2]) + b"abc" + bytes([(5 << 5) | 0, 2])
    assert lzf_decompress(stream, 10).tobytes() == b"abcabcabca"
    # length byte: run 7 + 10 -> 19 bytes copied from 1 back
    stream = bytes([0]) + b"z" + bytes([(7 << 5) | 0, 10, 0])
    assert lzf_decompress(stream, 20).tobytes() == b"z" * 20


@pytest.mark.parametrize(
    ("stream", "size", "match"),
    [
        (bytes([4]) + b"abc", 5, "decodes to"),  # truncated literal run
        (bytes([2]) + b"abc", 9, "decodes to"),  # announced size wrong
        (bytes([0]) + b"a" + bytes([(1 << 5) | 0, 5]), 4, "before the start"),
    ],
)
def test_lzf_decompress_damaged(stream: bytes, size: int, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        lzf_decompress(stream, size)


def test_damaged_compressed_pcd(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    _, comp = write_pair(tmp_path, "d", _layouts(rng, 100)["slam"])
    raw = comp.read_bytes()
    head, body = raw.split(b"DATA binary_compressed\n")
    head += b"DATA binary_compressed\n"
    csize, usize = struct.unpack("<II", body[:8])
    bad = tmp_path / "bad.pcd"
    bad.write_bytes(head + body[: 8 + csize // 2])
    with pytest.raises(CorruptFileError, match="compressed bytes announced"):
        read(bad)
    bad.write_bytes(head + struct.pack("<II", csize, usize + 4) + body[8:])
    with pytest.raises(CorruptFileError, match="uncompressed bytes announced"):
        read(bad)
    bad.write_bytes(head + body[:4])
    with pytest.raises(CorruptFileError, match="size header"):
        read(bad)
