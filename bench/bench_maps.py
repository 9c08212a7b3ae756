"""Maps of the real logs: build, schematise and score them; write the maps the real-data
benchmark uses (``bench/data/maps``).

READS /work/shared (not in a user's clone): the raw logs ``intel.orig.bag``,
``fr079.orig.bag``, ``mit-csail.clf`` and the per-scan references
``corrected/*.gfs_reference_per_scan.txt`` under ``--data`` (default
/work/shared/data/real; see its README.md).

For every log, every scan is read with its reference pose (laser frame in GMapping's map
frame; flag 1 = corrected, flag 0 = carried by odometry) and metric maps are built
(:func:`service.adapters.maps.build.build_map`) from three selections of scans: the corrected
(flag-1) ones only, those plus the flag-0 ones carried at most ``--max-carried`` m from a corrected
pose (the chosen map, :data:`clients.maps_cli.DEFAULT_MAX_CARRIED`), and every scan. Each is
scored by its fidelity on the flag-1 scans (median / p90 distance of their returns to the
map's polylines; scored on scans the map was drawn from), and, held out, by a map built from
the same selection without every second flag-1 scan and scored on those. The chosen map is
schematised (:func:`service.adapters.maps.schematize.schematize`, default parameters) and scored
too.

Writes ``bench/data/maps/{log}.geojson`` (metric polylines), ``{log}_schematic.geojson``,
``{log}.yaml`` + ``{log}.pgm`` (the occupancy grid, coarsened to ``--grid-resolution`` m to keep
the files small: a coarse cell is occupied if any fine cell is, else free if any is, else
unknown). Prints one table; ``--markdown`` prints it as Markdown (for docs/maps.md).

    .venv/bin/python -m bench.bench_maps [--logs intel fr079 mit-csail] [--no-write]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from clients.maps_cli import DEFAULT_MAX_CARRIED, LoggedScans, load_logged_scans
from service.adapters.maps.build import build_map
from service.adapters.maps.fidelity import map_fidelity
from service.adapters.maps.files import save_map_geojson
from service.adapters.maps.grid import OccupancyGrid, write_map_yaml
from service.adapters.maps.schematize import schematize

REPO = Path(__file__).resolve().parents[1]
LOGS = {
    "intel": "intel.orig.bag",
    "fr079": "fr079.orig.bag",
    "mit-csail": "mit-csail.clf",
}


def coarsen(grid: OccupancyGrid, factor: int) -> OccupancyGrid:
    """``grid`` at ``factor`` times its cell size: occupied (max) wins, then free, then
    unknown. The origin (lower-left corner) is kept: rows are padded at the top."""
    if factor <= 1:
        return grid
    d = grid.data.astype(np.int16)
    h, w = d.shape
    H, W = -(-h // factor), -(-w // factor)
    pad = np.full((H * factor, W * factor), -1, dtype=np.int16)
    pad[H * factor - h :, :w] = d
    blocks = pad.reshape(H, factor, W, factor).max(axis=(1, 3))
    return OccupancyGrid(blocks.astype(np.int8), grid.resolution * factor, grid.origin)


def _row(label: str, n: int, m, fid, held, seconds: float) -> dict:  # type: ignore[no-untyped-def]
    return {
        "map": label,
        "scans": n,
        "polylines": len(m.polylines),
        "vertices": sum(p.shape[0] for p in m.polylines),
        "median": fid.median,
        "p90": fid.p90,
        "held_median": held.median if held is not None else math.nan,
        "held_p90": held.p90 if held is not None else math.nan,
        "seconds": seconds,
    }


def bench_log(
    name: str, logged: LoggedScans, max_carried: float, out_dir: Path | None, grid_res: float
) -> list[dict]:
    """Rows of the table for one log; writes its maps into ``out_dir`` unless ``None``."""
    scans1, poses1 = logged.trusted()
    ok_idx = np.nonzero(logged.ok)[0]
    held = ok_idx[1::2]
    held_scans = [logged.scans[i] for i in held]
    held_poses = logged.poses[held]
    rows = []
    chosen = None
    ways = sorted({0.0, 0.5, max_carried, math.inf})
    for mc in ways:
        label = (
            "metric, flag-1 scans"
            if mc == 0.0
            else "metric, every scan"
            if math.isinf(mc)
            else f"metric, + flag-0 <= {mc:g} m"
        )
        if mc == max_carried:
            label += " (chosen)"
        idx = logged.usable(mc)
        t0 = time.perf_counter()
        built = build_map([logged.scans[i] for i in idx], logged.poses[idx], map_id=name)
        dt = time.perf_counter() - t0
        fid = map_fidelity(built.map_data, scans1, poses1)
        train = np.setdiff1d(idx, held)
        part = build_map([logged.scans[i] for i in train], logged.poses[train], map_id=name)
        hfid = map_fidelity(part.map_data, held_scans, held_poses)
        rows.append(_row(label, idx.size, built.map_data, fid, hfid, dt))
        if mc == max_carried:
            chosen = built
        print(f"  {name}: {label} done ({dt:.1f} s)", file=sys.stderr, flush=True)
    assert chosen is not None
    t0 = time.perf_counter()
    sch = schematize(chosen.map_data)
    dt = time.perf_counter() - t0
    rows.append(
        _row(
            "schematic (of the chosen)",
            chosen.n_scans,
            sch,
            map_fidelity(sch, scans1, poses1),
            None,
            dt,
        )
    )
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        factor = max(1, round(grid_res / chosen.grid.resolution))
        write_map_yaml(coarsen(chosen.grid, factor), out_dir / f"{name}.yaml")
        save_map_geojson(chosen.map_data, out_dir / f"{name}.geojson")
        save_map_geojson(sch, out_dir / f"{name}_schematic.geojson")
    return rows


def format_table(results: dict[str, list[dict]], markdown: bool) -> str:
    head = [
        "log",
        "map",
        "scans",
        "polylines",
        "vertices",
        "median cm",
        "p90 cm",
        "held-out median cm",
        "held-out p90 cm",
        "build s",
    ]
    lines = []
    for name, rows in results.items():
        for r in rows:
            lines.append(
                [
                    name,
                    r["map"],
                    str(r["scans"]),
                    str(r["polylines"]),
                    str(r["vertices"]),
                    f"{100 * r['median']:.2f}",
                    f"{100 * r['p90']:.2f}",
                    "-" if math.isnan(r["held_median"]) else f"{100 * r['held_median']:.2f}",
                    "-" if math.isnan(r["held_p90"]) else f"{100 * r['held_p90']:.2f}",
                    f"{r['seconds']:.1f}",
                ]
            )
    if markdown:
        out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        out += ["| " + " | ".join(x) + " |" for x in lines]
        return "\n".join(out)
    widths = [max(len(h), *(len(x[i]) for x in lines)) for i, h in enumerate(head)]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    return "\n".join([fmt.format(*head)] + [fmt.format(*x) for x in lines])


def main(
    data: Path,
    logs: list[str],
    *,
    max_carried: float = DEFAULT_MAX_CARRIED,
    out_dir: Path | None = REPO / "bench" / "data" / "maps",
    grid_res: float = 0.05,
    markdown: bool = False,
) -> dict[str, list[dict]]:
    """Build, score and (unless ``out_dir`` is ``None``) write the maps; print the table."""
    results = {}
    for name in logs:
        t0 = time.perf_counter()
        logged = load_logged_scans(
            data / LOGS[name], data / "corrected" / f"{name}.gfs_reference_per_scan.txt"
        )
        print(
            f"{name}: {len(logged.scans)} scans, {int(logged.ok.sum())} flag-1, read in "
            f"{time.perf_counter() - t0:.1f} s",
            file=sys.stderr,
            flush=True,
        )
        results[name] = bench_log(name, logged, max_carried, out_dir, grid_res)
    print(format_table(results, markdown))
    if out_dir is not None:
        files = sorted(p for p in out_dir.iterdir() if p.is_file())
        total = sum(p.stat().st_size for p in files)
        for p in files:
            print(f"{p.relative_to(REPO)}  {p.stat().st_size / 1024:.0f} KiB")
        print(f"total {total / 1024 / 1024:.1f} MiB in {len(files)} files")
    print(f"load: {os.getloadavg()[0]:.2f} (1-min average, 2 cores)")
    return results


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("/work/shared/data/real"))
    ap.add_argument("--logs", nargs="+", choices=sorted(LOGS), default=list(LOGS))
    ap.add_argument("--max-carried", type=float, default=DEFAULT_MAX_CARRIED)
    ap.add_argument("--grid-resolution", type=float, default=0.05, help="written grid, m")
    ap.add_argument("--no-write", action="store_true", help="do not write bench/data/maps")
    ap.add_argument("--markdown", action="store_true")
    a = ap.parse_args()
    main(
        a.data,
        a.logs,
        max_carried=a.max_carried,
        out_dir=None if a.no_write else REPO / "bench" / "data" / "maps",
        grid_res=a.grid_resolution,
        markdown=a.markdown,
    )
