"""The command-line convention of every shapeloc program.

``shapeloc`` (the CLI, :mod:`clients.__main__`), ``shapeloc-sim`` (the simulator and log
replay, :mod:`sim_publisher.__main__`) and ``shapeloc-service`` (:mod:`service.__main__`) all
follow it, and their parsers are built with the helpers here:

1. **Global options, one set, anywhere.** Connection and configuration options are the same
   flags in every program and are accepted both before and after a subcommand
   (``shapeloc --connect EP health`` = ``shapeloc health --connect EP``; given in both places,
   the one after the subcommand wins): ``--connect ENDPOINT`` (repeatable), ``--listen
   ENDPOINT`` (repeatable; programs that may listen), ``--mode client|peer|router``,
   ``--zenoh-config FILE`` (Zenoh JSON5: TLS, mTLS, user/password), ``--prefix``, ``--config
   FILE`` (TOML or YAML), ``--timeout S`` (programs that query the service) and
   ``-v/--verbose``. :func:`add_global_options` adds them; :func:`add_command` makes a
   subcommand that takes them too.
2. **One name, one unit.** Metres, radians, seconds. ``--rate`` is always scans per second
   (Hz); the time factor of a log replay is ``--speed``. A pose is three numbers:
   ``--initial-pose X Y THETA``, ``--laser-offset X Y THETA`` (:class:`PoseAction`).
3. **``--json``** on every command that prints data: one JSON object (a stream: one object a
   line) on standard output instead of the text.
4. **Help shows every default** (:class:`HelpFormatter`).
5. **Exit codes**: 0 success; 1 an error, one line ``<prog>: error: ...`` on standard error;
   2 bad usage.
6. **Deprecations**: an old spelling keeps working for one release and prints one line
   ``<prog>: warning: ... is deprecated ...; use ...`` on standard error
   (:func:`warn_deprecated`).

The configuration file (``--config FILE`` or the ``SHAPELOC_CONFIG`` environment variable) is
one file for all three programs (:func:`read_config_file`): the service reads its settings
from the top level (:mod:`service.node.settings`); ``shapeloc`` and ``shapeloc-sim`` read
``prefix`` from the top level and their connection options from the ``client`` table
(:func:`resolve_client_globals`), so a service and its clients can share one file::

    prefix = "lab"
    mode = "client"
    connect = ["tcp/router:7447"]
    state_dir = "/var/lib/shapeloc"

    [client]
    connect = ["tcp/router:7447"]
    timeout = 5.0

Relative paths in the file are relative to the file's directory. Precedence for the clients:
built-in defaults < configuration file < command line.

Only the standard library, PyYAML and :mod:`schemas.keys` are used: this module sits below the
service, the clients and the simulator (tests/test_layers.py), which all import it.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import textwrap
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from schemas.keys import DEFAULT_PREFIX, validate_prefix
from service.errors import InvalidMessage

__all__ = [
    "CONFIG_ENV",
    "DEFAULT_CONNECT",
    "DEFAULT_PREFIX",
    "DEFAULT_TIMEOUT",
    "MODES",
    "GlobalOptions",
    "HelpFormatter",
    "PoseAction",
    "add_command",
    "add_global_options",
    "add_json_option",
    "read_config_file",
    "resolve_client_globals",
    "warn_deprecated",
]

#: Where a client connects when nothing else says (a service on this machine, default port).
DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
#: Seconds a client waits for the service's answer to one request.
DEFAULT_TIMEOUT = 2.0
#: Zenoh session modes.
MODES = ("client", "peer", "router")
#: Environment variable naming the configuration file when ``--config`` is not given.
CONFIG_ENV = "SHAPELOC_CONFIG"
#: Largest configuration file read (bytes).
MAX_CONFIG_BYTES = 1_000_000
#: Keys of the configuration file's ``client`` table (the clients' global options).
CLIENT_KEYS = ("connect", "listen", "mode", "zenoh_config", "timeout")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help that shows every default: ``(default: X)`` is appended to an option's help unless
    the help already names its default or there is none to show (``None``, ``False``,
    suppressed). Descriptions and epilogs are wrapped line by line (their line breaks and
    leading indents are kept). A :class:`PoseAction` shows as ``X Y THETA``."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return "\n".join(
            textwrap.fill(line, width, initial_indent=indent, subsequent_indent=indent)
            if line.strip()
            else ""
            for line in text.splitlines()
        )

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "default" in text.lower() or "%(default)" in text:
            return text
        d = action.default
        if d is None or d is argparse.SUPPRESS or d is False or d == []:
            return text
        if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            return text
        return f"{text} (default: %(default)s)"

    def _format_args(self, action: argparse.Action, default_metavar: str) -> str:
        if isinstance(action, PoseAction):
            return "X Y THETA"
        return super()._format_args(action, default_metavar)


def warn_deprecated(prog: str, old: str, new: str, out: TextIO | None = None) -> None:
    """One line on standard error: ``<prog>: warning: <old> is deprecated ...; use <new>``."""
    print(
        f"{prog}: warning: {old} is deprecated and will be removed in the next release; use {new}",
        file=out or sys.stderr,
    )


class PoseAction(argparse.Action):
    """A pose option: three numbers ``X Y THETA`` (metres, metres, radians), stored as a list
    of three finite floats.

    The old single-token comma form ``X,Y,THETA`` is still read, with a deprecation warning
    (:func:`warn_deprecated`). Anything else is a usage error (exit 2). Negative numbers work
    (``--initial-pose -1.5 2 -0.3``). ``deprecated_for="--new-flag"`` makes the option an old
    spelling of ``--new-flag``: it still works and warns.
    """

    def __init__(
        self,
        option_strings: Sequence[str],
        dest: str,
        deprecated_for: str | None = None,
        **kwargs: Any,
    ) -> None:
        kwargs["nargs"] = "+"
        super().__init__(option_strings, dest, **kwargs)
        self.deprecated_for = deprecated_for

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        tokens = [str(v) for v in values]
        flag = option_string or self.option_strings[0]
        if self.deprecated_for is not None:
            warn_deprecated(parser.prog, flag, f"{self.deprecated_for} X Y THETA")
            flag = self.deprecated_for
        if len(tokens) == 1 and "," in tokens[0]:
            warn_deprecated(parser.prog, f"{flag} X,Y,THETA (comma form)", f"{flag} X Y THETA")
            tokens = tokens[0].split(",")
        try:
            pose = [float(t) for t in tokens]
        except ValueError:
            pose = []
        if len(pose) != 3 or not all(math.isfinite(v) for v in pose):
            parser.error(
                f"{flag} takes three finite numbers X Y THETA (metres, metres, radians), "
                f"got {' '.join(tokens)!r}"
            )
        setattr(namespace, self.dest, pose)


@dataclass(frozen=True)
class GlobalOptions:
    """Which global options a program takes and what its help says their defaults are.

    ``listen``: the program may listen (``--listen``); ``timeout``: it queries the service
    (``--timeout``); ``modes``: the Zenoh modes it accepts. The ``*_default`` texts are shown
    in the help; the values themselves are applied after parsing (by the program: the
    service's settings, or :func:`resolve_client_globals`), so an option not given stays
    ``None`` and the configuration file can fill it.
    """

    listen: bool = False
    timeout: bool = True
    modes: tuple[str, ...] = MODES
    connect_default: str = DEFAULT_CONNECT
    listen_default: str = "none"
    mode_default: str = "client"
    prefix_default: str = DEFAULT_PREFIX
    timeout_default: float = DEFAULT_TIMEOUT
    config_help: str = (
        "TOML or YAML configuration file: prefix at the top level, connection options in the "
        "'client' table (see docs)"
    )
    title: str = "global options (before or after the command)"


def add_global_options(
    p: argparse.ArgumentParser, spec: GlobalOptions, *, suppress: bool = False
) -> None:
    """Add the global options of :data:`spec` to ``p`` as the group "global options".

    On the top-level parser (``suppress=False``) an option not given is ``None`` (``False``
    for ``--verbose``); on a subcommand's parser (``suppress=True``, see :func:`add_command`)
    an option not given leaves no attribute, so a value given before the subcommand is kept.
    """
    none: Any = argparse.SUPPRESS if suppress else None
    g = p.add_argument_group(spec.title)
    g.add_argument(
        "--connect",
        action="append",
        default=none,
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to connect to, e.g. tcp/HOST:7447; repeatable "
        f"(default: {spec.connect_default})",
    )
    if spec.listen:
        g.add_argument(
            "--listen",
            action="append",
            default=none,
            metavar="ENDPOINT",
            help=f"Zenoh endpoint to listen on; repeatable (default: {spec.listen_default})",
        )
    g.add_argument(
        "--mode",
        choices=spec.modes,
        default=none,
        help=f"Zenoh session mode (default: {spec.mode_default})",
    )
    g.add_argument(
        "--zenoh-config",
        dest="zenoh_config",
        metavar="FILE",
        default=none,
        help="Zenoh JSON5 configuration (TLS, mutual TLS, user/password) used as the base; "
        f"{'--mode, --connect and --listen replace' if spec.listen else '--connect replaces'} "
        "its values (default: none)",
    )
    g.add_argument(
        "--prefix",
        default=none,
        help=f"key prefix of every shapeloc key (default: {spec.prefix_default})",
    )
    g.add_argument(
        "--config",
        metavar="FILE",
        default=none,
        help=f"{spec.config_help}; also ${CONFIG_ENV} (default: none)",
    )
    if spec.timeout:
        g.add_argument(
            "--timeout",
            type=_positive_seconds,
            default=none,
            metavar="S",
            help=f"seconds to wait for the service's answer to one request "
            f"(default: {spec.timeout_default:g})",
        )
    g.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        default=argparse.SUPPRESS if suppress else False,
        help="debug logging on standard error",
    )


def add_command(
    sub: argparse._SubParsersAction,  # type: ignore[type-arg]
    name: str,
    spec: GlobalOptions,
    *,
    help: str,
    description: str | None = None,
    **kwargs: Any,
) -> argparse.ArgumentParser:
    """A subcommand parser that also takes the global options (see :func:`add_global_options`)
    and shows defaults in its help."""
    sp = sub.add_parser(
        name,
        help=help,
        description=description or help,
        formatter_class=HelpFormatter,
        **kwargs,
    )
    add_global_options(sp, spec, suppress=True)
    return sp


def add_json_option(p: argparse.ArgumentParser, what: str = "the result") -> None:
    """``--json``: print ``what`` as JSON on standard output instead of text."""
    p.add_argument(
        "--json",
        action="store_true",
        help=f"print {what} as JSON instead of text",
    )


def _positive_seconds(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


# ------------------------------------------------------------------ configuration file
def read_config_file(path: str | Path) -> dict[str, Any]:
    """The mapping of a TOML (``.toml``) or YAML (``.yaml`` / ``.yml``) configuration file.

    Raises :class:`InvalidMessage` naming the file for a missing or unreadable file, another
    suffix, a syntax error, a top level that is not a mapping, or more than
    :data:`MAX_CONFIG_BYTES` bytes.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".toml", ".yaml", ".yml"):
        raise InvalidMessage(f"{p}: a configuration file ends in .toml, .yaml or .yml")
    try:
        size = p.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise InvalidMessage(f"{p}: file too large ({size} bytes > {MAX_CONFIG_BYTES})")
        text = p.read_text(encoding="utf-8")
    except InvalidMessage:
        raise
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidMessage(f"{p}: unreadable configuration file ({exc})") from exc
    if suffix == ".toml":
        try:
            doc: Any = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise InvalidMessage(f"{p}: bad TOML ({exc})") from exc
    else:
        import yaml

        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" line {mark.line + 1}" if mark is not None else ""
            problem = getattr(exc, "problem", None) or str(exc)
            raise InvalidMessage(f"{p}:{where} bad YAML ({problem})") from exc
        if doc is None:
            doc = {}
    if not isinstance(doc, dict) or not all(isinstance(k, str) for k in doc):
        raise InvalidMessage(f"{p}: the top level must be a mapping of setting names to values")
    return doc


def config_path(given: str | Path | None, environ: Mapping[str, str] | None = None) -> Path | None:
    """The configuration file to read: ``--config`` if given, else ``$SHAPELOC_CONFIG``."""
    if given:
        return Path(given)
    env = os.environ if environ is None else environ
    name = env.get(CONFIG_ENV, "").strip()
    return Path(name) if name else None


def _relative_to(base: Path, value: Any) -> Any:
    if isinstance(value, str) and value and not Path(value).is_absolute():
        return str(base / value)
    return value


def _endpoint_list(where: str, value: Any) -> list[str]:
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise InvalidMessage(f"{where}: must be an endpoint or a list of endpoints")
    return list(value)


def client_config_values(path: Path) -> dict[str, Any]:
    """The clients' global options from a configuration file: ``prefix`` from the top level,
    :data:`CLIENT_KEYS` from the ``client`` table. Raises :class:`InvalidMessage` for an
    unknown key in the ``client`` table or a value of the wrong type."""
    doc = read_config_file(path)
    out: dict[str, Any] = {}
    if "prefix" in doc:
        out["prefix"] = doc["prefix"]
    table = doc.get("client", {})
    if not isinstance(table, dict):
        raise InvalidMessage(f"{path}: 'client' must be a table of connection options")
    unknown = sorted(set(table) - set(CLIENT_KEYS))
    if unknown:
        raise InvalidMessage(
            f"{path}: unknown key(s) in the 'client' table: {', '.join(unknown)} "
            f"(known: {', '.join(CLIENT_KEYS)})"
        )
    for key in ("connect", "listen"):
        if key in table:
            out[key] = _endpoint_list(f"{path}: client.{key}", table[key])
    if "mode" in table:
        if table["mode"] not in MODES:
            raise InvalidMessage(f"{path}: client.mode must be one of {', '.join(MODES)}")
        out["mode"] = table["mode"]
    if "zenoh_config" in table:
        if not isinstance(table["zenoh_config"], str):
            raise InvalidMessage(f"{path}: client.zenoh_config must be a file name")
        out["zenoh_config"] = _relative_to(path.parent, table["zenoh_config"])
    if "timeout" in table:
        t = table["timeout"]
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (t > 0):
            raise InvalidMessage(f"{path}: client.timeout must be a number of seconds > 0")
        out["timeout"] = float(t)
    return out


def resolve_client_globals(
    args: argparse.Namespace,
    spec: GlobalOptions,
    environ: Mapping[str, str] | None = None,
) -> argparse.Namespace:
    """Fill the global options a client's command line left unset: from the configuration
    file (``--config`` or ``$SHAPELOC_CONFIG``, :func:`client_config_values`), else the
    built-in defaults (``connect`` stays ``None``: the caller's default endpoint applies in
    client mode only; ``mode`` stays ``None`` when a ``--zenoh-config`` file may set it).
    Validates the prefix. Returns ``args`` (changed in place); raises :class:`InvalidMessage`.
    """
    path = config_path(getattr(args, "config", None), environ)
    from_file = client_config_values(path) if path is not None else {}
    names = ["connect", "mode", "zenoh_config", "prefix"]
    if spec.listen:
        names.append("listen")
    if spec.timeout:
        names.append("timeout")
    for name in names:
        if getattr(args, name, None) is None and name in from_file:
            setattr(args, name, from_file[name])
    if getattr(args, "prefix", None) is None:
        args.prefix = spec.prefix_default
    validate_prefix(args.prefix)
    if spec.timeout and getattr(args, "timeout", None) is None:
        args.timeout = spec.timeout_default
    for name in ("connect", "listen", "mode", "zenoh_config"):
        if not hasattr(args, name):
            setattr(args, name, None)
    if not hasattr(args, "verbose"):
        args.verbose = False
    args.config = str(path) if path is not None else None
    return args
