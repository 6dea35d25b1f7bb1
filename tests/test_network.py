"""Drift networks: the centreline graph (edges, junctions, point assignment) on a synthetic
network with truth per branch and on the real junction scan."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest

from tunneldef.centerline.network import JUNCTION, extract_network
from tunneldef.centerline.plan import plan_grid
from tunneldef.errors import NetworkError, TunnelDefError
from tunneldef.network import NO_BRANCH
from tunneldef.synth import SectionSpec
from tunneldef.synth.network import (
    EdgeSpec,
    JunctionSpec,
    NetworkSpec,
    make_network_pair,
)

CHAMBER = Path(
    os.environ.get("TUNNELDEF_SHARED_DATA", Path(__file__).resolve().parents[1].parent
                   / "shared" / "data")
) / "freiberg_mine_chamber_tls_0005.laz"


def small_network() -> NetworkSpec:
    """A 40 m main drift, a 24 m cross-cut through it at x = 12 m (a crossing) and a 12 m dead
    end to the left at x = 28 m."""
    edges = (
        EdgeSpec("main", ((0.0, 0.0, 0.0), (40.0, 0.0, 0.0)), SectionSpec("rectangle", 4.0, 3.0)),
        EdgeSpec("xc", ((12.0, -12.0, 0.0), (12.0, 12.0, 0.0)), SectionSpec("arch", 3.6, 3.0)),
        EdgeSpec("dead-end", ((28.0, 0.0, 0.0), (28.0, 12.0, 0.0)),
                 SectionSpec("rectangle", 3.5, 3.0), faces=(False, True)),
    )
    junctions = (JunctionSpec("crossing", (12.0, 0.0, 0.0), (0, 1)),
                 JunctionSpec("tee", (28.0, 0.0, 0.0), (0, 2)))
    return NetworkSpec(edges, junctions, name="small")


@pytest.fixture(scope="module")
def pair():  # noqa: ANN201
    return make_network_pair(network=small_network(), deformations=(), ref_coverage=None,
                             cmp_coverage=None, density=150.0, drift=0.0, equipment=False,
                             seed=3)


@pytest.fixture(scope="module")
def result(pair):  # noqa: ANN001, ANN201
    return extract_network(pair.ref.xyz)


def _truth_axis_errors(net, cl, juncs, hw):  # noqa: ANN001, ANN202
    """Distances of a truth axis (every 0.25 m, 1 m inside its ends, 2 m beyond the other
    drifts' walls at junctions) to the network's curves."""
    s = np.arange(1.0, cl.length - 1.0, 0.25)
    p = cl.point_at(s)
    d = np.min(np.linalg.norm(p[:, None, :2] - juncs[None, :, :2], axis=2), axis=1)
    p = p[d > hw + 2.0]
    pr = net.project(p)
    return np.where(pr.inside, pr.distance, np.inf)


def test_every_branch_found_and_centred(pair, result) -> None:  # noqa: ANN001
    net = result.network
    assert len(net.edges) == 3
    assert len(net.junctions) == 2
    # the main drift passes through both junctions as one edge; the cross-cut passes through
    assert sorted(len(j.edges) for j in net.junctions) == [2, 2]
    juncs = pair.truth.junction_positions
    for b, cl in enumerate(pair.truth.centerlines):
        err = _truth_axis_errors(net, cl, juncs, 2.0)
        assert np.all(np.isfinite(err)), f"branch {b} not covered"
        assert np.percentile(err, 95) <= 0.03, (b, np.percentile(err, 95))
    # junction nodes where the drifts cross
    pos = np.array([j.position for j in net.junctions])
    d = np.linalg.norm(pos[:, None, :2] - juncs[None, :, :2], axis=2).min(axis=0)
    assert np.all(d < 0.3), d


def test_junction_slices_are_flagged_not_fitted(result) -> None:  # noqa: ANN001
    for e in result.network.edges:
        flagged = [r for r in e.slices if r.reason == JUNCTION]
        assert flagged, e.id
        assert not any(r.ok for r in flagged)
        assert e.zones
        ok = np.array([r.chainage for r in e.slices if r.ok])
        assert not np.any(e.in_zone(ok))


def test_points_are_assigned_to_their_branch(pair, result) -> None:  # noqa: ANN001
    net = result.network
    truth = pair.truth.ref
    pr = net.project(pair.ref.xyz, max_distance=5.0)
    m = ~truth.stray & (truth.label == 0)
    # map network edges to truth branches by majority, then compare away from junctions
    mapping = {}
    for e in net.edges:
        sel = m & (pr.branch == e.id)
        mapping[e.id] = int(np.bincount(truth.branch[sel]).argmax())
    assert sorted(mapping.values()) == [0, 1, 2]
    got = np.array([mapping.get(int(b), -1) for b in pr.branch[m]])
    away = ~pr.junction[m]
    assert np.mean(got[away] == truth.branch[m][away]) > 0.995
    # the far stray point belongs to no edge
    assert np.all(pr.branch[truth.stray] == NO_BRANCH)


def test_branches_and_common_lengths_read_a_chunk_at_a_time(pair, result,  # noqa: ANN001
                                                            monkeypatch) -> None:  # noqa: ANN001
    """The chunked edge assignment is the whole projection's, and the common lengths (1 m bins
    with 20 points of each epoch) are the ones counted over whole projections."""
    from tunneldef.registration import network as reg_network
    from tunneldef.registration.network import common_lengths

    monkeypatch.setattr(reg_network, "_CHUNK", 9_999)

    net, xyz = result.network, pair.ref.xyz
    whole = net.project(xyz, max_distance=5.0)
    np.testing.assert_array_equal(net.branches(xyz, max_distance=5.0, chunk=9_999), whole.branch)
    half = xyz[::2]
    ph = net.project(half, max_distance=5.0)
    got = common_lengths(net, xyz, half)
    for e in net.edges:
        counts = [np.bincount(np.floor(p.chainage[(p.branch == e.id) & p.inside]).astype(int),
                              minlength=int(np.ceil(e.length)) + 1)[:int(np.ceil(e.length)) + 1]
                  for p in (whole, ph)]
        assert got[e.id] == float(np.sum((counts[0] >= 20) & (counts[1] >= 20)))
        assert got[e.id] > 0.8 * e.length


def test_graph_json_ready(result) -> None:  # noqa: ANN001
    d = json.loads(json.dumps(result.network.to_dict(curves=False)))
    assert {"nodes", "edges"} <= set(d)
    assert all(len(n["edges"]) == len(n["chainages_m"]) for n in d["nodes"])


def test_each_edge_reports_its_drift_size(pair, result) -> None:  # noqa: ANN001
    """Every edge of the graph JSON gives its drift's width and height (medians of its fitted
    slices); here within 1 cm of the design sections (4.0 x 3.0 m rectangle, 3.6 x 3.0 m
    arch, 3.5 x 3.0 m rectangle)."""
    d = json.loads(json.dumps(result.network.to_dict(curves=False)))
    truth = pair.truth.ref
    pr = result.network.project(pair.ref.xyz, max_distance=5.0)
    shell = ~truth.stray & (truth.label == 0) & ~pr.junction
    for e in d["edges"]:
        b = pair.truth.branches[int(np.bincount(truth.branch[shell & (pr.branch == e["id"])])
                                    .argmax())]
        assert e["fitted_slices"] >= 10
        assert abs(e["width_m"] - b.spec.section.width) < 0.01, (e, b.spec.section)
        assert abs(e["height_m"] - b.spec.section.height) < 0.01, (e, b.spec.section)


def test_a_far_stray_point_creates_no_edge_and_no_huge_grid() -> None:
    rng = np.random.default_rng(0)
    x = rng.uniform([0, -2, -1.5], [30, 2, 1.5], size=(20000, 3))
    x = np.vstack([x, [[1e6, 5e5, 10.0]]])
    g = plan_grid(x)
    assert not g.keep[-1] and g.keep[:-1].all()
    assert g.footprint.size < 200 * 30 / 0.2**2


def test_drifts_above_one_another_are_refused() -> None:
    rng = np.random.default_rng(1)
    lower = rng.uniform([0, -2, -1.5], [30, 2, 1.5], size=(30000, 3))
    upper = rng.uniform([10, -2, 8.5], [20, 2, 11.5], size=(10000, 3))
    with pytest.raises(NetworkError, match="above one another"):
        plan_grid(np.vstack([lower, upper]))
    assert issubclass(NetworkError, TunnelDefError)


@pytest.mark.slow
@pytest.mark.skipif(not CHAMBER.is_file(), reason="real scan not present")
def test_real_junction_scan() -> None:
    from tunneldef.io import read

    x = read(CHAMBER).xyz
    x = x[np.random.default_rng(0).random(len(x)) < 0.5]
    net = extract_network(x).network
    # a drift about 13 m along y through the junction, a branch of about 5.5 m leaving it;
    # the drift's last 2.5 m widen and heighten into the scan's end (2.0-2.2 m against
    # 1.7 m), so its curve ends 10-11 m along
    assert len(net.edges) == 2 and len(net.junctions) == 1
    main, branch = net.edges
    d = main.centerline.points[-1] - main.centerline.points[0]
    assert 9.5 < main.length < 14.5 and abs(d[1]) > 10 * abs(d[2])
    assert 3.5 < branch.length < 7.0
    j = net.junctions[0]
    # the branch has only 3-4 usable sections: its end tangent, and so the node, moves by up
    # to about 1 m with the thinning and the fit
    assert np.linalg.norm(j.position[:2] - [0.1, -0.5]) < 1.0
    t = branch.centerline.points[-1] - branch.centerline.points[0]
    cos = abs(t[:2] @ d[:2]) / np.linalg.norm(t[:2]) / np.linalg.norm(d[:2])
    angle = np.degrees(np.arccos(cos))
    assert 50 < angle < 80


@pytest.mark.slow
def test_a_single_tube_run_refuses_a_network_at_once(pair, tmp_path, capsys,  # noqa: ANN001
                                                     monkeypatch) -> None:  # noqa: ANN001
    """`detect --single` on a drift network stops before any centreline (a second or two
    here), naming the drifts and junctions it saw and what to run instead; without a choice
    the plan's junctions send it to the network stages."""
    import tunneldef.pipeline as pipeline
    from tunneldef.centerline.skeleton import plan_topology
    from tunneldef.cli import main
    from tunneldef.synth.sampling import write_epochs

    topo = plan_topology(pair.ref.xyz)
    assert topo.junctions == 2 and len(topo.lengths) == 3
    assert topo.lengths[0] > 30.0  # the 40 m main drift, through its crossing
    # asked again of the same array, the answer is remembered; of a copy moved in place, not
    assert plan_topology(pair.ref.xyz) is topo
    moved = pair.ref.xyz.copy()
    assert plan_topology(moved) == topo and plan_topology(moved) is not topo
    moved[:, :2] *= 2.0  # the plan twice as large, in place
    assert plan_topology(moved).lengths[0] > 1.8 * topo.lengths[0]
    paths = write_epochs(pair.ref, pair.cmp, tmp_path, "ply")
    out = tmp_path / "out.ply"
    code = main(["detect", str(paths["ref"]), str(paths["cmp"]), "-o", str(out), "--quiet",
                 "--single"])
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert code == 2 and not out.exists()
    assert "reference_epoch.junctions 2 > limit 0" in line and "--network" in line

    def stub(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise TunnelDefError("the network stages were chosen")

    monkeypatch.setattr(pipeline, "detect_network", stub)
    code = main(["detect", str(paths["ref"]), str(paths["cmp"]), "-o", str(out), "--quiet"])
    assert code == 2 and "the network stages were chosen" in capsys.readouterr().err


def test_detect_network_measures_each_branch(tmp_path) -> None:  # noqa: ANN001
    """Each branch measured on its own edge; the edges' deformation runs in 8 m chainage
    tiles (Dask tasks, as the CLI runs it), which give the untiled values
    (tests/test_tiles.py)."""
    from tunneldef.pipeline import detect_network
    from tunneldef.synth import DeformationSpec
    from tunneldef.synth.network import BranchDeformation
    from tunneldef.transforms import apply_transform

    defs = (BranchDeformation(1, DeformationSpec("wall_bulge", 19.0, 3.0, 1.5, 0.06, "left")),)
    p = make_network_pair(network=small_network(), deformations=defs, ref_coverage=None,
                          cmp_coverage=None, density=100.0, drift=0.0, equipment=False,
                          seed=4, yaw_deg=70.0)
    r = detect_network(p.ref, p.cmp, tiles={"tile_length": 8.0, "workdir": tmp_path})
    err = np.linalg.norm(apply_transform(r.transform, p.cmp.xyz)
                         - apply_transform(p.truth.transform, p.cmp.xyz), axis=1)
    assert np.mean(err) < 0.005
    branch = r.cloud.fields["branch"]
    assert branch.dtype == np.uint16
    d = r.cloud.fields["deformation"]
    core = (p.truth.cmp.branch == 1) & (p.truth.cmp.displacement < -0.04) & np.isfinite(d)
    assert core.sum() > 20
    # measured on the cross-cut's edge, inward, near the truth
    assert len(np.unique(branch[core])) == 1
    assert np.median(d[core]) == pytest.approx(np.median(p.truth.cmp.displacement[core]),
                                               abs=0.015)
    s = json.loads(json.dumps(r.summary(), default=float))
    assert {b["branch"] for b in s["branches"]} == {0, 1, 2}
    assert all(b["common_length_m"] > 0.6 * b["length_m"] for b in s["branches"])
    assert all("branch" in x for x in s["sections"])
    # every edge's centreline in both epochs, the registration and every edge's deformation
    # are checked, and here all pass
    q = s["quality"]
    names = {c["check"] for c in q["checks"]}
    for k in (0, 1, 2):
        assert f"reference_network.edge{k}.curve_uncertainty" in names
        assert f"deformation.edge{k}.significant_share" in names
    assert {"registration.fit_excess", "registration.shared_misfit",
            "registration.translation_residual",
            "registration.translation_convergence"} <= names
    assert q["verified"] is True, q["failed"]
    assert "note" not in r.cloud.meta
    assert s["registration_check"]["spread"] < 0.005  # the cross-cuts fix the plan position


def test_network_registration_check_sees_an_offset(pair) -> None:  # noqa: ANN001
    """The independent check of a network registration: at the true pose nothing is left to
    move and every start ends in one place; 3 cm off along the main drift (where a single
    straight drift would have nothing to hold on to) the cross-cuts' walls find the offset."""
    from tunneldef.config import QualityConfig
    from tunneldef.quality import network_registration_checks
    from tunneldef.registration.verify import verify_network
    from tunneldef.transforms import apply_transform

    moved = apply_transform(pair.truth.transform, pair.cmp.xyz)
    length = float(sum(cl.length for cl in pair.truth.centerlines))
    good = verify_network(pair.ref.xyz, moved, length)
    assert np.linalg.norm(good.remaining) < 0.003 and good.spread < 0.005
    assert all(c.passed for c in network_registration_checks(good, QualityConfig()))
    off = verify_network(pair.ref.xyz, moved + np.array([0.03, 0.0, 0.0]), length)
    assert off.remaining[0] == pytest.approx(-0.03, abs=0.004)
    failed = [c.name for c in network_registration_checks(off, QualityConfig()) if not c.passed]
    assert "registration.translation_residual" in failed
    # the cross-cuts' walls hold the main drift's direction (19 % of the information here),
    # so the refusal says the fit did not converge, not that nothing holds the position
    assert abs(good.weak_direction[0]) > 0.99 and good.weak_share > 0.1
    (residual,) = [c for c in network_registration_checks(off, QualityConfig())
                   if c.name == "registration.translation_residual"]
    assert "did not converge" in residual.advice and "barely fix" not in residual.advice
    assert f"{1000 * (off.remaining @ off.weak_direction):+.1f} mm" in residual.note
    # a plain drift with no shared junction holds it by little more than the normals' noise
    # (2.7 % in a refused sweep case): the refusal says so and names the direction
    plain = dataclasses.replace(off, weak_share=0.027)
    (residual,) = [c for c in network_registration_checks(plain, QualityConfig())
                   if c.name == "registration.translation_residual"]
    assert "barely fix the position along (+1.00, " in residual.advice
    assert "did not converge" not in residual.advice


def test_a_tilted_scan_is_read_level_on_every_edge() -> None:
    """A scan tilted 3 degrees rolls the section of every drift at right angles to the tilt's
    axis: floor and roof slope across it and their density peaks smear over the slope. Each
    edge's roll is read along it and the slices levelled: the centres keep their millimetre
    scatter (they scattered by 4-6 cm p95 unlevelled)."""
    p = make_network_pair(network=small_network(), deformations=(), ref_coverage=None,
                          cmp_coverage=None, density=150.0, drift=0.0, equipment=False,
                          seed=3, noise_sigma=0.01, tilt_deg=3.0, yaw_deg=0.0)
    net = extract_network(p.cmp.xyz).network
    assert len(net.edges) == 3
    for e in net.edges:
        assert e.centerline.meta["centre_scatter_p95_m"] < 0.01, e.id
    # and the curves lie on the true axes, tilted with the scan
    axes = [cl.transformed(np.linalg.inv(p.truth.transform)) for cl in p.truth.centerlines]
    for e in net.edges:
        s = np.arange(2.0, e.length - 2.0, 0.5)
        s = s[~e.in_zone(s)]
        d = np.min([a.project(e.centerline.point_at(s)).distance for a in axes], axis=0)
        assert np.percentile(d, 95) < 0.02, e.id


def test_coherent_misfit_reads_an_offset_the_noise_hides(pair) -> None:  # noqa: ANN001
    """At +-2.5 cm noise a 6 mm offset of the compared floor and roof leaves the
    point-to-plane sigmas as they were (the excess reads 0); the misfit shared by
    neighbouring points reads it, and stays near 0 at the true pose."""
    from tunneldef.registration.verify import verify_network
    from tunneldef.transforms import apply_transform

    p = make_network_pair(network=small_network(), deformations=(), ref_coverage=None,
                          cmp_coverage=None, density=150.0, drift=0.0, equipment=False,
                          seed=3, noise_sigma=0.025)
    moved = apply_transform(p.truth.transform, p.cmp.xyz)
    length = float(sum(cl.length for cl in p.truth.centerlines))
    true = verify_network(p.ref.xyz, moved, length)
    off = verify_network(p.ref.xyz, moved + np.array([0.0, 0.0, 0.006]), length)
    assert off.excess < 0.001
    assert true.coherent < 0.002
    assert off.coherent > true.coherent + 0.001
    assert off.registration_sigma == pytest.approx(off.coherent)


@pytest.mark.slow
def test_drift_correction_lowers_the_residual_and_keeps_a_small_sag() -> None:
    from tunneldef.registration.network import correct_drift, register_networks
    from tunneldef.synth import DeformationSpec
    from tunneldef.synth.network import BranchDeformation
    from tunneldef.transforms import apply_transform

    # a 15 mm roof sag 1 m across, SLAM drift of 5 cm per sqrt(100 m) in each epoch
    defs = (BranchDeformation(0, DeformationSpec("roof_sag", 20.0, 1.0, 1.0, 0.015)),)
    p = make_network_pair(network=small_network(), deformations=defs, ref_coverage=None,
                          cmp_coverage=None, density=200.0, drift=0.05, equipment=False,
                          seed=5, yaw_deg=40.0)
    rn = extract_network(p.ref.xyz).network
    cn = extract_network(p.cmp.xyz).network
    moved = apply_transform(register_networks(p.ref.xyz, p.cmp.xyz, rn, cn).transform,
                            p.cmp.xyz)
    corr, info = correct_drift(p.ref.xyz, moved, rn)
    assert info["used"]
    assert info["residual_rms_after_m"] < info["residual_rms_before_m"] - 0.0005
    # the correction is smooth along the drift: it moves the sag's points as it moves their
    # surroundings, so it cannot take the sag out
    core = p.truth.cmp.displacement < -0.012
    ring = (np.linalg.norm(p.truth.cmp.xyz_ref - p.truth.cmp.xyz_ref[core].mean(axis=0),
                           axis=1) < 4.0) & ~core
    shift = corr - moved
    assert np.linalg.norm(np.median(shift[core], axis=0) - np.median(shift[ring], axis=0)) < 0.002
    # switched off: nothing moves
    off, info_off = correct_drift(p.ref.xyz, moved, rn, min_gain=np.inf)
    assert off is moved and not info_off["used"]


def test_points_without_a_drift_block_take_the_correction_of_their_neighbours() -> None:
    """Points on an edge (or a stretch of one) with too few points for a block of their own,
    such as the main drift's floor at the mouth of a cross-cut only the reference walked,
    take the mean displacement of their nearest corrected neighbours; left uncorrected they
    kept the rigid pose while the drift around them moved (sweep case 17000005: 14 mm of
    false change, 49 % of that edge beyond its LoD95, the survey refused)."""
    from tunneldef.registration.network import _borrow

    rng = np.random.default_rng(1)
    xyz = rng.uniform([0.0, -2.0, -1.5], [60.0, 2.0, 1.5], size=(20_000, 3))
    true = np.column_stack([0.0004 * xyz[:, 0], 0.01 + 0.0002 * xyz[:, 0],
                            np.full(len(xyz), -0.005)])  # smooth along the drift
    known = ~((xyz[:, 0] > 28.0) & (xyz[:, 0] < 32.0))  # a 4 m stretch without a block
    disp = np.where(known[:, None], true, 0.0)
    _borrow(xyz, disp, known, reach=20.0)
    err = np.linalg.norm(disp - true, axis=1)
    assert err[~known].max() < 0.0015  # the field is smooth: 1.6 mm change over 4 m
    assert np.array_equal(disp[known], true[known])
    # nothing within reach: left as it was
    d2 = np.vstack([true[:10], np.zeros((5, 3))])
    _borrow(np.vstack([xyz[:10], [[500.0, 0.0, 0.0]] * 5]), d2,
            np.r_[np.ones(10, bool), np.zeros(5, bool)], reach=20.0)
    assert not d2[10:].any()


@pytest.mark.slow
def test_cli_centerline_network_writes_the_graph(pair, tmp_path) -> None:  # noqa: ANN001
    from tunneldef.cli import main
    from tunneldef.io import read, write

    src = tmp_path / "ref.ply"
    write(src, pair.ref)
    assert main(["centerline", "--network", "--quiet", str(src), "-o",
                 str(tmp_path / "net.json")]) == 0
    graph = json.loads((tmp_path / "net.json").read_text())
    assert len(graph["edges"]) == 3 and len(graph["nodes"]) == 2
    assert all(len(e["centerline"]["points"]) > 10 for e in graph["edges"])
    assert main(["centerline", "--network", "--quiet", str(src), "-o",
                 str(tmp_path / "net.ply")]) == 0
    curve = read(tmp_path / "net.ply")
    assert set(np.unique(curve.fields["edge"])) == {0, 1, 2}


def test_a_corner_is_flagged_like_a_junction_and_a_bend_is_not() -> None:
    from tunneldef.centerline.network import _corners
    from tunneldef.curve import Centerline

    leg = np.linspace(0.0, 20.0, 201)
    ell = np.vstack([np.column_stack([leg, 0 * leg, 0 * leg]),
                     np.column_stack([20.0 + 0 * leg[1:], leg[1:], 0 * leg[1:]])])
    got = _corners(Centerline.from_polyline(ell, step=0.1), 2.0, 0.5)
    assert len(got) == 1
    xyz, half = got[0]
    assert np.linalg.norm(xyz[:2] - [20.0, 0.0]) < 1.0
    assert half == pytest.approx(2.0 + 0.5, abs=0.3)  # hw / sin 90 + margin
    # a 12 m radius bend (a ramp's) and a straight drift turn no corner
    a = np.linspace(0.0, np.pi / 2, 200)
    bend = np.column_stack([12.0 * np.sin(a), 12.0 * (1 - np.cos(a)), 0 * a])
    bend = np.vstack([np.column_stack([leg - 20.0, 0 * leg, 0 * leg])[:-1], bend])
    assert _corners(Centerline.from_polyline(bend, step=0.1), 2.5, 0.5) == []
    assert _corners(Centerline.from_polyline(ell[:201], step=0.1), 2.0, 0.5) == []


def test_a_chamber_at_a_drifts_end_is_no_corner() -> None:
    """A 2 m deep chamber 1.6-5.8 m from where the compared walk starts bends the end of the
    plan's medial axis by 48 degrees, but reaches no farther than a niche: no corner (it was
    one, and a plain drift was refused as a walk round a corner). A corner's legs still count
    when they reach 3 m beyond the other drift's wall."""
    from tunneldef.centerline.skeleton import plan_topology, sharp_turns
    from tunneldef.synth import DeformationSpec, PairSpec, SectionSpec, TunnelSpec, make_pair

    spec = PairSpec(
        tunnel=TunnelSpec(length=26.7, grade=-0.02, section=SectionSpec(
            kind="trapezoid", width=3.47, height=2.32), density=369.5, noise_sigma=0.0293,
            outlier_fraction=0.003, chamber=True, equipment=True, holes=1, roughness=0.0253,
            chamber_depth=2.0, chamber_length=4.0, chamber_side="left"),
        deformations=(DeformationSpec(kind="wall_bulge", chainage=17.8, length=3.0, width=1.0,
                                      amplitude=0.048, side="right"),),
        cmp_shift=9.673, yaw_deg=346.1, tilt_deg=0.75, seed=13000018)
    pair = make_pair(spec)
    assert plan_topology(pair.cmp.xyz).corners == 0
    assert plan_topology(pair.ref.xyz).corners == 0
    # an L: 20 m, then 8 m round the corner (reaching 8 m across); and a hook at an end as the
    # chamber's: 3.5 m across, then 3 m on, which reaches 3.5 m only
    leg = np.linspace(0.0, 1.0, 81)[:, None]
    ell = np.vstack([leg * [20.0, 0.0], [20.0, 0.0] + leg[1:] * [0.0, 8.0]])
    hook = np.vstack([leg * [20.0, 0.0], [20.0, 0.0] + leg[1:] * [0.0, 3.5],
                      [20.0, 3.5] + leg[1:] * [3.0, 0.0]])
    assert len(sharp_turns(ell, 1.8, trim=1.8, min_leg=4.8)) == 1
    assert len(sharp_turns(hook, 1.8, trim=1.8)) == 1
    assert sharp_turns(hook, 1.8, trim=1.8, min_leg=4.8) == []


def test_a_walk_round_a_corner_is_cut_into_its_two_drifts() -> None:
    """The walker goes down the main drift, a few metres past a cross-cut (a stub the skeleton
    prunes) and into the cross-cut: one skeleton edge that turns a right-angle corner. It is
    cut into two edges at a corner node; the slices there are no sections and are flagged,
    and each curve follows its drift."""
    from tunneldef.synth.network import NetworkPairSpec, Stretch

    edges = (
        EdgeSpec("main", ((0.0, 0.0, 0.0), (40.0, 0.0, 0.0)), SectionSpec("rectangle", 4.5, 3.0)),
        EdgeSpec("xc", ((30.0, 0.0, 0.0), (30.0, -20.0, 0.0)), SectionSpec("arch", 4.0, 3.0)),
    )
    net = NetworkSpec(edges, (JunctionSpec("j", (30.0, 0.0, 0.0), (0, 1)),))
    cover = (Stretch(0, 0.0, 33.0), Stretch(1, 0.0, 20.0))
    spec = NetworkPairSpec(net, ref_coverage=cover, cmp_coverage=cover, density=150.0,
                           noise_sigma=0.01, drift=0.0, seed=3)
    pair = make_network_pair(spec)
    # no junction is left, but the corner sends `tunneldef detect` down the network path
    from tunneldef.centerline.skeleton import plan_topology
    from tunneldef.pipeline import is_network

    topo = plan_topology(pair.ref.xyz)
    assert (topo.junctions, topo.corners) == (0, 1)
    assert "turning 1 corner" in topo.describe()
    assert is_network([pair.ref])
    from tunneldef.config import QualityConfig
    from tunneldef.quality import topology_checks

    failed = [c.name for c in topology_checks(topo, QualityConfig(), "reference") if not c.passed]
    assert failed == ["reference_epoch.corners"]  # --single refuses it, naming the corner
    res = extract_network(pair.ref.xyz)
    # the corner cuts the walk into its two drifts, meeting at a node where their axes cross
    net = res.network
    assert len(net.edges) == 2 and len(net.junctions) == 1
    corner = net.junctions[0]
    assert net.meta["corners"] == [corner.id] and sorted(corner.edges) == [0, 1]
    assert np.linalg.norm(corner.position - [30.0, 0.0, 0.0]) < 0.05
    for e, s in zip(corner.edges, corner.chainages, strict=True):
        zone = net.edges[e].zones
        assert any(a <= s <= b for a, b in zone)  # the corner's sections are flagged
    # each curve follows its own drift over its whole length, the node's zone included (one
    # stiff curve round the corner swung about 0.2 m off for some 6 m past its zone)
    for e in net.edges:
        q = e.centerline.point_at(np.arange(0.5, e.length - 0.5, 0.25))
        d = np.min([ax.project(q).distance for ax in pair.truth.centerlines], axis=0)
        assert np.percentile(d, 95) < 0.01 and d.max() < 0.03, (e.id, d.max())
    # an edge left out elsewhere keeps the corner, though only two ends meet there
    from tunneldef.curve import Centerline
    from tunneldef.network import CenterlineNetwork, NetworkEdge

    stub = NetworkEdge(2, "edge-2", Centerline.from_polyline(
        np.array([[0.0, 10.0, 0.0], [6.0, 10.0, 0.0]]), step=0.1), (), (-1, -1), [])
    big = CenterlineNetwork(net.edges + (stub,), net.junctions, net.meta)
    kept = big.without({2: "x"})
    assert len(kept.edges) == 2 and kept.meta["corners"] == [kept.junctions[0].id]
    # and is dropped with one of its drifts
    kept = big.without({1: "x"})
    assert kept.junctions == () and kept.meta["corners"] == []


def test_a_corner_in_one_epoch_registers_onto_a_junction_in_the_other() -> None:
    """The reference walker turns the corner into the cross-cut; the compared one walks on
    down the main drift too (a T junction there). The corner's node and the junction pair up,
    and a sag in the cross-cut is read on its own branch."""
    from tunneldef.pipeline import detect_network
    from tunneldef.synth import DeformationSpec
    from tunneldef.synth.network import BranchDeformation, NetworkPairSpec, Stretch
    from tunneldef.transforms import apply_transform

    edges = (
        EdgeSpec("main", ((0.0, 0.0, 0.0), (45.0, 0.0, 0.0)), SectionSpec("rectangle", 4.5, 3.0)),
        EdgeSpec("xc", ((30.0, 0.0, 0.0), (30.0, -22.0, 0.0)), SectionSpec("arch", 4.0, 3.0)),
    )
    net = NetworkSpec(edges, (JunctionSpec("j", (30.0, 0.0, 0.0), (0, 1)),))
    defs = (BranchDeformation(1, DeformationSpec("roof_sag", 14.0, 2.0, 1.0, 0.03)),)
    spec = NetworkPairSpec(net, ref_coverage=(Stretch(0, 0.0, 33.0), Stretch(1, 0.0, 22.0)),
                           cmp_coverage=(Stretch(0, 0.0, 45.0), Stretch(1, 0.0, 22.0)),
                           density=150.0, noise_sigma=0.015, drift=0.0, seed=3,
                           deformations=defs, yaw_deg=60.0)
    p = make_network_pair(spec)
    r = detect_network(p.ref, p.cmp)
    assert r.ref_network.meta["corners"] == [0] and len(r.ref_network.edges) == 2
    assert r.registration.junction_pairs == [(0, 0)]  # the corner's node on the T's junction
    err = np.linalg.norm(apply_transform(r.transform, p.cmp.xyz)
                         - apply_transform(p.truth.transform, p.cmp.xyz), axis=1)
    assert np.mean(err) < 0.003
    d = r.cloud.fields["deformation"]
    core = (p.truth.cmp.branch == 1) & (p.truth.cmp.displacement < -0.024) & np.isfinite(d)
    assert core.sum() > 10
    assert len(np.unique(r.cloud.fields["branch"][core])) == 1
    assert np.median(d[core]) == pytest.approx(np.median(p.truth.cmp.displacement[core]),
                                               abs=0.008)
    stable = (np.abs(p.truth.cmp.displacement) < 1e-4) & np.isfinite(d)
    assert np.mean(np.abs(d[stable]) > 0.01) < 0.005


def test_the_mouths_of_a_crossing_nobody_walked_into_do_not_pull_the_curve() -> None:
    """The walker passes an oblique crossing without looking in: both walls of the main drift
    have a hole there, and those slices' walls come from the section's extent, 3-5 cm off.
    Wall lines on either side bracket them closely, so the curve bridges them instead."""
    from tunneldef.centerline.network import EXTENT_WALLS
    from tunneldef.synth.network import NetworkPairSpec, Stretch

    ang = np.radians(55.0)
    reach = 12.0 * np.array([np.cos(ang), np.sin(ang), 0.0])
    edges = (
        EdgeSpec("main", ((0.0, 0.0, 0.0), (50.0, 0.0, 0.0)), SectionSpec("rectangle", 5.5, 3.0)),
        EdgeSpec("xc", (tuple([25.0, 0.0, 0.0] - reach), tuple([25.0, 0.0, 0.0] + reach)),
                 SectionSpec("rectangle", 4.5, 3.0)),
    )
    net = NetworkSpec(edges, (JunctionSpec("x", (25.0, 0.0, 0.0), (0, 1)),))
    cover = (Stretch(0, 0.0, 50.0),)
    pair = make_network_pair(NetworkPairSpec(net, ref_coverage=cover, cmp_coverage=cover,
                                             density=150.0, noise_sigma=0.02, drift=0.0, seed=2))
    edge = extract_network(pair.ref.xyz).network.edges[0]
    extent = [r for r in edge.slices if r.methods.get("left") == EXTENT_WALLS]
    assert len(extent) >= 5 and not any(r.ok for r in extent)
    assert all("bridged" in r.reason for r in extent)
    cl = edge.centerline
    q = cl.point_at(np.arange(2.0, cl.length - 2.0, 0.25))
    d = pair.truth.centerlines[0].project(q).distance
    assert np.percentile(d[np.abs(q[:, 0] - 25.0) < 9.0], 95) < 0.01  # 4.8 cm before


def test_a_stub_whose_curve_ends_short_of_its_junction_is_a_dead_end() -> None:
    """A cross-cut seen a few metres in keeps a curve over its readable slices only, which
    can end metres short of the junction it leaves (no node there): it is still a dead end,
    and so may be left out when it fails its checks; a main drift with a junction along it
    is not."""
    from tunneldef.curve import Centerline
    from tunneldef.network import CenterlineNetwork, Junction, NetworkEdge

    def line(a, b):  # noqa: ANN001, ANN202
        return Centerline.from_polyline(np.array([a, b], dtype=float), step=0.25)

    main = NetworkEdge(0, "edge-0", line((0, 0, 0), (40, 0, 0)))
    stub = NetworkEdge(1, "edge-1", line((20, 4.7, 0), (20, 6.2, 0)))  # 1.5 m, 4.7 m away
    tee = NetworkEdge(2, "edge-2", line((30, 0, 0), (30, 10, 0)), nodes=(1, -1))
    net = CenterlineNetwork((main, stub, tee), (
        Junction(0, np.array([20.0, 0, 0]), (0, 1), (20.0, -4.7)),
        Junction(1, np.array([30.0, 0, 0]), (0, 2), (30.0, 0.0)),
    ), {})
    assert [net.is_dead_end(k) for k in range(3)] == [False, True, True]
    # a junction in the middle of an edge hangs something on it: no dead end
    mid = CenterlineNetwork((main, stub), (Junction(0, np.array([20.0, 5.4, 0]), (0, 1),
                                                    (20.0, 0.7)),), {})
    assert mid.is_dead_end(1) is True  # within END_REACH of its start
    inner = CenterlineNetwork((main, stub), (Junction(0, np.array([20.0, 5.4, 0]), (0, 1),
                                                      (20.0, 0.75)),
                                             Junction(1, np.array([20.0, 6.2, 0]), (1,),
                                                      (1.5,))), {})
    assert inner.is_dead_end(1) is False  # left from both ends
    assert net.without({1: "unreadable"}).meta["left_out"][0]["edge"] == "edge-1"


def test_a_drift_split_at_a_junction_does_not_take_its_own_continuation_for_a_branch() -> None:
    """Zones at a junction where the skeleton split a straight drift into two edges: each leg's
    zone is set by the cross-cut, not by the other leg, even when both legs' chords bend into
    the cross-cut's fork (27 degrees between them, as in sweep case 19000003, where glancing-
    angle zones of 11.8 m covered the 18 m between two junctions and the survey was refused)."""
    from tunneldef.centerline.network import _Edge, _zones
    from tunneldef.curve import Centerline

    def line(a, b):
        return Centerline.from_polyline(np.array([a, b], dtype=float), step=0.1)

    skew = np.radians(13.5)  # each leg's chord bent towards the fork
    node = np.zeros(3)
    legs = [line([-20.0 * np.cos(skew), 20.0 * np.sin(skew), 0.0], node),  # ends at the node
            line(node, [20.0 * np.cos(skew), 20.0 * np.sin(skew), 0.0])]  # starts there
    xc = line(node, [10.0 * np.cos(np.radians(58)), 10.0 * np.sin(np.radians(58)), 0.0])
    curves = [*legs, xc]
    hw = (2.7, 2.7, 2.15)
    edges = [_Edge(np.zeros((0, 2)), [], [], c, h, 0.0) for c, h in zip(curves, hw, strict=True)]
    zones = _zones(edges, {0: node}, curves, {0: [0, 1, 2]}, 0.5)
    for k, s in ((0, 20.0), (1, 0.0)):
        (a, b), = zones[k]
        half = 0.5 * (b - a)
        assert a <= s <= b
        # the cross-cut meets each leg at 44.5-71.5 degrees: at most 2.15 / sin 44.5 +
        # 2.7 cos 44.5 / sin 44.5 + 0.5 = 6.3 m (the other leg at 153 degrees gave 11.8 m)
        assert half < 6.5, half
    # a glancing branch (leaving the node the same way as a leg) still widens that leg's zone
    glance = line(node, [20.0 * np.cos(np.radians(25)), 20.0 * np.sin(np.radians(25)), 0.0])
    edges.append(_Edge(np.zeros((0, 2)), [], [], glance, 2.15, 0.0))
    zones = _zones(edges, {0: node}, [*curves, glance], {0: [0, 1, 2, 3]}, 0.5)
    (a, b), = zones[1]
    assert 0.5 * (b - a) > 8.0


def test_a_crossing_edge_with_a_few_centres_either_side_of_its_junction_keeps_a_line() -> None:
    """Sweep case 20000005: an oblique crossing's edge had 5 usable centres, 2 and 3 either
    side of a 15 m junction zone; a cubic through them was 45.8 m long for 18.6 m of centres,
    and the whole network was refused as having stray points. So few, so gappy centres now
    give the edge the axis moved onto them; their scatter about it is still checked."""
    from tunneldef.centerline.extract import SliceRecord
    from tunneldef.centerline.network import _fit_edge
    from tunneldef.config import CenterlineConfig
    from tunneldef.curve import Centerline

    centres = np.array([[46.454, 5.746, 0.043], [47.229, 4.892, 0.041], [56.105, -5.152, 0.045],
                        [56.769, -5.9, 0.04], [58.999, -7.95, 0.039]])
    way = (centres[-1] - centres[0]) / np.linalg.norm(centres[-1] - centres[0])
    start = centres[0] - 1.4 * way + np.array([0.3, 0.3, 0.0])  # the skeleton's: 0.4 m off
    axis = Centerline.from_polyline(start + np.linspace(0.0, 21.0, 50)[:, None] * way)
    records = [SliceRecord(station=float(s), centre=c, ok=True)
               for s, c in zip([1.4, 2.4, 17.4, 18.4, 21.4], centres, strict=True)]
    records += [SliceRecord(station=float(s), reason="junction") for s in range(4, 17)]
    curve = _fit_edge(records, CenterlineConfig(), "edge 3", axis)
    assert curve.meta["method"] == "axis_offset" and curve.meta["sparse_centres"]
    assert not curve.meta.get("short_branch")  # so the scatter check applies
    assert curve.length == pytest.approx(20.0, abs=0.5)
    # the axis moved by the centres' median offset: through the middle of them, parallel
    dist = curve.project(centres).distance
    assert np.median(dist) < 0.01 and dist.max() < 0.3
    chord = curve.points[-1] - curve.points[0]
    assert abs(chord @ way) / np.linalg.norm(chord) > 0.9999


def test_a_drift_going_on_as_a_narrower_ramp_is_cut_at_its_change_of_section() -> None:
    """A 5.6 m rectangle goes on as a 4.0 m trapezoid ramp, its centre 10 cm lower, with no
    junction there. One curve through the step in its centres rang 4-6 cm about it for 10 m;
    the change of section now cuts the walk into two drifts at a node, and each curve follows
    its own drift."""
    from tunneldef.synth.network import NetworkPairSpec, Stretch

    main = SectionSpec("rectangle", 5.6, 2.8)
    ramp = SectionSpec("trapezoid", 4.0, 2.6)
    z = -1.4 + 1.3
    edges = (
        EdgeSpec("main", ((0.0, 0.0, 0.0), (45.0, 0.0, 0.0)), main),
        EdgeSpec("ramp", ((45.0, 0.0, z), (51.0, 0.0, z), (80.0, 0.0, z + 3.5)), ramp,
                 bend_radius=20.0),
    )
    net = NetworkSpec(edges, (JunctionSpec("portal", (45.0, 0.0, 0.0), (0, 1)),))
    cover = (Stretch(0, 0.0, None), Stretch(1, 0.0, None))
    spec = NetworkPairSpec(net, ref_coverage=cover, cmp_coverage=cover, density=150.0,
                           noise_sigma=0.01, drift=0.0, stray_distance=0.0, seed=5)
    pair = make_network_pair(spec)
    res = extract_network(pair.ref.xyz)
    net = res.network
    assert len(net.edges) == 2 and len(net.junctions) == 1
    node = net.junctions[0]
    assert abs(node.position[0] - 45.0) < 1.5 and abs(node.position[1]) < 0.3
    for e in net.edges:
        s = np.arange(2.0, e.length - 2.0, 0.25)
        for a, b in e.zones:
            s = s[(s < a - 2.0) | (s > b + 2.0)]
        d = np.min([ax.project(e.centerline.point_at(s)).distance
                    for ax in pair.truth.centerlines], axis=0)
        assert np.percentile(d, 95) < 0.02, (e.id, np.percentile(d, 95))
    # a straight drift of one section is not cut, a short chamber in it neither
    from tunneldef.synth import PairSpec, TunnelSpec, make_pair

    one = make_pair(PairSpec(TunnelSpec(length=60.0, chamber=True, density=150.0), seed=3))
    assert len(extract_network(one.ref.xyz).network.edges) == 1


def test_a_gappy_edge_with_centres_off_its_line_keeps_the_line_most_lie_on() -> None:
    """Sweep case 57000010: an edge crossed by another drift had 10 usable centres, 3 at one
    end scattered by 0.5-2 m and 7 on a line 15 m on; a cubic through them was 554.8 m long
    and the whole network was refused. The skeleton's axis ran 9 degrees off the 7, so the
    edge now keeps the straight line that most of its centres lie on; with no such line, the
    implausible curve is refused as before."""
    from tunneldef.centerline.extract import SliceRecord
    from tunneldef.centerline.network import _fit_edge, _on_line
    from tunneldef.config import CenterlineConfig
    from tunneldef.curve import Centerline

    centres = np.array([
        [-0.302, -0.027, 0.251], [-1.712, -1.336, 0.252], [-0.207, -2.173, 0.22],
        [10.21, -10.609, -0.006], [10.587, -10.946, -0.018], [10.976, -11.275, -0.021],
        [11.356, -11.61, -0.036], [11.741, -11.942, -0.045], [12.123, -12.275, -0.053],
        [12.494, -12.619, -0.06]])
    stations = [-0.796, 0.204, 1.204, 16.204, 16.704, 17.204, 17.704, 18.204, 18.704, 19.204]
    way = (centres[-1] - centres[3]) / np.linalg.norm(centres[-1] - centres[3])
    turn = np.radians(9.0)
    skew = np.array([way[0] * np.cos(turn) - way[1] * np.sin(turn),
                     way[0] * np.sin(turn) + way[1] * np.cos(turn), 0.0])
    axis = Centerline.from_polyline(centres[3] - 17.0 * way + np.linspace(0.0, 20.0, 60)[:, None]
                                    * skew)

    def records(xyz: np.ndarray) -> list:
        out = [SliceRecord(station=float(s), centre=c, ok=True)
               for s, c in zip(stations, xyz, strict=True)]
        return out + [SliceRecord(station=float(s), reason="junction") for s in range(2, 16)]

    curve = _fit_edge(records(centres), CenterlineConfig(), "edge 1", axis)
    assert curve.meta["method"] == "line" and curve.meta["n_on_line"] == 7
    assert not curve.meta.get("short_branch")  # so the scatter check sees every centre
    assert curve.length == pytest.approx(20.0, abs=0.3)
    dist = curve.project(centres).distance
    assert dist[3:].max() < 0.02 and dist[:3].min() > 0.4
    # centres on no common line: none (and the implausible curve is refused, as before)
    rng = np.random.default_rng(0)
    scattered = centres + rng.normal(0.0, 0.3, centres.shape)
    assert _on_line(records(scattered)[:10], 24, CenterlineConfig()) is None
