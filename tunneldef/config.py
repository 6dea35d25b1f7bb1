"""Every parameter of the pipeline, in one tree of frozen dataclasses.

Each stage has its own section; a library function takes only its own sections (frozen,
typed, checked when built) as keyword arguments, never the whole tree, and the pipeline hands
each stage the sections it needs. Defaults that come from the paper (Sensors 2024, 24,
2299, doi:10.3390/s24072299) cite it in the field's ``source`` metadata, which
``tunneldef config --dump`` prints beside each value.

Load a partial TOML file with :func:`load_config` (unknown keys are an error); every key that is
absent keeps its default.

One idea at this length: the whole parameter tree, so that one file shows every default and its
source; each section is short.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import ConfigError

__all__ = [
    "SlicingConfig",
    "CenterlineConfig",
    "RegistrationConfig",
    "DeformationConfig",
    "DangerConfig",
    "NetworkConfig",
    "QualityConfig",
    "Config",
    "load_config",
    "dump_config",
    "check_positive",
]


def check_positive(name: str, value: Any, *, unit: str = "m", allow_zero: bool = False) -> float:
    """``value`` as a float if it is a finite number > 0 (>= 0 with ``allow_zero``).

    Raises
    ------
    ConfigError
        Naming the parameter, its unit and the value given.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    ok = v >= 0.0 if allow_zero else v > 0.0
    if not (math.isfinite(v) and ok):
        sign = "non-negative" if allow_zero else "positive"
        raise ConfigError(f"{name} must be a {sign} number ({unit}), got {value!r}")
    return v


def _p(default: Any, source: str, choices: tuple[str, ...] = ()) -> Any:
    """A dataclass field with a documented source for its default (and, for text, its
    allowed values, checked whenever a config is built)."""
    meta = {"source": source, "choices": choices}
    if isinstance(default, (list, dict)):
        # each instance its own copy: a shared mutable default would leak between configs
        return field(default_factory=lambda: copy.deepcopy(default), metadata=meta)
    return field(default=default, metadata=meta)


def _check_choices(section: Any) -> None:
    """Raise ConfigError for a text value outside its field's allowed values."""
    name = type(section).__name__.removesuffix("Config").lower()
    for f in dataclasses.fields(section):
        allowed = f.metadata.get("choices", ())
        value = getattr(section, f.name)
        if allowed and value not in allowed:
            raise ConfigError(
                f"config key {name}.{f.name} must be one of {', '.join(map(repr, allowed))}, "
                f"got {value!r}"
            )


@dataclass(frozen=True)
class SlicingConfig:
    """Cutting the cloud into cross-section slices along the axis (paper §3.1.1)."""

    step: float = _p(0.5, "ours: 2 slices per metre, twice the paper's 1 m (§4.1, Fig. 12) so "
                          "the fit keeps enough centres where slices are rejected")
    thickness: float = _p(0.2, "ours: 0.2 m holds ~1e3 points at handheld density (400 pts/m^2 "
                               "x 17 m perimeter x 0.2 m) while a 1/120 m^-1 bend moves the "
                               "wall by < 0.1 mm across it")
    min_points: int = _p(200, "ours: fewer points than this and a slice is rejected")


@dataclass(frozen=True)
class CenterlineConfig:
    """Roof/floor lines, wall lines and the NURBS centreline (paper §3.1.2-3.1.4)."""

    kde_bandwidth: float = _p(0.1, "paper §4.1, Fig. 13: Gaussian KDE window 0.1 m")
    refine_bandwidth: float = _p(0.02, "ours: narrow KDE that refines a line within the paper's "
                                       "window (removes the bias of the wide window, ~1 cm)")
    crown_fit: bool = _p(True, "ours: read the roof from a trimmed parabola through the points "
                               "near its density peak, at the section's middle (an arch's "
                               "peak lies below its crown by part of the noise); false: the "
                               "peak itself, as the paper")
    min_peak_share: float = _p(0.05, "ours: a roof/floor peak must hold >= 5% of the slice's "
                                     "points within +-kde_bandwidth (noise, cables do not)")
    beyond_gap: float = _p(0.15, "ours: points this far beyond a roof/floor line (5 sigma of "
                                 "3 cm noise) belong to a surface beyond it, m")
    max_beyond_cover: float = _p(0.6, "ours: a slice whose points beyond its roof or floor "
                                      "line span >= 60% of its width read that line inside the "
                                      "section (a clump on a wall, a support) and is not used; "
                                      "1 turns this off")
    grid_cell: float = _p(0.02, "ours: pixel of the 2-D linear-kernel density image, m")
    wall_kernel: float = _p(0.04, "ours: half-width of the linear kernel (paper eq. 3) across "
                                  "the axis, m; along it a quarter of the slice thickness")
    wall_band_low: float = _p(0.15, "ours: walls are read above floor + 15% of the height")
    wall_band_high: float = _p(0.6, "ours: ... and below floor + 60% (arch springing, roof "
                                    "equipment and pipes under the roof stay out)")
    max_wall_angle_deg: float = _p(20.0, "ours: Hough lines within 20 deg of the axis only")
    hough_peak_ratio: float = _p(0.3, "ours: Hough peaks below 30% of the strongest are ignored")
    max_width_jump: float = _p(0.3, "ours: a slice wider than its neighbours' reference "
                                    "width (the narrowest that 30 % of them agree with, within "
                                    "this) by more than this is a chamber/niche/junction and is "
                                    "rejected (narrower: inconsistent walls), m")
    narrow_sigmas: float = _p(3.0, "ours: a slice narrower or wider than its neighbours' "
                                   "median width, or higher or lower than their median "
                                   "height, by more than this many robust spreads of those "
                                   "values is rejected (a wall read on pipes where a hole "
                                   "hides it, or in a short drift's mouth; a sparse arch's "
                                   "roof peak on its shoulder); 0 = off")
    max_height_jump: float = _p(0.3, "ours: same against the neighbours' median height "
                                     "(missing floor/roof), m")
    neighbour_window: float = _p(10.0, "ours: neighbours within +-10 m of a slice, m")
    degree: int = _p(3, "paper §3.1.4: cubic NURBS")
    ctrl_spacing: float = _p(2.0, "ours: the most flexible curve has about one control point "
                                  "per 2 m: fewer control points than centres, so the "
                                  "least-squares curve smooths their noise")
    max_ctrl_spacing: float = _p(8.0, "ours: the stiffest curve tried has a control point "
                                      "every 8 m: rock relief and overbreak shift section "
                                      "midpoints by cm over 1-8 m, which a design axis does "
                                      "not do; a stiff curve averages them out")
    max_misfit: float = _p(0.01, "ours: the stiffest curve (8, 4, then 2 m) whose centres' "
                                 "running mean over max_ctrl_spacing stays within this of it "
                                 "is kept; a bend it cuts shows as such a misfit, m")
    sample_step: float = _p(0.05, "ours: spacing of centreline samples, m")
    max_iterations: int = _p(3, "ours: re-slicing passes normal to the curve (curved tunnels)")
    converge_tol: float = _p(0.01, "ours: stop re-slicing when the curve moves less (p95), "
                                   "m; about twice the noise of the slice centres")
    min_slices: int = _p(5, "ours: fewer accepted slices and there is no centreline")
    max_points: int = _p(2_000_000, "ours: larger clouds are thinned at random (seeded) before "
                                    "slicing; the lines need ~1e4 points per slice, not 1e5")
    remove_strays: bool = _p(True, "ours: drop far stray points (a return 130 m away, small "
                                   "far clusters: what lies 3 m beyond the box of 99.8 % of "
                                   "the points) before the PCA frame and the slicing; one far "
                                   "point stretched the slicing over 130 m of nothing")
    vertical: str = _p("world", "ours: keep world z as vertical ('pca' = paper §3.1.1)",
                       ("world", "pca"))


@dataclass(frozen=True)
class RegistrationConfig:
    """Registration of the compared epoch onto the reference (paper §3.2)."""

    method: str = _p("centerline", "paper §3.2; also icp_point, icp_plane, gicp, ndt",
                     ("centerline", "icp_point", "icp_plane", "gicp", "ndt"))
    floor_ransac_distance: float = _p(0.05, "ours: RANSAC inlier distance for the floor plane")
    plan_angle_step_deg: float = _p(0.01, "ours: smallest rotation step of the plan alignment")
    refine: bool = _p(
        True,
        "ours, measured (benchmarks/registration.py): robust point-to-plane on the stable shell, "
        "kept only when it measurably helps (refine_keep). On "
        "synth pairs the centreline stages are already at 0.6-2.6 mm and 0.01 deg, and an "
        "applied refinement absorbed 0.7-1.3 mm of a 3 cm sag (centreline stages: < 0.1 mm); "
        "on the real drift the stages alone were 2.5 deg off (noisy centrelines of a 1.9 m "
        "rough drift) and the refinement brought it to 0.05 deg, 1.6 mm",
    )
    refine_min_angle_deg: float = _p(
        0.05, "ours: smaller refinement rotations are noise and are not applied, deg"
    )
    refine_min_shift: float = _p(
        0.005, "ours: smaller RMS refinement moves are noise and are not applied, m"
    )
    refine_keep: str = _p(
        "offset",
        "ours: how a refinement is judged. 'thresholds' keeps it beyond refine_min_angle_deg / "
        "refine_min_shift; 'offset' keeps it when the stable shell's per-cell median offsets "
        "ask for it: the least-squares share of each cell's move that its offset before the "
        "move asks for is at least one half and above 0 by refine_offset_z standard errors "
        "plus sqrt(6)/2 (the ICP fitted 6 parameters to the same shell); refused when below "
        "one half and below 1 by refine_offset_z standard errors; the thresholds decide in "
        "between (docs/accuracy.md: the demo's 1.5 mm lateral correction is kept, its "
        "registration 2.5 -> 0.7 mm)",
        ("thresholds", "offset"),
    )
    refine_offset_z: float = _p(
        2.0, "ours: how many standard errors of the cell medians' noise the 'offset' rule "
        "asks of the share before it decides (95 %)"
    )
    voxel: float = _p(0.05, "ours: voxel size for refinement and baselines, m")
    coarse_vertical: str = _p("world", "ours: 'world' keeps z up in the coarse PCA (levelled "
                              "SLAM scans; 2 direction candidates), 'pca' = paper §3.2.1 (4)",
                              ("world", "pca"))
    axial_search: float = _p(
        10.0,
        "ours: largest along-axis shift searched after PCA, m (0: half the summed lengths; "
        "wider searches find spurious partial overlaps on featureless stretches)",
    )
    max_points: int = _p(200_000, "ours: points per epoch used by the registration stages")
    max_points_per_metre: int = _p(
        1500,
        "ours: more points for long tunnels (350 m: 525 k); with 200 k over 350 m the "
        "along-axis images were too sparse to fix the shift (benchmarks/detect_speed.py)",
    )
    min_overlap: float = _p(0.5, "ours: least fraction of common-stretch points within 0.1 m")
    min_overlap_length: float = _p(3.0, "ours: least common stretch of tunnel, m")
    max_axial_uncertainty: float = _p(
        0.5,
        "ours: detect refuses a registration whose position along the tunnel is less certain "
        "than this (a featureless overlap), m; inf accepts it",
    )


@dataclass(frozen=True)
class DeformationConfig:
    """Per-point and per-section deformation (paper §3.3)."""

    method: str = _p("robust", "ours: local-surface estimator, noise floor ~2 mm vs ~25 mm for "
                     "'knn', the paper's §3.3.1 KNN centroid (benchmarks/deformation_accuracy.py)",
                     ("robust", "knn"))
    k: int = _p(3, "paper §4.3, Table 3: k = 3 nearest neighbours")
    section_step: float = _p(1.0, "paper Table 4: sections 1 m apart")
    section_thickness: float = _p(0.2, "ours: points within +-0.1 m of a section's chainage")
    max_distance: float = _p(0.5, "ours (knn): no counterpart farther than this (NaN), m")
    normal_radius: float = _p(0.3, "ours (robust): plane-fit radius for the normal, m; ~20x the "
                              "1.5 cm noise sigma, small against a 3 m section (M3C2 rule)")
    cylinder_radius: float = _p(0.2, "ours (robust): cylinder radius along the normal, m; ~50 "
                                "points/epoch at 400 pts/m2 -> 3 mm noise for sigma 1.5 cm")
    standoff_reach: float = _p(1.5, "ours (robust): a surface the shell classifier left out is "
                               "an object in front of the shell (KNN change, never danger) when "
                               "reference points lie behind it within this distance, m (the "
                               "belt 0.9 m above the floor, pipes on the walls); else shell")
    max_depth: float = _p(0.3, "ours (robust): largest measurable motion along the normal, m")
    core_spacing: float = _p(0.2, "ours (robust): voxel edge of the core points, m; = the "
                             "cylinder radius: 1 M points in < 10 s on 2 cores")
    pool: bool = _p(True, "ours (robust): where a cylinder's standard error exceeds 1.5 mm "
                    "(sparse scans), pool it with its neighbours over ~0.3 m, bias-corrected: "
                    "400 pts/m2 noise floor 2.0 -> 1.7 mm; a clear change (beyond 3 LoD95) is "
                    "read on its own cylinder, smoothing bias taken out, so peaks keep their size; "
                    "false keeps the plain cylinders (benchmarks/deformation_accuracy.py)")
    registration_sigma_floor: float = _p(
        0.0005, "ours, measured (robust): the least registration error the level of detection "
        "assumes, m. The registration check cannot see errors below its resolution and then "
        "reports 0; the best registrations on synthetic pairs with a truth still leave "
        "0.3-0.8 mm (docs/accuracy.md). With 0, the quick demo registered to 0.77 mm had 7.4 % "
        "of its unchanged shell beyond its LoD95 (nominal 5 %); with 0.5 mm, 3.0 %")


@dataclass(frozen=True)
class DangerConfig:
    """Danger classification (paper §4.3, Fig. 22)."""

    threshold: float = _p(0.05, "ours: |deformation| above 50 mm is flagged")
    rule: str = _p("absolute", "'absolute' threshold, or 'mean' (paper §4.3: mean |deformation|)",
                   ("absolute", "mean"))
    min_zone_length: float = _p(0.2, "ours: danger runs shorter along the chainage are dropped, m")
    merge_gap: float = _p(0.5, "ours: danger runs closer than this along the chainage merge, m")
    neighbours: int = _p(64, "ours: judged on the median of this many nearest shell points "
                             "(1 = paper §4.3's per-point rule)")
    peak_points: int = _p(200, "ours: a zone's peak is the median over this many points")


@dataclass(frozen=True)
class NetworkConfig:
    """Drift networks: the plan-view skeleton that gives the graph of edges and junctions."""

    cell: float = _p(0.2, "ours: plan grid cell, m; >= 10 cells across a 2 m drift")
    min_count: int = _p(2, "ours: least points for an occupied plan cell")
    min_component_area: float = _p(20.0, "ours: dense parts of the plan smaller than this are "
                                         "strays, m^2 (a 2 m drift 10 m long is 20 m^2)")
    max_hole_area: float = _p(16.0, "ours: holes of the plan footprint smaller than this (a "
                                    "static scanner's blind cone) are filled, m^2; larger ones "
                                    "are pillars")
    max_cells: int = _p(20_000_000, "ours: largest plan grid, cells")
    max_height_ratio: float = _p(1.8, "ours: a plan cell spanning more than this times the "
                                      "drifts' height means drifts above one another (refused)")
    min_branch_length: float = _p(3.0, "ours: a dead end must reach this far beyond the wall "
                                       "of the drift it leaves to be a branch (niches, the "
                                       "corners of a drift's end are not), m")
    through_angle_deg: float = _p(35.0, "ours: drifts meeting within this angle of straight "
                                        "on are one edge through the junction, deg")
    zone_margin: float = _p(0.5, "ours: junction zones reach this far beyond the other "
                                 "drift's wall, m")
    drift_correction: bool = _p(True, "ours: after the rigid registration (of one drift or "
                                      "of two networks), a piecewise-rigid correction of SLAM "
                                      "drift along the reference centreline or each edge, "
                                      "used only when it lowers the coherent misfit by more "
                                      "than 0.5 mm; false switches it off")
    drift_block: float = _p(20.0, "ours: length of the blocks of the drift correction, m")
    drift_block_fine: float = _p(10.0, "ours: a shorter block length tried after drift_block, "
                                       "kept where it lowers the coherent misfit by more than "
                                       "0.5 mm below drift_block's (drift that bends within a "
                                       "block); 0 tries drift_block alone, m")
    drift_change: float = _p(0.008, "ours: a 1 m patch whose median misfit after a block's "
                                    "first fit exceeds this (and three standard errors) is "
                                    "left out of its second fit, so a sag or a bulge does not "
                                    "pull the block; 0 fits each block once on all points, m")
    max_left_out_length: float = _p(15.0, "ours: a dead end up to this long whose own checks "
                                          "fail (a cross-cut seen a few metres in from the "
                                          "main drift) is left out of the measurement, said "
                                          "in the log and the summary, rather than refusing "
                                          "the run; 0 refuses, m")


@dataclass(frozen=True)
class QualityConfig:
    """The self-checks of every stage and their limits (``tunneldef.quality``)."""

    enforce: bool = _p(True, "ours: a failed check stops detect with a one-line reason (exit 2); "
                             "false (or the CLI's --force) writes the result marked 'unverified'")
    max_tilt_deg: float = _p(5.0, "ours: levelled scans (registration.coarse_vertical = "
                                  "'world'): the registration may tip the compared epoch's "
                                  "vertical by at most this, degrees (a flat drift going on up "
                                  "a 12 % ramp, turned end for end, lies on itself tipped by "
                                  "6.8 degrees)")
    max_height_to_width: float = _p(1.5, "ours: advisory: the reference's section (median of "
                                         "its fitted slices) may be at most this much taller "
                                         "than wide; taller, its z axis may not point up (a "
                                         "y-up export), and roof, walls, floor and the "
                                         "vertical/horizontal split would be read about the "
                                         "wrong axis")
    min_usable_share: float = _p(0.5, "ours: at least half the slices of the kept centreline pass "
                                      "must show a floor, a roof and two walls")
    max_curve_uncertainty: float = _p(0.03, "ours: 95 % uncertainty of a centreline, taken as "
                                            "the p95 distance of its slice centres from it (no "
                                            "averaging credit: the centres' errors are "
                                            "correlated along the tunnel), m; 3 cm is the "
                                            "accuracy the sweep (benchmarks/sweep.py) holds "
                                            "centrelines to")
    max_edge_scatter: float = _p(0.05, "ours: drift networks: the same figure for each edge of "
                                       "the reference network, m. A rough drift's centres "
                                       "scatter with its rock, which the curve smooths on "
                                       "purpose: on 24 reference edges of random networks "
                                       "with 2-3 cm relief (benchmarks/network_sweep.py) the "
                                       "curve lay 0.2-1.0 x that scatter from the design axis "
                                       "(12-35 mm of scatter, 5-29 mm off), so 3 cm refused "
                                       "sound rough drifts; 5 cm still refuses a section read "
                                       "on the wrong walls. No scatter shows a bias shared "
                                       "along a drift: one arch read 18 mm off with 9 mm")
    max_fit_excess: float = _p(0.008, "ours: cross-epoch point-to-plane misfit the scans' own "
                                      "noise does not explain, each sigma taken patch by patch "
                                      "(a 20 m synthetic pair at +-1.2 cm noise: correct 1.8 mm, "
                                      "2 cm lateral offset 9.3 mm, 0.1 deg yaw 3.5 mm, which "
                                      "neither this nor the shared misfit, 2.4 mm, refuses), m; "
                                      "also the limit of the misfit neighbouring points share "
                                      "(registration.shared_misfit: 1-3 mm on correct pairs)")
    max_centreline_difference: float = _p(0.03, "ours: p95 distance between the two epochs' "
                                                "registered centrelines / sqrt(2), m: about "
                                                "either curve's p95 error; 3 cm as the sweep "
                                                "holds centrelines to (benchmarks/sweep.py)")
    max_axial_disagreement: float = _p(3.0, "ours: section correlation and point-to-plane "
                                            "slide must agree within 3 combined sigmas")
    max_axial_residual: float = _p(0.01, "ours: an independent point-to-plane slide from the "
                                         "registered pose may find it off along the axis by "
                                         "at most 1 cm at either normal scale, the accuracy "
                                         "the sweep (benchmarks/sweep.py) holds registrations "
                                         "to")
    max_axial_spread: float = _p(0.01, "ours: the point-to-plane slide started at the "
                                       "registered position and 2 cm either side of it must "
                                       "end within 1 cm of one another (the accuracy the sweep "
                                       "holds registrations to); a wider spread means the "
                                       "slide sticks where it starts")
    min_alternative_margin: float = _p(0.02, "ours: drift networks: the chosen pose's evidence "
                                             "(share of compared points the reference "
                                             "explains, less those it contradicts) must beat "
                                             "every other pose more than 10 m away by this "
                                             "much, else the networks fit two places alike (a "
                                             "look-alike cross-cut along a plain drift); 0.02 "
                                             "is hundreds of points of a 20 000-point probe")
    max_pose_mismatch: float = _p(1.0, "ours: the section images at the registered position "
                                       "may match worse than at the best shift by at most "
                                       "their noise (coarse_shift's own tolerance)")
    max_junctions: int = _p(0, "ours: a single-tube run refuses an epoch whose plan skeleton "
                               "has junctions (a drift network: its cross-cuts would be "
                               "measured against the main drift's centreline; use --network)")
    max_significant_share: float = _p(0.25, "ours: share of shell points beyond their LoD95 "
                                            "(robust estimator); about 5 % by chance plus the "
                                            "truly deformed shell, far more after a wrong "
                                            "registration")
    max_two_surface_share: float = _p(0.001, "ours: share of the measured shell whose change "
                                             "one epoch contradicts with both surfaces (a SLAM "
                                             "map's double wall) before a warning; one in a "
                                             "thousand is about a square metre of a 60 m drift")
    max_spread_ratio: float = _p(1.2, "ours: ratio of the epochs' surface spreads (either way) "
                                      "that 3 m of one surface may reach, against the "
                                      "survey's, or the whole survey, before a warning; a wall "
                                      "held twice 3 cm apart at +-1.5 cm noise reads 1.2-1.35, "
                                      "surveyor's pairs without it 1.01-1.05")


@dataclass(frozen=True)
class Config:
    """The whole parameter tree."""

    slicing: SlicingConfig = field(default_factory=SlicingConfig)
    centerline: CenterlineConfig = field(default_factory=CenterlineConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    danger: DangerConfig = field(default_factory=DangerConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    quality: QualityConfig = field(default_factory=QualityConfig)

    def replace(self, **sections: dict[str, Any]) -> Config:
        """A copy with some values of some sections changed, e.g.
        ``cfg.replace(danger={"threshold": 0.02})``."""
        return _from_dict(self, sections)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain nested dict of all values."""
        return dataclasses.asdict(self)


def _from_dict(base: Config, data: dict[str, Any]) -> Config:
    changes = {}
    for section, values in data.items():
        if section not in {f.name for f in dataclasses.fields(base)}:
            raise ConfigError(f"unknown config section [{section}]")
        if not isinstance(values, dict):
            raise ConfigError(f"config section [{section}] must be a table")
        current = getattr(base, section)
        known = {f.name: f for f in dataclasses.fields(current)}
        checked: dict[str, Any] = {}
        for key, value in values.items():
            if key not in known:
                raise ConfigError(f"unknown config key {section}.{key}")
            expected = type(getattr(current, key))
            if expected is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
                raise ConfigError(
                    f"config key {section}.{key} must be {expected.__name__}, got {value!r}"
                )
            checked[key] = value
        changes[section] = dataclasses.replace(current, **checked)
        _check_choices(changes[section])
    return dataclasses.replace(base, **changes)


def load_config(path: str | Path | None = None) -> Config:
    """Read a (partial) TOML config; missing keys keep their defaults.

    Raises
    ------
    ConfigError
        If the file is missing, not TOML, or has unknown keys or wrongly typed values.
    """
    if path is None:
        return Config()
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file not found: {p}")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file {p} is not valid TOML: {exc}") from None
    return _from_dict(Config(), data)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(v)


def dump_config(config: Config | None = None) -> str:
    """TOML text of every parameter, each with its source as a comment."""
    config = config or Config()
    lines = ["# tunneldef configuration: every parameter, its value and the source of its default"]
    for sec in dataclasses.fields(config):
        section = getattr(config, sec.name)
        lines.append(f"\n[{sec.name}]")
        for f in dataclasses.fields(section):
            lines.append(f"{f.name} = {_toml_value(getattr(section, f.name))}"
                         f"  # {f.metadata.get('source', '')}")
    return "\n".join(lines) + "\n"
