"""Settings precedence (defaults < SHAPELOC_* environment < CLI) and the Zenoh config built
from them. Pure, no network; runs in well under a second."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from service.errors import InvalidMessage
from service.node.settings import ServiceSettings, load_settings, zenoh_config


def _get(conf: object, key: str) -> object:
    """A config value as a Python object (``get_json`` returns JSON text)."""
    return json.loads(conf.get_json(key))  # type: ignore[attr-defined]


def test_defaults() -> None:
    s = load_settings([], {})
    assert s.listen == ["tcp/127.0.0.1:7447"]
    assert s.connect == []
    assert s.mode == "peer"
    assert s.prefix == "shapeloc"
    assert s.robots == "**"
    assert s.state_dir == Path("./state")
    assert s.workers == max(1, os.cpu_count() or 1)
    assert s.zenoh_config is None
    assert s.multicast_scouting is False


def test_env_overrides_defaults() -> None:
    env = {
        "SHAPELOC_PREFIX": "lab/a",
        "SHAPELOC_LISTEN": "tcp/127.0.0.1:1000, tcp/127.0.0.1:1001",
        "SHAPELOC_WORKERS": "3",
        "SHAPELOC_MULTICAST_SCOUTING": "yes",
        "SHAPELOC_POSE_SAVE_INTERVAL_S": "0.25",
        "UNRELATED": "x",
    }
    s = load_settings([], env)
    assert s.prefix == "lab/a"
    assert s.listen == ["tcp/127.0.0.1:1000", "tcp/127.0.0.1:1001"]
    assert s.workers == 3
    assert s.multicast_scouting is True
    assert s.pose_save_interval_s == 0.25


def test_a_queued_request_waits_for_a_worker_start_and_a_timed_out_request_before_it() -> None:
    s = load_settings(
        [], {"SHAPELOC_WORKER_START_TIMEOUT_S": "60", "SHAPELOC_WORKER_TIMEOUT_S": "10"}
    )
    assert s.worker_start_timeout_s == 60.0
    assert s.reply_wait_s == 60.0 + 2 * 10.0 + 5.0


def test_env_json_list() -> None:
    s = load_settings([], {"SHAPELOC_CONNECT": '["tcp/127.0.0.1:5", "tcp/127.0.0.1:6"]'})
    assert s.connect == ["tcp/127.0.0.1:5", "tcp/127.0.0.1:6"]


def test_cli_overrides_env() -> None:
    env = {"SHAPELOC_PREFIX": "fromenv", "SHAPELOC_WORKERS": "3", "SHAPELOC_MODE": "router"}
    s = load_settings(
        ["--prefix", "fromcli", "--listen", "tcp/127.0.0.1:9", "--listen", "tcp/127.0.0.1:10"],
        env,
    )
    assert s.prefix == "fromcli"
    assert s.listen == ["tcp/127.0.0.1:9", "tcp/127.0.0.1:10"]
    assert s.workers == 3  # env value survives where the CLI is silent
    assert s.mode == "router"
    s2 = load_settings(["--workers", "0", "--mode", "client", "--robots", "r$*"], env)
    assert (s2.workers, s2.mode, s2.robots) == (0, "client", "r$*")


@pytest.mark.parametrize(
    ("argv", "env", "needle"),
    [
        (["--prefix", "bad prefix"], {}, "prefix"),
        (["--prefix", "a//b"], {}, "prefix"),
        (["--robots", "a*"], {}, "robots"),
        (["--robots", "a/b"], {}, "robots"),
        (["--workers", "-1"], {}, "workers"),
        (["--instance-id", "has space"], {}, "instance_id"),
        (["--listen", "nowhere"], {}, "listen"),
        ([], {"SHAPELOC_MULTICAST_SCOUTING": "maybe"}, "MULTICAST"),
        ([], {"SHAPELOC_WORKERS": "many"}, "workers"),
    ],
)
def test_invalid_values_are_named(argv: list[str], env: dict[str, str], needle: str) -> None:
    with pytest.raises(InvalidMessage, match=needle):
        load_settings(argv, env)


def test_unknown_flag_exits_2() -> None:
    with pytest.raises(SystemExit) as e:
        load_settings(["--no-such-flag"], {})
    assert e.value.code == 2


def test_zenoh_config_loopback_defaults() -> None:
    s = load_settings(["--listen", "tcp/127.0.0.1:7001", "--connect", "tcp/127.0.0.1:7002"], {})
    c = zenoh_config(s)
    assert _get(c, "mode") == "peer"
    assert _get(c, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert _get(c, "connect/endpoints") == ["tcp/127.0.0.1:7002"]
    assert _get(c, "scouting/multicast/enabled") is False
    assert _get(c, "scouting/delay") == 0


def test_zenoh_config_client_mode_does_not_listen() -> None:
    s = load_settings(["--mode", "client", "--connect", "tcp/127.0.0.1:7002"], {})
    c = zenoh_config(s)
    assert _get(c, "mode") == "client"
    assert _get(c, "listen/endpoints") != ["tcp/127.0.0.1:7447"]


def test_zenoh_config_file_merged(tmp_path: Path) -> None:
    f = tmp_path / "z.json5"
    f.write_text(
        "// comment allowed in json5\n"
        + json.dumps({"mode": "router", "listen": {"endpoints": ["tcp/127.0.0.1:7100"]}})
    )
    c = zenoh_config(load_settings(["--zenoh-config", str(f)], {}))
    assert _get(c, "mode") == "router"  # file wins over defaults
    assert _get(c, "listen/endpoints") == ["tcp/127.0.0.1:7100"]
    assert _get(c, "scouting/multicast/enabled") is False
    c2 = zenoh_config(
        load_settings(["--zenoh-config", str(f), "--listen", "tcp/127.0.0.1:7200"], {})
    )
    assert _get(c2, "listen/endpoints") == ["tcp/127.0.0.1:7200"]  # explicit flag wins
    assert _get(c2, "mode") == "router"


def test_zenoh_config_bad_file(tmp_path: Path) -> None:
    f = tmp_path / "bad.json5"
    f.write_text("{ this is not json5")
    with pytest.raises(InvalidMessage, match=r"bad\.json5"):
        zenoh_config(load_settings(["--zenoh-config", str(f)], {}))


def test_instance_id() -> None:
    assert ServiceSettings(instance_id="svc-1").effective_instance_id() == "svc-1"
    auto = ServiceSettings().effective_instance_id()
    assert auto.endswith(f"-{os.getpid()}")
    assert all(ch.isalnum() or ch in "_.-" for ch in auto)
