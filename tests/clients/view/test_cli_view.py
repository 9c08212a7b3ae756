"""``shapeloc view`` and ``shapeloc record`` on the command line: their options, the shared
global options, and one-line errors (exit 1) for what they cannot do. Running them against a
service: tests/clients/view/test_view_browser.py and tests/integration/test_record_replay.py
(through ``python -m clients.view`` / ``clients.record``, the same commands)."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from clients.__main__ import build_parser, cli
from clients.view import DEFAULT_NICE

REPO = Path(__file__).resolve().parents[3]

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


def test_a_nice_outside_0_to_19_is_refused(capsys) -> None:
    assert build_parser().parse_args(["view"]).nice == DEFAULT_NICE
    assert cli(["view", "--nice", "-1"]) == 1
    assert "--nice must be in 0..19" in capsys.readouterr().err


def _nice_of_threads(pid: int) -> dict[int, int]:
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            # field 19 of stat is the niceness; the command name (field 2) may hold spaces
            stat = (task / "stat").read_text()
            out[int(task.name)] = int(stat.rsplit(")", 1)[1].split()[16])
    return out


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("nice", [None, 7, 0])
def test_the_view_process_lowers_its_priority_on_every_thread(tmp_path: Path, nice) -> None:
    from clients.session import zenoh_config

    ep = f"tcp/127.0.0.1:{free_port()}"
    args = ["--connect", ep, "--port", "0"] + ([] if nice is None else ["--nice", str(nice)])
    base = os.getpriority(os.PRIO_PROCESS, 0)
    want = min(19, base + (DEFAULT_NICE if nice is None else nice))
    log = tmp_path / "view.log"
    with zenoh.open(zenoh_config("router", listen=[ep])), open(log, "wb") as f:
        proc = subprocess.Popen(
            [sys.executable, "-m", "clients.view", *args],
            cwd=REPO,
            stdout=f,
            stderr=subprocess.STDOUT,
        )
        try:
            end = time.monotonic() + 30
            while "shapeloc view: http://" not in log.read_text(errors="replace"):
                assert proc.poll() is None and time.monotonic() < end, log.read_text()
                time.sleep(0.1)
            threads = _nice_of_threads(proc.pid)
        finally:
            proc.terminate()
            proc.wait(15)
    # Zenoh's runtime threads and the asyncio executor's included
    assert len(threads) > 3 and set(threads.values()) == {want}, threads
