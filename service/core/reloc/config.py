"""Settings of relocalisation (:class:`GlobalConfig`): the view index, the global search, the
hypotheses over a drive, the decision rule and the integrity of tracking.

Two presets (:meth:`GlobalConfig.for_kind`): ``metric`` (a map drawn from the robot's own
scans: furniture included) and ``schematic`` (a floor plan: walls only, so furniture returns
are never explained and the bars on how much of a scan the map explains are lower). The user
knobs among these fields are listed in :mod:`service.core.config`; settings no preset or user
changes are constants of the modules that use them. Metres, radians; costs are beam costs
(:meth:`service.core.sensor.scoring.BeamFractions.cost`: 0.05 explained whole, 1.05 nothing),
log-likelihoods in nats.
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
        "do per scan, the rest on the next scans. None: every scan searches to the end (the "
        "paper's experiment). The service sets 50 by default.",
    )
    # --- viewpoints, search ------------------------------------------------------------------
    min_enclosed: float = Field(
        0.9,
        gt=0,
        le=1,
        description="Share of enclosure beams that must hit for a viewpoint to be inside the "
        "building. Schematic: 0.6 (plans draw doors open; at 0.9 whole paths lie far from any).",
    )
    shortlist: int = Field(
        0,
        ge=0,
        description="Coarse pose cells polished and ranked by a quick beam check before "
        "refine_top are refined; 0: rank the raw poses by point support. Schematic: 150 "
        "(furniture hides the walls point support needs).",
    )
    shortlist_violation_beams: int = Field(
        0,
        ge=0,
        description="Beams that rank the coarse cells by support less VIOLATION_WEIGHT x their "
        "share through drawn walls; 0: by support alone. Schematic: 40 (a wrong place that the "
        "furniture fits sends many beams through walls, the true pose few).",
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
        description="On keyframes a short return counts exp(-(pred - r) / this) of one (0: one). "
        "Schematic: 1.0 (furniture stands just before its room's walls, not far before them).",
    )
    # --- the decision ------------------------------------------------------------------------
    fix_llr: float = Field(
        25.0,
        gt=0,
        description="A hypothesis is fixed once its log-likelihood over the window, with its "
        "prior, beats the distinct alternatives' and the unseen place's together by this many "
        "nats: 1.25 x the smallest threshold without a false fix on the tuning split "
        "(bench/calibrate_llr.py).",
    )
    null_cost: float = Field(
        0.8,
        gt=0,
        description="The unseen place (what the search has not found) explains each frame at "
        "this cost; the leader must beat it too. Schematic: 0.7, the true pose's 90th "
        "percentile on the tuning floor plans.",
    )
    null_slope: float = Field(
        0.0,
        ge=0,
        description="The unseen place's cost on a keyframe rises by this per metre that the "
        "map's walls, seen from the leader's pose there, stand beyond drive.NULL_REACH on "
        "average (at most drive.EVIDENCE_CLIP): unmapped furniture stands between far walls, "
        "and the true place explains the keyframe worse. Schematic: 0.05. Metric: 0 (the map "
        "holds the furniture).",
    )
    kidnap_weight: float = Field(
        0.01,
        gt=0,
        le=1,
        description="After a loss the prior is the dead-reckoned pose's Gaussian and this share "
        "spread over the map: a robot carried off is rarer than a map that lacks a corridor.",
    )
    probation_travel: float = Field(
        0.0,
        ge=0,
        description="With odometry a winner is tracked this far (m) while the evidence goes on, "
        "and fixed if it still wins then. Schematic: 2.0 (a plan that lacks walls can let a "
        "wrong place explain a metre or two best).",
    )
    # --- tracking's integrity (honest status) ------------------------------------------------
    good_support: float = Field(
        0.7,
        gt=0,
        le=1,
        description="A tracked scan whose fit explains this share of its points anchors the "
        "dead-reckoned reference; a fit of a scan explained worse is only believed within "
        "states.GATE_SIGMAS of that reference. Schematic: 0.5.",
    )
    track_sigma: float = Field(
        0.15,
        gt=0,
        description="A poorly explained scan is published as tracking only while the "
        "dead-reckoned reference's position sigma is below this (m); beyond, the robot "
        "dead-reckons (status lost).",
    )
    collapse_score: float = Field(
        0.5,
        ge=0,
        le=1,
        description="Without odometry, a rejected scan scoring below this fits the map nowhere "
        "near the pose and ends the track. Schematic: 0.45.",
    )
    relock_scans: int = Field(
        3, ge=1, description="Scans in a row explained well that end dead reckoning (relock)."
    )
    max_dead_reckoning_sigma: float = Field(
        3.0, gt=0, description="Position sigma (m) past which dead reckoning gives way to a search."
    )
    contradiction: float = Field(
        0.05,
        ge=0,
        le=1,
        description="A scan contradicts a pose when more than this share of its beams returns "
        "from beyond a drawn wall: more than at the true pose, less than kidnapped.",
    )
    scan_odometry_violation: float = Field(
        1.0,
        ge=0,
        le=1,
        description="With laser odometry (update(from_scans=True)), a tracked pose with more "
        "than this share of violation beams is contradicted, accepted or not: that odometry "
        "carries a pose that slid along a corridor as precisely as a right one. Schematic: "
        "0.15. Metric: 1 (off; the map's furniture pins the pose).",
    )
    settle_scans: int = Field(
        20, ge=0, description="Scans a fixed robot stays unsettled (on a service's search worker)."
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
