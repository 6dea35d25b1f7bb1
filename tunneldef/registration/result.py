"""The result of the registration stage."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..textfiles import jsonable

__all__ = ["Registration"]


@dataclass(frozen=True)
class Registration:
    """The result of :func:`register`.

    Attributes
    ----------
    transform : ndarray, shape (4, 4)
        Rigid transform mapping compared coordinates into the reference frame.
    method : str
        Method used.
    fitness : float
        The paper's fitness score (§4.2, Table 2): RMSE of nearest-neighbour distances between
        the registered compared points and the reference (pairs within 0.1 m), metres.
    slice_fitness : list of dict
        ``{"chainage", "fitness", "points"}`` for five slices across the overlap (Table 2).
    axial_uncertainty : float
        One standard deviation of the position along the tunnel axis, metres (``inf`` when
        the overlap has no feature along the axis, i.e. the position along it is undetermined;
        whole-cloud methods report NaN).
    overlap : float
        Fraction of compared points within the common stretch lying within 0.1 m of the
        reference after registration.
    stages : dict of str to ndarray (4, 4)
        Cumulative cmp -> ref transform after each stage (``coarse``, ``cross_section``,
        ``longitudinal``, ``plan``, ``common_stretch`` (second pass over the stretch both
        epochs cover), ``refine``; or ``coarse`` and the baseline's name).
    timings : dict of str to float
        Seconds per stage.
    info : dict
        Diagnostics: ``floor_tilt_deg``, ``axial_*`` shifts, ``direction_candidates`` (overlap
        of each PCA sign candidate), ``direction_ambiguous`` (the tunnel looks the same both
        ways round and the tilt does not tell), ``direction_tilt_gap_deg`` and
        ``direction_tilts_deg`` (where both ways fit alike: how far each tips the compared
        epoch's vertical, the kept one first), ``refine`` (its correction and whether it was
        applied).
    """

    transform: np.ndarray
    method: str
    fitness: float
    slice_fitness: list[dict[str, float]]
    axial_uncertainty: float
    overlap: float
    stages: dict[str, np.ndarray] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (infinite values become None)."""

        def num(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {
            "method": self.method,
            "transform": np.asarray(self.transform).tolist(),
            "fitness_m": num(self.fitness),
            "slice_fitness": [
                {k: (num(v) if isinstance(v, float) else v) for k, v in d.items()}
                for d in self.slice_fitness
            ],
            "axial_uncertainty_m": num(self.axial_uncertainty),
            "overlap": num(self.overlap),
            "stages": {k: np.asarray(v).tolist() for k, v in self.stages.items()},
            "timings_s": {k: float(v) for k, v in self.timings.items()},
            "info": jsonable(self.info),
        }
