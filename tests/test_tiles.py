"""Deformation in chainage tiles gives the untiled values, fields and danger zones alike."""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef import synth
from tunneldef.centerline import extract_centerline
from tunneldef.config import Config
from tunneldef.deformation import compute_deformation, danger_zones, section_statistics
from tunneldef.tiles import tile_margin, tiled_deformation

THRESHOLD = 0.02  # m: the pair's sag and bulge pass it


def small_pair(length: float = 100.0, density: float = 60.0, seed: int = 5):
    """A sparse synthetic pair with a chamber, equipment, a roof sag and a wall bulge."""
    spec = synth.PairSpec(
        tunnel=synth.TunnelSpec(length=length, density=density, chamber=True,
                                chamber_chainage=length * 0.4, equipment=True, roughness=0.02),
        deformations=(
            synth.DeformationSpec(kind="roof_sag", chainage=length * 0.5, length=4.0, width=2.0,
                                  amplitude=0.08),
            synth.DeformationSpec(kind="wall_bulge", chainage=length * 0.25, length=3.0,
                                  width=1.5, amplitude=0.06),
        ),
        cmp_shift=1.0, seed=seed,
    )
    return synth.make_pair(spec)


def assert_fields_equal(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    """Float fields within 1e-6 m (NaN where NaN), integer fields equal."""
    assert sorted(a) == sorted(b)
    for name, want in b.items():
        got = np.asarray(a[name])
        if want.dtype.kind == "f":
            x, y = got.astype(np.float64), want.astype(np.float64)
            np.testing.assert_array_equal(np.isnan(x), np.isnan(y), err_msg=name)
            ok = ~np.isnan(y)
            assert np.max(np.abs(x[ok] - y[ok]), initial=0.0) <= 1e-6, name
        else:
            np.testing.assert_array_equal(got, want, err_msg=name)


def assert_zones_equal(za: list[dict], zb: list[dict]) -> None:
    assert len(za) == len(zb)
    for a, b in zip(za, zb, strict=True):
        assert a.keys() == b.keys()
        for key, v in b.items():
            if isinstance(v, float):
                assert a[key] == pytest.approx(v, abs=1e-6, nan_ok=True), key
            else:
                assert a[key] == v, key


@pytest.fixture(scope="module")
def registered():
    """The pair with the compared epoch in the reference frame (the synthetic truth: the
    registration is not what is tested here) and the reference centreline."""
    pair = small_pair()
    cfg = Config()
    line = extract_centerline(pair.ref.xyz, slicing=cfg.slicing, settings=cfg.centerline)
    return pair.ref.xyz, pair.truth.cmp_xyz_in_ref, line.centerline


def _zones(d):
    return danger_zones(d, threshold=THRESHOLD)


@pytest.mark.parametrize(("method", "tile_length"),
                         [("robust", 25.0), ("knn", 25.0), ("robust", 500.0)])
def test_tiles_equal_untiled(registered, method: str, tile_length: float, monkeypatch) -> None:
    """Four tiles, and one tile holding the whole pair; with a registration uncertainty,
    which widens the LoD95 and so changes which support each point is measured at. The
    robust tiles' measuring pass resumes from their spreads pass's cylinders."""
    from tunneldef.deformation.local_surface import CylinderPass

    loaded = []
    load = CylinderPass.load
    monkeypatch.setattr(CylinderPass, "load", classmethod(
        lambda cls, path: loaded.append(path) or load(path)))
    ref, cmp, line = registered
    settings = Config().replace(deformation={"method": method}).deformation
    sigma = 0.004
    whole = compute_deformation(ref, cmp, line, settings=settings, registration_sigma=sigma)
    tiled = tiled_deformation(ref, cmp, line, settings=settings, tile_length=tile_length,
                              registration_sigma=sigma)
    assert len(loaded) == (4 if (method, tile_length) == ("robust", 25.0) else 0)
    assert_fields_equal(tiled.fields(), whole.fields())
    if method == "robust":  # what the quality checks read besides the fields
        np.testing.assert_array_equal(tiled.spread_ratio, whole.spread_ratio)
        np.testing.assert_array_equal(tiled.two_surfaces, whole.two_surfaces)
        assert tiled.typical_spread == pytest.approx(whole.typical_spread, rel=1e-9)
    danger_t, zones_t = _zones(tiled)
    danger_w, zones_w = _zones(whole)
    if method == "robust":
        assert len(zones_w) >= 2, "the sag and the bulge should be danger zones"
    np.testing.assert_array_equal(danger_t, danger_w)
    assert_zones_equal(zones_t, zones_w)
    assert len(section_statistics(tiled)) == len(section_statistics(whole))


def test_margin_covers_the_estimator_reach() -> None:
    cfg = Config().deformation
    assert tile_margin(cfg) > 1.0 + cfg.normal_radius + 2 * cfg.cylinder_radius
    # the stand-off rays of a point the classifier left out reach twice standoff_reach
    # behind its core, wherever the surfaces' chain ends
    for reach in (1.5, 4.0):
        far = Config().replace(deformation={"standoff_reach": reach}).deformation
        assert tile_margin(far) >= 1.2 * (2 * reach + far.normal_radius + 1.0)
    assert tile_margin(Config().replace(deformation={"method": "knn"}).deformation) >= (
        3 * cfg.max_distance)


def test_tiles_take_the_callers_chainage_and_labels(registered) -> None:
    """The chainage and surface labels a caller hands over give the fields the tiles draw
    themselves; merged float fields are float32 (as written); half a projection is refused."""
    from tunneldef.deformation.sections import surface_labels

    ref, cmp, line = registered
    settings = Config().replace(deformation={"method": "knn"}).deformation
    p = line.project(cmp)
    surface = surface_labels(p.chainage, p.lateral, p.vertical, step=settings.section_step)
    own = tiled_deformation(ref, cmp, line, settings=settings, tile_length=25.0)
    given = tiled_deformation(ref, cmp, line, settings=settings, tile_length=25.0,
                              chainage=p.chainage, surface=surface)
    assert_fields_equal(given.fields(), own.fields())
    assert own.deformation.dtype == np.float32 and own.chainage.dtype == np.float64
    with pytest.raises(ValueError, match="both"):
        tiled_deformation(ref, cmp, line, settings=settings, tile_length=25.0,
                          chainage=p.chainage)


def test_detect_can_map_the_compared_epoch_in_place(tmp_path) -> None:
    """``overwrite_compared``: the compared cloud itself comes back in the reference frame,
    with the coordinates and fields of the copying run."""
    from tunneldef.pipeline import detect

    pair = small_pair(length=40.0, density=80.0, seed=2)
    tiles = {"tile_length": 15.0, "workdir": tmp_path}
    copied = detect(pair.ref, pair.cmp.copy(), tiles=tiles)
    cmp = pair.cmp.copy()
    before = cmp.xyz.copy()
    in_place = detect(pair.ref, cmp, tiles=tiles, overwrite_compared=True)
    assert in_place.cloud is cmp
    assert not np.allclose(cmp.xyz, before)  # moved by the synthetic pair's rigid motion
    np.testing.assert_allclose(cmp.xyz, copied.cloud.xyz, rtol=0, atol=1e-9)
    assert_fields_equal(in_place.cloud.fields, copied.cloud.fields)


@pytest.mark.parametrize("threads", [1, 2])
def test_thread_map_keeps_order_reports_progress_and_raises(threads: int) -> None:
    """Results in the order of the arguments whatever order the threads finish in; progress
    from 0 to 1 in the calling thread; a task's own exception reaches the caller as itself."""
    import threading
    import time

    from tunneldef.engine import thread_map

    seen: list[tuple[str, float, str]] = []

    def progress(stage: str, fraction: float) -> None:
        seen.append((stage, fraction, threading.current_thread().name))

    def slow_first(i: int, x: float) -> float:
        time.sleep(0.02 if i == 0 else 0.0)  # the first finishes last in two threads
        return i * x

    out = thread_map(slow_first, [(i, 1.5) for i in range(7)], threads=threads,
                     stage="pieces", progress=progress)
    assert out == [i * 1.5 for i in range(7)]
    fractions = [f for _, f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and len(fractions) == 7
    assert {s for s, _, _ in seen} == {"pieces"}
    assert {t for _, _, t in seen} == {threading.current_thread().name}

    def fails(i: int) -> int:
        if i == 3:
            raise ValueError("piece 3 has no floor")
        return i

    with pytest.raises(ValueError, match="piece 3 has no floor"):
        thread_map(fails, [(i,) for i in range(6)], threads=threads)
