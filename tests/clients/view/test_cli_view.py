"""``shapeloc view`` and ``shapeloc record`` on the command line: their options, the shared
global options, and one-line errors (exit 1) for what they cannot do. Running them against a
service: tests/clients/view/test_view_browser.py and tests/integration/test_record_replay.py
(through ``python -m clients.view`` / ``clients.record``, the same commands)."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from clients.__main__ import build_parser, cli

pytestmark = pytest.mark.timeout(60)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_view_and_record_take_their_options_and_the_global_ones() -> None:
    a = build_parser().parse_args(
        ["view", "--port", "0", "--frame-rate", "5", "--connect", "tcp/127.0.0.1:1"]
    )
    assert (a.command, a.port, a.frame_rate, a.host) == ("view", 0, 5.0, "127.0.0.1")
    assert a.connect == ["tcp/127.0.0.1:1"]
    a = build_parser().parse_args(
        ["--prefix", "lab", "record", "x.mcap", "--robot", "a", "--robot", "b", "--seconds", "3"]
    )
    assert (a.file, a.robots, a.seconds, a.prefix, a.json) == (
        "x.mcap",
        ["a", "b"],
        3.0,
        "lab",
        False,
    )


def test_a_frame_rate_below_one_is_refused(capsys) -> None:
    assert cli(["view", "--frame-rate", "0.5"]) == 1
    assert "--frame-rate must be >= 1" in capsys.readouterr().err


def test_nothing_listening_is_one_line_and_no_file(capsys, tmp_path: Path) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "run.mcap"
    assert cli(["record", str(out), "--connect", ep]) == 1
    err = capsys.readouterr().err
    assert err.startswith("shapeloc: error: cannot reach") and err.count("\n") == 1
    assert not out.exists()
    assert cli(["view", "--connect", ep, "--port", "0"]) == 1
    assert "cannot reach" in capsys.readouterr().err


def test_a_busy_port_is_one_line(capsys) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        assert cli(["view", "--port", str(port)]) == 1
    assert f"cannot serve the view on 127.0.0.1:{port}" in capsys.readouterr().err
