"""Time to read one cloud stored as LAZ, binary PCD and binary_compressed PCD.

The cloud: N points (default 180 000, a 3 MB compressed PCD) along a 300 m drift, coordinates
rounded to 1 mm, a float intensity and a packed rgb; the compressed PCD is written by Open3D
(PCL's layout: one LZF stream, one block per field). Rows:

- ``in process``: best of 5 reads with Open3D already imported (it is, in any pipeline run:
  registration and stray removal use it);
- ``fresh process``: one read in a new interpreter, imports included (``import open3d`` alone
  costs about 1-2.5 s, half of it Open3D's plotting helpers);
- ``numpy LZF``: the fallback decoder alone (used when x, y, z have different types).

Run: ``python benchmarks/read_speed.py [--points 180000]``
"""

from __future__ import annotations

import argparse
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tunneldef.cloud import Cloud
from tunneldef.io import read, write
from tunneldef.io.pcd import lzf_decompress


def _write_compressed(path: Path, xyz: np.ndarray, intensity: np.ndarray, rgb: np.ndarray) -> None:
    import open3d as o3d

    tpc = o3d.t.geometry.PointCloud()
    tpc.point.positions = o3d.core.Tensor(xyz)
    tpc.point.intensity = o3d.core.Tensor(intensity[:, None])
    tpc.point.colors = o3d.core.Tensor(rgb)
    if not o3d.t.io.write_point_cloud(str(path), tpc, write_ascii=False, compressed=True):
        raise RuntimeError(f"Open3D could not write {path}")


def _best(path: Path, repeat: int = 5) -> float:
    read(path)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        read(path)
        times.append(time.perf_counter() - start)
    return min(times)


def _fresh(path: Path) -> float:
    code = (
        "import time; t = time.perf_counter(); from pathlib import Path; "
        f"from tunneldef.io import read; read(Path({str(path)!r})); "
        "print(time.perf_counter() - t)"
    )
    root = str(Path(__file__).resolve().parents[1])
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        env={"PYTHONPATH": root, "PATH": ""},
    )
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--points", type=int, default=180_000)
    args = parser.parse_args()
    import open3d  # noqa: F401  (imported as in a pipeline run)

    rng = np.random.default_rng(0)
    n = args.points
    xyz = np.round(rng.random((n, 3)) * [300.0, 4.0, 4.0], 3).astype(np.float32)
    intensity = rng.integers(0, 255, n).astype(np.float32)
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        comp = d / "cloud_compressed.pcd"
        _write_compressed(comp, xyz, intensity, rgb)
        cloud = read(comp)
        write(d / "cloud.laz", Cloud(cloud.xyz, dict(cloud.fields)))
        write(d / "cloud_binary.pcd", cloud)
        size = comp.stat().st_size / 1e6
        print(f"{n} points; compressed PCD {size:.1f} MB\n")
        print("| file | in process | fresh process |")
        print("| --- | --- | --- |")
        for name in ("cloud.laz", "cloud_binary.pcd", "cloud_compressed.pcd"):
            path = d / name
            print(f"| {name} | {_best(path):.3f} s | {_fresh(path):.2f} s |")
        raw = comp.read_bytes()
        start = raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
        csize, usize = struct.unpack_from("<II", raw, start)
        t = time.perf_counter()
        lzf_decompress(raw[start + 8 : start + 8 + csize], usize)
        print(f"| numpy LZF decoder alone | {time.perf_counter() - t:.3f} s | |")


if __name__ == "__main__":
    main()
