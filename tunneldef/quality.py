"""Self-checks of every stage: a figure, a limit, a verdict.

Each stage states its own quality (the centreline extraction its passes' figures, the
registration an independent look at its fit, :mod:`tunneldef.registration.verify`, the
deformation the share of shell beyond its level of detection); the functions here turn those
figures into :class:`Check` rows against the limits of :class:`~tunneldef.config.QualityConfig`.
:func:`tunneldef.pipeline.detect` collects them in a :class:`QualityReport`, stops on the first
failure with a :class:`QualityError` (one line: what failed, by how much, what to try) unless
the checks are not enforced, and then marks every output "unverified".

One idea at this length: the check rows of every stage, which share one type, one report and one way
of wording a refusal.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .config import QualityConfig
from .errors import TunnelDefError

log = logging.getLogger(__name__)

__all__ = [
    "Check",
    "QualityReport",
    "QualityError",
    "UNVERIFIED",
    "topology_checks",
    "centerline_checks",
    "upright_check",
    "rigid_convergence_check",
    "registration_checks",
    "deformation_checks",
    "thick_spans",
    "edge_checks",
    "network_registration_checks",
    "edge_difference_checks",
]

#: The words every output of a run whose checks failed carries (summary, file headers).
UNVERIFIED = "UNVERIFIED: quality checks failed, result written on request"


class QualityError(TunnelDefError):
    """A stage's result failed its self-check; the result is not trustworthy.

    ``report`` holds every check made up to the failure (figures for diagnostics)."""

    def __init__(self, message: str, report: QualityReport | None = None) -> None:
        super().__init__(message)
        self.report = report


@dataclass(frozen=True)
class Check:
    """One self-check.

    Attributes
    ----------
    name : str
        What is checked, e.g. ``"registration.axial_agreement"``.
    figure : float
        The measured value.
    limit : float
        The limit it is held to.
    comparison : {"<=", ">="}
        ``figure <= limit`` or ``figure >= limit`` passes.
    unit : str
        Unit of figure and limit ("m", "" for ratios and shares).
    passed : bool
        The verdict (NaN figures pass: nothing to judge, said in ``note``).
    advice : str
        What the user can do when it fails.
    note : str
        How the figure was made.
    advisory : bool
        The figure judges something no output depends on alone (the compared epoch's own
        centreline, which only feeds a registration that is checked on its own): a failure
        is reported, as a warning, but neither stops the run nor leaves it unverified.
    """

    name: str
    figure: float
    limit: float
    comparison: str
    unit: str
    passed: bool
    advice: str = ""
    note: str = ""
    advisory: bool = False

    def reason(self) -> str:
        """One line: the failed check, its figure against its limit, and the advice."""
        op = ">" if self.comparison == "<=" else "<"
        u = f" {self.unit}" if self.unit else ""
        text = f"{self.name} {self.figure:.4g}{u} {op} limit {self.limit:.4g}{u}"
        return f"{text}: {self.advice}" if self.advice else text

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""

        def num(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {
            "check": self.name,
            "figure": num(self.figure),
            "limit": num(self.limit),
            "comparison": self.comparison,
            "unit": self.unit,
            "verdict": "pass" if self.passed else ("warning" if self.advisory else "fail"),
            "advisory": self.advisory,
            "note": self.note,
        }


def _check(
    name: str, figure: float, limit: float, comparison: str, unit: str, advice: str, note: str
) -> Check:
    f = float(figure)
    if np.isnan(f):
        ok = True
    elif comparison == "<=":
        ok = f <= limit
    else:
        ok = f >= limit
    return Check(name, f, float(limit), comparison, unit, bool(ok), advice, note)


@dataclass
class QualityReport:
    """All checks of one run.

    Attributes
    ----------
    checks : list of Check
    enforced : bool
        True when a failed check stops the run (``[quality] enforce``, no ``--force``).
    """

    checks: list[Check] = field(default_factory=list)
    enforced: bool = True

    @property
    def failed(self) -> list[Check]:
        """The failed checks that count (not advisory)."""
        return [c for c in self.checks if not c.passed and not c.advisory]

    @property
    def warnings(self) -> list[Check]:
        """The failed advisory checks."""
        return [c for c in self.checks if not c.passed and c.advisory]

    @property
    def verified(self) -> bool:
        """True when every check passed."""
        return not self.failed

    def add(self, checks: list[Check]) -> None:
        """Record checks and, when enforced, stop at the first failure.

        Raises
        ------
        QualityError
            One line naming the failed check, its figure and limit, and what to try.
        """
        self.checks.extend(checks)
        for c in checks:
            if not c.passed and c.advisory:
                log.warning("quality warning (advisory, not enforced): %s", c.reason())
        bad = [c for c in checks if not c.passed and not c.advisory]
        if bad and self.enforced:
            raise QualityError(
                f"quality check failed: {bad[0].reason()} (--force or [quality] enforce = "
                "false writes the result anyway, marked unverified)",
                report=self,
            )

    def to_dict(self) -> dict[str, Any]:
        """The summary's ``quality`` block."""
        return {
            "verified": self.verified,
            "enforced": self.enforced,
            "status": "verified" if self.verified else UNVERIFIED,
            "failed": [c.name for c in self.failed],
            "warnings": [c.name for c in self.warnings],
            "checks": [c.to_dict() for c in self.checks],
        }


def topology_checks(topology: Any, qc: QualityConfig, epoch: str) -> list[Check]:
    """Is the epoch one drift? Junctions in its plan skeleton (a
    :class:`~tunneldef.centerline.skeleton.PlanTopology`) mean a drift network, which a
    single-tube run would measure against one centreline; a corner (a walk round a right
    angle) is measured as a network too, whose edges flag it (NaN, passing, when the plan
    could not be read)."""
    figure = np.nan if topology.reason else float(topology.junctions)
    return [
        _check(f"{epoch}_epoch.junctions", figure, qc.max_junctions, "<=", "",
               f"the {epoch} epoch is a drift network: {topology.describe()}; run "
               "`tunneldef detect --network`",
               f"junctions of the plan footprint's skeleton: {topology.describe()}"),
        _check(f"{epoch}_epoch.corners", np.nan if topology.reason else
               float(topology.corners), 0.0, "<=", "",
               f"the {epoch} epoch turns a corner: {topology.describe()}; one centreline cannot "
               "follow a right angle, run `tunneldef detect --network`",
               f"sharp turns of the plan footprint's skeleton: {topology.describe()}"),
    ]


def centerline_checks(extraction: Any, qc: QualityConfig, epoch: str) -> list[Check]:
    """Checks of one epoch's centreline (a
    :class:`~tunneldef.centerline.extract.CenterlineResult`): share of usable slices, centre
    residuals, curve-to-cloud distance, length against the cloud's extent."""
    q = extraction.quality_of_curve
    if q is None:
        return []
    name = f"{epoch}_centreline"
    advice = (
        f"the {epoch} centreline is unreliable; check that the cloud is one tunnel in metres "
        "and try [slicing] thickness/step"
    )
    return [
        _check(f"{name}.usable_slices", q.usable_share, qc.min_usable_share, ">=", "", advice,
               f"share of slices with floor, roof and two walls (pass {q.number})"),
        _check(f"{name}.curve_uncertainty", q.curve_uncertainty, qc.max_curve_uncertainty, "<=",
               "m", advice, f"95th percentile distance of the {q.used} used slice centres from "
               "the most flexible curve through them (their local scatter; from the kept curve: "
               f"median {q.residual_p50:.4f} m, p95 {q.residual_p95:.4f} m): the curve is held "
               "no better than its centres scatter"),
        _check(f"{name}.cloud_distance", q.cloud_distance, q.cloud_distance_limit, "<=", "m",
               advice, "largest distance of a curve sample from the cloud; limit half the "
               "section diagonal + 0.5 m"),
        _check(f"{name}.length_vs_extent", q.length - q.extent, 1.0, "<=", "m", advice,
               "curve length minus the cloud's extent along it"),
    ]


def upright_check(extraction: Any, qc: QualityConfig) -> Check:
    """Whether the reference epoch's z axis looks like the vertical (an advisory check).

    Roof, walls and floor, and the vertical and horizontal parts of the deformation, are read
    about the reference's z axis. A cloud exported with y up (or rolled on its side) looks
    like a tunnel as much as a levelled one, and the run would call a roof sag a wall bulge.
    Nothing in the points says where gravity was, but mine drifts are rarely much taller
    than wide: the figure is the median height / width of the reference's fitted slices (a
    single-drift extraction's, or every edge's of a network; NaN, passing, without any).
    """
    slices = extraction.slices if hasattr(extraction, "slices") else [
        r for e in extraction.network.edges for r in e.slices]
    ratios = [r.height / r.width for r in slices
              if r.ok and np.isfinite(r.height) and np.isfinite(r.width) and r.width > 0]
    figure = float(np.median(ratios)) if ratios else np.nan
    check = _check(
        "reference_section.upright", figure, qc.max_height_to_width, "<=", "",
        "the reference's section is much taller than wide, which mine drifts rarely are: if "
        "its z axis does not point up (a y-up export, a cloud on its side), roof, walls and "
        "floor and the vertical and horizontal deformation are read about the wrong axis; "
        "rotate both epochs so that z points up",
        "median height / width of the reference's fitted slices, about its z axis",
    )
    return dataclasses.replace(check, advisory=True)


def registration_checks(check: Any, qc: QualityConfig) -> list[Check]:
    """Checks of the registration from its independent figures (a
    :class:`~tunneldef.registration.verify.RegistrationCheck`)."""
    return [
        *_fit_excess(check, qc, "the compared epoch does not lie on the reference as closely "
                     "as the scans' noise allows (tilt or offset); check that both epochs show "
                     "the same tunnel"),
        _check("registration.centreline_difference", check.centreline_difference,
               qc.max_centreline_difference, "<=", "m",
               "the two epochs' centrelines do not agree after registration (sparse or noisy "
               "sections, or a wrong registration); denser scans or a larger [slicing] "
               "thickness may help", "p95 distance between the registered centrelines / sqrt(2)"),
        _check("registration.axial_pose", check.pose_mismatch, qc.max_pose_mismatch, "<=",
               "noise", "the section images match better at another position along the tunnel "
               "than at the registered one; the registration may have slid",
               f"section mismatch at the registered position vs the best shift, in units of "
               f"its noise (best shift {check.coarse_shift:+.2f} m, equally good within "
               f"{check.coarse_spread:.2f} m)"),
        _check("registration.axial_residual",
               _remaining_slide(check.fine_shift, check.wide_shift,
                                *check.narrow_shifts),
               qc.max_axial_residual, "<=", "m",
               "an independent point-to-plane fit at both normal scales finds the compared "
               "epoch off along the tunnel; the surfaces that fix the position are too weak "
               "for the noise (denser or less noisy scans, or a stretch with a chamber)",
               f"remaining slide {check.fine_shift:+.4f} m (normals over 0.15 m) and "
               f"{check.wide_shift:+.4f} m (0.3 m); with a 5 cm kernel "
               + ", ".join(f"{v:+.4f} m" for v in check.narrow_shifts)
               + f"; the largest (fine/wide disagreement: {check.scale_disagreement:.2f} "
               "sigma)"),
        _check("registration.axial_convergence", check.axial_spread,
               qc.max_axial_spread, "<=", "m",
               "started 2 cm either side of the registered position, the point-to-plane slide "
               "ends elsewhere: the surfaces along the tunnel do not fix the position against "
               "the noise (denser or less noisy scans, or a stretch with a chamber)",
               f"the slide ends {_mm(check.fine_shift)} from the registered position, "
               f"{_mm(check.probe_shifts[0])} and {_mm(check.probe_shifts[1])} when started "
               "2 cm before and after it; the figure is their spread"),
        _check("registration.axial_agreement", check.axial_disagreement,
               qc.max_axial_disagreement, "<=", "sigma",
               "section correlation and point-to-plane fit disagree on the position along the "
               "tunnel; the registration may have slid",
               f"section correlation {check.coarse_shift:+.3f} m, point-to-plane "
               f"{check.fine_shift:+.4f} +- {check.fine_sigma:.4f} m"),
    ]


def direction_check(info: dict[str, Any]) -> Check:
    """Whether the registration knows which way round the compared epoch goes: where both
    ways fit alike (``direction_tilt_gap_deg`` in the registration's ``info``; absent when
    one way fits clearly better), only how far each tips the compared epoch's vertical tells
    them apart, and only with levelled scans."""
    from .registration.register import DIRECTION_TILT_GAP_DEG

    gap = float(info.get("direction_tilt_gap_deg", np.nan))
    tilts = info.get("direction_tilts_deg", [np.nan, np.nan])
    return _check(
        "registration.direction", gap, DIRECTION_TILT_GAP_DEG, ">=", "deg",
        "the tunnel fits itself turned end for end as well as the right way round (a "
        "symmetric stretch: a flat drift going on up a ramp, a plain drift); with levelled "
        "scans only a clear difference in tilt settles it; register a stretch with a chamber, "
        "a junction or a bend that is not symmetric",
        "both ways round fit alike; the kept one tips the compared epoch's vertical by "
        f"{tilts[0]:.2f} degrees, the other by {tilts[1]:.2f}; the figure is their difference "
        "(none when one way round fits clearly better)",
    )


def tilt_check(tilt_deg: float, qc: QualityConfig) -> Check:
    """How far the registration tips the compared epoch's vertical (levelled scans only:
    NaN, which passes, otherwise)."""
    return _check(
        "registration.tilt", tilt_deg, qc.max_tilt_deg, "<=", "deg",
        "the registration tips the compared epoch far from its own vertical, which levelled "
        "scans do not need: it may have laid a symmetric stretch on itself the wrong way "
        "round (a flat drift going on up a ramp); if the scans are not levelled, set "
        "registration.coarse_vertical = \"pca\"",
        "angle between the compared epoch's vertical, registered, and the reference's",
    )


def rigid_convergence_check(spread: float, qc: QualityConfig) -> Check:
    """How far apart a rigid point-to-plane fit ends from the registered pose and from 2 cm
    either side of it along the drift (:func:`~tunneldef.registration.verify.rigid_convergence`),
    held to the slides' convergence limit: for a drift that the curves' shapes placed."""
    return _check(
        "registration.rigid_convergence", spread, qc.max_axial_spread, "<=", "m",
        "started 2 cm before and after the registered position along the drift, the rigid "
        "point-to-plane fit (rotations included) ends elsewhere: the surfaces trade a slide "
        "along the drift for a small tilt (a flat drift going on up a ramp), so the position "
        "along it is known no better than this; a stretch with a chamber, a junction or a "
        "bend in plan fixes it",
        "largest distance between where a compared point lies in the three fitted poses",
    )


def _fit_excess(check: Any, qc: QualityConfig, advice: str) -> list[Check]:
    """The misfit the scans' own noise does not explain, and the misfit neighbouring points
    share (drift or network): both enter the LoD95, which then cannot show a poor fit as
    change, so both are held to the same limit here."""
    return [
        _check("registration.fit_excess", check.excess, qc.max_fit_excess, "<=", "m", advice,
               f"cross-epoch point-to-plane sigma {check.cross_residual:.4f} m vs the "
               f"epochs' own {check.ref_residual:.4f} / {check.cmp_residual:.4f} m"),
        _check("registration.shared_misfit", check.coherent, qc.max_fit_excess, "<=", "m",
               advice, "spread of the signed point-to-plane misfit's medians in 2 m patches, "
               "less their own noise: what a tilt, an offset or a SLAM drift residue leaves"),
    ]


def _mm(v: float) -> str:
    return f"{1000 * v:+.1f} mm" if np.isfinite(v) else "nowhere (nothing to hold on to)"


def _remaining_slide(*slides: float) -> float:
    """The largest along-axis slide any of the readings (normal scales, kernels) still finds
    from the registered pose (NaN when all are missing). The largest, not the one they agree
    on: when they disagree, the position is known no better than their spread."""
    v = [abs(x) for x in slides if np.isfinite(x)]
    return float(max(v)) if v else np.nan


def deformation_checks(deformation: Any, qc: QualityConfig) -> list[Check]:
    """Share of shell points beyond their LoD95 (robust estimator only; a correct registration
    leaves about 5 % by chance plus the truly deformed shell), and (advisory) the share of
    the measured shell whose change one epoch contradicts by showing both surfaces."""
    sig = getattr(deformation, "significant", None)
    if sig is None:
        return []
    shell = np.asarray(deformation.shell, dtype=bool)
    lod = np.asarray(deformation.lod95, dtype=np.float64)
    use = shell & np.isfinite(lod)
    share = float(np.mean(np.asarray(sig, dtype=bool)[use])) if use.any() else np.nan
    checks = [
        _check("deformation.significant_share", share, qc.max_significant_share, "<=", "",
               "far more of the shell changed than deformation explains: the registration "
               "is probably wrong", "share of shell points whose |deformation| exceeds LoD95"),
    ]
    two = getattr(deformation, "two_surfaces", None)
    if two is not None:
        two = np.asarray(two, dtype=bool)
        both = shell & two
        measured = shell & (np.isfinite(np.asarray(deformation.deformation)) | two)
        figure = float(both.sum() / measured.sum()) if measured.any() else np.nan
        where = ""
        if both.any():
            s = np.asarray(deformation.chainage)[both]
            where = f" (chainage {np.min(s):.1f}-{np.max(s):.1f} m)"
        check = _check(
            "deformation.two_surfaces", figure, qc.max_two_surface_share, "<=", "",
            f"one epoch shows both surfaces of a change{where}: the map holds the same "
            "surface twice (a SLAM pass that did not close onto the other, a lining in front "
            "of rock); those points have no value; look at both epochs there",
            "share of the measured shell whose change one epoch contradicts by showing both "
            "surfaces")
        checks.append(dataclasses.replace(check, advisory=True))
    ratio = getattr(deformation, "spread_ratio", None)
    if ratio is not None:
        checks += _thick_surface_checks(deformation, np.asarray(ratio), qc)
    return checks


_THICK_BIN = 1.0  # m of chainage per bin of :func:`thick_spans`
_THICK_MIN_POINTS = 50  # measured shell points a bin needs to count
_THICK_RUN = 3  # neighbouring bins a stretch needs (at 100-200 points/m2 two bins of clean
# network edges reached 1.17, their medians' sampling scatter)
_THICK_SAMPLE = 2_000_000  # at most this many points (a stride) make the bins' medians
_EPOCH_MIN_POINTS = 1_000  # measured shell points the whole-epoch ratio needs


def thick_spans(ratio: np.ndarray, chainage: np.ndarray, surface: np.ndarray,
                limit: float) -> tuple[float, list[tuple[int, float, float, float]], float]:
    """Stretches of a surface where one epoch's surface is thicker than the other's, beyond
    what the two epochs' spreads are elsewhere in the survey.

    Parameters
    ----------
    ratio : ndarray, shape (N,)
        Compared cylinder spread over reference cylinder spread per point (NaN where not
        measured; :attr:`~tunneldef.deformation.DeformationResult.spread_ratio`).
    chainage, surface : ndarray, shape (N,)
        Chainage (m) and surface label (0-3) of each point.
    limit : float
        Ratio (either way, > 1) against the survey's median ratio beyond which a 1 m bin of
        one surface is thick.

    Returns
    -------
    worst : float
        The largest ratio against the survey's median, folded to >= 1, that
        ``_THICK_RUN`` neighbouring bins of one surface all reach (NaN without such bins).
    spans : list of (surface, start, end, ratio)
        Runs of at least ``_THICK_RUN`` neighbouring bins of one surface beyond ``limit``
        (chainage in metres; ``ratio`` their median ratio, > 1 where the compared epoch is
        thicker).
    median : float
        The survey's median ratio (NaN with too few measured points).
    """
    limit = max(float(limit), 1.0)
    ok = np.flatnonzero(np.isfinite(ratio) & (ratio > 0))
    if len(ok) > _THICK_SAMPLE:
        ok = ok[:: -(-len(ok) // _THICK_SAMPLE)]
    if len(ok) < 2 * _THICK_MIN_POINTS:
        return np.nan, [], np.nan
    lr = np.log(ratio[ok].astype(np.float64))
    survey = float(np.median(lr))
    b = np.floor(chainage[ok] / _THICK_BIN).astype(np.int64)
    b0 = int(b.min())
    b -= b0
    nb = int(b.max()) + 2  # one empty bin between surfaces: no run crosses from one to the next
    key = surface[ok].astype(np.int64) * nb + b
    order = np.lexsort((lr, key))
    key, lr = key[order], lr[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    full = counts >= _THICK_MIN_POINTS
    starts, counts = starts[full], counts[full]
    if len(starts) < 2:
        return np.nan, [], float(np.exp(survey))
    keys = key[starts]
    med = 0.5 * (lr[starts + (counts - 1) // 2] + lr[starts + counts // 2])
    rel = med - survey
    folded = np.abs(rel)
    k = _THICK_RUN - 1
    run = np.ones(max(len(keys) - k, 0), dtype=bool)
    low = folded[k:].copy()
    for o in range(k):  # the next bins on the same surface, the same way round
        run &= (keys[o + 1:len(keys) - k + o + 1] == keys[o:len(keys) - k + o] + 1)
        run &= np.sign(rel[o + 1:len(keys) - k + o + 1]) == np.sign(rel[:len(keys) - k])
        low = np.minimum(low, folded[o:len(keys) - k + o])
    worst = float(np.exp(low[run].max())) if run.any() else np.nan
    hit = folded > np.log(limit)
    spans = []
    i = 0
    while i < len(keys):  # runs over bins (a few thousand per kilometre), not points
        if not hit[i]:
            i += 1
            continue
        j = i
        while (j + 1 < len(keys) and hit[j + 1] and keys[j + 1] == keys[j] + 1
               and np.sign(rel[j + 1]) == np.sign(rel[i])):
            j += 1
        if j - i + 1 >= _THICK_RUN:
            start = (b0 + keys[i] % nb) * _THICK_BIN
            spans.append((int(keys[i] // nb), start, start + (j - i + 1) * _THICK_BIN,
                          float(np.exp(np.median(med[i:j + 1])))))
        i = j + 1
    return worst, spans, float(np.exp(survey))


def _thick_surface_checks(deformation: Any, ratio: np.ndarray, qc: QualityConfig) -> list[Check]:
    """Advisory: a stretch of a surface one epoch sees thicker than the other (a SLAM map
    that holds it twice closer than the noise separates, or a noisier scan there), and one
    epoch's surfaces thicker throughout."""
    from .deformation.sections import SURFACE_NAMES

    worst, spans, survey = thick_spans(ratio, np.asarray(deformation.chainage),
                                       np.asarray(deformation.surface), qc.max_spread_ratio)
    typical = getattr(deformation, "typical_spread", None)
    where = ""
    if spans:
        s, a, b, r = max(spans, key=lambda sp: abs(np.log(sp[3] / survey)) * (sp[2] - sp[1]))
        epoch, other = ("compared", "reference") if r > survey else ("reference", "compared")
        folded = max(r / survey, survey / r)
        extra = ""
        if typical is not None:
            t = float(typical[0] if r > survey else typical[1])
            extra = (f"; values there can be off by up to about "
                     f"{1e3 * t * np.sqrt(folded**2 - 1):.0f} mm, more than their LoD95 says")
        more = ""
        if len(spans) > 1:
            more = f" ({len(spans) - 1} more stretch{'es' if len(spans) > 2 else ''} besides)"
        where = (f": the {epoch} epoch's {SURFACE_NAMES[s].replace('_', ' ')} at chainage "
                 f"{a:.0f}-{b:.0f} m is {folded:.2f} times as thick as the {other}'s, against "
                 f"the rest of the survey (the compared spread over the reference's {r:.2f} "
                 f"there, {survey:.2f} over the survey){more}{extra}")
    local = _check(
        "deformation.thick_surface", worst, qc.max_spread_ratio, "<=", "",
        f"one epoch sees a stretch of a surface thicker than the other{where}: a map that "
        "holds it twice a few centimetres apart (a SLAM pass that did not close onto the "
        "other) or a noisier scan there; look at both epochs' points across that surface",
        "largest ratio of the epochs' surface spreads (either way) over 3 m of one surface, "
        "against the survey's")
    checks = [dataclasses.replace(local, advisory=True)]
    # the median of the points' own ratios, both epochs at the same places: the typical
    # spreads are each epoch's over all its cores, with those the other epoch does not cover
    # (a stub's compared typical read 1.44 times the reference's, its points' ratio 1.04)
    g = survey if np.sum(np.isfinite(ratio)) >= _EPOCH_MIN_POINTS else np.nan
    thick, thin = ("compared", "reference") if g > 1 else ("reference", "compared")
    folded = max(g, 1 / g) if np.isfinite(g) else np.nan
    whole = _check(
        "deformation.epoch_spread", folded, qc.max_spread_ratio, "<=", "",
        f"the {thick} epoch's surfaces are {folded:.2f} times as thick as the {thin}'s "
        "throughout: a noisier scan, which the LoD95 takes in, or a map that holds every "
        "surface twice (a SLAM map whose passes did not close onto each other), which it "
        "does not; look at that epoch's points across a wall",
        "median ratio of the epochs' surface spreads at the same places (either way)")
    checks.append(dataclasses.replace(whole, advisory=True))
    return checks


def edge_checks(edge: Any, qc: QualityConfig, epoch: str, junction: str, *,
                advisory: bool = False) -> list[Check]:
    """Checks of one edge of a centreline network (a
    :class:`~tunneldef.network.NetworkEdge`): the share of its slices outside junction zones
    that show a tunnel section, and the scatter of their centres about the curve. A short
    branch (too few sections for a curve: the axis moved onto its centres) gets only the
    first. ``advisory``: the compared epoch's edges, whose curves only feed the registration
    (checked on its own): reported, not enforced."""
    name = f"{epoch}_network.edge{edge.id}"
    records = [r for r in edge.slices if r.reason != junction]
    ok = [r for r in records if r.ok]
    share = len(ok) / len(records) if records else np.nan
    advice = (f"edge {edge.id} of the {epoch} network ({edge.length:.1f} m) is unreliable; "
              "raise [network] min_branch_length to leave short branches out, or try "
              "[slicing] thickness/step")
    out = [_check(f"{name}.usable_slices", share, qc.min_usable_share, ">=", "", advice,
                  f"share of the {len(records)} slices outside junction zones with floor, "
                  "roof and two walls")]
    if not edge.centerline.meta.get("short_branch") and ok:
        res = edge.centerline.project(np.array([r.centre for r in ok])).distance
        scatter = float(edge.centerline.meta.get("centre_scatter_p95_m",
                                                 np.percentile(res, 95)))
        out.append(_check(f"{name}.curve_uncertainty", scatter,
                          qc.max_edge_scatter, "<=", "m", advice,
                          f"95th percentile distance of the {len(ok)} used slice centres "
                          "from the most flexible curve through them (their local scatter)"))
    if advisory:
        out = [dataclasses.replace(c, advisory=True) for c in out]
    return out


def network_registration_checks(check: Any, qc: QualityConfig) -> list[Check]:
    """Checks of a network registration from its independent figures (a
    :class:`~tunneldef.registration.verify.NetworkCheck`)."""
    rem = float(np.linalg.norm(check.remaining)) if np.all(np.isfinite(check.remaining)) \
        else np.inf
    return [
        *_fit_excess(check, qc, "the compared network does not lie on the reference as "
                     "closely as the scans' noise allows; check that both epochs show the same "
                     "drifts"),
        _check("registration.translation_residual", rem, qc.max_axial_residual, "<=", "m",
               "an independent point-to-plane fit finds the compared network off its "
               "registered position; " + _weak_advice(check),
               "length of the translation a robust point-to-plane fit still finds "
               f"({', '.join(f'{1000 * v:+.1f}' for v in check.remaining)} mm); "
               + _weak_text(check)),
        _check("registration.translation_convergence", check.spread, qc.max_axial_spread,
               "<=", "m",
               "started 2 cm off along x or y, the point-to-plane fit ends elsewhere: the "
               "common part of the networks does not fix their position against the noise "
               "(one drift direction only, or too sparse and noisy)",
               "largest distance between where the fit ends from the registered pose and "
               "from 2 cm off along +-x and +-y"),
        _check("registration.alternative_margin", check.alternative_margin,
               qc.min_alternative_margin, ">=", "",
               "the compared network fits another place nearly as well as the registered "
               "one (a look-alike cross-cut along a plain drift); a survey that shares more "
               "junctions or a distinct drift settles it",
               "evidence of the chosen pose less that of the best other pose more than 10 m "
               "away (evidence: the share of compared points on the reference less the share "
               "inside a drift the reference scanned but off its surfaces, after ICP from "
               "each; with no other pose left, the chosen evidence + 1)"),
    ]


#: below this share of the point-to-plane information, a direction counts as weakly held
#: (a network whose cross-cuts both epochs walk held 19 % along its main drift; a plain
#: drift with a bend and no common junction 2.7 %, about what the normals' noise gives)
_WEAK_SHARE = 0.05


def _direction(w: np.ndarray) -> str:
    return f"({w[0]:+.2f}, {w[1]:+.2f}, {w[2]:+.2f})"


def _weak_text(check: Any) -> str:
    w = np.asarray(check.weak_direction, dtype=np.float64)
    share = float(check.weak_share)
    if not (np.all(np.isfinite(w)) and np.isfinite(share)):
        return "the fit's weakest direction unknown"
    along = 1000 * float(np.asarray(check.remaining, dtype=np.float64) @ w)
    return (f"the surfaces hold the position least along {_direction(w)}, "
            f"{100 * share:.1f} % of the fit's information, where it reads {along:+.1f} mm")


def _weak_advice(check: Any) -> str:
    share = float(check.weak_share)
    if np.isfinite(share) and share < _WEAK_SHARE:
        return (f"the surfaces barely fix the position along "
                f"{_direction(np.asarray(check.weak_direction, dtype=np.float64))} "
                f"({100 * share:.1f} % of the fit's information, much of it the normals' "
                "own noise): the epochs share no junction or corner that would; survey a "
                "cross-cut both walk, or denser and less noisy scans")
    return "the registration did not converge"


def edge_difference_checks(differences: dict[int, float], qc: QualityConfig) -> list[Check]:
    """Per reference edge, the two epochs' centrelines after registration
    (:func:`~tunneldef.registration.verify.edge_centreline_differences`). Advisory: the
    compared curve's own error enters it (a compared main drift 5.5 cm from its own centres
    read 4.3 cm here over a reference curve 8 mm from the truth), and the compared curve feeds
    only the registration, which is checked on its own."""
    out = []
    for k, v in sorted(differences.items()):
        c = _check(f"registration.edge{k}.centreline_difference", v,
                   qc.max_centreline_difference, "<=", "m",
                   f"the two epochs' centrelines of edge {k} do not agree after registration "
                   "(sparse or noisy sections, or a wrong registration); denser scans or a "
                   "larger [slicing] thickness may help",
                   "p95 distance of the compared centreline from the reference one over the "
                   "common part, / sqrt(2)")
        out.append(dataclasses.replace(c, advisory=True))
    return out
