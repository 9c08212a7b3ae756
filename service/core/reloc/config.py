"""Settings of relocalisation (:class:`GlobalConfig`): the view index, the global search, the
hypotheses over a drive, the decision rule and the integrity of tracking.

Two presets (:meth:`GlobalConfig.for_kind`): ``metric`` (a map drawn from the robot's own
scans: furniture included) and ``schematic`` (a floor plan: walls only, so furniture returns
are never explained and the bars on how much of a scan the map explains are lower). The user
knobs among these fields are listed in :mod:`service.core.config`; the settings no preset or
user changes are constants of the modules that use them, each with its reason. Metres,
radians; costs are beam costs (:meth:`service.core.sensor.scoring.BeamFractions.cost`, 0.05 =
explained whole, 1.05 = nothing), log-likelihoods in nats
(:meth:`service.core.sensor.scoring.SensorModel.score`).
"""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field

from service.core.types import Settings
from service.errors import LocalizationError


class GlobalConfig(Settings):
    """Weights and thresholds of relocalisation (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["metric", "schematic"] = Field("metric", description="Map kind these suit.")
    # --- the per-scan work budget -----------------------------------------------------------
    search_budget_ms: float | None = Field(
        None,
        ge=0,
        description="Work (reference ms, service.core.reloc.global_search.WORK_MS) a search may "
        "do per scan; the rest waits for the next scans. None: no budget, every scan searches as "
        "far as the search goes (the paper's experiment). The service sets it (50 by default).",
    )
    # --- viewpoints, search ------------------------------------------------------------------
    min_enclosed: float = Field(
        0.9,
        gt=0,
        le=1,
        description="Share of enclosure beams that must hit: a viewpoint is inside the building. "
        "Schematic: 0.6 (plans draw doors open: at 0.9 fr079 / intel paths lay 34 / 38 % over "
        "0.52 m from a viewpoint, where the search induces no pose; at 0.6 1.4 / 2.6 %).",
    )
    shortlist: int = Field(
        0,
        ge=0,
        description="Coarse pose cells polished on the distance field and ranked by a quick beam "
        "check before refine_top are refined; 0 = rank the raw poses by point support. "
        "Schematic: 150 (furniture hides the walls point support needs).",
    )
    shortlist_violation_beams: int = Field(
        0,
        ge=0,
        description="Beams marched on the distance field to rank the coarse cells by support "
        "less VIOLATION_WEIGHT x the share through drawn walls; 0 = by support alone. "
        "Schematic: 40 (wrong places whose walls furniture fits let a third to two thirds of "
        "their beams through walls, the true pose 0-15 %: fr079's east hall).",
    )
    refine_top: int = Field(
        16, ge=1, description="Hypotheses refined and verified. Schematic: 32 (twin rooms)."
    )
    verify_beams: int = Field(
        240,
        ge=10,
        description="Beams of a verification. Schematic: 720 (a door tells rooms apart).",
    )
    keep: int = Field(8, ge=1, description="Judged hypotheses kept (and as many being judged).")
    # --- the beam model of the search and the evidence ---------------------------------------
    violation_margin: float = Field(
        0.0,
        ge=0,
        description="A return counts as through a wall only this far (m) beyond it (at least "
        "the support tolerance). Schematic: 0.5 (plans leave out niches and door jambs).",
    )
    see_through: bool = Field(
        False,
        description="A return beyond the predicted wall on a mapped surface behind it is no "
        "violation. Metric: on (a map drawn from scans holds chairs and doors that moved; "
        "fr079: 30 % of scans verified at cost > 0.95 at their reference pose, 7 % with it).",
    )
    short_credit: float = Field(
        0.0,
        ge=0,
        le=1,
        description="Credit for a return short of the predicted wall (something unmapped in "
        "front). Schematic: 0.5 (a floor plan has no furniture).",
    )
    # --- the evidence over a drive ------------------------------------------------------------
    evidence_span: float = Field(
        6.0,
        gt=0,
        description="The window holds the keyframes of the last this many metres: longer and "
        "the odometry's drift bends a hypothesis' older poses off the map.",
    )
    evidence_short_scale: float = Field(
        0.0,
        ge=0,
        description="On keyframes a short return counts exp(-(pred - r) / this) of one (0: "
        "as one). Schematic: 1.0 (furniture stands just in front of its room's walls; a wrong "
        "place puts them far behind the returns).",
    )
    # --- the decision ------------------------------------------------------------------------
    fix_llr: float = Field(
        25.0,
        gt=0,
        description="A hypothesis is fixed once its log-likelihood over the window, with its "
        "prior, exceeds every distinct alternative's and the unseen place's together by this "
        "many nats (service.core.reloc.decision); set from the false-fix rate on the tuning "
        "split (bench/calibrate_llr.py: the smallest threshold without a false fix, times "
        "1.25; budget 50). Metric maps: 80 drives of intel and fr079, a false fix up to 15 "
        "nats (fr079, a corridor's twin 12.8 m away and turned 180 degrees, while the robot "
        "crept), none from 20; 78 of 80 fixed within 15 m at 20 and at 25, p50 0.87 m to the "
        "fix at 25 (60 drives of buildings 0-19 and the logs had shown none from 10). Floor "
        "plans: 60 drives, 2 false fixes at 15, none from 20; 57 of 60 fixed within 15 m.",
    )
    null_cost: float = Field(
        0.8,
        gt=0,
        description="The unseen place: what the search has not found is assumed to explain "
        "each frame at this cost. The leader must beat it as it beats the places found. "
        "Schematic: 0.7, the true pose's frame cost at the 90th percentile on the tuning "
        "floor plans (fr079 p50 / p90 0.47 / 0.72, intel 0.28 / 0.72, buildings 0-5 0.31-0.59 "
        "/ 0.46-0.85; 379 frames): at 0.8 a corridor alias of fr079 12 m off, explaining its "
        "17 keyframes at a mean cost of 0.69 while the true place was never found, beat the "
        "unseen place by 20 nats and was fixed (drive bench, start 2553).",
    )
    null_slope: float = Field(
        0.0,
        ge=0,
        description="The unseen place's cost on a keyframe rises by this per metre that the "
        "map's walls, seen from the leader's pose there along the keyframe's beams, stand "
        "beyond drive.NULL_REACH on average (at most drive.EVIDENCE_CLIP): where they stand "
        "far off, furniture the map does not hold stands between, and the true place explains "
        "a keyframe worse. Schematic: 0.05, the true pose's keyframe cost at the 90th "
        "percentile by that mean range on the tuning logs' floor plans (fr079 and intel, 849 "
        "frames): up to 5 m 0.57-0.66, 5-6 m 0.66-0.74, 6-8 m 0.76-0.78, beyond 8 m 0.89-0.92 "
        "(fr079's east hall, drawn as its outline: the true place at 0.71-0.74 lost to a "
        "constant 0.7). Metric: 0 (a map drawn from scans holds the furniture).",
    )
    repeat_window: int = Field(
        1,
        ge=1,
        description="With odometry a robot standing or creeping gains at most this many "
        "keyframes' evidence from one (service.core.reloc.drive.Drive.repeat; 1: none). 1 on "
        "both kinds of map: a repeat's evidence about the walls is the keyframe's own, and a "
        "wrong place gains from it as much as the true one. With 6 on metric maps a robot "
        "standing where a map lacks a corridor (intel, a third of its walls removed) fixed a "
        "place 13.7 m off at 26 nats while its dead-reckoned pose was 0.16 m from the truth: "
        "tracking poses more than 0.5 m off on the tuning logs' partial maps 0.61 % (21) with "
        "6, none with 1 (bench_partial --logs intel,fr079). On floor plans 6 gave a false "
        "fix at 37 nats on intel's plan.",
    )
    kidnap_weight: float = Field(
        0.01,
        gt=0,
        le=1,
        description="After a loss the prior is the dead-reckoned pose's Gaussian, and this "
        "share spread evenly over the map: a robot carried off is rarer than a map that lacks "
        "a corridor, so a far place must explain the drive by many nats more.",
    )
    probation_travel: float = Field(
        0.0,
        ge=0,
        description="With odometry, a winner is tracked this far (m) before it is published, "
        "while the evidence goes on; it is fixed if it still wins then. Schematic: 2.0 (a plan "
        "that lacks walls can let a wrong place explain a metre or two best).",
    )
    # --- tracking's integrity (honest status) ------------------------------------------------
    good_support: float = Field(
        0.7,
        gt=0,
        le=1,
        description="A tracked scan whose fit explains at least this share of its points "
        "anchors the dead-reckoned reference; below it the fit is only believed within "
        "states.GATE_SIGMAS of the pose the odometry carried from the last such scan. "
        "Schematic: 0.5.",
    )
    track_sigma: float = Field(
        0.15,
        gt=0,
        description="A scan the map does not explain well is published as tracking only while "
        "the dead-reckoned reference's position sigma is below this (m): beyond, a pose may "
        "be half a metre off (3 sigma) without the map saying so, and the robot dead-reckons "
        "with the status lost.",
    )
    collapse_score: float = Field(
        0.5,
        ge=0,
        le=1,
        description="Without odometry, a rejected scan scoring below this fits the map nowhere "
        "near the pose and ends the track at once (nothing bridges it). Schematic: 0.45.",
    )
    relock_scans: int = Field(
        3,
        ge=1,
        description="Dead reckoning ends when the tracker, run from the dead-reckoned pose, "
        "explains this many scans in a row well (good_support) within the gate.",
    )
    max_dead_reckoning_sigma: float = Field(
        3.0,
        gt=0,
        description="Dead reckoning gives way to a global search (with the dead-reckoned "
        "pose as the prior) once its position sigma exceeds this (m).",
    )
    contradiction: float = Field(
        0.05,
        ge=0,
        le=1,
        description="A scan contradicts a pose when more than this share of its beams returns "
        "from beyond a drawn wall (unexplained scans at the true pose on fr079: 0.011 / 0.033 "
        "p50 / p90; kidnapped: 0.06 / 0.24 p10 / p50). The kidnap bench compares it with -1 "
        "(bench/bench_kidnap.py).",
    )
    scan_odometry_violation: float = Field(
        1.0,
        ge=0,
        le=1,
        description="With an odometry measured from the scans themselves (laser odometry, "
        "update(from_scans=True)), a tracked scan whose pose has more than this share of the "
        "tracker's violation beams returning from beyond a drawn wall contradicts it, accepted "
        "and well explained or not: such an odometry moves a pose that slid along a corridor "
        "(neither the scans nor a floor plan pin it there) or turned wrong as precisely as a "
        "right one, and only the map can tell. Above the share at the true pose, which a plan "
        "drawn with closed doors raises: tuning buildings 0-9 (setup 2) p99 0.078, max 0.122, "
        "never 3 scans in a row above 0.1; tuning log intel's schematised map, poses within "
        "0.3 m, p99 0.078. Schematic: 0.15. Metric: 1 (off): there the laser odometry gives "
        "no increment along an unobserved axis and the map's furniture pins the pose (tuning "
        "log intel's metric map: lost 1.0 -> 1.8 % with it on).",
    )
    settle_scans: int = Field(
        20,
        ge=0,
        description="After a search's fix the localiser counts as unsettled for this many "
        "scans: a service keeps it on its search worker meanwhile.",
    )

    @classmethod
    def for_kind(cls, kind: str) -> GlobalConfig:
        """The preset of a map ``kind`` (``metric`` or ``schematic``)."""
        if kind == "metric":
            return cls(see_through=True)
        if kind == "schematic":
            return cls(
                kind="schematic",
                short_credit=0.5,
                refine_top=32,
                shortlist=150,
                shortlist_violation_beams=40,
                verify_beams=720,
                violation_margin=0.5,
                evidence_short_scale=1.0,
                probation_travel=2.0,
                min_enclosed=0.6,
                good_support=0.5,
                null_cost=0.7,
                null_slope=0.05,
                collapse_score=0.45,
                scan_odometry_violation=0.15,
            )
        raise LocalizationError(f"unknown map kind {kind!r}; expected metric or schematic")
