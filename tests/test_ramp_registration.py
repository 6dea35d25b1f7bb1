"""A single drift that goes on up a ramp: the way round and the position along it.

Flat for a stretch, then up a ramp, straight in plan, smooth rock: turned end for end and
tipped by the grade, such a drift lies on itself (its sag curve is symmetric), so only the
tilt of levelled scans tells the two ways round apart. Along it, only the ramp's floor and
roof see a slide, and a translation alone trades that slide for any tilt left over.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from tunneldef.config import QualityConfig
from tunneldef.quality import direction_check, tilt_check
from tunneldef.registration.axial import neighbour_centroids, rigid_fit, translation_fit
from tunneldef.registration.verify import rigid_convergence
from tunneldef.registration.views import normals
from tunneldef.transforms import apply_transform


def _flat_then_ramp(rng: np.random.Generator, n: int, sigma: float = 0.005,
                    grade: float = 0.12) -> np.ndarray:
    """A 4 m x 3 m rectangular drift: flat for 40 m, then up a ramp (12 %) for 40 m."""
    s, u = rng.uniform(0.0, 80.0, n), rng.uniform(0.0, 1.0, n)
    side = rng.integers(0, 4, n)  # left wall, right wall, floor, roof
    floor = np.where(s < 40.0, 0.0, grade * (s - 40.0))
    y = np.where(side == 0, -2.0, np.where(side == 1, 2.0, -2.0 + 4.0 * u))
    z = floor + np.where(side < 2, 3.0 * u, np.where(side == 2, 0.0, 3.0))
    return np.c_[s, y, z] + rng.normal(0.0, sigma, (n, 3))


def test_rigid_fit_holds_the_slide_that_a_translation_trades_for_a_tilt() -> None:
    rng = np.random.default_rng(3)
    ref, cmp = _flat_then_ramp(rng, 150_000), _flat_then_ramp(rng, 40_000)
    tree = cKDTree(ref)
    # 3 cm along the drift and 0.01 degrees of pitch, as the earlier stages may leave it
    off = np.eye(4)
    off[:3, :3] = Rotation.from_rotvec([0.0, np.radians(0.01), 0.0]).as_matrix()
    c = cmp.mean(axis=0)
    off[:3, 3] = [0.03, 0.0, 0.0] + c - off[:3, :3] @ c
    moved = apply_transform(off, cmp)
    fit = rigid_fit(ref, normals(ref), moved, tree=tree,
                    plane_points=neighbour_centroids(ref, tree))
    err = np.abs(apply_transform(fit, moved) - cmp).max(axis=0)
    assert err[0] < 0.01 and err[1:].max() < 0.002, err  # every point, 5 mm noise
    # the translation alone takes the tilt's height change on the ramp for a slide
    t = translation_fit(ref, normals(ref), moved, tree=tree)
    assert abs(np.mean(moved[:, 0] + t[0] - cmp[:, 0])) > 0.02


def test_rigid_convergence_tells_a_held_slide_from_a_free_one() -> None:
    """Started 2 cm before and after the pose along the drift, the rigid fit ends in one
    place where the ramp holds the slide, and wanders on a plain drift (the compared points
    10 m inside the reference's ends either way, whose edges would draw every start alike)."""
    rng = np.random.default_rng(4)

    def spread(grade: float) -> tuple[float, np.ndarray]:
        ref, cmp = _flat_then_ramp(rng, 150_000, grade=grade), _flat_then_ramp(rng, 40_000,
                                                                                grade=grade)
        inner = cmp[(cmp[:, 0] > 10.0) & (cmp[:, 0] < 70.0)]
        return rigid_convergence(ref, inner, np.array([1.0, 0.0, 0.0]))

    held, ends = spread(0.12)
    assert held < 0.005 and np.abs(ends).max() < 0.01, (held, ends)  # and near the truth
    free, ends = spread(0.0)
    assert free > 2 * QualityConfig().max_axial_spread, free  # nothing along the drift
    assert ends.shape == (3, 3)


def test_rigid_fit_reports_no_surface() -> None:
    ref = _flat_then_ramp(np.random.default_rng(1), 2_000)
    fit = rigid_fit(ref, normals(ref), ref + [0.0, 0.0, 5.0])
    assert np.all(np.isnan(fit))


def test_direction_check() -> None:
    # one way round fitted clearly better: nothing to tell apart
    assert direction_check({}).passed
    # both fitted alike; the kept way tips the compared epoch 2.0 degrees, the other 8.8
    told = direction_check({"direction_tilt_gap_deg": 6.8, "direction_tilts_deg": [2.0, 8.8]})
    assert told.passed and "8.80" in told.note
    # both alike and both tipped alike (or no known vertical): refused
    left = direction_check({"direction_tilt_gap_deg": 0.3, "direction_tilts_deg": [2.0, 2.3]})
    assert not left.passed and left.figure == pytest.approx(0.3)


def test_tilt_check() -> None:
    qc = QualityConfig()
    assert tilt_check(float("nan"), qc).passed  # scans not levelled: nothing to hold
    assert tilt_check(2.0, qc).passed
    assert not tilt_check(6.8, qc).passed  # a ramp's grade: turned end for end


def test_detect_keeps_the_way_round_that_levelled_scans_allow() -> None:
    """End to end on the single-drift path: a 25 m flat stretch going on up a 12 % ramp,
    smooth rectangle, the compared epoch in its own frame (turned 140 degrees, tipped 1.5).
    Both ways round fit alike; the kept one tips the compared epoch by its frame's 1.5 degrees,
    the other by the grade's 6.8 less that. Before, the better overlap by a few parts in a
    thousand chose, and the wrong way round passed every check."""
    from tunneldef.pipeline import detect
    from tunneldef.synth import SectionSpec
    from tunneldef.synth.network import (
        EdgeSpec,
        NetworkPairSpec,
        NetworkSpec,
        Stretch,
        make_network_pair,
    )

    main = EdgeSpec("main", ((0.0, 0.0, 0.0), (25.0, 0.0, 0.0), (50.0, 0.0, 3.0)),
                    SectionSpec("rectangle", 4.5, 3.0), bend_radius=15.0)
    spec = NetworkPairSpec(NetworkSpec((main,), (), name="flat then ramp"),
                           ref_coverage=(Stretch(0, 0.0, 50.0),),
                           cmp_coverage=(Stretch(0, 3.0, 48.0),), density=100.0,
                           noise_sigma=0.008, drift=0.0, stray_distance=0.0, stray_clusters=0,
                           yaw_deg=140.0, tilt_deg=1.5, seed=2)
    pair = make_network_pair(spec)
    result = detect(pair.ref, pair.cmp)
    reg = result.registration
    kept, other = reg.info["direction_tilts_deg"]
    assert kept == pytest.approx(1.5, abs=0.3) and other > kept + 3.0
    x = pair.cmp.xyz[::20]
    err = np.linalg.norm(apply_transform(reg.transform, x)
                         - apply_transform(pair.truth.transform, x), axis=1)
    assert err.max() < 0.02, err.max()
    checks = {c.name: c for c in result.quality.checks}
    assert checks["registration.direction"].passed and checks["registration.tilt"].passed
    assert result.quality.verified
