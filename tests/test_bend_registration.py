"""A single drift that bends between two straights is placed along its axis by the bend.

Smooth rock, one section, no chamber: the surfaces alone leave the position along the drift
open (the section images follow the reference curve round the bend). The curves' shapes fix
it: slid along the reference, the compared curve no longer fits it by any rigid motion
(:func:`tunneldef.registration.axial.curve_shift`).
"""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef.curve import Centerline
from tunneldef.registration.axial import curve_shift
from tunneldef.synth import SectionSpec
from tunneldef.synth.network import EdgeSpec, NetworkPairSpec, NetworkSpec, Stretch


def _arc_polyline(straight: float, radius: float, turn_deg: float, after: float) -> np.ndarray:
    """A straight, an arc of ``radius`` turning ``turn_deg``, a straight (plan, z = 0)."""
    a = np.linspace(0.0, np.radians(turn_deg), 200)
    arc = np.c_[straight + radius * np.sin(a), radius * (1 - np.cos(a)), np.zeros_like(a)]
    end, head = arc[-1], np.array([np.cos(a[-1]), np.sin(a[-1]), 0.0])
    tail = end + np.outer(np.linspace(0.0, after, 50)[1:], head)
    return np.vstack([[0.0, 0.0, 0.0], arc, tail])


def _noisy(cl: Centerline, rng: np.random.Generator, sigma: float = 0.004) -> Centerline:
    s = np.arange(0.0, cl.length, 0.5)
    return Centerline.from_polyline(cl.point_at(s) + rng.normal(0.0, sigma, (len(s), 3)),
                                    step=0.025)


def _cut(cl: Centerline, a: float, b: float) -> Centerline:
    return Centerline.from_polyline(cl.point_at(np.arange(a, b, 0.05)), step=0.025)


def test_a_bend_between_straights_fixes_the_slide() -> None:
    rng = np.random.default_rng(4)
    ref = _noisy(Centerline.from_polyline(_arc_polyline(60.0, 40.0, 30.0, 20.0), step=0.025), rng)
    # the compared walker started 7 m later and stopped 3 m short; its curve is then slid
    # 3.3 m along the reference's first straight, as a featureless first pass leaves it
    cmp = _noisy(_cut(ref, 7.0, ref.length - 3.0), rng)
    slid = cmp.transformed(np.array([[1, 0, 0, 3.3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]))
    out = curve_shift(ref, slid, search=10.0)
    assert out.informative
    assert out.shift == pytest.approx(-3.3, abs=0.05)
    # honest: the figure claimed covers the error made, and fixes the position well enough
    assert 0.01 < out.uncertainty < 0.2
    assert out.rms < 0.01
    # the later survey goes on three times as far as the earlier one covers: its common part
    # still pairs (the overlap asked for is a share of the shorter curve)
    short = _noisy(_cut(ref, 45.0, 75.0), rng)
    slid = short.transformed(np.array([[1, 0, 0, 2.0], [0, 1, 0, 0], [0, 0, 1, 0],
                                       [0, 0, 0, 1.0]]))
    out = curve_shift(slid, ref, search=10.0)
    assert out.informative and out.uncertainty < 0.2


def test_a_constant_radius_bend_or_a_straight_fixes_nothing() -> None:
    rng = np.random.default_rng(5)
    a = np.linspace(0.0, np.radians(80.0), 400)
    circle = Centerline.from_polyline(np.c_[60 * np.sin(a), 60 * (1 - np.cos(a)), 0 * a],
                                      step=0.025)
    straight = Centerline.from_polyline(np.array([[0.0, 0, 0], [80.0, 0, 0]]), step=0.025)
    for cl in (circle, straight):
        ref = _noisy(cl, rng)
        cmp = _noisy(_cut(ref, 5.0, ref.length - 5.0), rng)
        out = curve_shift(ref, cmp, search=10.0)
        assert not out.informative and out.uncertainty == np.inf


def test_detect_places_a_featureless_bent_drift_by_its_bend() -> None:
    """End to end on the single-drift path: smooth rectangle, no chamber, no clutter; the
    epochs in different frames, covering different stretches. Before, refused as having no
    feature along the axis; now registered within millimetres of the truth, and the check
    that vouches for it is a rigid point-to-plane fit, which the bend's walls hold."""
    from tunneldef.pipeline import detect
    from tunneldef.synth.network import make_network_pair
    from tunneldef.transforms import apply_transform

    main = EdgeSpec("main", ((0.0, 0.0, 0.0), (45.0, 0.0, 0.0), (62.0, 11.0, 0.0)),
                    SectionSpec("rectangle", 4.5, 3.0), bend_radius=30.0)
    net = NetworkSpec((main,), (), name="bent drift")
    spec = NetworkPairSpec(net, ref_coverage=(Stretch(0, 0.0, 62.0),),
                           cmp_coverage=(Stretch(0, 5.0, 60.0),), density=150.0,
                           noise_sigma=0.008, drift=0.0, stray_distance=0.0, yaw_deg=140.0,
                           tilt_deg=1.5, seed=11)
    pair = make_network_pair(spec)
    result = detect(pair.ref, pair.cmp)
    reg = result.registration
    assert reg.info["axial_curve"]["informative"]
    x = pair.cmp.xyz[::20]
    err = np.linalg.norm(apply_transform(reg.transform, x)
                         - apply_transform(pair.truth.transform, x), axis=1)
    assert err.mean() < 0.01, err.mean()
    assert reg.axial_uncertainty < 0.5
    names = {c.name for c in result.quality.checks}
    assert "registration.translation_residual" in names
    assert not names & {"registration.axial_residual", "registration.axial_pose"}
    assert result.quality.verified


@pytest.mark.slow
def test_drift_correction_reads_survey_coordinates_as_local_ones() -> None:
    """The SLAM-drift correction in survey coordinates (5.6e6 m) corrects as in local ones.
    Its reference normals came from Open3D in place, whose raw moments lose a 0.4 m
    neighbourhood at that size: the normals came out at random, and the blocks' fits on them
    ended 37 mm (median) from the local correction on the 62 m drift of the test below."""
    from tunneldef.network import CenterlineNetwork, NetworkEdge
    from tunneldef.registration.network import correct_drift
    from tunneldef.synth.network import make_network_pair
    from tunneldef.transforms import apply_transform

    main = EdgeSpec("main", ((0.0, 0.0, 0.0), (30.0, 0.0, 0.0), (42.0, 8.0, 0.0)),
                    SectionSpec("rectangle", 4.5, 3.0), bend_radius=25.0)
    spec = NetworkPairSpec(NetworkSpec((main,), (), name="bent drift"), (),
                           ref_coverage=None, cmp_coverage=None, density=100.0,
                           noise_sigma=0.012, drift=0.05, stray_distance=0.0, seed=3)
    pair = make_network_pair(spec)
    moved = apply_transform(pair.truth.transform, pair.cmp.xyz)
    shift = np.eye(4)
    shift[:3, 3] = [4.5e5, 5.6e6, 310.0]
    out = []
    for t in (np.eye(4), shift):
        axis = pair.truth.centerlines[0].transformed(t)
        net = CenterlineNetwork((NetworkEdge(0, "drift", axis),))
        xyz, info = correct_drift(apply_transform(t, pair.ref.xyz), apply_transform(t, moved),
                                  net, block=(20.0, 10.0), change=0.01)
        assert info["used"]
        out.append((xyz - t[:3, 3], info))
    (local, li), (survey, si) = out
    assert si["coherent_before_m"] == pytest.approx(li["coherent_before_m"], abs=1e-4)
    assert si["block_m"] == li["block_m"]
    # the same correction up to the fits' own numerical path (ICP about another origin)
    assert np.percentile(np.linalg.norm(survey - local, axis=1), 95) < 0.002


@pytest.mark.slow
def test_detect_corrects_slam_drift_along_one_drift() -> None:
    """A handheld SLAM map of one drift bends slowly away from the other epoch's: one rigid
    transform leaves that in the data as false change (this pair, corrected rigidly only:
    4.2 % of the unchanged shell beyond 10 mm; a 166 m drift: 33 %). ``detect`` corrects it
    piecewise along the reference centreline, as along a network's edges, and the 30 mm sag
    3 m long and 2 m across survives it."""
    from tunneldef.pipeline import detect
    from tunneldef.synth import DeformationSpec
    from tunneldef.synth.network import BranchDeformation, make_network_pair

    main = EdgeSpec("main", ((0.0, 0.0, 0.0), (45.0, 0.0, 0.0), (62.0, 11.0, 0.0)),
                    SectionSpec("rectangle", 4.5, 3.0), bend_radius=30.0)
    sag = BranchDeformation(0, DeformationSpec("roof_sag", 25.0, 3.0, 2.0, 0.03))
    spec = NetworkPairSpec(NetworkSpec((main,), (), name="bent drift"), (sag,),
                           ref_coverage=(Stretch(0, 0.0, 62.0),),
                           cmp_coverage=(Stretch(0, 5.0, 60.0),), density=150.0,
                           noise_sigma=0.012, drift=0.05, stray_distance=0.0, yaw_deg=140.0,
                           tilt_deg=1.5, seed=1)
    pair = make_network_pair(spec)
    result = detect(pair.ref, pair.cmp)
    assert result.quality.verified
    drift = result.drift_correction
    assert drift["enabled"] and drift["used"]
    assert drift["coherent_after_m"] < drift["coherent_before_m"] - 0.0005
    assert result.summary()["drift_correction"]["used"]
    truth = pair.truth.cmp
    d = result.cloud.fields["deformation"]
    unchanged = d[truth.shell & (truth.displacement == 0)]
    unchanged = unchanged[np.isfinite(unchanged)]
    assert np.mean(np.abs(unchanged) > 0.01) < 0.01  # 0.05 % measured (20 m blocks: 0.3 %)
    core = truth.shell & (truth.displacement < -0.024)
    true, read = np.median(truth.displacement[core]), np.nanmedian(d[core])
    assert read == pytest.approx(true, rel=0.15)  # -27.5 against -26.8 mm measured
