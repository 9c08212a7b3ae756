"""Configuration of the localizer service: one model, three layers.

Precedence is defaults < environment (``SHAPELOC_*`` variables) < command-line flags. The same
:class:`ServiceSettings` instance drives the Zenoh session (:func:`zenoh_config`), the state
store and the worker pool. Times are seconds, sizes are counts of messages or bytes.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from service.errors import InvalidMessage

if TYPE_CHECKING:
    import zenoh

ENV_PREFIX = "SHAPELOC_"
_ID_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_LOG_LEVELS = ("debug", "info", "warning", "error")

log = logging.getLogger("shapeloc.service")


def _default_workers() -> int:
    return max(1, os.cpu_count() or 1)


class ServiceSettings(BaseModel):
    """Every option of ``shapeloc-service`` (see docs/service.md for the table).

    ``listen``/``connect`` are Zenoh endpoints such as ``tcp/127.0.0.1:7447``. ``robots`` is a
    Zenoh key expression over a single robot-id chunk selecting the robots this instance serves
    (``**``: all; ``a$*``: ids starting with ``a``); others are ignored silently. ``workers`` is
    the number of localisation worker processes; 0 computes in the service process itself.
    ``shard`` ``"hash"`` spreads the robots over the live instances of the prefix by
    rendezvous hashing of the robot id (membership from the instances' liveliness tokens,
    docs/cluster.md); ``"static"`` serves what ``robots`` matches.
    ``search_budget_ms`` is the per-scan work (reference ms) a robot's global search may take
    before the worker moves on (the search goes on with its next scan; 0: a whole search per
    scan). Default 50 (issue 13, docs/global.md "Why 50"): a search reaches its fix sooner
    than at 25 (drive bench, travel to the fix p50: held-out mit-csail metric map 6.6 -> 3.0
    m, fr079 floor plan 13.7 -> 9.9 m; mit-csail metric within 15 m 80 -> 100 %). A robot
    gets the whole budget only while it is alone on its worker, and half of it while other
    robots share the worker (a 50 ms searching scan takes up to ~100 ms of wall time at p99
    on a real metric map, too long for a robot queued behind it). Tracked robots do not
    queue behind searches at all with the search
    worker (below). With 20 tracked robots at 10 Hz on a 2-core machine, one robot searching
    back to back added +14 / +16 ms to their p99 at 25 and +5 ms at 12 on an earlier, slower
    machine, and +2.5 to +6.6 ms (median +3.4) at 25 and +3.5 to +4.4 ms at 15 on the
    ~1.6x faster one of 2026-11-24
    (``bench/bench_service.py --robots 20 --searching 0,1 --search-budget-ms 15``); a lower
    budget needs about twice the scans to a fix. ``search_worker`` (with
    ``workers`` >= 1) adds one worker process, niced by ``search_worker_nice``, that takes
    every robot while it searches (moved there with its localiser's state after the scan
    that started the search, and back to the least-loaded worker once it tracks again): a
    searching robot then never holds a worker that tracked robots wait for.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    mode: Literal["peer", "client", "router"] = "peer"
    zenoh_config: Path | None = None
    multicast_scouting: bool = False
    prefix: str = "shapeloc"
    state_dir: Path = Path("./state")
    robots: str = "**"
    instance_id: str | None = None
    workers: int = Field(default_factory=_default_workers, ge=0, le=64)
    pose_save_interval_s: float = Field(default=1.0, gt=0.0)
    reset_state: bool = False
    control_queue_size: int = Field(default=1024, ge=1)
    control_queue_bytes: int = Field(default=64 * 1024 * 1024, ge=1024)
    query_queue_size: int = Field(default=256, ge=1)
    intake_per_robot: int = Field(default=16, ge=1)
    intake_queue_bytes: int = Field(default=64 * 1024 * 1024, ge=64 * 1024)
    reconnect_max_ms: int = Field(default=1000, ge=100)
    max_robots: int = Field(default=1000, ge=1)
    worker_timeout_s: float = Field(default=30.0, gt=0.0)
    worker_start_timeout_s: float = Field(default=120.0, gt=0.0)
    search_budget_ms: float = Field(default=50.0, ge=0.0, le=10_000.0)
    search_worker: bool = True
    search_worker_nice: int = Field(default=19, ge=0, le=19)
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    shard: Literal["static", "hash"] = "static"
    takeover_grace_s: float = Field(default=0.25, ge=0.0, le=30.0)
    handover_delay_s: float = Field(default=0.2, ge=0.0, le=30.0)
    catchup_timeout_s: float = Field(default=2.0, gt=0.0, le=60.0)

    @property
    def reply_wait_s(self) -> float:
        """How long a thread waits for a worker's reply to a request it queued: the worker
        may first have to start (``worker_start_timeout_s``), then time out on a request
        before this one and be restarted (``worker_timeout_s`` each), plus 5 s of slack."""
        return self.worker_start_timeout_s + 2.0 * self.worker_timeout_s + 5.0

    @field_validator("prefix")
    @classmethod
    def _check_prefix(cls, v: str) -> str:
        chunks = v.split("/")
        if not v or any(not _ID_RE.match(c) for c in chunks):
            raise ValueError(
                f"prefix {v!r} must be '/'-separated chunks of 1-64 characters of [A-Za-z0-9_.-]"
            )
        return v

    @field_validator("robots")
    @classmethod
    def _check_robots(cls, v: str) -> str:
        if not v or "/" in v:
            raise ValueError(f"robots {v!r} must be a key expression over one chunk, e.g. '**'")
        import zenoh

        try:
            zenoh.KeyExpr(v)
        except Exception as e:  # zenoh raises ZError
            raise ValueError(f"robots {v!r} is not a valid Zenoh key expression: {e}") from e
        return v

    @field_validator("instance_id")
    @classmethod
    def _check_instance(cls, v: str | None) -> str | None:
        if v is not None and not _ID_RE.match(v):
            raise ValueError(f"instance_id {v!r} must be 1-64 characters of [A-Za-z0-9_.-]")
        return v

    @field_validator("listen", "connect")
    @classmethod
    def _check_endpoints(cls, v: list[str]) -> list[str]:
        for e in v:
            if "/" not in e or not e.split("/", 1)[1]:
                raise ValueError(f"endpoint {e!r} must look like 'tcp/127.0.0.1:7447'")
        return v

    @model_validator(mode="after")
    def _check_shard(self) -> ServiceSettings:
        if self.shard == "hash" and self.robots != "**":
            raise ValueError(
                f"shard 'hash' spreads every robot over the instances; robots must stay '**' "
                f"(got {self.robots!r})"
            )
        return self

    def effective_instance_id(self) -> str:
        """The liveliness id: ``instance_id`` or ``<hostname>-<pid>`` made key-safe."""
        if self.instance_id:
            return self.instance_id
        host = re.sub(r"[^A-Za-z0-9_.-]", "-", os.uname().nodename)[:40] or "host"
        return f"{host}-{os.getpid()}"

    def summary(self) -> dict[str, Any]:
        """JSON-friendly dict of the effective settings (for the start-up log)."""
        return json.loads(self.model_dump_json())


# Field -> how to parse an environment string.
def _env_value(name: str, raw: str) -> Any:
    field = ServiceSettings.model_fields[name]
    ann = str(field.annotation)
    if "list" in ann:
        raw = raw.strip()
        if raw.startswith("["):
            try:
                return json.loads(raw)
            except json.JSONDecodeError as e:
                raise InvalidMessage(f"{ENV_PREFIX}{name.upper()}: invalid JSON list: {e}") from e
        return [p.strip() for p in raw.split(",") if p.strip()]
    if "bool" in ann:
        low = raw.strip().lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise InvalidMessage(f"{ENV_PREFIX}{name.upper()}: expected a boolean, got {raw!r}")
    if "None" in ann and raw.strip() == "":
        return None
    return raw


def settings_from_env(environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Collect ``SHAPELOC_<FIELD>`` variables (upper-case field names) as raw overrides."""
    env = os.environ if environ is None else environ
    out: dict[str, Any] = {}
    for name in ServiceSettings.model_fields:
        key = ENV_PREFIX + name.upper()
        if key in env:
            out[name] = _env_value(name, env[key])
    return out


def build_parser() -> argparse.ArgumentParser:
    """The ``shapeloc-service`` argument parser (every default is ``None`` = not given)."""
    p = argparse.ArgumentParser(
        prog="shapeloc-service",
        description="Shape-based laser localisation service over Eclipse Zenoh.",
        argument_default=None,
    )
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help="Zenoh listen endpoint")
    p.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="Zenoh endpoint to connect to"
    )
    p.add_argument("--mode", choices=["peer", "client", "router"])
    p.add_argument("--zenoh-config", dest="zenoh_config", metavar="FILE", help="json5 file")
    p.add_argument(
        "--multicast-scouting",
        dest="multicast_scouting",
        action="store_const",
        const=True,
        help="enable Zenoh multicast scouting (off by default)",
    )
    p.add_argument("--prefix", help="key prefix (default shapeloc)")
    p.add_argument("--state-dir", dest="state_dir", metavar="DIR")
    p.add_argument("--robots", metavar="KEYEXPR", help="serve only robot ids matching this")
    p.add_argument("--instance-id", dest="instance_id")
    p.add_argument("--workers", type=int, help="worker processes (0: compute in-process)")
    p.add_argument(
        "--pose-save-interval",
        dest="pose_save_interval_s",
        type=float,
        metavar="S",
        help="seconds between saves of the last poses (default 1)",
    )
    p.add_argument(
        "--reset-state",
        dest="reset_state",
        action="store_const",
        const=True,
        help="if the state file is unreadable or invalid, move it aside "
        "(shapeloc.sqlite3.bad-<time>) and start with no maps and no robots",
    )
    p.add_argument(
        "--shard",
        choices=["static", "hash"],
        help="static: serve the robots --robots matches; hash: spread the robots over the "
        "live instances of the prefix (rendezvous hash of the robot id, docs/cluster.md)",
    )
    p.add_argument(
        "--takeover-grace",
        dest="takeover_grace_s",
        type=float,
        metavar="S",
        help="with --shard hash: seconds between an instance's liveliness token vanishing "
        "and taking over its robots (default 0.25)",
    )
    p.add_argument("--max-robots", dest="max_robots", type=int)
    p.add_argument(
        "--no-search-worker",
        dest="search_worker",
        action="store_false",
        default=None,
        help="searching robots stay on their worker (no extra, lower-priority search worker)",
    )
    p.add_argument(
        "--search-budget-ms",
        dest="search_budget_ms",
        type=float,
        help="per-scan work of a global search (reference ms; 0: a whole search per scan)",
    )
    p.add_argument("--log-level", dest="log_level", choices=list(_LOG_LEVELS))
    return p


def load_settings(
    argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None
) -> ServiceSettings:
    """Defaults, then environment, then CLI flags. Raises :class:`InvalidMessage` on bad values
    (argparse itself exits with status 2 on unknown flags)."""
    values = settings_from_env(environ)
    if argv is not None:
        ns = build_parser().parse_args(list(argv))
        values.update({k: v for k, v in vars(ns).items() if v is not None})
    try:
        return ServiceSettings(**values)
    except ValidationError as e:
        errs = "; ".join(f"{'.'.join(map(str, x['loc']))}: {x['msg']}" for x in e.errors())
        raise InvalidMessage(f"invalid service settings: {errs}") from e


def zenoh_config(settings: ServiceSettings) -> zenoh.Config:
    """Build the Zenoh session configuration.

    Starts from ``settings.zenoh_config`` (json5 file: TLS, mutual TLS, user/password
    authentication, access control, ...) if given, else an empty config. Mode, listen and
    connect endpoints from the settings are applied on top, except that with a file only the
    options explicitly set (env/CLI) override it. Multicast scouting is switched off unless
    ``multicast_scouting`` is true; ``scouting/delay`` is 0 so open returns at once. Unless
    the file sets ``connect/retry``, lost connections are retried every 250 ms doubling up to
    ``reconnect_max_ms`` (Zenoh's own default backs off to 4 s), so the service is back within
    about a second of its router.
    """
    import zenoh

    explicit = settings.model_fields_set
    file_conf: dict[str, Any] = {}
    if settings.zenoh_config is not None:
        try:
            conf = zenoh.Config.from_file(str(settings.zenoh_config))
            file_conf = json.loads(str(conf))
        except Exception as e:
            raise InvalidMessage(f"zenoh config {settings.zenoh_config}: {e}") from e
        base_given = True
    else:
        conf = zenoh.Config()
        base_given = False

    def apply(field: str) -> bool:
        return not base_given or field in explicit

    if apply("mode"):
        conf.insert_json5("mode", json.dumps(settings.mode))
    if apply("listen") and settings.mode != "client":
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if apply("connect"):
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if not (file_conf.get("connect") or {}).get("retry"):
        retry = {
            "period_init_ms": min(250, settings.reconnect_max_ms),
            "period_max_ms": settings.reconnect_max_ms,
            "period_increase_factor": 2,
        }
        conf.insert_json5("connect/retry", json.dumps(retry))
    conf.insert_json5(
        "scouting/multicast/enabled", "true" if settings.multicast_scouting else "false"
    )
    conf.insert_json5("scouting/delay", "0")
    return conf


def security_summary(conf: zenoh.Config) -> str:
    """One line naming the wire security a Zenoh config switches on (TLS listeners, mutual
    TLS, user/password, access control), without any secret, for the start-up log."""
    try:
        d = json.loads(str(conf))
    except ValueError:
        return "zenoh config not inspectable"
    eps = (d.get("listen") or {}).get("endpoints") or []
    if isinstance(eps, dict):
        eps = [e for v in eps.values() for e in (v or [])]
    link = ((d.get("transport") or {}).get("link") or {}).get("tls") or {}
    auth = ((d.get("transport") or {}).get("auth") or {}).get("usrpwd") or {}
    acl = d.get("access_control") or {}
    parts = [
        f"mode {d.get('mode') or 'peer'}",
        f"listen {list(eps)}",
        "TLS listener" if link.get("listen_certificate") else "no TLS certificate",
        "mutual TLS" if link.get("enable_mtls") else "no mutual TLS",
        "user/password dictionary" if auth.get("dictionary_file") else "no user/password",
    ]
    if acl.get("enabled"):
        parts.append(
            f"access control on (default {acl.get('default_permission')}, "
            f"{len(acl.get('policies') or [])} policies)"
        )
    else:
        parts.append("access control off")
    return ", ".join(parts)
