"""Stage 1: the tunnel centreline of one epoch (paper §3.1).

Modules: :mod:`.extract` (the passes: PCA frame, slices, section lines, NURBS, re-slicing along
the curve), :mod:`.slicing`, :mod:`.roof_floor` (1-D Gaussian KDE peaks), :mod:`.walls` (2-D
linear-kernel density, Canny, Hough) and :mod:`.fit` (least-squares NURBS). The curve type
itself, :class:`tunneldef.curve.Centerline`, lives on the ground floor so that later stages
use it without loading this stage.
"""

from __future__ import annotations

from ..curve import Centerline, Projection
from .extract import CenterlineResult, SliceRecord, analyse_slice, extract_centerline

__all__ = [
    "Centerline",
    "Projection",
    "SliceRecord",
    "CenterlineResult",
    "extract_centerline",
    "analyse_slice",
]
