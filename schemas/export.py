"""JSON Schema files of the wire messages (``schemas/json/<name>.schema.json``).

``python -m schemas.export`` (re)writes them; ``python -m schemas.export --check`` exits 1 and
names every file that is missing, stale or unexpected. Output is stable: sorted keys, indent 2,
trailing newline.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from schemas.messages import MESSAGES

#: Where the committed schema files live.
JSON_DIR: Path = Path(__file__).resolve().parent / "json"
_SUFFIX = ".schema.json"
_ID_BASE = "https://shapeloc.invalid/schemas/wire-v1/"


def render_schemas() -> dict[str, str]:
    """File name -> file text for every message, deterministic."""
    out: dict[str, str] = {}
    for model in MESSAGES:
        schema = model.model_json_schema(mode="validation")
        schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        schema["$id"] = f"{_ID_BASE}{model.schema_name}{_SUFFIX}"
        schema["x-unknown-keys"] = "ignored (forward compatibility)"
        name = f"{model.schema_name}{_SUFFIX}"
        out[name] = json.dumps(schema, sort_keys=True, indent=2, ensure_ascii=False) + "\n"
    return out


def write_schemas(directory: Path = JSON_DIR) -> list[Path]:
    """Write every schema file into ``directory`` (created if needed); return the paths."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, text in render_schemas().items():
        path = directory / name
        path.write_text(text, encoding="utf-8", newline="\n")
        paths.append(path)
    return paths


def drifted(directory: Path = JSON_DIR) -> list[str]:
    """Names of schema files in ``directory`` that are missing, differ, or are not generated."""
    expected = render_schemas()
    bad = []
    for name, text in expected.items():
        path = directory / name
        if not path.is_file() or path.read_bytes() != text.encode("utf-8"):
            bad.append(name)
    if directory.is_dir():
        bad += sorted(p.name for p in directory.glob(f"*{_SUFFIX}") if p.name not in expected)
    return bad


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns the exit status."""
    ap = argparse.ArgumentParser(prog="python -m schemas.export", description=__doc__)
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 on drift")
    ap.add_argument("--dir", type=Path, default=JSON_DIR, help="output directory")
    args = ap.parse_args(argv)
    if args.check:
        bad = drifted(args.dir)
        if bad:
            print(
                "schema files out of date (run `python -m schemas.export`): " + ", ".join(bad),
                file=sys.stderr,
            )
            return 1
        print(f"{len(MESSAGES)} schema files up to date in {args.dir}")
        return 0
    for path in write_schemas(args.dir):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
