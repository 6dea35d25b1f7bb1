"""Surface labels and per-section statistics (paper §3.3.2, Table 4)."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from tunneldef.config import DeformationConfig
from tunneldef.deformation import DeformationResult
from tunneldef.deformation import compute_deformation as _compute_deformation
from tunneldef.deformation.sections import (
    FLOOR,
    LEFT_WALL,
    RIGHT_WALL,
    ROOF,
    SURFACE_NAMES,
    section_statistics,
    surface_labels,
    write_sections_csv,
)
from tunneldef.errors import ConfigError, InvalidCloudError
from tunneldef.synth import DeformationSpec, PairSpec, TunnelSpec, make_pair

# these tests check the paper's method (§3.3): KNN centroid, unless a test says otherwise
KNN = DeformationConfig(method="knn")


def compute_deformation(*args, **kwargs):
    """The stage with the paper's KNN centroid (these tests check the paper's Table 4)."""
    return _compute_deformation(*args, settings=KNN, **kwargs)


def _rectangle(rng, n, *, width=5.8, height=2.86, length=10.0, centre=(0.0, 0.0)):
    """Points on a rectangular section outline swept along chainage 0..length, with labels."""
    perim = 2 * (width + height)
    t = rng.uniform(0, perim, n)
    lat = np.empty(n)
    ver = np.empty(n)
    lab = np.empty(n, np.uint8)
    w, h = width / 2, height / 2
    a = t < width
    lat[a], ver[a], lab[a] = w - t[a], h, ROOF
    b = (t >= width) & (t < width + height)
    lat[b], ver[b], lab[b] = -w, h - (t[b] - width), RIGHT_WALL
    c = (t >= width + height) & (t < 2 * width + height)
    lat[c], ver[c], lab[c] = -w + (t[c] - width - height), -h, FLOOR
    e = t >= 2 * width + height
    lat[e], ver[e], lab[e] = w, -h + (t[e] - 2 * width - height), LEFT_WALL
    return rng.uniform(0, length, n), lat - centre[0], ver - centre[1], lab


def _result(
    chainage, deformation, *, surface=None, shell=None, horizontal=None, vertical=None, length=None
) -> DeformationResult:
    n = len(chainage)
    z = np.zeros(n)
    return DeformationResult(
        deformation=np.asarray(deformation, float),
        horizontal=z if horizontal is None else np.asarray(horizontal, float),
        vertical=z if vertical is None else np.asarray(vertical, float),
        chainage=np.asarray(chainage, float),
        surface=np.zeros(n, np.uint8) if surface is None else np.asarray(surface, np.uint8),
        shell=np.ones(n, bool) if shell is None else np.asarray(shell, bool),
        xyz=np.c_[chainage, z, z],
        centerline_length=length,
    )


# --- surface labels ---------------------------------------------------------------------------


@pytest.mark.parametrize("centre", [(0.0, 0.0), (0.4, -0.2)])
def test_surface_labels_on_a_rectangle(centre):
    rng = np.random.default_rng(0)
    s, lat, ver, truth = _rectangle(rng, 20000, centre=centre)
    lab = surface_labels(s, lat, ver, step=1.0)
    # every point is labelled by the diagonal through the section's corners; only points
    # within ~5 % of a corner may differ
    assert np.mean(lab == truth) > 0.99
    for code in range(4):
        assert np.mean(lab[truth == code] == code) > 0.98, SURFACE_NAMES[code]


def test_surface_labels_edge_cases():
    assert surface_labels(np.empty(0), np.empty(0), np.empty(0)).shape == (0,)
    with pytest.raises(ConfigError, match="section step must be > 0 m"):
        surface_labels(np.zeros(3), np.zeros(3), np.zeros(3), step=0.0)


# --- statistics -------------------------------------------------------------------------------


def test_section_statistics_known_numbers():
    # points every 1 cm along chainage 0..3; section k holds the points within 0.1 m of k
    s = np.round(np.arange(0.0, 3.0001, 0.01), 6)
    sec = np.round(s)  # nearest section
    d = np.where(np.abs(s - sec) <= 0.1 + 1e-9, -0.01 * (sec + 1), 9.0)  # 9.0 between sections
    surface = np.where(np.arange(s.size) % 2 == 0, ROOF, LEFT_WALL)
    vertical = np.where(surface == ROOF, d, 0.0)
    horizontal = np.where(surface == LEFT_WALL, d, 0.0)
    shell = np.ones(s.size, bool)
    shell[np.isclose(s, 1.0)] = False  # one non-shell point at the middle section
    r = _result(
        s, d, surface=surface, shell=shell, horizontal=horizontal, vertical=vertical, length=3.0
    )
    rows = section_statistics(r, step=1.0, thickness=0.2)
    assert [row["chainage"] for row in rows] == [0.0, 1.0, 2.0, 3.0]
    n = [row["n_points"] for row in rows]
    assert n == [11, 21, 21, 11]  # ends hold one side only
    assert [row["n_shell"] for row in rows] == [11, 20, 21, 11]
    for k, row in enumerate(rows):
        assert row["mean"] == pytest.approx(-0.01 * (k + 1))
        assert row["std"] == pytest.approx(0.0, abs=1e-12)
        assert row["mean_abs"] == pytest.approx(0.01 * (k + 1))
        assert row["min"] == row["max"] == pytest.approx(-0.01 * (k + 1))
        assert row["roof_n"] + row["left_wall_n"] == row["n_shell"]
        assert row["floor_n"] == row["right_wall_n"] == 0
        assert math.isnan(row["floor_mean"])
        assert row["roof_mean_vertical"] == pytest.approx(-0.01 * (k + 1))
        assert row["left_wall_mean_horizontal"] == pytest.approx(-0.01 * (k + 1))
        # half the points are roof (vertical), half wall (horizontal)
        frac_roof = row["roof_n"] / row["n_shell"]
        assert row["mean_vertical"] == pytest.approx(-0.01 * (k + 1) * frac_roof)


def test_section_statistics_spread_and_range():
    rng = np.random.default_rng(3)
    s = rng.uniform(-2.0, 12.0, 50000)
    d = rng.normal(0.004, 0.02, s.size)
    rows = section_statistics(_result(s, d, length=10.0), step=2.0, thickness=0.5)
    # clipped to the centreline [0, 10]
    assert [row["chainage"] for row in rows] == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
    for row in rows:
        assert row["n_points"] == pytest.approx(50000 * 0.5 / 14, rel=0.15)
        assert row["mean"] == pytest.approx(0.004, abs=0.003)
        assert row["std"] == pytest.approx(0.02, rel=0.1)
    rows = section_statistics(_result(s, d, length=10.0), step=2.0, thickness=0.5, start=-2.0)
    assert rows[0]["chainage"] == -2.0


def test_section_statistics_errors():
    r = _result(np.zeros(3), np.zeros(3))
    with pytest.raises(ConfigError, match="section step must be > 0 m"):
        section_statistics(r, step=0.0)
    with pytest.raises(ConfigError, match="section thickness must be > 0 m"):
        section_statistics(r, thickness=-1.0)
    with pytest.raises(InvalidCloudError, match="no points to compute section statistics"):
        section_statistics(_result(np.empty(0), np.empty(0)))


def test_write_sections_csv_round_trip(tmp_path):
    rows = [
        {"chainage": 1.0, "n_points": 5, "mean": -0.0123456789},
        {"chainage": 2.0, "n_points": 0, "mean": math.nan, "roof_n": 3},
    ]
    path = tmp_path / "sections.csv"
    write_sections_csv(rows, path)
    with path.open(newline="") as f:
        back = list(csv.DictReader(f))
    assert list(back[0]) == ["chainage", "n_points", "mean", "roof_n"]
    assert float(back[0]["mean"]) == pytest.approx(-0.0123457, rel=1e-5)
    assert back[0]["roof_n"] == "" and back[1]["roof_n"] == "3"
    assert math.isnan(float(back[1]["mean"]))
    assert [p.name for p in tmp_path.iterdir()] == ["sections.csv"]  # no temp file left


def test_write_sections_csv_leaves_nothing_on_failure(tmp_path):
    class Boom(float):
        def __format__(self, spec):
            raise RuntimeError("boom")

    path = tmp_path / "sections.csv"
    with pytest.raises(RuntimeError, match="boom"):
        write_sections_csv([{"chainage": Boom(1.0)}], path)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError):
        write_sections_csv([{"chainage": 1.0}], tmp_path / "missing" / "s.csv")


# --- on a synthetic pair: a roof sag shows up in its sections ---------------------------------


def test_sections_of_a_roof_sag():
    pair = make_pair(
        PairSpec(
            tunnel=TunnelSpec(length=12.0),
            deformations=(DeformationSpec(kind="roof_sag", chainage=6.0, amplitude=0.03),),
            cmp_shift=0.0,
            cmp_length=12.0,
            seed=4,
        )
    )
    t = pair.truth
    d = compute_deformation(pair.ref.xyz, t.cmp_xyz_in_ref, t.centerline, shell=t.label == 0)
    rows = {row["chainage"]: row for row in section_statistics(d, step=1.0, thickness=0.2)}
    assert sorted(rows) == [float(k) for k in range(13)]
    sag = rows[6.0]
    sel = (np.abs(t.chainage - 6.0) <= 0.1) & (t.label == 0) & (d.surface == 0)
    truth = t.displacement[sel].mean()  # ~ -5 mm: 2 m wide patch, cos^2 across, 5.8 m roof
    assert sag["roof_n"] == sel.sum()
    assert sag["roof_mean"] == pytest.approx(truth, abs=0.002)
    assert 0.6 < sag["roof_mean_vertical"] / truth < 1.1  # the KNN centroid attenuates ~20 %
    assert abs(sag["floor_mean_vertical"]) < 0.003
    assert sag["min"] < -0.05
    for k in (1.0, 2.0, 10.0, 11.0):
        assert abs(rows[k]["roof_mean_vertical"]) < 0.004
        assert abs(rows[k]["mean_horizontal"]) < 0.004
        assert 0.015 < rows[k]["mean_abs"] < 0.035  # the noise level (paper Table 4: 27 mm)


def test_surface_labels_are_the_same_a_chunk_at_a_time(monkeypatch) -> None:
    """Labels drawn a chunk at a time (large surveys) equal those drawn at once, bins with
    too few points taking the whole cloud's extents."""
    from tunneldef.deformation import sections

    rng = np.random.default_rng(4)
    n = 20_000
    s = np.concatenate([rng.uniform(0.0, 40.0, n - 10), [55.5] * 10])  # a sparse last bin
    lat, ver = rng.normal(0.0, 2.0, n), rng.normal(0.0, 1.5, n)
    whole = sections.surface_labels(s, lat, ver, step=1.0)
    monkeypatch.setattr(sections, "_CHUNK", 777)
    monkeypatch.setattr(sections, "_GROUP", 900)  # the bins' extents a few bins at a time
    np.testing.assert_array_equal(sections.surface_labels(s, lat, ver, step=1.0), whole)
    assert set(np.unique(whole)) == {0, 1, 2, 3}
    # the rule written out point by point: each side's extent is the 95th percentile of the
    # bin's offsets to that side (the whole cloud's below 30 points)
    def extent(v: np.ndarray, whole_v: np.ndarray) -> float:
        return float(np.quantile(v, 0.95)) if v.size >= 30 else float(np.quantile(whole_v, 0.95))

    b = np.floor(s).astype(int)
    expected = np.empty(n, dtype=np.uint8)
    for k in np.unique(b):
        m = b == k
        la, ve = lat[m], ver[m]
        e = [extent(la[la > 0], lat[lat > 0]), extent(-la[la < 0], -lat[lat < 0]),
             extent(ve[ve > 0], ver[ver > 0]), extent(-ve[ve < 0], -ver[ver < 0])]
        nl = np.where(la >= 0, la / e[0], -la / e[1])
        nv = np.where(ve >= 0, ve / e[2], -ve / e[3])
        expected[m] = np.where(nv >= nl, np.where(ve >= 0, ROOF, FLOOR),
                               np.where(la >= 0, LEFT_WALL, RIGHT_WALL))
    np.testing.assert_array_equal(whole, expected)


@pytest.mark.parametrize(("step", "thickness"), [(1.0, 0.2), (0.5, 0.5), (0.3, 0.2999)])
def test_section_statistics_hold_every_point_within_half_the_thickness(
    step: float, thickness: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each section holds exactly the points within half its thickness of its chainage (the
    points between sections are never sorted, a chunk at a time)."""
    from tunneldef.deformation import sections

    rng = np.random.default_rng(6)
    n = 30_000
    s = rng.uniform(-0.4, 25.3, n)
    s[:50] = np.round(s[:50] / step) * step + thickness / 2  # on a section's edge
    d = DeformationResult(
        deformation=rng.normal(0.0, 0.01, n), horizontal=rng.normal(0.0, 0.01, n),
        vertical=rng.normal(0.0, 0.01, n), chainage=s, surface=rng.integers(0, 4, n).astype(
            np.uint8), shell=rng.random(n) < 0.9, xyz=np.zeros((n, 3)), method="robust",
        centerline_length=25.0,
    )
    monkeypatch.setattr(sections, "_CHUNK", 1_234)
    rows = section_statistics(d, step=step, thickness=thickness)
    centres = np.arange(0, math.floor(25.0 / step + 1e-9) + 1) * step
    assert [r["chainage"] for r in rows] == pytest.approx(list(centres))
    for row, c in zip(rows, centres, strict=True):
        inside = (s >= c - thickness / 2) & (s <= c + thickness / 2)
        use = inside & d.shell
        assert row["n_points"] == int(inside.sum())
        assert row["n_valid"] == int(use.sum())
        assert row["mean"] == pytest.approx(float(d.deformation[use].mean()), rel=1e-12)


def test_surface_labels_with_a_stray_chainage_far_off() -> None:
    """A point projected kilometres beyond the rest gets its own bin (the whole cloud's
    extents), the others keep their labels."""
    from tunneldef.deformation import sections

    rng = np.random.default_rng(5)
    n = 5_000
    s, lat, ver = rng.uniform(0.0, 20.0, n), rng.normal(0.0, 2.0, n), rng.normal(0.0, 1.5, n)
    far = sections.surface_labels(np.r_[s, 5.0e7], np.r_[lat, 1.0], np.r_[ver, 0.0], step=0.1)
    np.testing.assert_array_equal(far[:n], sections.surface_labels(s, lat, ver, step=0.1))
    assert far[n] == sections.LEFT_WALL


@pytest.mark.parametrize("n", [1, 2, 7, 10_001])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_shell_moments_are_numpys_figures_without_a_float64_copy(n, dtype, monkeypatch):
    """The summary's statistics, summed a chunk at a time (chunks of 1,000 here): NumPy's
    mean, std, min, max and linear percentiles of the float64 values."""
    from tunneldef import pipeline

    monkeypatch.setattr(pipeline, "_MOMENT_CHUNK", 1000)
    rng = np.random.default_rng(n)
    d = rng.normal(0.001, 0.01, 2 * n + 1).astype(dtype)
    d[rng.random(d.size) < 0.1] = np.nan
    keep = rng.random(d.size) < 0.5
    d[0], keep[0] = 0.002, True  # at least one value
    v = d[keep & np.isfinite(d)]
    n = v.size
    want = v.astype(np.float64)
    got = pipeline.shell_moments(d, keep)
    assert got["count"] == n
    assert got["mean"] == pytest.approx(want.mean(), rel=1e-12, abs=1e-18)
    assert got["std"] == pytest.approx(want.std(), rel=1e-12, abs=1e-18)
    assert (got["min"], got["max"]) == (want.min(), want.max())
    a = np.abs(want)
    assert got["mean_abs"] == pytest.approx(a.mean(), rel=1e-12)
    p50, p95 = np.percentile(a, [50, 95])
    assert (got["p50_abs"], got["p95_abs"]) == (p50, p95)
    assert pipeline.shell_moments(d, np.zeros(d.size, bool)) == {"count": 0}
    assert pipeline.shell_moments(np.empty(0, dtype)) == {"count": 0}
