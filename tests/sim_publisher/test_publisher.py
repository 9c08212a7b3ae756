"""Simulated robots and the simulator process loop: valid wire messages, ordering, determinism.

The network test runs the simulator's ``main`` against an in-process loopback router (no
service). Runs in about 3 s.
"""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest
import zenoh

from clients.client import zenoh_config
from schemas.codec import decode, encode, scan_arrays
from schemas.messages import Map, RobotConfig, Scan, Truth
from sim_publisher.__main__ import (
    COMMANDS,
    SimOptions,
    build_parser,
    cli,
    main,
    options_from_args,
)
from sim_publisher.laser import LaserConfig
from sim_publisher.publisher import SimFleet, SimRobot, fleet_specs
from sim_publisher.scenario import make_setup

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def setup1():
    return make_setup(1, seed=3, max_scans=60)


def test_scan_and_truth_messages_are_valid_and_ordered(setup1) -> None:
    robot = SimRobot("r0", setup1, "office", start=10)
    cfg = LaserConfig()
    seqs = []
    for k in range(5):
        scan, truth = robot.step(100.0 + k)
        scan2 = decode(Scan, encode(scan, ranges_as_bytes=True))
        truth2 = decode(Truth, encode(truth))
        seqs.append(scan2.seq)
        assert truth2.seq == scan2.seq and truth2.stamp == scan2.stamp == 100.0 + k
        assert scan2.angle_min == pytest.approx(-np.pi / 2)
        assert scan2.angle_increment == pytest.approx(np.pi / 360)
        assert (scan2.range_min, scan2.range_max) == (cfg.range_min, cfg.max_range)
        assert len(scan2.ranges) == cfg.beams
        np.testing.assert_allclose(truth2.pose, setup1.truth[10 + k], atol=1e-12)
        np.testing.assert_allclose(scan2.odom, setup1.odom[10 + k], atol=1e-12)
        expected, angles = setup1.scan(10 + k)
        ranges, angles2 = scan_arrays(scan2)
        assert np.array_equal(np.isnan(ranges), np.isnan(expected))
        np.testing.assert_allclose(ranges, expected, rtol=1e-6, equal_nan=True)  # float32 wire
        np.testing.assert_allclose(angles2, angles, atol=1e-12)
    assert seqs == [0, 1, 2, 3, 4]


def test_config_carries_true_start_or_null_for_global(setup1) -> None:
    r = SimRobot("r0", setup1, "office", "icp", start=7)
    cfg = decode(RobotConfig, encode(r.config()))
    assert cfg.method == "icp" and cfg.map_id == "office"
    np.testing.assert_allclose(cfg.initial_pose, setup1.truth[7], atol=1e-12)
    g = SimRobot("r1", setup1, "office", global_localization=True)
    assert g.config().initial_pose is None


def test_robot_turns_back_at_the_end_of_the_tour(setup1) -> None:
    n = len(setup1.truth)
    r = SimRobot("r0", setup1, "office", start=n - 2)
    idx = []
    for _ in range(4):
        idx.append(r.index)
        r.step(0.0)
    assert idx == [n - 2, n - 1, n - 2, n - 3]
    assert r.seq == 4


def test_stride_and_odometry_option(setup1) -> None:
    r = SimRobot("r0", setup1, "office", stride=5, send_odom=False)
    scan, _ = r.step(0.0)
    assert scan.odom is None
    assert r.index == 5


def test_bad_robot_arguments_are_rejected(setup1) -> None:
    with pytest.raises(ValueError, match="unknown method 'sift'"):
        SimRobot("r0", setup1, "office", "sift")
    with pytest.raises(ValueError, match="stride"):
        SimRobot("r0", setup1, "office", stride=0)


def test_fleet_specs_cycle_maps_methods_seeds_and_starts() -> None:
    specs = fleet_specs(4, ["metric", "schematic"], ["shape", "icp", "lines"], seed=10)
    assert [s.robot_id for s in specs] == ["sim-0", "sim-1", "sim-2", "sim-3"]
    assert [s.map_spec for s in specs] == ["metric", "schematic", "metric", "schematic"]
    assert [s.method for s in specs] == ["shape", "icp", "lines", "shape"]
    assert [s.seed for s in specs] == [10, 11, 12, 13]
    assert [s.setup for s in specs] == [1, 2, 1, 2]
    assert [s.start_fraction for s in specs] == [0.0, 0.25, 0.5, 0.75]
    assert [s.setup for s in fleet_specs(2, ["metric", "schematic"], setup=2)] == [2, 2]
    with pytest.raises(ValueError, match="at least one robot"):
        fleet_specs(0)
    with pytest.raises(ValueError, match="start fractions"):
        fleet_specs(3, starts=[0.1])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        fleet_specs(1, starts=[1.5])


def test_fleet_builds_maps_steps_and_is_deterministic() -> None:
    specs = fleet_specs(2, ["metric", "schematic"], seed=1, starts=[0.2, 0.4])
    a = SimFleet.from_specs(specs)
    b = SimFleet.from_specs(specs)
    kinds = {m.map_id: m.kind for m in a.map_messages()}
    assert kinds == {"office": "metric", "office-schematic": "schematic"}
    assert all(isinstance(m, Map) for m in a.map_messages())
    assert [r.map_id for r in a.robots] == ["office", "office-schematic"]
    for ra, rb in zip(a.robots, b.robots, strict=True):
        for _ in range(2):
            sa, ta = ra.step(1.0)
            sb, tb = rb.step(1.0)
            assert sa == sb and ta == tb
    # setup-2 sampling (~104 mm) for the schematic robot, ~11 mm for the metric one
    steps = []
    for r in a.robots:
        p0 = r.start_pose
        r.step(0.0)
        steps.append(float(np.hypot(*(r.start_pose[:2] - p0[:2]))))
    assert steps[0] == pytest.approx(0.011, abs=0.004)
    assert steps[1] == pytest.approx(0.104, abs=0.03)
    coarse = SimFleet.from_specs(fleet_specs(1, step_mm=55.0)).robots[0]
    p0 = coarse.start_pose
    coarse.step(0.0)
    assert float(np.hypot(*(coarse.start_pose[:2] - p0[:2]))) == pytest.approx(0.055, abs=0.01)


def test_options_from_args_validation() -> None:
    p = build_parser()
    o = options_from_args(
        p.parse_args(
            [
                "--robots",
                "3",
                "--map",
                "metric,schematic",
                "--method",
                "icp",
                "--scans",
                "5",
                "--global",
            ]
        )
    )
    assert o.robots == 3 and o.maps == ["metric", "schematic"] and o.methods == ["icp"]
    assert o.scans == 5 and o.global_localization
    with pytest.raises(ValueError, match="unknown method 'foo'"):
        options_from_args(p.parse_args(["--method", "shape,foo"]))
    with pytest.raises(ValueError, match="--rate"):
        options_from_args(p.parse_args(["--rate", "0"]))
    with pytest.raises(SystemExit):
        p.parse_args(["--setup", "1", "--step-mm", "20"])
    assert cli(["--robots", "0"]) == 2


def test_subcommands_and_run_as_the_deprecated_default(capsys) -> None:
    """``shapeloc-sim ARGS`` without a command still means ``shapeloc-sim run ARGS``, with a
    deprecation warning; global options may come before the command."""
    p = build_parser()
    argv = ["--robots", "2", "--map", "metric,schematic", "--rate", "5"]
    explicit = p.parse_args(["run", "--connect", "tcp/h:1", *argv])
    assert capsys.readouterr().err == ""
    before = p.parse_args(["--connect", "tcp/h:1", "run", *argv])
    implicit = p.parse_args(["--connect", "tcp/h:1", *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "shapeloc-sim: warning: shapeloc-sim without a command is deprecated and will be "
        "removed in the next release; use shapeloc-sim run ..."
    ]
    assert implicit.command == explicit.command == before.command == "run"
    assert vars(implicit) == vars(explicit) == vars(before)
    assert options_from_args(implicit) == options_from_args(explicit)
    assert p.parse_args([]).command == "run"  # no arguments at all: the default run
    assert (
        p.parse_args(["--prefix", "x", "-v", "replay", "L", "--robot", "r", "--map", "m"]).command
        == "replay"
    )
    assert set(COMMANDS) == {"run", "replay", "experiment"}
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        p.parse_args(["-h"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "run" in out and "replay" in out and "experiment" in out and "(default: client)" in out
    with pytest.raises(SystemExit) as exc:
        p.parse_args(["run", "-h"])
    out = " ".join(capsys.readouterr().out.split())
    assert (
        "--robots ROBOTS" in out and "(default: 10.0)" in out and "--laser-offset X Y THETA" in out
    )
    with pytest.raises(SystemExit):
        p.parse_args(["experiment", "--robots", "2"])  # run's options are not experiment's


def test_laser_offset_flag_reaches_every_robot(capsys) -> None:
    p = build_parser()
    o = options_from_args(p.parse_args(["run", "--laser-offset", "0.3", "0.1", "0.2"]))
    assert o.laser_offset == [0.3, 0.1, 0.2]
    o = options_from_args(p.parse_args(["run", "--laser-offset", "0.3,0.1,0.2"]))
    assert o.laser_offset == [0.3, 0.1, 0.2]
    assert "--laser-offset X,Y,THETA (comma form) is deprecated" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        p.parse_args(["run", "--laser-offset", "0.3", "0.1"])


def test_cli_unreachable_router_fails_fast(capsys) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    assert cli(["--connect", f"tcp/127.0.0.1:{port}", "--scans", "1"]) == 1
    assert time.monotonic() - t0 < 10.0
    assert f"tcp/127.0.0.1:{port}" in capsys.readouterr().err


def test_main_publishes_maps_configs_scans_and_truth_over_zenoh() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def record(sample: zenoh.Sample) -> None:
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))

    with zenoh.open(zenoh_config("router", listen=[ep])) as router:
        sub = router.declare_subscriber("shapeloc/**", record)
        try:
            # paced: scans are dropped under congestion like a real sensor's, and an unpaced
            # burst lost three of four on a loaded 2-core machine
            opts = SimOptions(
                robots=2, maps=["metric", "schematic"], scans=4, rate=20.0, wait_service=0.0
            )
            assert main(zenoh_config("client", connect=[ep]), opts) == 0
            time.sleep(0.3)
        finally:
            sub.undeclare()
    keys = [k for k, _ in got]
    assert "shapeloc/maps/office" in keys and "shapeloc/maps/office-schematic" in keys
    for rid in ("sim-0", "sim-1"):
        cfg = [v for k, v in got if k == f"shapeloc/robots/{rid}/config"]
        assert len(cfg) == 1 and decode(RobotConfig, cfg[0]).initial_pose is not None
        scans = [decode(Scan, v) for k, v in got if k == f"shapeloc/robots/{rid}/scan"]
        truths = [decode(Truth, v) for k, v in got if k == f"shapeloc/robots/{rid}/truth"]
        assert [m.seq for m in scans] == [0, 1, 2, 3]
        assert [m.seq for m in truths] == [0, 1, 2, 3]
    # the map is put before any configuration, and truth before its scan
    assert keys.index("shapeloc/maps/office") < keys.index("shapeloc/robots/sim-0/config")
    assert keys.index("shapeloc/robots/sim-0/truth") < keys.index("shapeloc/robots/sim-0/scan")


def test_map_file_spec_is_loaded_for_the_fleet(tmp_path) -> None:
    import json

    f = tmp_path / "plan.json"
    f.write_text(
        json.dumps(
            {
                "map_id": "plan",
                "kind": "schematic",
                "polylines": [[[0, 0], [14, 0], [14, 23], [0, 23], [0, 0]]],
            }
        )
    )
    fleet = SimFleet.from_specs(fleet_specs(1, [str(f)]))
    assert list(fleet.maps) == ["plan"] and fleet.maps["plan"].kind == "schematic"
    assert fleet.robots[0].map_id == "plan"
    assert fleet.map_messages()[0].polylines[0].shape == (5, 2)
