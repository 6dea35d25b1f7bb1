"""Robust signed deformation (tunneldef.deformation.local_surface) against synthetic truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.special import ndtri

from tunneldef.deformation import local_surface
from tunneldef.deformation.cylinders import _INNER_TRIM
from tunneldef.deformation.local_surface import (
    CylinderPass,
    RobustDeformation,
    robust_deformation,
    voxel_cores,
)
from tunneldef.errors import ConfigError, InvalidCloudError
from tunneldef.synth import DeformationSpec, PairSpec, SectionSpec, TunnelSpec, make_pair

LENGTH = 12.0
SAG = 0.015  # the paper's Table 5 roof deformation, m


def _pair(*, noise: float = 0.015, deformations=(), seed: int = 3, length=LENGTH, **tunnel):
    spec = PairSpec(
        tunnel=TunnelSpec(length=length, noise_sigma=noise, **tunnel),
        deformations=tuple(deformations),
        cmp_shift=0.0,
        seed=seed,
    )
    return make_pair(spec)


def _run(pair, **kw) -> RobustDeformation:
    tr = pair.truth
    return robust_deformation(pair.ref.xyz, tr.cmp_xyz_in_ref, tr.centerline, **kw)


@pytest.fixture(scope="module")
def sag_pair():
    return _pair(deformations=[DeformationSpec(kind="roof_sag", chainage=6.0, amplitude=SAG)])


@pytest.fixture(scope="module")
def sag_result(sag_pair):
    return _run(sag_pair)


def _unchanged(tr) -> np.ndarray:
    inner = (tr.chainage > 0.5) & (tr.chainage < LENGTH - 0.5)
    return (tr.label == 0) & (tr.displacement == 0.0) & inner


def test_noise_floor_on_unchanged_shell(sag_pair, sag_result):
    # sigma 1.5 cm per axis, 400 points/m2, perfect registration: the paper's KNN distance
    # reports ~27 mm here; the cylinder means must stay at the millimetre level
    tr = sag_pair.truth
    d = np.abs(sag_result.deformation[_unchanged(tr)])
    # a few cylinders without support (the two epochs cover different parts of them) are NaN
    ok = np.isfinite(d)
    assert ok.mean() >= 0.98
    d = d[ok]
    assert d.mean() <= 0.0033  # target 3 mm, +10 % for the small sample
    assert np.percentile(d, 95) <= 0.008
    assert np.mean(d > 0.010) <= 0.006  # false alarms at a 10 mm threshold
    # unbiased: the mean signed value over the unchanged shell is far below the noise
    assert abs(np.nanmean(sag_result.deformation[_unchanged(tr)])) < 0.0005


def test_sag_peak_and_detection(sag_pair, sag_result):
    tr = sag_pair.truth
    d = sag_result.deformation
    shell = tr.label == 0
    centre = np.argmin(np.where(shell, tr.displacement, np.inf))
    disc = shell & (np.linalg.norm(tr.cmp_xyz_in_ref - tr.cmp_xyz_in_ref[centre], axis=1) < 0.3)
    # peak: the median over a 0.3 m disc at the sag's centre, within 2 mm of the truth there
    assert np.median(d[disc]) == pytest.approx(np.median(tr.displacement[disc]), abs=0.002)
    core = shell & (tr.displacement <= -0.8 * SAG)
    assert np.mean(d[core] < -0.010) >= 0.9  # recall at a 10 mm threshold in the sag core
    half = shell & (tr.displacement <= -0.5 * SAG)
    # the half-amplitude patch holds ~650 points per epoch: its mean alone has a standard error
    # of 15 mm * sqrt(2 / 650) = 0.8 mm, so 2 mm is about 2.5 of them
    assert np.mean(d[half]) == pytest.approx(np.mean(tr.displacement[half]), abs=0.002)
    assert sag_result.significant[core].mean() >= 0.9


def test_sign_on_roof_walls_and_floor():
    a = 0.03
    pair = _pair(
        deformations=[
            DeformationSpec(kind="roof_sag", chainage=2.5, amplitude=a),
            DeformationSpec(kind="wall_bulge", chainage=6.0, amplitude=a, side="left"),
            DeformationSpec(kind="wall_bulge", chainage=6.0, amplitude=-a, side="right"),
            DeformationSpec(kind="floor_heave", chainage=9.5, amplitude=a),
        ],
        seed=4,
    )
    tr = pair.truth
    r = _run(pair)
    shell = tr.label == 0
    patch = shell & (np.abs(tr.displacement) >= 0.5 * a)
    for surface, sign in ((0, -1), (1, -1), (2, 1), (3, -1)):  # right wall moved outward
        m = patch & (tr.surface == surface)
        assert m.sum() > 200
        assert np.sign(np.median(r.deformation[m])) == sign
        # a few cores' noise (~3 mm each) on a patch of ~1 m2: 4 mm
        assert np.median(r.deformation[m]) == pytest.approx(
            np.median(tr.displacement[m]), abs=0.004
        )
    # normals point away from the centreline
    roof = shell & (tr.surface == 0)
    assert np.median(r.normal[roof, 2]) > 0.99
    floor = shell & (tr.surface == 3)
    assert np.median(r.normal[floor, 2]) < -0.99



@pytest.mark.parametrize("seed", [1, 2])
def test_a_bulge_wrapped_round_the_wall_floor_edge_reads_at_full_size(seed):
    """A horseshoe's walls meet its floor within 0.15 m of mid-wall, so a wall bulge there
    wraps round the edge. The cores within a normal radius of the edge straddle wall and floor
    at that radius; they are fitted again on a smaller ball, and their points read the bulge
    on their own cylinders rather than borrowing the value of cores 0.3 m or more away (which
    read it at 72-80 % of its size, and a wider one at a third)."""
    a = 0.04
    spec = PairSpec(
        tunnel=TunnelSpec(
            length=LENGTH, noise_sigma=0.012, section=SectionSpec("horseshoe", 5.9, 3.1)
        ),
        deformations=(DeformationSpec(kind="wall_bulge", chainage=6.0, length=3.0, width=2.0,
                                      amplitude=a),),
        cmp_shift=0.0,
        seed=seed,
    )
    pair = make_pair(spec)
    tr = pair.truth
    r = _run(pair)
    assert r.meta["edge_cores"] > 100
    shell = tr.label == 0
    core = shell & (tr.displacement <= -0.8 * a)
    assert core.sum() > 100 and np.isfinite(r.deformation[core]).all()
    true = np.median(tr.displacement[core])
    # ~170 points of ~8 cores, each with ~2 mm noise: within 15 % (6 mm) of the truth
    assert np.median(r.deformation[core]) == pytest.approx(true, rel=0.15)
    # and the unchanged shell stays quiet, its edges included
    quiet = shell & (tr.displacement == 0.0) & (tr.chainage > 0.5) & (tr.chainage < LENGTH - 0.5)
    d = np.abs(r.deformation[quiet])
    assert np.mean(d[np.isfinite(d)] > 0.010) <= 0.005


def test_a_wrapped_bulge_on_a_sparse_scan_is_not_pooled_away():
    """At 222 points/m^2 the cores are pooled with their neighbours on the surface; next to
    the wall-floor edge those are unchanged rock, and the pooled bulge fell below the gate
    that reads a clear change on the core's own cylinder (seed 3: -15.3 of a true -36.1 mm).
    A core whose own cylinder clears the gate by its own noise is read there."""
    a = 0.0514
    spec = PairSpec(
        tunnel=TunnelSpec(
            length=LENGTH, noise_sigma=0.011, density=222.0,
            section=SectionSpec("horseshoe", 5.9, 3.1),
        ),
        deformations=(DeformationSpec(kind="wall_bulge", chainage=6.0, length=3.6, width=1.46,
                                      amplitude=a, side="right"),),
        cmp_shift=0.0,
        seed=3,
    )
    pair = make_pair(spec)
    tr = pair.truth
    r = _run(pair)
    core = (tr.label == 0) & (tr.displacement <= -0.5 * a)
    true = np.median(tr.displacement[core])
    # seeds 1-3 read 73-87 % (pooling still smooths the cores below the gate)
    assert np.nanmedian(r.deformation[core]) <= 0.65 * true
    quiet = (tr.label == 0) & (tr.displacement == 0.0)
    quiet &= (tr.chainage > 0.5) & (tr.chainage < LENGTH - 0.5)
    d = np.abs(r.deformation[quiet])
    assert np.mean(d[np.isfinite(d)] > 0.010) <= 0.005

@pytest.mark.parametrize("seed", [1, 2])
def test_a_bulge_behind_pipes_is_not_read_from_a_plane_that_does_not_pass_there(seed):
    """Pipes cover the lower left wall of an arch from 0.1 to 0.9 m up; the wall behind them
    is seen through gaps (80 % shadowed), and each cylinder there holds the pipes and the
    rock, so its own core gives no value. Those points took the value of the planar core
    whose plane passed closest to them, however far: a floor core 0.65 m below. A 41 mm
    bulge there read -5 and +6 mm against a true -38 and -36 mm, with a LoD95 of 10-12 mm:
    confident and wrong. A plane that does not pass within 0.1 m of a point (as the
    interpolation between cores already asks) is not its surface: no value there."""
    a = 0.041
    length = 20.0
    bulge = DeformationSpec(kind="wall_bulge", chainage=10.0, length=3.0, width=1.2, amplitude=a)
    pair = _pair(noise=0.018, deformations=[bulge], seed=seed, length=length, density=204.0,
                 equipment=True, section=SectionSpec("arch", 4.7, 2.5))
    tr = pair.truth
    r = _run(pair)
    cmp_ = tr.cmp_xyz_in_ref
    shell = tr.label == 0
    core = shell & (tr.displacement <= -0.8 * a)
    assert core.sum() >= 20
    d, lod, true = r.deformation[core], r.lod95[core], tr.displacement[core]
    read = np.isfinite(d)
    # what is read is right within its LoD95 (before: every read point 30-40 mm off)
    assert np.all(np.abs(d[read] - true[read]) <= lod[read])
    # every value comes from a core whose plane passes within 0.1 m of the point
    fin = np.flatnonzero(np.isfinite(r.deformation))
    c = r.core[fin]
    off = np.abs(np.einsum("ij,ij->i", cmp_[fin] - r.core_xyz[c], r.core_normal[c]))
    assert np.quantile(off, 0.999) <= 0.1  # before: 0.62 m
    # at the cost of the wall behind the pipes only: the unchanged shell keeps its values
    quiet = shell & (tr.displacement == 0.0) & (tr.chainage > 0.5) & (tr.chainage < length - 0.5)
    dq = r.deformation[quiet]
    assert np.isnan(dq).mean() <= 0.05  # 3.3-3.5 %; 0.8 % before, 1.4 % without pipes
    assert np.mean(np.abs(dq[np.isfinite(dq)]) > 0.010) <= 0.01


def test_lod_grows_with_noise():
    # the plain cylinder means (pooling, which lowers a sparse scan's LoD, is checked below)
    quiet_pair = _pair(noise=0.005, seed=5, length=5.0)
    quiet = _run(quiet_pair, pool=False)
    noisy_pair = _pair(noise=0.03, seed=5, length=5.0)
    noisy = _run(noisy_pair, pool=False)
    lq, ln = np.nanmedian(quiet.lod95), np.nanmedian(noisy.lod95)
    assert ln > 4.0 * lq
    # LoD95 ~ 1.96 sigma sqrt(2 / n) with ~50 points per epoch in a 0.2 m cylinder
    n = np.nanmedian(noisy.n_ref)
    assert ln == pytest.approx(1.96 * 0.03 * np.sqrt(2.0 / n), rel=0.35)
    # the registration uncertainty adds 1.96 sigma_reg
    reg = _run(quiet_pair, registration_sigma=0.004)
    assert np.nanmedian(reg.lod95) == pytest.approx(lq + 1.96 * 0.004, abs=0.0005)
    # pooled, the noisy scan's LoD is lower and still honest: nothing moved, so about 5 % of
    # the shell at most may exceed it. Neighbouring points share their cores' errors, so one
    # 5 m pair is a small sample of the level (single seeds read 3.0-5.0 %, ten seeds 3.8 %):
    # three pairs are judged together
    pooled = _run(noisy_pair)
    assert pooled.meta["pooled_cores"] > 0.5 * pooled.meta["cores"]
    assert 0.5 * ln < np.nanmedian(pooled.lod95) < 0.9 * ln
    beyond, total = 0, 0
    for seed, res in ((5, pooled), (6, None), (7, None)):
        pair = noisy_pair if res is not None else _pair(noise=0.03, seed=seed, length=5.0)
        res = res if res is not None else _run(pair)
        shell = (pair.truth.label == 0) & np.isfinite(res.deformation)
        beyond += int(res.significant[shell].sum())
        total += int(shell.sum())
    assert beyond / total <= 0.05


def _brute_core(ref, cmp_, res, q, *, ref_core, cmp_core, max_depth=0.3, radius_c=0.2):
    """Plain NumPy cylinder statistics of core q (float32 offsets as in the fast path)."""
    c = res.core_xyz[q]
    n = res.core_normal[q]
    r = res.core_radius[q]
    out = []
    for pts, owner, depth in (
        (ref, ref_core, res.core_ref_depth[q]),
        (cmp_, cmp_core, min(max_depth, radius_c)),
    ):
        origin = ref.mean(axis=0)
        off = (pts - origin).astype(np.float32) - (c - origin).astype(np.float32)
        n32 = n.astype(np.float32)
        a = np.einsum("ij,j->i", off, n32)
        lat2 = np.einsum("ij,ij->i", off, off) - a * a
        same = np.einsum("ij,j->i", res.core_normal[owner].astype(np.float32), n32)
        inside = (lat2 <= r * r) & (np.abs(a) <= depth) & (same >= np.cos(np.radians(35.0)))
        v = a[inside].astype(np.float64)
        keep = np.abs(v - v.mean()) <= max(3 * v.std(ddof=1), 0.005)
        mu, sd = v[keep].mean(), v[keep].std(ddof=1)
        keep = np.abs(v - mu) <= max(3 * sd, 0.005)
        if _INNER_TRIM > 0:
            keep &= v - mu >= -ndtri(1.0 - _INNER_TRIM) * sd  # the innermost points
        mu2, sd2 = v[keep].mean(), v[keep].std(ddof=1)
        keep &= np.abs(v - mu2) <= max(3 * sd2, 0.005)
        out.append((v[keep].mean(), int(keep.sum())))
    return out[1][0] - out[0][0], out[0][1], out[1][1]


def test_vectorised_path_matches_numpy_reference():
    pair = _pair(
        deformations=[DeformationSpec(kind="roof_sag", chainage=6.0, amplitude=0.03)], seed=6
    )
    ref, cmp_ = pair.ref.xyz, pair.truth.cmp_xyz_in_ref
    res = _run(pair, pool=False)  # the cylinder means themselves (pooling mixes cores)
    # owner core of every point: the nearest core for reference points, the voxel's core for
    # compared points (their normals decide which points belong to a core's surface)
    _, ref_core = cKDTree(res.core_xyz).query(ref)
    _, cmp_core = voxel_cores(cmp_ - ref.mean(axis=0), res.meta["core_spacing"])
    rng = np.random.default_rng(0)
    for i in rng.choice(np.flatnonzero(np.isfinite(res.deformation)), 12, replace=False):
        d, nr, nc = _brute_core(ref, cmp_, res, res.core[i], ref_core=ref_core, cmp_core=cmp_core)
        assert (res.n_ref[i], res.n_cmp[i]) == (nr, nc)
        assert res.core_deformation[res.core[i]] == pytest.approx(d, abs=1e-7)
    # each point's value interpolates the cores around it: a convex combination of the cores
    # within 1.5 core spacings (its own included)
    tree = cKDTree(res.core_xyz)
    for i in rng.choice(np.flatnonzero(np.isfinite(res.deformation)), 200, replace=False):
        near = tree.query_ball_point(cmp_[i], 1.5 * res.meta["core_spacing"]) + [res.core[i]]
        vals = res.core_deformation[near]
        vals = vals[np.isfinite(vals)]
        assert vals.min() - 1e-12 <= res.deformation[i] <= vals.max() + 1e-12


def test_every_point_gets_a_value_where_reference_exists():
    pair = make_pair(
        PairSpec(
            tunnel=TunnelSpec(length=LENGTH, equipment=True, conveyor=True),
            cmp_shift=3.0,
            seed=7,
        )
    )
    tr = pair.truth
    r = _run(pair)
    assert r.deformation.shape == (len(pair.cmp),)
    overlap = tr.chainage < LENGTH - 0.6
    beyond = tr.chainage > LENGTH + 0.8
    # shell, equipment and coal all get a value, but for stray points in mid-air (label 3),
    # without a reference surface within max_depth, and a few cylinders without support
    # (flagged: the epochs cover different parts of them, or no single surface)
    got = np.isfinite(r.deformation) | r.unsupported
    assert got[overlap & (tr.label != 3)].all()
    assert r.unsupported[overlap & (tr.label == 0)].mean() < 0.02
    assert np.isnan(r.deformation[beyond & (tr.label == 0)]).mean() > 0.95
    assert np.array_equal(np.isnan(r.lod95), np.isnan(r.deformation))
    assert not r.significant[np.isnan(r.deformation)].any()


@pytest.mark.parametrize("masked", [False, True])
def test_resuming_from_a_saved_cylinder_pass_gives_the_same_values(tmp_path, masked):
    """A tile's measuring pass resumes from its spreads pass (saved to disk in between):
    every field, core value and count is the one a single call gives, bit for bit; a state
    computed on other points is refused."""
    pair = _pair(seed=4, deformations=[DeformationSpec(kind="roof_sag", chainage=6.0,
                                                       amplitude=0.03)], equipment=True)
    ref, cmp_ = pair.ref.xyz, pair.truth.cmp_xyz_in_ref
    kw: dict = {"registration_sigma": 0.002}
    if masked:  # masks and a measured subset, as the tiles give them
        rng = np.random.default_rng(0)
        kw |= {"ref_mask": rng.random(len(ref)) < 0.9, "cmp_mask": rng.random(len(cmp_)) < 0.9,
               "measure": rng.random(len(cmp_)) < 0.8}
    whole = _run(pair, **kw)
    state = _run(pair, spreads_only=True, **kw)
    assert isinstance(state, CylinderPass)
    state.save(str(tmp_path / "c.npz"))
    loaded = CylinderPass.load(str(tmp_path / "c.npz"))
    np.testing.assert_array_equal(loaded.spread_ref, state.spread_ref)
    resumed = _run(pair, resume=loaded, **kw)
    fresh = CylinderPass.load(str(tmp_path / "c.npz"))  # resuming leaves the state as it was
    for key, v in fresh.out.items():
        np.testing.assert_array_equal(loaded.out[key], v, key)
    np.testing.assert_array_equal(loaded.variation, fresh.variation)
    np.testing.assert_array_equal(loaded.radius_used, fresh.radius_used)
    for name in ("deformation", "lod95", "significant", "normal", "n_ref", "n_cmp",
                 "sigma_ref", "sigma_cmp", "core", "core_deformation", "core_lod95",
                 "core_radius", "core_ref_depth"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(whole, name), name)
    assert resumed.meta == whole.meta
    assert whole.meta["wide_cylinder_cores"] > 0  # the resumed pass built its indexes again
    with pytest.raises(ValueError, match="saved cylinder pass"):
        robust_deformation(ref[:-10], cmp_, pair.truth.centerline, resume=loaded,
                           **{k: v for k, v in kw.items() if k != "ref_mask"})


def test_errors():
    pair = _pair(seed=8)
    ref, cmp_, line = pair.ref.xyz, pair.truth.cmp_xyz_in_ref, pair.truth.centerline
    with pytest.raises(ConfigError, match="cylinder_radius"):
        robust_deformation(ref, cmp_, line, cylinder_radius=0.0)
    with pytest.raises(ConfigError, match="max_depth"):
        robust_deformation(ref, cmp_, line, max_depth=-1.0)
    with pytest.raises(ConfigError, match="registration_sigma"):
        robust_deformation(ref, cmp_, line, registration_sigma=float("nan"))
    with pytest.raises(ConfigError, match="min_points"):
        robust_deformation(ref, cmp_, line, min_points=0)
    with pytest.raises(InvalidCloudError, match="N x 3"):
        robust_deformation(ref[:, :2], cmp_, line)
    with pytest.raises(InvalidCloudError, match="NaN"):
        bad = cmp_.copy()
        bad[3, 1] = np.nan
        robust_deformation(ref, bad, line)
    with pytest.raises(InvalidCloudError, match="ref_mask"):
        robust_deformation(ref, cmp_, line, ref_mask=np.ones(5, dtype=bool))
    with pytest.raises(InvalidCloudError, match="fewer than 3"):
        robust_deformation(ref, cmp_, line, ref_mask=np.zeros(len(ref), dtype=bool))


def test_radius_index_finds_exactly_the_kd_tree_neighbours():
    from tunneldef.deformation.cylinders import _RadiusIndex

    rng = np.random.default_rng(4)
    pts = rng.uniform(-3.0, 3.0, (20_000, 3))
    centres = rng.uniform(-3.0, 3.0, (300, 3))
    group, idx, d2 = _RadiusIndex(pts, 0.3).ball(centres, 0.45)  # a wider query than indexed
    assert np.all(np.diff(group) >= 0)
    np.testing.assert_allclose(d2, ((pts[idx] - centres[group]) ** 2).sum(axis=1), atol=1e-5)
    lists = cKDTree(pts).query_ball_point(centres, 0.45)
    for c in range(len(centres)):
        # float32 coordinates: only points within a micrometre of the sphere may differ
        got, want = set(idx[group == c]), set(lists[c])
        edge = np.abs(np.linalg.norm(pts[list(got ^ want)] - centres[c], axis=1) - 0.45)
        assert np.all(edge < 1e-5)
    empty = _RadiusIndex(np.empty((0, 3)), 0.3).ball(centres, 0.3)
    assert all(a.size == 0 for a in empty)


def test_sharpening_takes_out_the_smoothing_bias_only_where_the_cylinders_are_dense():
    # a 30 mm, 1 m wide sag with little noise at the handheld scanner's density: the plain
    # cylinder and interpolation means read its peak about 6 % low; sharpened, within 2 %
    amp = 0.03
    pair = _pair(
        noise=0.002,
        length=5.0,
        density=2600.0,
        deformations=[DeformationSpec(kind="roof_sag", chainage=2.5, amplitude=amp)],
        seed=6,
    )
    tr = pair.truth
    shell = tr.label == 0
    centre = np.argmin(np.where(shell, tr.displacement, np.inf))
    disc = shell & (np.linalg.norm(tr.cmp_xyz_in_ref - tr.cmp_xyz_in_ref[centre], axis=1) < 0.3)
    truth = np.median(tr.displacement[disc])
    plain = _run(pair, sharpen=False)
    sharp = _run(pair)
    assert plain.meta["sharpened_cores"] == 0
    assert sharp.meta["sharpened_cores"] > 0.7 * sharp.meta["cores"]
    assert np.median(plain.deformation[disc]) - truth > 0.04 * amp  # read low
    assert abs(np.median(sharp.deformation[disc]) - truth) < 0.02 * amp
    # its price, a noisier core, is in the level of detection
    assert np.nanmedian(sharp.core_lod95) > 1.2 * np.nanmedian(plain.core_lod95)
    # sparse and noisy (400 points/m^2, +-3 cm): the cylinders cannot afford it
    sparse = _run(_pair(length=5.0, seed=6))
    assert sparse.meta["sharpened_cores"] < 0.05 * sparse.meta["cores"]
    # and the dense cylinders need no pooling
    assert sharp.meta["pooled_cores"] < 0.05 * sharp.meta["cores"]


def test_pooling_cancels_its_own_smoothing_bias_and_lowers_the_noise():
    # cores on a flat roof every 0.2 m carrying a 30 mm, 4 m x 2 m cosine sag (the synthetic
    # sag's shape), each with a plain cylinder's bias-free value: the pooled field must read
    # the peak within 4 % where a single Gaussian mean of the same width reads it 9 % low
    from tunneldef.deformation.core_pooling import _pool

    g = np.arange(-4.0, 4.0 + 1e-9, 0.2)
    x, y = np.meshgrid(g, g, indexing="ij")
    cores = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, 2.0)])
    normals = np.tile([0.0, 0.0, 1.0], (len(cores), 1))
    variation = np.zeros(len(cores))

    def taper(u, length):
        return np.where(np.abs(u) < length / 2, 0.5 * (1 + np.cos(2 * np.pi * u / length)), 0.0)

    truth = -0.03 * taper(cores[:, 0], 4.0) * taper(cores[:, 1], 2.0)
    se = np.full(len(cores), 0.003)
    kw = dict(sigma=0.2, base=0.0, overlap=1.0)
    ids, lam, d, se_p = _pool(cores, normals, variation, truth, se, **kw)
    assert np.array_equal(ids, np.arange(len(cores))) and np.all(lam == 1.0)
    peak = int(np.argmin(truth))
    got = d[ids == peak][0]
    assert got == pytest.approx(truth[peak], rel=0.04)
    w = np.exp(-0.5 * ((cores - cores[peak]) ** 2).sum(axis=1) / 0.2**2)
    single = np.sum(w * truth) / w.sum()
    assert single > 0.91 * truth[peak]  # reads low
    # beyond the pooling's reach (3 sigma of the wider mean, 0.85 m) nothing is invented
    far = (np.abs(cores[:, 0]) > 2.9) | (np.abs(cores[:, 1]) > 1.9)
    assert np.abs(d[far]).max() < 1e-12
    # independent noise of 3 mm per core comes out well below it, and the propagated error
    # says by how much
    rng = np.random.default_rng(1)
    noisy = truth + rng.normal(0.0, 0.003, len(cores))
    _, _, dn, se_n = _pool(cores, normals, variation, noisy, se, **kw)
    inner = (np.abs(cores[:, 0]) < 3.0) & (np.abs(cores[:, 1]) < 3.0)
    err = (dn - truth)[inner]
    assert err.std() < 0.5 * 0.003
    assert err.std() == pytest.approx(np.median(se_n[inner]), rel=0.25)
    # cores at or below 1.5 mm are left alone, a corner core is never pooled
    variation[peak] = 0.1
    ids2, *_ = _pool(cores, normals, variation, truth, np.where(cores[:, 0] > 0, se, 0.001), **kw)
    assert peak not in ids2 and np.all(cores[ids2, 0] > 0)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_sparse_cylinder_is_widened_only_as_far_as_it_needs(seed, monkeypatch):
    """At 110 points/m^2 a 0.2 m cylinder holds about 14 points of an epoch, fewer than
    ``min_points`` (20); twice the area holds enough. Widened straight to twice the radius
    the cylinders read a 40 mm bulge 1.2 m wide as 28-29 mm (seeds 1-3); widened by sqrt(2)
    first they read it 30-34 mm, and the unchanged shell stays as quiet."""
    a = 0.040
    spec = PairSpec(
        tunnel=TunnelSpec(length=LENGTH, noise_sigma=0.012, density=110.0,
                          section=SectionSpec("rectangle", 4.6, 3.0)),
        deformations=(DeformationSpec(kind="wall_bulge", chainage=6.0, length=3.0, width=1.2,
                                      amplitude=a, side="right"),),
        cmp_shift=0.0,
        seed=seed,
    )
    pair = make_pair(spec)
    tr = pair.truth
    core = (tr.label == 0) & (tr.displacement <= -0.8 * a)
    true = np.median(tr.displacement[core])
    quiet = _unchanged(tr)
    r = _run(pair)
    radius = np.round(r.core_radius, 3)
    assert np.mean(radius == round(0.2 * np.sqrt(2.0), 3)) >= 0.5
    assert r.meta["mid_cylinder_cores"] == int(np.sum(radius == round(0.2 * np.sqrt(2.0), 3)))
    d = np.abs(r.deformation[quiet])
    assert np.mean(d[np.isfinite(d)] > 0.010) <= 0.005
    new = np.nanmedian(r.deformation[core])
    monkeypatch.setattr(local_surface, "_MID_WIDTH", 2.0)  # straight to twice the radius
    old = np.nanmedian(_run(pair).deformation[core])
    assert abs(new - true) < abs(old - true) - 0.0008
    assert abs(new - true) <= 0.18 * abs(true)
