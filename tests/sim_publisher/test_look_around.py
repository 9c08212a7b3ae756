"""Look-around start of simulated robots: turn in place before driving the tour.

Checks truth, scans and odometry during the spin, the seamless hand-over to the tour, that
``look_around=0`` changes nothing, argument validation and the CLI flags. Runs in about 3 s.
"""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zenoh

from clients.client import zenoh_config
from schemas.codec import decode, encode
from schemas.messages import RobotConfig, Scan, Truth
from service.core.pose import relative
from service.core.types import wrap_angle
from sim_publisher.__main__ import SimOptions, build_parser, main, options_from_args
from sim_publisher.publisher import SimFleet, SimRobot, fleet_specs
from sim_publisher.scenario import make_setup

pytestmark = pytest.mark.timeout(120)

START = 10


@pytest.fixture(scope="module")
def setup1():
    return make_setup(1, seed=3, max_scans=60)


def _run(robot: SimRobot, n: int, t0: float = 50.0) -> tuple[list[Scan], list[Truth]]:
    scans, truths = [], []
    for k in range(n):
        s, t = robot.step(t0 + 0.1 * k)
        scans.append(s)
        truths.append(t)
    return scans, truths


@pytest.mark.parametrize("turn", [math.pi / 2, -math.radians(60.0), math.radians(135.0)])
def test_spin_truths_turn_in_place_and_end_at_the_tour_start(setup1, turn: float) -> None:
    n_look = 3
    r = SimRobot("r0", setup1, "office", start=START, look_around=n_look, look_turn=turn)
    _, truths = _run(r, n_look + 4)
    start = setup1.truth[START]
    poses = np.array([t.pose for t in truths])
    for k in range(n_look):
        np.testing.assert_allclose(poses[k, :2], start[:2], atol=1e-12)
        expected = wrap_angle(start[2] - (n_look - 1 - k) * turn)
        assert wrap_angle(poses[k, 2] - expected) == pytest.approx(0.0, abs=1e-12)
        assert -math.pi < poses[k, 2] <= math.pi
    # neighbouring spin scans differ by exactly one turn; the spin ends facing the tour
    for k in range(n_look - 1):
        assert wrap_angle(poses[k + 1, 2] - poses[k, 2]) == pytest.approx(turn, abs=1e-12)
    assert wrap_angle(poses[n_look - 1, 2] - start[2]) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_array_equal(poses[n_look], start)
    for j in range(4):
        np.testing.assert_array_equal(poses[n_look + j], setup1.truth[START + j])


def test_spin_scans_are_taken_at_the_turned_pose(setup1) -> None:
    n_look = 2
    r = SimRobot("r0", setup1, "office", start=START, look_around=n_look)
    scans, truths = _run(r, n_look + 1)
    sigma = setup1.laser.config.noise_sigma
    for s, t in zip(scans, truths, strict=True):
        exact = setup1.laser.exact(np.array(t.pose))
        ok = ~np.isnan(s.ranges) & ~np.isnan(exact)
        assert ok.sum() > 0.8 * len(exact)
        assert np.max(np.abs(s.ranges[ok] - exact[ok])) < 6 * sigma
    # the room looks different when turned by 90 degrees: the first scan is not the start scan
    at_start = setup1.laser.exact(setup1.truth[START])
    both = ~np.isnan(scans[0].ranges) & ~np.isnan(at_start)
    assert np.median(np.abs(scans[0].ranges[both] - at_start[both])) > 0.2
    # a spun scan has its own noise draw, not the one of the tour scan at the start index
    reused, _ = setup1.laser.scan(np.array(truths[0].pose), START)
    assert not np.array_equal(scans[0].ranges, reused, equal_nan=True)
    # scan N is the tour's own scan at the start index (same noise draw)
    ranges_n, _ = setup1.scan(START)
    np.testing.assert_array_equal(scans[n_look].ranges, ranges_n)


def test_spin_odometry_turns_in_place_without_a_jump_at_the_hand_over(setup1) -> None:
    n_look, turn = 4, math.pi / 2
    r = SimRobot("r0", setup1, "office", start=START, look_around=n_look, look_turn=turn)
    assert 0.01 <= abs(r.look_turn_error) <= 0.03
    scans, _ = _run(r, n_look + 3)
    odom = np.array([s.odom for s in scans])
    deltas = np.array([relative(odom[k], odom[k + 1]) for k in range(n_look - 1)])
    # every in-place turn has no translation ...
    np.testing.assert_allclose(deltas[:, :2], 0.0, atol=1e-12)
    # ... and turns by the commanded angle within 5 %, but not exactly (rotation error)
    assert np.all(np.abs(deltas[:, 2] - turn) <= 0.05 * turn)
    assert np.all(np.abs(deltas[:, 2] - turn) > 1e-6)
    np.testing.assert_allclose(deltas[:, 2], deltas[-1, 2], atol=1e-12)
    np.testing.assert_allclose(deltas[-1, 2], turn * (1.0 + r.look_turn_error), atol=1e-12)
    # the spin ends where the tour starts: no jump and no turn at the hand-over
    np.testing.assert_array_equal(odom[n_look - 1], odom[n_look])
    # after the spin the setup's odometry continues in the same frame
    np.testing.assert_array_equal(odom[n_look], setup1.odom[START])
    drive = relative(odom[n_look], odom[n_look + 1])
    np.testing.assert_allclose(
        drive, relative(setup1.odom[START], setup1.odom[START + 1]), atol=1e-12
    )
    assert np.all(np.abs(odom[:, 2]) <= math.pi)


def test_rotation_error_is_seeded_and_stable_across_processes(setup1) -> None:
    a = SimRobot("sim-0", setup1, "office", look_around=2, look_seed=5).look_turn_error
    b = SimRobot("sim-0", setup1, "office", look_around=2, look_seed=5).look_turn_error
    c = SimRobot("sim-0", setup1, "office", look_around=2, look_seed=6).look_turn_error
    d = SimRobot("sim-1", setup1, "office", look_around=2, look_seed=5).look_turn_error
    assert a == b
    assert len({a, c, d}) == 3
    code = (
        "from sim_publisher.scenario import make_setup\n"
        "from sim_publisher.publisher import SimRobot\n"
        "s = make_setup(1, seed=3, max_scans=5)\n"
        "print(repr(SimRobot('sim-0', s, 'office', look_around=2, look_seed=5).look_turn_error))"
    )
    env = dict(os.environ, PYTHONHASHSEED="12345")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    assert float(out.stdout.strip()) == a


def test_seq_and_stamps_are_continuous_through_the_spin(setup1) -> None:
    r = SimRobot("r0", setup1, "office", start=START, look_around=3)
    scans, truths = _run(r, 8, t0=7.0)
    assert [s.seq for s in scans] == list(range(8)) == [t.seq for t in truths]
    assert [s.stamp for s in scans] == [t.stamp for t in truths]
    np.testing.assert_allclose(np.diff([s.stamp for s in scans]), 0.1, atol=1e-9)
    assert r.seq == 8 and r.index == START + 5


def test_after_the_spin_messages_equal_the_plain_robots_shifted_by_n(setup1) -> None:
    n_look = 3
    n = len(setup1.truth)
    look = SimRobot("r0", setup1, "office", start=n - 4, look_around=n_look)
    plain = SimRobot("r0", setup1, "office", start=n - 4)
    _run(look, n_look)
    for j in range(8):  # through the turn-back at the end of the tour
        sl, tl = look.step(float(j))
        sp, tp = plain.step(float(j))
        assert sl.seq == n_look + j and sp.seq == j
        assert sl.model_copy(update={"seq": j}) == sp
        assert tl.model_copy(update={"seq": j}) == tp


def test_look_around_zero_leaves_every_message_unchanged(setup1) -> None:
    kw = {"start": 50, "kidnap_at": 6, "kidnap_to": 20}
    ref = SimRobot("r0", setup1, "office", **kw)
    zero = SimRobot("r0", setup1, "office", look_around=0, look_turn=1.234, look_seed=9, **kw)
    assert encode(zero.config()) == encode(ref.config())
    for k in range(16):  # turn-back at the tour end and a kidnap at seq 6
        s0, t0 = zero.step(3.0 + k)
        s1, t1 = ref.step(3.0 + k)
        assert encode(s0, ranges_as_bytes=True) == encode(s1, ranges_as_bytes=True)
        assert encode(t0) == encode(t1)
        assert np.array_equal(s0.ranges, s1.ranges, equal_nan=True)
        np.testing.assert_array_equal(s0.odom, s1.odom)
        np.testing.assert_array_equal(t0.pose, t1.pose)
    no_odom = SimRobot("r0", setup1, "office", send_odom=False, look_around=2)
    assert all(s.odom is None for s in _run(no_odom, 3)[0])


def test_config_initial_pose_is_the_first_spun_pose(setup1) -> None:
    r = SimRobot("r0", setup1, "office", start=START, look_around=3)
    pose = decode(RobotConfig, encode(r.config())).initial_pose
    _, truth = r.step(0.0)
    np.testing.assert_allclose(pose, truth.pose, atol=1e-12)
    assert abs(wrap_angle(pose[2] - setup1.truth[START][2])) == pytest.approx(math.pi, abs=1e-9)
    g = SimRobot("r1", setup1, "office", global_localization=True, look_around=2)
    assert g.config().initial_pose is None


def test_kidnap_keeps_its_absolute_seq(setup1) -> None:
    after = SimRobot("r0", setup1, "office", start=START, look_around=3, kidnap_at=5, kidnap_to=40)
    _, truths = _run(after, 7)
    np.testing.assert_array_equal(truths[3].pose, setup1.truth[START])
    np.testing.assert_array_equal(truths[4].pose, setup1.truth[START + 1])
    np.testing.assert_array_equal(truths[5].pose, setup1.truth[40])
    np.testing.assert_array_equal(truths[6].pose, setup1.truth[41])
    # a kidnap during the spin ends it: carried to the kidnap position, then driving on
    during = SimRobot("r0", setup1, "office", start=START, look_around=3, kidnap_at=1, kidnap_to=40)
    scans, truths = _run(during, 3)
    np.testing.assert_allclose(truths[0].pose[:2], setup1.truth[START][:2], atol=1e-12)
    assert truths[0].pose[2] != pytest.approx(setup1.truth[START][2])
    np.testing.assert_array_equal(truths[1].pose, setup1.truth[40])
    np.testing.assert_array_equal(truths[2].pose, setup1.truth[41])
    # the wheels do not see the carry: the odometry stands still across the jump, then moves
    # by the tour's own increments
    np.testing.assert_allclose(scans[1].odom, scans[0].odom, atol=1e-12)
    np.testing.assert_allclose(
        relative(np.asarray(scans[1].odom), np.asarray(scans[2].odom)),
        relative(setup1.odom[40], setup1.odom[41]),
        atol=1e-12,
    )


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"look_around": -1}, "look_around must be >= 0"),
        ({"look_around": 1.5}, "look_around must be an integer"),
        ({"look_around": True}, "look_around must be an integer"),
        ({"look_turn": math.nan}, "look_turn must be a finite"),
        ({"look_turn": math.inf}, "look_turn must be a finite"),
        ({"look_turn": -math.inf}, "look_turn must be a finite"),
    ],
)
def test_invalid_look_around_arguments_raise(setup1, kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        SimRobot("r0", setup1, "office", **kw)


def test_fleet_passes_look_around_to_every_robot() -> None:
    specs = fleet_specs(2, ["metric", "schematic"], seed=4, starts=[0.1, 0.3])
    fleet = SimFleet.from_specs(specs, look_around=2, look_turn=math.radians(45.0))
    errors = set()
    for r, sp in zip(fleet.robots, specs, strict=True):
        assert (r.look_around, r.look_turn) == (2, pytest.approx(math.pi / 4))
        ref = SimRobot(sp.robot_id, r.setup, r.map_id, look_around=2, look_seed=sp.seed)
        assert r.look_turn_error == ref.look_turn_error
        errors.add(r.look_turn_error)
        p0 = r.start_pose
        _, t0 = r.step(0.0)
        _, t1 = r.step(0.0)
        np.testing.assert_allclose(t0.pose[:2], t1.pose[:2], atol=1e-12)
        assert wrap_angle(t1.pose[2] - t0.pose[2]) == pytest.approx(math.pi / 4, abs=1e-12)
        np.testing.assert_allclose(t0.pose, p0, atol=1e-12)
    assert len(errors) == 2
    plain = SimFleet.from_specs(specs)
    assert all(r.look_around == 0 for r in plain.robots)


def test_cli_parses_look_around_flags(capsys) -> None:
    p = build_parser()

    def opts(*argv: str) -> SimOptions:
        return options_from_args(p.parse_args(["run", *argv]))

    o = opts("--global", "--look-around", "3", "--look-turn-deg", "60")
    assert o.look_around == 3 and o.look_turn_deg == 60.0 and o.global_localization
    d = opts()
    assert d.look_around == 0 and d.look_turn_deg == 90.0
    assert SimOptions().look_around == 0 and SimOptions().look_turn_deg == 90.0
    with pytest.raises(ValueError, match="--look-around"):
        opts("--look-around", "-1")
    with pytest.raises(ValueError, match="--look-turn-deg"):
        opts("--look-turn-deg", "nan")
    with pytest.raises(SystemExit):
        p.parse_args(["run", "--look-around", "1.5"])
    capsys.readouterr()
    with pytest.raises(SystemExit):
        p.parse_args(["run", "-h"])
    help_text = capsys.readouterr().out
    assert "--look-around N" in help_text and "--look-turn-deg DEG" in help_text


def test_main_publishes_the_spin_over_zenoh() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def record(sample: zenoh.Sample) -> None:
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))

    with zenoh.open(zenoh_config("router", listen=[ep])) as router:
        sub = router.declare_subscriber("shapeloc/robots/**", record)
        try:
            opts = SimOptions(
                robots=1,
                scans=4,
                max_rate=True,
                wait_service=0.0,
                global_localization=True,
                look_around=2,
                look_turn_deg=-90.0,
            )
            assert main(zenoh_config("client", connect=[ep]), opts) == 0
            time.sleep(0.3)
        finally:
            sub.undeclare()
    cfg = [decode(RobotConfig, v) for k, v in got if k == "shapeloc/robots/sim-0/config"]
    assert len(cfg) == 1 and cfg[0].initial_pose is None
    truths = [decode(Truth, v) for k, v in got if k == "shapeloc/robots/sim-0/truth"]
    assert [t.seq for t in truths] == [0, 1, 2, 3]
    poses = np.array([t.pose for t in truths])
    np.testing.assert_allclose(poses[1, :2], poses[0, :2], atol=1e-12)
    np.testing.assert_allclose(poses[2, :2], poses[0, :2], atol=1e-12)
    assert wrap_angle(poses[1, 2] - poses[0, 2]) == pytest.approx(-math.pi / 2, abs=1e-9)
    np.testing.assert_array_equal(poses[2], poses[1])  # the spin ended facing the tour
    assert np.hypot(*(poses[3, :2] - poses[2, :2])) > 1e-3  # driving after the spin
