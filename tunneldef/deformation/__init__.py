"""Stage 3: deformation between two registered epochs, per point, per section, danger zones.

Contents
--------
compute_deformation
    Per-point signed deformation of the compared epoch against the reference (the paper's KNN
    centroid, §3.3.1, or the local-surface estimator), split into horizontal and vertical
    components relative to the centreline (§3.3.2).
DeformationResult
    Its per-point arrays and the fields to write.
section_statistics, write_sections_csv
    Statistics of cross-sections along the chainage (paper Table 4).
danger_zones, danger_threshold, robust_peak
    Danger classification and chainage intervals (paper §4.3, Fig. 22).

Modules: :mod:`.compute` (the stage), :mod:`.result`, :mod:`.knn` (the paper's estimator),
:mod:`.local_surface` (the local-surface estimator, built on :mod:`.cylinders` and
:mod:`.core_pooling`), :mod:`.shell` (shell versus clutter), :mod:`.sections`, :mod:`.classify`.
"""

from __future__ import annotations

from .classify import danger_threshold, danger_zones, normal_component, robust_peak
from .compute import METHODS, compute_deformation
from .result import DeformationResult
from .sections import SURFACE_NAMES, section_statistics, surface_labels, write_sections_csv

__all__ = [
    "compute_deformation",
    "DeformationResult",
    "METHODS",
    "section_statistics",
    "write_sections_csv",
    "danger_zones",
    "danger_threshold",
    "robust_peak",
    "normal_component",
    "surface_labels",
    "SURFACE_NAMES",
]
