"""Centreline diagnostic figures (paper Fig. 3, 4, 12, 15, 16 analogues)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tunneldef.centerline import extract_centerline
from tunneldef.config import Config
from tunneldef.report.centerline_plots import plot_centerline_diagnostics
from tunneldef.synth import TunnelSpec, make_tunnel

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def small() -> tuple[np.ndarray, object]:
    cloud, _ = make_tunnel(TunnelSpec(length=12.0, density=100.0, equipment=True), seed=4)
    cfg = Config().replace(centerline={"max_iterations": 1})
    return cloud.xyz, extract_centerline(cloud.xyz, slicing=cfg.slicing, settings=cfg.centerline)


def test_writes_the_five_figures(small, tmp_path: Path) -> None:  # noqa: ANN001
    xyz, res = small
    out = tmp_path / "figs"
    files = plot_centerline_diagnostics(res, xyz, out, slices=2)
    names = sorted(f.name for f in files)
    assert names == [
        "centerline_fig03_roof_floor.png",
        "centerline_fig04_walls.png",
        "centerline_fig12_slices.png",
        "centerline_fig15_wall_lines.png",
        "centerline_fig16_fit_comparison.png",
    ]
    for f in files:
        assert f.parent == out
        data = f.read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 10_000
