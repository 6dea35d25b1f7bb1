"""Registration of two drift-network epochs by the common part of their centreline graphs.

Steps of :func:`register_networks`:

1. Coarse: every pairing of a reference junction with a compared junction, and of a branch
   direction at one with a branch direction at the other, proposes a rotation about the
   vertical and a translation (junction onto junction); so does every edge of one epoch laid
   along every edge of the other and slid along it a metre at a time (two surveys need not
   share a junction: a cross-cut walked in one of them only). Each proposal is scored by how
   much of the compared network's curves (sampled every metre) falls within
   ``coarse_radius`` of the reference network's curves in plan; either epoch may cover
   stretches the other does not, so the score counts the common part and does not penalise
   the rest.
2. Hypotheses: the best distinct poses (``pool``) each go through
3. Curves: robust rigid ICP of the compared curve samples onto the reference curve samples
   with a shrinking match radius (3 m, 1 m, 0.3 m), which takes out the tilt of the compared
   epoch's frame (a step that raises the curves' truncated squared distance is not taken),
   and then the best ``hypotheses`` of them by their points' evidence (within 0.3 m: the
   curves place a pose to decimetres) through
4. Fine: Open3D point-to-plane ICP of the voxel-thinned clouds from there.
5. The hypothesis the reference's points explain best is kept (:func:`_evidence`: compared
   points on the reference count for it, compared points inside a drift the reference
   scanned but off its surfaces count against it, points beyond the reference's coverage
   neither way); the best evidence of the others is reported, for the registration check to
   judge whether the networks fit two places alike. A wrong junction pairing slides the
   compared epoch along a plain drift onto a look-alike cross-cut; where the two surveys
   cover different stretches, the curves' overlap alone prefers the slide that lays their
   ends over each other, and only the features (a cross-cut's mouth in the other's wall)
   tell.

The common length per reference edge is the length of 1 m bins along that edge where both
epochs have points after registration.

One idea at this length: one algorithm, the registration of two networks, whose steps hand
hypotheses from one to the next.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..errors import RegistrationError
from ..network import CenterlineNetwork
from ..spatial import plane_normals, random_keep, voxel_grid
from ..transforms import apply_transform
from .baselines import icp_plane
from .verify import coherent_misfit, patch_medians

__all__ = ["NetworkRegistration", "register_networks", "common_lengths", "correct_drift"]

_CHUNK = 2_000_000  # points projected at once by common_lengths


@dataclass
class NetworkRegistration:
    """Result of :func:`register_networks`.

    Attributes
    ----------
    transform : ndarray, shape (4, 4)
        Compared -> reference rigid transform.
    stages : dict
        The chosen pose after each stage (``coarse``, ``curves``, ``quick``: the thinned
        ICP that ranks the hypotheses, ``fine``).
    junction_pairs : list of (int, int)
        Reference / compared junctions matched within 1 m after registration.
    curve_rms : float
        RMS distance of the compared curve samples to the reference curves over the common part
        after registration, metres.
    fitness : float
        Share of the thinned compared points within ``fit_distance`` of the reference.
    hypotheses : list of dict
        Every distinct coarse pose carried through ICP (its coarse score, its evidence after
        the curve alignment and after ICP, its stages), best first.
    evidence : float
        The chosen pose's evidence: the share of compared points on the reference less the
        share inside a drift the reference scanned but off its surfaces.
    alternative_evidence : float
        The best evidence of a hypothesis that ended more than ``distinct_distance`` from the
        chosen pose (-1 when none did): near the chosen one, the networks fit two places
        alike.
    """

    transform: np.ndarray
    stages: dict[str, list[list[float]]] = field(default_factory=dict)
    junction_pairs: list[tuple[int, int]] = field(default_factory=list)
    curve_rms: float = float("nan")
    fitness: float = float("nan")
    hypotheses: list[dict[str, Any]] = field(default_factory=list)
    evidence: float = float("nan")
    alternative_evidence: float = -1.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        return {
            "method": "network",
            "transform": np.asarray(self.transform).tolist(),
            "stages": self.stages,
            "junction_pairs": [list(p) for p in self.junction_pairs],
            "curve_rms_m": self.curve_rms,
            "fitness": self.fitness,
            "evidence": self.evidence,
            "alternative_evidence": self.alternative_evidence,
            "hypotheses": self.hypotheses,
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


def _kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    w = np.ones(len(src)) if w is None else np.asarray(w, dtype=np.float64)
    cs = np.sum(src * w[:, None], axis=0) / w.sum()
    cd = np.sum(dst * w[:, None], axis=0) / w.sum()
    u, _, vt = np.linalg.svd(((src - cs) * w[:, None]).T @ (dst - cd))
    r = vt.T @ u.T
    if np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = vt.T @ u.T
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = cd - r @ cs
    return t


def _plan_dirs(net: CenterlineNetwork, min_length: float, window: float = 30.0,
               distinct_deg: float = 1.5) -> list[tuple[np.ndarray, float, np.ndarray, float]]:
    """Per edge of at least ``min_length`` metres, its straight stretches: the centroid of
    the samples (3,) of each ``window`` metres of the edge (half a window apart), their plan
    heading (radians, the principal direction of the samples in plan), that direction (2,)
    and the edge's length. Of the windows of one edge only those whose heading differs by
    more than ``distinct_deg`` from every one kept before are kept, so a straight edge gives
    one. The heading of a whole bent edge is none of its stretches' (a main drift that goes
    on up a ramp and turns read 3 degrees off its straight part, which laid the two epochs'
    main drifts across each other and left the right slide out of the candidates)."""
    out = []
    tol = np.radians(distinct_deg)
    for e in net.edges:
        if e.length < min_length:
            continue
        p = e.centerline.point_at(np.arange(0.0, e.length + 1e-9, 1.0))
        w = int(min(window, e.length))
        last = max(len(p) - 1 - w, 0)  # the final window ends at the edge's end
        starts = sorted({*range(0, last + 1, max(w // 2, 1)), last})
        kept: list[float] = []
        for a in starts:
            q = p[a: a + w + 1]
            c = q.mean(axis=0)
            _, _, vt = np.linalg.svd(q[:, :2] - c[:2], full_matrices=False)
            heading = float(np.arctan2(vt[0, 1], vt[0, 0]))
            # headings are axial (a line, not a way along it): compare modulo pi
            if any(abs(np.angle(np.exp(2j * (heading - h)))) / 2 < tol for h in kept):
                continue
            kept.append(heading)
            out.append((c, heading, vt[0], e.length))
    return out


def _plan_score(tree2: cKDTree, moved: np.ndarray, radius: float) -> float:
    """How many (moved) compared curve samples lie within ``radius`` of the reference curves
    in plan (curve samples are 1 m apart: metres of common curve)."""
    d, _ = tree2.query(moved[:, :2], distance_upper_bound=radius)
    return float(np.sum(d < radius))


def _candidates(ref_net: CenterlineNetwork, cmp_net: CenterlineNetwork, cmp_s: np.ndarray,
                ref_s: np.ndarray, tree2: cKDTree, radius: float) -> list[tuple[float, np.ndarray]]:
    """Coarse poses (yaw about the vertical and a translation), each with its plan score.

    * junction onto junction, each branch direction at one onto each at the other;
    * drift along drift: every straight stretch of an edge of one epoch laid along every
      straight stretch of the other's (both ways), slid along it a metre at a time. This
      needs no junction in either epoch: a cross-cut walked in one survey only, or seen a
      few metres in, leaves the two networks no junction in common, and the pose along the
      main drift then comes from everything else the two share (their curves' overlap
      here, the surfaces later).
    """
    out: list[tuple[float, np.ndarray]] = []
    for i, ji in enumerate(ref_net.junctions):
        di = _directions(ref_net, i)
        for j, jj in enumerate(cmp_net.junctions):
            for a in di:
                for b in _directions(cmp_net, j):
                    t = _yaw_transform(a - b, jj.position, ji.position)
                    out.append((_plan_score(tree2, apply_transform(t, cmp_s), radius), t))
    for ce, ca, _, cl in _plan_dirs(cmp_net, 10.0):
        for re_, ra, rd, rl in _plan_dirs(ref_net, 10.0):
            for yaw in (ra - ca, ra - ca + np.pi):
                base = _yaw_transform(yaw, ce, re_)  # centroid onto centroid
                moved = apply_transform(base, cmp_s)
                # the stretches' centroids may lie anywhere along their edges
                offsets = np.arange(-(rl + cl), rl + cl + 1e-9, 1.0)
                shift = np.zeros((len(offsets), 3))
                shift[:, :2] = offsets[:, None] * rd[None, :]
                pts = (moved[None, :, :] + shift[:, None, :]).reshape(-1, 3)
                d, _ = tree2.query(pts[:, :2], distance_upper_bound=radius)
                score = np.sum((d < radius).reshape(len(offsets), -1), axis=1)
                for k in np.flatnonzero(score >= max(0.5 * score.max(), 1)):
                    t = base.copy()
                    t[:3, 3] += shift[k]
                    out.append((float(score[k]), t))
    return out


def _distinct(cands: list[tuple[float, np.ndarray]], centre: np.ndarray, most: int,
              floor: float) -> list[tuple[float, np.ndarray]]:
    """The best candidate of each distinct pose (the compared network's centre moved more
    than 3 m apart, or turned more than 5 degrees apart), best first, at most ``most``,
    scoring at least ``floor`` of the best."""
    order = sorted(cands, key=lambda c: -c[0])
    kept: list[tuple[float, np.ndarray, np.ndarray, float]] = []
    for score, t in order:
        if kept and score < floor * kept[0][0]:
            break
        p = apply_transform(t, centre[None])[0]
        yaw = float(np.arctan2(t[1, 0], t[0, 0]))
        if any(np.linalg.norm(p - q) < 3.0 and abs(np.angle(np.exp(1j * (yaw - y))))
               < np.radians(5.0) for _, _, q, y in kept):
            continue
        kept.append((score, t, p, yaw))
        if len(kept) == most:
            break
    return [(s_, t) for s_, t, _, _ in kept]


def _plan_kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The weighted rigid motion in plan (a rotation about the vertical, a horizontal
    translation) moving ``src`` (K, 2) onto ``dst``, as a 4 x 4 transform."""
    cs = np.sum(src * w[:, None], axis=0) / w.sum()
    cd = np.sum(dst * w[:, None], axis=0) / w.sum()
    h = ((src - cs) * w[:, None]).T @ (dst - cd)
    yaw = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s_ = np.cos(yaw), np.sin(yaw)
    t = np.eye(4)
    t[:2, :2] = [[c, -s_], [s_, c]]
    t[:2, 3] = cd - t[:2, :2] @ cs
    return t


def _tilt_and_lift(src: np.ndarray, dst: np.ndarray, w: np.ndarray,
                   min_spread: float = 2.0) -> np.ndarray:
    """The small tilt and vertical shift that best carry the heights of ``src`` (K, 3) onto
    those of ``dst``: ``dz = a dx + b dy + c`` by weighted least squares about the centroid,
    the slopes damped along plan directions in which the samples spread less than
    ``min_spread`` metres (curves along one drift fix its pitch, not the roll about it).
    Returned as a 4 x 4 rigid transform (a rotation about the centroid)."""
    from scipy.spatial.transform import Rotation

    c = np.sum(src * w[:, None], axis=0) / w.sum()
    x = np.column_stack([src[:, 0] - c[0], src[:, 1] - c[1], np.ones(len(src))])
    dz = dst[:, 2] - src[:, 2]
    a = (x * w[:, None]).T @ x
    a[:2, :2] += np.eye(2) * w.sum() * min_spread**2
    slope_a, slope_b, lift = np.linalg.solve(a, (x * w[:, None]).T @ dz)
    r = Rotation.from_rotvec([slope_b, -slope_a, 0.0]).as_matrix()
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = c - r @ c + np.array([0.0, 0.0, lift])
    return t


def _align_curves(t: np.ndarray, cmp_s: np.ndarray, ref_s: np.ndarray, tree: cKDTree,
                  radius: float, max_tilt_deg: float = 10.0) -> np.ndarray:
    """ICP of the compared curve samples onto the reference ones with a shrinking match
    radius (3, 1, 0.3, 0.3 m) and Tukey weights: a rigid motion in plan, then the small tilt
    and lift of the compared frame. Curves are nearly lines, so a free 3-D rotation would
    turn about them at will; the tilt is fitted only along the directions the matched
    samples span, and never beyond ``max_tilt_deg`` from the start (SLAM maps are levelled
    by their IMU). ``ref_s`` samples the reference curves densely (every 0.1 m), so that a
    distance to them is a distance to the curve; a step that raises the truncated squared
    distance of the compared samples to the curves (each at most ``radius``) is not taken.
    (Counting the samples within ``radius`` instead refused a step that took a pose from
    0.75 to 0.40 m off and levelled it, because one sample fell out of reach.)"""
    def cost(tt: np.ndarray) -> float:
        d, _ = tree.query(apply_transform(tt, cmp_s), distance_upper_bound=radius)
        return float(np.sum(np.minimum(d, radius) ** 2))

    cos_max = np.cos(np.radians(max_tilt_deg))
    best, best_cost = t, cost(t)
    for r in (3.0, 1.0, 0.3, 0.3):
        moved = apply_transform(best, cmp_s)
        d, k = tree.query(moved, distance_upper_bound=r)
        m = np.isfinite(d)
        if m.sum() < 10:
            break
        w = (1.0 - (d[m] / r) ** 2) ** 2
        plan = _plan_kabsch(moved[m, :2], ref_s[k[m], :2], w)
        lifted = apply_transform(plan, moved[m])
        step = _tilt_and_lift(lifted, ref_s[k[m]], w) @ plan @ best
        if (step[:3, :3] @ t[:3, :3].T)[2, 2] < cos_max:
            break
        c = cost(step)
        if c <= best_cost:
            best, best_cost = step, c
    return best


def _evidence(t: np.ndarray, probe: np.ndarray, ref_tree: cKDTree, ref_net: CenterlineNetwork,
              half: np.ndarray, fit_distance: float, against: float = 0.3) -> float:
    """How well a pose explains the compared points: the share of ``probe`` points (moved by
    ``t``) within ``fit_distance`` of the reference, less the share that land inside a drift
    the reference scanned (within its half-width + 0.5 m of one of its curves, along it) but
    farther than ``against`` from any reference point: where the reference saw rock or open
    drift, a compared wall cannot be. Points beyond the reference's coverage count neither
    way, so a pose is not rewarded for sliding its ends over more of the other epoch's
    drift, only for its features meeting theirs."""
    moved = apply_transform(t, probe)
    d, _ = ref_tree.query(moved, distance_upper_bound=against)
    on = d < fit_distance
    pr = ref_net.project(moved, max_distance=float(half.max()) + 0.5)
    hw = np.where(pr.branch < len(half), half[np.minimum(pr.branch, len(half) - 1)], -np.inf)
    inside = pr.inside & (pr.distance <= hw + 0.5)
    off = inside & ~np.isfinite(d)
    return float(np.mean(on) - np.mean(off))


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
    pool: int = 64,
    hypotheses: int = 8,
    fit_distance: float = 0.1,
    distinct_distance: float = 10.0,
) -> NetworkRegistration:
    """Register the compared epoch onto the reference by the common part of their networks.

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (M, 3), (N, 3)
        The epochs, each in its own frame, metres.
    ref_net, cmp_net : CenterlineNetwork
        Their centreline networks.
    coarse_radius : float
        A compared curve sample within this distance of the reference curves (in plan)
        counts as common in the coarse search, metres.
    voxel, fine_distance : float
        Voxel size and match distance of the final point-to-plane ICP, metres.
    max_points : int
        Points per epoch used by the ICP (thinned at random, seeded).
    pool, hypotheses : int
        Distinct coarse poses judged by their points after the curve alignment (about 25 ms
        each), and how many of the best of those are carried through ICP (a quick one each,
        about a second); the one whose points the reference explains best
        (:func:`_evidence`) is kept. The pool is wide because the curves' overlap in plan
        does not rank slides along a drift: a main drift that goes on up a ramp, straight in
        plan, overlays the other epoch's main drift best when slid back by the ramp's length,
        and twelve distinct slides of that plateau left the right pose out.
    fit_distance : float
        A compared point within this distance of the reference lies on it, metres.
    distinct_distance : float
        A hypothesis that ends farther than this from the chosen pose (the compared network's
        centre, metres) is an alternative: its evidence is reported. Closer ones are slides
        along a drift, which the registration check's translation fits judge.

    Raises
    ------
    RegistrationError
        If less than 20 m of curve is common under every coarse pose.
    """
    import open3d as o3d

    # the compared curves sampled every metre (scores count metres of common curve), the
    # reference's every 0.1 m (a distance to its samples is a distance to its curves)
    ref_s, cmp_s = _samples(ref_net, 0.1), _samples(cmp_net)
    tree, tree2 = cKDTree(ref_s), cKDTree(ref_s[:, :2])
    cands = _candidates(ref_net, cmp_net, cmp_s, ref_s, tree2, coarse_radius)
    if not cands or max(c[0] for c in cands) < 20:
        best = max((c[0] for c in cands), default=0.0)
        raise RegistrationError(
            f"the two networks share only {best:.0f} m of centreline; do the epochs "
            "cover the same drifts?"
        )
    rng = np.random.default_rng(0)
    r = ref_xyz if len(ref_xyz) <= max_points else ref_xyz[
        random_keep(len(ref_xyz), max_points / len(ref_xyz), rng)]
    c = cmp_xyz if len(cmp_xyz) <= max_points else cmp_xyz[
        random_keep(len(cmp_xyz), max_points / len(cmp_xyz), rng)]
    origin = np.round(r[:: max(len(r) // 1000, 1)].mean(axis=0), -3)
    # (the voxel grid in Morton order: its normals took a third of the time)
    ref_pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(voxel_grid(r - origin, voxel)))
    ref_pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    rp, rn = np.asarray(ref_pc.points) + origin, np.asarray(ref_pc.normals)
    ref_tree = cKDTree(rp)
    probe = c[rng.choice(len(c), min(len(c), 20_000), replace=False)]
    half = np.array([float(e.centerline.meta.get("half_width_m", 1.0)) for e in ref_net.edges])

    def evidence(tt: np.ndarray, fit: float = fit_distance) -> float:
        return _evidence(tt, probe, ref_tree, ref_net, half, fit)

    # poses from the curves are good to decimetres (a 0.5 m slide along a rough drift took
    # the evidence at 0.1 m from 0.92 to 0.67, below a pose 5.8 m off), so they are ranked
    # with the tolerance of the evidence against (0.3 m), and only ICP's are judged at 0.1 m
    judged = []
    for score, t0 in _distinct(cands, cmp_s.mean(axis=0), pool, 0.5):
        t1 = _align_curves(t0, cmp_s, ref_s, tree, coarse_radius)
        judged.append((evidence(t1, 0.3), score, t0, t1))
    judged.sort(key=lambda x: -x[0])
    # each hypothesis through a quick ICP (both epochs thinned to 0.25 m once, the reference
    # keeping its normals averaged from the fine ones: a 1.2 s ICP onto the 0.1 m reference
    # took 0.4 s), judged; the chosen one through the full ICP
    quick_pc = ref_pc.voxel_down_sample(2.5 * voxel)
    qp, qn = np.asarray(quick_pc.points) + origin, np.asarray(quick_pc.normals)
    qn = qn / np.maximum(np.linalg.norm(qn, axis=1, keepdims=True), 1e-12)
    cq = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        c - origin)).voxel_down_sample(2.5 * voxel).points) + origin
    runs = []
    for ev0, score, t0, t1 in judged[:hypotheses]:
        t = icp_plane(qp, cq, t1, voxel=0.0, max_distance=1.0, iterations=20, ref_normals=qn)
        t = icp_plane(qp, cq, t, voxel=0.0, max_distance=fine_distance, iterations=20,
                      ref_normals=qn)
        runs.append({"coarse_score_m": score, "evidence_curves": ev0, "evidence": evidence(t),
                     "stages": {"coarse": t0.tolist(), "curves": t1.tolist(),
                                "quick": t.tolist()}, "transform": t})
    runs.sort(key=lambda x: -x["evidence"])
    chosen = runs[0]
    t = icp_plane(rp, c, chosen["transform"], voxel=voxel, max_distance=1.0, iterations=30,
                  ref_normals=rn)
    t = icp_plane(rp, c, t, voxel=voxel, max_distance=fine_distance, iterations=60,
                  ref_normals=rn)
    chosen["stages"]["fine"] = t.tolist()
    chosen["evidence"] = evidence(t)
    centre = cmp_s.mean(axis=0)
    p0 = apply_transform(t, centre[None])[0]
    others = [x["evidence"] for x in runs[1:]
              if np.linalg.norm(apply_transform(x["transform"], centre[None])[0] - p0)
              > distinct_distance]
    alternative = max(others, default=-1.0)
    d, _ = ref_tree.query(apply_transform(t, probe), distance_upper_bound=fit_distance)
    fitness = float(np.mean(np.isfinite(d)))
    moved_s = apply_transform(t, cmp_s)
    d, _ = tree.query(moved_s, distance_upper_bound=0.5)
    rms = float(np.sqrt(np.mean(d[np.isfinite(d)] ** 2))) if np.isfinite(d).any() else np.nan
    pairs = []
    for ji in ref_net.junctions:
        for jj in cmp_net.junctions:
            if np.linalg.norm(apply_transform(t, jj.position[None])[0] - ji.position) < 1.0:
                pairs.append((ji.id, jj.id))
    return NetworkRegistration(t, chosen["stages"], pairs, rms, fitness,
                               [{k: v for k, v in x.items() if k != "transform"} for x in runs],
                               chosen["evidence"], alternative)


def common_lengths(
    net: CenterlineNetwork, ref_xyz: np.ndarray, cmp_xyz: np.ndarray, *, bin_m: float = 1.0,
    min_points: int = 20, max_distance: float = 5.0,
) -> dict[int, float]:
    """Per edge, the length covered by both epochs (1 m bins with at least ``min_points``
    points of each, points within ``max_distance`` of the edge), metres."""
    nbins = {e.id: int(np.ceil(e.length / bin_m)) + 1 for e in net.edges}
    counts = [{i: np.zeros(nb, dtype=np.int64) for i, nb in nbins.items()} for _ in range(2)]
    for xyz, count in zip((ref_xyz, cmp_xyz), counts, strict=True):
        for a in range(0, len(xyz), _CHUNK):  # a chunk at a time: no full-size projection
            p = net.project(xyz[a:a + _CHUNK], max_distance=max_distance)
            for e in net.edges:
                m = (p.branch == e.id) & p.inside
                nb = nbins[e.id]
                count[e.id] += np.bincount(np.floor(p.chainage[m] / bin_m).astype(np.int64),
                                           minlength=nb)[:nb]
    return {e.id: float(np.sum((counts[0][e.id] >= min_points)
                               & (counts[1][e.id] >= min_points)) * bin_m)
            for e in net.edges}


def _plane_residual(ref_tree: cKDTree, normals: np.ndarray, ref_pts: np.ndarray,
                    xyz: np.ndarray, trim: float) -> np.ndarray:
    """Point-to-plane distance of ``xyz`` to the reference (NaN beyond ``trim``)."""
    d, k = ref_tree.query(xyz, distance_upper_bound=trim)
    out = np.full(len(xyz), np.nan)
    m = np.isfinite(d)
    out[m] = np.einsum("ij,ij->i", xyz[m] - ref_pts[k[m]], normals[k[m]])
    return out


_BORROW_CHUNK = 1_000_000
_BORROW_SOURCES = 200_000


def _borrow(xyz: np.ndarray, disp: np.ndarray, known: np.ndarray, *, reach: float,
            k: int = 8) -> None:
    """Give the points without a drift estimate of their own (``~known``: on an edge, or a
    stretch of one, with too few points for a block, such as the mouth of a cross-cut the
    other epoch did not walk, whose points lie nearest its axis) the mean displacement of the
    ``k`` nearest points with one, within ``reach`` (in place).

    Drift is smooth in space: left uncorrected, those points kept the rigid pose while the
    main drift around them moved by the correction (14 mm at a junction), and read it as
    change. The neighbours are drawn from every n-th corrected point, at most
    ``_BORROW_SOURCES`` of them (a smooth field needs no more, and no pass over the survey
    beyond the stride).
    """
    lost = np.flatnonzero(~known)
    have = np.flatnonzero(known)
    if lost.size == 0 or have.size == 0:
        return
    src = have[:: max(1, have.size // _BORROW_SOURCES)]
    tree = cKDTree(xyz[src])
    k = min(k, src.size)
    for a in range(0, lost.size, _BORROW_CHUNK):  # (chunk, k, 3) at a time
        part = lost[a:a + _BORROW_CHUNK]
        dist, j = tree.query(xyz[part], k=k, distance_upper_bound=reach)
        dist, j = dist.reshape(len(part), k), j.reshape(len(part), k)
        found = np.isfinite(dist)
        n = found.sum(axis=1)
        got = n > 0
        vals = disp[src[np.where(found, j, 0)]] * found[:, :, None]
        disp[part[got]] = vals[got].sum(axis=1) / n[got, None]


def correct_drift(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    net: CenterlineNetwork,
    *,
    block: float | tuple[float, ...] = 20.0,
    voxel: float = 0.1,
    max_distance: float = 0.1,
    min_gain: float = 0.0005,
    sample: int = 40_000,
    inplace: bool = False,
    change: float | None = 0.008,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Piecewise-rigid correction of SLAM drift along each edge, after a rigid registration.

    Along every reference edge, blocks ``block`` metres long (centred every ``block``, each
    reaching half a block into its neighbours) of the compared points are registered onto the
    reference by point-to-plane ICP with a tight match distance (``max_distance``: a local
    change such as a sag, a bulge or a heave is a small part of a block's shell and outside
    the match distance where it is large). The blocks' displacements are blended linearly along
    the chainage between block centres, so the correction is continuous along each edge. A
    block with too few points gets no estimate, and the blend runs between the blocks beside it;
    points with no block at all (an edge too thin for one, like the main drift's floor at the
    mouth of a cross-cut the compared walker did not enter) take their nearest corrected
    neighbours' displacement within a block's length (:func:`_borrow`).

    Each block is fitted twice when ``change`` is given: after the first fit, the points of
    1 m patches whose median misfit exceeds ``change`` (and three standard errors) are left
    out, and the block is fitted again without them. A sag, a bulge, a heave or changed coal
    then does not pull the block's fit towards it; only what moved less than ``change``
    across a patch still weighs in.

    The correction is used only when it lowers the compared points' coherent misfit
    (:func:`~tunneldef.registration.verify.coherent_misfit`: the point-to-plane misfit shared
    by neighbouring points, which the scans' noise does not explain) by more than ``min_gain``
    (the RMS point-to-plane residual, trimmed at ``max_distance``, where that cannot be
    measured); otherwise the points are returned unchanged, and where the coherent misfit is
    at most ``min_gain`` to begin with, no block is fitted at all. With several block lengths
    (longest first), a shorter one is kept only when it lowers the coherent misfit by more
    than ``min_gain`` below the longer one's: SLAM drift that bends within a long block
    (measured: 20 m blocks left 3.5 mm of coherent misfit and 6.2 % of a drift's unchanged
    shell beyond 10 mm, 10 m blocks 1.7 mm and 0.15 %) is taken out by the shorter blocks,
    and a pair without it keeps the longer ones, which a long change moves less.

    Parameters
    ----------
    ref_xyz, cmp_xyz : ndarray, shape (M, 3), (N, 3)
        Reference and registered compared points, metres.
    net : CenterlineNetwork
        The reference network (the compared points are assigned to its edges); a single
        drift is a network of one edge.
    block : float or tuple of float
        Block length(s), m, longest first.
    change : float or None
        Misfit of a 1 m patch beyond which its points are left out of a block's second fit,
        m; None fits each block once, on all its points.
    inplace : bool
        Correct ``cmp_xyz`` itself (when used) rather than a copy: one survey-sized array
        less in memory.

    Returns
    -------
    xyz : ndarray, shape (N, 3)
        The corrected compared points (or ``cmp_xyz`` itself when not used, or ``inplace``).
    info : dict
        ``used``, ``block_m`` (the length kept), residual RMS and coherent misfit before and
        after (m), ``tried`` (each length's coherent misfit after), per edge the blocks'
        centres and their displacement at the block centre (m).
    """
    rng = np.random.default_rng(0)
    # (normals about the centroid: in survey coordinates Open3D's own came out at random)
    rp = voxel_grid(ref_xyz, voxel / 2)
    rn = plane_normals(rp, 4 * voxel, 30)
    tree = cKDTree(rp)

    def displacement(block: float) -> tuple[np.ndarray, dict[str, Any], list[float]]:
        """The blended displacement of every compared point for ``block``-metre blocks,
        each edge's blocks, and the share of each block left out as changed."""
        # float32: the displacements are centimetres, held to far below a micrometre
        disp = np.zeros(cmp_xyz.shape, dtype=np.float32)
        wsum = np.zeros(len(cmp_xyz), dtype=np.float32)
        edges: dict[str, Any] = {}
        excluded: list[float] = []
        for e in net.edges:
            mc = np.flatnonzero(branch_c == e.id)
            if len(mc) < 1000:
                continue
            n_blocks = max(int(round(e.length / block)), 1)
            centres = (np.arange(n_blocks) + 0.5) * e.length / n_blocks
            width = e.length / n_blocks
            # the edge's points in chainage order: a block's points are one run of them
            order = np.argsort(chain_c[mc], kind="stable")
            mc = mc[order]
            s = chain_c[mc]
            del order
            rows = []
            for c in centres:
                a = np.searchsorted(s, c - 0.75 * width, side="left")
                b = np.searchsorted(s, c + 0.75 * width, side="right")
                sel = np.sort(mc[a:b])
                rsel = (pr.branch == e.id) & (np.abs(pr.chainage - c) <= 0.75 * width + 1.0)
                if len(sel) < 2000 or rsel.sum() < 2000:
                    rows.append(None)  # no estimate: the blocks beside it, or the points near
                    continue
                # (in the points' own order: queries that follow the survey run about four
                # times faster than in random order)
                pick = sel if len(sel) <= sample \
                    else np.sort(rng.choice(sel, sample, replace=False))
                t = icp_plane(rp[rsel], cmp_xyz[pick], np.eye(4), voxel=voxel,
                              max_distance=max_distance, iterations=30, ref_normals=rn[rsel])
                if change is not None:
                    bad = _changed_patches(apply_transform(t, cmp_xyz[pick]), rp, rn, tree,
                                           change)
                    excluded.append(float(np.mean(bad)))
                    if bad.any() and np.sum(~bad) >= 2000:
                        t = icp_plane(rp[rsel], cmp_xyz[pick[~bad]], t, voxel=voxel,
                                      max_distance=max_distance, iterations=30,
                                      ref_normals=rn[rsel])
                rows.append(t)
            # blend the blocks' displacements with hat functions on the centres of the blocks
            # that have one (a block without: the linear blend of those on either side)
            est = [(c, t) for c, t in zip(centres, rows, strict=True) if t is not None]
            at = [c for c, _ in est]
            for k, (c, t) in enumerate(est):
                lo = np.searchsorted(s, at[k - 1], side="right") if k > 0 else 0
                hi = np.searchsorted(s, at[k + 1], side="left") if k + 1 < len(at) else len(s)
                for a in range(lo, hi, _CHUNK):  # a chunk at a time: no full-size temporaries
                    sk = s[a:min(a + _CHUNK, hi)]
                    up = np.clip((sk - at[k - 1]) / (c - at[k - 1]), 0, 1) if k > 0 \
                        else np.ones_like(sk)
                    down = np.clip((at[k + 1] - sk) / (at[k + 1] - c), 0, 1) \
                        if k + 1 < len(at) else np.ones_like(sk)
                    w = np.where(sk <= c, up, down)
                    idx = mc[a:a + len(sk)]
                    p = cmp_xyz[idx]
                    disp[idx] += w[:, None] * (apply_transform(t, p) - p)
                    wsum[idx] += w
            edges[str(e.id)] = {
                "block_centres_m": centres.tolist(),
                "block_shift_m": [None if t is None else float(np.linalg.norm(
                    apply_transform(t, e.centerline.point_at(c))[0]
                    - e.centerline.point_at(c)[0]))
                    for c, t in zip(centres, rows, strict=True)],
            }
            del mc, s
        ok = wsum > 0
        disp[ok] /= wsum[ok, None]
        del wsum
        _borrow(cmp_xyz, disp, ok, reach=block)
        return disp, edges, excluded

    probe = np.sort(rng.choice(len(cmp_xyz), min(len(cmp_xyz), 200_000), replace=False))
    before = _plane_residual(tree, rn, rp, cmp_xyz[probe], max_distance)
    # the misfit shared by neighbouring points, which the scans' noise does not drown: at
    # +-2 cm noise a 5 mm drift residue moves the RMS above by 0.4 mm, and this by 5 mm
    cb = coherent_misfit(cmp_xyz[probe], rp, rn, tree)
    lengths = np.atleast_1d(np.asarray(block, dtype=float))
    if np.isfinite(cb) and cb <= min_gain:
        # no correction can take out more than the coherent misfit there is: none is tried
        fin = np.isfinite(before)
        rb = float(np.sqrt(np.mean(before[fin] ** 2))) if fin.any() else np.nan
        return cmp_xyz, {
            "block_m": float(lengths[0]), "edges": {}, "tried": [], "used": False,
            "residual_rms_before_m": rb, "residual_rms_after_m": rb, "coherent_before_m": cb,
            "coherent_after_m": cb, "min_gain_m": min_gain, "change_m": change,
            "changed_share_max": None}
    # each point's edge and chainage, for the blocks (not needed where none is fitted)
    branch_c, chain_c = _branch_chainage(net, cmp_xyz, max_distance=10.0)
    pr = net.project(rp, max_distance=10.0)
    best: dict[str, Any] | None = None
    tried = []
    for length in lengths:
        if best is not None and np.isfinite(best["ca"]) and best["ca"] <= min_gain:
            break  # shorter blocks cannot gain min_gain over what is left
        disp, edges, excluded = displacement(float(length))
        probe_out = cmp_xyz[probe] + disp[probe]
        after = _plane_residual(tree, rn, rp, probe_out, max_distance)
        both = np.isfinite(before) & np.isfinite(after)
        rb = float(np.sqrt(np.mean(before[both] ** 2))) if both.any() else np.nan
        ra = float(np.sqrt(np.mean(after[both] ** 2))) if both.any() else np.nan
        ca = coherent_misfit(probe_out, rp, rn, tree)
        tried.append({"block_m": float(length), "coherent_after_m": ca,
                      "residual_rms_after_m": ra,
                      "changed_share_max": max(excluded) if excluded else None})
        if best is None or (_gain(cb, ca, rb, ra) - _gain(cb, best["ca"], rb, best["ra"])
                            > min_gain):
            best = {"disp": disp, "edges": edges, "block": float(length), "rb": rb,
                    "ra": ra, "ca": ca, "excluded": excluded}
        del disp
    assert best is not None
    used = bool(_gain(cb, best["ca"], best["rb"], best["ra"]) > min_gain)
    info: dict[str, Any] = {
        "block_m": best["block"], "edges": best["edges"], "tried": tried, "used": used,
        "residual_rms_before_m": best["rb"], "residual_rms_after_m": best["ra"],
        "coherent_before_m": cb, "coherent_after_m": best["ca"], "min_gain_m": min_gain,
        "change_m": change,
        "changed_share_max": max(best["excluded"]) if best["excluded"] else None}
    if not used:
        return cmp_xyz, info
    disp = best.pop("disp")
    out = cmp_xyz if inplace else np.empty_like(cmp_xyz)
    for a in range(0, len(cmp_xyz), _CHUNK):
        out[a:a + _CHUNK] = cmp_xyz[a:a + _CHUNK] + disp[a:a + _CHUNK]
    return out, info


def _gain(cb: float, ca: float, rb: float, ra: float) -> float:
    """What a correction gained: the coherent misfit before less after (``cb - ca``), or the
    RMS residual's (``rb - ra``) where the coherent misfit cannot be measured, m."""
    if np.isfinite(cb) and np.isfinite(ca):
        return cb - ca
    return rb - ra if np.isfinite(rb) and np.isfinite(ra) else -np.inf


def _changed_patches(xyz: np.ndarray, rp: np.ndarray, rn: np.ndarray, tree: cKDTree,
                     change: float, cell: float = 1.0) -> np.ndarray:
    """True for the points of ``xyz`` in a ``cell``-metre patch whose median point-to-plane
    misfit against the reference exceeds ``change`` and three of its standard errors: the
    surface there moved (a sag, a bulge, a heave) or was never the same (coal), and a block's
    drift is fitted without it."""
    pm = patch_medians(xyz, rp, rn, tree, cell=cell, min_points=15)
    if pm is None:
        return np.zeros(len(xyz), dtype=bool)
    se = np.sqrt(0.5 * np.pi) * pm.sigma / np.sqrt(np.maximum(pm.count, 1))
    bad = pm.full & (np.abs(np.nan_to_num(pm.median)) > np.maximum(change, 3.0 * se))
    return (pm.cell >= 0) & bad[np.maximum(pm.cell, 0)]


def _branch_chainage(net: CenterlineNetwork, xyz: np.ndarray, *,
                     max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Each point's edge and chainage on it (``net.project``), ``_CHUNK`` points at a time:
    no full-size projection arrays beyond these two."""
    branch = np.empty(len(xyz), dtype=np.uint16)
    chainage = np.empty(len(xyz))
    for a in range(0, len(xyz), _CHUNK):
        p = net.project(xyz[a:a + _CHUNK], max_distance=max_distance)
        branch[a:a + _CHUNK], chainage[a:a + _CHUNK] = p.branch, p.chainage
    return branch, chainage
