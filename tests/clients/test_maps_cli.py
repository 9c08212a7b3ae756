"""``shapeloc map import|build|schematize|fidelity``: local map tools, no service needed.

Import reads a hand-made PGM + YAML (``negate``, ``occupied_thresh``, an origin) and the
polylines land where the occupied pixels are, in metres; build draws a map from a tiny CARMEN
log ray-cast in a known room with a per-scan reference file; schematize writes a file that
loads back as a schematic map; fidelity reads the built map back and scores the same log.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import shapely

from clients import maps_cli
from clients.__main__ import cli
from service.adapters.maps.files import load_map_file
from service.adapters.maps.grid import read_map_yaml
from service.adapters.maps.world import World
from service.core.sensor.raycast import RayCaster

RES = 0.1


def _write_hall(tmp_path: Path) -> Path:
    """A 3 x 2 m image at 0.1 m: with ``negate: 1`` a pixel's occupancy is ``value / 255``.
    Column 5 (x = 0.5 .. 0.6 m in the image) is 200 (0.78: occupied at the 0.6 threshold);
    row 15 (y = 0.4 .. 0.5 m) is 140 (0.55: not occupied at 0.6, occupied at 0.5); everything
    else 0 (free)."""
    pix = np.zeros((20, 30), dtype=np.uint8)
    pix[15, :] = 140
    pix[:, 5] = 200
    (tmp_path / "hall.pgm").write_bytes(b"P5\n30 20\n255\n" + pix.tobytes())
    y = tmp_path / "hall.yaml"
    y.write_text(
        "image: hall.pgm\nresolution: 0.1\norigin: [2.0, -1.0, 0.0]\nnegate: 1\n"
        "occupied_thresh: 0.6\nfree_thresh: 0.2\n"
    )
    return y


def test_import_places_the_walls_in_metres(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    y = _write_hall(tmp_path)
    out = tmp_path / "hall.geojson"
    assert cli(["map", "import", str(y), "--id", "hall", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "imported hall (metric): 1 polylines" in text
    m = load_map_file(out)
    assert (m.map_id, m.kind) == ("hall", "metric")
    verts = np.vstack(m.polylines)
    # the occupied column spans x = 2.0 + 0.5 .. 2.0 + 0.6 m, y = -1.0 .. 1.0 m (whole height);
    # the 140 row (0.55 < 0.6) is not a wall
    assert verts[:, 0].min() == pytest.approx(2.5, abs=1e-9)
    assert verts[:, 0].max() == pytest.approx(2.6, abs=1e-9)
    assert verts[:, 1].min() == pytest.approx(-1.0, abs=0.051)
    assert verts[:, 1].max() == pytest.approx(1.0, abs=0.051)
    # with occupied_thresh 0.5 the 140 row is a wall too: a cross
    y.write_text(y.read_text().replace("occupied_thresh: 0.6", "occupied_thresh: 0.5"))
    cross = maps_cli.import_map(y)
    v2 = np.vstack(cross.polylines)
    assert v2[:, 0].min() == pytest.approx(2.0, abs=0.051)
    assert v2[:, 0].max() == pytest.approx(5.0, abs=0.051)
    assert read_map_yaml(y).data[15, 0] == 100


def test_import_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert cli(["map", "import", str(tmp_path / "none.yaml"), "--id", "x"]) == 1
    assert "none.yaml" in capsys.readouterr().err
    assert cli(["map", "import", str(_write_hall(tmp_path)), "--out", str(tmp_path / "a.txt")]) == 1
    assert ".geojson or .json" in capsys.readouterr().err


#: A 6 x 4 m room with a 1 x 0.5 m cabinet (world frame, metres).
WKT = (
    "POLYGON ((-0.2 -0.2, 6.2 -0.2, 6.2 4.2, -0.2 4.2, -0.2 -0.2), (0 0, 6 0, 6 4, 0 4, 0 0))\n"
    "POLYGON ((4.0 3.0, 5.0 3.0, 5.0 3.5, 4.0 3.5, 4.0 3.0))"
)


def _write_log(tmp_path: Path) -> tuple[Path, Path]:
    """A CARMEN log of 60 FLASER scans (361 beams over 180 deg, 1 cm noise) driving an
    ellipse in the room, and a per-scan reference file: every 3rd pose corrected (flag 1), the
    others carried (flag 0, true poses too)."""
    rng = np.random.default_rng(5)
    world = World.from_wkt(WKT)
    rc = RayCaster(world.segments())
    ang = -math.pi / 2 + math.pi / 360 * np.arange(361)
    t = np.linspace(0.0, 2.0 * math.pi, 60, endpoint=False)
    poses = np.column_stack((3.0 + 1.8 * np.cos(t), 2.0 + 1.1 * np.sin(t), t + math.pi / 2))
    log_lines, ref_lines = [], ["# raw_stamp x y theta flag"]
    for i, p in enumerate(poses):
        r = rc.cast(p, ang, 30.0) + rng.normal(0.0, 0.01, ang.size)
        stamp = 1000.0 + 0.1 * i
        rs = " ".join(f"{v:.3f}" for v in r)
        log_lines.append(
            f"FLASER 361 {rs} {p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {p[0]:.4f} {p[1]:.4f} "
            f"{p[2]:.4f} {stamp:.6f} test {stamp:.6f}"
        )
        ref_lines.append(f"{stamp:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {int(i % 3 == 0)}")
    log = tmp_path / "room.clf"
    log.write_text("\n".join(log_lines) + "\n")
    ref = tmp_path / "room.gfs_reference_per_scan.txt"
    ref.write_text("\n".join(ref_lines) + "\n")
    return log, ref


def test_build_schematize_fidelity(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    log, ref = _write_log(tmp_path)
    prefix = tmp_path / "out" / "room"
    prefix.parent.mkdir()
    assert cli(["map", "build", str(log), "--poses", str(ref), "--out", str(prefix)]) == 0
    text = capsys.readouterr().out
    assert "from 20 of 60 scans (20 corrected)" in text  # default: corrected scans only
    for suffix in (".yaml", ".pgm", ".geojson"):
        assert prefix.with_name("room" + suffix).is_file()
    fid_line = next(ln for ln in text.splitlines() if ln.startswith("fidelity:"))
    median_cm = float(fid_line.split("median ")[1].split(" cm")[0])
    # 1 cm range noise (|N(0, 1 cm)| has median 0.67 cm), 60 scans only: measured 1.2 cm
    assert median_cm < 1.6
    built = load_map_file(prefix.with_name("room.geojson"))
    assert (built.map_id, built.kind) == ("room", "metric")
    pts = np.vstack(built.polylines)
    d = shapely.distance(World.from_wkt(WKT).union.boundary, shapely.points(pts))
    assert np.median(d) < 0.01
    grid = read_map_yaml(prefix.with_name("room.yaml"))
    assert grid.resolution == pytest.approx(0.025)

    # every scan (max-carried inf): 60 scans
    p0 = tmp_path / "out" / "room0"
    argv = ["map", "build", str(log), "--poses", str(ref), "--out", str(p0), "--max-carried", "inf"]
    assert cli(argv) == 0
    assert "from 60 of 60 scans" in capsys.readouterr().out

    # fidelity of the written map on the same log agrees with what build printed
    assert cli(["map", "fidelity", str(prefix) + ".geojson", str(log), "--poses", str(ref)]) == 0
    assert capsys.readouterr().out.strip() == fid_line

    # schematize: a loadable schematic map with fewer vertices; the cabinet (1 m) is dropped
    sch = tmp_path / "room_schematic.geojson"
    argv = ["map", "schematize", str(prefix) + ".geojson", "--out", str(sch), "--min-extent", "1.5"]
    assert cli(argv) == 0
    assert f"wrote {sch}: room (schematic)" in capsys.readouterr().out
    s = load_map_file(sch)
    assert s.kind == "schematic"
    assert sum(p.shape[0] for p in s.polylines) < sum(p.shape[0] for p in built.polylines)
    assert (
        shapely.distance(
            shapely.MultiLineString([shapely.LineString(p) for p in s.polylines]),
            shapely.Point(4.5, 3.0),
        )
        > 0.4
    )
    # bad parameter values are one-line errors
    assert cli(["map", "schematize", str(sch), "--out", str(sch), "--min-extent", "-1"]) == 1
    assert "schematize parameters" in capsys.readouterr().err
