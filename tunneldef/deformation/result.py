"""The per-point result of the deformation stage and the fields it writes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DeformationResult"]


@dataclass(frozen=True)
class DeformationResult:
    """Per-point deformation of the compared epoch (all arrays shape (N,), compared order).

    Attributes
    ----------
    deformation : float64, metres
        Signed deformation: negative = the surface moved into the tunnel (roof sag, wall bulge,
        floor heave), positive = outward. ``knn``: the distance to the KNN-centroid
        counterpart (paper §3.3.1), signed by the section deformation ``horizontal +
        vertical``. NaN where the point has no counterpart: beyond the chainage range the
        reference covers, or (``knn``) farther than ``max_distance`` from it.
    horizontal, vertical : float64, metres
        Change of |lateral| and |vertical| distance to the centreline between the counterpart
        and the point (paper §3.3.2, Manhattan split); negative = towards the centreline.
    chainage : float64, metres
        Chainage of each point on the reference centreline.
    surface : uint8
        0 roof, 1 left wall, 2 right wall, 3 floor (:data:`SURFACE_NAMES`).
    shell : bool
        True on the tunnel shell; False on equipment, conveyor, coal, people, outliers.
    xyz : float64, shape (N, 3)
        The compared points (reference frame) the values belong to; used for smoothing.
    method : str
        ``"knn"`` or ``"robust"``.
    k : int or None
        Neighbours of the KNN centroid (``knn`` only).
    significant, lod95 : optional
        ``robust`` only: change beyond the 95 % level of detection, and that level (m).
    centerline_length : float or None
        Length of the reference centreline, metres.
    two_surfaces : bool, optional
        ``robust`` only: points whose change one epoch contradicts by showing both surfaces
        (a SLAM map's double wall); their deformation is NaN.
    spread_ratio : float16, optional
        ``robust`` only: on the measured shell, the spread of the compared epoch's cylinder
        over the reference's (about 1 where both epochs see one surface alike; NaN
        elsewhere). Not written; the quality checks ``deformation.thick_surface`` and
        ``deformation.epoch_spread`` read it.
    typical_spread : (float, float), optional
        ``robust`` only: the survey's typical cylinder spread of the reference and the
        compared epoch, metres.
    """

    deformation: np.ndarray
    horizontal: np.ndarray
    vertical: np.ndarray
    chainage: np.ndarray
    surface: np.ndarray
    shell: np.ndarray
    xyz: np.ndarray
    method: str = "knn"
    k: int | None = None
    significant: np.ndarray | None = None
    lod95: np.ndarray | None = None
    centerline_length: float | None = None
    two_surfaces: np.ndarray | None = None
    spread_ratio: np.ndarray | None = None
    typical_spread: tuple[float, float] | None = None

    def __len__(self) -> int:
        return int(self.deformation.shape[0])

    def fields(self) -> dict[str, np.ndarray]:
        """Per-point fields to write: float32 ``deformation``, ``deformation_horizontal``,
        ``deformation_vertical``, ``chainage``; uint8 ``surface``, ``shell``; plus uint8
        ``significant`` and float32 ``lod95`` when the robust estimator gave them. Arrays
        already of their field's type are shared, not copied."""
        out = {
            "deformation": self.deformation.astype(np.float32, copy=False),
            "deformation_horizontal": self.horizontal.astype(np.float32, copy=False),
            "deformation_vertical": self.vertical.astype(np.float32, copy=False),
            "chainage": self.chainage.astype(np.float32, copy=False),
            "surface": self.surface.astype(np.uint8, copy=False),
            "shell": self.shell.astype(np.uint8),
        }
        if self.significant is not None:
            out["significant"] = np.asarray(self.significant).astype(np.uint8)
        if self.lod95 is not None:
            out["lod95"] = np.asarray(self.lod95).astype(np.float32, copy=False)
        return out
