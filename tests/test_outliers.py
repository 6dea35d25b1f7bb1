"""Stray-point removal and the robust extent, on a synthetic drift with planted strays."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tunneldef.errors import InvalidCloudError
from tunneldef.outliers import (
    _compress,
    _neighbour_pairs,
    remove_strays,
    robust_extent,
    stray_report,
)
from tunneldef.synth import TunnelSpec, make_tunnel

ORIGIN = np.array([4.5e5, 5.6e6, 310.0])  # UTM-like coordinates


@pytest.fixture(scope="module")
def planted() -> dict[str, np.ndarray]:
    """A 20 m curved drift (pipes, cables, conveyor, coal) with planted strays:
    one point 130 m away, five far clusters of 3-11 points, 300 ghost points 0.7-1.3 m
    outside the walls, and a lone sparse cable hanging 0.6 m below the roof."""
    spec = TunnelSpec(
        length=20.0,
        radius=60.0,
        density=100.0,
        equipment=True,
        conveyor=True,
        outlier_fraction=0.0,
    )
    cloud, truth = make_tunnel(spec, seed=3)
    xyz = cloud.xyz
    rng = np.random.default_rng(0)
    mid = xyz.mean(axis=0)
    far = mid[None] + [[130.0, 0.0, 0.0]]
    centres = [mid + rng.normal(0, 20, 3) * [1, 1, 0.2] + [0, 0, 8] for _ in range(5)]
    clusters = np.concatenate([c + rng.normal(0, 0.1, (rng.integers(3, 12), 3)) for c in centres])
    wall = np.nonzero((truth.surface == 1) | (truth.surface == 2))[0]
    sel = rng.choice(wall, 300)
    proj = truth.centerline.project(xyz[sel])
    _, lateral, _ = truth.centerline.frame_at(proj.chainage)
    out = np.sign(proj.lateral)[:, None] * lateral
    ghosts = xyz[sel] + out * rng.uniform(0.7, 1.3, (300, 1))
    s = np.linspace(2.0, 18.0, 128)  # 8 points per metre
    cable = truth.centerline.point_at(s) + [0, 0, spec.section.height / 2 - 0.6]
    cable += rng.normal(0, 0.005, cable.shape)
    kind = np.concatenate(
        [
            np.full(len(xyz), 0),
            [1],
            np.full(len(clusters), 2),
            np.full(300, 3),
            np.full(len(cable), 4),
        ]
    )
    return {
        "xyz": np.concatenate([xyz, far, clusters, ghosts, cable]) + ORIGIN,
        "kind": kind,
        "label": truth.label,
    }


def test_strays_go_and_the_tunnel_stays(planted: dict[str, np.ndarray]) -> None:
    xyz, kind, label = planted["xyz"], planted["kind"], planted["label"]
    report = stray_report(xyz)
    keep = report.keep
    assert not keep[kind == 1].any()  # the point 130 m away
    assert not keep[kind == 2].any()  # the far clusters
    assert keep[kind == 3].sum() <= 3  # ghosts a metre off the walls (300 planted)
    assert keep[kind == 4].mean() > 0.95  # a lone cable across the void stays
    tunnel = keep[kind == 0]
    for lab in (0, 1, 2):  # shell (roof, walls, floor), pipes/cables/conveyor, coal
        assert (~tunnel[label == lab]).mean() < 0.005
    assert (~tunnel).mean() < 0.001
    assert report.removed == report.sparse + report.distant + report.detached
    np.testing.assert_array_equal(remove_strays(xyz), keep)


def test_far_stray_does_not_blow_up_the_grid(planted: dict[str, np.ndarray]) -> None:
    xyz = np.concatenate([planted["xyz"], planted["xyz"][:1] + [1.4e6, 0, 0]])
    start = time.perf_counter()
    keep = remove_strays(xyz)
    assert time.perf_counter() - start < 5.0
    assert not keep[-1]
    assert keep[:-1][planted["kind"] == 0].mean() > 0.999


def test_extent_ignores_strays(planted: dict[str, np.ndarray]) -> None:
    xyz, kind = planted["xyz"], planted["kind"]
    keep = remove_strays(xyz)
    raw = robust_extent(xyz, quantile=0.0)
    clean = robust_extent(xyz, keep=keep, quantile=0.0)
    truth = robust_extent(xyz[kind == 0], quantile=0.0)
    assert raw.longest > 130.0
    np.testing.assert_allclose(clean.lower, truth.lower, atol=1e-9)
    np.testing.assert_allclose(clean.upper, truth.upper, atol=1e-9)
    # along directions: the percentiles of the projections
    d = np.array([[1.0, 0.0, 0.0], [0.6, 0.8, 0.0]])
    along = robust_extent(xyz, keep=keep, quantile=0.0, directions=d)
    assert along.lower.shape == (2,)
    assert along.lower[0] == pytest.approx(clean.lower[0], abs=1e-6)
    proj = xyz[keep] @ d[1]
    assert along.size[1] == pytest.approx(proj.max() - proj.min(), abs=1e-6)
    arc = robust_extent(xyz, keep=keep, quantile=0.1, directions=[1.0, 0.0, 0.0])
    assert arc.size[0] == pytest.approx(20.4, abs=0.3)  # (60 + 2.9) m x sin(20 m / 60 m)
    assert clean.diagonal == pytest.approx(float(np.linalg.norm(clean.size)))


def test_robust_extent_percentiles() -> None:
    x = np.arange(1001.0)
    xyz = np.c_[x, 2 * x, np.zeros_like(x)]
    ext = robust_extent(xyz, quantile=1.0)
    np.testing.assert_allclose(ext.lower, [10.0, 20.0, 0.0])
    np.testing.assert_allclose(ext.upper, [990.0, 1980.0, 0.0])
    assert ext.longest == pytest.approx(1960.0)
    with pytest.raises(InvalidCloudError):
        robust_extent(xyz, keep=np.zeros(1001, dtype=bool))
    with pytest.raises(ValueError, match="quantile"):
        robust_extent(xyz, quantile=60.0)


def test_bad_input_is_refused() -> None:
    with pytest.raises(InvalidCloudError):
        remove_strays(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(ValueError, match="voxel"):
        remove_strays(np.zeros((10, 3)), voxel=0.0)


def test_neighbour_pairs_and_compression() -> None:
    cells = np.array([[0, 0, 0], [1, 1, 1], [3, 0, 0], [10**9, 0, 0], [10**9 + 1, 0, 1]])
    np.testing.assert_array_equal(_compress(cells)[:, 0], [0, 1, 3, 5, 6])
    r, c = _neighbour_pairs(cells)
    pairs = {tuple(sorted(p)) for p in zip(r.tolist(), c.tolist(), strict=True)}
    assert pairs == {(0, 1), (3, 4)}


def test_real_drift_keeps_its_points(drift_path) -> None:  # noqa: ANN001
    """The Freiberg drift (2.68 M TLS points, pipes and cables on the walls): with a point
    130 m away and three small clusters planted, those go and < 0.1 % of the scan does
    (measured: 0.009 %)."""
    from tunneldef.io import read

    xyz = read(drift_path).xyz
    rng = np.random.default_rng(8)
    planted = np.concatenate(
        [[[0.0, 130.0, 0.0]]]
        + [c + rng.normal(0, 0.05, (5, 3)) for c in ([6, 20, 0], [-9, 0, 3], [0, -40, 1])]
    )
    keep = remove_strays(np.concatenate([xyz, planted]))
    assert not keep[len(xyz) :].any()
    assert (~keep[: len(xyz)]).mean() < 0.001


def test_too_sparse_a_cloud_is_reported(caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(9)
    xyz = np.c_[rng.uniform(0, 50, 2000), rng.uniform(0, 5, 2000), rng.uniform(0, 3, 2000)]
    with caplog.at_level("WARNING", logger="tunneldef.outliers"):
        keep = remove_strays(xyz)  # ~3 points per m^3: everything looks stray
    assert (~keep).mean() > 0.5
    assert "larger voxel" in caplog.text
    with pytest.raises(ValueError, match="unit vectors"):
        robust_extent(xyz, directions=[2.0, 0.0, 0.0])
