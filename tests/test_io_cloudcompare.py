"""The real CloudCompare loads a PLY written by tunneldef.io with our scalar fields by name."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tunneldef.cloud import Cloud
from tunneldef.io import write

CLOUDCOMPARE = shutil.which("CloudCompare")

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(CLOUDCOMPARE is None, reason="CloudCompare is not on PATH"),
]


def test_cloudcompare_reads_our_ply_scalar_fields(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    n = 2000
    xyz = np.array([450000.0, 5600000.0, 300.0]) + rng.random((n, 3)) * [30.0, 6.0, 3.0]
    fields = {
        "deformation": rng.normal(0.0, 0.02, n).astype(np.float32),
        "chainage": (xyz[:, 0] - 450000.0).astype(np.float32),
        "danger": (rng.random(n) > 0.9).astype(np.uint8),
        "returns": rng.integers(0, 60000, n, dtype=np.uint16),
        "index": np.arange(n, dtype=np.uint32) * 100,
        "sigma": rng.random(n) * 0.01,
    }
    ply = tmp_path / "result.ply"
    write(ply, Cloud(xyz, fields))

    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    cmd = [
        CLOUDCOMPARE, "-SILENT", "-AUTO_SAVE", "OFF",
        "-O", "-GLOBAL_SHIFT", "AUTO", str(ply),
        "-C_EXPORT_FMT", "ASC", "-ADD_HEADER", "-NO_TIMESTAMP", "-SAVE_CLOUDS",
    ]  # fmt: skip
    run = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    asc = tmp_path / "result.asc"  # CloudCompare writes next to the input, same base name
    assert run.returncode == 0 and asc.is_file(), run.stdout[-2000:] + run.stderr[-2000:]

    with open(asc) as stream:
        header = stream.readline().strip()
    assert header.startswith("//")
    names = header[2:].split()
    assert names[:3] == ["X", "Y", "Z"]
    assert sorted(names[3:]) == sorted(fields)  # the scalar_ prefix is gone: our names
    table = np.loadtxt(asc, comments="//", ndmin=2)
    assert table.shape == (n, 3 + len(fields))
    np.testing.assert_allclose(table[:, :3], xyz, rtol=0, atol=1e-4)
    for k, name in enumerate(names[3:], start=3):
        np.testing.assert_allclose(table[:, k], fields[name], rtol=0, atol=1e-4, err_msg=name)
