"""The ``shapeloc`` command line: argument handling, exit codes and one-line error messages.

Network cases use an in-process loopback router (with a tiny fake service where needed);
the real service is exercised in tests/integration/test_sim_and_cli.py. Runs in about 2 s.
"""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from clients.__main__ import GLOBAL_OPTIONS, build_parser, cli
from clients.client import zenoh_config
from schemas.codec import encode
from schemas.messages import Health, PoseMsg

pytestmark = pytest.mark.timeout(60)


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


@pytest.fixture
def router() -> Iterator[tuple[zenoh.Session, str]]:
    ep = free_endpoint()
    with zenoh.open(zenoh_config("router", listen=[ep])) as session:
        yield session, ep


@pytest.fixture
def fake_service(router) -> Iterator[str]:
    session, ep = router

    def health(q: zenoh.Query) -> None:
        h = Health(
            status="ok", version="1.2.3", robots=1, maps=0, scans_processed=42, scans_rejected=3
        )
        q.reply(q.key_expr, encode(h))

    def pose(q: zenoh.Query) -> None:
        rid = str(q.key_expr).split("/")[-2]
        if rid != "r1":
            q.reply_err(f"unknown robot {rid!r}".encode())
            return
        p = PoseMsg(
            robot_id="r1",
            seq=9,
            stamp=3.0,
            pose=[1.5, -2.25, 1.0],
            status="tracking",
            score=0.75,
            method="shape",
            map_id="office",
            latency_ms=4.5,
        )
        q.reply(q.key_expr, encode(p))

    ents = [
        session.declare_queryable("shapeloc/service/health", health),
        session.declare_queryable("shapeloc/robots/*/pose", pose),
    ]
    try:
        yield ep
    finally:
        for e in ents:
            e.undeclare()


def test_parser_requires_a_command_and_valid_arguments(capsys) -> None:
    p = build_parser()
    for bad in (
        [],
        ["configure", "r1", "--map", "m"],
        ["configure", "r1", "--pose", "1", "2"],
        ["configure", "r1", "--map", "m", "--pose", "1", "2", "3", "--global"],
        ["configure", "r1", "--map", "m", "--global", "--method", "sift"],
        ["--timeout", "0", "health"],
        ["map", "put"],
        ["frobnicate"],
    ):
        with pytest.raises(SystemExit) as ei:
            p.parse_args(bad)
        assert ei.value.code == 2, bad
    a = p.parse_args(
        [
            "--connect",
            "tcp/h:1",
            "--timeout",
            "0.5",
            "configure",
            "r1",
            "--map",
            "office",
            "--pose",
            "1",
            "2",
            "-0.5",
            "--method",
            "icp",
        ]
    )
    assert a.connect == ["tcp/h:1"] and a.timeout == 0.5 and a.initial_pose == [1.0, 2.0, -0.5]
    assert a.method == "icp" and not a.global_localization
    w = p.parse_args(["watch"])
    assert w.robot_id == "*" and w.count is None


def test_unreachable_service_exits_1_fast_with_one_line(capsys) -> None:
    ep = free_endpoint()
    t0 = time.monotonic()
    assert cli(["--connect", ep, "health"]) == 1
    assert time.monotonic() - t0 < 3.0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("shapeloc: error: cannot reach") and ep in err[0]


def test_router_without_service_exits_1_with_timeout_message(router, capsys) -> None:
    assert cli(["--connect", router[1], "--timeout", "0.5", "pose", "r1"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (
        "shapeloc: error: no shapeloc service answered on shapeloc/robots/r1/pose within 0.5 s"
    )


def test_health_pose_and_unknown_robot_against_a_fake_service(fake_service, capsys) -> None:
    assert cli(["--connect", fake_service, "health"]) == 0
    out = capsys.readouterr().out
    assert "ok: shapeloc 1.2.3" in out and "42 scans processed" in out and "3 rejected" in out
    assert cli(["--connect", fake_service, "pose", "r1"]) == 0
    out = capsys.readouterr().out
    assert "r1: x=1.500 m y=-2.250 m theta=57.3 deg" in out and "tracking" in out
    assert cli(["--connect", fake_service, "pose", "nobody"]) == 1
    cap = capsys.readouterr()
    assert cap.err.strip() == "shapeloc: error: unknown robot 'nobody'" and cap.out == ""
    assert cli(["--connect", fake_service, "maps"]) == 0
    assert capsys.readouterr().out.strip() == "no maps stored"


def test_invalid_robot_id_is_a_clean_error(fake_service, capsys) -> None:
    assert cli(["--connect", fake_service, "pose", "bad/id"]) == 1
    assert "robot_id" in capsys.readouterr().err


def test_experiment_is_no_longer_a_shapeloc_command(capsys) -> None:
    """The paper's experiment moved to the simulator (``shapeloc-sim experiment``)."""
    with pytest.raises(SystemExit) as exc:
        cli(["experiment", "--setup", "2"])
    assert exc.value.code == 2
    assert "invalid choice: 'experiment'" in capsys.readouterr().err


REPO = Path(__file__).resolve().parents[2]


def _compose_commands(text: str) -> dict[str, list[str]]:
    """``command:`` lists of each compose service (block style ``- item`` lists only)."""
    out: dict[str, list[str]] = {}
    current = None
    in_cmd = False
    for raw in text.splitlines():
        line = raw.split(" #", 1)[0].rstrip()
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        indent = len(line) - len(line.lstrip())
        if indent == 2 and line.endswith(":"):
            current, in_cmd = line.strip()[:-1], False
        elif indent == 4:
            in_cmd = line.strip() == "command:"
            if in_cmd and current is not None:
                out[current] = []
        elif in_cmd and current is not None and line.strip().startswith("- "):
            out[current].append(line.strip()[2:].strip().strip('"'))
    return out


def _dockerfile_instruction(text: str, name: str) -> list[str]:
    """The exec-form (JSON list) command of a Dockerfile instruction (``CMD``, or the
    ``CMD`` of ``HEALTHCHECK``), continuation lines joined."""
    joined = text.replace("\\\n", " ")
    line = next(ln for ln in joined.splitlines() if ln.startswith(name + " "))
    return json.loads(line[line.index("[") : line.rindex("]") + 1])


def test_docker_commands_parse_with_the_real_command_lines(monkeypatch) -> None:
    """The compose commands, the image's CMD and HEALTHCHECK parse with the real parsers and,
    with the image's configuration file, connect where the compose topology listens."""
    from schemas.cli import resolve_client_globals
    from service.node.settings import load_settings
    from sim_publisher.__main__ import build_parser as sim_parser
    from sim_publisher.__main__ import options_from_args
    from sim_publisher.networked import GLOBAL_OPTIONS as SIM_GLOBALS

    config = REPO / "docker" / "shapeloc.toml"
    env = {"SHAPELOC_CONFIG": str(config)}
    monkeypatch.setenv("SHAPELOC_CONFIG", str(config))
    text = (REPO / "docker" / "compose.yaml").read_text()
    assert "image: eclipse/zenoh:" in text and '"7447:7447/tcp"' in text
    assert "shapeloc-state:/var/lib/shapeloc" in text and "shapeloc-data:/data" in text
    cmds = _compose_commands(text)
    assert cmds["service"] == ["shapeloc-service"] and cmds["simulator"][:2] == [
        "shapeloc-sim",
        "run",
    ]
    svc = load_settings(cmds["service"][1:], env)
    assert svc.mode == "client" and svc.connect == ["tcp/router:7447"]
    assert svc.state_dir == Path("/var/lib/shapeloc")
    sim_args = sim_parser().parse_args(cmds["simulator"][1:])
    sim = options_from_args(sim_args)
    assert sim.robots == 2 and sim.maps == ["metric", "schematic"] and sim.timeout == 5.0
    resolve_client_globals(sim_args, SIM_GLOBALS)
    assert sim_args.mode is None and sim_args.connect == ["tcp/router:7447"]

    docker = (REPO / "docker" / "Dockerfile").read_text()
    assert docker.startswith("#") and "FROM python:3.11-slim" in docker
    assert "SHAPELOC_CONFIG=/etc/shapeloc/shapeloc.toml" in docker
    assert "COPY docker/shapeloc.toml /etc/shapeloc/shapeloc.toml" in docker
    cmd = _dockerfile_instruction(docker, "CMD")
    assert cmd == ["shapeloc-service"]
    health = _dockerfile_instruction(docker, "HEALTHCHECK")
    assert health[0] == "shapeloc" and health[-1] == "health"
    args = build_parser().parse_args(health[1:])
    resolve_client_globals(args, GLOBAL_OPTIONS)
    assert args.connect == ["tcp/router:7447"] and args.timeout == 5.0


def test_watch_prints_count_poses_then_exits(router, fake_service, capsys) -> None:
    import threading

    session, ep = router
    done = threading.Event()

    def publish() -> None:
        seq = 0
        while not done.is_set() and seq < 200:
            for rid in ("r1", "r2"):
                p = PoseMsg(
                    robot_id=rid,
                    seq=seq,
                    stamp=0.0,
                    pose=[0.5, 0.25, 0.0],
                    status="tracking",
                    score=0.5,
                    method="icp",
                    map_id="m",
                    latency_ms=1.0,
                )
                session.put(f"shapeloc/robots/{rid}/pose", encode(p))
            seq += 1
            done.wait(0.05)

    th = threading.Thread(target=publish)
    th.start()
    try:
        assert cli(["--connect", ep, "watch", "r2", "--count", "3", "--seconds", "10"]) == 0
        lines = capsys.readouterr().out.strip().splitlines()
        assert len(lines) == 3 and all(ln.startswith("r2: x=0.500 m y=0.250 m") for ln in lines)
        # --json: one pose message a line
        assert cli(["watch", "r1", "--count", "2", "--json", "--connect", ep]) == 0
        lines = capsys.readouterr().out.strip().splitlines()
        msgs = [json.loads(ln) for ln in lines]
        assert len(msgs) == 2 and all(m["robot_id"] == "r1" and m["method"] == "icp" for m in msgs)
    finally:
        done.set()
        th.join()


# ---------------------------------------------------------------- the CLI convention
# (schemas/cli.py): global options anywhere, one pose spelling, --json, defaults in the help,
# deprecated spellings warn.


def test_global_options_go_before_or_after_the_command() -> None:
    p = build_parser()
    before = p.parse_args(
        ["--connect", "tcp/h:1", "--prefix", "lab", "--timeout", "3", "pose", "r"]
    )
    after = p.parse_args(["pose", "r", "--connect", "tcp/h:1", "--prefix", "lab", "--timeout", "3"])
    for a in (before, after):
        assert (a.connect, a.prefix, a.timeout, a.robot_id) == (["tcp/h:1"], "lab", 3.0, "r")
    # nested commands take them too, and the value after the command wins
    a = p.parse_args(["--prefix", "one", "map", "get", "m", "--prefix", "two", "-v"])
    assert a.prefix == "two" and a.verbose and a.map_id == "m"
    # not given anywhere: None until resolved (so a config file can fill it)
    assert p.parse_args(["health"]).prefix is None


def test_initial_pose_takes_three_numbers_and_old_spellings_warn(capsys) -> None:
    p = build_parser()
    a = p.parse_args(["configure", "r", "--map", "m", "--initial-pose", "-1.5", "2", "-0.3"])
    assert a.initial_pose == [-1.5, 2.0, -0.3]
    assert capsys.readouterr().err == ""
    a = p.parse_args(["configure", "r", "--map", "m", "--initial-pose", "1,2,0.5"])
    assert a.initial_pose == [1.0, 2.0, 0.5]
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        len(err) == 1 and "warning: --initial-pose X,Y,THETA (comma form) is deprecated" in err[0]
    )
    a = p.parse_args(["configure", "r", "--map", "m", "--pose", "1", "2", "3"])
    assert a.initial_pose == [1.0, 2.0, 3.0]
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "shapeloc configure: warning: --pose is deprecated and will be removed in the next "
        "release; use --initial-pose X Y THETA"
    ]
    for bad in (["1", "2"], ["1", "2", "x"], ["1,2"], ["1", "2", "nan"]):
        with pytest.raises(SystemExit) as ei:
            p.parse_args(["configure", "r", "--map", "m", "--initial-pose", *bad])
        assert ei.value.code == 2
        assert "--initial-pose takes three finite numbers" in capsys.readouterr().err
    a = p.parse_args(
        ["configure", "r", "--map", "m", "--global", "--laser-offset", "0.3", "0", "0"]
    )
    assert a.laser_offset == [0.3, 0.0, 0.0] and a.global_localization


def test_help_shows_the_defaults() -> None:
    p = build_parser()
    text = " ".join(p.format_help().split())
    assert "(default: tcp/127.0.0.1:7447)" in text and "(default: shapeloc)" in text
    assert "(default: 2)" in text  # --timeout
    sub = " ".join(
        p._subparsers._group_actions[0].choices["configure"].format_help().split()  # type: ignore[union-attr]
    )
    assert "(default: shape)" in sub and "X Y THETA" in sub and "--pose" not in sub


def test_json_output_of_health_pose_maps(fake_service, capsys) -> None:
    assert cli(["health", "--connect", fake_service, "--json"]) == 0
    h = json.loads(capsys.readouterr().out)
    assert h["version"] == "1.2.3" and h["scans_processed"] == 42 and h["status"] == "ok"
    assert cli(["--connect", fake_service, "pose", "r1", "--json"]) == 0
    m = json.loads(capsys.readouterr().out)
    assert m["pose"] == [1.5, -2.25, 1.0] and m["robot_id"] == "r1" and m["seq"] == 9
    assert cli(["--connect", fake_service, "maps", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == []
    # errors stay one line on stderr with --json too
    assert cli(["--connect", fake_service, "pose", "nobody", "--json"]) == 1
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.strip() == "shapeloc: error: unknown robot 'nobody'"


def test_config_file_gives_the_connection(fake_service, tmp_path: Path, capsys) -> None:
    cfg = tmp_path / "shapeloc.toml"
    cfg.write_text(
        f'prefix = "shapeloc"\nstate_dir = "s"\n[client]\nconnect = ["{fake_service}"]\n'
    )
    assert cli(["--config", str(cfg), "health", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["version"] == "1.2.3"
    yml = tmp_path / "shapeloc.yaml"
    yml.write_text(f"client:\n  connect: {fake_service}\n  timeout: 0.5\n")
    assert cli(["health", "--config", str(yml)]) == 0
    assert "shapeloc 1.2.3" in capsys.readouterr().out
    # the command line wins over the file: a wrong prefix finds no service
    assert cli(["--config", str(cfg), "--prefix", "other", "--timeout", "0.3", "health"]) == 1
    assert "no shapeloc service answered on other/service/health" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[client]\nconect = []\n")
    assert cli(["--config", str(bad), "health"]) == 1
    assert "unknown key(s) in the 'client' table: conect" in capsys.readouterr().err


def test_config_file_from_the_environment(
    fake_service, tmp_path: Path, monkeypatch, capsys
) -> None:
    cfg = tmp_path / "c.yml"
    cfg.write_text(f"client:\n  connect: [{fake_service}]\n")
    monkeypatch.setenv("SHAPELOC_CONFIG", str(cfg))
    assert cli(["health"]) == 0
    assert "shapeloc 1.2.3" in capsys.readouterr().out
