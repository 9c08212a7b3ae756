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
    # a peer waits for its connect endpoints: a query sent before the link is up is lost
    assert _get(c, "scouting/delay") is None


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


# ---------------------------------------------------------------- configuration file
def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_precedence_defaults_file_env_flags(tmp_path: Path) -> None:
    """defaults < configuration file < environment < command line, key by key."""
    f = _write(
        tmp_path,
        "svc.toml",
        'prefix = "fromfile"\nworkers = 3\nsearch_budget_ms = 40\nmode = "client"\n'
        'connect = ["tcp/127.0.0.1:5"]\n',
    )
    env = {"SHAPELOC_WORKERS": "4", "SHAPELOC_SEARCH_BUDGET_MS": "30"}
    s = load_settings(["--config", str(f), "--search-budget-ms", "20"], env)
    assert s.prefix == "fromfile"  # file over default
    assert s.mode == "client" and s.connect == ["tcp/127.0.0.1:5"]
    assert s.workers == 4  # environment over file
    assert s.search_budget_ms == 20.0  # flag over environment
    assert s.max_robots == 1000  # default where nobody says
    assert s.config == f


def test_yaml_file_and_the_config_environment_variable(tmp_path: Path) -> None:
    f = _write(tmp_path, "svc.yaml", "prefix: lab/a\nlisten:\n  - tcp/127.0.0.1:7100\n")
    s = load_settings([], {"SHAPELOC_CONFIG": str(f)})
    assert s.prefix == "lab/a" and s.listen == ["tcp/127.0.0.1:7100"] and s.config == f
    # --config wins over SHAPELOC_CONFIG
    g = _write(tmp_path, "other.yml", "prefix: other\n")
    assert load_settings(["--config", str(g)], {"SHAPELOC_CONFIG": str(f)}).prefix == "other"


def test_file_paths_are_relative_to_the_file(tmp_path: Path) -> None:
    sub = tmp_path / "etc"
    sub.mkdir()
    f = _write(sub, "svc.toml", 'state_dir = "state"\nzenoh_config = "/abs/z.json5"\n')
    s = load_settings(["--config", str(f)], {})
    assert s.state_dir == sub / "state"
    assert s.zenoh_config == Path("/abs/z.json5")


def test_the_clients_table_is_ignored_by_the_service(tmp_path: Path) -> None:
    f = _write(tmp_path, "all.toml", 'prefix = "p"\n[client]\nconnect = ["tcp/h:1"]\n')
    assert load_settings(["--config", str(f)], {}).prefix == "p"


@pytest.mark.parametrize(
    ("name", "text", "needle"),
    [
        ("a.toml", "wokers = 2\n", "unknown setting.*wokers"),
        ("b.toml", "workers = [\n", "bad TOML"),
        ("c.yaml", "- 1\n- 2\n", "mapping"),
        ("d.json", "{}", r"\.toml, \.yaml or \.yml"),
        ("e.toml", "workers = -1\n", r"workers \(.*e\.toml\)"),
    ],
)
def test_bad_files_are_named(tmp_path: Path, name: str, text: str, needle: str) -> None:
    f = _write(tmp_path, name, text)
    with pytest.raises(InvalidMessage, match=needle):
        load_settings(["--config", str(f)], {})


def test_a_missing_file_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(InvalidMessage, match="unreadable"):
        load_settings(["--config", str(tmp_path / "nope.toml")], {})


def test_errors_name_where_the_bad_value_came_from() -> None:
    with pytest.raises(InvalidMessage, match=r"workers \(SHAPELOC_WORKERS\)"):
        load_settings([], {"SHAPELOC_WORKERS": "-3"})
    with pytest.raises(InvalidMessage, match=r"workers \(flag --workers\)"):
        load_settings(["--workers", "-3"], {})


def test_verbose_means_debug_unless_log_level_is_given() -> None:
    assert load_settings(["-v"], {}).log_level == "debug"
    assert load_settings(["-v", "--log-level", "warning"], {}).log_level == "warning"
    assert load_settings([], {}).log_level == "info"


def test_help_shows_every_default(capsys) -> None:
    from service.node.settings import build_parser

    text = build_parser().format_help()
    for needle in (
        "(default: tcp/127.0.0.1:7447)",
        "(default: peer)",
        "(default: shapeloc)",
        "(default: ./state)",
        "(default: 50.0)",
        "(default: 1000)",
        "(default: number of cores",
        "worker_timeout_s (default: 30.0)",  # settings without a flag: listed in the epilog
        "Precedence: defaults < configuration file < environment",
    ):
        assert needle in " ".join(text.split()), needle
    # every flag of a setting has a description and a default in its help
    for action in build_parser()._actions:
        if action.dest in ServiceSettings.model_fields and action.dest != "config":
            assert action.help and "default" in action.help, action.dest


def test_every_setting_has_a_description_for_users() -> None:
    for name, field in ServiceSettings.model_fields.items():
        assert field.description and len(field.description) > 30, name


def test_summary_hides_secret_fields(monkeypatch) -> None:
    from service.node import settings as mod

    s = load_settings(["--prefix", "p"], {})
    assert s.summary()["prefix"] == "p"
    monkeypatch.setattr(mod, "SECRET_FIELDS", frozenset({"prefix"}))
    assert s.summary()["prefix"] == "***"


def test_direct_construction_reads_the_environment(monkeypatch) -> None:
    monkeypatch.setenv("SHAPELOC_MAX_ROBOTS", "7")
    assert ServiceSettings().max_robots == 7
    assert ServiceSettings(max_robots=9).max_robots == 9
