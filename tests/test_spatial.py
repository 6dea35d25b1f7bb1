"""Helpers on point arrays (tunneldef.spatial)."""

from __future__ import annotations

import numpy as np

from tunneldef.spatial import random_keep, random_subset


def test_random_keep_is_one_draw_made_a_chunk_at_a_time() -> None:
    """The mask drawn in chunks is ``default_rng(seed).random(n) < fraction`` itself, and a
    shared generator advances by ``n`` draws (a second mask continues its stream)."""
    n = 10_007
    np.testing.assert_array_equal(random_keep(n, 0.3, 5, chunk=1_000),
                                  np.random.default_rng(5).random(n) < 0.3)
    gen, ref = np.random.default_rng(9), np.random.default_rng(9)
    first, second = random_keep(n, 0.2, gen, chunk=333), random_keep(77, 0.5, gen, chunk=10)
    np.testing.assert_array_equal(first, ref.random(n) < 0.2)
    np.testing.assert_array_equal(second, ref.random(77) < 0.5)
    assert 0.18 < first.mean() < 0.22
    assert random_keep(0, 0.5).shape == (0,)


def test_random_subset_keeps_small_clouds_whole() -> None:
    xyz = np.arange(30.0).reshape(10, 3)
    assert random_subset(xyz, 10) is xyz
    sub = random_subset(xyz, 4, seed=1)
    assert sub.shape == (4, 3)
    assert len({tuple(r) for r in sub}) == 4
    assert all(tuple(r) in {tuple(x) for x in xyz} for r in sub)
