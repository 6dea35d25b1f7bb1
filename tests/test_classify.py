"""Danger threshold, per-point danger flags and danger zones (paper §4.3, Fig. 22)."""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef.deformation import DeformationResult
from tunneldef.deformation.classify import (
    danger_threshold,
    danger_zones,
    judged_values,
    local_median,
    normal_component,
    robust_peak,
)
from tunneldef.deformation.sections import FLOOR, LEFT_WALL, ROOF
from tunneldef.errors import ConfigError

STEP = 0.01  # point spacing along the chainage, m


def _line_result() -> DeformationResult:
    """A roof line and a floor line, chainage 0..10 m, one point per cm.

    roof: -0.05 on [2.0, 3.4), -0.08 on [3.4, 4.0] except a 0.3 m gap at [3.0, 3.3) (zero);
    a 0.1 m run of -0.05 at [6.0, 6.1]; a non-shell object of -0.2 at [5.0, 5.5].
    floor: +0.06 on [8.0, 9.0]. Everything else 0.
    """
    s = np.round(np.arange(0.0, 10.0 + 1e-9, STEP), 6)
    roof_v = np.zeros(s.size)
    roof_v[(s >= 2.0) & (s < 3.4)] = -0.05
    roof_v[(s >= 3.4) & (s <= 4.0)] = -0.08
    roof_v[(s >= 3.0) & (s < 3.3)] = 0.0
    roof_v[(s >= 6.0) & (s <= 6.1)] = -0.05
    roof_v[(s >= 5.0) & (s <= 5.5)] = -0.2
    floor_v = np.where((s >= 8.0) & (s <= 9.0), 0.06, 0.0)
    n = s.size
    chainage = np.r_[s, s]
    value = np.r_[roof_v, floor_v]
    shell = np.ones(2 * n, bool)
    shell[:n][(s >= 5.0) & (s <= 5.5)] = False
    xyz = np.c_[chainage, np.zeros(2 * n), np.r_[np.full(n, 1.43), np.full(n, -1.43)]]
    return DeformationResult(
        deformation=value,
        horizontal=np.zeros(2 * n),
        vertical=value,
        chainage=chainage,
        surface=np.r_[np.full(n, ROOF), np.full(n, FLOOR)].astype(np.uint8),
        shell=shell,
        xyz=xyz,
        centerline_length=10.0,
    )


def test_zones_are_merged_dropped_and_measured():
    d = _line_result()
    danger, zones = danger_zones(
        d, threshold=0.04, min_zone_length=0.2, merge_gap=0.5, neighbours=1, peak_points=41
    )
    assert [(z["surface"], z["start"], z["end"]) for z in zones] == [
        ("roof", 2.0, 4.0),  # the 0.3 m gap is bridged
        ("floor", 8.0, 9.0),
    ]
    roof, floor = zones
    assert roof["length"] == pytest.approx(2.0)
    assert roof["n_points"] == 201 - 30  # flagged points, the gap excluded
    assert roof["peak"] == pytest.approx(-0.08)
    assert roof["peak_chainage"] == pytest.approx(3.7, abs=0.1)
    assert roof["peak_normal"] == pytest.approx(-0.08)
    assert floor["peak"] == pytest.approx(0.06) and floor["n_points"] == 101
    assert floor["mean"] == pytest.approx(0.06)
    # flags: the zones' points only; not the short run at 6 m, not the non-shell object
    s, n = d.chainage, len(d) // 2
    assert danger.dtype == np.uint8
    assert danger.sum() == 171 + 101
    assert danger[:n][(s[:n] >= 6.0) & (s[:n] <= 6.1)].sum() == 0
    assert danger[~d.shell].sum() == 0


def test_a_larger_merge_gap_and_a_shorter_minimum():
    d = _line_result()
    _, zones = danger_zones(d, threshold=0.04, min_zone_length=0.05, merge_gap=0.1, neighbours=1)
    assert [(z["surface"], z["start"], z["end"]) for z in zones] == [
        ("roof", 2.0, 2.99),
        ("roof", 3.3, 4.0),
        ("roof", 6.0, 6.1),
        ("floor", 8.0, 9.0),
    ]


def test_threshold_rules():
    d = _line_result()
    mean_abs = np.abs(d.deformation[d.shell]).mean()
    assert danger_threshold(d, threshold=0.04) == 0.04
    assert danger_threshold(d, threshold=123.0, rule="mean") == pytest.approx(mean_abs)
    # the mean rule gives ~0.009 m here: every non-zero shell point is flagged, the 0.1 m run
    # at 6 m is still too short to be a zone
    danger, zones = danger_zones(d, rule="mean", neighbours=1)
    assert mean_abs == pytest.approx(0.0087, abs=1e-4)
    assert danger.sum() == 171 + 101 and len(zones) == 2
    # above every value: nothing
    danger, zones = danger_zones(d, threshold=0.1, neighbours=1)
    assert danger.sum() == 0 and zones == []


def test_threshold_errors():
    d = _line_result()
    with pytest.raises(ConfigError, match="unknown danger rule 'median'"):
        danger_threshold(d, rule="median")
    with pytest.raises(ConfigError, match="danger threshold must be > 0 m, got 0"):
        danger_zones(d, threshold=0)
    with pytest.raises(ConfigError, match="danger threshold must be > 0 m, got nan"):
        danger_threshold(d, threshold=float("nan"))
    with pytest.raises(ConfigError, match="min_zone_length and merge_gap must be >= 0 m"):
        danger_zones(d, min_zone_length=-1.0)
    with pytest.raises(ConfigError, match="neighbours must be >= 1, got 0"):
        danger_zones(d, neighbours=0)
    no_shell = DeformationResult(**{**d.__dict__, "shell": np.zeros(len(d), bool)})
    with pytest.raises(ConfigError, match="rule 'mean' needs shell points"):
        danger_threshold(no_shell, rule="mean")
    danger, zones = danger_zones(no_shell, threshold=0.01)
    assert danger.sum() == 0 and zones == []


def test_a_lone_spike_is_flagged_per_point_but_not_after_smoothing():
    rng = np.random.default_rng(5)
    n = 20000
    xyz = np.c_[rng.uniform(0, 10, n), rng.uniform(-2.9, 2.9, n), np.full(n, 1.43)]
    v = rng.normal(0.0, 0.005, n)
    v[123] = -0.3
    d = DeformationResult(
        v, np.zeros(n), v, xyz[:, 0].copy(), np.zeros(n, np.uint8), np.ones(n, bool), xyz
    )
    danger, zones = danger_zones(d, threshold=0.05, min_zone_length=0.0, neighbours=1)
    assert danger.sum() == 1 and len(zones) == 1 and zones[0]["n_points"] == 1
    danger, zones = danger_zones(d, threshold=0.05, min_zone_length=0.0, neighbours=64)
    assert danger.sum() == 0 and zones == []


def test_local_median_known_answer():
    xyz = np.c_[np.arange(50.0), np.zeros(50), np.zeros(50)]
    v = np.ones(50)
    v[10] = 100.0
    v[30] = np.nan
    m = local_median(xyz, v, neighbours=5)
    np.testing.assert_allclose(m, 1.0)
    np.testing.assert_array_equal(local_median(xyz, v, neighbours=1), v)


def test_robust_peak_of_a_noisy_bump():
    rng = np.random.default_rng(6)
    n = 8000  # 400 points per m^2 on a 4 m x 5 m roof patch
    xyz = np.c_[rng.uniform(0, 4, n), rng.uniform(-2.5, 2.5, n), np.zeros(n)]
    taper = np.cos(np.clip(np.abs(xyz[:, 0] - 2.0) / 2.0, 0, 1) * np.pi / 2) ** 2
    taper *= np.cos(np.clip(np.abs(xyz[:, 1] - 0.5) / 1.0, 0, 1) * np.pi / 2) ** 2
    v = -0.03 * taper + rng.normal(0, 0.017, n)
    assert v.min() < -0.06  # the raw extreme is the noise's
    value, s, i = robust_peak(xyz, v, xyz[:, 0], points=200)
    # 200 points (a disc of ~0.4 m) average the crest: 0.86 of the amplitude on this bump
    assert value == pytest.approx(-0.03 * 0.86, abs=0.004)
    assert s == pytest.approx(2.0, abs=0.3)
    assert abs(xyz[i, 1] - 0.5) < 0.3


def test_judged_values_and_normal_component():
    d = _line_result()
    d2 = DeformationResult(
        **{
            **d.__dict__,
            "horizontal": np.full(len(d), 0.01),
            "surface": np.full(len(d), LEFT_WALL, np.uint8),
        }
    )
    np.testing.assert_allclose(judged_values(d2), d.vertical + 0.01)
    np.testing.assert_allclose(normal_component(d2), 0.01)
    np.testing.assert_allclose(normal_component(d), d.vertical)
    robust = DeformationResult(**{**d.__dict__, "method": "robust"})
    assert judged_values(robust) is robust.deformation
