"""The tunnel frame: principal (PCA) axes of a cloud, world <-> tunnel coordinates.

The tunnel frame is the paper's (§3.1.1): x along the tunnel (largest variance), y across it,
z up. Handheld SLAM clouds are gravity-aligned, so by default z is kept as the world vertical and
only the horizontal axes come from PCA; ``vertical="pca"`` takes all three axes from PCA as the
paper does (for clouds that are not levelled).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from .cloud import check_points
from .errors import NotATunnelError
from .spatial import random_subset

__all__ = ["TunnelFrame", "principal_frame", "pca_axes"]

_MAX_PCA_POINTS = 200_000


@dataclass(frozen=True)
class TunnelFrame:
    """A right-handed orthonormal frame.

    Attributes
    ----------
    origin : ndarray, shape (3,)
        World coordinates of the frame origin (metres), the cloud's centroid.
    axes : ndarray, shape (3, 3)
        Rows are the unit x (along), y (across, to the left) and z (up) axes in world coordinates.
    variances : ndarray, shape (3,)
        Variance of the points along each axis (m^2).
    """

    origin: np.ndarray
    axes: np.ndarray
    variances: np.ndarray

    def to_local(self, xyz: np.ndarray) -> np.ndarray:
        """World (N, 3) -> tunnel-frame (N, 3) coordinates."""
        return (np.asarray(xyz, dtype=np.float64) - self.origin) @ self.axes.T

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """Tunnel-frame (N, 3) -> world (N, 3) coordinates."""
        return np.asarray(local, dtype=np.float64) @ self.axes + self.origin

    @property
    def matrix(self) -> np.ndarray:
        """4 x 4 homogeneous transform mapping world to tunnel-frame coordinates."""
        m = np.eye(4)
        m[:3, :3] = self.axes
        m[:3, 3] = -self.axes @ self.origin
        return m

    @property
    def elongation(self) -> float:
        """sqrt(var_x / var_y): about L / (sqrt(3) * W) for a straight tunnel of length L."""
        return float(np.sqrt(self.variances[0] / max(self.variances[1], 1e-12)))


def pca_axes(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, principal axes (rows, by decreasing variance) and variances of points.

    The axes form a right-handed basis; the first axis is oriented so that its largest world
    component is positive (a deterministic choice: PCA itself has no sign).
    """
    pts = random_subset(check_points(xyz, min_points=3), _MAX_PCA_POINTS)
    centroid = pts.mean(axis=0)
    cov = np.cov((pts - centroid).T)
    w, v = np.linalg.eigh(cov)
    order = np.argsort(w)[::-1]
    w, axes = w[order], v[:, order].T.copy()
    if axes[0, np.argmax(np.abs(axes[0]))] < 0:
        axes[0] = -axes[0]
    if axes[2, 2] < 0:
        axes[2] = -axes[2]
    axes[1] = np.cross(axes[2], axes[0])
    return centroid, axes, w


def principal_frame(
    xyz: np.ndarray,
    *,
    vertical: Literal["world", "pca"] = "world",
    min_elongation: float = 1.5,
) -> TunnelFrame:
    """The tunnel frame of a cloud by principal component analysis (paper §3.1.1, §3.2.1).

    Parameters
    ----------
    xyz : ndarray, shape (N, 3)
        World coordinates, metres.
    vertical : {"world", "pca"}
        ``"world"`` keeps z as the world vertical and finds the tunnel direction by PCA of the
        horizontal coordinates (right for gravity-aligned SLAM clouds); ``"pca"`` uses the
        third principal axis as z, as in the paper.
    min_elongation : float
        Smallest acceptable ratio of the standard deviations along and across the axis; a
        cloud below it has no tunnel axis (a blob, a plane patch) and raises.

    Returns
    -------
    TunnelFrame

    Raises
    ------
    NotATunnelError
        If the cloud is not elongated enough to define an axis.
    """
    pts = random_subset(check_points(xyz, min_points=10), _MAX_PCA_POINTS)
    centroid = pts.mean(axis=0)
    if vertical == "pca":
        _, axes, _ = pca_axes(pts)
    elif vertical == "world":
        d = pts[:, :2] - centroid[:2]
        w, v = np.linalg.eigh(np.cov(d.T))
        ax = v[:, np.argmax(w)]
        if ax[np.argmax(np.abs(ax))] < 0:
            ax = -ax
        x = np.array([ax[0], ax[1], 0.0])
        z = np.array([0.0, 0.0, 1.0])
        axes = np.stack([x, np.cross(z, x), z])
    else:
        raise ValueError(f"vertical must be 'world' or 'pca', got {vertical!r}")
    local = (pts - centroid) @ axes.T
    variances = local.var(axis=0)
    frame = TunnelFrame(centroid, axes, variances)
    if frame.elongation < min_elongation:
        raise NotATunnelError(
            f"the cloud is not elongated (along/across spread ratio {frame.elongation:.2f} < "
            f"{min_elongation}); is it a tunnel? a tunnel scan should be several times longer "
            "than wide"
        )
    return frame
