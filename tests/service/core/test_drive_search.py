"""The budgeted search over a drive (service/core/drive_search.py) on a generated building."""

from __future__ import annotations

import numpy as np

from service.core.factory import create_localizer
from service.core.types import wrap_angle


def test_a_true_place_held_off_its_pose_still_wins_over_the_congruent_room() -> None:
    """Building 65's floor plan (setup 2; a building no run had seen before stop 41), from scan
    17 with no initial pose, odometry and a 50 ms search budget. The true place's hypothesis
    was induced 0.17 m off and the re-scoring's narrow polish kept it there; a congruent room
    4.6 m west then explained the drive better and was tracked to the end of the tour
    (measured: fixed on scan 59, 4.6 m off). Two mechanisms each prevent it: the verdict's
    refinement (``verdict_refine``, on for floor plans: at the probation's end the hypothesis
    is moved onto the place its keyframes' beams fit, the congruent room is beaten and the
    true place is fixed at 10.8 m), and ``refound_margin`` (opt-in) at 0.1, with which the
    hypothesis takes the pose a later search found it at (0.04 m off; fixed on scan 78).
    Checked with stop 43's twin checks (``twin_hold_kept`` off): with stop 44's the searches
    that re-checks took run instead, and the drive no longer reaches the congruent room even
    without either mechanism (measured: fixed on scan 69, 0.11 m off). And with the shortlist
    ranked by support alone (``shortlist_violation_beams`` 0, before stop 45): with stop 45's
    ranking the true place's search finds it sooner and neither mechanism is needed either
    (measured: fixed on scan 46, 0.11 m off); checked without stop 45's contested window
    winners too (``probation_contest_all``), which also end the wrong fix here."""
    from sim_publisher.generator import BuildingParams, generate_building
    from sim_publisher.scenario import building_setup

    su = building_setup(generate_building(65, BuildingParams(people=0)), 2, seed=0)

    def drive(margin: float, refine: bool) -> list[tuple[int, float, float]]:
        """The tracking estimates' (scan, position error m, heading error deg)."""
        loc = create_localizer("shape", su.map_data, None, search_budget_ms=50.0)
        assert loc.gconfig.verdict_refine
        update = {
            "refound_margin": margin,
            "verdict_refine": refine,
            "twin_hold_kept": False,
            "shortlist_violation_beams": 0,
            "probation_contest_all": False,
        }
        loc.gconfig = loc.gconfig.model_copy(update=update)
        out = []
        for i in range(17, 125):
            est = loc.update(*su.scan(i), su.odom[i])
            if est.status == "tracking":
                err = float(np.hypot(*(est.pose[:2] - su.truth[i][:2])))
                turn = float(np.rad2deg(abs(wrap_angle(est.pose[2] - su.truth[i][2]))))
                out.append((i, err, turn))
        return out

    for margin, refine in ((0.0, True), (0.1, False)):
        fixed = drive(margin, refine)
        assert fixed, ("never fixed", margin, refine)
        assert all(e < 0.5 and t < 10.0 for _i, e, t in fixed), (margin, refine, fixed[:3])
    neither = drive(0.0, False)
    assert neither and neither[0][1] > 4.0, neither[:3]  # the congruent room


def test_the_evidence_rule_names_a_winner_after_its_rivals_are_placed_where_the_beams_fit() -> None:
    """Building 62's floor plan (setup 2, tuning), from scan 29 with no initial pose, odometry
    and a 50 ms budget. On scan 91 the evidence rule named a place 15 m off (turned 180
    degrees; mean 0.598 over 20 keyframes) by 0.152 over the true place, whose hypothesis sat
    0.17 m off (0.750); the probation passed and it was published 18 m off. With
    ``verdict_refine`` the rule waits for the refinement of the leader and its closest rivals
    (scans 91-95): the true place then explains the drive at 0.398 against 0.562, and it is
    the one fixed (scan 117, 0.03 m). Checked with stop 43's twin checks (``twin_hold_kept``
    off): with stop 44's, more searches run and the drive is not fixed before scan 140 (traced
    from scan 30 of the same building: they find places 14-18 m off that tie the true place
    on single scans, 0.219 against 0.219 on scan 102, where stop 43's drive had none). And
    with the shortlist ranked by support alone (``shortlist_violation_beams`` 0): with stop
    45's ranking the true place is fixed without the refinement (measured: scan 92, 0.06 m)."""
    from sim_publisher.generator import BuildingParams, generate_building
    from sim_publisher.scenario import building_setup

    su = building_setup(generate_building(62, BuildingParams(people=0)), 2, seed=0)

    def first_fix(refine: bool) -> tuple[int, float]:
        loc = create_localizer("shape", su.map_data, None, search_budget_ms=50.0)
        update = {"verdict_refine": refine, "twin_hold_kept": False, "shortlist_violation_beams": 0}
        loc.gconfig = loc.gconfig.model_copy(update=update)
        refining = 0
        for i in range(29, 140):
            est = loc.update(*su.scan(i), su.odom[i])
            refining += "drive_refining" in est.extras
            if est.status == "tracking":
                assert (refining > 0) == refine
                return i, float(np.hypot(*(est.pose[:2] - su.truth[i][:2])))
        return -1, float("inf")

    scan, err = first_fix(True)
    assert scan > 0 and err < 0.5, (scan, err)
    scan, err = first_fix(False)
    assert err > 10.0, (scan, err)  # the place 15 m off


def test_a_probation_pickled_before_it_moved_module_still_loads() -> None:
    """Localiser states saved before stop 43 name ``service.core.drive_search.Probation``;
    that name still resolves to the class now in :mod:`service.core.probation`."""
    import pickle

    from service.core.probation import Probation

    assert pickle.loads(b"cservice.core.drive_search\nProbation\n.") is Probation


def test_a_held_twin_that_is_kept_is_not_searched_for_again() -> None:
    """The office floor plan (two congruent rooms), from scan 0 with no initial pose,
    odometry and a 50 ms budget. By default the true place's self-similarity check is run
    again every ~2 scans for the whole drive, each time re-finding the twin the hypotheses
    already hold (traced: 32 checks in 103 scans). With ``twin_hold_kept`` a check whose twin
    is kept is not run again while it stays kept: far fewer checks, the same correct fix."""
    from sim_publisher.scenario import make_setup

    su = make_setup(2)

    def drive(hold: bool) -> tuple[int, int, float]:
        """(checks started, scan of the first fix, its position error m)."""
        loc = create_localizer("shape", su.map_data, None, search_budget_ms=50.0)
        loc.gconfig = loc.gconfig.model_copy(update={"twin_hold_kept": hold})
        checks = 0
        for i in range(0, 150):
            job = loc._twin_job
            est = loc.update(*su.scan(i), su.odom[i])
            checks += loc._twin_job is not None and loc._twin_job is not job
            if est.status == "tracking":
                return checks, i, float(np.hypot(*(est.pose[:2] - su.truth[i][:2])))
        return checks, -1, float("inf")

    plain, held = drive(False), drive(True)
    assert plain[1] > 0 and plain[2] < 0.5, plain
    assert held[1] > 0 and held[2] < 0.5, held
    assert held[0] * 3 <= plain[0], (held, plain)


def test_a_window_winner_is_contested_by_a_place_its_probation_search_finds() -> None:
    """Building 65's floor plan (setup 2, tuning), from scan 29 with no initial pose,
    odometry and a 50 ms budget. The drive's window named a congruent room 4.6 m off by 0.18
    at 1.7 m of travel, while the true place had never been among the hypotheses; a winner of
    the window's mean had no search and no verdict on its probation, so the room passed and
    was tracked to the end of the tour (measured). With ``probation_contest_all`` its
    probation searches as a single-scan winner's does, the true place joins, beats the room
    on the drive's keyframes, and is the one fixed (measured: scan 121, 0.06 m)."""
    from sim_publisher.generator import BuildingParams, generate_building
    from sim_publisher.scenario import building_setup

    su = building_setup(generate_building(65, BuildingParams(people=0)), 2, seed=0)

    def first_fix(contest: bool) -> tuple[int, float]:
        loc = create_localizer("shape", su.map_data, None, search_budget_ms=50.0)
        assert loc.gconfig.probation_contest_all
        loc.gconfig = loc.gconfig.model_copy(update={"probation_contest_all": contest})
        for i in range(29, 160):
            est = loc.update(*su.scan(i), su.odom[i])
            if est.status == "tracking":
                return i, float(np.hypot(*(est.pose[:2] - su.truth[i][:2])))
        return -1, float("inf")

    scan, err = first_fix(True)
    assert scan > 0 and err < 0.5, (scan, err)
    scan, err = first_fix(False)
    assert 4.0 < err < 5.5, (scan, err)  # the congruent room
