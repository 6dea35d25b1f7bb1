"""Registration of two drift-network epochs by the common part of their centreline graphs.

Steps of :func:`register_networks`:

1. Coarse: every pairing of a reference junction with a compared junction, and of a branch
   direction at one with a branch direction at the other, proposes a rotation about the
   vertical and a translation (junction onto junction). Each proposal is scored by how much of
   the compared network's curves (sampled every metre) falls within ``coarse_radius`` of the
   reference network's curves; either epoch may cover stretches the other does not, so the
   score counts the common part and does not penalise the rest.
2. Curves: rigid ICP of the compared curve samples onto the reference curve samples with a
   shrinking match radius (3 m, 1 m, 0.3 m), which takes out the tilt of the compared
   epoch's frame.
3. Fine: Open3D point-to-plane ICP of the voxel-thinned clouds from there.

The common length per reference edge is the length of 1 m bins along that edge where both
epochs have points after registration.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..errors import RegistrationError
from ..network import CenterlineNetwork
from ..transforms import apply_transform
from .baselines import icp_plane
from .verify import coherent_misfit

__all__ = ["NetworkRegistration", "register_networks", "common_lengths", "correct_drift"]


@dataclass
class NetworkRegistration:
    """Result of :func:`register_networks`.

    Attributes
    ----------
    transform : ndarray, shape (4, 4)
        Compared -> reference rigid transform.
    stages : dict
        The transform after each stage (``coarse``, ``curves``, ``fine``).
    junction_pairs : list of (int, int)
        Reference / compared junctions matched within 1 m after registration.
    curve_rms : float
        RMS distance of the compared curve samples to the reference curves over the common part
        after registration, metres.
    fitness : float
        Share of the thinned compared points within ``fine_distance`` of the reference.
    """

    transform: np.ndarray
    stages: dict[str, list[list[float]]] = field(default_factory=dict)
    junction_pairs: list[tuple[int, int]] = field(default_factory=list)
    curve_rms: float = float("nan")
    fitness: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        return {
            "method": "network",
            "transform": np.asarray(self.transform).tolist(),
            "stages": self.stages,
            "junction_pairs": [list(p) for p in self.junction_pairs],
            "curve_rms_m": self.curve_rms,
            "fitness": self.fitness,
        }


def _samples(net: CenterlineNetwork, step: float = 1.0) -> np.ndarray:
    out = []
    for e in net.edges:
        s = np.arange(0.0, e.length + 1e-9, step)
        out.append(e.centerline.point_at(s))
    return np.concatenate(out)


def _yaw_transform(yaw: float, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    t = np.eye(4)
    t[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    t[:3, 3] = dst - t[:3, :3] @ src
    return t


def _directions(net: CenterlineNetwork, j: int) -> list[float]:
    """Plan headings (radians) of the branches leaving junction ``j`` (both ways along edges
    that pass through)."""
    jn = net.junctions[j]
    out = []
    for e_id, s in zip(jn.edges, jn.chainages, strict=True):
        cl = net.edges[e_id].centerline
        for sign in (1.0, -1.0):
            s2 = s + sign * 5.0
            if -1.0 <= s2 <= cl.length + 1.0:
                d = cl.point_at(s2)[0] - cl.point_at(s)[0]
                out.append(float(np.arctan2(d[1], d[0])))
    return out


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    r = vt.T @ u.T
    if np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = vt.T @ u.T
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = cd - r @ cs
    return t


def register_networks(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    ref_net: CenterlineNetwork,
    cmp_net: CenterlineNetwork,
    *,
    coarse_radius: float = 1.0,
    voxel: float = 0.1,
    fine_distance: float = 0.3,
    max_points: int = 400_000,
) -> NetworkRegistration:
    """Register the compared epoch onto the reference by the common part of their networks.

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (M, 3), (N, 3)
        The epochs, each in its own frame, metres.
    ref_net, cmp_net : CenterlineNetwork
        Their centreline networks.
    coarse_radius : float
        A compared curve sample within this distance of the reference curves counts as common
        in the coarse search, metres.
    voxel, fine_distance : float
        Voxel size and match distance of the final point-to-plane ICP, metres.
    max_points : int
        Points per epoch used by the ICP (thinned at random, seeded).

    Raises
    ------
    RegistrationError
        If either network has no junction (nothing fixes the position along the drifts: use
        the single-tube registration), or less than 20 m of curve is common.
    """
    if not ref_net.junctions or not cmp_net.junctions:
        raise RegistrationError(
            "a network registration needs a junction in both epochs; one epoch shows none "
            "(a single drift: use the single-tube detect)"
        )
    ref_s, cmp_s = _samples(ref_net), _samples(cmp_net)
    tree = cKDTree(ref_s)
    best = (-1.0, np.inf, np.eye(4))
    for i, ji in enumerate(ref_net.junctions):
        di = _directions(ref_net, i)
        for j, jj in enumerate(cmp_net.junctions):
            for a in di:
                for b in _directions(cmp_net, j):
                    t = _yaw_transform(a - b, jj.position, ji.position)
                    d, _ = tree.query(apply_transform(t, cmp_s), distance_upper_bound=3.0)
                    score = float(np.sum(d < coarse_radius))
                    med = float(np.median(d[np.isfinite(d)])) if np.isfinite(d).any() else np.inf
                    if score > best[0] or (score == best[0] and med < best[1]):
                        best = (score, med, t)
    if best[0] < 20:
        raise RegistrationError(
            f"the two networks share only {best[0]:.0f} m of centreline; do the epochs "
            "cover the same drifts?"
        )
    t = best[2]
    stages = {"coarse": t.tolist()}
    for radius in (3.0, 1.0, 0.3, 0.3):
        moved = apply_transform(t, cmp_s)
        d, k = tree.query(moved, distance_upper_bound=radius)
        m = np.isfinite(d)
        if m.sum() < 10:
            break
        t = _kabsch(moved[m], ref_s[k[m]]) @ t
    stages["curves"] = t.tolist()
    rng = np.random.default_rng(0)
    r = ref_xyz if len(ref_xyz) <= max_points else ref_xyz[rng.random(len(ref_xyz)) <
                                                           max_points / len(ref_xyz)]
    c = cmp_xyz if len(cmp_xyz) <= max_points else cmp_xyz[rng.random(len(cmp_xyz)) <
                                                           max_points / len(cmp_xyz)]
    t = icp_plane(r, c, t, voxel=voxel, max_distance=1.0, iterations=30)
    t = icp_plane(r, c, t, voxel=voxel, max_distance=fine_distance, iterations=60)
    stages["fine"] = t.tolist()
    moved_s = apply_transform(t, cmp_s)
    d, _ = tree.query(moved_s, distance_upper_bound=0.5)
    rms = float(np.sqrt(np.mean(d[np.isfinite(d)] ** 2))) if np.isfinite(d).any() else np.nan
    dr, _ = cKDTree(r).query(apply_transform(t, c[:: max(len(c) // 50_000, 1)]),
                             distance_upper_bound=fine_distance)
    pairs = []
    for ji in ref_net.junctions:
        for jj in cmp_net.junctions:
            if np.linalg.norm(apply_transform(t, jj.position[None])[0] - ji.position) < 1.0:
                pairs.append((ji.id, jj.id))
    return NetworkRegistration(t, stages, pairs, rms, float(np.mean(np.isfinite(dr))))


def common_lengths(
    net: CenterlineNetwork, ref_xyz: np.ndarray, cmp_xyz: np.ndarray, *, bin_m: float = 1.0,
    min_points: int = 20, max_distance: float = 5.0,
) -> dict[int, float]:
    """Per edge, the length covered by both epochs (1 m bins with at least ``min_points``
    points of each, points within ``max_distance`` of the edge), metres."""
    pr = net.project(ref_xyz, max_distance=max_distance)
    pc = net.project(cmp_xyz, max_distance=max_distance)
    out = {}
    for e in net.edges:
        nb = int(np.ceil(e.length / bin_m)) + 1
        counts = []
        for p in (pr, pc):
            m = (p.branch == e.id) & p.inside
            counts.append(np.bincount(np.floor(p.chainage[m] / bin_m).astype(np.int64),
                                      minlength=nb)[:nb])
        out[e.id] = float(np.sum((counts[0] >= min_points) & (counts[1] >= min_points)) * bin_m)
    return out


def _plane_residual(ref_tree: cKDTree, normals: np.ndarray, ref_pts: np.ndarray,
                    xyz: np.ndarray, trim: float) -> np.ndarray:
    """Point-to-plane distance of ``xyz`` to the reference (NaN beyond ``trim``)."""
    d, k = ref_tree.query(xyz, distance_upper_bound=trim)
    out = np.full(len(xyz), np.nan)
    m = np.isfinite(d)
    out[m] = np.einsum("ij,ij->i", xyz[m] - ref_pts[k[m]], normals[k[m]])
    return out


def correct_drift(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    net: CenterlineNetwork,
    *,
    block: float = 20.0,
    voxel: float = 0.1,
    max_distance: float = 0.1,
    min_gain: float = 0.0005,
    sample: int = 40_000,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Piecewise-rigid correction of SLAM drift along each edge, after a rigid registration.

    Along every reference edge, blocks ``block`` metres long (centred every ``block``, each
    reaching half a block into its neighbours) of the compared points are registered onto the
    reference by point-to-plane ICP with a tight match distance (``max_distance``: a local
    change such as a sag, a bulge or a heave is a small part of a block's shell and outside
    the match distance where it is large). The blocks' displacements are blended linearly along
    the chainage between block centres, so the correction is continuous along each edge.

    The correction is used only when it lowers the compared points' coherent misfit
    (:func:`~tunneldef.registration.verify.coherent_misfit`: the point-to-plane misfit shared
    by neighbouring points, which the scans' noise does not explain) by more than ``min_gain``
    (the RMS point-to-plane residual, trimmed at ``max_distance``, where that cannot be
    measured); otherwise the points are returned unchanged.

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (M, 3), (N, 3)
        Reference and registered compared points, metres.
    net : CenterlineNetwork
        The reference network (the compared points are assigned to its edges).

    Returns
    -------
    xyz : ndarray, shape (N, 3)
        The corrected compared points (or ``cmp_xyz`` itself when not used).
    info : dict
        ``used``, residual RMS before and after (m), per edge the blocks' centres and their
        displacement at the block centre (m).
    """
    import open3d as o3d

    rng = np.random.default_rng(0)
    ref_pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ref_xyz)).voxel_down_sample(
        voxel / 2)
    ref_pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    rp, rn = np.asarray(ref_pc.points), np.asarray(ref_pc.normals)
    tree = cKDTree(rp)
    pc = net.project(cmp_xyz, max_distance=10.0)
    pr = net.project(rp, max_distance=10.0)
    disp = np.zeros_like(cmp_xyz)
    wsum = np.zeros(len(cmp_xyz))
    info: dict[str, Any] = {"block_m": block, "edges": {}}
    for e in net.edges:
        mc = np.flatnonzero(pc.branch == e.id)
        if len(mc) < 1000:
            continue
        n_blocks = max(int(round(e.length / block)), 1)
        centres = (np.arange(n_blocks) + 0.5) * e.length / n_blocks
        width = e.length / n_blocks
        s = pc.chainage[mc]
        rows = []
        for c in centres:
            sel = mc[np.abs(s - c) <= 0.75 * width]
            rsel = (pr.branch == e.id) & (np.abs(pr.chainage - c) <= 0.75 * width + 1.0)
            if len(sel) < 2000 or rsel.sum() < 2000:
                rows.append(np.eye(4))
                continue
            pick = sel if len(sel) <= sample else rng.choice(sel, sample, replace=False)
            t = icp_plane(rp[rsel], cmp_xyz[pick], np.eye(4), voxel=voxel,
                          max_distance=max_distance, iterations=30, ref_normals=rn[rsel])
            rows.append(t)
        # blend the blocks' displacements with hat functions on the block centres
        for k, (c, t) in enumerate(zip(centres, rows, strict=True)):
            up = np.clip((s - centres[k - 1]) / (c - centres[k - 1]), 0, 1) if k > 0 \
                else np.ones_like(s)
            down = np.clip((centres[k + 1] - s) / (centres[k + 1] - c), 0, 1) \
                if k + 1 < len(centres) else np.ones_like(s)
            w = np.where(s <= c, up, down)
            m = w > 0
            p = cmp_xyz[mc[m]]
            disp[mc[m]] += w[m, None] * (apply_transform(t, p) - p)
            wsum[mc[m]] += w[m]
        info["edges"][str(e.id)] = {
            "block_centres_m": centres.tolist(),
            "block_shift_m": [float(np.linalg.norm(
                apply_transform(t, e.centerline.point_at(c))[0] - e.centerline.point_at(c)[0]))
                for c, t in zip(centres, rows, strict=True)],
        }
    ok = wsum > 0
    out = cmp_xyz.copy()
    out[ok] += disp[ok] / wsum[ok, None]
    probe = rng.choice(len(cmp_xyz), min(len(cmp_xyz), 200_000), replace=False)
    before = _plane_residual(tree, rn, rp, cmp_xyz[probe], max_distance)
    after = _plane_residual(tree, rn, rp, out[probe], max_distance)
    both = np.isfinite(before) & np.isfinite(after)
    rb = float(np.sqrt(np.mean(before[both] ** 2))) if both.any() else np.nan
    ra = float(np.sqrt(np.mean(after[both] ** 2))) if both.any() else np.nan
    # the misfit shared by neighbouring points, which the scans' noise does not drown: at
    # +-2 cm noise a 5 mm drift residue moves the RMS above by 0.4 mm, and this by 5 mm
    cb = coherent_misfit(cmp_xyz[probe], rp, rn, tree)
    ca = coherent_misfit(out[probe], rp, rn, tree)
    if np.isfinite(cb) and np.isfinite(ca):
        used = bool(cb - ca > min_gain)
    else:
        used = bool(np.isfinite(rb) and rb - ra > min_gain)
    info.update({"used": used, "residual_rms_before_m": rb, "residual_rms_after_m": ra,
                 "coherent_before_m": cb, "coherent_after_m": ca, "min_gain_m": min_gain})
    return (out if used else cmp_xyz), info
