"""Fleet benchmark of the localizer service: N robots that start together on a fresh service.

Every run (:func:`bench.fleet_run.run_fleet`) starts its own service with an empty state
directory, puts one map as soon as the service answers, waits until the service reports the
map ready (``Health.maps_ready``: the map put's acknowledgement), configures the N robots
(true start poses) and lets every robot send its scans with odometry at ``--rate`` Hz, all
robots in the same instant, for ``--duration`` s: a cold start, queueing included. Nothing is
primed and no second is left out of the figures.

Three parts, each a table of the markdown page ``--out`` writes:

* ``--cold``: the cold-start fleet, ``--reps`` runs of ``--robots`` robots, each run on the next
  world of ``--world`` (default: the held-out generated buildings 1000-1009, one per run,
  maps none of the tuning saw): answered, first-scan latency, p50/p99, poses more than 0.1 m
  off. Acceptance: every run >= 99 % answered, 0 poses off, p99 <= 50 ms, every first scan
  answered within 200 ms.
* ``--curve``: robots (``--robots``, e.g. 10,20,50,100) against answered, p50/p99, the
  service's CPU per scan, on each of ``--world`` x ``--map`` (default the office, the held-out
  building 1000 and that building's floor plan); the largest N per world that meets the
  capacity line (>= 99 % answered, p99 <= 100 ms, every pose correct: none *wrong*, i.e.
  beyond 0.5 m or 10 deg of the truth, and on a metric map none more than 0.1 m off; a floor
  plan's own scale error keeps well-tracked poses 0.1-0.2 m from the truth there).
* ``--acceptance``: all three with the acceptance settings: the cold start (20 robots, 10 runs on
  buildings 1000-1009), the 50-robot line (50 robots x 10 Hz, 3 runs on the office and
  building 1000) and the curve (10, 20, 50, 100 robots on the office, building 1000 and its
  floor plan); prints PASS/FAIL per line and writes docs/results/fleet.md with ``--out``.

Figures per run: *answered* poses over scans sent (mean over robots, and the worst robot);
latency = pose receipt minus the scan's stamp (its send time: both Zenoh hops, decoding,
queueing, the localisation); *first scan* = the latency of each robot's first scan (``inf``:
replaced unprocessed); *off* = answered poses more than 0.1 m from the scan's true pose
(scans are simulated against the true world with setup 1's laser; the poses are judged in
the map's frame, a floor plan's scale error included); *wrong* = beyond 0.5 m or 10 deg;
*not tracking* = poses whose status is not ``tracking``; *CPU per scan* = the service's own
accounting (``Health.scan_cpu_ms``: its threads plus the worker, p50/p99 over the run's last
4096 scans) and the whole service (process, workers, Zenoh's threads, the search worker;
the map's view index is built before the map is ready, so before the run) from /proc divided
by the poses answered. The
load generator (publisher and receiver processes) shares the machine's cores with the
service; the 1-minute load average is given per run, and *probe*: the wall time of a fixed
CPU workload just before the run (:func:`bench.harness.machine_probe_ms`), which tells how
much CPU the machine gave then (on a virtual machine the host's other tenants change it).

Usage: ``python -m bench.bench_fleet --acceptance --out docs/results/fleet.md``, or e.g.
``python -m bench.bench_fleet --cold --robots 20 --reps 3`` or ``python -m bench.bench_fleet
--curve --robots 10,50 --world office --map metric``. Without a part it runs a short cold
start (``--robots 5 --reps 1 --duration 5``, for ``make bench``).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import shlex
import sys
from pathlib import Path
from typing import Any

from bench.fleet_run import FleetSpec, run_fleet
from bench.harness import exit_on_sigterm, machine_probe_ms
from bench.scale_report import git_commit
from bench.scale_walks import Pool, make_pool, world_name

#: The cold start's acceptance.
COLD_ANSWERED, COLD_P99_MS, COLD_FIRST_MS = 0.99, 50.0, 200.0
#: The capacity line: what a fleet size must meet to count as served.
LINE_ANSWERED, LINE_P99_MS = 0.99, 100.0


def _csv(s: str) -> list[str]:
    out: list[str] = []
    for part in (x.strip() for x in s.split(",")):
        if "-" in part and part.replace("-", "").isdigit():
            a, b = (int(v) for v in part.split("-"))
            out += [str(v) for v in range(a, b + 1)]
        elif part:
            out.append(part)
    return out


def machine() -> str:
    """CPU model and cores."""
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores"


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def _f(v: float, fmt: str = ".1f") -> str:
    return "n/a" if v is None or not math.isfinite(v) else format(v, fmt)


class Pools:
    """Scan pools by (world, map), made on first use."""

    def __init__(self, stride: int) -> None:
        self.stride = stride
        self._pools: dict[tuple[str, str], Pool] = {}

    def get(self, world: str, map_kind: str) -> Pool:
        key = (world, map_kind)
        if key not in self._pools:
            self._pools[key] = make_pool(world, map_kind, self.stride)
        return self._pools[key]


def cold_ok(r: dict[str, Any]) -> bool:
    """A cold-start run meets the acceptance."""
    return (
        r["answered"] >= COLD_ANSWERED
        and r["off"] == 0
        and r["p99"] <= COLD_P99_MS
        and r["first_max"] <= COLD_FIRST_MS
    )


def line_ok(r: dict[str, Any]) -> bool:
    """A run meets the capacity line: >= 99 % answered, p99 <= 100 ms, every pose correct
    (none wrong; on a metric map also none more than 0.1 m off)."""
    exact = r["map"] != "metric" or r["off"] == 0
    return (
        r["answered"] >= LINE_ANSWERED
        and r["p99"] <= LINE_P99_MS
        and r.get("wrong", 0) == 0
        and exact
    )


def _run(spec: FleetSpec, pools: Pools, rep: int) -> dict[str, Any]:
    pool = pools.get(spec.world, spec.map_kind)
    probe = machine_probe_ms()
    r = run_fleet(spec, pool, rep)
    r.update(world=spec.world, map=spec.map_kind, rate=spec.rate, probe_ms=probe)
    cpu = r.get("scan_cpu_ms") or {}
    print(
        f"{world_name(spec.world)} {spec.map_kind} N={spec.n} run {rep}: answered "
        f"{100 * r['answered']:.1f} % (worst {100 * r['answered_min']:.1f} %), first scan max "
        f"{_f(r['first_max'], '.0f')} ms, p50 {_f(r['p50'])} p99 {_f(r['p99'])} ms, off "
        f"{r['off']} (max {_f(r['err_max'], '.3f')} m), not tracking {r['not_tracking']}, CPU/scan "
        f"p50 {_f(cpu.get('p50', math.nan), '.2f')} p99 {_f(cpu.get('p99', math.nan), '.2f')} "
        f"ms, whole {_f(r['cpu_ms_per_pose'], '.2f')} ms, ready {r['ready_s']:.1f} s, load "
        f"{r['load_after']:.2f}, probe {probe:.1f} ms",
        flush=True,
    )
    return r


COLD_HEAD = (
    "run", "world", "answered mean / worst", "first scan max / p50 ms", "p50 ms", "p99 ms",
    "max ms", "off > 0.1 m", "not tracking", "skipped", "ready s", "load", "probe ms", "ok",
)  # fmt: skip
CURVE_HEAD = (
    "world", "map", "N", "answered mean / worst", "p50 ms", "p99 ms", "off > 0.1 m", "wrong",
    "CPU/scan p50 / p99 ms", "whole CPU/scan ms", "svc CPU %", "load", "probe ms", "line",
)  # fmt: skip


def cold_cells(r: dict[str, Any]) -> list[str]:
    return [
        str(r["rep"]),
        f"{world_name(r['world'])} {r['map']}",
        f"{100 * r['answered']:.1f} / {100 * r['answered_min']:.1f} %",
        f"{_f(r['first_max'], '.0f')} / {_f(r['first_p50'], '.0f')}",
        _f(r["p50"]),
        _f(r["p99"]),
        _f(r["max"], ".0f"),
        f"{r['off']} / {r['poses']}",
        str(r["not_tracking"]),
        str(r["skipped"]),
        f"{r['ready_s']:.1f}",
        f"{r['load_after']:.2f}",
        _f(r.get("probe_ms", math.nan)),
        "yes" if cold_ok(r) else "**no**",
    ]


def curve_cells(r: dict[str, Any]) -> list[str]:
    cpu = r.get("scan_cpu_ms") or {}
    return [
        world_name(r["world"]),
        r["map"],
        str(r["n"]),
        f"{100 * r['answered']:.1f} / {100 * r['answered_min']:.1f} %",
        _f(r["p50"]),
        _f(r["p99"]),
        f"{r['off']} / {r['poses']}",
        str(r.get("wrong", 0)),
        f"{_f(cpu.get('p50', math.nan), '.2f')} / {_f(cpu.get('p99', math.nan), '.2f')}",
        _f(r["cpu_ms_per_pose"], ".2f"),
        _f(r["svc_cpu_pct"], ".0f"),
        f"{r['load_after']:.2f}",
        _f(r.get("probe_ms", math.nan)),
        "yes" if line_ok(r) else "no",
    ]


def md_table(head: tuple[str, ...], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def largest(results: list[dict[str, Any]]) -> dict[tuple[str, str], int]:
    """Per (world, map): the largest N whose every run meets the capacity line (0: none)."""
    by: dict[tuple[str, str], dict[int, bool]] = {}
    for r in results:
        d = by.setdefault((r["world"], r["map"]), {})
        d[r["n"]] = d.get(r["n"], True) and line_ok(r)
    return {k: max([n for n, ok in d.items() if ok], default=0) for k, d in by.items()}


def report(meta: dict[str, Any], cold: list, line: list, curve: list) -> str:
    """The markdown page."""
    out = [
        "# Fleet: cold start and capacity (bench/bench_fleet.py)",
        "",
        f"Command: `{meta['command']}`  ",
        f"Commit: `{meta['commit']}`, {meta['date']}; machine: {meta['machine']}; load "
        f"average before {meta['load_before']}, after {meta['load_after']}.  ",
        f"Service: method `shape`, {meta['workers']} tracking workers (+ the search worker), "
        f"odometry on every scan, {meta['rate']:g} Hz per robot, all robots in the same "
        f"instant, {meta['duration']:g} s per run; every run on a fresh service and a fresh "
        "map (cold start, nothing primed or left out). The load generator shares the cores. "
        "*probe ms*: the wall time of a fixed CPU workload just before each run "
        "(`bench.harness.machine_probe_ms`), how much CPU the machine gave then; the same "
        "commit's latencies move with it.",
        "",
    ]
    if meta.get("note"):
        out += [f"> {meta['note']}", ""]
    if cold:
        ok = sum(cold_ok(r) for r in cold)
        out += [
            f"## Cold-start fleet: {cold[0]['n']} robots, {len(cold)} runs",
            "",
            f"Acceptance per run: >= {100 * COLD_ANSWERED:g} % answered, 0 poses > 0.1 m off, "
            f"p99 <= {COLD_P99_MS:g} ms, every robot's first scan answered within "
            f"{COLD_FIRST_MS:g} ms of its sending (sent once the map was reported ready and "
            f"the robots configured). Runs meeting it: **{ok} of {len(cold)}**.",
            "",
            md_table(COLD_HEAD, [cold_cells(r) for r in cold]),
            "",
        ]
    if line:
        ok = sum(line_ok(r) for r in line)
        out += [
            f"## The capacity line: {line[0]['n']} robots",
            "",
            f"Per run: >= {100 * LINE_ANSWERED:g} % answered, p99 <= {LINE_P99_MS:g} ms, every "
            "pose correct (none wrong, none more than 0.1 m off on these metric maps). Runs "
            f"meeting it: **{ok} of {len(line)}**.",
            "",
            md_table(CURVE_HEAD, [curve_cells(r) for r in line]),
            "",
        ]
    if curve:
        big = largest(curve)
        out += [
            "## Robots against answered, latency and CPU per scan",
            "",
            md_table(CURVE_HEAD, [curve_cells(r) for r in curve]),
            "",
            "Largest fleet meeting the capacity line: "
            + "; ".join(f"{world_name(w)} {m}: **{n}**" for (w, m), n in big.items())
            + ".",
            "",
        ]
    out += [
        "CPU per scan: *CPU/scan* is the service's own accounting (`Health.scan_cpu_ms`: the "
        "service process's threads for the scan -- decoding, validation, scheduling, the "
        "pose -- plus its worker's localisation; p50 / p99 over the run's last 4096 scans); "
        "*whole* is the CPU of the service process and all its workers (Zenoh's threads and "
        "the search worker included; the map's view index is built before the map is ready) "
        "from /proc over the run, per answered pose.",
        "",
    ]
    return "\n".join(out)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cold", action="store_true", help="the cold-start fleet")
    ap.add_argument("--curve", action="store_true", help="robots against capacity")
    ap.add_argument("--acceptance", action="store_true", help="all three parts")
    ap.add_argument("--robots", default=None, help="N (cold) or a comma list (curve)")
    ap.add_argument("--reps", type=int, default=None, help="runs per N (cold: 10, curve: 1)")
    ap.add_argument("--world", default=None, help="comma list; a-b is a range of seeds")
    ap.add_argument("--map", default="metric", help="comma list: metric and/or schematic")
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of scans per run")
    ap.add_argument("--workers", type=int, default=None, help="service workers (default: cores)")
    ap.add_argument("--stride", type=int, default=5, help="tour samples (11 mm) between scans")
    ap.add_argument("--out", type=Path, default=None, help="write the markdown page here")
    ap.add_argument("--json", type=Path, default=None, help="write the raw runs here")
    ap.add_argument("--note", default="", help="a line quoted at the top of the page")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run the parts; 0, or 2 if an acceptance line fails."""
    args = build_parser().parse_args(argv)
    exit_on_sigterm()
    pools = Pools(args.stride)
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    cold: list[dict[str, Any]] = []
    line: list[dict[str, Any]] = []
    curve: list[dict[str, Any]] = []
    load_before = _load()

    def spec(world: str, mk: str, n: int) -> FleetSpec:
        return FleetSpec(world, mk, n, args.rate, args.duration, workers=args.workers)

    quick = not (args.cold or args.curve or args.acceptance)
    if args.cold or args.acceptance or quick:
        n = int(args.robots or (5 if quick else 20)) if not args.acceptance else 20
        reps = args.reps or (1 if quick else 10)
        worlds = _csv(args.world or "1000-1009") if not args.acceptance else _csv("1000-1009")
        if quick:
            args.duration = 5.0
        for rep in range(reps):
            cold.append(_run(spec(worlds[rep % len(worlds)], "metric", n), pools, rep))
    if args.acceptance:
        for rep in range(3):
            for w in ("office", "1000"):
                line.append(_run(spec(w, "metric", 50), pools, rep))
    if args.curve or args.acceptance:
        ns = [int(v) for v in _csv(args.robots or "10,20,50,100")]
        if args.acceptance:
            ns = [10, 20, 50, 100]
            combos = [("office", "metric"), ("1000", "metric"), ("1000", "schematic")]
        else:
            combos = [(w, m) for w in _csv(args.world or "office,1000") for m in _csv(args.map)]
        for w, mk in combos:
            for n in ns:
                for rep in range(args.reps or 1):
                    curve.append(_run(spec(w, mk, n), pools, rep))
    meta = {
        "command": "python -m bench.bench_fleet "
        + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv)),
        "commit": git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(),
        "workers": workers,
        "rate": args.rate,
        "duration": args.duration,
        "load_before": load_before,
        "load_after": _load(),
        "note": args.note,
    }
    failed = False
    print()
    for r in cold:
        failed |= not cold_ok(r)
    if cold:
        print(f"# cold start: {sum(cold_ok(r) for r in cold)} of {len(cold)} runs meet it")
    if line:
        failed |= not all(line_ok(r) for r in line)
        print(f"# capacity line: {sum(line_ok(r) for r in line)} of {len(line)} runs meet it")
    if curve:
        for (w, m), n in largest(curve).items():
            print(f"# largest fleet meeting the line, {world_name(w)} {m}: {n}")
    print(f"# load after: {meta['load_after']}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report(meta, cold, line, curve))
        print(f"# wrote {args.out}")
    if args.json is not None:
        args.json.write_text(
            json.dumps({"meta": meta, "cold": cold, "line": line, "curve": curve}, default=str)
        )
    return 2 if failed and (args.acceptance or args.cold) else 0


if __name__ == "__main__":
    sys.exit(main())
