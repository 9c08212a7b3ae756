"""Global localisation: viewpoints, the view index, global search on the office maps,
ambiguity on a symmetric room, the kidnapped robot and dead reckoning (in process)."""

from __future__ import annotations

import numpy as np
import pytest

from service.core import kernels
from service.core.factory import create_localizer
from service.core.reloc import global_localization as gl
from service.core.reloc import states as st
from service.core.reloc import view_index as vi
from service.core.reloc.global_search import run_steps, search_steps, self_similar_steps, verify
from service.core.shapes.configuration import scan_configuration
from service.core.types import MapData, wrap_angle
from sim_publisher.laser import LaserSimulator
from sim_publisher.office import office_metric_map, office_schematic_map, office_world
from sim_publisher.publisher import SimFleet, fleet_specs, random_free_poses
from sim_publisher.scenario import make_setup
from sim_publisher.trajectory import simulate_odometry


def _ring(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]], dtype=float)


def _room_map(map_id: str = "room", box_at: float = 1.5) -> MapData:
    """A 6 x 4 m room with a 0.8 m box and an L-shaped alcove wall (not symmetric)."""
    walls = np.array([[0, 0], [6, 0], [6, 4], [2.5, 4], [2.5, 3.2], [0, 3.2], [0, 0]], float)
    return MapData.from_lists(
        map_id, "metric", [walls, _ring(box_at, 1.0, box_at + 0.8, 1.8), _ring(4, 2, 4.3, 2.3)]
    )


def _found(pose: np.ndarray, truth: np.ndarray) -> bool:
    return bool(
        np.hypot(*(pose[:2] - truth[:2])) < 0.5
        and abs(wrap_angle(float(pose[2] - truth[2]))) < np.deg2rad(10.0)
    )


# ------------------------------------------------------------------------- viewpoints


def test_viewpoints_office_metric_in_free_space_and_not_in_furniture() -> None:
    md = office_metric_map()
    vps = vi.candidate_viewpoints(md, 0.6, min_clearance=0.3)
    world = office_world()
    assert len(vps) > 300  # 276 m² of free space at 0.36 m² per cell, minus clearance
    clearance = world.clearance(vps)
    assert np.all(clearance > 0.29), "a viewpoint inside or next to an obstacle"
    furniture = [o.geometry for o in world.obstacles if o.kind != "wall"]
    assert furniture
    import shapely

    for geom in furniture:
        assert not np.any(shapely.contains_xy(geom, vps[:, 0], vps[:, 1]))


def test_viewpoints_small_map_enclosed_outside_box_and_alcove() -> None:
    md = _room_map()
    vps = vi.candidate_viewpoints(md, 0.25, min_clearance=0.2)
    assert len(vps) > 100
    # inside the room outline (no point outside the walls: the enclosure test)
    inside = (vps[:, 0] > 0) & (vps[:, 0] < 6) & (vps[:, 1] > 0) & (vps[:, 1] < 4)
    alcove = (vps[:, 0] < 2.5) & (vps[:, 1] > 3.2)
    assert np.all(inside & ~alcove)
    # none inside the small closed rings (the box, the pillar)
    in_box = (vps[:, 0] > 1.5) & (vps[:, 0] < 2.3) & (vps[:, 1] > 1.0) & (vps[:, 1] < 1.8)
    in_pillar = (vps[:, 0] > 4) & (vps[:, 0] < 4.3) & (vps[:, 1] > 2) & (vps[:, 1] < 2.3)
    assert not np.any(in_box | in_pillar)


# ------------------------------------------------------------------------- global search


def _global_trials(
    md: MapData,
    setup: int,
    n: int,
    seed: int,
    motion: str = "creep",
    laser_odometry: bool = False,
) -> tuple[int, int, int]:
    """``n`` random free-space poses, no initial pose, up to 3 scans. ``creep``: 3 cm forward
    per scan, no odometry (the paper's mode, or with ``laser_odometry`` the motion measured
    between the scans as odometry); ``look-around``: 90 degrees in place per scan with (noisy)
    odometry, which the localiser fuses into one 360-degree composite. Returns (found within
    3 scans, confident wrong poses, trials)."""
    su = make_setup(setup, max_scans=2)
    world = office_world()
    found = wrong = 0
    for k, start in enumerate(random_free_poses(world, n, seed)):
        if motion == "look-around":
            truth = np.array([[start[0], start[1], start[2] + s * np.pi / 2] for s in range(3)])
            truth[:, 2] = wrap_angle(truth[:, 2])
            odom: np.ndarray | None = simulate_odometry(truth, seed=1000 + k)
        else:
            step = np.array([0.03 * np.cos(start[2]), 0.03 * np.sin(start[2]), 0.0])
            truth = np.array([start + s * step for s in range(3)])
            odom = None
        loc = create_localizer("shape", md, None, laser_odometry=laser_odometry)
        for s in range(3):
            p = truth[s]
            r, a = su.laser.scan(p, 1000 * k + s)
            est = loc.update(r, a, None if odom is None else odom[s])
            # a floor plan's winner is tracked on probation (GlobalConfig.probation_travel)
            # before it is published: turning in place, it never is; the winner is judged
            if est.status == "tracking" or "probation" in est.extras:
                if _found(est.pose, p):
                    found += 1
                else:
                    wrong += 1
                break
            assert est.status == "initializing"
            assert est.ambiguity is not None and 0.0 <= est.ambiguity <= 1.0
        if md.kind == "schematic" and odom is not None:
            assert est.status != "tracking", "published without the probation's travel"
    return found, wrong, n


#: Of these 20 starts, 3 creeping scans (6 cm) tell 13 apart from every other place by the
#: odds a fix takes on a metric map (GlobalConfig.fix_llr 25, from the false-fix rate of 80
#: tuning drives on intel and fr079: a corridor's twin led at 15 nats); with the scans' own
#: motion as odometry none (test_global_search_with_laser_odometry_fixes_no_robot_wrongly).
#: The rest are not fixed (none wrongly): at 2 another room explains the scan
#: within 0.012 of beam cost, at others the rivals explain 80 % of the beams; the robot has
#: to drive first.
CREEP_FOUND = 13


def test_global_search_metric_office_random_poses() -> None:
    found, wrong, n = _global_trials(office_metric_map(), 1, 20, seed=2026)
    assert wrong == 0
    assert found >= CREEP_FOUND, f"found {found}/{n}"


def test_global_search_with_laser_odometry_fixes_no_robot_wrongly() -> None:
    """The same starts with the scans' own motion as odometry: the search weighs places over
    the drive's keyframes, one per 0.3 m, so three creeping scans (6 cm) add none after the
    first and no place reaches the fix odds yet (a scan repeating its keyframe's view would
    count that view's evidence again, for a wrong place as much as for the true one). None is
    fixed wrongly."""
    found, wrong, n = _global_trials(office_metric_map(), 1, 20, seed=2026, laser_odometry=True)
    assert wrong == 0, f"{wrong} of {n} wrong ({found} right)"


def test_global_search_schematic_office_random_poses() -> None:
    """On the floor plan 3 scans, creeping or turning in place, are weak evidence (the plan
    holds no furniture, rooms W1 and W4 are congruent within 15 cm): at most 8 nats creeping
    with a 180-degree laser, 17 looking around, against a fix_llr of 25 that the tuning
    split set (a false fix at 15). A fix there would be a guess: none of these starts is
    fixed, nor put on probation, at a wrong place; the robot must drive first
    (test_look_around_start_fixes_within_five_metres_and_keeps_tracking)."""
    found, wrong, n = _global_trials(office_schematic_map(), 2, 12, seed=2027)
    assert wrong == 0, f"{wrong} of {n} wrong ({found} right)"


def test_look_around_metric_office_random_poses() -> None:
    """Turning 90 degrees in place per scan, 3 scans (a 270-degree composite): 9 of 12 starts
    reach the metric map's fix odds (GlobalConfig.fix_llr), none at a wrong place."""
    found, wrong, n = _global_trials(office_metric_map(), 1, 12, seed=2029, motion="look-around")
    assert wrong == 0
    assert found >= 9, f"found {found}/{n}"


def test_look_around_schematic_office_random_poses() -> None:
    """Turning 90 degrees in place per scan on the floor plan: no wrong place is fixed (see
    test_global_search_schematic_office_random_poses)."""
    found, wrong, n = _global_trials(office_schematic_map(), 2, 16, seed=2028, motion="look-around")
    assert wrong == 0, f"{wrong} of {n} wrong ({found} right)"


def test_global_search_ranks_the_true_pose_first_on_a_distinctive_view() -> None:
    su = make_setup(1)
    idx = gl.load_or_build_index(su.map_data)
    truth = su.truth[1836]
    r, a = su.scan(1836)
    g = gl.GlobalConfig.for_kind("metric")
    res = run_steps(search_steps(idx, r, a, gl.ShapeConfig.for_kind("metric"), g))
    assert res.candidates > 20
    best = res.hypotheses[0]
    assert _found(best.pose, truth)
    assert best.hit > 0.9 and best.violation < 0.05
    # the best distinct alternative explains the scan clearly worse
    from service.core.reloc.global_search import distinct

    other = next(h for h in res.hypotheses[1:] if distinct(h.pose, best.pose))
    assert other.cost > best.cost + 0.05


# ------------------------------------------------------------------------- symmetry


def test_symmetric_room_stays_initializing_with_high_ambiguity() -> None:
    # a plain 6 x 4 m rectangle: (x, y, th) and (6 - x, 4 - y, th + pi) see the same scan
    md = MapData.from_lists("rect", "metric", [_ring(0, 0, 6, 4)])
    laser = LaserSimulator(md.segments(), seed=3)
    loc = create_localizer("shape", md, None)
    truth = np.array([1.6, 1.3, 0.4])
    for s in range(5):
        p = truth + np.array([0.03 * s * np.cos(truth[2]), 0.03 * s * np.sin(truth[2]), 0])
        r, a = laser.scan(p, s)
        est = loc.update(r, a)
        assert est.status == "initializing", f"scan {s}: {est.status} at {est.pose}"
        # the posterior probability that the leader is not the place: a tie with the twin is
        # 0.5 or more (a confident leader would be near 0)
        assert est.ambiguity is not None and est.ambiguity >= 0.5
        mirror = np.array([6 - p[0], 4 - p[1], wrap_angle(p[2] + np.pi)])
        assert _found(est.pose, p) or _found(est.pose, mirror)


def test_symmetric_room_stays_ambiguous_after_looking_around() -> None:
    # a full 360-degree view of a plain rectangle still fits the truth and its 180-degree twin
    md = MapData.from_lists("rect", "metric", [_ring(0, 0, 6, 4)])
    laser = LaserSimulator(md.segments(), seed=4)
    loc = create_localizer("shape", md, None)
    start = np.array([1.6, 1.3, 0.4])
    truth = np.array([[1.6, 1.3, wrap_angle(0.4 + s * np.pi / 2)] for s in range(4)])
    odom = simulate_odometry(truth, seed=5)
    for s in range(4):
        r, a = laser.scan(truth[s], s)
        est = loc.update(r, a, odom[s])
        assert est.status == "initializing", f"scan {s}: {est.status} at {est.pose}"
        # the twins are back-scored on the keyframes from odometry-moved poses: their
        # log-likelihoods differ by the polish's noise (~1 nat), so the posterior of the
        # leader may drift from a tie, but stays far below the odds a fix takes (e^fix_llr)
        assert est.ambiguity is not None and est.ambiguity >= 0.1
    assert len(loc.state.drive.history) == 3  # the composite held the last 3 scans
    p = truth[-1]
    mirror = np.array([6 - p[0], 4 - p[1], wrap_angle(p[2] + np.pi)])
    assert _found(est.pose, p) or _found(est.pose, mirror), start
    cands = est.candidates[:, :3]
    assert any(_found(c, p) for c in cands) and any(_found(c, mirror) for c in cands)


def test_composite_needs_odometry_and_stays_within_the_travel_limit() -> None:
    assert st.dr.COMPOSITE_SCANS == 3 and st.dr.COMPOSITE_TRAVEL == 0.5
    drive = st.dr.Drive()
    a = np.linspace(-np.pi / 2, np.pi / 2, 181)
    r = np.full(181, 2.0)

    def feed(odom: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        return drive.composite(r, a, odom)

    out, _ = feed(None)  # no odometry: the scan alone, nothing kept
    assert out is r and drive.history == []
    feed(np.array([0.0, 0.0, 0.0]))
    out, ang = feed(np.array([0.0, 0.0, np.pi]))  # turned around: a full circle
    # 1-degree beams: 360 bins, not 720 (finer bins would leave a hole between beams)
    assert len(drive.history) == 2 and ang.size == 360
    assert np.isfinite(out).all()
    feed(np.array([0.1, 0.0, np.pi / 2]))
    feed(np.array([0.2, 0.0, 0.0]))
    assert len(drive.history) == 3  # the newest 3 only
    feed(np.array([2.0, 0.0, 0.0]))  # 1.8 m on: the older scans' occlusions no longer hold
    assert len(drive.history) == 1
    feed(None)  # odometry stopped: history dropped
    assert drive.history == []


# ------------------------------------------------------------------------- kidnapping


@pytest.mark.parametrize("laser", [False, True], ids=["paper", "laser-odometry"])
@pytest.mark.parametrize("setup,stride", [(1, 5), (2, 1)])
def test_kidnapped_robot_goes_lost_and_relocalises(setup: int, stride: int, laser: bool) -> None:
    """Carried from 10 % to 60 % of the tour between two scans, without odometry: lost within
    3 scans, never ``tracking`` at a wrong pose, then fixed again. In the paper's mode the
    search publishes a fix within 10 scans; with the laser odometry the search weighs the
    places over the drive, and a floor plan's winner is published after its probation's
    travel (GlobalConfig.probation_travel, 2 m: 20 scans of setup 2), so the run is longer."""
    su = make_setup(setup)
    n = len(su)
    a0, b0 = round(0.1 * (n - 1)), round(0.6 * (n - 1))
    loc = create_localizer("shape", su.map_data, su.truth[a0], laser_odometry=laser)
    for i in range(a0, a0 + 8 * stride, stride):
        est = loc.update(*su.scan(i))
        assert est.status == "tracking"
        # (a scan the tracker rejects keeps its prior, which may lag a sharp turn)
        assert "rejected" in est.extras or _found(est.pose, su.truth[i])
    statuses = []
    scans = 35 if laser else 14
    for k, i in enumerate(range(b0, b0 + scans * stride, stride)):
        est = loc.update(*su.scan(i))
        statuses.append(est.status)
        if est.status == "tracking" and k > 0 and "rejected" not in est.extras:
            assert _found(est.pose, su.truth[i]), f"scan {k} after the jump: tracking wrongly"
    assert "lost" in statuses[:3], statuses
    first_lost = statuses.index("lost")
    assert "tracking" in statuses[first_lost : 10 if not laser else 30], statuses
    assert statuses[-1] == "tracking"


def test_after_a_kidnap_a_probation_passes_at_fix_llr_not_at_the_first_fixes_pass() -> None:
    """pass_llr is set on first fixes (no prior pose); after a loss the search weighs the
    dead-reckoned prior and its winner passes at fix_llr: with the first fixes' pass out of
    reach the kidnapped robot on the floor plan is still fixed again, at the truth."""
    su = make_setup(2)
    n = len(su)
    a0, b0 = round(0.1 * (n - 1)), round(0.6 * (n - 1))
    loc = create_localizer("shape", su.map_data, su.truth[a0], laser_odometry=True)
    loc.gconfig = loc.gconfig.model_copy(update={"pass_llr": 1e6})  # the inner localiser's
    for i in range(a0, a0 + 8):
        loc.update(*su.scan(i))
    statuses = []
    for i in range(b0, b0 + 35):
        est = loc.update(*su.scan(i))
        statuses.append(est.status)
    assert "lost" in statuses[:3] and statuses[-1] == "tracking", statuses
    assert _found(est.pose, su.truth[b0 + 34])


# ------------------------------------------------------------------ kernels, evidence, composite


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_field_score_kernel_agrees_with_the_numpy_reference(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    idx = gl.load_or_build_index(office_schematic_map())
    rng = np.random.default_rng(61)
    poses = np.column_stack(
        [rng.uniform(-1, 15, 300), rng.uniform(-1, 24, 300), rng.uniform(-4, 4, 300)]
    )
    pts = rng.uniform(-6, 6, size=(80, 2))
    got = idx.sensor.field_score(poses, pts, 0.05)
    monkeypatch.setattr(kernels, "HAVE_NUMBA", False)
    ref = idx.sensor.field_score(poses, pts, 0.05)
    assert np.max(np.abs(got - ref)) < 1e-12
    assert np.ptp(ref) > 0.1  # the inputs exercise the field, not only its outside


# ------------------------------------------------------------------------- look-around start


def _sim_run(
    start: float, scans: int, ends: list[dict[str, float]] | None = None, **update: float
) -> list[tuple[str, bool, bool]]:
    """A simulated robot on the schematic map with a 3-scan look-around start and no initial
    pose; (status, pose passes 0.5 m / 10 deg, winner on probation) per scan. ``update`` sets
    GlobalConfig fields; a beaten probation's extras are appended to ``ends``."""
    fleet = SimFleet.from_specs(
        fleet_specs(1, ["schematic"], starts=[start]), global_localization=True, look_around=3
    )
    robot = fleet.robots[0]
    loc = create_localizer("shape", next(iter(fleet.maps.values())), None)
    loc.gconfig = loc.gconfig.model_copy(update=update)
    out = []
    for k in range(scans):
        scan, truth = robot.step(float(k))
        r = np.asarray(scan.ranges, dtype=float)
        a = scan.angle_min + scan.angle_increment * np.arange(r.size)
        est = loc.update(r, a, np.asarray(scan.odom))
        ok = _found(est.pose, np.asarray(truth.pose))
        out.append((est.status, ok, "probation" in est.extras))
        if ends is not None and "probation_llr" in est.extras:
            ends.append(dict(est.extras))
    return out


#: Scans a look-around start may take to a decision on the office's floor plan: the 3-scan
#: look-around and 5 m of driving. Views in place are weak evidence there (the plan holds no
#: furniture; rooms W1 and W4 are congruent): 9-15 nats after the look-around, against a
#: fix_llr of 25 that the tuning split set (a false fix at 15). Measured: the decision at
#: scan 8 from 0.35, 44 from 0.45; published after the probation's 2 m.
LOOK_AROUND_START_SCANS = 53


@pytest.mark.parametrize("start", [0.35, 0.45])
def test_look_around_start_fixes_within_five_metres_and_keeps_tracking(start: float) -> None:
    # On this floor plan the winner is tracked on probation until the robot has driven 2 m
    # (GlobalConfig.probation_travel), then published; from the decision on every estimate
    # names the true place, and once published it stays tracking.
    run = _sim_run(start, LOOK_AROUND_START_SCANS + 30)
    decided = [s == "tracking" or p for s, _ok, p in run]
    assert True in decided[:LOOK_AROUND_START_SCANS], run
    first = decided.index(True)
    assert all(d and ok for d, (_s, ok, _p) in zip(decided[first:], run[first:], strict=True)), run
    statuses = [s for s, _ok, _p in run]
    assert "tracking" in statuses, run
    fix = statuses.index("tracking")
    assert fix > first and all(s == "tracking" for s in statuses[fix:]), run


def test_a_probation_passes_only_once_its_winner_leads_at_pass_llr() -> None:
    """A winner enters probation at fix_llr and is fixed only if, after probation_travel, the
    decision names it at pass_llr (fix_llr if higher). Out of reach, every probation ends
    beaten and says how far its winner led: the robot is never published as tracking."""
    ends: list[dict[str, float]] = []
    run = _sim_run(0.35, LOOK_AROUND_START_SCANS + 30, ends, pass_llr=1e6)
    assert not any(s == "tracking" for s, _ok, _p in run), run
    assert any(p for _s, _ok, p in run), "no winner ever entered probation"
    led = [e for e in ends if e["probation_lead"] == 1.0]
    assert led and all(e["probation_llr"] >= 25.0 for e in led), ends


def test_predict_moves_the_tracker_pose_by_a_relative_motion() -> None:
    from service.core.tracking.localizer import ShapeLocalizer

    loc = ShapeLocalizer(office_metric_map(), np.array([1.0, 2.0, np.pi / 2]))
    loc.predict(np.array([1.0, 0.0, np.pi / 2]))  # 1 m forward (= +y), then a left turn
    assert loc.pose is not None
    np.testing.assert_allclose(loc.pose, [1.0, 3.0, np.pi], atol=1e-12)
    with pytest.raises(gl.LocalizationError):
        loc.predict(np.array([np.nan, 0.0, 0.0]))
    empty = ShapeLocalizer(office_metric_map(), None)
    empty.predict(np.array([1.0, 0.0, 0.0]))
    assert empty.pose is None


# ------------------------------------------------------------------------- self-similarity


def _twin_rooms(n: int = 2) -> MapData:
    """``n`` congruent L-shaped rooms 7 m apart (no 180-degree symmetry within a room)."""
    room = np.array([[0, 0], [5, 0], [5, 2], [3, 2], [3, 3.5], [0, 3.5], [0, 0]], dtype=float)
    return MapData.from_lists(
        "twins", "metric", [room + np.array([7.0 * k, 0.0]) for k in range(n)]
    )


def test_self_similar_finds_every_congruent_room_from_the_map_alone() -> None:
    md = _twin_rooms(3)
    laser = LaserSimulator(md.segments(), seed=7)
    truth = np.array([1.2, 1.0, 0.3])
    r, a = laser.scan(truth, 0)
    idx = gl.load_or_build_index(md)
    cfg = gl.ShapeConfig.for_kind("metric")
    g = gl.GlobalConfig.for_kind("metric")
    P = scan_configuration(r, a, cfg.extraction())
    best = verify(idx, truth, r, a, P, cfg, g)
    (one,) = run_steps(self_similar_steps(idx, best, r, a, P, cfg, g))
    twins = run_steps(self_similar_steps(idx, best, r, a, P, cfg, g, count=3))
    assert [t.cost for t in twins] == sorted(t.cost for t in twins)
    assert one.cost == twins[0].cost
    for k in (1, 2):  # each other room, once
        shifted = truth + np.array([7.0 * k, 0.0, 0.0])
        assert sum(_found(t.pose, shifted) for t in twins) == 1, [t.pose for t in twins]
    assert all(abs(t.cost - best.cost) < 0.05 for t in twins[:2])  # the scan cannot tell them apart


def test_congruent_rooms_never_give_a_fix() -> None:
    md = _twin_rooms()
    laser = LaserSimulator(md.segments(), seed=8)
    loc = create_localizer("shape", md, None)
    truth = np.array([[1.2, 1.0, wrap_angle(0.3 + s * np.pi / 2)] for s in range(5)])
    odom = simulate_odometry(truth, seed=9)
    for s in range(5):
        r, a = laser.scan(truth[s], s)
        est = loc.update(r, a, odom[s])
        assert est.status == "initializing", f"scan {s}: {est.status} at {est.pose}"
        assert est.ambiguity is not None and est.ambiguity >= 0.5


# ------------------------------------------------------------- recovery near the lost track


def _room_scans(poses: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    from service.core.sensor.raycast import RayCaster

    rc = RayCaster(_room_map().segments())
    ang = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    rng = np.random.default_rng(21)
    return ang, [rc.cast(p, ang, 15.0) + rng.normal(0, 0.01, ang.shape) for p in poses]


def test_dead_reckoning_relocks_near_its_pose_and_a_kidnap_never_does() -> None:
    """A robot dead-reckoning (the map did not explain its scans) publishes the dead-reckoned
    pose with status lost; once the map explains relock_scans scans in a row near it, it
    tracks again. Scans from elsewhere (a kidnap) never relock: they contradict the pose, and
    the robot searches with the dead-reckoned pose as its prior; it tracks again only where
    the scans were taken (the search's fix, at 25 nats on the fifth scan when measured)."""
    from service.core.pose import compose

    poses = [np.array([2.0 + 0.08 * k, 2.4, 0.2]) for k in range(8)]
    frame = np.array([5.0, -3.0, 1.0])  # the odometry's own frame
    odom = [compose(frame, p) for p in poses]
    ang, scans = _room_scans(poses)
    loc = create_localizer("shape", _room_map(), poses[0])
    g = loc.gconfig
    assert loc.update(scans[0], ang, odom[0]).status == "tracking"
    loc.state = st.DeadReckoning(poses[0].copy(), np.diag([0.05**2, 0.05**2, 0.02**2]))
    out = [loc.update(scans[k], ang, odom[k]) for k in range(1, 1 + g.relock_scans)]
    assert [e.status for e in out] == ["lost"] * (g.relock_scans - 1) + ["tracking"]
    assert [e.state for e in out] == ["dead_reckoning"] * (g.relock_scans - 1) + ["tracking"]
    for k, e in enumerate(out[:-1], start=1):
        assert np.hypot(*(e.pose[:2] - poses[k][:2])) < 0.05  # dead-reckoned, not zeros
        assert e.covariance is not None and np.all(np.isfinite(e.covariance))
    assert out[-1].extras["relocked"] == 1.0
    assert np.hypot(*(out[-1].pose[:2] - poses[g.relock_scans][:2])) < 0.03
    # kidnapped: the odometry says the robot is at poses[k], the scans come from elsewhere
    far = [np.array([4.8, 0.8, 2.5]) for _ in range(6)]
    _, kid = _room_scans(far)
    loc2 = create_localizer("shape", _room_map(), poses[0])
    loc2.update(scans[0], ang, odom[0])
    loc2.state = st.DeadReckoning(poses[0].copy(), np.diag([0.05**2, 0.05**2, 0.02**2]))
    out2 = [loc2.update(kid[k], ang, odom[k + 1]) for k in range(6)]
    states = [e.state for e in out2]
    assert "searching" in states, states
    first = states.index("searching")
    assert all(e.status == "lost" for e in out2[: first + 1]), states
    for e in out2[first:]:  # lost, or fixed where the scans come from, never near the DR pose
        assert e.status == "lost" or _found(e.pose, far[0]), (states, e.pose)


def test_speed_known_before_a_loss_is_carried_to_the_fix() -> None:
    """Without odometry the tracker's speed bound holds from the first scan after a
    relocalisation: the speed was measured before the loss."""
    loc = create_localizer("shape", _room_map(), np.array([2.0, 2.4, 0.2]))
    t = loc.tracker
    assert t.known_speed() is None
    t.set_speed(np.array([0.1, 0.0]))
    np.testing.assert_allclose(t.known_speed(), [0.1, 0.0])
    pred = t.motion.predict(t.pose, None)
    cfg = t.config
    assert t._max_step(pred) == pytest.approx(cfg.speed_step_floor + cfg.speed_step_factor * 0.1)
    with pytest.raises(gl.LocalizationError):
        t.set_speed(np.array([np.nan, 0.0]))
