"""Parameters of the search over a drive (:class:`DriveConfig`): the per-scan work budget, the
drive's keyframe evidence, the winner's probation and the re-scoring of kept hypotheses, used by
:mod:`service.core.drive_search`, :mod:`service.core.evidence` and
:mod:`service.core.hypotheses`. :class:`service.core.global_config.GlobalConfig` inherits them:
one settings model, split along this seam so that each file can be read whole."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class DriveConfig(BaseModel):
    """The search over a drive, within a per-scan budget (metres, radians; costs as the
    search's). Use it through :class:`service.core.global_config.GlobalConfig`."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    search_budget_ms: float | None = Field(
        None,
        gt=0,
        description="Per-scan work budget of a search (reference ms, a deterministic work "
        "model: ``global_search.WORK_MS``). ``None``: every searching scan runs a whole "
        "search (offline runs, the paper's experiment). With a budget the search is spread "
        "over scans: the kept hypotheses are moved by odometry and re-scored on every scan, "
        "and a search started on one scan delivers its hypotheses some scans later. The "
        "service sets it (``ServiceSettings.search_budget_ms``) so that one searching robot "
        "cannot hold a worker much longer than a tracked scan takes.",
    )
    twin_shortlist: int = Field(
        48,
        ge=0,
        description="With a budget, the self-similarity check's search keeps at most this "
        "many coarse cells (``shortlist``, where the map kind uses one): it matches the map's "
        "own view, whose twins rank near the top, so a third of the full search's work finds "
        "them.",
    )
    twin_refine_top: int = Field(
        12,
        ge=1,
        description="With a budget, at most this ``refine_top`` in the self-similarity check.",
    )
    evidence_spacing: float = Field(
        0.3,
        gt=0,
        description="Budgeted search with odometry: a scan becomes a keyframe of the drive's "
        "evidence when the robot has driven this far (m) since the last one "
        "(:mod:`service.core.evidence`).",
    )
    evidence_turn: float = Field(
        0.3, gt=0, description="... or turned this far (rad) since the last keyframe."
    )
    evidence_span: float = Field(
        6.0,
        gt=0,
        description="The evidence window: keyframes within this travel (m) of the newest.",
    )
    evidence_frames: int = Field(20, ge=1, description="At most this many keyframes.")
    evidence_min_frames: int = Field(
        5,
        ge=1,
        description="Evidence rule: a hypothesis scored on at least this many keyframes "
        "(and every distinct alternative on as many of the same), spanning drive_travel "
        "metres, whose mean cost over the window is at most drive_max_cost and lower than "
        "every distinct alternative's on the same keyframes by drive_margin, wins (after its "
        "self-similarity check and the tracker's confirmation) even where no single scan's "
        "cost meets max_fix_cost: a real laser in a furnished building rarely verifies as "
        "well as a simulated one, but the true place stays the best explanation of the drive.",
    )
    evidence_share: float = Field(
        0.2,
        gt=0,
        le=1,
        description="With a budget, at most this share of it scores the hypotheses on the "
        "keyframes they lack (after the re-scoring; the search gets the rest).",
    )
    evidence_clip: float = Field(
        1.0,
        gt=0,
        description="A keyframe's cost counts at most this much (one bad keyframe, e.g. a "
        "person in front of the laser, must not outweigh the rest of the drive).",
    )
    evidence_short_scale: float = Field(
        0.0,
        ge=0,
        description="On the drive's keyframes a return short of the predicted wall counts "
        "exp(-(predicted - measured) / this) of short_credit (m; 0: all of it). Furniture "
        "stands just in front of the walls of its room; a place that puts the walls far "
        "behind the same returns explains them by nothing, and with the flat credit scored "
        "as well as the true place (tuning log fr079's east hall, floor plan: offices 8.2 m "
        "apart within 0.003-0.011 over 20 keyframes). Schematic: 1.0 (2.0 measured alike).",
    )
    evidence_drop: float = Field(
        0.3,
        gt=0,
        description="A hypothesis whose mean over at least evidence_drop_frames keyframes is "
        "worse than the best fully scored one's by this much is not scored further, and "
        "pruned.",
    )
    evidence_drop_frames: int = Field(3, ge=1, description="See evidence_drop.")
    evidence_junk: float = Field(
        0.95,
        gt=0,
        description="A hypothesis whose mean over at least evidence_drop_frames keyframes is "
        "at least this explains nearly nothing of the drive: it is not scored further, and "
        "pruned (its scoring would take the search's budget).",
    )
    refound_margin: float = Field(
        0.0,
        ge=0,
        description="Opt-in (0 = off; 0.1 measured on floor plans). A kept hypothesis that a "
        "later search finds again at a pose more than refound_offset m or refound_turn rad "
        "from its own takes the search's pose if that pose costs this much less on the "
        "newest keyframe the hypothesis was scored on; its keyframe scores are then redone "
        "from the new pose. Without it the search's refined pose is dropped and the "
        "hypothesis stays where the re-scoring's narrow polish (+-0.13 m) holds it: on "
        "building 65 (not tuned on when this was found) the true place's hypothesis sat 0.18 m "
        "off for 40 scans and a congruent room 4.6 m away was fixed and tracked to the end. "
        "At 0.1 the generated buildings' floor plans gain fixes and lose wrong ones "
        "(buildings 60-99: 796 -> 799 of 800 within 15 m, 2 -> 1 wrong), but it helps a "
        "wrong place as much as the true one: on the tuning log intel (start 3636) a wrong "
        "place 24 m off, re-found at a better pose, won the drive by 0.16 (0.11 before) and "
        "was fixed. Off by default.",
    )
    refound_offset: float = Field(0.05, gt=0, description="See refound_margin.")
    refound_turn: float = Field(0.02, gt=0, description="See refound_margin.")
    probation_rejects: int = Field(
        3,
        ge=1,
        description="A probation also fails once the tracker has rejected this many of its "
        "scans (in a row or not): on a floor plan the tracker keeps a wrong place through "
        "scans that fit it half-way, rejecting most but accepting some.",
    )
    fix_min_found: int = Field(
        1,
        ge=1,
        description="With a budget, a winner away from a lost track is fixed only once this "
        "many of the searches have found it (the one it came from and later ones): one search "
        "can miss the true place, and a lone alias then wins every rule unopposed (tuning "
        "building 9, floor plan, 50 ms: the only search finished in 2.6 m of driving had "
        "not found the true place; its best alias won the evidence rule with no alternative "
        "left). Schematic: 2. Metric: 1 (an exact map's costs leave an alias no such lead).",
    )
    probation_travel: float = Field(
        0.0,
        ge=0,
        description="With odometry, a search's winner (not one recovered next to the lost "
        "track) is first tracked for this much travel (m) while the published status stays "
        "initializing / lost; where tracking would have ended (the tracker loses the scan, "
        "or lost_after unfit scans in a row), after probation_rejects rejected scans, or on a "
        "scan without odometry the probation fails and the search goes on with the "
        "hypotheses it held, the winner among them without its wins "
        "(:meth:`service.core.drive_search.DriveSearch._probation_step`). Schematic: 2.0 -- a "
        "floor plan that leaves out walls the laser sees can make a wrong place explain the "
        "scans better than the true one for a metre or more, and no rule on the scans or the "
        "drive's keyframes can tell (the true place is the worse fit all along): only the "
        "tracker losing the wrong place does. Tuning logs: fr079 start 3540, a place 2.6 m "
        "away, lost 0.8 m after its fix; fr079 3692, an alias 14 m away turned 180 degrees "
        "(scan cost 0.22 against the true place's 0.41, drive 0.43 against 0.46), lost on the "
        "scan after a 1-m probation; intel 12318, a place 4.6 m away (0.12-0.20 against the "
        "true pose's 0.32-0.37; the true place was never a hypothesis), lost 0.7 m after a 1-m "
        "probation. Metric maps: 0 (an exact map has no such stretch).",
    )
    probation_slide: float = Field(
        0.15,
        ge=0,
        description="During a probation the odometry is the reference: the confirmed pose "
        "moved by the odometry since (dead-reckoned; over the probation's 2 m the checked "
        "odometry is good to a few cm). A tracked pose farther than this (m) from it that "
        "lets probation_slide_violation more of the checked beams through map walls than it "
        "does has slid along furniture or a double wall: the tracker is put back on the "
        "dead-reckoned pose, and the probation goes on from there (0 = off; "
        ":meth:`service.core.drive_search.DriveSearch._slide_check`). Tuning log fr079, floor "
        "plan, start 4361: the tracker slid 0.34 m from the dead-reckoned pose into 24 % of "
        "beams through walls (dead-reckoned 8 %) and was published 0.52 m off; on the tuning "
        "trials a correct probation's tracked pose never let more than 3.3 % more beams "
        "through walls than the dead-reckoned one on the real logs, up to 20 % on generated "
        "buildings, where putting it back changed no fix.",
    )
    probation_slide_violation: float = Field(
        0.1,
        ge=0,
        le=1,
        description="See probation_slide: the excess share of beams through walls.",
    )
    probation_relock: float = Field(
        0.0,
        ge=0,
        description="A probation whose scans the tracker rejected probation_rejects times or "
        "more (held through them, probation_hold_violation) passes only after the tracker has "
        "accepted every scan of the last this many metres of odometry travel: while it "
        "rejected the scans it followed the odometry alone, which can be wrong (the tuning "
        "log fr079 counts forward while the robot backs up), and a single accepted scan "
        "after that does not show the tracker has the place again. 0 = off, the default: "
        "the case that showed it (tuning log fr079 fed every 3rd scan, start 1174, 1.29 m "
        "off) came with a search setting not kept, and at 0.5 m it delayed 23 of 880 "
        "tuning fixes by 0.2-2.2 m without changing a first fix.",
    )
    probation_hold_violation: float = Field(
        0.1,
        ge=0,
        le=1,
        description="A probation whose winner was fixed by the evidence rule (drive_margin "
        "over every distinct alternative on the drive's keyframes) is not failed by the "
        "tracker's rejections (probation_rejects, or lost_after unfit scans in a row) while "
        "the evidence, kept up on the probation's own keyframes, still names it (no distinct "
        "alternative has caught up: a margin above 0, a hysteresis on the margin it won by) "
        "and the scan at the tracked pose lets at most this share of the checked beams through "
        "the map's walls. A rejection there means the map explains little of the scan, not "
        "that another place explains it better: in the east hall of the tuning log fr079 the "
        "floor plan shows the outline only, and 13 probations at the true place (0.01-0.2 m "
        "off) failed on 3 rejected scans, with 0.00-0.04 of the beams through walls. Wrong "
        "winners the tracker's rejections caught in the tuning trials either lost the "
        "evidence (intel 7771, 20 m off) or were fixed by the single-scan bars, except one: "
        "an alias 2.8 m along fr079's corridor won the evidence with the true place not "
        "among the hypotheses, and its rejected scans let 0.24-0.43 of the beams through "
        "walls. 0 = never held.",
    )
    confirm_drive_prior: bool = Field(
        False,
        description="A winner of the evidence rule (drive_margin) whose confirming scan, "
        "fitted alone (the weak prior of a fresh reset), lands beyond confirm_distance / "
        "confirm_angle or is rejected, is confirmed again as if the tracker had been "
        "following it: the scan's prior is the winner's pose with the odometry's per-scan "
        "sigma floors (MotionConfig.sigma_xy_floor, sigma_theta_floor). The drive has "
        "followed the winner scan by scan (polished on its keyframes, moved by the "
        "odometry in between), as the tracker follows its own pose. Unless the scan alone "
        "explained itself clearly better (confirm_unexplained): the place it pointed to "
        "joins the hypotheses for the drive's evidence to judge, and nothing is fixed on "
        "this scan. Tuning log fr079, floor plan, east hall (a third of the scan on the "
        "plan): the evidence rule named the true place (0.01-0.2 m off) 7.7 m into start "
        "4371 and 14.6 m into 4267, and every fit-alone confirmation of the next 2-3 m "
        "failed (the scan swung the pose 0.2-0.5 m / up to 70 degrees, or was rejected) "
        "while a tracker running there holds it within 0.15 m. Schematic: on (a probation "
        "follows every such fix); metric maps: off.",
    )
    confirm_unexplained: float = Field(
        0.5,
        gt=0,
        le=1,
        description="See confirm_drive_prior: the fit under the winner's prior is refused "
        "when the scan fitted alone (with min_support) leaves at most this share of what "
        "the held fit leaves unexplained (1 - support): the scan then contradicts the "
        "winner's pose, not only its clutter. Every held confirmation in the 360 trials "
        "of six tuning sets (fr079 and intel, 45-55 ms, every 1st / 3rd / 4th scan): 12 "
        "held fits, all at the true place, ratios 0.61-1.0 (0.80-1.0 in fr079's east hall, "
        "where furniture the plan lacks leaves two thirds of the scan unexplained at any "
        "pose; 0.61 at intel 12145); one refused, 0.29: a winner 1.37 m along intel's "
        "corridor from the true place (start 8329, every 4th scan: support 0.91 alone, 0.69 "
        "held; fixed 0.86 m off without this bar).",
    )
    probation_verdict: bool = Field(
        False,
        description="The probation of a winner of the single-scan rules keeps up the drive's "
        "evidence too (an evidence-rule winner's always does, probation_hold_violation), and "
        "fails when its travel is done if a distinct alternative then explains the drive's "
        "keyframes better (evidence_drop_frames of them in common); the search goes on "
        "(:meth:`service.core.drive_search.DriveSearch._probation_step`). Such a winner "
        "only had to be not beaten on the drive when it was confirmed, and may lead by a "
        "hair: the 2 m of keyframes the probation adds are what can tell it from the true "
        "place. Tuning logs, floor plan, 45 ms budget: fr079 2871 (a place 18 m off, "
        "probation passed without a rejected scan) and intel 12318 (3.5 m / 80 degrees off, "
        "leading by 0.02 when confirmed) were published wrong; both are beaten at the "
        "probation's end and fixed at the true place 2-3 m later. Not for a winner of the "
        "evidence rule's window mean: its 6 m window slides during the probation past what "
        "told it apart (fr079 fed every 3rd scan, starts 1174 and 1201: the true place won "
        "by 0.18, and an alias 31 m away that fits the corridor's scans better beat it at "
        "the probation's end); but for one of the newest keyframes (drive_recent_frames), "
        "whose deciding keyframes stay in the window (tuning building 1, start 13: a place "
        "15 m off won so, and 2 m later the true place explained the window better by "
        "0.16). Schematic: on. Metric maps have no probation.",
    )
    probation_verdict_margin: float = Field(
        0.0,
        ge=0,
        description="probation_verdict: the winner fails unless it explains the drive's "
        "keyframes better than every distinct alternative by this much (0: only an "
        "alternative that explains them better fails it). A cluttered building "
        "(tuning building 1 at clutter 0.25, start 12, bench_global --clutter 0.25): a "
        "single-scan winner 11.6 m off passed, leading the true place by 0.02 on the 20 "
        "keyframes. Schematic: 0.05.",
    )
    rescore_keep_moved: bool = Field(
        False,
        description="With odometry, the re-scoring verifies a kept hypothesis both where the "
        "odometry moved it and where the distance-field polish took it, and keeps the pose "
        "with the lower cost (one more verification per hypothesis and scan, counted in the "
        "budget). On a floor plan furniture returns pull the polish off the walls: generated "
        "tuning building 46, a hypothesis at the exact pose was polished 0.07-0.17 m away at "
        "up to twice the cost; its keyframes then scored 0.2-0.3 worse than a congruent room "
        "8 m away, which won (3 wrong first fixes at 50 ms). Off by default: on the 800 "
        "drives of buildings 20-59 at 50 ms it fixed those 3 and brought 2 others, one of "
        "them a place 2.7 m off tracked to the end.",
    )
    probation_reversal: bool = Field(
        False,
        description="A winner of the evidence rule's window mean (drive_margin), which the "
        "verdict does not judge, fails at its probation's end if the drive has turned against "
        "it: a distinct alternative explains the newest drive_recent_frames keyframes better "
        "by drive_recent_margin (the bar of the rule's second way) and the window at least as "
        "well (:func:`service.core.evidence.overturned`); the search goes on. Generated "
        "buildings 20-59 (tuning, floor plans, 45 ms): places 13 m off (turned 90 degrees) "
        "and 7 m off (turned 180) won by 0.16 and passed although by the probation's end the "
        "true place explained the window as well or better. Schematic: on.",
    )
    probation_contest_all: bool = Field(
        False,
        description="A winner of the evidence rule's window mean gets what a single-scan "
        "winner's probation has: the probation_searches, whose places join the hypotheses, and "
        "probation_verdict at its end. Without it a place the searches had not found before "
        "the window named a winner cannot contest it: generated building 65 (tuning, floor "
        "plan, 50 ms, start 29), a congruent room 4.6 m off won the window by 0.18 at 1.7 m "
        "of travel, the true place never among the hypotheses, and passed its probation; "
        "with it a probation search finds the true place, which beats the room, and it is "
        "fixed at 9.6 m. Schematic: on.",
    )
    verdict_refine: bool = Field(
        False,
        description="Before a verdict on the drive's keyframes -- the evidence rule naming a "
        "winner, and probation_verdict judging a single-scan winner at its probation's end "
        "-- the winner and its closest distinct rivals (verdict_refine_tracks) are each "
        "moved as one rigid body, all of its keyframe poses together, to where the drive's "
        "beams fit it best (:mod:`service.core.window_refine`). A hypothesis' keyframe poses "
        "were polished on the distance field, which on a floor plan can settle off the "
        "place (furniture returns by the walls pull it, a corridor's axis is free), and a "
        "hypothesis held 0.15-0.2 m off its place scores like a wrong place: tuning "
        "building 62, start 29: the true place 0.17 m off at 0.750 against 0.598 for a place "
        "15 m off, which the rule named (0.398 against 0.562 refined); tuning building 65, "
        "start 17, and held-out building 1001, start 17: congruent rooms passed the "
        "probation verdict (1001: 0.357 against 0.284; 0.13 at the true pose). The rule "
        "waits for the refinement, which takes the search's share of the budget; a "
        "probation goes on until it is done. Schematic: on.",
    )
    verdict_refine_tracks: int = Field(
        3,
        ge=0,
        description="See verdict_refine: at most this many alternatives, the closest to the "
        "winner on the drive's keyframes (within evidence_drop of its mean).",
    )
    probation_searches: int = Field(
        0,
        ge=0,
        description="Searches that go on during the probation of a winner of the single-scan "
        "rules (0: none), each within the budget the tracker and the drive's evidence leave; "
        "the places they find join the hypotheses, are scored on the drive's keyframes and "
        "can beat the winner at the probation's end (probation_verdict). Without them a place "
        "not found before the probation cannot contest it: tuning log intel 7147 (floor "
        "plan, 55 ms, evidence_short_scale 1 m), a place 10 m off passed, ahead of the 8 "
        "other hypotheses by 0.17 or more, the true place not among them; one search fixes "
        "it at the true place. Searching all the probation long did the same and put the "
        "floor plans' CPU to a fix (p50) from 0.41-0.88 s to 1.06-1.29 s. Schematic: 1.",
    )
    window_polish: bool = Field(
        False,
        description="A winner of the evidence rule is polished on the points of every keyframe "
        "of the window at once, placed by the odometry (:func:`service.core.evidence."
        "window_polish`), before the tracker confirms it: one scan leaves a pose free along "
        "a corridor that metres of driving and turns pin down. Tuning log intel 8414 (floor "
        "plan, 45 ms, evidence_short_scale 1 m): the rule named a track 0.23-0.28 m and 5 "
        "degrees off, and the probation published it 0.50 m off. Schematic: on.",
    )
    drive_travel: float = Field(
        1.0, ge=0, description="Evidence rule: the window spans at least this travel (m)."
    )
    drive_margin: float = Field(
        0.15, gt=0, description="Evidence rule: the margin over every alternative."
    )
    drive_recent_frames: int = Field(
        0,
        ge=0,
        description="Evidence rule, second way to win (0: off): the leader over the whole "
        "window also wins if it explains the newest this many keyframes better than every "
        "distinct alternative, each scored on all of them, by drive_recent_margin (the cost "
        "bars on the whole window still apply). A window-wide mean lags what tells two "
        "places apart by the window's length: on the tuning log fr079 (floor plan, east "
        "hall, starts 4109 and 4112) congruent offices 8.2 m apart tied within 0.011 over "
        "20 keyframes until the robot left them at ~10 m, and the mean reached the margin "
        "only at 13.7-14 m. Longer windows (10 m / 40 keyframes, or 40 keyframes) lost "
        "three tuning starts there; this fixed four more. Schematic: 8.",
    )
    drive_recent_margin: float = Field(
        0.18,
        gt=0,
        description="See drive_recent_frames: fewer keyframes, so a higher bar than "
        "drive_margin (chosen on replays of the tuning sets' rule evaluations: 0.18 over 8 "
        "named one wrong leader more than the rule alone, which the confirmation and the "
        "probation then caught).",
    )
    drive_recent_tie: float = Field(
        0.05,
        ge=0,
        description="See drive_recent_frames: no distinct alternative may explain the "
        "window's older keyframes better than the leader by more than this (the newest "
        "keyframes settle a tie, they do not overrule the older ones; "
        ":func:`service.core.evidence.recent_margin`).",
    )
    drive_max_cost: float = Field(
        0.85,
        gt=0,
        description="Evidence rule: the winner's mean and median cost over the window "
        "(keyframe costs clipped at evidence_clip). On the tuning log fr079's metric map, "
        "drawn from a cluttered office, the true place scored 0.74-0.88 over the window "
        "(before see_through) "
        "(the single scans of a 180-degree laser), the best alternatives 0.95-1.0: the "
        "margin, not this bar, tells them apart; the bar only refuses a leader that "
        "explains the drive no better than a wrong place does.",
    )
    settle_scans: int = Field(
        20,
        ge=0,
        description="After a fix by the search, the localiser counts as unsettled for this "
        "many tracked scans (``GlobalShapeLocalizer.unsettled``): a service keeps it on its "
        "search worker meanwhile.",
    )
    rescore_share: float = Field(
        0.3,
        gt=0,
        le=1,
        description="With a budget, at most this share of it re-scores the kept hypotheses "
        "on the scan (best first); then evidence_share scores them on the keyframes they "
        "lack, and the search gets the rest. 0.3 / 0.2 against 0.5 / 0.3 on the tuning "
        "split (worlds 0-19, floor plans, 200 drive starts): 96.0 against 93.0 % fixed "
        "within 15 m, no wrong fix in either (the search finds the true place sooner).",
    )
    twin_hold_kept: bool = Field(
        True,
        description="With a budget: once a track's self-similarity check has found a twin "
        "that is now kept among the hypotheses, the check is not run again while that twin "
        "stays kept; on each scan that re-scores both, the track passes as a check would "
        "when the twin trails it by the ambiguity bar. A repeated check searches the map "
        "for the twin the hypotheses already hold: on the office floor plan a leader was "
        "re-checked every 2 scans for the whole drive (32 checks in 103 scans, about half "
        "the search's CPU). The work goes to searches instead. Tuning split, floor plans: "
        "office CPU to the fix p50 -15 %, travel p90 7.7 -> 7.0 "
        "m; buildings 60-99 travel p90 6.5 -> 5.9 m, 799 -> 797 of 800 within 15 m (more "
        "searches find more aliases that tie the true place on single scans); no wrong fix.",
    )
    rescore_prior: float = Field(
        0.02,
        ge=0,
        description="With odometry, the re-scoring's polish of a kept hypothesis maximises its "
        "field score less this x ((offset / 0.1 m)^2 + (turn / 0.04 rad)^2) from the pose the "
        "odometry moved it to: the odometry is a motion prior there too. Without it a "
        "hypothesis in a corridor slid ~0.1 m per scan along the corridor's axis, wherever "
        "the plan matched a little better (tuning building 12: the true hypothesis led, "
        "drifted 2 m while its confirmation waited for a constraining view, and was then "
        "fixed 2.3 m off). 0 = none.",
    )
