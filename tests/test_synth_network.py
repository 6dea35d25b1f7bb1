"""Synthetic drift networks (tunneldef.synth.network): geometry, truth, drift, strays, walks."""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef.errors import ConfigError
from tunneldef.io import read
from tunneldef.synth import (
    LABEL_DYNAMIC,
    LABEL_EQUIPMENT,
    LABEL_OUTLIER,
    SURFACE_FLOOR,
    SURFACE_LEFT,
    SURFACE_RIGHT,
    SectionSpec,
    section_outline,
)
from tunneldef.synth.network import (
    NO_BRANCH,
    SURFACE_FACE,
    EdgeSpec,
    NetworkPairSpec,
    NetworkSpec,
    Stretch,
    build_branches,
    make_network_pair,
    network_250m,
    network_250m_pair,
    ramp_survey_pair,
    write_network_pair,
)

SIGMA = 0.015
DENSITY = 60.0


@pytest.fixture(scope="module")
def pair():
    return make_network_pair(density=DENSITY, seed=7)


def _in_ref(pair, name):
    t = pair.truth
    if name == "ref":
        return pair.ref.xyz
    xyz = pair.cmp.xyz
    return xyz @ t.transform[:3, :3].T + t.transform[:3, 3]


def _axis_distance(branches, xyz):
    return np.min([b.tree.query(xyz)[0] for b in branches], axis=0)


# --------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------


def test_branch_lengths_and_ramp_geometry():
    net = network_250m()
    branches = build_branches(net)
    lengths = [b.length for b in branches]
    assert lengths[:4] == pytest.approx([110.0, 40.0, 30.0, 20.0], abs=1e-9)
    # the ramp: polyline length minus what each fillet cuts off, plus the arcs
    v = np.asarray(net.edges[4].vertices)
    seg = np.diff(v, axis=0)
    d = seg / np.linalg.norm(seg, axis=1, keepdims=True)
    r = net.edges[4].bend_radius
    th = np.arccos(np.clip(np.einsum("ij,ij->i", d[:-1], d[1:]), -1, 1))
    expect = np.linalg.norm(seg, axis=1).sum() - np.sum(2 * r * np.tan(th / 2) - r * th)
    assert lengths[4] == pytest.approx(expect, abs=1e-9)
    assert 48.0 < lengths[4] < 52.0
    assert sum(lengths) == pytest.approx(250.0, abs=2.0)
    for b in branches:
        assert b.centerline.length == pytest.approx(b.length, abs=1e-9)
        # samples are spaced by the chainage step (arc length)
        seg_len = np.linalg.norm(np.diff(b.centerline.points, axis=0), axis=1)
        assert np.allclose(seg_len, b.step, atol=1e-5)
    ramp = branches[4].centerline
    # grade 10-15 % over the climbing part, a 60 degree bend to the left
    s = np.arange(10.0, ramp.length - 1.0, 1.0)
    t = np.stack(ramp.frame_at(s)[0])
    grade = t[:, 2] / np.hypot(t[:, 0], t[:, 1])
    assert np.all((grade > 0.10) & (grade < 0.15))
    t0, t1 = ramp.frame_at(np.array([1.0, ramp.length - 0.5]))[0]
    heading = np.degrees(np.arctan2(t1[1], t1[0]) - np.arctan2(t0[1], t0[0]))
    assert heading == pytest.approx(60.0, abs=0.1)
    assert branches[4].max_curvature == pytest.approx(1 / 12.0, rel=1e-3)


def test_sections_of_the_preset():
    kinds = [e.section.kind for e in network_250m().edges]
    assert set(kinds) == {"rectangle", "arch", "trapezoid", "horseshoe"}
    o = section_outline(SectionSpec("horseshoe", 4.0, 3.2))
    assert o.signed_distance(np.array([0.0]), np.array([1.6]))[0] == pytest.approx(0.0, abs=1e-12)
    assert o.signed_distance(np.array([0.0]), np.array([-1.6]))[0] == pytest.approx(0.0, abs=1e-12)
    # span 4 m at the springing line, 1.2 m above the floor; walls of radius 4 m about the
    # opposite springing point
    assert o.half_width(-0.4)[0] == pytest.approx(2.0, abs=1e-3)
    assert o.half_width(-1.6)[0] == pytest.approx(np.sqrt(16.0 - 1.2**2) - 2.0, abs=5e-3)
    with pytest.raises(ConfigError):
        SectionSpec("horseshoe", 4.0, 1.5)


# --------------------------------------------------------------------------------------------
# truth of the points
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("epoch", ["ref", "cmp"])
def test_shell_points_lie_on_their_branch(pair, epoch):
    t = pair.truth
    ep = getattr(t, epoch)
    for b in t.branches:
        m = (ep.branch == b.index) & ep.shell & (ep.surface != SURFACE_FACE)
        assert m.sum() > 1000
        sd, pr = b.signed_distance(ep.xyz_ref[m])
        res = sd - ep.displacement[m]
        assert np.std(res) == pytest.approx(SIGMA, rel=0.06)
        assert abs(np.mean(res)) < 0.002
        assert np.max(np.abs(res)) < 6 * SIGMA
        # chainage: that of the noisy point (first order on the bend)
        assert np.max(np.abs(pr.chainage - ep.chainage[m])) < 0.005
    # dead-end face: in the section plane at the end of the edge
    face = ep.surface == SURFACE_FACE
    assert face.sum() > 0 and set(np.unique(ep.branch[face])) == {3}
    b3 = t.branches[3]
    pr = b3.project(ep.xyz_ref[face])
    assert np.std(pr.chainage - b3.length) == pytest.approx(SIGMA, rel=0.15)
    assert np.all(b3.outline.signed_distance(pr.lateral, pr.vertical) < 4 * SIGMA)


def test_deformed_points_moved_by_their_truth(pair):
    t = pair.truth
    assert np.all(t.ref.displacement == 0.0)
    ep = t.cmp
    assert len(t.deformations) == 5
    amps = sorted(d.amplitude for d in t.deformations)
    assert amps[0] >= 0.010 and amps[-1] <= 0.060
    assert {d.branch for d in t.deformations} >= {0, 2, 4}
    moved = ep.displacement < 0
    found = np.zeros(moved.shape[0], dtype=bool)
    for d in t.deformations:
        b = t.branches[d.branch]
        half = d.deformation.length / 2 + 0.1
        m = (ep.branch == d.branch) & (np.abs(ep.chainage - d.chainage) < half) & moved
        assert m.sum() > 20
        found |= m
        # the peak: close to the amplitude, nowhere beyond it
        assert -ep.displacement[m].min() == pytest.approx(d.amplitude, rel=0.1)
        assert -ep.displacement[m].min() <= d.amplitude + 1e-12
        sd, _ = b.signed_distance(ep.xyz_ref[m])
        # displaced by the truth: the design surface offset is the displacement (+ noise)
        res = sd - ep.displacement[m]
        assert abs(np.mean(res)) < 3 * SIGMA / np.sqrt(m.sum()) + 0.001
        assert np.mean(sd) == pytest.approx(np.mean(ep.displacement[m]), abs=0.004)
        surf = {"roof_sag": 0, "floor_heave": SURFACE_FLOOR}.get(d.kind)
        if surf is None:
            surf = SURFACE_LEFT if d.deformation.side == "left" else SURFACE_RIGHT
        assert np.bincount(ep.surface[m]).argmax() == surf
    assert not np.any(moved & ~found)


def test_junctions_are_open(pair):
    t = pair.truth
    for ep in (t.ref, t.cmp):
        for b in t.branches:
            m = (ep.branch == b.index) & ep.shell
            xyz = ep.xyz_ref[m]
            for f in t.branches:
                if f is b:
                    continue
                near = np.isfinite(f.tree.query(xyz, distance_upper_bound=f.radius + 0.1)[0])
                if not near.any():
                    continue
                sd, pr = f.signed_distance(xyz[near])
                deep = (pr.chainage > 0.1) & (pr.chainage < f.length - 0.1) & (sd < -0.1)
                assert not deep.any(), (b.name, f.name)
    # the crossing: no wall points of the main drift across the cross-cut's 4.2 m mouth,
    # nor of the cross-cut inside the main drift's 5 m width
    ep = t.ref
    main = (ep.branch == 0) & np.isin(ep.surface, (SURFACE_LEFT, SURFACE_RIGHT))
    # above the floor, below the cross-cut arch's springing line
    main &= (ep.xyz_ref[:, 2] > -1.5) & (ep.xyz_ref[:, 2] < -0.1)
    assert not np.any(main & (np.abs(ep.chainage - 30.0) < 2.0))
    assert np.sum(main & (np.abs(ep.chainage - 45.0) < 1.9)) > 200
    xc = (ep.branch == 1) & ep.shell
    assert not np.any(xc & (np.abs(ep.chainage - 20.0) < 2.3))
    # junction nodes are on the main drift's axis
    cl = t.centerlines[0]
    assert np.all(cl.project(t.junction_positions).distance < 1e-9)
    # coincident floors at the crossing are sampled once (by the main drift)
    floor = ep.shell & (ep.surface == SURFACE_FLOOR)
    near = floor & (np.abs(ep.xyz_ref[:, 0] - 30.0) < 2.0) & (np.abs(ep.xyz_ref[:, 1]) < 2.0)
    assert near.sum() == pytest.approx(DENSITY * 16.0, rel=0.25)


def test_drift(pair):
    t = pair.truth
    spec = pair.spec
    offsets = []
    for name in ("ref", "cmp"):
        ep = getattr(t, name)
        off = _in_ref(pair, name) - ep.xyz_ref
        model = ep.drift_offset()
        assert np.max(np.abs(off - model)) < 1e-8
        assert np.max(np.abs(off[ep.stray])) < 1e-8
        # the rate: RMS of |centreline drift| / sqrt(path / 100 m) over the knots
        tau = np.concatenate([k[:, 0] for k in ep.drift.knots])
        d = np.concatenate([np.linalg.norm(k[:, 1:4], axis=1) for k in ep.drift.knots])
        use = tau > 0
        rate = np.sqrt(np.mean(d[use] ** 2 / (tau[use] / 100.0)))
        assert rate == pytest.approx(spec.drift, rel=1e-9)
        # a few centimetres per 100 m, everywhere
        mag = np.linalg.norm(off, axis=1)
        first = ~ep.stray & (ep.path < 100.0)
        assert 0.003 < mag[first].max() < 0.12
        assert mag[~ep.stray].max() < 0.25
        # smooth: neighbouring points of the walk drift alike
        walk = np.flatnonzero(~ep.stray & (ep.stretch == 0))
        assert np.max(np.abs(np.diff(off[walk], axis=0))) < 0.005
        # continuous across a junction: main drift and cross-cut at the crossing
        at = np.array([[30.0, 0.0, -1.6]])
        k_main = 0
        k_xc = int(np.flatnonzero([s.branch == 1 for s in ep.coverage])[0])
        o_main = ep.drift.offset(
            at, np.array([k_main]), ep.drift.tau0[[k_main]] + 30.0 - (ep.coverage[0].start)
        )
        o_xc = ep.drift.offset(at, np.array([k_xc]), ep.drift.tau0[[k_xc]])
        assert np.linalg.norm(o_main - o_xc) < 2e-4
        # removing it gives the truth back
        m = ~ep.stray
        back = ep.drift.remove(ep.xyz_ref[m] + off[m], ep.stretch[m], ep.path[m])
        assert np.max(np.abs(back - ep.xyz_ref[m])) < 1e-6
        offsets.append(model)
    # each epoch its own drift
    assert not np.allclose(t.ref.drift.knots[0][:3], t.cmp.drift.knots[0][:3])
    rot = t.transform[:3, :3]
    assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)


def test_strays_far_away(pair):
    t = pair.truth
    for ep in (t.ref, t.cmp):
        st = ep.stray
        assert 1 + 3 * 5 <= st.sum() <= 1 + 3 * 40
        assert np.all(ep.branch[st] == NO_BRANCH) and np.all(np.isnan(ep.chainage[st]))
        assert np.all(ep.label[st] == LABEL_OUTLIER)
        d = _axis_distance(t.branches, ep.xyz_ref[st])
        # the first stray is the single far point, 130 m from the nearest design axis
        assert d[0] == pytest.approx(130.0, abs=0.3)
        assert np.all(d > 39.0)
        # strays come last; the rest is in walk order
        assert np.all(st[-st.sum() :])
        assert np.all(np.diff(ep.path[~st]) >= 0)
    assert not np.allclose(t.ref.xyz_ref[t.ref.stray][0], t.cmp.xyz_ref[t.cmp.stray][0])


def test_coverage_of_the_epochs(pair):
    t = pair.truth
    lengths = t.branch_lengths
    # cross-cuts 2 and 3 start on the main drift's axis: their first metres are inside it
    for ep, expect in (
        (t.ref, {0: (0, 110), 1: (0, 40), 2: (None, 24), 3: (None, 20), 4: (0, 42)}),
        (t.cmp, {0: (6, 110), 1: (0, 40), 2: (None, 30), 3: (None, 20), 4: (0, lengths[4])}),
    ):
        shell = ep.shell & ~ep.stray
        for b, (lo, hi) in expect.items():
            c = ep.chainage[shell & (ep.branch == b)]
            if lo is None:
                assert 1.0 < c.min() < 4.0
            else:
                assert c.min() == pytest.approx(lo, abs=0.1)
            assert c.max() == pytest.approx(hi, abs=0.1)
        # the walk: every stretch after the first branches off an earlier one
        assert ep.drift.parent[0] == -1 and np.all(ep.drift.parent[1:] < np.arange(1, 6))
    # the later epoch covers more
    assert np.sum(t.cmp.branch == 4) > np.sum(t.ref.branch == 4)
    # density: the dead-end cross-cut (no junction on its far part), per m^2
    b = t.branches[3]
    ep = t.ref
    m = ep.shell & (ep.branch == 3) & (ep.chainage > 5) & (ep.chainage < 19)
    assert m.sum() / (14.0 * b.outline.perimeter) == pytest.approx(DENSITY, rel=0.06)
    # the ramp's bend: the inner (left) side gets fewer points per metre of chainage than the
    # outer side, the same per m^2 (roof and floor, 1-2.25 m off the axis)
    b4 = t.branches[4]
    m = ep.shell & (ep.branch == 4) & (ep.chainage > 20) & (ep.chainage < 31)
    m &= np.isin(ep.surface, (0, SURFACE_FLOOR))
    lat = b4.project(ep.xyz_ref[m]).lateral
    k = b4.max_curvature
    ratio = np.sum(lat > 1.0) / np.sum(lat < -1.0)
    assert ratio == pytest.approx((1 - 1.625 * k) / (1 + 1.625 * k), rel=0.08)
    # clutter where asked for: pipes in the main drift and on the ramp, a conveyor with coal
    # (dynamic, drawn anew) in the main drift
    eq = ep.label == LABEL_EQUIPMENT
    assert set(np.unique(ep.branch[eq])) == {0, 4}
    for e in (t.ref, t.cmp):
        coal = e.label == LABEL_DYNAMIC
        assert coal.sum() > 100 and set(np.unique(e.branch[coal])) == {0}


def test_the_ramp_survey_pair_covers_more_in_the_later_epoch():
    """The survey-shaped preset: the reference walks the main drift and its three cross-cuts,
    the compared walk also the ramp (climbing about 20 m) and its four dead ends."""
    p = make_network_pair(ramp_survey_pair(density=20.0, seed=1))
    t = p.truth
    shell = t.ref.label == 0
    assert set(np.unique(t.ref.branch[shell & ~t.ref.stray])) == {0, 1, 2, 3}
    assert set(np.unique(t.cmp.branch[(t.cmp.label == 0) & ~t.cmp.stray])) == set(range(9))
    ramp = t.cmp.xyz_ref[(t.cmp.branch == 4) & (t.cmp.label == 0)]
    assert 18.0 < np.ptp(ramp[:, 2]) - 3.0 < 22.0
    assert len(p.cmp) > 1.8 * len(p.ref)


def test_seeded_and_deterministic():
    spec = network_250m_pair(density=20.0, drift=0.05, stray_clusters=1)
    a = make_network_pair(spec, seed=3)
    b = make_network_pair(spec, seed=3)
    c = make_network_pair(spec, seed=4)
    assert np.array_equal(a.ref.xyz, b.ref.xyz) and np.array_equal(a.cmp.xyz, b.cmp.xyz)
    assert np.array_equal(a.truth.cmp.displacement, b.truth.cmp.displacement)
    assert np.array_equal(a.truth.transform, b.truth.transform)
    assert len(a.ref) != len(c.ref) or not np.array_equal(a.ref.xyz, c.ref.xyz)


def test_default_walk_and_bad_walks():
    net = NetworkSpec(
        (
            EdgeSpec("a", ((0, 0, 0), (30, 0, 0))),
            EdgeSpec("b", ((15, -10, 0), (15, 10, 0)), SectionSpec("arch", 4.0, 2.86)),
        )
    )
    p = make_network_pair(NetworkPairSpec(net, density=20.0, seed=1))
    cov = p.truth.ref.coverage
    # the crossing edge is walked both ways from the crossing
    assert cov[0] == Stretch(0, 0.0, 30.0)
    assert {(s.branch, s.start) for s in cov[1:]} == {(1, 10.0)}
    assert {s.end for s in cov[1:]} == {0.0, 20.0}
    with pytest.raises(ConfigError, match="does not start"):
        make_network_pair(
            NetworkPairSpec(net, ref_coverage=(Stretch(0, 0, 10), Stretch(1, 0, 20)), density=20)
        )
    with pytest.raises(ConfigError, match="overlap"):
        make_network_pair(
            NetworkPairSpec(net, ref_coverage=(Stretch(0, 0, 20), Stretch(0, 25, 10)), density=20)
        )
    with pytest.raises(ConfigError, match="too short"):
        build_branches(
            NetworkSpec((EdgeSpec("c", ((0, 0, 0), (10, 0, 0), (10, 3, 0)), bend_radius=15.0),))
        )


def test_write_pair(tmp_path):
    p = make_network_pair(density=10.0, seed=2, stray_clusters=1)
    for fmt in ("ply", "laz"):
        paths = write_network_pair(p, tmp_path / fmt, fmt=fmt)
        back = read(paths["cmp"])
        assert len(back) == len(p.cmp)
        assert np.allclose(back.xyz, p.cmp.xyz, atol=2e-4)
    with np.load(paths["truth"]) as z:
        assert z["ref_branch"].shape == (len(p.ref),)
        assert z["cmp_xyz_ref"].shape == (len(p.cmp), 3)
        assert z["deformations"].shape == (5, 5)
        assert z["junctions"].shape == (4, 3)
        assert "centerline_4" in z and "spec_json" in z


def test_noise_free_surfaces_are_exact():
    """Without noise and drift the points are the design surfaces, cut exactly at junctions."""
    p = make_network_pair(density=15.0, seed=5, noise_sigma=0.0, drift=0.0, equipment=False)
    t = p.truth
    ep = t.ref
    assert np.array_equal(p.ref.xyz, ep.xyz_ref)
    for b in t.branches:
        m = (ep.branch == b.index) & ep.shell & (ep.surface != SURFACE_FACE)
        sd, pr = b.signed_distance(ep.xyz_ref[m])
        assert np.max(np.abs(sd)) < 5e-5
        assert np.max(np.abs(pr.chainage - ep.chainage[m])) < 5e-5
        for f in t.branches:
            if f is not b:
                assert not np.any(f.inside(ep.xyz_ref[m], margin=0.006)), (b.name, f.name)
    cmp = t.cmp
    back = p.cmp.xyz @ t.transform[:3, :3].T + t.transform[:3, 3]
    assert np.max(np.abs(back - cmp.xyz_ref)) < 1e-9
    shell = cmp.shell & (cmp.surface != SURFACE_FACE)
    for d in t.deformations:
        b = t.branches[d.branch]
        m = shell & (cmp.branch == d.branch)
        sd, _ = b.signed_distance(cmp.xyz_ref[m])
        assert np.max(np.abs(sd - cmp.displacement[m])) < 5e-5


def test_rock_relief_is_the_same_rock_in_both_epochs():
    """``roughness`` moves every edge's shell off its design outline by a smooth relief of that
    standard deviation, the same in both epochs (where the rock did not move)."""
    from scipy.spatial import cKDTree

    rough = 0.04
    p = make_network_pair(density=15.0, seed=5, noise_sigma=0.0, drift=0.0, equipment=False,
                          roughness=rough)
    t = p.truth
    sds = {}
    for name, ep in (("ref", t.ref), ("cmp", t.cmp)):
        m = ep.shell & (ep.surface != SURFACE_FACE) & (ep.displacement == 0)
        sd = np.full(len(ep.branch), np.nan)
        for b in t.branches:
            mb = m & (ep.branch == b.index)
            sd[mb] = b.signed_distance(ep.xyz_ref[mb])[0]
        sds[name] = (ep.xyz_ref[m], sd[m])
    for name in ("ref", "cmp"):
        assert np.std(sds[name][1]) == pytest.approx(rough, rel=0.25), name
    # the compared epoch's relief, read off the reference points next to it
    (rx, rsd), (cx, csd) = sds["ref"], sds["cmp"]
    dist, nn = cKDTree(rx).query(cx)
    close = dist < 0.04  # the relief is steep: compare points a few cm apart only
    assert close.sum() > 1000
    diff = csd[close] - rsd[nn[close]]
    assert np.std(diff) < 0.25 * rough  # independent rock would give sqrt(2) * rough
    with pytest.raises(ConfigError, match="roughness"):
        make_network_pair(density=15.0, seed=5, roughness=-0.01)


def test_edge_checks():
    with pytest.raises(ConfigError, match="at least 2"):
        EdgeSpec("a", ((0, 0, 0),))
    with pytest.raises(ConfigError, match="repeated"):
        EdgeSpec("a", ((0, 0, 0), (0, 0, 0), (5, 0, 0)))
    with pytest.raises(ConfigError, match="steeper"):
        build_branches(NetworkSpec((EdgeSpec("shaft", ((0, 0, 0), (0.5, 0, 20))),)))
    with pytest.raises(ConfigError, match="unique"):
        NetworkSpec((EdgeSpec("a", ((0, 0, 0), (5, 0, 0))), EdgeSpec("a", ((0, 0, 0), (0, 5, 0)))))
