"""4 x 4 rigid transforms: the one place that maps points by them."""

from __future__ import annotations

import numpy as np

__all__ = ["apply_transform"]


def apply_transform(transform: np.ndarray, xyz: np.ndarray, *, blas: bool = True) -> np.ndarray:
    """Points mapped by a 4 x 4 rigid (or affine) transform.

    Parameters
    ----------
    transform : ndarray, shape (4, 4)
        Homogeneous transform; its last row is ignored.
    xyz : ndarray, shape (N, 3)
        Points, metres (N may be 0).
    blas : bool
        True: one matrix product (BLAS, may use several threads). False: ``einsum``, which
        uses no BLAS threads (for callers that already run in threads, as the synthetic
        generator does); the two differ in the last bit (about 1e-13 m at 1e3 m).

    Returns
    -------
    ndarray, shape (N, 3), float64
    """
    t = np.asarray(transform, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    if not blas:
        out = np.einsum("ij,kj->ik", xyz, t[:3, :3])
        out += t[:3, 3]
        return out
    return xyz @ t[:3, :3].T + t[:3, 3]
