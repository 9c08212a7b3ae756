"""The budgeted search over a drive (service/core/drive_search.py): a fix on the move within
the per-scan budget, deterministic; congruent rooms never fixed; the factory's budget; a robot
the search found unsettled for ``settle_scans`` scans; a pending twin check taking turns with
the search; the evidence rule naming the leader the newest keyframes tell apart. On generated
buildings and the office floor plan: true places winning over congruent rooms, a held twin not
searched for again, the evidence rule naming a winner once its rivals are placed where the
beams fit, a window winner contested by its probation's search; and a probation pickled before
it moved module still loading."""

from __future__ import annotations

import numpy as np

from service.core import evidence as ev
from service.core import global_search as gs
from service.core import hypotheses as hy
from service.core.factory import create_localizer
from service.core.global_config import GlobalConfig
from service.core.global_localization import GlobalShapeLocalizer
from service.core.laser_odometry import LaserOdometryLocalizer
from service.core.types import MapData, wrap_angle
from sim_publisher.laser import LaserSimulator
from sim_publisher.scenario import make_setup
from sim_publisher.trajectory import simulate_odometry
from tests.service.core.budgeted import _budgeted, _drive, _ok


def _building_drive(
    seed: int, first: int, last: int, update: dict
) -> list[tuple[int, float, float]]:
    """Generated building ``seed``'s floor plan (setup 2), scans ``first``..``last`` with
    odometry, no initial pose and a 50 ms search budget, the global configuration changed by
    ``update``: the tracking estimates' (scan, position error m, heading error deg)."""
    from sim_publisher.generator import BuildingParams, generate_building
    from sim_publisher.scenario import building_setup

    su = building_setup(generate_building(seed, BuildingParams(people=0)), 2, seed=0)
    loc = create_localizer("shape", su.map_data, None, search_budget_ms=50.0)
    loc.gconfig = loc.gconfig.model_copy(update=update)
    out = []
    for i in range(first, last + 1):
        est = loc.update(*su.scan(i), su.odom[i])
        if est.status == "tracking":
            err = float(np.hypot(*(est.pose[:2] - su.truth[i][:2])))
            turn = float(np.rad2deg(abs(wrap_angle(est.pose[2] - su.truth[i][2]))))
            out.append((i, err, turn))
    return out


def _correct(track: list[tuple[int, float, float]]) -> bool:
    return all(e < 0.5 and t < 10.0 for _i, e, t in track)


def test_a_true_place_held_off_its_pose_still_wins_over_the_congruent_room() -> None:
    """Building 65's floor plan from scan 17: a congruent room 4.6 m west explains the drive
    about as well as the true place, whose hypothesis can be induced 0.17 m off and kept
    there by the re-scoring's narrow polish. Two mechanisms move such a hypothesis onto the
    place its beams fit: the verdict's refinement (``verdict_refine``, on for floor plans) and
    ``refound_margin`` (opt-in; the hypothesis takes the pose a later search found it at).
    With either alone, and with the defaults, the drive is fixed and every tracking estimate
    is the true place; with neither, nothing wrong is ever published.

    Which scan the fix comes on depends on the last bits of the search's arithmetic, so the
    test asserts outcomes and invariants, not one trajectory."""
    off = {"twin_hold_kept": False, "shortlist_violation_beams": 0, "probation_contest_all": False}
    for update in (
        {},
        {**off, "refound_margin": 0.0, "verdict_refine": True},
        {**off, "refound_margin": 0.1, "verdict_refine": False},
    ):
        fixed = _building_drive(65, 17, 124, update)
        assert fixed, ("never fixed", update)
        assert _correct(fixed), (update, fixed[:3])
    neither = _building_drive(65, 17, 124, {**off, "refound_margin": 0.0, "verdict_refine": False})
    assert _correct(neither), neither[:3]


def test_the_evidence_rule_names_a_winner_after_its_rivals_are_placed_where_the_beams_fit() -> None:
    """Building 62's floor plan from scan 29: a place 15 m off (turned 180 degrees) can lead
    the drive's keyframes while the true place's hypothesis sits 0.17 m off its pose. With
    ``verdict_refine`` the rule waits for the refinement of the leader and its closest rivals
    before naming a winner. With and without the refinement, and with the defaults, the drive
    is fixed at the true place before the tour ends (scan 240) and stays there."""
    off = {"twin_hold_kept": False, "shortlist_violation_beams": 0}
    for update in ({}, {**off, "verdict_refine": True}, {**off, "verdict_refine": False}):
        fixed = _building_drive(62, 29, 240, update)
        assert fixed, ("never fixed", update)
        assert _correct(fixed), (update, fixed[:3])


def test_a_probation_pickled_before_it_moved_module_still_loads() -> None:
    """Localiser states saved before probation had its module name
    ``service.core.drive_search.Probation``;
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
    """Building 65's floor plan from scan 29: the drive's window can name a congruent room
    4.6 m off at 1.7 m of travel while the true place has never been among the hypotheses.
    With ``probation_contest_all`` (the default) a window winner's probation searches as a
    single-scan winner's does, so the true place can join and beat the room on the drive's
    keyframes. With it (default) and without it, the drive is fixed at the true place."""
    loc = create_localizer("shape", make_setup(2).map_data, None, search_budget_ms=50.0)
    assert loc.gconfig.probation_contest_all
    for update in ({}, {"probation_contest_all": False}):
        fixed = _building_drive(65, 29, 159, update)
        assert fixed, ("never fixed", update)
        assert _correct(fixed), (update, fixed[:3])


def test_budgeted_search_fixes_on_the_move_within_the_budget() -> None:
    """Floor plan, a start in the corridor, odometry: no searching scan works much beyond the
    budget (one step at most), the hypotheses are published while initializing, and the fix
    comes on the move, correct."""
    su = make_setup(2)
    budget = 25.0
    loc = _budgeted(su.map_data, budget)
    run = _drive(loc, su, 250, 90)
    i, last, _ = run[-1]
    assert last.status == "tracking", f"no fix in {len(run)} scans"
    assert _ok(last.pose, su.truth[i])
    searching = [(j, e, w) for j, e, w in run if e.status != "tracking"]
    assert len(searching) >= 5  # a floor-plan search does not fit in one scan's budget
    assert max(w for _j, _e, w in searching) <= budget + 15.0
    assert all(e.status == "initializing" for _j, e, _w in searching)
    later = [e for _j, e, _w in searching if e.hypotheses]
    assert later, "no hypotheses reported"
    for e in later:
        assert e.candidates is not None and e.candidates.shape[1] == 4
        assert 1 <= len(e.candidates) <= e.hypotheses
        assert np.all(np.diff(e.candidates[:, 3]) >= 0)  # best first


def test_budgeted_search_is_deterministic() -> None:
    su = make_setup(1, max_scans=2100)
    poses = []
    for _ in range(2):
        loc = _budgeted(su.map_data, 25.0)
        poses.append(np.array([e.pose for _i, e, _w in _drive(loc, su, 2000, 40)]))
    assert poses[0].shape == poses[1].shape
    np.testing.assert_array_equal(poses[0], poses[1])


def _twin_rooms(scans: int) -> tuple[MapData, LaserSimulator, np.ndarray, np.ndarray]:
    """Two congruent rooms 7 m apart, and a robot creeping and turning in the first: the
    map, its laser, the true poses and their odometry."""
    room = np.array([[0, 0], [5, 0], [5, 2], [3, 2], [3, 3.5], [0, 3.5], [0, 0]], dtype=float)
    md = MapData.from_lists("twins", "metric", [room, room + np.array([7.0, 0.0])])
    laser = LaserSimulator(md.segments(), seed=8)
    truth = np.array([[1.2 + 0.02 * s, 1.0, wrap_angle(0.3 + s * 0.5)] for s in range(scans)])
    return md, laser, truth, simulate_odometry(truth, seed=9)


def test_congruent_rooms_never_fix_with_a_budget() -> None:
    md, laser, truth, odom = _twin_rooms(30)
    loc = _budgeted(md, 25.0)
    seen = 0
    for s in range(len(truth)):
        r, a = laser.scan(truth[s], s)
        est = loc.update(r, a, odom[s])
        assert est.status == "initializing", f"scan {s}: {est.status} at {est.pose}"
        seen = max(seen, est.hypotheses or 0)
    assert seen >= 2  # both rooms are held as hypotheses


def test_the_factory_passes_the_budget_to_the_global_search() -> None:
    su = make_setup(1, max_scans=2)
    loc = create_localizer("shape", su.map_data, None, search_budget_ms=12.5)
    assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
    assert isinstance(loc.inner, GlobalShapeLocalizer)
    assert loc.gconfig.search_budget_ms == 12.5
    assert create_localizer("shape", su.map_data, None).gconfig.search_budget_ms is None


def test_a_fixed_robot_stays_unsettled_for_settle_scans() -> None:
    """A robot configured with a pose is settled at once; one found by the search counts as
    unsettled (the service keeps it on its search worker) until it has tracked settle_scans
    scans."""
    su = make_setup(1, max_scans=2100)
    assert not create_localizer("shape", su.map_data, su.truth[0]).unsettled
    loc = _budgeted(su.map_data, 25.0)
    assert loc.unsettled
    run = _drive(loc, su, 2000, 60)
    i, est, _w = run[-1]
    assert est.status == "tracking" and loc.unsettled
    n = loc.gconfig.settle_scans
    for k in range(i + 1, i + 1 + n):
        assert loc.unsettled, k
        loc.update(*su.scan(k), su.odom[k])
    assert not loc.unsettled


def test_a_pending_twin_check_and_the_search_take_turns(monkeypatch) -> None:
    """While the self-similarity check of a leader only one search has found is pending, the
    search still advances every other scan: the check must not stop the search that may find
    a better place."""
    md, laser, truth, odom = _twin_rooms(40)
    # 10 ms: at 25 the work model of 2026-11-25 (which counts this machine's CPU; a floor
    # plan's search costs ~1/3 of the model before it) finishes the check in two scans
    loc = _budgeted(md, 10.0)
    calls: list[str] = []
    real = hy.advance

    def spy(job: hy.Job, spent: float, budget: float) -> tuple[float, bool, object]:
        calls.append("twin" if job.track is not None else "search")
        return real(job, spent, budget)

    monkeypatch.setattr(hy, "advance", spy)
    turns = []
    for s in range(len(truth)):
        job = loc._twin_job
        pending = job is not None and job.track is not None and job.track.found < 2
        calls.clear()
        loc.update(*laser.scan(truth[s], s), odom[s])
        if pending:
            turns.append(set(calls))
    assert len(turns) >= 6, "no twin check was pending long enough to test"
    assert sum("search" in t for t in turns) >= len(turns) // 2 - 1
    assert sum("twin" in t for t in turns) >= len(turns) // 2 - 1


def test_the_evidence_rule_also_names_the_leader_that_the_newest_keyframes_tell_apart() -> None:
    """Two congruent places tie on most of the window; once the robot drives out of the
    congruent part the newest keyframes tell them apart, which the window's mean shows only
    a window later (fr079's east hall). The leader over the whole window wins if it beats
    every distinct alternative by ``drive_recent_margin`` on the newest
    ``drive_recent_frames`` keyframes, each alternative scored on all of them; the cost bars
    on the whole window still apply."""
    su = make_setup(2)
    g = GlobalConfig.for_kind("schematic")
    assert (g.drive_recent_frames, g.drive_recent_margin, g.drive_margin) == (8, 0.18, 0.15)
    frames = [
        ev.Keyframe(k, np.ones(3), np.zeros(3), np.ones((3, 2)), np.zeros(3), 0.3 * k)
        for k in range(20)
    ]

    def won(  # type: ignore[no-untyped-def]
        gaps_recent: float,
        cfg: GlobalConfig,
        lead_cost: float = 0.5,
        scored=range(20),
        older_gap: float = 0.005,
    ):
        tracks = []
        for x in (0.0, 8.2):
            pose = np.array([x, 0.0, 0.0])
            t = hy.Track(pose, [lead_cost], gs.Hypothesis(pose=pose.copy(), cost=lead_cost))
            t.ev = {k: lead_cost + (older_gap if x else 0.0) for k in range(12)}  # a tie
            t.ev.update({k: lead_cost + (gaps_recent if x else 0.0) for k in range(12, 20)})
            tracks.append(t)
        tracks[1].ev = {k: v for k, v in tracks[1].ev.items() if k in scored}
        loc = GlobalShapeLocalizer(su.map_data, None, gconfig=cfg)
        loc._frames, loc._tracks = frames, tracks
        extras: dict[str, float] = {}
        out = loc._evidence_won(tracks[0], extras)
        assert extras["drive_margin"] < g.drive_margin  # the window's mean alone: no win
        assert ("drive_recent" in extras) == out  # its probation ends with a verdict
        return out

    assert won(0.25, g)  # 0.25 on the newest 8: the mean over 20 is only ~0.10
    assert not won(0.25, g, older_gap=-0.1)  # the older keyframes named the alternative
    assert won(0.25, g, older_gap=-0.04)  # ... a tie within drive_recent_tie (0.05)
    assert not won(0.15, g)  # below drive_recent_margin
    assert not won(0.25, g.model_copy(update={"drive_recent_frames": 0}))  # off: as before
    assert not won(0.25, g, lead_cost=0.9)  # explains the drive too poorly
    assert not won(0.25, g, scored=range(19))  # the alternative lacks the newest keyframe
