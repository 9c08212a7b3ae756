"""The committed JSON Schema files match the models (regenerate and compare byte-for-byte)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from schemas.export import JSON_DIR, drifted, main, render_schemas, write_schemas
from schemas.messages import MESSAGES

EXPECTED = {
    "map.schema.json",
    "robot_config.schema.json",
    "scan.schema.json",
    "pose.schema.json",
    "health.schema.json",
    "error_notice.schema.json",
    "truth.schema.json",
}


def test_committed_schema_files_have_not_drifted(tmp_path: Path) -> None:
    written = write_schemas(tmp_path)
    assert {p.name for p in written} == EXPECTED == {p.name for p in JSON_DIR.glob("*.json")}
    for p in written:
        committed = JSON_DIR / p.name
        assert committed.read_bytes() == p.read_bytes(), (
            f"{p.name} drifted: run `python -m schemas.export` and commit schemas/json/"
        )
    assert drifted(JSON_DIR) == []


def test_rendering_is_stable_and_valid_json() -> None:
    a, b = render_schemas(), render_schemas()
    assert a == b
    assert len(a) == len(MESSAGES)
    for name, text in a.items():
        assert text.endswith("}\n") and not text.endswith("\n\n")
        doc = json.loads(text)
        assert doc["type"] == "object", name
        assert json.dumps(doc, sort_keys=True, indent=2, ensure_ascii=False) + "\n" == text


def test_schema_content_describes_the_wire_types() -> None:
    scan = json.loads((JSON_DIR / "scan.schema.json").read_text())
    ranges = scan["properties"]["ranges"]
    assert ranges["type"] == "array" and ranges["maxItems"] == 8192
    assert "float32" in ranges["description"]
    assert set(scan["required"]) == {
        "seq",
        "stamp",
        "angle_min",
        "angle_increment",
        "range_min",
        "range_max",
        "ranges",
    }
    pose = json.loads((JSON_DIR / "pose.schema.json").read_text())
    assert pose["properties"]["pose"]["minItems"] == 3
    assert pose["properties"]["status"]["enum"] == ["tracking", "lost", "initializing"]
    assert pose["properties"]["robot_id"]["pattern"] == "^[A-Za-z0-9_.-]{1,64}$"
    cfg = json.loads((JSON_DIR / "robot_config.schema.json").read_text())
    assert cfg["properties"]["method"]["default"] == "shape"
    assert cfg["required"] == ["map_id"]


def test_check_reports_drift_and_exits_one(tmp_path: Path, capsys) -> None:
    write_schemas(tmp_path)
    assert main(["--check", "--dir", str(tmp_path)]) == 0
    (tmp_path / "scan.schema.json").write_text("{}\n")
    (tmp_path / "truth.schema.json").unlink()
    (tmp_path / "stale.schema.json").write_text("{}\n")
    capsys.readouterr()
    assert main(["--check", "--dir", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    for name in ("scan.schema.json", "truth.schema.json", "stale.schema.json"):
        assert name in err
    assert "map.schema.json" not in err


def test_module_entry_point_check_on_the_repository() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "schemas.export", "--check"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "7 schema files up to date" in proc.stdout
