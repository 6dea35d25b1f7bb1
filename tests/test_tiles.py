"""Deformation in chainage tiles gives the untiled values (issue: full-size surveys)."""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef import synth
from tunneldef.config import Config
from tunneldef.pipeline import detect
from tunneldef.tiles import tile_margin

FLOAT_FIELDS = ("deformation", "deformation_horizontal", "deformation_vertical", "chainage",
                "lod95")
EXACT_FIELDS = ("danger", "shell", "surface", "significant")


def _pair(length: float = 100.0, density: float = 60.0):
    spec = synth.PairSpec(
        tunnel=synth.TunnelSpec(length=length, density=density, chamber=True,
                                chamber_chainage=length * 0.4, equipment=True, roughness=0.02),
        deformations=(
            synth.DeformationSpec(kind="roof_sag", chainage=length * 0.5, length=4.0, width=2.0,
                                  amplitude=0.08),
            synth.DeformationSpec(kind="wall_bulge", chainage=length * 0.25, length=3.0,
                                  width=1.5, amplitude=0.06),
        ),
        cmp_shift=1.0, seed=5,
    )
    return synth.make_pair(spec)


def assert_same(tiled, whole) -> None:
    """Every field within 1e-6 m (NaN where NaN), flags equal, the same zones."""
    a, b = tiled.cloud.fields, whole.cloud.fields
    assert sorted(a) == sorted(b)
    for name in FLOAT_FIELDS:
        if name in b:
            x, y = np.asarray(a[name], np.float64), np.asarray(b[name], np.float64)
            np.testing.assert_array_equal(np.isnan(x), np.isnan(y), err_msg=name)
            ok = ~np.isnan(y)
            assert np.max(np.abs(x[ok] - y[ok]), initial=0.0) <= 1e-6, name
    for name in EXACT_FIELDS:
        if name in b:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    np.testing.assert_array_equal(tiled.cloud.xyz, whole.cloud.xyz)
    assert len(tiled.zones) == len(whole.zones)
    for za, zb in zip(tiled.zones, whole.zones, strict=True):
        assert za.keys() == zb.keys()
        for key, v in zb.items():
            if isinstance(v, float):
                assert za[key] == pytest.approx(v, abs=1e-6, nan_ok=True), key
            else:
                assert za[key] == v, key


@pytest.fixture(scope="module")
def pair_100m():
    return _pair()


@pytest.fixture(scope="module")
def untiled_100m(pair_100m):
    return detect(pair_100m.ref, pair_100m.cmp, Config())


def test_four_tiles_equal_untiled(pair_100m, untiled_100m) -> None:
    tiled = detect(pair_100m.ref, pair_100m.cmp, Config(), tiles={"tile_length": 25.0})
    assert untiled_100m.zones, "the pair should have danger zones"
    assert_same(tiled, untiled_100m)
    assert tiled.sections == untiled_100m.sections or len(tiled.sections) == len(
        untiled_100m.sections)


def test_knn_tiles_equal_untiled(pair_100m) -> None:
    config = Config().replace(deformation={"method": "knn"})
    whole = detect(pair_100m.ref, pair_100m.cmp, config)
    tiled = detect(pair_100m.ref, pair_100m.cmp, config, tiles={"tile_length": 25.0})
    assert_same(tiled, whole)


def test_margin_covers_the_estimator_reach() -> None:
    cfg = Config().deformation
    assert tile_margin(cfg) > 1.0 + cfg.normal_radius + 2 * cfg.cylinder_radius
    assert tile_margin(cfg.__class__(method="knn")) >= 3 * cfg.max_distance
