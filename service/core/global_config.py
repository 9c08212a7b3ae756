"""Weights and thresholds of global localisation (:class:`GlobalConfig`), shared by the view
index (:mod:`service.core.view_index`), the search (:mod:`service.core.global_search`) and
:class:`service.core.global_localization.GlobalShapeLocalizer`."""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field

from service.core.drive_config import DriveConfig
from service.errors import LocalizationError


class GlobalConfig(DriveConfig):
    """Weights and thresholds of global localisation (metres, radians; "support" fractions).

    :meth:`for_kind` gives the schematic variant (furniture in the scan is never explained by a
    floor plan, so the quality bars are lower there). The search over a drive's fields (budget,
    keyframe evidence, probation) are :class:`~service.core.drive_config.DriveConfig`'s.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["metric", "schematic"] = Field(
        "metric", description="The map kind these values are the preset of (for_kind)."
    )
    # --- viewpoints and index ----------------------------------------------------------------
    spacing: float = Field(0.6, gt=0, description="Viewpoint grid spacing (m).")
    min_clearance: float = Field(0.3, ge=0, description="Viewpoint distance to any polyline (m).")
    enclosure_beams: int = Field(90, ge=8, description="Beams of the enclosure test.")
    min_enclosed: float = Field(
        0.9, gt=0, le=1, description="Fraction of enclosure beams that must hit within range."
    )
    small_ring_area: float = Field(
        6.0, ge=0, description="Closed rings smaller than this (m²) are obstacles, not rooms."
    )
    grid_resolution: float = Field(0.05, gt=0, description="Distance-field cell size (m).")
    # --- search ------------------------------------------------------------------------------
    scan_units: int = Field(5, ge=1, description="Most complex scan units compared by S*.")
    min_unit_complexity: float = Field(0.05, ge=0, description="Smallest unit complexity (m·rad).")
    range_slack: float = Field(
        0.4, ge=0, description="|range difference| allowed beyond the grid half-diagonal (m)."
    )
    view_complexity_ratio: float = Field(
        0.25,
        ge=0,
        description="View units less complex than this times the scan unit's are skipped.",
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
        description="Coarse pose cells (best induced pose each) polished on the distance field "
        "and ranked by a quick beam check before the refine_top best are chosen; 0 = rank the "
        "raw induced poses by point support. Schematic: 150 (furniture hides the walls that "
        "point support needs; on the exact map support ranks well and this is off).",
    )
    shortlist_cell: float = Field(0.4, gt=0, description="Coarse pose cell size (m).")
    shortlist_angle: float = Field(0.2, gt=0, description="Coarse pose cell heading width (rad).")
    shortlist_beams: int = Field(90, ge=8, description="Beams of the shortlist's quick check.")
    shortlist_violation_beams: int = Field(
        0,
        ge=0,
        description="Beams marched on the distance field to rank the coarse pose cells for "
        "the shortlist by support less violation_weight x the share of beams through a drawn "
        "wall (pose_scoring._field_violations); 0 = by support alone. Schematic: 40 (where the "
        "plan shows less than half of a scan, wrong places whose walls the furniture fits "
        "out-rank the true pose on support, but let a third to two thirds of their beams "
        "through walls, the true pose 0-15 %: fr079's east hall).",
    )
    refine_top: int = Field(
        16, ge=1, description="Hypotheses refined and verified. Schematic: 32 (twin rooms)."
    )
    refine_iterations: int = Field(6, ge=1, description="Point-to-line fit steps per stage.")
    fine_scale: float = Field(
        0.05, gt=0, description="Cauchy scale (m) of the second, tight refinement stage."
    )
    verify_beams: int = Field(
        240, ge=10, description="Beams of the per-hypothesis verification. Schematic: 720."
    )
    keep: int = Field(8, ge=1, description="Hypotheses kept from one scan to the next.")
    distinct_distance: float = Field(
        0.8, gt=0, description="Hypotheses farther apart than this (m) are distinct."
    )
    distinct_angle: float = Field(
        0.5, gt=0, description="... or whose headings differ more than this (rad)."
    )
    violation_weight: float = Field(
        2.0, ge=0, description="Cost weight of beams that pass through a map wall."
    )
    violation_margin: float = Field(
        0.0,
        ge=0,
        description="A return counts as a violation only this far (m) beyond the predicted "
        "wall (at least the support tolerance). Schematic: 0.5 — a floor plan leaves out "
        "niches and door-jamb faces, so the true pose sees shallow 'violations' too.",
    )
    see_through: bool = Field(
        False,
        description="A return beyond the predicted wall that lies on a mapped surface the "
        "beam crosses behind it is no violation (:func:`service.core.pose_scoring."
        "_beam_fractions`). Metric: on (a map drawn from a robot's scans holds chairs, "
        "cabinets and doors that are elsewhere, open or seen past later: on the tuning log "
        "fr079 30 % of the scans verified at cost > 0.95 at their reference pose, 7 % with "
        "this; intel 3 % -> 0). Schematic: off (a floor plan draws walls only).",
    )
    short_credit: float = Field(
        0.0,
        ge=0,
        le=1,
        description="Credit for a return short of the predicted wall (an unmapped object in "
        "front of it). Schematic: 0.5 (a floor plan has no furniture).",
    )
    cost_floor: float = Field(0.05, gt=0, description="Added to every hypothesis' cost.")
    ambiguity_scale: float = Field(
        0.1,
        gt=0,
        description="Cost margin of the best over the best distinct alternative at which the "
        "ambiguity reaches 0 (ambiguity = 1 - margin / scale, clipped); on an exact map "
        "small margins are significant. Schematic: 0.2.",
    )
    composite_scans: int = Field(
        3,
        ge=1,
        description="While searching, the last this many scans are fused into one virtual "
        "360-degree scan from the newest pose (service.core.composite), when they came with "
        "odometry; 1 = every scan alone.",
    )
    composite_bins: int = Field(
        720,
        ge=8,
        description="Beams of the virtual composite scan (fewer when the laser's own beams are "
        "coarser: never finer than them).",
    )
    composite_travel: float = Field(
        0.5,
        gt=0,
        description="Older scans taken farther than this (m, by odometry) from the newest one "
        "are left out of the composite (their occlusions would no longer hold).",
    )
    odom_turn_assist: float = Field(
        1.0,
        gt=0,
        description="While tracking without the odometry prior (``motion.use_odometry`` "
        "false), an odometry turn larger than this (rad) since the last scan still moves the "
        "tracker's pose first (the tracker follows turns up to its max_turn of 1.3 rad).",
    )
    # --- decision ----------------------------------------------------------------------------
    window: int = Field(3, ge=1, description="Scans over which a hypothesis' cost is averaged.")
    max_fix_cost: float = Field(
        0.2, gt=0, description="A winner's mean cost must be below this. Schematic: 0.3."
    )
    max_fix_ambiguity: float = Field(
        0.5, gt=0, le=1, description="A winner's ambiguity must be below this. Schematic: 0.35."
    )
    fused_fix_ambiguity: float = Field(
        0.5,
        gt=0,
        le=1,
        description="max_fix_ambiguity for a composite scan (look-around): it holds every "
        "scan of the window at once, so a smaller margin is as telling. Schematic: 0.7 "
        "(margin >= 0.06; safe only together with the self-similarity check: without it the "
        "twin rooms W1/W4 and E1/E3 won by noise, 2 % confident wrong fixes over 200 poses).",
    )
    fused_fix_cost: float = Field(
        0.2,
        gt=0,
        description="max_fix_cost for a composite scan. Schematic: 0.45 (a 360-degree view "
        "of a furnished room leaves a third of its beams unexplained by a floor plan).",
    )
    fused_single_ambiguity: float = Field(
        0.35,
        ge=0,
        le=1,
        description="single_scan_ambiguity for a composite scan (the fit must also meet "
        "max_fix_cost then). Schematic: 0 (always two scans: a 270-degree composite can miss "
        "the one door that tells twin rooms apart).",
    )
    single_scan_ambiguity: float = Field(
        0.35,
        ge=0,
        le=1,
        description="Below this ambiguity one scan suffices; else two. Schematic: 0 (always "
        "two: similar rooms of a floor plan differ by little more than noise).",
    )
    min_information: float = Field(
        0.0,
        ge=0,
        description="No fix from a scan whose most complex units sum to less shape complexity "
        "(m·rad): facing a bare wall, any wall fits. Schematic: 8.0.",
    )
    confirm_distance: float = Field(
        0.3, gt=0, description="The tracker's first pose must be this close to the winner (m)."
    )
    confirm_angle: float = Field(
        0.1,
        gt=0,
        description="... and turned less than this from it (rad): a tracker fit that swings the "
        "heading away from the verified pose is not a confirmation.",
    )
    confirm_sigma: float = Field(
        0.05,
        gt=0,
        description="... and the confirming fit must pin the position down: the largest "
        "standard deviation of its xy covariance at most this (m). A corridor's parallel "
        "walls verify equally well 0.8 m further along (tuning log intel, schematised map: a "
        "fix 0.8 m off with a 0.19 m sigma along the corridor; correct fixes 0.004-0.01 m).",
    )
    # --- recovery near the lost track ------------------------------------------------------
    near_radius: float = Field(
        1.0,
        gt=0,
        description="After a loss, hypotheses within this (m) of the dead-reckoned last pose "
        "(moved by odometry, or held without it) are 'near the track': one of them is fixed "
        "on one scan if its cost is within near_cost_margin of the best (the motion history is "
        "the prior that twin places far away lack).",
    )
    near_growth: float = Field(
        0.2,
        ge=0,
        description="The near radius grows by this share of the odometry travel since the "
        "loss; without odometry by twice the robot's recent speed per scan.",
    )
    near_turn: float = Field(
        0.6,
        gt=0,
        description="With odometry, a near hypothesis must also be turned less than this "
        "(rad) from the dead-reckoned heading.",
    )
    near_cost_margin: float = Field(
        0.1,
        ge=0,
        description="A near hypothesis wins over a far one unless the far one's cost is lower "
        "by more than this.",
    )
    far_confirm_scans: int = Field(
        4,
        ge=1,
        description="A fix far from the dead-reckoned last pose must have been the best "
        "hypothesis on this many consecutive scans (never on one scan alone).",
    )
    reacquire_support: float = Field(
        0.5,
        ge=0,
        le=1,
        description="After a loss with odometry, the tracker is also run from the "
        "dead-reckoned last pose on every scan; when it accepts reacquire_scans scans in a "
        "row from there, each fit explaining at least this share of the scan, tracking "
        "resumes without a search fix (a stretch the map explained too little of is "
        "behind the robot).",
    )
    reacquire_scans: int = Field(3, ge=1, description="See reacquire_support.")
    # --- integrity ---------------------------------------------------------------------------
    collapse_score: float = Field(
        0.5,
        ge=0,
        le=1,
        description="A rejected scan scoring below this means 'lost' at once (with an "
        "odometry prior: lost_after such scans in a row, see collapse_violation). "
        "Schematic: 0.45.",
    )
    collapse_violation: float = Field(
        0.05,
        ge=-1,
        le=1,
        description="With an odometry prior, a rejected scan below collapse_score counts "
        "towards the collapse (lost_after in a row) only when it contradicts the tracked "
        "pose: more than this share of the tracker's violation beams return from beyond a "
        "mapped wall (ShapeLocalizer.violations). Otherwise the odometry bridges it, as the "
        "tracker bridges its rejected scans until lost_sigma_xy. Once the scan-to-scan fit "
        "has failed to match a scan to the one before (a break in what the laser sees, "
        "ScanOdometryConfig.min_inliers; 0.02-0.37 % of the real logs' scans, and a "
        "kidnap's first scan), every scan below collapse_score counts, accepted or not, "
        "until one scores above it. A hall drawn as its outline leaves most of a scan "
        "unexplained without contradicting the pose: on the tuning log fr079 each "
        "unexplained stretch there ended the track, 0.04 m from the truth, and a search "
        "re-fixed it 0.4-0.9 m off (unexplained scans at the true pose: violation share "
        "0.011 / 0.033 p50 / p90; kidnapped: 0.06 / 0.24 p10 / p50). Not applied to a "
        "winner on probation. -1: every unexplained scan counts (the earlier rule).",
    )
    scan_odometry_violation: float = Field(
        1.0,
        ge=0,
        le=1,
        description="With an odometry measured from the scans themselves (laser odometry, "
        "update(from_scans=True)), a scan whose tracked pose has more than this share of the "
        "tracker's violation beams returning from beyond a mapped wall counts towards the "
        "collapse (lost_after in a row) even when it was accepted: on a floor plan such an "
        "odometry moves a pose that slid along a corridor (neither the scans nor the plan pin "
        "it there) or turned wrong as precisely as a right one, and only the map can tell. "
        "Above the share at the true pose, which a plan drawn with closed doors raises: "
        "tuning buildings 0-9 (setup 2) p99 0.078, max 0.122, never 3 scans in a row above "
        "0.1; tuning log intel's schematised map, poses within 0.3 m, p99 0.078. "
        "Schematic: 0.15. Metric: 1 (off): there the laser odometry gives no increment "
        "along an unobserved axis (LaserOdometryConfig.unobserved_unknown) and the map's "
        "furniture pins the pose; a map drawn from a log shows through what it left out "
        "(tuning log intel's metric map: lost 1.0 -> 1.8 % with it on).",
    )

    @classmethod
    def for_kind(cls, kind: str) -> GlobalConfig:
        """Defaults for a map ``kind`` (``metric`` or ``schematic``)."""
        if kind == "metric":
            return cls(see_through=True)
        if kind == "schematic":
            return cls(
                kind="schematic",
                max_fix_cost=0.3,
                short_credit=0.5,
                ambiguity_scale=0.2,
                collapse_score=0.45,
                scan_odometry_violation=0.15,
                min_information=8.0,
                max_fix_ambiguity=0.35,
                single_scan_ambiguity=0.0,
                refine_top=32,
                fused_fix_ambiguity=0.7,
                fused_single_ambiguity=0.0,
                fused_fix_cost=0.45,
                shortlist=150,
                shortlist_violation_beams=40,
                verify_beams=720,
                violation_margin=0.5,
                probation_travel=2.0,
                fix_min_found=2,
                probation_verdict=True,
                confirm_drive_prior=True,
                evidence_short_scale=1.0,
                probation_searches=1,
                verdict_refine=True,
                probation_verdict_margin=0.05,
                probation_reversal=True,
                probation_contest_all=True,
                window_polish=True,
                drive_recent_frames=8,
            )
        raise LocalizationError(f"unknown map kind {kind!r}; expected metric or schematic")
