"""The in-memory point cloud: coordinates plus named per-point fields."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import InvalidCloudError

__all__ = ["Cloud", "check_points"]


def check_points(xyz: Any, *, name: str = "xyz", min_points: int = 1) -> np.ndarray:
    """Validate an (N, 3) coordinate array and return it as contiguous float64.

    Parameters
    ----------
    xyz : array_like, shape (N, 3)
        Coordinates in metres.
    name : str
        Name used in error messages.
    min_points : int
        Smallest acceptable N.

    Raises
    ------
    InvalidCloudError
        If the array is not N x 3, has fewer than ``min_points`` rows or non-finite values.
    """
    arr = np.asarray(xyz)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidCloudError(f"{name} must be an N x 3 array, got shape {arr.shape}")
    if arr.shape[0] < min_points:
        raise InvalidCloudError(
            f"{name} has {arr.shape[0]} points; at least {min_points} are needed"
        )
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise InvalidCloudError(f"{name} has {bad} points with NaN or infinite coordinates")
    return arr


@dataclass
class Cloud:
    """A point cloud: float64 coordinates and named per-point fields.

    Parameters
    ----------
    xyz : ndarray, shape (N, 3), float64
        Coordinates in metres (world frame, full precision: survey coordinates are kept).
    fields : dict of str to ndarray, shape (N,)
        Per-point attributes (intensity, classification, scalar fields...), any numeric dtype.
    meta : dict
        Source metadata used to write a file back faithfully (e.g. the LAS header, the PLY
        element layout, the path it was read from). Readers fill it; algorithms ignore it.
    """

    xyz: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise InvalidCloudError(f"xyz must be an N x 3 array, got shape {self.xyz.shape}")
        n = self.xyz.shape[0]
        for name, values in self.fields.items():
            values = np.asarray(values)
            if values.shape[0] != n:
                raise InvalidCloudError(
                    f"field {name!r} has {values.shape[0]} values for {n} points"
                )
            self.fields[name] = values

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def __getitem__(self, index: Any) -> Cloud:
        """Subset by boolean mask, index array or slice; returns a new :class:`Cloud`."""
        return Cloud(
            self.xyz[index],
            {k: v[index] for k, v in self.fields.items()},
            dict(self.meta),
        )

    def add_fields(self, fields: Mapping[str, np.ndarray]) -> None:
        """Add or replace several per-point fields at once."""
        n = len(self)
        for name, values in fields.items():
            values = np.asarray(values)
            if values.shape != (n,):
                raise InvalidCloudError(
                    f"field {name!r} must have shape ({n},), got {values.shape}"
                )
            self.fields[name] = values

    def add_field(self, name: str, values: np.ndarray) -> None:
        """Add or replace one per-point field."""
        self.add_fields({name: values})

    def copy(self) -> Cloud:
        """A deep copy (arrays copied, metadata shallow-copied)."""
        return Cloud(self.xyz.copy(), {k: v.copy() for k, v in self.fields.items()},
                     dict(self.meta))

    def transformed(self, transform: np.ndarray) -> Cloud:
        """A copy with coordinates mapped by a 4 x 4 rigid transform (fields unchanged)."""
        from .transforms import apply_transform

        return Cloud(apply_transform(transform, self.xyz), dict(self.fields), dict(self.meta))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the axis-aligned bounding box, metres."""
        return self.xyz.min(axis=0), self.xyz.max(axis=0)
