"""Classic whole-cloud registration methods, to compare the centreline method against.

Each starts from the same coarse (PCA) transform and refines it on voxel-downsampled clouds:

* ``icp_point`` / ``icp_plane``: Open3D ICP, point-to-point and point-to-plane;
* ``gicp``: Open3D generalized ICP (plane-to-plane);
* ``ndt``: our own vectorised point-to-distribution NDT (Magnusson 2009): the reference is cut
  into voxels holding a Gaussian each, and the compared points are moved to maximise the NDT
  score, by Gauss-Newton steps on the score's weights (no maintained NDT library installs from
  PyPI here; python-pcl and pclpy are unmaintained).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..spatial import morton_order, unique_rows, voxel_grid
from ..transforms import apply_transform

__all__ = ["BASELINES", "icp_point", "icp_plane", "gicp", "ndt"]

_reg = o3d.pipelines.registration


def _sorted(xyz: np.ndarray, voxel: float) -> o3d.geometry.PointCloud:
    """The points thinned to a ``voxel`` grid (none when 0), in Morton order (see
    :func:`_open3d_icp`), as an Open3D cloud."""
    xyz = np.asarray(xyz, dtype=np.float64)
    pts = voxel_grid(xyz, voxel) if voxel > 0 else xyz[morton_order(xyz)]
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))


def _criteria(iterations: int) -> o3d.pipelines.registration.ICPConvergenceCriteria:
    return _reg.ICPConvergenceCriteria(
        relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=iterations
    )


def _open3d_icp(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    init: np.ndarray,
    kind: str,
    *,
    voxel: float,
    max_distance: float,
    iterations: int,
    ref_normals: np.ndarray | None = None,
) -> np.ndarray:
    """One Open3D ICP variant ("point", "plane" or "generalized") from ``init``.

    With ``ref_normals`` (point-to-plane only) the reference is taken as it is, already thinned
    and with these unit normals, instead of being thinned to ``voxel`` and given normals here.

    Both clouds are moved by the same offset (the reference's centroid, rounded to 1 km)
    first: Open3D linearises the rotation about the origin, and in survey coordinates
    (5.6e6 m) a milliradian of rotation is kilometres of translation, so the ICP diverged.
    """
    origin = np.round(np.mean(np.asarray(ref_xyz[:: max(len(ref_xyz) // 1000, 1)],
                                         dtype=np.float64), axis=0), -3)
    if np.any(np.abs(origin) > 0):
        to_local, to_world = np.eye(4), np.eye(4)
        to_local[:3, 3], to_world[:3, 3] = -origin, origin
        local = _open3d_icp(ref_xyz - origin, cmp_xyz - origin,
                            to_local @ np.asarray(init, dtype=np.float64) @ to_world, kind,
                            voxel=voxel, max_distance=max_distance, iterations=iterations,
                            ref_normals=ref_normals)
        return to_world @ local @ to_local
    # both clouds in Morton order: Open3D's nearest-neighbour queries and the reference's
    # points then follow space in memory (a voxel grid's points come out in hash order, a
    # sample in random order): 300,000 points fitted 3-6 times faster, to the same transform
    # (a sum over the same correspondences)
    if ref_normals is not None and kind == "plane":
        order = morton_order(ref_xyz)
        dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
            np.asarray(ref_xyz, dtype=np.float64)[order]))
        dst.normals = o3d.utility.Vector3dVector(
            np.asarray(ref_normals, dtype=np.float64)[order])
    else:
        dst = _sorted(ref_xyz, voxel)
        if kind == "plane":
            dst.estimate_normals(
                o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    run = _reg.registration_generalized_icp if kind == "generalized" else _reg.registration_icp
    estimation = {
        "point": _reg.TransformationEstimationPointToPoint,
        "plane": _reg.TransformationEstimationPointToPlane,
        "generalized": _reg.TransformationEstimationForGeneralizedICP,
    }[kind]()
    res = run(_sorted(cmp_xyz, voxel), dst, max_distance, init, estimation,
              _criteria(iterations))
    return np.asarray(res.transformation)


def icp_point(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    init: np.ndarray,
    *,
    voxel: float = 0.05,
    max_distance: float = 0.5,
    iterations: int = 60,
) -> np.ndarray:
    """Open3D point-to-point ICP; returns the (4, 4) cmp -> ref transform (metres)."""
    return _open3d_icp(ref_xyz, cmp_xyz, init, "point", voxel=voxel, max_distance=max_distance,
                       iterations=iterations)


def icp_plane(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    init: np.ndarray,
    *,
    voxel: float = 0.05,
    max_distance: float = 0.5,
    iterations: int = 60,
    ref_normals: np.ndarray | None = None,
) -> np.ndarray:
    """Open3D point-to-plane ICP; returns the (4, 4) cmp -> ref transform (metres).
    ``ref_normals``: the reference's unit normals, when it is already thinned and has them."""
    return _open3d_icp(ref_xyz, cmp_xyz, init, "plane", voxel=voxel, max_distance=max_distance,
                       iterations=iterations, ref_normals=ref_normals)


def gicp(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    init: np.ndarray,
    *,
    voxel: float = 0.05,
    max_distance: float = 0.5,
    iterations: int = 60,
) -> np.ndarray:
    """Open3D generalized ICP; returns the (4, 4) cmp -> ref transform (metres)."""
    return _open3d_icp(ref_xyz, cmp_xyz, init, "generalized", voxel=voxel,
                       max_distance=max_distance, iterations=iterations)


def _ndt_cells(xyz: np.ndarray, cell: float, min_points: int = 6):
    key = np.floor(xyz / cell).astype(np.int64)
    _, inv, cnt = unique_rows(key)
    ok = cnt >= min_points
    n = len(cnt)
    s1 = np.zeros((n, 3))
    np.add.at(s1, inv, xyz)
    mu = s1 / cnt[:, None]
    d = xyz - mu[inv]
    s2 = np.zeros((n, 3, 3))
    np.add.at(s2, inv, d[:, :, None] * d[:, None, :])
    cov = s2 / np.maximum(cnt - 1, 1)[:, None, None]
    # regularise flat cells (Magnusson: eigenvalues >= 1e-3 of the largest)
    w, v = np.linalg.eigh(cov[ok])
    w = np.maximum(w, 1e-3 * w[:, 2:3] + 1e-8)
    icov = np.einsum("nij,nj,nkj->nik", v, 1.0 / w, v)
    return mu[ok], icov


def ndt(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    init: np.ndarray,
    *,
    voxel: float = 0.05,
    cell: float = 0.5,
    iterations: int = 30,
) -> np.ndarray:
    """Point-to-distribution NDT (Magnusson 2009), our vectorised implementation.

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (N, 3), (M, 3)
        Reference and compared points, metres.
    init : ndarray, shape (4, 4)
        Starting cmp -> ref transform.
    voxel : float
        Downsampling of the compared points, metres.
    cell : float
        NDT cell size, metres (two resolutions are used: 2 x cell, then cell).

    Returns
    -------
    ndarray, shape (4, 4)
        The cmp -> ref transform.
    """
    src = np.asarray(_sorted(cmp_xyz, 2 * voxel).points)
    ref = np.asarray(_sorted(ref_xyz, voxel).points)
    t = np.asarray(init, dtype=np.float64).copy()
    c0 = ref.mean(axis=0)  # work about the reference centroid (numerics)
    for size in (2 * cell, cell):
        mu, icov = _ndt_cells(ref - c0, size)
        tree = cKDTree(mu)
        # Magnusson's d1, d2 for an outlier ratio of 0.55
        c1, c2 = 10 * (1 - 0.55), 0.55 / size**3
        d3 = -np.log(c2)
        d1 = -np.log(c1 + c2) - d3
        d2 = -2 * np.log((-np.log(c1 * np.exp(-0.5) + c2) - d3) / d1)
        for _ in range(iterations):
            x = apply_transform(t, src) - c0
            _, idx = tree.query(x, k=2, distance_upper_bound=size)
            idx = idx.reshape(len(x), -1)
            g = np.zeros(6)
            h = np.zeros((6, 6))
            for col in range(idx.shape[1]):
                ok = idx[:, col] < len(mu)
                if not ok.any():
                    continue
                xo = x[ok]
                q = xo - mu[idx[ok, col]]
                ic = icov[idx[ok, col]]
                cq = np.einsum("nij,nj->ni", ic, q)
                e = np.exp(-0.5 * d2 * np.einsum("ni,ni->n", q, cq))
                w = -d1 * d2 * e  # minimised: sum d1 exp(-d2/2 q C q), d1 < 0; w > 0
                # Jacobian of the moved point wrt (rotation vector, translation) at identity
                jac = np.zeros((len(xo), 3, 6))
                jac[:, 0, 1], jac[:, 0, 2] = xo[:, 2], -xo[:, 1]
                jac[:, 1, 0], jac[:, 1, 2] = -xo[:, 2], xo[:, 0]
                jac[:, 2, 0], jac[:, 2, 1] = xo[:, 1], -xo[:, 0]
                jac[:, :, 3:] = np.eye(3)
                cj = np.matmul(ic, jac)  # (n, 3, 6)
                g += np.einsum("n,ni,nij->j", w, q, cj, optimize=True)
                h += np.einsum("nij,nik->jk", jac * w[:, None, None], cj, optimize=True)
            if not np.any(h):
                break
            step = -np.linalg.solve(h + 1e-9 * np.eye(6), g)
            d = np.eye(4)
            d[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
            d[:3, 3] = step[3:]
            # the step is about the reference centroid
            shift = np.eye(4)
            shift[:3, 3] = -c0
            t = np.linalg.inv(shift) @ d @ shift @ t
            if np.linalg.norm(step[:3]) < 1e-7 and np.linalg.norm(step[3:]) < 1e-6:
                break
    return t


BASELINES = {"icp_point": icp_point, "icp_plane": icp_plane, "gicp": gicp, "ndt": ndt}
