"""The configuration reference (docs/configuration.md), generated from the pydantic models'
field descriptions so that it cannot drift from the code.

``python -m service.node.reference`` prints it, ``--write`` writes docs/configuration.md and
docs/configuration-localisers.md, ``--check`` exits 1 when they are stale (so does
``tests/service/node/test_reference.py``). Every section is one model: the service's settings
(with their flag, environment variable and file key), a robot's configuration on the wire,
and the localisers' configurations with their per-map-kind presets.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Callable, Iterator, Sequence
from enum import Enum
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from schemas.messages import RobotConfig
from service.core.baselines.icp import ICPConfig
from service.core.baselines.lines import LineConfig
from service.core.reloc.config import GlobalConfig
from service.core.tracking.shape_config import ShapeConfig
from service.node.settings import ENV_PREFIX, ServiceSettings, flag_of

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "configuration.md"
#: The localisers' parameters, on a page of their own (they are many, and most are internal).
DOC_LOCALISERS = REPO / "docs" / "configuration-localisers.md"

HEADER = """# Configuration reference

Generated from the field descriptions in the code by `python -m service.node.reference --write`
(`tests/service/node/test_reference.py` fails when this page is stale). Do not edit it by hand.

- [Service settings](#service-settings): `shapeloc-service`'s flags, environment and file.
- [Robot configuration](#robot-configuration): what a client puts on
  `<prefix>/robots/<id>/config`.
- [Localisers](configuration-localisers.md): the `shape`, `icp` and `lines` methods'
  parameters, with the presets for metric maps and floor plans (the service picks the preset
  by the map's kind).
"""

HEADER_LOCALISERS = """# Configuration reference: the localisers

Generated from the field descriptions in the code by `python -m service.node.reference --write`
(`tests/service/node/test_reference.py` fails when this page is stale). Do not edit it by hand.
The service's settings and a robot's configuration: [configuration.md](configuration.md).
"""


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _value(v: Any) -> str:
    if isinstance(v, BaseModel):
        return "(below)"
    if isinstance(v, Enum):
        v = v.value
    if isinstance(v, Path):
        return f"`{v}`"
    if isinstance(v, float):
        return f"`{v:g}`"
    if isinstance(v, tuple | list | dict | bool | int | str) or v is None:
        return f"`{json.dumps(v, default=str)}`"
    return f"`{v}`"


def _default(field: FieldInfo) -> str:
    """The default as a user reads it: a computed default says how it is computed (its
    factory's docstring) rather than what it gave on the machine that wrote the page."""
    if field.default_factory is not None:
        factory = field.default_factory
        ours = getattr(factory, "__module__", "").split(".")[0] in ("service", "schemas")
        doc = (factory.__doc__ or "").strip() if ours else ""
        if doc:
            return doc.splitlines()[0].rstrip(".")
        return _value(field.default_factory())
    if field.default is PydanticUndefined:
        return "required"
    return _value(field.default)


def _type(field: FieldInfo) -> str:
    text = repr(field.annotation).replace("typing.", "").replace("NoneType", "None")
    for noise in ("pathlib.", "<class '", "'>"):
        text = text.replace(noise, "")
    return f"`{text}`" if len(text) < 60 else "see description"


def fields(model: type[BaseModel], prefix: str = "") -> Iterator[tuple[str, FieldInfo]]:
    """``(dotted name, field)`` of every leaf field, nested models expanded."""
    for name, field in model.model_fields.items():
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            yield from fields(ann, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", field


def _get(obj: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def service_section() -> list[str]:
    out = [
        "## Service settings",
        "",
        "Lowest to highest precedence: the defaults below, the configuration file (`--config "
        "FILE` or `SHAPELOC_CONFIG`; TOML or YAML, one key per setting, e.g. `state_dir = "
        '"/var/lib/shapeloc"`), the environment (`SHAPELOC_` + the name in capitals, e.g. '
        "`SHAPELOC_STATE_DIR`) and the command line. Settings without a flag are set by the "
        "file or the environment. The service logs the effective settings at start.",
        "",
        "| setting | flag | default | description |",
        "|---|---|---|---|",
    ]
    for name, field in ServiceSettings.model_fields.items():
        flag = flag_of(field)
        flag_text = f"`{flag.name}`" if flag is not None else ""
        if name in ("listen", "connect", "mode", "zenoh_config", "prefix", "config"):
            flag_text = f"`--{name.replace('_', '-')}`"
        out.append(
            f"| `{name}` (`{ENV_PREFIX}{name.upper()}`) | {flag_text} | {_cell(_default(field))}"
            f" | {_cell(field.description or '')} |"
        )
    out.append("")
    return out


def robot_section() -> list[str]:
    out = [
        "## Robot configuration",
        "",
        "Put on `<prefix>/robots/<robot_id>/config` (msgpack or JSON; `shapeloc configure`, "
        "`ShapelocClient.configure`). Each put resets the robot's localiser.",
        "",
        "| field | type | default | description |",
        "|---|---|---|---|",
    ]
    for name, field in RobotConfig.model_fields.items():
        out.append(
            f"| `{name}` | {_type(field)} | {_cell(_default(field))} | "
            f"{_cell(field.description or '')} |"
        )
    out.append("")
    return out


@dataclasses.dataclass(frozen=True)
class Method:
    """A localiser's configuration model and its presets by map kind."""

    name: str
    title: str
    model: type[BaseModel]
    presets: dict[str, Callable[[], BaseModel]]


METHODS: tuple[Method, ...] = (
    Method(
        "shape",
        "`shape`: tracking (the paper's method)",
        ShapeConfig,
        {k: (lambda k=k: ShapeConfig.for_kind(k)) for k in ("metric", "schematic")},
    ),
    Method(
        "shape",
        "`shape`: global localisation and relocalisation",
        GlobalConfig,
        {k: (lambda k=k: GlobalConfig.for_kind(k)) for k in ("metric", "schematic")},
    ),
    Method("icp", "`icp`: ICP on an occupancy grid (baseline)", ICPConfig, {"any": ICPConfig}),
    Method("lines", "`lines`: line-based matching (baseline)", LineConfig, {"any": LineConfig}),
)


def localiser_section() -> list[str]:
    out = [
        "Chosen per robot by `method`; the parameters are the service's, per map kind (metric "
        "map or floor plan). Units: metres, radians, seconds, unless a name says otherwise.",
        "",
    ]
    for m in METHODS:
        presets = {k: f() for k, f in m.presets.items()}
        cols = list(presets)
        out += [
            f"### {m.title}",
            "",
            "| parameter | " + " | ".join(cols) + " | description |",
            "|---|" + "---|" * len(cols) + "---|",
        ]
        for name, field in fields(m.model):
            vals = [_value(_get(p, name)) for p in presets.values()]
            out.append(
                f"| `{name}` | " + " | ".join(vals) + f" | {_cell(field.description or '')} |"
            )
        out.append("")
    return out


def _page(lines: list[str]) -> str:
    return "\n".join(lines).rstrip() + "\n"


def render() -> dict[Path, str]:
    """The pages, by path."""
    return {
        DOC: _page([HEADER, *service_section(), *robot_section()]),
        DOC_LOCALISERS: _page([HEADER_LOCALISERS, *localiser_section()]),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Print the reference, write it (``--write``) or check the committed page (``--check``)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = ap.add_mutually_exclusive_group()
    group.add_argument("--write", action="store_true", help="write the pages under docs/")
    group.add_argument("--check", action="store_true", help="exit 1 if the page is stale")
    args = ap.parse_args(argv)
    pages = render()
    if args.write:
        for path, text in pages.items():
            path.write_text(text)
        return 0
    if args.check:
        stale = [p for p, text in pages.items() if not p.exists() or p.read_text() != text]
        for p in stale:
            print(f"{p} is stale: run python -m service.node.reference --write", file=sys.stderr)
        return 1 if stale else 0
    sys.stdout.write("\n".join(pages.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
