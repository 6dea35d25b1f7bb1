"""Shell versus objects in front of it (tunneldef.deformation.shell) against synthetic labels."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tunneldef.curve import Centerline
from tunneldef.deformation.shell import classify_shell, outer_envelope, shell_envelope, shell_mask
from tunneldef.errors import ConfigError, InvalidCloudError
from tunneldef.synth import DeformationSpec, PairSpec, SectionSpec, TunnelSpec, make_pair

SHELL, EQUIPMENT, DYNAMIC, OUTLIER = 0, 1, 2, 3


def _scores(pred: np.ndarray, label: np.ndarray) -> tuple[float, float]:
    truth = label == SHELL
    tp = float((pred & truth).sum())
    return tp / pred.sum(), tp / truth.sum()


@pytest.mark.parametrize("kind", ["rectangle", "arch", "trapezoid"])
def test_precision_recall_with_equipment_and_conveyor(kind):
    pair = make_pair(
        PairSpec(
            tunnel=TunnelSpec(
                length=12.0, equipment=True, conveyor=True, section=SectionSpec(kind=kind)
            ),
            deformations=(DeformationSpec(kind="roof_sag", chainage=6.0, amplitude=0.03),),
            seed=11,
        )
    )
    tr = pair.truth
    for xyz, label in ((tr.cmp_xyz_in_ref, tr.label), (pair.ref.xyz, tr.ref_label)):
        shell = classify_shell(xyz, tr.centerline)
        precision, recall = _scores(shell, label)
        assert precision >= 0.95
        assert recall >= 0.98
        assert not shell[label == DYNAMIC].any()  # the coal load is never shell
        assert shell[label == OUTLIER].mean() < 0.15  # stray points in mid-air
        # the conveyor belt, its frame and the pipes standing off the rock are not shell
        assert shell[label == EQUIPMENT].mean() < 0.3
    # the 3 cm roof sag is still shell
    sag = (tr.label == SHELL) & (tr.displacement < -0.02)
    assert classify_shell(tr.cmp_xyz_in_ref, tr.centerline)[sag].mean() >= 0.99


def test_people_and_clean_tunnel():
    pair = make_pair(PairSpec(tunnel=TunnelSpec(length=10.0, people=3), seed=12))
    tr = pair.truth
    shell = classify_shell(tr.cmp_xyz_in_ref, tr.centerline)
    precision, recall = _scores(shell, tr.label)
    assert recall >= 0.99 and precision >= 0.99
    for surface in range(4):  # roof, both walls and floor alike
        m = (tr.label == SHELL) & (tr.surface == surface)
        assert shell[m].mean() >= 0.98
    people = tr.label == DYNAMIC  # their feet touch the floor: the rest of them is inside
    assert shell[people].mean() < 0.1


def test_outer_envelope_of_a_square_follows_its_sides():
    # a 2 x 2 m square section around the axis: the envelope along each ray is the exact
    # distance to the side it hits, and the obliquity is 1 / cos(angle to the side's normal)
    rng = np.random.default_rng(1)
    n = 40_000
    t = rng.uniform(-1.0, 1.0, n)
    side = rng.integers(0, 4, n)
    lat = np.choose(side, [np.ones(n), -np.ones(n), t, t])
    ver = np.choose(side, [t, t, np.ones(n), -np.ones(n)])
    theta, rho = np.arctan2(ver, lat), np.hypot(lat, ver)
    env, obl = outer_envelope(np.zeros(n, dtype=np.int64), theta, rho, sectors=180, rank=0)
    assert np.allclose(env, rho, atol=2e-3)
    expected = 1.0 / np.maximum(np.abs(np.cos(theta)), np.abs(np.sin(theta)))
    inner = np.abs(np.abs(t) - 1.0) > 0.05  # away from the corners
    assert np.allclose(obl[inner], expected[inner], rtol=0.02)


def test_objects_inside_are_rejected():
    # a plain 4 m circular drift with a 0.3 m pipe run 0.2 m off the wall
    rng = np.random.default_rng(2)
    n = 30_000
    s = rng.uniform(0.0, 8.0, n)
    a = rng.uniform(-np.pi, np.pi, n)
    r = 2.0 + rng.normal(0.0, 0.015, n)
    m = 3_000
    sp = rng.uniform(0.0, 8.0, m)
    ap = rng.uniform(-np.pi, np.pi, m)
    centre = np.array([1.65, 0.0])
    py = centre[0] + 0.15 * np.cos(ap)
    pz = centre[1] + 0.15 * np.sin(ap)
    xyz = np.concatenate(
        [np.stack([s, r * np.cos(a), r * np.sin(a)], 1), np.stack([sp, py, pz], 1)]
    )
    line = Centerline.from_polyline(np.array([[0.0, 0.0, 0.0], [8.0, 0.0, 0.0]]))
    shell = classify_shell(xyz, line)
    assert shell[:n].mean() >= 0.99
    assert not shell[n:].any()


def test_errors():
    line = Centerline.from_polyline(np.array([[0.0, 0.0, 0.0], [8.0, 0.0, 0.0]]))
    xyz = np.random.default_rng(3).normal(size=(100, 3))
    with pytest.raises(ConfigError, match="window"):
        classify_shell(xyz, line, window=0.0)
    with pytest.raises(ConfigError, match="inner_tolerance"):
        classify_shell(xyz, line, inner_tolerance=-0.1)
    with pytest.raises(ConfigError, match="sectors"):
        classify_shell(xyz, line, sectors=4)
    with pytest.raises(InvalidCloudError, match="N x 3"):
        classify_shell(xyz[:, :2], line)
    with pytest.raises(InvalidCloudError, match="at least 1"):
        classify_shell(np.empty((0, 3)), line)


def test_a_given_projection_gives_the_same_mask_and_is_checked():
    pair = make_pair(PairSpec(tunnel=TunnelSpec(length=8.0, equipment=True, conveyor=True), seed=5))
    tr = pair.truth
    xyz = tr.cmp_xyz_in_ref
    proj = tr.centerline.project(xyz)
    np.testing.assert_array_equal(
        classify_shell(xyz, tr.centerline, projection=proj), classify_shell(xyz, tr.centerline)
    )
    with pytest.raises(InvalidCloudError, match="projection"):
        classify_shell(xyz[:-1], tr.centerline, projection=proj)


def test_an_envelope_evaluated_elsewhere_and_the_common_cut():
    pair = make_pair(
        PairSpec(
            tunnel=TunnelSpec(length=8.0, equipment=True, conveyor=True),
            deformations=(DeformationSpec(kind="roof_sag", chainage=4.0, amplitude=0.08),),
            seed=5,
        )
    )
    tr, line = pair.truth, pair.truth.centerline
    ref, cmp_ = pair.ref.xyz, tr.cmp_xyz_in_ref
    p_ref, p_cmp = line.project(ref), line.project(cmp_)
    env_r, off_r, obl_r = shell_envelope(ref, line, projection=p_ref)
    env_c, off_c, obl_c = shell_envelope(cmp_, line, projection=p_cmp)
    # evaluated at its own points, the envelope gives back the offsets it was built with
    o, f = env_r.offset(p_ref)
    np.testing.assert_array_equal(o, off_r)
    np.testing.assert_array_equal(f, obl_r)
    # beyond its chainage windows it has no value
    assert np.isnan(env_r.offset(replace(p_ref, chainage=p_ref.chainage + 100.0))[0]).all()
    # the 8 cm sag moved the compared envelope inward there, by most of its depth (each bin's
    # upper quartile over a 1 m window leans to the less sagged part of the window)
    o_rc, f_rc = env_r.offset(p_cmp)
    core = tr.displacement < -0.07
    assert -0.085 < np.median(o_rc[core] - off_c[core]) < -0.045
    # with the local difference taken out it matches the own envelope there, and away from
    # the sag both stay within the envelopes' own noise
    m_rc, mf_rc = env_r.matched_offset(p_cmp, off_c)
    np.testing.assert_array_equal(mf_rc, f_rc)
    assert abs(np.median(m_rc[core] - off_c[core])) < 0.015
    still = (tr.label == SHELL) & (tr.displacement == 0.0) & np.isfinite(m_rc)
    assert np.percentile(np.abs(m_rc - off_c)[still], 90) < 0.025
    # the rule: inside the inner tolerance of either envelope, never beyond the own outer one
    own = shell_mask(off_c, obl_c)
    both = shell_mask(off_c, obl_c, other=(o_rc, f_rc))
    assert (both >= own).all()
    either = (off_c >= -0.055 * obl_c) | (o_rc >= -0.055 * f_rc)
    np.testing.assert_array_equal(both, either & (off_c <= 0.1 * obl_c))
    # the reference at the sag is cut from the compared (inner) envelope: it keeps all its
    # shell points there, as the compared points keep theirs against their own envelope
    o_cr, f_cr = env_c.offset(p_ref)
    ref_both = shell_mask(off_r, obl_r, other=(o_cr, f_cr))
    assert (ref_both >= shell_mask(off_r, obl_r)).all()
    sag_ref = (tr.ref_label == SHELL) & (np.abs(tr.ref_chainage - 4.0) < 0.3)
    sag_ref &= p_ref.vertical > 0.8 * p_ref.vertical.max()
    assert sag_ref.sum() > 100
    assert ref_both[sag_ref].mean() >= 0.995
    assert both[core & (tr.label == SHELL)].mean() >= 0.995
    # a point too far inside both envelopes is not shell, NaN (no other envelope) is the own
    one = np.ones(1)
    assert not shell_mask(np.array([-0.2]), one, other=(np.array([-0.1]), one))[0]
    assert shell_mask(np.array([-0.2]), one, other=(np.array([-0.05]), one))[0]
    nan = (np.array([np.nan]), np.array([np.nan]))
    assert shell_mask(np.array([-0.05]), one, other=nan)[0]
    assert not shell_mask(np.array([-0.06]), one, other=nan)[0]
