"""An independent look at a finished registration: does it fit as well as the scans allow, and
do two different measures of the position along the axis agree?

Neither figure is produced by the registration itself, so neither can be talked into agreeing
with it:

* **fit against the scans' own noise.** The compared points' robust point-to-plane distance to
  the reference surface is set against the same distance measured within each epoch (one half
  of its points against the planes of the other half). A correct registration leaves the
  cross-epoch figure at the level of the noisier epoch; a tilt or a lateral offset adds to it.
  Deformation touches a minority of the shell and the robust scale (1.4826 MAD) ignores it.
* **the along-axis position twice.** From the final pose, the section-correlation
  (:func:`.axial.coarse_shift`, to a 0.25 m bin, with the spread of equally good matches) and
  the point-to-plane slide (:func:`.axial.fine_shift`, with its standard deviation) must both
  find no further shift, and agree with each other within their uncertainties. A slide along a
  featureless prism passes the first test and fails this one (or shows as undetermined).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..curve import Centerline
from ..spatial import random_subset
from ..transforms import apply_transform
from .axial import coarse_shift
from .views import axial_correction, normals

__all__ = ["RegistrationCheck", "verify_registration"]

_SAMPLE = 25_000  # points per epoch and half the checks use
_REACH = 0.1  # m: correspondences farther apart are not the same surface
_NORMAL_RADIUS = 0.15  # m, as the registration's normals


@dataclass(frozen=True)
class RegistrationCheck:
    """Independent figures of a registration (metres).

    Attributes
    ----------
    cross_residual : float
        Robust sigma (1.4826 MAD) of the compared points' distance to the reference planes.
    ref_residual, cmp_residual : float
        The same within each epoch (half of its points against the planes of the other half):
        what the scans themselves show.
    residual_ratio : float
        ``cross_residual / max(ref_residual, cmp_residual)``; about 1 when registered.
    excess : float
        ``sqrt(max(cross^2 - max(ref, cmp)^2, 0))``: the misfit the scans' noise does not
        explain (registration error, plus deformation the robust scale did not ignore).
    coarse_shift, coarse_spread : float
        Remaining along-axis shift by section correlation (0.25 m bins) and the spread of
        equally good matches (large: the overlap has no feature along the axis).
    fine_shift, fine_sigma : float
        Remaining along-axis shift by point-to-plane sliding, and its standard deviation.
    axial_disagreement : float
        ``|coarse_shift - fine_shift|`` expressed in units of their combined uncertainty
        (half a bin and ``fine_sigma`` added in quadrature); <= 3 when they agree; NaN when
        the point-to-plane slide found nothing to hold on to.
    """

    cross_residual: float
    ref_residual: float
    cmp_residual: float
    residual_ratio: float
    excess: float
    coarse_shift: float
    coarse_spread: float
    fine_shift: float
    fine_sigma: float
    axial_disagreement: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (non-finite values become None)."""
        return {k: (float(v) if np.isfinite(v) else None) for k, v in self.__dict__.items()}


def _plane_sigma(src: np.ndarray, dst: np.ndarray, dst_n: np.ndarray, tree: cKDTree) -> float:
    d, j = tree.query(src, distance_upper_bound=_REACH, workers=-1)
    ok = np.isfinite(d)
    if ok.sum() < 100:
        return np.inf
    r = np.einsum("ij,ij->i", src[ok] - dst[j[ok]], dst_n[j[ok]])
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def verify_registration(
    ref_xyz: np.ndarray,
    cmp_xyz: np.ndarray,
    ref_centerline: Centerline,
    *,
    transform: np.ndarray | None = None,
    search: float = 10.0,
) -> RegistrationCheck:
    """Independent figures of a registration (see the module notes).

    Parameters
    ----------
    ref_xyz : ndarray, shape (N, 3)
        Reference points, metres.
    cmp_xyz : ndarray, shape (M, 3)
        Compared points, metres: registered already, or in their own frame with
        ``transform``.
    ref_centerline : Centerline
        The reference centreline (reference frame).
    transform : ndarray, shape (4, 4), optional
        Compared -> reference transform (applied to a subsample only).
    search : float
        Largest along-axis shift the section correlation looks for, metres.

    Returns
    -------
    RegistrationCheck
    """
    origin = np.asarray(ref_xyz[0], dtype=np.float64)
    ref = random_subset(np.asarray(ref_xyz) - origin, 2 * _SAMPLE, 11)
    cmp = random_subset(np.asarray(cmp_xyz), 2 * _SAMPLE, 12)
    if transform is not None:
        cmp = apply_transform(np.asarray(transform, dtype=np.float64), cmp)
    cmp = cmp - origin
    cl = ref_centerline.transformed(_shift_matrix(-origin))
    # only the stretch both epochs cover, 0.5 m inside the reference's ends
    pc = cl.project(cmp)
    cmp = cmp[(pc.chainage > 0.5) & (pc.chainage < cl.length - 0.5)]
    ref_a, ref_b = ref[0::2], ref[1::2]
    cmp_a, cmp_b = cmp[0::2], cmp[1::2]
    ref_bn = normals(ref_b, _NORMAL_RADIUS)
    ref_tree = cKDTree(ref_b)
    cross = _plane_sigma(cmp_a, ref_b, ref_bn, ref_tree)
    own_ref = _plane_sigma(ref_a, ref_b, ref_bn, ref_tree)
    own_cmp = (
        _plane_sigma(cmp_a, cmp_b, normals(cmp_b, _NORMAL_RADIUS), cKDTree(cmp_b))
        if len(cmp_b) >= 100
        else np.inf
    )
    own = max(own_ref, own_cmp)
    ratio = cross / own if own > 0 and np.isfinite(own) else np.inf
    excess = float(np.sqrt(max(cross**2 - own**2, 0.0))) if np.isfinite(ratio) else np.inf

    rp = cl.project(ref)
    mp = cl.project(cmp)
    c_shift, c_spread = coarse_shift(
        (rp.chainage, rp.lateral, rp.vertical), (mp.chainage, mp.lateral, mp.vertical), cl,
        search=search,
    )
    _, fine = axial_correction(ref, normals(ref, _NORMAL_RADIUS), cmp, cl)
    combined = float(np.hypot(0.125, fine.uncertainty))
    # without a point-to-plane solution (no surface across the axis) there is nothing to
    # compare: NaN, and the spread of the section correlation decides alone
    disagreement = abs(c_shift - fine.shift) / combined if fine.informative else np.nan
    return RegistrationCheck(
        cross_residual=cross,
        ref_residual=own_ref,
        cmp_residual=own_cmp,
        residual_ratio=float(ratio),
        excess=excess,
        coarse_shift=float(c_shift),
        coarse_spread=float(c_spread),
        fine_shift=float(fine.shift),
        fine_sigma=float(fine.uncertainty),
        axial_disagreement=float(disagreement),
    )


def _shift_matrix(t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m
