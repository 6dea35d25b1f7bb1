"""Stage 2: registration of the compared epoch onto the reference (paper §3.2).

:func:`register` takes both epochs' points and centrelines (stage 1's output; it never runs
stage 1 itself) and returns a :class:`Registration`. Modules: :mod:`.register` (the stage),
:mod:`.views` (the paper's cross-section, longitudinal and plan views), :mod:`.axial` (the
shift along the axis), :mod:`.refine` (stable-shell refinement), :mod:`.baselines` (ICP, GICP,
NDT) and :mod:`.metrics`.
"""

from __future__ import annotations

from .metrics import fitness, overlap_fraction, rotation_error_deg, slice_fitness
from .register import METHODS, Registration, register

__all__ = [
    "register",
    "Registration",
    "METHODS",
    "fitness",
    "overlap_fraction",
    "rotation_error_deg",
    "slice_fitness",
]
