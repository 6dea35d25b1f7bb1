"""Known-answer tests of the synthetic tunnel generator."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tunneldef.errors import ConfigError
from tunneldef.synth import (
    LABEL_DYNAMIC,
    LABEL_EQUIPMENT,
    LABEL_OUTLIER,
    LABEL_SHELL,
    SURFACE_FLOOR,
    SURFACE_LEFT,
    SURFACE_ROOF,
    DeformationSpec,
    PairSpec,
    SectionSpec,
    TunnelSpec,
    make_pair,
    make_tunnel,
    section_outline,
    write_pair,
)

W2, H2 = 5.8 / 2, 2.86 / 2
CLEAN = {"noise_sigma": 0.0, "outlier_fraction": 0.0}


def _away_from_corners(lat: np.ndarray, ver: np.ndarray, margin: float = 0.1) -> np.ndarray:
    return (np.abs(np.abs(lat) - W2) > margin) | (np.abs(np.abs(ver) - H2) > margin)


@pytest.fixture(scope="module")
def busy_pair():
    tunnel = TunnelSpec(
        length=20.0,
        density=150.0,
        equipment=True,
        conveyor=True,
        chamber=True,
        holes=4,
        uneven_density=0.3,
    )
    return make_pair(
        PairSpec(tunnel=tunnel, deformations=(DeformationSpec(chainage=10.0),), seed=3)
    )


def test_transform_is_exact_rigid_motion(busy_pair):
    t = busy_pair.truth
    m = t.transform
    mapped = busy_pair.cmp.xyz @ m[:3, :3].T + m[:3, 3]
    np.testing.assert_allclose(mapped, t.cmp_xyz_in_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(m[3], [0, 0, 0, 1])
    # the motion is large: the raw compared cloud is far from the reference frame
    assert np.linalg.norm(busy_pair.cmp.xyz.mean(0) - t.cmp_xyz_in_ref.mean(0)) > 100.0


def test_tilt_and_yaw_as_specified():
    pair = make_pair(tunnel=TunnelSpec(length=10.0, density=50.0), yaw_deg=30.0, tilt_deg=3.0)
    rot = pair.truth.transform[:3, :3].T  # design -> compared frame
    angle = np.degrees(np.arccos((np.trace(rot) - 1) / 2))
    assert 30.0 - 3.0 - 1e-9 <= angle <= 30.0 + 3.0 + 1e-9
    z_new = rot @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(z_new[2])) == pytest.approx(3.0, abs=1e-9)


def test_reference_shell_lies_on_design_section_within_noise():
    sigma = 0.015
    cloud, truth = make_tunnel(TunnelSpec(density=150.0, noise_sigma=sigma, outlier_fraction=0))
    pr = truth.centerline.project(cloud.xyz)
    keep = pr.inside & _away_from_corners(pr.lateral, pr.vertical)
    res = truth.outline.signed_distance(pr.lateral, pr.vertical)[keep]
    assert abs(res.mean()) < 0.1 * sigma
    assert res.std() == pytest.approx(sigma, rel=0.2)
    assert np.all(truth.label == LABEL_SHELL)


@pytest.mark.parametrize("kind", ["rectangle", "arch", "trapezoid"])
def test_noise_free_points_sit_on_outline(kind):
    defs = (
        DeformationSpec("roof_sag", chainage=3.0, length=3.0, width=1.5, amplitude=0.06),
        DeformationSpec("floor_heave", chainage=6.0, length=3.0, width=1.5, amplitude=0.04),
    )
    spec = TunnelSpec(length=8.0, density=120.0, section=SectionSpec(kind=kind), **CLEAN)
    cloud, truth = make_tunnel(spec, deformations=defs)
    pr = truth.centerline.project(cloud.xyz)
    offset = truth.outline.signed_distance(pr.lateral, pr.vertical)
    np.testing.assert_allclose(offset, truth.displacement, atol=1e-9)
    assert truth.displacement.min() == pytest.approx(-0.06, abs=1e-3)
    sag = truth.displacement < -1e-3
    assert np.all(truth.surface[sag] != 255)
    roof_z = cloud.xyz[sag & (truth.surface == SURFACE_ROOF), 2]
    floor_z = cloud.xyz[sag & (truth.surface == SURFACE_FLOOR), 2]
    assert roof_z.size > 20 and floor_z.size > 20
    assert roof_z.max() < spec.section.height / 2 and floor_z.min() > -spec.section.height / 2


def test_deformed_points_sit_where_truth_says():
    defs = (
        DeformationSpec("roof_sag", chainage=8.0, length=4.0, width=2.0, amplitude=0.05),
        DeformationSpec("wall_bulge", chainage=14.0, side="left", amplitude=0.04),
        DeformationSpec("floor_heave", chainage=20.0, amplitude=-0.03),
    )
    cloud, truth = make_tunnel(TunnelSpec(density=300.0, **CLEAN), deformations=defs)
    pr = truth.centerline.project(cloud.xyz)
    offset = truth.outline.signed_distance(pr.lateral, pr.vertical)
    np.testing.assert_allclose(offset, truth.displacement, atol=1e-9)
    moved = truth.displacement != 0
    # each patch reaches its amplitude at the centre (within the sampling of the taper)
    for d in defs:
        near = moved & (np.abs(truth.chainage - d.chainage) < d.length / 2)
        peak = truth.displacement[near][np.argmax(np.abs(truth.displacement[near]))]
        assert peak == pytest.approx(-d.amplitude, abs=2e-3 * abs(d.amplitude))
        assert np.abs(truth.displacement[near]).max() <= abs(d.amplitude) + 1e-12
        assert d.taper(np.zeros(1), np.zeros(1))[0] == pytest.approx(1.0, abs=1e-12)
    # nothing moves outside the patches
    far = np.all([np.abs(truth.chainage - d.chainage) >= d.length / 2 for d in defs], axis=0)
    assert np.all(truth.displacement[far] == 0)


def test_sign_conventions():
    defs = (
        DeformationSpec("roof_sag", chainage=5.0, amplitude=0.05),
        DeformationSpec("wall_bulge", chainage=12.0, side="left", amplitude=0.05),
        DeformationSpec("floor_heave", chainage=20.0, amplitude=0.05),
    )
    cloud, truth = make_tunnel(TunnelSpec(density=100.0, **CLEAN), deformations=defs)
    z, y = cloud.xyz[:, 2], cloud.xyz[:, 1]
    moved = truth.displacement < -1e-3
    roof, wall, floor = (
        moved & (truth.surface == k) for k in (SURFACE_ROOF, SURFACE_LEFT, SURFACE_FLOOR)
    )
    assert roof.sum() > 50 and wall.sum() > 50 and floor.sum() > 50
    assert np.all(z[roof] < H2)  # the roof comes down
    assert np.all(y[wall] < W2)  # the left wall (+y on a straight tunnel along +x) comes in
    assert np.all(z[floor] > -H2)  # the floor comes up
    np.testing.assert_allclose(z[roof], H2 + truth.displacement[roof], atol=1e-12)


def test_chainage_truth_matches_projection():
    cloud, truth = make_tunnel(TunnelSpec(density=100.0, outlier_fraction=0.01))
    pr = truth.centerline.project(cloud.xyz)
    np.testing.assert_allclose(pr.chainage, truth.chainage, atol=1e-9)  # straight: exact
    cloud, truth = make_tunnel(TunnelSpec(density=60.0, radius=40.0, grade=0.04))
    pr = truth.centerline.project(cloud.xyz)
    # the centreline's nearest-sample projection is first-order accurate on a curve
    err = np.abs(pr.chainage - truth.chainage)[pr.inside]
    assert err.max() < 3e-3


@pytest.mark.parametrize("radius", [40.0, -60.0])
def test_curved_walls_at_right_distance_from_arc(radius):
    cloud, truth = make_tunnel(TunnelSpec(length=25.0, density=80.0, radius=radius, **CLEAN))
    centre = np.array([0.0, radius])  # the axis starts at the origin heading +x
    dist = np.hypot(cloud.xyz[:, 0] - centre[0], cloud.xyz[:, 1] - centre[1])
    left = truth.surface == SURFACE_LEFT  # the left side is the inner side of a left turn
    r = abs(radius)
    sign = np.sign(radius)
    np.testing.assert_allclose(dist[left], r - sign * W2, atol=1e-9)
    np.testing.assert_allclose(dist[truth.surface == 2], r + sign * W2, atol=1e-9)
    np.testing.assert_allclose(truth.centerline.length, 25.0, atol=1e-9)
    ends = truth.centerline.points[[0, -1]]
    np.testing.assert_allclose(np.hypot(*(ends[:, :2] - centre).T), r, atol=1e-9)


def test_cmp_stretch_is_shifted():
    pair = make_pair(
        tunnel=TunnelSpec(length=20.0, density=60.0, outlier_fraction=0),
        cmp_shift=3.0,
        cmp_length=12.0,
        seed=5,
    )
    t = pair.truth
    assert t.ref_chainage.min() == pytest.approx(0.0, abs=0.05)
    assert t.ref_chainage.max() == pytest.approx(20.0, abs=0.05)
    assert t.chainage.min() == pytest.approx(3.0, abs=0.05)
    assert t.chainage.max() == pytest.approx(15.0, abs=0.05)
    assert t.cmp_range == (3.0, 15.0)
    pr = t.centerline.project(t.cmp_xyz_in_ref)
    np.testing.assert_allclose(pr.chainage, t.chainage, atol=1e-9)


def test_labels_coal_in_both_epochs_and_it_changes(busy_pair):
    t = busy_pair.truth
    for label in (t.label, t.ref_label):
        counts = np.bincount(label, minlength=4)
        assert all(
            counts[k] > 0 for k in (LABEL_SHELL, LABEL_EQUIPMENT, LABEL_DYNAMIC, LABEL_OUTLIER)
        )
    lo, hi = t.cmp_range[0], t.ref_range[1]
    bins = np.arange(lo, hi + 1e-9, 0.5)
    ref_coal = np.histogram(t.ref_chainage[t.ref_label == LABEL_DYNAMIC], bins)[0] > 0
    cmp_coal = np.histogram(t.chainage[t.label == LABEL_DYNAMIC], bins)[0] > 0
    assert (ref_coal != cmp_coal).sum() >= 3
    # equipment is static: the same pipes in both epochs
    assert t.displacement[t.label != LABEL_SHELL].max() == 0.0


def test_coal_unchanged_when_asked():
    tunnel = TunnelSpec(length=15.0, density=60.0, conveyor=True)
    pair = make_pair(tunnel=tunnel, coal_change=False, cmp_shift=0.0, seed=2)
    t = pair.truth
    bins = np.arange(0.0, 15.0 + 1e-9, 0.5)
    ref_coal = np.histogram(t.ref_chainage[t.ref_label == LABEL_DYNAMIC], bins)[0] > 0
    cmp_coal = np.histogram(t.chainage[t.label == LABEL_DYNAMIC], bins)[0] > 0
    assert (ref_coal != cmp_coal).sum() <= 2


def test_point_counts_follow_density_and_area():
    perimeter = 2 * (5.8 + 2.86)
    for density in (50.0, 100.0):
        cloud, _ = make_tunnel(TunnelSpec(length=20.0, density=density, **CLEAN))
        assert len(cloud) == pytest.approx(density * perimeter * 20.0, rel=0.01)
    curved, _ = make_tunnel(TunnelSpec(length=20.0, density=100.0, radius=30.0, **CLEAN))
    assert len(curved) == pytest.approx(100.0 * perimeter * 20.0, rel=0.02)
    outline = section_outline(SectionSpec(kind="arch"))
    arch, _ = make_tunnel(
        TunnelSpec(length=20.0, density=100.0, section=SectionSpec(kind="arch"), **CLEAN)
    )
    assert len(arch) == pytest.approx(100.0 * outline.perimeter * 20.0, rel=0.01)


def test_uneven_density_and_holes():
    base = {"length": 40.0, "density": 60.0, **CLEAN}
    flat, tf = make_tunnel(TunnelSpec(**base))
    uneven, tu = make_tunnel(TunnelSpec(**base, uneven_density=0.6))
    bins = np.arange(0.0, 40.0 + 1e-9, 1.0)
    cv_flat = np.std(np.histogram(tf.chainage, bins)[0]) / np.mean(
        np.histogram(tf.chainage, bins)[0]
    )
    h = np.histogram(tu.chainage, bins)[0]
    assert cv_flat < 0.05
    assert np.std(h) / np.mean(h) > 0.15
    assert len(uneven) == pytest.approx(len(flat), rel=0.2)
    holed, _ = make_tunnel(TunnelSpec(**base, holes=10))
    assert 0.9 * len(flat) < len(holed) < len(flat) - 10 * np.pi * 0.3**2 * 60.0 * 0.5


def test_outliers_inside_tunnel_and_fraction():
    cloud, truth = make_tunnel(TunnelSpec(density=60.0, outlier_fraction=0.01))
    out = truth.label == LABEL_OUTLIER
    assert out.sum() == pytest.approx(0.01 * (~out).sum(), rel=0.02)
    pr = truth.centerline.project(cloud.xyz[out])
    assert np.all(truth.outline.signed_distance(pr.lateral, pr.vertical) < 0)
    assert np.all(truth.surface[out] == 255)


def test_chamber_recess_depth():
    spec = TunnelSpec(density=80.0, chamber=True, chamber_depth=2.0, chamber_length=4.0, **CLEAN)
    cloud, truth = make_tunnel(spec)
    pr = truth.centerline.project(cloud.xyz)
    deep = pr.lateral > W2 + 0.01
    assert pr.lateral.max() == pytest.approx(W2 + 2.0, abs=1e-9)
    assert pr.chainage[deep].min() == pytest.approx(13.0, abs=0.05)
    assert pr.chainage[deep].max() == pytest.approx(17.0, abs=0.05)
    # the wall itself is open along the chamber
    wall = np.isclose(pr.lateral, W2, atol=1e-9) & (np.abs(pr.chainage - 15.0) < 1.9)
    assert wall.sum() == 0
    # the chamber flag marks exactly the rock beyond the design outline
    outside = truth.outline.signed_distance(pr.lateral, pr.vertical) > 1e-9
    np.testing.assert_array_equal(truth.chamber, outside)
    assert np.all(truth.label[truth.chamber] == LABEL_SHELL)


def test_intensity_field_and_no_truth_on_clouds(busy_pair):
    for cloud in (busy_pair.ref, busy_pair.cmp):
        assert set(cloud.fields) == {"intensity"}
        assert cloud.fields["intensity"].dtype == np.uint16
    t = busy_pair.truth
    inten = busy_pair.cmp.fields["intensity"].astype(float)
    assert np.median(inten[t.label == LABEL_DYNAMIC]) < 0.5 * np.median(
        inten[t.label == LABEL_SHELL]
    )


def test_seed_determinism():
    spec = PairSpec(tunnel=TunnelSpec(length=10.0, density=40.0, conveyor=True), seed=7)
    a, b = make_pair(spec), make_pair(spec)
    np.testing.assert_array_equal(a.cmp.xyz, b.cmp.xyz)
    np.testing.assert_array_equal(a.ref.fields["intensity"], b.ref.fields["intensity"])
    np.testing.assert_array_equal(a.truth.transform, b.truth.transform)
    c = make_pair(spec, seed=8)
    assert len(c.ref) != len(a.ref) or not np.array_equal(c.ref.xyz, a.ref.xyz)
    assert not np.allclose(c.truth.transform, a.truth.transform)
    # make_tunnel with the same seed is the reference epoch of make_pair
    cloud, _ = make_tunnel(spec.tunnel, seed=7)
    np.testing.assert_array_equal(cloud.xyz, a.ref.xyz)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: SectionSpec(width=-5.8), "section width must be a positive"),
        (lambda: SectionSpec(kind="circle"), "unknown section kind 'circle'"),
        (lambda: DeformationSpec(kind="collapse"), "unknown deformation kind"),
        (lambda: DeformationSpec(side="up"), "side must be 'left' or 'right'"),
        (lambda: TunnelSpec(density=0.0), "density must be a positive"),
        (lambda: TunnelSpec(radius=5.0), "too tight"),
        (lambda: TunnelSpec(uneven_density=1.5), "uneven_density"),
        (
            lambda: PairSpec(deformations=(DeformationSpec(amplitude=1.5),)),
            "larger than half the section",
        ),
        (
            lambda: make_tunnel(
                TunnelSpec(length=5.0, density=10.0),
                deformations=(DeformationSpec(amplitude=-2.0),),
            ),
            "larger than half the section",
        ),
    ],
)
def test_bad_specs_raise(build, match):
    with pytest.raises(ConfigError, match=match):
        build()


@pytest.mark.parametrize("fmt", ["ply", "las", "laz"])
def test_write_pair(tmp_path, fmt):
    from tunneldef.io import read

    pair = make_pair(tunnel=TunnelSpec(length=6.0, density=30.0), seed=4)
    paths = write_pair(pair, tmp_path, fmt=fmt)
    assert set(paths) == {"ref", "cmp", "truth"}
    assert paths["cmp"].suffix == f".{fmt}"
    assert all(p.is_file() for p in paths.values())
    truth = np.load(paths["truth"])
    np.testing.assert_array_equal(truth["transform"], pair.truth.transform)
    np.testing.assert_array_equal(truth["label"], pair.truth.label)
    assert truth["cmp_xyz_in_ref"].shape == (len(pair.cmp), 3)
    assert json.loads(str(truth["spec_json"]))["seed"] == 4
    back = read(paths["cmp"])
    np.testing.assert_allclose(back.xyz, pair.cmp.xyz, atol=1e-3)  # LAS scale 1 mm
    np.testing.assert_allclose(back.fields["intensity"], pair.cmp.fields["intensity"], rtol=1e-6)


def test_people_and_belt_shadow():
    spec = TunnelSpec(length=20.0, density=200.0, conveyor=True, people=3, **CLEAN)
    cloud, truth = make_tunnel(spec, seed=1)
    pr = truth.centerline.project(cloud.xyz)
    people = (truth.label == LABEL_DYNAMIC) & (pr.lateral > -1.2)  # coal: on the belt, right
    expected = 3 * 200.0 * 2 * np.pi * 0.2 * 1.75
    assert people.sum() == pytest.approx(expected, rel=0.1)
    assert pr.vertical[people].min() == pytest.approx(-H2, abs=0.01)
    # the belt (0.9 m above the floor, right side) shadows a band of the right wall below it;
    # a handheld scanner still records a fifth of it
    wall = truth.surface == 2
    band = wall & (pr.vertical > -0.9) & (pr.vertical < -0.7)
    free = wall & (pr.vertical > -0.2) & (pr.vertical < 0.6)
    ratio = (band.sum() / 0.2) / (free.sum() / 0.8)
    assert ratio == pytest.approx(0.2, abs=0.05)


def test_static_roughness_is_shared_by_both_epochs():
    from scipy.spatial import cKDTree

    tunnel = TunnelSpec(length=12.0, density=400.0, roughness=0.03, **CLEAN)
    pair = make_pair(
        tunnel=tunnel,
        cmp_shift=0.0,
        seed=6,
        deformations=(DeformationSpec(chainage=6.0, amplitude=0.05),),
    )
    t = pair.truth
    ref_pr = t.centerline.project(pair.ref.xyz)
    ref_off = t.outline.signed_distance(ref_pr.lateral, ref_pr.vertical)
    keep = ref_pr.inside & _away_from_corners(ref_pr.lateral, ref_pr.vertical, 0.2)
    assert ref_off[keep].std() == pytest.approx(0.03, rel=0.25)
    cmp_pr = t.centerline.project(t.cmp_xyz_in_ref)
    cmp_off = t.outline.signed_distance(cmp_pr.lateral, cmp_pr.vertical) - t.displacement
    _, j = cKDTree(pair.ref.xyz).query(t.cmp_xyz_in_ref)
    sel = (t.label == LABEL_SHELL) & keep[j]
    assert np.median(np.abs(cmp_off - ref_off[j])[sel]) < 0.003


def test_cmp_centerline_in_cmp_frame():
    pair = make_pair(
        tunnel=TunnelSpec(length=15.0, density=40.0, radius=50.0, **CLEAN), cmp_shift=2.0, seed=9
    )
    line = pair.truth.cmp_centerline
    assert line.length == pytest.approx(15.0, abs=1e-9)
    pr = line.project(pair.cmp.xyz)
    np.testing.assert_allclose(pr.chainage + 2.0, pair.truth.chainage, atol=3e-3)


def test_progress_is_reported():
    seen: list[tuple[str, float]] = []
    make_pair(
        tunnel=TunnelSpec(length=5.0, density=20.0), progress=lambda s, f: seen.append((s, f))
    )
    fractions = [f for _, f in seen]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0
    assert fractions == sorted(fractions)
    seen.clear()
    make_tunnel(TunnelSpec(length=5.0, density=20.0), progress=lambda s, f: seen.append((s, f)))
    assert [f for _, f in seen] == [0.0, 1.0]


def test_shell_drawn_in_stretches_is_one_uniform_sample(monkeypatch):
    from tunneldef.synth import sampling

    defs = (DeformationSpec("roof_sag", chainage=10.0, amplitude=0.05),)
    spec = TunnelSpec(length=20.0, density=100.0, holes=6, equipment=True, **CLEAN)
    whole, tw = make_tunnel(spec, deformations=defs, seed=3)
    monkeypatch.setattr(sampling, "_SHELL_CHUNK", 3000)  # ~12 stretches
    parts, tp = make_tunnel(spec, deformations=defs, seed=3)
    assert len(parts) == pytest.approx(len(whole), rel=0.02)
    assert np.all(np.diff(tp.chainage) >= 0)  # still in walk order
    h = np.histogram(tp.chainage[tp.label == LABEL_SHELL], np.arange(0.0, 20.01, 1.0))[0]
    assert np.std(h) / np.mean(h) < 0.12  # holes aside, no seams at the stretch edges
    pr = tp.centerline.project(parts.xyz)
    shell = tp.label == LABEL_SHELL
    offset = tp.outline.signed_distance(pr.lateral[shell], pr.vertical[shell])
    np.testing.assert_allclose(offset, tp.displacement[shell], atol=1e-9)
    assert tp.displacement.min() == pytest.approx(-0.05, abs=1e-3)


def test_large_pair_written_stretch_by_stretch_is_the_same_kind_of_pair(tmp_path):
    from tunneldef.io import read
    from tunneldef.synth.large import write_large_pair
    from tunneldef.transforms import apply_transform

    tunnel = TunnelSpec(length=20.0, density=150.0, conveyor=True, **CLEAN)
    spec = PairSpec(tunnel=tunnel, deformations=(DeformationSpec(chainage=10.0),),
                    cmp_shift=1.0, seed=5)
    paths = write_large_pair(spec, tmp_path, fmt="laz", stretch=6.0)
    truth = json.loads(paths["truth"].read_text())
    ref, cmp = read(paths["ref"]), read(paths["cmp"])
    whole = make_pair(spec)
    # the same density, drawn in four stretches per epoch
    assert truth["points"] == {"ref": len(ref), "cmp": len(cmp)}
    assert abs(len(ref) / len(whole.ref) - 1) < 0.02
    assert abs(len(cmp) / len(whole.cmp) - 1) < 0.02
    assert truth["cmp_range"] == [1.0, 21.0]
    # the transform takes the compared epoch onto the design section, coal and belt inside it
    back = apply_transform(np.array(truth["transform"]), cmp.xyz)
    assert back[:, 0].min() == pytest.approx(1.0, abs=0.05)
    assert back[:, 0].max() == pytest.approx(21.0, abs=0.05)
    assert np.abs(back[:, 1]).max() < W2 + 1e-3 and np.abs(back[:, 2]).max() < H2 + 1e-3
    # no seam: every metre of chainage holds its share of the shell
    per_m = np.bincount(np.floor(back[:, 0] - 1.0).astype(int).clip(0, 19), minlength=20)
    assert per_m.min() > 0.8 * per_m.mean()
    # the 30 mm sag is in the compared epoch only, at its chainage
    def roof(xyz, lo, hi):
        m = (xyz[:, 0] > lo) & (xyz[:, 0] < hi) & (np.abs(xyz[:, 1]) < 0.3) & (xyz[:, 2] > 0)
        return np.median(xyz[m, 2])

    assert roof(back, 9.7, 10.3) == pytest.approx(H2 - 0.03, abs=2e-3)
    assert roof(ref.xyz, 9.7, 10.3) == pytest.approx(H2, abs=1e-3)
    with pytest.raises(ConfigError, match="LAS or LAZ"):
        write_large_pair(spec, tmp_path, fmt="ply")
