"""Settings of relocalisation (:class:`GlobalConfig`), with two presets: ``metric`` (a map
drawn from the robot's own scans, furniture included) and ``schematic`` (a floor plan: walls
only, so furniture returns are never explained). The user knobs among them are listed in
:mod:`service.core.config`; settings no preset or user changes are constants of the modules
that use them. Metres, radians; beam costs 0.05 (explained whole) to 1.05; nats.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import ConfigDict, Field

from service.core.types import Settings
from service.errors import LocalizationError

Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]
Share = Annotated[float, Field(ge=0, le=1)]
PositiveShare = Annotated[float, Field(gt=0, le=1)]
Count = Annotated[int, Field(ge=0)]
AtLeastOne = Annotated[int, Field(ge=1)]


class GlobalConfig(Settings):
    """Weights and thresholds of relocalisation (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["metric", "schematic"] = Field("metric", description="Map kind these suit.")
    # --- the per-scan work budget -----------------------------------------------------------
    search_budget_ms: NonNegative | None = Field(
        None,
        description="Work (reference ms, global_search.WORK_MS) a search may do per scan, the "
        "rest on the next scans; None: each scan searches to the end. The service sets 50.",
    )
    # --- viewpoints, search ------------------------------------------------------------------
    min_enclosed: PositiveShare = Field(
        0.9,
        description="Share of enclosure beams that must hit for a viewpoint to be inside the "
        "building. Schematic: 0.6 (plans draw doors open; at 0.9 whole paths lie far from any).",
    )
    shortlist: Count = Field(
        0,
        description="Coarse pose cells polished and ranked by a quick beam check before "
        "refine_top are refined (0: by point support). Schematic: 150 (furniture hides walls).",
    )
    shortlist_violation_beams: Count = Field(
        0,
        description="Beams that rank the coarse cells by support less their share through drawn "
        "walls. Schematic: 40 (where the furniture fits a wrong place, its beams cross walls).",
    )
    refine_top: AtLeastOne = Field(
        16, description="Hypotheses refined and verified. Schematic: 32 (twin rooms)."
    )
    verify_beams: int = Field(
        240,
        ge=10,
        description="Beams of a verification. Schematic: 720 (a door tells rooms apart).",
    )
    keep: AtLeastOne = Field(8, description="Judged hypotheses kept (and as many being judged).")
    # --- the beam model of the search and the evidence ---------------------------------------
    violation_margin: NonNegative = Field(
        0.0,
        description="A return counts as through a wall only this far (m) beyond it (at least "
        "the support tolerance). Schematic: 0.5 (plans leave out niches and door jambs).",
    )
    see_through: bool = Field(
        False,
        description="A return beyond the predicted wall on a mapped surface behind it is no "
        "violation. Metric: on (a map drawn from scans holds chairs and doors that moved).",
    )
    short_credit: Share = Field(
        0.0,
        description="Credit for a return short of the predicted wall (something unmapped in "
        "front). Schematic: 0.5 (a floor plan has no furniture).",
    )
    # --- the evidence over a drive ------------------------------------------------------------
    evidence_span: Positive = Field(
        6.0,
        description="The window holds the keyframes of the last this many metres (odometry drift "
        "bends older poses off the map); a fix outside the dead-reckoned gate is doubted as far.",
    )
    evidence_short_scale: NonNegative = Field(
        0.0,
        description="On keyframes a short return counts exp(-(pred - r) / this) of one (0: one). "
        "Schematic: 1.0 (furniture stands just before its room's walls, not far before them).",
    )
    # --- the decision ------------------------------------------------------------------------
    fix_llr: Positive = Field(
        25.0,
        description="A hypothesis is fixed once its log-likelihood ratio against the rest reaches "
        "this (nats), set from the false fixes of 100 tuning drives (docs/results/llr-threshold"
        ".md): metric maps none from 8 (an earlier sample had one at 15). With probation_travel "
        "a winner enters probation here and is fixed at pass_llr (docs/decisions/0029).",
    )
    pass_llr: Positive = Field(
        25.0,
        description="A first fix's probation (no prior pose) passes, after probation_travel, "
        "once the decision names its winner at this (nats; at fix_llr after a loss). Schematic: "
        "62.5, the rule of docs/results/llr-probation.md (50 x 1.25; decisions/0029).",
    )
    null_cost: Positive = Field(
        0.8,
        description="The unseen place (what the search has not found) explains each frame at "
        "this cost. Schematic: 0.7, the true pose's 90th percentile on tuning floor plans.",
    )
    null_slope: NonNegative = Field(
        0.05,
        description="The unseen place's cost on a keyframe rises by this per metre the map's "
        "walls stand beyond drive.NULL_REACH on average: what the map lacks (furniture a floor "
        "plan leaves out, a corridor missing from a metric map) stands before far walls, and "
        "the true place explains less there. The true place's median cost on the tuning logs' "
        "metric maps with corridors removed rises so (0.80 at 6-7 m, 0.97 at 8-10 m).",
    )
    kidnap_weight: PositiveShare = Field(
        0.01,
        description="After a loss the prior is the dead-reckoned pose's Gaussian and this share "
        "spread over the map: a robot carried off is rarer than a map that lacks a corridor.",
    )
    probation_travel: NonNegative = Field(
        0.0,
        description="With odometry a winner is tracked this far (m) and fixed if it still wins "
        "then. Schematic: 2.0 (a plan lacking walls lets a wrong place win for a metre or two).",
    )
    # --- tracking's integrity (honest status) ------------------------------------------------
    good_support: PositiveShare = Field(
        0.7,
        description="A fit explaining this share of its scan anchors the dead-reckoned reference; "
        "a worse one is believed within states.GATE_SIGMAS of it. Schematic: 0.5.",
    )
    track_sigma: Positive = Field(
        0.15,
        description="A poorly explained scan is tracking only while the dead-reckoned "
        "reference's position sigma is below this (m): beyond, a pose may be half a metre off "
        "(3 sigma) without the map saying so, and the robot dead-reckons.",
    )
    collapse_score: Share = Field(
        0.5,
        description="Without odometry, a rejected scan scoring below this fits the map nowhere "
        "near the pose and ends the track. Schematic: 0.45.",
    )
    relock_window: bool = Field(
        True,
        description="Dead reckoning relocks from a window search over its gate too. Schematic: "
        "off (a held-out building's floor plan relocked 0.5 m+ off on a room drawn alike).",
    )
    relock_support: PositiveShare = Field(
        0.5,
        description="A relock's fit from the window search's distinct peak is good explaining "
        "this share (good_support if lower), as does a search's fix without probation_travel: "
        "half the scan explained is a map that holds.",
    )
    relock_scans: AtLeastOne = Field(
        3, description="Scans in a row explained well that end dead reckoning (relock)."
    )
    max_dead_reckoning_sigma: Positive = Field(
        3.0, description="Position sigma (m) past which dead reckoning gives way to a search."
    )
    contradiction: Share = Field(
        0.05,
        description="A scan contradicts a pose when more than this share of its beams returns "
        "from beyond a drawn wall: more than at the true pose, less than kidnapped.",
    )
    scan_odometry_violation: Share = Field(
        1.0,
        description="With laser odometry, a tracked pose with more than this share of beams "
        "through walls is contradicted: that odometry carries a pose that slid along a "
        "corridor as well as a right one. Schematic: 0.15. Metric: 1 (off: furniture pins it).",
    )
    settle_scans: Count = Field(
        20, description="Scans a fixed robot stays unsettled (on a service's search worker)."
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
                pass_llr=62.5,
                min_enclosed=0.6,
                good_support=0.5,
                null_cost=0.7,
                collapse_score=0.45,
                scan_odometry_violation=0.15,
                relock_window=False,
            )
        raise LocalizationError(f"unknown map kind {kind!r}; expected metric or schematic")
