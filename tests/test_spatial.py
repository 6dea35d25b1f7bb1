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


def _tilted_plane(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points on a 20 x 3 m plane rising 10 % along x (2 mm noise), and its normal."""
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([rng.uniform(0, 20, n), rng.uniform(0, 3, n), np.zeros(n)])
    xyz[:, 2] = 0.1 * xyz[:, 0] + 0.002 * rng.standard_normal(n)
    normal = np.array([-0.1, 0.0, 1.0])
    return xyz, normal / np.linalg.norm(normal)


def test_plane_normals_keep_their_direction_in_survey_coordinates() -> None:
    """Open3D sums raw moments: at 5.6e6 m its own normals of this plane were 76 degrees off at
    the median. ``plane_normals`` estimates them about the centroid, so survey coordinates read
    as local ones, and returns them in the points' own order."""
    from tunneldef.spatial import plane_normals

    xyz, normal = _tilted_plane(40_000)
    local = plane_normals(xyz, 0.4, 30)
    survey = plane_normals(xyz + np.array([4.5e5, 5.6e6, 310.0]), 0.4, 30)
    for n in (local, survey):
        angle = np.degrees(np.arccos(np.clip(np.abs(n @ normal), 0.0, 1.0)))
        assert np.median(angle) < 2.0 and np.percentile(angle, 95) < 5.0  # 1.0 / 2.1 measured
    # the same normals, point for point (up to their arbitrary sign)
    assert np.abs(np.abs(np.einsum("ij,ij->i", local, survey)) - 1.0).max() < 1e-6


def test_voxel_grid_is_open3ds_grid_in_morton_order() -> None:
    import open3d as o3d

    from tunneldef.spatial import morton_order, voxel_grid

    xyz, _ = _tilted_plane(20_000, seed=1)
    grid = voxel_grid(xyz, 0.1)
    o3d_grid = np.asarray(o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(xyz)).voxel_down_sample(0.1).points)
    assert len(grid) == len(o3d_grid) < len(xyz)
    np.testing.assert_allclose(grid, o3d_grid[morton_order(o3d_grid)], atol=1e-12)
    np.testing.assert_array_equal(morton_order(grid), np.arange(len(grid)))


def test_unique_rows_is_numpys_row_wise_unique() -> None:
    """Packed into one key where the spans allow, unpacked where they do not: either way
    NumPy's own answer, rows in the same order."""
    from tunneldef.spatial import unique_rows

    rng = np.random.default_rng(2)
    for ijk in (rng.integers(-50, 50, (5_000, 3)),
                np.column_stack([rng.integers(-3, 3, 800), rng.integers(0, 2, 800),
                                 rng.integers(-2**40, 2**40, 800)]),
                np.array([[0, 0, 0], [2**31, -2**31, 2**31]]) + rng.integers(0, 2, (2, 3))):
        rows, inverse, counts = unique_rows(ijk)
        want = np.unique(ijk, axis=0, return_inverse=True, return_counts=True)
        np.testing.assert_array_equal(rows, want[0])
        np.testing.assert_array_equal(inverse, want[1].ravel())
        np.testing.assert_array_equal(counts, want[2])
    assert unique_rows(np.empty((0, 3), dtype=np.int64))[0].shape == (0, 3)
