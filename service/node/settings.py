"""Configuration of the localizer service: one model, four layers.

Precedence: built-in defaults < configuration file (``--config FILE`` or ``SHAPELOC_CONFIG``;
TOML or YAML, one key per setting) < environment (``SHAPELOC_<NAME>``, the upper-case field
name, e.g. ``SHAPELOC_STATE_DIR``) < command-line flags. :class:`ServiceSettings` is a
pydantic-settings model: every field is one setting, its ``description`` is the text of the
configuration reference and of ``--help``, and a :class:`Flag` in its annotation gives it a
command-line flag (fields without one are set by the file or the environment only). To add a
setting, add one field here (with a :class:`Flag` if it deserves one); :func:`build_parser`,
:func:`load_settings`, the start-up log and the help pick it up.

The connection options (``--listen``, ``--connect``, ``--mode``, ``--zenoh-config``,
``--prefix``, ``--config``, ``-v``) are the global options of every shapeloc program
(:mod:`schemas.cli`). The same :class:`ServiceSettings` instance drives the Zenoh session
(:func:`zenoh_config`), the state store and the worker pool. Times are seconds, sizes are
counts of messages or bytes.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, get_args, get_origin

from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    SettingsError,
)

from schemas.cli import (
    CONFIG_ENV,
    GlobalOptions,
    HelpFormatter,
    add_global_options,
    config_path,
    read_config_file,
)
from service.errors import InvalidMessage

if TYPE_CHECKING:
    import zenoh

ENV_PREFIX = "SHAPELOC_"
_ID_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_LOG_LEVELS = ("debug", "info", "warning", "error")
#: Fields whose value never goes into the start-up log (none holds a secret today; a future
#: password or token field is added here and shows as "***").
SECRET_FIELDS: frozenset[str] = frozenset()
#: Configuration-file keys the service ignores: the clients' table (schemas.cli).
IGNORED_FILE_KEYS = frozenset({"client"})

log = logging.getLogger("shapeloc.service")


def _default_workers() -> int:
    """One per core."""
    return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class Flag:
    """The command-line flag of a :class:`ServiceSettings` field.

    ``name``: the flag (``--state-dir``); ``metavar``: the value's placeholder; ``const``:
    for a boolean field, the value the bare flag sets (``True`` for ``--multicast-scouting``,
    ``False`` for ``--no-search-worker``); ``repeat``: a list field whose flag may be given
    several times. Fields without a ``Flag`` are set by the configuration file or the
    environment only.
    """

    name: str
    metavar: str | None = None
    const: bool | None = None
    repeat: bool = False


def flag_of(field: Any) -> Flag | None:
    """The :class:`Flag` of a :class:`ServiceSettings` field, or ``None``."""
    return next((m for m in field.metadata if isinstance(m, Flag)), None)


#: Endpoint lists: from the environment as a JSON list or comma-separated (``NoDecode``: the
#: validator below splits them, not pydantic-settings' JSON decoding).
Endpoints = Annotated[list[str], NoDecode]


class ServiceSettings(BaseSettings):
    """Every setting of ``shapeloc-service`` (the configuration reference is generated from
    the field descriptions). Build it with :func:`load_settings` (command line, environment
    and configuration file) or directly in Python (keyword arguments, then the environment)."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_ignore_empty=True,
        extra="forbid",
        validate_assignment=True,
        validate_default=True,
    )

    # -- connection (the global options of schemas.cli; flags added by build_parser)
    listen: Endpoints = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"],
        description="Zenoh endpoints the service listens on (ignored in client mode). The "
        "default accepts clients on this machine only; use tcp/0.0.0.0:7447 to accept robots "
        "on the network.",
    )
    connect: Endpoints = Field(
        default_factory=list,
        description="Zenoh endpoints to connect to: a router, or other services and robots. "
        "Empty by default (the service waits for others to connect to it).",
    )
    mode: Literal["peer", "client", "router"] = Field(
        default="peer",
        description="Zenoh session mode. peer (default) lets clients connect to the service "
        "directly; client when a Zenoh router is the only process that listens "
        "(deployments, docker/compose.yaml).",
    )
    zenoh_config: Path | None = Field(
        default=None,
        description="Zenoh JSON5 configuration file used as the base (TLS, mutual TLS, "
        "user/password, access control: docs/security.md). mode, listen and connect, when "
        "set by a flag, the environment or the configuration file, replace its values.",
    )
    prefix: str = Field(
        default="shapeloc",
        description="Key prefix of every shapeloc key ('/'-separated chunks of "
        "[A-Za-z0-9_.-]). Change it to run several independent deployments on one Zenoh "
        "network; clients need the same prefix.",
    )
    config: Path | None = Field(
        default=None,
        description="The configuration file these settings were read from (TOML or YAML, one "
        "key per setting; relative paths in it are relative to its directory). Set by "
        f"--config or {CONFIG_ENV}; not a key of the file itself.",
    )
    multicast_scouting: Annotated[bool, Flag("--multicast-scouting", const=True)] = Field(
        default=False,
        description="Zenoh multicast discovery. Off by default: every process names its peers "
        "with explicit endpoints, which works across subnets and in containers; turn it on "
        "only on a trusted LAN where robots should find the service by themselves.",
    )
    reconnect_max_ms: int = Field(
        default=1000,
        ge=100,
        description="Longest wait (ms) between attempts to reconnect to a lost router or peer: "
        "attempts start at 250 ms and double up to this, so the service is back within about "
        "a second of its router (Zenoh's own default backs off to 4 s). Ignored when the "
        "--zenoh-config file sets connect/retry.",
    )

    # -- what this instance serves and where it keeps its state
    state_dir: Annotated[Path, Flag("--state-dir", "DIR")] = Field(
        default=Path("./state"),
        description="Directory of the persistent state (maps, robot configurations, last "
        "poses; created if missing). Keep it on a volume that survives restarts; two services "
        "cannot share one.",
    )
    reset_state: Annotated[bool, Flag("--reset-state", const=True)] = Field(
        default=False,
        description="If the state file is unreadable or invalid, move it aside "
        "(shapeloc.sqlite3.bad-<time>) and start with no maps and no robots, instead of "
        "refusing to start. Off by default so that no state is ever lost silently.",
    )
    robots: Annotated[str, Flag("--robots", "KEYEXPR")] = Field(
        default="**",
        description="Serve only robot ids matching this one-chunk Zenoh key expression "
        "('**': all; 'a$*': ids starting with a). Others are ignored silently. For static "
        "shards of several instances: their expressions should cover every id exactly once "
        "(docs/cluster.md).",
    )
    shard: Annotated[Literal["static", "hash"], Flag("--shard")] = Field(
        default="static",
        description="static: serve the robots --robots matches. hash: spread the robots over "
        "the live instances of the prefix by rendezvous hashing of the robot id and take over "
        "a dead instance's robots (docs/cluster.md); needs --robots '**'.",
    )
    instance_id: Annotated[str | None, Flag("--instance-id", "ID")] = Field(
        default=None,
        description="Name of this instance (its liveliness token and health); set it to keep "
        "one name across restarts.",
    )
    max_robots: Annotated[int, Flag("--max-robots", "N")] = Field(
        default=1000,
        ge=1,
        description="Robot configurations beyond this many are refused (a notice on "
        "<prefix>/errors): a bound on memory against a misbehaving publisher.",
    )
    pose_save_interval_s: Annotated[float, Flag("--pose-save-interval", "S")] = Field(
        default=1.0,
        gt=0.0,
        description="Seconds between saves of the robots' last poses (and on shutdown). After "
        "a kill -9 at most this much of poses is lost; raise it on slow storage.",
    )

    # -- compute
    workers: Annotated[int, Flag("--workers", "N")] = Field(
        default_factory=_default_workers,
        ge=0,
        le=64,
        description="Localisation worker processes: one per core by default, since the shape "
        "method is CPU-bound and one process saturates one core. 0 computes in the service "
        "process itself (debugging, tests).",
    )
    search_budget_ms: Annotated[float, Flag("--search-budget-ms", "MS")] = Field(
        default=50.0,
        ge=0.0,
        le=10_000.0,
        description="Per-scan work of a robot's global search, in reference ms of a "
        "deterministic work model; the search goes on with the robot's next scans. A robot "
        "alone on its worker gets all of it, half while others share the worker. 50 fixes "
        "sooner than 25 (drive bench: held-out mit-csail metric map 6.6 -> 3.0 m of travel to "
        "the fix) at a cost to the other robots' latency of a few ms at p99 "
        "(docs/decisions/0005-search-budget-and-work-model.md). "
        "0: a whole search on one scan.",
    )
    search_worker: Annotated[bool, Flag("--no-search-worker", const=False)] = Field(
        default=True,
        description="With worker processes, one more worker takes every robot while it "
        "searches (lost or without an initial pose), at low priority, so searching robots "
        "never hold a worker that tracked robots wait for. The flag turns it off: searching "
        "robots then stay on their worker.",
    )
    search_worker_nice: int = Field(
        default=19,
        ge=0,
        le=19,
        description="Nice level of the search worker (batch scheduling class). 19 keeps "
        "searches out of the tracked robots' way; lower it where the service shares its cores "
        "with other busy work, or searches may starve (docs/decisions/0006-search-worker.md).",
    )
    worker_timeout_s: float = Field(
        default=30.0,
        gt=0.0,
        description="A worker slower than this on one request is killed and restarted (the "
        "scan in flight gets a notice). Far above any scan's time; a guard against a hang.",
    )
    worker_start_timeout_s: float = Field(
        default=120.0,
        gt=0.0,
        description="A worker process that has not started (interpreter, imports and, for a "
        "tracking worker, the warm-up: each method run once) within this is killed and "
        "restarted; its start-up is not charged to worker_timeout_s. Large because a loaded "
        "machine can take a minute to import numpy, scipy and numba.",
    )
    index_timeout_s: float = Field(
        default=600.0,
        gt=0.0,
        description="The search worker's limit for building a map's view index of global "
        "localisation (after each map put; 3.6 s for the office, 26 s for a 160-polyline "
        "building on a loaded 2-core machine); beyond it the worker is restarted and the "
        "first search builds the index instead.",
    )

    # -- queues and limits against floods
    control_queue_size: int = Field(
        default=1024,
        ge=1,
        description="Map and configuration messages waiting to be applied; beyond this "
        "(or control_queue_bytes) new ones are rejected with a notice.",
    )
    control_queue_bytes: int = Field(
        default=64 * 1024 * 1024,
        ge=1024,
        description="Bytes of map and configuration messages waiting to be applied "
        "(default 64 MiB: four maps at the 16 MiB wire limit).",
    )
    query_queue_size: int = Field(
        default=256,
        ge=1,
        description="Pending get queries (health, pose, maps); beyond this they are dropped "
        "and the getter sees no reply.",
    )
    intake_per_robot: int = Field(
        default=16,
        ge=2,
        description="Received scans of one robot waiting for validation before its backlog is "
        "compacted (the newest valid scan kept: latest wins).",
    )
    intake_queue_bytes: int = Field(
        default=64 * 1024 * 1024,
        ge=64 * 1024,
        description="Bytes of received scans of all robots waiting for validation before a "
        "robot's backlog is compacted.",
    )

    # -- several instances on one prefix (docs/cluster.md)
    takeover_grace_s: Annotated[float, Flag("--takeover-grace", "S")] = Field(
        default=0.25,
        ge=0.0,
        le=30.0,
        description="With --shard hash: seconds between an instance's liveliness token "
        "vanishing and taking over its robots (rides out a short network blip).",
    )
    handover_delay_s: float = Field(
        default=0.2,
        ge=0.0,
        le=30.0,
        description="With --shard hash: a joining instance takes its share of the robots this "
        "long after declaring its token.",
    )
    catchup_timeout_s: float = Field(
        default=2.0,
        gt=0.0,
        le=60.0,
        description="How long a (re)starting instance of a cluster waits for the others' "
        "state before serving.",
    )

    # -- ROS 2 (docs/ros2.md)
    ros2: Annotated[bool, Flag("--ros2", const=True)] = Field(
        default=False,
        description="Also speak ROS 2 on the service's Zenoh session (rmw_zenoh's keys, as "
        "nav2's AMCL looks to a ROS 2 robot): scan/tf/tf_static in, amcl_pose and map -> odom "
        "out, one namespace per robot (service/ros2).",
    )
    ros_domain_id: Annotated[int | None, Flag("--ros-domain-id", "N")] = Field(
        default=None,
        ge=0,
        description="ROS domain id of the ROS 2 front (unset: ROS_DOMAIN_ID, else 0).",
    )
    ros_options: dict[str, Any] = Field(
        default_factory=dict,
        description="The ROS 2 front's other options, by their names in "
        "service.ros2.options.Ros2Options (global_frame_id, odom_frame_id, base_frame_id, "
        "transform_tolerance, default_robot_id, method, global_map_id, import_maps, ...).",
    )

    # -- logging
    log_level: Annotated[Literal["debug", "info", "warning", "error"], Flag("--log-level")] = Field(
        default="info",
        description="Level of the service's log on standard error (-v: debug). Zenoh's "
        "own log goes to stdout at warn (RUST_LOG overrides).",
    )

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Highest first: keyword arguments (the command line), the environment, the
        configuration file."""
        ctx = _LOADING.get()
        env: PydanticBaseSettingsSource = env_settings
        if ctx is not None and ctx.environ is not None:
            env = _MappingEnvSource(settings_cls, ctx.environ)
        return (init_settings, env, _ConfigFileSource(settings_cls, init_settings, env))

    @property
    def reply_wait_s(self) -> float:
        """How long a thread waits for a worker's reply to a request it queued: the worker
        may first have to start (``worker_start_timeout_s``), then time out on a request
        before this one and be restarted (``worker_timeout_s`` each), plus 5 s of slack."""
        return self.worker_start_timeout_s + 2.0 * self.worker_timeout_s + 5.0

    @field_validator("listen", "connect", mode="before")
    @classmethod
    def _split_endpoints(cls, v: Any) -> Any:
        if isinstance(v, str):
            text = v.strip()
            if text.startswith("["):
                try:
                    return json.loads(text)
                except json.JSONDecodeError as e:
                    raise ValueError(f"invalid JSON list: {e}") from e
            return [p.strip() for p in text.split(",") if p.strip()]
        return v

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
        """JSON-friendly dict of the effective settings (for the start-up log); the fields of
        :data:`SECRET_FIELDS` show as ``"***"``."""
        out = json.loads(self.model_dump_json())
        for name in SECRET_FIELDS & set(out):
            if out[name] is not None:
                out[name] = "***"
        return out


# ------------------------------------------------------------------ sources
@dataclass(frozen=True)
class _Loading:
    """What :func:`load_settings` hands to the sources: the environment to read (``None``:
    ``os.environ``) and the configuration file already read (``None``: find and read it)."""

    environ: Mapping[str, str] | None
    file_values: dict[str, Any] | None


_LOADING: ContextVar[_Loading | None] = ContextVar("shapeloc_settings_loading", default=None)


@contextmanager
def _loading(ctx: _Loading) -> Iterator[None]:
    token = _LOADING.set(ctx)
    try:
        yield
    finally:
        _LOADING.reset(token)


class _MappingEnvSource(EnvSettingsSource):
    """The environment source reading a given mapping instead of ``os.environ`` (tests)."""

    def __init__(self, settings_cls: type[BaseSettings], environ: Mapping[str, str]) -> None:
        super().__init__(settings_cls)
        self.env_vars = {
            k.lower(): v for k, v in environ.items() if not (self.env_ignore_empty and v == "")
        }


class _ConfigFileSource(PydanticBaseSettingsSource):
    """The configuration file's values (below the environment and the command line)."""

    def __init__(
        self,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
    ) -> None:
        super().__init__(settings_cls)
        self._init = init_settings
        self._env = env_settings

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False  # unused: __call__ returns the whole mapping

    def __call__(self) -> dict[str, Any]:
        ctx = _LOADING.get()
        if ctx is not None and ctx.file_values is not None:
            return dict(ctx.file_values)
        given = getattr(self._init, "init_kwargs", {}).get("config")
        env_vars = getattr(self._env, "env_vars", {})
        path = config_path(given, {CONFIG_ENV: env_vars.get(CONFIG_ENV.lower()) or ""})
        return {} if path is None else file_settings(path)


def file_settings(path: str | Path) -> dict[str, Any]:
    """The settings of a configuration file (:func:`schemas.cli.read_config_file`): every
    top-level key but the clients' ``client`` table, relative paths made relative to the
    file's directory, ``config`` set to the file. Raises :class:`InvalidMessage` naming the
    file for an unknown key (a typo must not be ignored)."""
    p = Path(path)
    doc = read_config_file(p)
    fields = ServiceSettings.model_fields
    unknown = sorted(k for k in doc if k not in fields and k not in IGNORED_FILE_KEYS)
    if "config" in doc:
        unknown.append("config")
    if unknown:
        raise InvalidMessage(
            f"{p}: unknown setting(s) {', '.join(unknown)} (see shapeloc-service --help)"
        )
    out = {k: v for k, v in doc.items() if k in fields}
    for name in ("state_dir", "zenoh_config"):
        v = out.get(name)
        if isinstance(v, str) and v and not Path(v).is_absolute():
            out[name] = str(p.parent / v)
    out["config"] = str(p)
    return out


# ------------------------------------------------------------------ command line
#: The global options of the service (schemas.cli): it may listen and has no --timeout.
GLOBAL_OPTIONS = GlobalOptions(
    listen=True,
    timeout=False,
    modes=("peer", "client", "router"),
    connect_default="none",
    listen_default="tcp/127.0.0.1:7447",
    mode_default="peer",
    config_help="TOML or YAML file of settings, one key per setting (the names below in "
    "lower case)",
    title="connection and configuration",
)


def _default_text(name: str) -> str:
    field = ServiceSettings.model_fields[name]
    if name == "workers":
        return f"number of cores, {_default_workers()} here"
    if name == "instance_id":
        return "<hostname>-<pid>"
    d = field.get_default(call_default_factory=True)
    if isinstance(d, bool):
        return "on" if d else "off"
    if isinstance(d, Path) and not d.is_absolute():
        return f"./{d}"
    if isinstance(d, list):
        return ",".join(d) if d else "none"
    return "none" if d is None else str(d)


def _env_only_epilog() -> str:
    lines = [
        "Settings without a flag (configuration file key, or environment SHAPELOC_<NAME>):",
    ]
    global_names = {"listen", "connect", "mode", "zenoh_config", "prefix", "config"}
    for name, field in ServiceSettings.model_fields.items():
        if flag_of(field) is None and name not in global_names:
            lines.append(f"  {name} (default: {_default_text(name)})")
    lines.append("")
    lines.append(
        "Precedence: defaults < configuration file < environment SHAPELOC_<NAME> < flags. "
        "The effective settings are logged at start."
    )
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The ``shapeloc-service`` argument parser: the global options of :mod:`schemas.cli`
    plus one flag per :class:`ServiceSettings` field with a :class:`Flag`. Every value not
    given is ``None`` (absent), so the environment and the configuration file can fill it;
    the help shows each setting's default."""
    p = argparse.ArgumentParser(
        prog="shapeloc-service",
        description="Shape-based laser localisation service over Eclipse Zenoh.",
        epilog=_env_only_epilog(),
        formatter_class=HelpFormatter,
    )
    add_global_options(p, GLOBAL_OPTIONS)
    g = p.add_argument_group("service settings")
    for name, field in ServiceSettings.model_fields.items():
        flag = flag_of(field)
        if flag is None:
            continue
        help_text = f"{field.description} (default: {_default_text(name)})"
        kw: dict[str, Any] = {"dest": name, "default": None, "help": help_text}
        if flag.const is not None:
            g.add_argument(flag.name, action="store_const", const=flag.const, **kw)
            continue
        ann = field.annotation
        if get_origin(ann) is Literal:
            kw["choices"] = list(get_args(ann))
        if flag.repeat:
            kw["action"] = "append"
        g.add_argument(flag.name, metavar=flag.metavar, **kw)
    return p


def _source_of(
    name: str, cli: Mapping[str, Any], environ: Mapping[str, str], file_values: Mapping[str, Any]
) -> str:
    env_name = ENV_PREFIX + name.upper()
    if name in cli:
        flag = flag_of(ServiceSettings.model_fields[name])
        return f"flag {flag.name}" if flag else f"flag --{name.replace('_', '-')}"
    if env_name in environ:
        return env_name
    if name in file_values:
        return f"{file_values.get('config', 'the configuration file')}"
    return "default"


def parse_args(
    argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None
) -> tuple[ServiceSettings, argparse.Namespace]:
    """Parse the command line and build the settings: defaults < configuration file <
    environment < flags. Returns the settings and the parsed namespace (for options that
    are not settings). Raises :class:`InvalidMessage` naming the setting and where its bad
    value came from (argparse itself exits with status 2 on unknown flags)."""
    env = os.environ if environ is None else environ
    ns = build_parser().parse_args([] if argv is None else list(argv))
    fields = ServiceSettings.model_fields
    cli = {k: v for k, v in vars(ns).items() if k in fields and v is not None}
    if getattr(ns, "verbose", False) and "log_level" not in cli:
        cli["log_level"] = "debug"
    path = config_path(cli.get("config"), env)
    file_values = file_settings(path) if path is not None else {}
    if path is not None:
        cli["config"] = str(path)
    try:
        with _loading(_Loading(environ=env, file_values=file_values)):
            settings = ServiceSettings(**cli)
    except ValidationError as e:
        parts = []
        for x in e.errors():
            name = str(x["loc"][0]) if x["loc"] else ""
            where = _source_of(name, cli, env, file_values) if name in fields else ""
            field_path = ".".join(map(str, x["loc"]))
            parts.append(f"{field_path} ({where}): {x['msg']}" if where else x["msg"])
        raise InvalidMessage(f"invalid service settings: {'; '.join(parts)}") from e
    except SettingsError as e:
        raise InvalidMessage(f"invalid service settings: {e}") from e
    return settings, ns


def load_settings(
    argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None
) -> ServiceSettings:
    """The settings of a command line (see :func:`parse_args`); ``environ`` replaces
    ``os.environ`` (tests)."""
    return parse_args(argv, environ)[0]


def zenoh_config(settings: ServiceSettings) -> zenoh.Config:
    """Build the Zenoh session configuration.

    Starts from ``settings.zenoh_config`` (json5 file: TLS, mutual TLS, user/password
    authentication, access control, ...) if given, else an empty config. Mode, listen and
    connect endpoints from the settings are applied on top, except that with a file only the
    options explicitly set (flag, environment or configuration file) override it. Multicast
    scouting is switched off unless ``multicast_scouting`` is true. Zenoh's scouting delay is
    kept: in peer mode open waits (up to 500 ms) for the connect endpoints, because a query
    sent before a peer link is up never reaches the queryables behind it. Unless
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
