"""Centreline of the real Freiberg drift scan (../shared/data, README there).

A static TLS scan, scanner at the origin: ~13 m of a straight drift about 1.9 m x 1.85 m
(overall extent), axis roughly along world y; the floor and roof are missing within ~1.1 m of
the scanner (blind cone) and the far end is seen at grazing angles. The 2.7 M points are
thinned to one per 3 cm voxel (~130 k, uniform density along the drift) for speed.

Measured (this subsample, default config): centreline 12.1 m long, 20 of 27 slices accepted
(rejected: the blind cone, far-end walls seen at grazing angles), 3 passes; wall-to-wall
1.78 m and floor-to-roof 1.65 m (medians of the dense wall/roof surfaces), against 1.85 m x
1.73 m for the 1-99 % extents of the same sections (rough rock, ledges). ~1 s for 130 k points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tunneldef.centerline import CenterlineResult, extract_centerline

VOXEL = 0.03


def _voxel_thin(xyz: np.ndarray, size: float) -> np.ndarray:
    ijk = np.floor((xyz - xyz.min(axis=0)) / size).astype(np.int64)
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    _, first = np.unique(key, return_index=True)
    return xyz[np.sort(first)]


@pytest.fixture(scope="module")
def drift(drift_path: Path) -> np.ndarray:
    laspy = pytest.importorskip("laspy")
    las = laspy.read(drift_path)
    return _voxel_thin(np.stack([las.x, las.y, las.z], axis=1), VOXEL)


@pytest.fixture(scope="module")
def drift_result(drift: np.ndarray) -> CenterlineResult:
    return extract_centerline(drift)


def test_drift_axis_is_along_world_y(drift_result: CenterlineResult) -> None:
    axis = drift_result.frame.axes[0]
    assert abs(axis[1]) > 0.99  # "axis roughly along y"
    cl = drift_result.centerline
    assert cl.length >= 10.5  # of ~13 m; the far end's walls are seen at grazing angles
    span = np.ptp(cl.points[:, 1])
    assert span >= 10.4  # the passes keep the best curve, which may end a centimetre short


def test_drift_centreline_stays_inside(drift: np.ndarray, drift_result: CenterlineResult) -> None:
    cl = drift_result.centerline
    p = cl.project(drift)
    scanner_xy = np.hypot(*cl.points[:, :2].T)
    checked = 0
    for s0 in np.arange(0.0, cl.length, 0.25):
        near = np.abs(p.chainage - s0) < 0.1
        band = near & (np.abs(p.vertical) < 0.4)
        lat = p.lateral[band]
        if lat.size < 50:
            continue
        checked += 1
        # shell on both sides, the curve at least 30 cm from the outermost points
        assert np.percentile(lat, 99) > 0.3, s0
        assert np.percentile(lat, 1) < -0.3, s0
        i = int(np.clip(round(s0 / (cl.chainage[1] - cl.chainage[0])), 0, len(cl.points) - 1))
        if scanner_xy[i] > 1.6:  # outside the blind cone floor and roof are seen
            col = near & (np.abs(p.lateral) < 0.4)
            ver = p.vertical[col]
            assert np.percentile(ver, 99) > 0.6, s0
            assert np.percentile(ver, 1) < -0.6, s0
    assert checked >= 40


def test_drift_width_and_height(drift: np.ndarray, drift_result: CenterlineResult) -> None:
    ok = drift_result.accepted
    assert len(ok) >= 15
    width = float(np.median([r.width for r in ok]))
    height = float(np.median([r.height for r in ok]))
    # README: about 1.9 m wide and 1.85 m high (overall extent)
    assert width == pytest.approx(1.9, abs=0.2)
    assert height == pytest.approx(1.85, abs=0.3)
    # the lines are the dense surfaces: inside the 1-99 % extents of the same sections, by less
    # than 15 cm (rock roughness)
    cl = drift_result.centerline
    p = cl.project(drift)
    ext_w, ext_h = [], []
    for r in ok:
        near = np.abs(p.chainage - r.chainage) < 0.1
        band = near & (np.abs(p.vertical) < 0.4)
        col = near & (np.abs(p.lateral) < 0.4)
        ext_w.append(np.ptp(np.percentile(p.lateral[band], [1, 99])))
        ext_h.append(np.ptp(np.percentile(p.vertical[col], [1, 99])))
    assert 0.0 < np.median(ext_w) - width < 0.15
    assert 0.0 < np.median(ext_h) - height < 0.15
    # the blind cone under the scanner is rejected, not guessed
    reasons = " ".join(r.reason for r in drift_result.slices if not r.ok)
    assert "floor" in reasons or "roof" in reasons


def test_junction_scan_keeps_the_main_drift(chamber_path: Path) -> None:
    """The four-way junction scan (second real file): the cross drifts make the junction
    slices wide; they are rejected as chambers and the centreline follows the main drift.
    Measured: 6 of 26 slices accepted (widths 1.6-2.2 m), 10 rejected as chamber/niche,
    centreline 12.6 m along world y."""
    laspy = pytest.importorskip("laspy")
    las = laspy.read(chamber_path)
    xyz = _voxel_thin(np.stack([las.x, las.y, las.z], axis=1), VOXEL)
    res = extract_centerline(xyz)
    assert abs(res.frame.axes[0][1]) > 0.99
    assert res.centerline.length >= 10.0
    ok = res.accepted
    assert len(ok) >= 5
    assert sum("chamber" in r.reason for r in res.slices) >= 6
    width = np.array([r.width for r in ok])
    assert np.all((width > 1.3) & (width < 2.4))
