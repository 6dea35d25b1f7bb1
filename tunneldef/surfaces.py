"""The codes of the four surfaces of a tunnel section, shared by the results and the truth."""

from __future__ import annotations

__all__ = ["ROOF", "LEFT_WALL", "RIGHT_WALL", "FLOOR", "NO_SURFACE", "SURFACE_NAMES"]

ROOF, LEFT_WALL, RIGHT_WALL, FLOOR = 0, 1, 2, 3
#: Points on no surface (equipment, clutter) in the synthetic truth.
NO_SURFACE = 255
#: Names of the surface codes 0..3, in code order.
SURFACE_NAMES: tuple[str, ...] = ("roof", "left_wall", "right_wall", "floor")
