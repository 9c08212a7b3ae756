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
        "do per scan; the rest waits for the next scans. None: every scan searches to the end "
        "(the paper's experiment). The service sets it (50 by default).",
    )
    # --- viewpoints, search ------------------------------------------------------------------
    min_enclosed: float = Field(
        0.9,
        gt=0,
        le=1,
        description="Share of enclosure beams that must hit: a viewpoint is inside the building. "
        "Schematic: 0.6 (plans draw doors open: at 0.9 a third of a robot's path lies far from "
        "any viewpoint, where the search induces no pose).",
    )
    shortlist: int = Field(
        0,
        ge=0,
        description="Coarse pose cells polished on the distance field and ranked by a quick beam "
        "check before refine_top are refined; 0: rank the raw poses by point support. "
        "Schematic: 150 (furniture hides the walls point support needs).",
    )
    shortlist_violation_beams: int = Field(
        0,
        ge=0,
        description="Beams marched on the distance field to rank the coarse cells by support "
        "less VIOLATION_WEIGHT x the share through drawn walls; 0: by support alone. "
        "Schematic: 40 (a wrong place whose walls the furniture fits lets many beams through "
        "drawn walls, the true pose few).",
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
        "violation. Metric: on (a map drawn from scans holds chairs and doors that moved).",
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
        "many nats (service.core.reloc.decision): the smallest threshold without a false fix "
        "on the tuning split, times 1.25 (bench/calibrate_llr.py; docs/decisions/0017).",
    )
    null_cost: float = Field(
        0.8,
        gt=0,
        description="The unseen place: what the search has not found is assumed to explain "
        "each frame at this cost. The leader must beat it as it beats the places found. "
        "Schematic: 0.7, the true pose's frame cost at the 90th percentile on the tuning "
        "floor plans (at 0.8 an alias was fixed while the true place was never found).",
    )
    null_slope: float = Field(
        0.0,
        ge=0,
        description="The unseen place's cost on a keyframe rises by this per metre that the "
        "map's walls, seen from the leader's pose there along the keyframe's beams, stand "
        "beyond drive.NULL_REACH on average (at most drive.EVIDENCE_CLIP): where they stand "
        "far off, furniture the map does not hold stands between, and the true place explains "
        "a keyframe worse. Schematic: 0.05, the true pose's keyframe cost at the 90th "
        "percentile by that range on the tuning floor plans. Metric: 0 (a map drawn from "
        "scans holds the furniture).",
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
        "from beyond a drawn wall: above the share at the true pose, below a kidnapped "
        "robot's (bench/bench_kidnap.py).",
    )
    scan_odometry_violation: float = Field(
        1.0,
        ge=0,
        le=1,
        description="With an odometry measured from the scans themselves (laser odometry, "
        "update(from_scans=True)), a tracked scan whose pose has more than this share of the "
        "tracker's violation beams returning from beyond a drawn wall contradicts it, accepted "
        "or not: such an odometry moves a pose that slid along a corridor or turned wrong as "
        "precisely as a right one, and only the map can tell. Schematic: 0.15, above the share "
        "at the true pose on plans drawn with closed doors. Metric: 1 (off): the map's "
        "furniture pins the pose, and with it on more scans were lost.",
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
