"""Settings of relocalisation (:class:`GlobalConfig`): the view index, the global search, the
hypotheses over a drive, the decision rule and the integrity of tracking.

Two presets (:meth:`GlobalConfig.for_kind`): ``metric`` (a map drawn from the robot's own
scans: furniture included) and ``schematic`` (a floor plan: walls only, so furniture returns
are never explained and the bars on how much of a scan the map explains are lower). The user
knobs among these fields are listed in :mod:`service.core.config`; the rest are internal,
each described with the reason for its value. Metres, radians; costs are beam costs
(:meth:`service.core.sensor.scoring.BeamFractions.cost`, 0.05 = explained whole, 1.05 =
nothing), log-likelihoods in nats (:meth:`service.core.sensor.scoring.SensorModel.score`).
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
        description="Work (reference ms, service.core.reloc.search.WORK_MS) a search may do per "
        "scan; the rest waits for the next scans. None: no budget, every scan searches as far "
        "as the search goes (the paper's experiment). The service sets it (50 by default).",
    )
    rescore_share: float = Field(
        0.3,
        gt=0,
        le=1,
        description="With a budget, at most this share re-scores the kept hypotheses on the "
        "scan, evidence_share scores them on the keyframes they lack, the search gets the rest "
        "(0.3 / 0.2 against 0.5 / 0.3 on tuning worlds 0-19: 96 against 93 % fixed in 15 m).",
    )
    evidence_share: float = Field(
        0.2, gt=0, le=1, description="See rescore_share (at least one keyframe is scored)."
    )
    # --- viewpoints and index ----------------------------------------------------------------
    spacing: float = Field(
        0.6, gt=0, description="Viewpoint grid spacing (m): finer than a room, coarser than a door."
    )
    min_clearance: float = Field(
        0.3, ge=0, description="Viewpoint distance to any polyline (m): where a robot fits."
    )
    enclosure_beams: int = Field(90, ge=8, description="Beams of the enclosure test (4 degrees).")
    min_enclosed: float = Field(
        0.9,
        gt=0,
        le=1,
        description="Share of enclosure beams that must hit: a viewpoint is inside the building. "
        "Schematic: 0.6 (plans draw doors open: at 0.9 fr079 / intel paths lay 34 / 38 % over "
        "0.52 m from a viewpoint, where the search induces no pose; at 0.6 1.4 / 2.6 %).",
    )
    small_ring_area: float = Field(
        6.0,
        ge=0,
        description="Closed rings smaller than this (m²) are furniture, not rooms: no viewpoint.",
    )
    # --- search ------------------------------------------------------------------------------
    scan_units: int = Field(
        5, ge=1, description="Most complex scan units compared by S* (the rest repeat them)."
    )
    min_unit_complexity: float = Field(
        0.05, ge=0, description="Smallest unit complexity (m·rad): a straight wall tells nothing."
    )
    range_slack: float = Field(
        0.4, ge=0, description="|range difference| allowed beyond the grid half-diagonal (m)."
    )
    view_complexity_ratio: float = Field(
        0.25, ge=0, description="View units less complex than this x the scan unit's are skipped."
    )
    max_shape_distance: float = Field(0.6, gt=0, description="S* gate for a pair (m).")
    max_turn_difference: float = Field(
        0.35, gt=0, description="Corresponding anchor corners turn alike within this (rad)."
    )
    pairs_budget: int = Field(
        360, ge=1, description="Induced poses per scan, shared by the chosen scan units."
    )
    support_points: int = Field(80, ge=10, description="Scan points of the support test.")
    shortlist: int = Field(
        0,
        ge=0,
        description="Coarse pose cells polished on the distance field and ranked by a quick beam "
        "check before refine_top are refined; 0 = rank the raw poses by point support. "
        "Schematic: 150 (furniture hides the walls point support needs).",
    )
    shortlist_cell: float = Field(0.4, gt=0, description="Coarse pose cell size (m).")
    shortlist_angle: float = Field(0.2, gt=0, description="Coarse pose cell heading width (rad).")
    shortlist_beams: int = Field(90, ge=8, description="Beams of the shortlist's quick check.")
    shortlist_violation_beams: int = Field(
        0,
        ge=0,
        description="Beams marched on the distance field to rank the coarse cells by support "
        "less violation_weight x the share through drawn walls; 0 = by support alone. "
        "Schematic: 40 (wrong places whose walls furniture fits let a third to two thirds of "
        "their beams through walls, the true pose 0-15 %: fr079's east hall).",
    )
    refine_top: int = Field(
        16, ge=1, description="Hypotheses refined and verified. Schematic: 32 (twin rooms)."
    )
    refine_iterations: int = Field(6, ge=1, description="Point-to-line fit steps per stage.")
    fine_scale: float = Field(
        0.05, gt=0, description="Cauchy scale (m) of the tight fit stage and of the polish."
    )
    verify_beams: int = Field(
        240,
        ge=10,
        description="Beams of a verification. Schematic: 720 (a door tells rooms apart).",
    )
    keep: int = Field(8, ge=1, description="Judged hypotheses kept (and as many being judged).")
    distinct_distance: float = Field(
        0.8, gt=0, description="Hypotheses farther apart than this (m) are distinct places."
    )
    distinct_angle: float = Field(
        0.5, gt=0, description="... or whose headings differ more than this (rad)."
    )
    twin_shortlist: int = Field(
        60, ge=0, description="shortlist of a self-similarity check (it searches the map's view)."
    )
    twin_refine_top: int = Field(12, ge=1, description="refine_top of a self-similarity check.")
    composite_scans: int = Field(
        3,
        ge=1,
        description="With odometry the search matches the last this many scans fused into one "
        "360-degree scan (service.core.reloc.composite): a look-around sees the door that "
        "tells twin rooms apart; 1 = every scan alone.",
    )
    composite_bins: int = Field(
        720, ge=8, description="Beams of the composite (never finer than the laser's)."
    )
    composite_travel: float = Field(
        0.5, gt=0, description="Scans farther than this (m) from the newest stay out of it."
    )
    # --- the beam model of the search and the evidence ---------------------------------------
    violation_weight: float = Field(
        2.0,
        ge=0,
        description="Cost of a beam through a drawn wall, in units of an unexplained beam: a "
        "wall in the way contradicts a pose, a missing one only fails to confirm it.",
    )
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
    cost_floor: float = Field(0.05, gt=0, description="Added to every beam cost.")
    # --- the evidence over a drive ------------------------------------------------------------
    evidence_spacing: float = Field(
        0.3,
        gt=0,
        description="With odometry, a scan becomes a keyframe when the robot has driven this "
        "far (m) since the last one: closer scans repeat each other's evidence.",
    )
    evidence_turn: float = Field(
        0.3, gt=0, description="... or turned this much (rad): a turn shows new walls."
    )
    evidence_span: float = Field(
        6.0,
        gt=0,
        description="The window holds the keyframes of the last this many metres: longer and "
        "the odometry's drift bends a hypothesis' older poses off the map.",
    )
    evidence_frames: int = Field(20, ge=1, description="At most this many keyframes.")
    evidence_clip: float = Field(
        1.0,
        gt=0,
        description="A keyframe's cost is clipped here: one keyframe with a person in front "
        "of the laser must not outweigh the drive.",
    )
    evidence_short_scale: float = Field(
        0.0,
        ge=0,
        description="On keyframes a short return counts exp(-(pred - r) / this) of one (0: "
        "as one). Schematic: 1.0 (furniture stands just in front of its room's walls; a wrong "
        "place puts them far behind the returns).",
    )
    evidence_drop: float = Field(
        60.0,
        gt=0,
        description="A hypothesis this many nats below the leader, on keyframes both were "
        "scored on (3 at least), is let go (a mean cost 0.3 worse over 10 keyframes).",
    )
    rescore_prior: float = Field(
        0.02,
        ge=0,
        description="With odometry, the re-scoring's polish keeps the odometry-moved pose as a "
        "prior of this weight: without it a hypothesis slid ~0.1 m per scan along corridors "
        "(tuning building 12).",
    )
    # --- the decision ------------------------------------------------------------------------
    fix_llr: float = Field(
        12.5,
        gt=0,
        description="A hypothesis is fixed once its log-likelihood over the window, with its "
        "prior, exceeds every distinct alternative's and the unseen place's together by this "
        "many nats (service.core.reloc.decision); set from the false-fix rate on the tuning "
        "split (bench/calibrate_llr.py: the smallest threshold without a false fix, times "
        "1.25; 60 tuning drives, buildings 0-19 and 20 each of intel and fr079, budget 50). "
        "Metric: 12.5 (1 false fix up to 8 nats, a robot turning in place on fr079, none "
        "from 10 on; 59 of 60 fixed within the travel limit, p50 0.20 m to the fix at 12). "
        "Schematic: 25 (2 false fixes at 15, none from 20 on, 57 of 60 fixed within 15 m at "
        "20 and at 25).",
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
        "beyond null_reach on average (at most evidence_clip): where they stand far off, "
        "furniture the map does not hold stands between, and the true place explains a "
        "keyframe worse. Schematic: 0.05, the true pose's keyframe cost at the 90th "
        "percentile by that mean range on the tuning logs' floor plans (fr079 and intel, 849 "
        "frames): up to 5 m 0.57-0.66, 5-6 m 0.66-0.74, 6-8 m 0.76-0.78, beyond 8 m 0.89-0.92 "
        "(fr079's east hall, drawn as its outline: the true place at 0.71-0.74 lost to a "
        "constant 0.7). Metric: 0 (a map drawn from scans holds the furniture).",
    )
    null_reach: float = Field(
        5.0, ge=0, description="See null_slope (m): the mean range where the rise begins."
    )
    scan_window: int = Field(
        6, ge=1, description="Without odometry the window holds the last this many scans."
    )
    repeat_window: int = Field(
        6,
        ge=1,
        description="With odometry a robot standing or creeping gains at most this many "
        "keyframes' evidence from one (service.core.reloc.drive.Drive.repeat; 1: none). Metric: "
        "6, as scan_window (tuning split: false fixes unchanged, travel to the fix p50 0.33 -> "
        "0.20 m at 12 nats). Schematic: 1 (a false fix at 37 nats on intel's plan with 6).",
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
    confirm_distance: float = Field(
        0.3, gt=0, description="The tracker's first fit must lie this close to the winner (m) ..."
    )
    confirm_angle: float = Field(0.1, gt=0, description="... and turned less than this (rad) ...")
    confirm_sigma: float = Field(
        0.05,
        gt=0,
        description="... with a position sigma of at most this (m): a corridor's parallel walls "
        "verify equally well 0.8 m further along (intel floor plan: a fix 0.8 m off, sigma "
        "0.19 m; correct fixes 0.004-0.01 m).",
    )
    # --- tracking's integrity (honest status) ------------------------------------------------
    good_support: float = Field(
        0.7,
        gt=0,
        le=1,
        description="A tracked scan whose fit explains at least this share of its points "
        "anchors the dead-reckoned reference; below it the fit is only believed within "
        "gate_sigmas of the pose the odometry carried from the last such scan. Schematic: 0.5.",
    )
    gate_sigmas: float = Field(
        3.0,
        gt=0,
        description="How many standard deviations of the dead-reckoned reference a poorly "
        "explained fit may stray from it before the localiser dead-reckons.",
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
        "p50 / p90; kidnapped: 0.06 / 0.24 p10 / p50).",
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
    odom_turn_assist: float = Field(
        1.0,
        gt=0,
        description="With the odometry prior off, an odometry turn larger than this (rad) still "
        "moves the tracker's pose first (the tracker follows turns up to 1.3 rad).",
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
                fix_llr=25.0,
                repeat_window=1,
                collapse_score=0.45,
                scan_odometry_violation=0.15,
            )
        raise LocalizationError(f"unknown map kind {kind!r}; expected metric or schematic")
