"""Drift networks as surveyors walk them: cross-cuts seen only a few metres in, surveys that
share no junction, oblique crossings, networks that are not elongated, far stray points.
Each case here came out of ``benchmarks/network_sweep.py`` refused or registered metres off."""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef.centerline.network import extract_network
from tunneldef.centerline.skeleton import plan_graph
from tunneldef.cloud import Cloud
from tunneldef.config import Config
from tunneldef.errors import NotATunnelError
from tunneldef.pipeline import check_epochs
from tunneldef.registration.network import register_networks
from tunneldef.synth import SectionSpec
from tunneldef.synth.network import (
    EdgeSpec,
    JunctionSpec,
    NetworkSpec,
    Stretch,
    make_network_pair,
)
from tunneldef.transforms import apply_transform

RECT = SectionSpec("rectangle", 4.6, 3.0)
XC = SectionSpec("rectangle", 3.6, 2.6)


def _pair(edges, junctions, ref_cov, cmp_cov, **kw):  # noqa: ANN001, ANN003, ANN202
    spec = dict(network=NetworkSpec(tuple(edges), tuple(junctions)), deformations=(),
                ref_coverage=tuple(ref_cov), cmp_coverage=tuple(cmp_cov), density=120.0,
                drift=0.0, equipment=False, tilt_deg=1.5, seed=5)
    spec.update(kw)
    return make_network_pair(**spec)


def _rms_error(pair, transform) -> float:  # noqa: ANN001
    probe = pair.cmp.xyz[::50]
    err = apply_transform(transform, probe) - apply_transform(pair.truth.transform, probe)
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def test_surveys_that_share_no_junction_register_by_their_drift() -> None:
    """Sweep case 1000008's pattern: the earlier survey walks cross-cut A, the later one only
    looks a few metres into A (a stub, left out of its network) and walks cross-cut B, which
    the earlier one passed by. The two networks share no junction; pairing A with B slid the
    later survey 66 m along the main drift with every registration check passing. The main
    drift and the mouths in its walls fix the pose."""
    edges = [EdgeSpec("main", ((0.0, 0.0, 0.0), (70.0, 0.0, 0.0)), RECT),
             EdgeSpec("A", ((15.0, 0.0, -0.2), (24.0, 22.0, -0.2)), XC, faces=(False, True)),
             EdgeSpec("B", ((50.0, 0.0, -0.2), (59.0, 22.0, -0.2)), XC, faces=(False, True))]
    junctions = [JunctionSpec("a", (15.0, 0.0, 0.0), (0, 1)),
                 JunctionSpec("b", (50.0, 0.0, 0.0), (0, 2))]
    pair = _pair(edges, junctions,
                 [Stretch(0, 1.0, 66.0), Stretch(1, 0.0, None)],
                 [Stretch(0, 6.0, 69.0), Stretch(1, 0.0, 7.0), Stretch(2, 0.0, None)])
    cfg = Config()
    nets = [extract_network(p.xyz, slicing=cfg.slicing, settings=cfg.centerline,
                            network=cfg.network).network for p in (pair.ref, pair.cmp)]
    reg = register_networks(pair.ref.xyz, pair.cmp.xyz, *nets)
    assert _rms_error(pair, reg.transform) < 0.05  # metres off before: 66 m
    # a pose slid to lay the look-alike cross-cuts over each other explains far less
    assert reg.evidence - reg.alternative_evidence > cfg.quality.min_alternative_margin


@pytest.fixture(scope="module")
def stub_pair():  # noqa: ANN201
    """A 50 m drift with a cross-cut at 25 m that the later survey looks 7.5 m into."""
    edges = [EdgeSpec("main", ((0.0, 0.0, 0.0), (50.0, 0.0, 0.0)), RECT),
             EdgeSpec("xc", ((25.0, 0.0, -0.2), (25.0, -25.0, -0.2)), XC, faces=(False, True))]
    junctions = [JunctionSpec("t", (25.0, 0.0, 0.0), (0, 1))]
    return _pair(edges, junctions, [Stretch(0, 0.0, None), Stretch(1, 0.0, None)],
                 [Stretch(0, 0.0, None), Stretch(1, 0.0, 7.5)])


def test_a_stub_whose_sections_cannot_be_read_is_left_out(stub_pair, monkeypatch) -> None:
    """A cross-cut seen a few metres in from the main drift may hold too few sections for a
    centreline (sweep cases 1000004, 1000008: 2 of 19-21 slices, the rest its mouth). Such a
    dead end is left out of its network and said so, instead of failing the whole survey;
    the mouth on the main drift is then no junction, but the main drift keeps its zone."""
    import tunneldef.centerline.network as cn
    from tunneldef.errors import NetworkError

    fit = cn._fit_edge

    def fail_short(records, c, name, axis):  # noqa: ANN001, ANN202
        if axis.length < 12.0:
            raise NetworkError(f"{name}: only 2 of 19 slices show a tunnel section")
        return fit(records, c, name, axis)

    monkeypatch.setattr(cn, "_fit_edge", fail_short)
    net = extract_network(stub_pair.cmp.xyz).network
    assert len(net.edges) == 1 and not net.junctions
    (left,) = net.meta["left_out"]
    assert "sections cannot be read" in left["reason"] and left["length_m"] < 12.0
    assert net.edges[0].zones  # the main drift keeps its zone at the mouth


def test_the_compared_network_leaves_out_any_edge_it_cannot_read(stub_pair, monkeypatch) -> None:
    """Sweep case 58000002: the later walker saw a crossing cross-cut a few metres into
    either side, and that edge, one other drifts cross, refused the whole survey. The
    compared epoch's edges only place it on the reference's (the registration is checked on
    its own), so there any unreadable edge is left out; the reference's carries its
    network; and a network none of whose edges can be read is refused."""
    import tunneldef.centerline.network as cn
    from tunneldef.errors import NetworkError

    fit = cn._fit_edge
    cut = {"at": 30.0}

    def fail_long(records, c, name, axis):  # noqa: ANN001, ANN202
        if axis.length > cut["at"]:
            raise NetworkError(f"{name}: only 1 of 32 slices show a tunnel section")
        return fit(records, c, name, axis)

    monkeypatch.setattr(cn, "_fit_edge", fail_long)
    with pytest.raises(NetworkError, match="only 1 of 32"):
        extract_network(stub_pair.cmp.xyz)
    net = extract_network(stub_pair.cmp.xyz, leave_out_any=True).network
    assert len(net.edges) >= 1 and all(e.length < 30.0 for e in net.edges)
    assert any(left["length_m"] > 30.0 for left in net.meta["left_out"])
    cut["at"] = 0.0
    with pytest.raises(NetworkError, match="no edge of the network can be read"):
        extract_network(stub_pair.cmp.xyz, leave_out_any=True)


def test_a_short_dead_end_that_fails_its_checks_is_left_out(stub_pair) -> None:
    """In detect, a dead end up to ``[network] max_left_out_length`` that fails its own
    checks is left out with the check's figure as the reason; any other edge's failure is
    recorded (here: not enforced) as before, and the compared epoch's only as a warning (its
    curves feed nothing but the registration, which is checked on its own)."""
    from tunneldef.pipeline import _check_edges
    from tunneldef.quality import QualityReport

    cfg = Config().replace(quality={"max_edge_scatter": 1e-4, "enforce": False})
    ex = extract_network(stub_pair.cmp.xyz)
    assert len(ex.network.edges) == 2
    report = QualityReport(enforced=False)
    _check_edges(ex, report, cfg, "reference")
    assert len(ex.network.edges) == 1
    (left,) = ex.network.meta["left_out"]
    assert left["reason"].startswith("reference_network.edge1.curve_uncertainty")
    assert [c.name for c in report.failed] == ["reference_network.edge0.curve_uncertainty"]
    # a longer dead end is no stub: its failure stands
    ex = extract_network(stub_pair.cmp.xyz)
    report = QualityReport(enforced=True)
    _check_edges(ex, report, cfg.replace(network={"max_left_out_length": 5.0}), "compared")
    assert len(ex.network.edges) == 2
    assert report.verified and len(report.warnings) == 2


def test_an_oblique_crossing_is_one_junction() -> None:
    """A cross-cut crossing a wider drift at 55 degrees skeletonises into two forks about
    5 m apart along the drift; they are one crossing, and the cross-cut one edge through it
    (two three-way junctions gave junction zones of 25 m and refused the cross-cut)."""
    a = np.radians(55.0)
    d = np.array([np.cos(a), np.sin(a), 0.0])
    at = np.array([30.0, 0.0, -0.2])
    edges = [EdgeSpec("main", ((0.0, 0.0, 0.0), (60.0, 0.0, 0.0)), SectionSpec(
                 "rectangle", 5.0, 3.0)),
             EdgeSpec("xc", (tuple(at - 14.0 * d), tuple(at + 14.0 * d)), XC)]
    pair = _pair(edges, [JunctionSpec("x", (30.0, 0.0, 0.0), (0, 1))],
                 [Stretch(0, 0.0, None), Stretch(1, 14.0, 0.0), Stretch(1, 14.0, 28.0)],
                 [Stretch(0, 0.0, None)])
    _, graph = plan_graph(pair.ref.xyz, Config().network)
    assert len(graph.junctions) == 1
    assert sorted(round(e.length) for e in graph.edges)[0] > 20  # the cross-cut, whole
    net = extract_network(pair.ref.xyz).network
    xc = min(net.edges, key=lambda e: e.length)
    (zone,) = xc.zones
    assert zone[1] - zone[0] < 12.0  # 2.5 m / sin 55 + ... : about 10 m, not 25


def test_a_network_need_not_be_elongated() -> None:
    """A 30 m drift with a 30 m cross-cut is no elongated cloud: the single-drift check
    refuses it, the network check lets it through (its drifts' widths are compared once
    their centrelines are known)."""
    edges = [EdgeSpec("main", ((0.0, 0.0, 0.0), (30.0, 0.0, 0.0)), RECT),
             EdgeSpec("xc", ((15.0, 0.0, -0.2), (15.0, 30.0, -0.2)), XC, faces=(False, True))]
    pair = _pair(edges, [JunctionSpec("t", (15.0, 0.0, 0.0), (0, 1))],
                 [Stretch(0, 0.0, None), Stretch(1, 0.0, None)],
                 [Stretch(0, 0.0, None), Stretch(1, 0.0, None)], density=40.0)
    with pytest.raises(NotATunnelError, match="not elongated"):
        check_epochs(pair.ref, pair.cmp)
    check_epochs(pair.ref, pair.cmp, network=True)


def test_a_far_stray_does_not_stretch_a_single_drift() -> None:
    """One return 130 m away and a small far cluster, as in a real handheld-SLAM map: the
    centreline is sliced over the drift only (they were sliced over 130 m of nothing, and
    two thirds of the slices were empty)."""
    from tunneldef.centerline import extract_centerline
    from tunneldef.synth import TunnelSpec, make_pair

    pair = make_pair(tunnel=TunnelSpec(length=30.0, density=150.0, noise_sigma=0.01), seed=2)
    rng = np.random.default_rng(0)
    far = np.vstack([pair.ref.xyz.mean(axis=0) + [130.0, 40.0, 3.0],
                     pair.ref.xyz.mean(axis=0) + [-70.0, 60.0, 0.0] + rng.normal(0, 0.1, (30, 3))])
    cloud = Cloud(np.vstack([pair.ref.xyz, far]))
    ex = extract_centerline(cloud.xyz)
    q = ex.quality_of_curve
    assert q.usable_share > 0.8
    assert ex.centerline.length < 31.0


def test_the_curves_alignment_levels_a_pose_a_little_off() -> None:
    """Sweep case 1000003: the best coarse pose sat 0.75 m along the main drift and untilted
    (the compared frame is tilted 0.9 degrees: 0.7 m of height across the survey); the curves'
    ICP refused the step that levelled it because one curve sample fell out of reach, and
    the survey ended 5.5 m along its drift. Here one compared sample the reference does not
    share leaves reach as the pose levels; the truncated sum of distances to the reference
    curves still falls, and the step is taken (counting samples within reach refused it)."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    from tunneldef.registration.network import _align_curves

    def curves(step: float) -> np.ndarray:  # a main drift and a cross-cut off it at 90 m
        main = np.arange(0.0, 110.0 + 1e-9, step)
        xc = np.arange(step, 37.0 + 1e-9, step)
        return np.vstack([np.column_stack([main, np.zeros_like(main), np.zeros_like(main)]),
                          np.column_stack([np.full_like(xc, 90.0), xc, np.zeros_like(xc)])])

    ref_s = curves(0.1)
    truth = np.eye(4)  # compared -> reference: a yaw, a 0.9 degree tilt, a survey offset
    truth[:3, :3] = Rotation.from_euler("zyx", [13.4, 0.6, -0.65], degrees=True).as_matrix()
    truth[:3, 3] = [-624.9, 1380.9, 933.1]
    inv = np.linalg.inv(truth)
    cmp_s = apply_transform(inv, curves(1.0))  # the compared curves in their own frame
    # the coarse pose: the yaw right, no tilt, 0.75 m along the main drift, heights met at
    # the compared curves' centroid
    start = np.eye(4)
    start[:3, :3] = Rotation.from_euler("z", 13.4, degrees=True).as_matrix()
    start[:3, 3] = [0.75, 0.0, 0.0] + (curves(1.0) - cmp_s @ start[:3, :3].T).mean(axis=0)
    rng = np.random.default_rng(3)
    cmp_s = cmp_s + rng.normal(0.0, 0.03, cmp_s.shape)
    # and one sample the reference does not share (the compared epoch's own niche), 0.95 m
    # above the main drift under the coarse pose and out of reach once levelled
    cmp_s = np.vstack([cmp_s, apply_transform(np.linalg.inv(start), np.array([[5.0, 0, 0.95]]))])
    got = _align_curves(start, cmp_s, ref_s, cKDTree(ref_s), 1.0)
    ends = apply_transform(inv, np.array([[0.0, 0, 0], [110.0, 0, 0], [90.0, 37.0, 0]]))
    before = apply_transform(start, ends) - apply_transform(truth, ends)
    after = apply_transform(got, ends) - apply_transform(truth, ends)
    assert np.abs(before[:, 2]).max() > 0.3, before
    # levelled and laid on the curves; the slide along the drift is left to the points' ICP
    assert np.abs(after[:, 1:]).max() < 0.1, (before, after)
    assert np.abs(after[:, 0]).max() < np.abs(before[:, 0]).max(), (before, after)
