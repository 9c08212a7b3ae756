"""Scale benchmark of the localizer service: N simulated robots at R Hz against one service.

Starts ``python -m service`` on a free loopback port and puts the maps the rows need. Each
row configures N *tracked* robots (initial pose = their true start pose) and K *searching*
robots (initial pose null: global localisation), primes every robot with one scan (so cold
costs — map models, the global-search view index, numba caches — stay out of the window),
then a separate publisher process sends every robot's scans at ``--rate`` Hz (robots
staggered within the period) while this process receives the poses. After the row the
robots' configs are deleted, so every row starts from an empty service with the same maps.

Worlds and maps (``--world``, ``--map``): ``office`` is the paper's office world; an integer
is a generated building (``sim_publisher.generator``, default parameters, no moving people;
seeds 0-19 are the tuning split of ``bench/bench_worlds.py``, >= 1000 held out). ``metric``
gives the service the exact metric map (setup 1's), ``schematic`` the schematic map (setup
2's). Scans are always simulated against the TRUE world (furniture included) along the
world's tour, sampled every 11 mm (setup 1) and taken every ``--stride`` samples (default 5:
~55 mm and ~19 deg mean turn between consecutive scans; the run prints the measured
statistics), with the setup's laser (361 beams over 180 deg, 15 m, 1 cm noise, 1 % dropouts).

Motion and odometry: every robot walks back and forth along the tour from its own start
(reversing, heading kept, at either end). ``--odom`` (default) sends an odometry pose with each
scan: the walk's true poses run through the simulator's odometry error model
(``sim_publisher.trajectory.simulate_odometry``: scale error, translational noise, rotational
drift per metre and noise), one noise stream per robot, over the whole walk including the
turnarounds, so the error accumulates continuously and the increments always match the motion
actually driven. The odometry is expressed in its own frame (the robot's first pose is the
origin), as a real robot's would be.

Searching robots (``--searching K``, ``--search-mode``): ``refix`` (default) sends them real
scans of the same world along the tour and re-puts their config with a null pose as soon as
one of their poses reports ``tracking``, so they run global searches back to back for the
whole window (the search, its confirmation and the twin check included; between a fix and
the new config a few scans are tracked, which the row reports as their tracking share).
``foreign`` sends them mirror images of the world's scans (beams reversed, odometry mirrored):
a building that does not exist, so the search never ends (a fix is re-put the same way).
They are assigned to workers like any robot (the least-loaded worker, after the tracked
robots), so about half the tracked robots share a worker with a searcher on two workers.

Figures per row, over the window (``--duration`` minus ``--warmup`` s; scans are assigned to
the window by their scheduled send time): *answered* = poses received / scans sent (mean over
tracked robots and the worst robot; below 100 % the service skipped older scans: latest
wins, or a pose came more than 1 s after the publisher stopped); latency p50/p99 = pose
receipt minus the scan's ``stamp`` (its send time: both Zenoh hops, decoding, queueing and the
localisation); *starved* = some tracked robot got no pose, or answered less than half the
mean; *correct* = answered poses within ``--correct-m`` (0.5 m) and ``--correct-deg``
(10 deg) of the scan's true pose, whatever their status; *confident wrong* = poses with status
``tracking`` failing that test; *lost* = tracked robots' poses whose status is not
``tracking``. The CPU columns are the service (with its workers) and the load generator (this
process and the publisher) in % of one core, and the 1-min load average at the window's end:
both share the machine's cores with the service.

``--acceptance`` runs the staggered fleet's acceptance table in one command: office metric and
schematic, held-out building 1000 metric and schematic, N=20 at 10 Hz; office metric N=40 at
5 Hz; and office metric N=20 at 10 Hz with K=0 and K=1 searching robots. It prints PASS/FAIL
per line: >= 99 % answered, p99 <= 50 ms, none starved; a searching robot adds <= 5 ms to the
tracked robots' p99. ``--out docs/results/service.md`` writes the tables as markdown with
the command, the git commit and the date.

Usage: ``python -m bench.bench_service [--robots 1,5,10,20,30] [--method shape]
[--world office,1000] [--map metric,schematic] [--rate 10] [--searching 0,1]
[--workers 2] [--duration 10] [--out FILE] [--json FILE]`` (every comma list is crossed into
rows), or ``python -m bench.bench_service --acceptance [--duration 20]
--out docs/results/service.md``.
Numbers depend on the machine load; the load average is printed with every row.

The work is split along its seams: ``scale_walks`` (worlds, scans, walks, odometry, robot
plans), ``scale_load`` (loopback Zenoh sessions, the publisher process, the pose receiver, CPU
accounting), ``scale_row`` (one row: run and summarise) and ``scale_report`` (acceptance,
tables, the markdown report); this script keeps the command line and re-exports their names.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from bench.harness import (
    REPO,
    ServiceStartError,
    client_config,
    free_endpoint,
    start_service,
    wait_ready,
)
from bench.scale_load import (
    MSGPACK,
    P,
    Receiver,
    health,
    publisher_main,
    scan_payload,
    tree_cpu_s,
)
from bench.scale_report import (
    ACCEPT_ANSWERED,
    ACCEPT_P99_MS,
    ACCEPT_SEARCH_ADDS_MS,
    METHOD_TEXT,
    PAIR_HEAD,
    ROW_HEAD,
    SEARCH_HEAD,
    acceptance_lines,
    acceptance_rows,
    fmt_num,
    git_commit,
    markdown_table,
    pair_cells,
    report,
    row_cells,
    row_ok,
    search_cells,
    search_pairs,
    text_table,
)
from bench.scale_row import Context, RowSpec, run_row, summarise_row
from bench.scale_walks import (
    Pool,
    RobotPlan,
    make_pool,
    mirror_poses,
    motion_stats,
    odometry_frame,
    ping_pong,
    plan_robots,
    pose_correct,
    walk_odometry,
    world_name,
)
from schemas.codec import encode

#: What this script offers its importers (tests, ``soak.py``, ``bench_cluster.py``): its own
#: command line and the names of the modules it was split into.
__all__ = [
    "ACCEPT_ANSWERED",
    "ACCEPT_P99_MS",
    "ACCEPT_SEARCH_ADDS_MS",
    "METHOD_TEXT",
    "MSGPACK",
    "PAIR_HEAD",
    "REPO",
    "ROW_HEAD",
    "SEARCH_HEAD",
    "Context",
    "P",
    "Pool",
    "Receiver",
    "RobotPlan",
    "RowSpec",
    "acceptance_lines",
    "acceptance_rows",
    "argv_of",
    "build_parser",
    "client_config",
    "free_endpoint",
    "git_commit",
    "health",
    "main",
    "make_pool",
    "markdown_table",
    "mirror_poses",
    "motion_stats",
    "odometry_frame",
    "pair_cells",
    "ping_pong",
    "plan_robots",
    "pose_correct",
    "publisher_main",
    "report",
    "row_cells",
    "row_ok",
    "run_row",
    "scan_payload",
    "search_cells",
    "search_pairs",
    "summarise_row",
    "text_table",
    "tree_cpu_s",
    "walk_odometry",
    "world_name",
]


# --------------------------------------------------------------------------- main


def _csv(s: str) -> list[str]:
    return [x.strip() for x in s.split(",") if x.strip()]


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="1,5,10,20,30", help="comma-separated N values")
    ap.add_argument("--method", default="shape", choices=["shape", "icp", "lines"])
    ap.add_argument(
        "--world", default="office", help="comma list: office and/or generated building seeds"
    )
    ap.add_argument("--map", default="metric", help="comma list: metric and/or schematic")
    ap.add_argument("--workers", type=int, default=None, help="service workers (default: cores)")
    ap.add_argument("--search-budget-ms", type=float, default=None, help="service's (default 50)")
    ap.add_argument("--rate", default="10", help="comma list of scans per second per robot")
    ap.add_argument("--searching", default="0", help="comma list of K searching robots")
    ap.add_argument(
        "--search-mode",
        default="refix",
        choices=["refix", "foreign"],
        help="searching robots: real scans, re-configured on every fix; or mirrored scans",
    )
    ap.add_argument(
        "--odom", action=argparse.BooleanOptionalAction, default=True, help="send odometry"
    )
    ap.add_argument("--duration", type=float, default=None, help="s per row (10; acceptance 20)")
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds ignored at the start")
    ap.add_argument("--stride", type=int, default=5, help="tour samples (11 mm) between scans")
    ap.add_argument("--correct-m", type=float, default=0.5)
    ap.add_argument("--correct-deg", type=float, default=10.0)
    ap.add_argument(
        "--acceptance", action="store_true", help="the staggered fleet's acceptance table"
    )
    ap.add_argument("--out", type=Path, default=None, help="write the markdown report here")
    ap.add_argument("--json", type=Path, default=None, help="write the raw rows here")
    ap.add_argument("--note", default="", help="a line quoted at the top of the --out report")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run the table; returns 0 (1 if the service failed; 2 if an acceptance line FAILs)."""
    args = build_parser().parse_args(argv)
    duration = args.duration or (20.0 if args.acceptance else 10.0)
    if duration <= args.warmup:
        raise SystemExit("--duration must exceed --warmup")
    if args.acceptance:
        specs = acceptance_rows()
    else:
        specs = [
            RowSpec(w, mk, int(n), float(rt), int(k))
            for w in _csv(args.world)
            for mk in _csv(args.map)
            for rt in _csv(args.rate)
            for k in _csv(args.searching)
            for n in _csv(args.robots)
        ]
    if any(s.k for s in specs) and args.method != "shape":
        raise SystemExit("searching robots need --method shape (global localisation)")
    pools: dict[tuple[str, str], Pool] = {}
    for s in specs:
        if (s.world, s.map_kind) not in pools:
            pools[(s.world, s.map_kind)] = make_pool(s.world, s.map_kind, args.stride)
    endpoint = free_endpoint()
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    load_before = _load()
    results: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        extra = ["--log-level", "warning"]
        if args.search_budget_ms is not None:
            extra += ["--search-budget-ms", str(args.search_budget_ms)]
        svc = start_service(
            Path(tmp) / "state",
            *extra,
            endpoint=endpoint,
            workers=workers,
            log_path=Path(tmp) / "service.log",
        )
        rec = None
        try:
            try:
                wait_ready(svc, 60.0)
            except ServiceStartError as exc:
                print(exc, file=sys.stderr)
                return 1
            session = zenoh.open(client_config(endpoint))
            with session:
                for pool in pools.values():
                    session.put(f"{P}/maps/{pool.map_id}", encode(pool.map_msg), encoding=MSGPACK)
                deadline = time.time() + 60
                while (h := health(session)) is None or h.maps < len(pools):
                    if time.time() > deadline:
                        raise RuntimeError("maps not stored in 60 s")
                    time.sleep(0.2)
                rec = Receiver(session)
                ctx = Context(
                    session=session,
                    endpoint=endpoint,
                    rec=rec,
                    svc_pid=svc.pid,
                    method=args.method,
                    duration=duration,
                    warmup=args.warmup,
                    odom=args.odom,
                    search_mode=args.search_mode,
                    correct_m=args.correct_m,
                    correct_deg=args.correct_deg,
                    pools=pools,
                )
                print(
                    f"# service: method={args.method} workers={workers} "
                    f"odom={'on' if args.odom else 'off'} search-mode={args.search_mode} "
                    f"window={duration - args.warmup:g} s; load before: {load_before}",
                    flush=True,
                )
                for i, spec in enumerate(specs):
                    r = run_row(ctx, spec, i)
                    results.append(r)
                    t = r["tracked"]
                    line = (
                        f"{spec.label}: answered {100 * t['answered_mean']:.1f} % (worst "
                        f"{100 * t['answered_min']:.1f} %), p50 {fmt_num(t['p50'])} p99 "
                        f"{fmt_num(t['p99'])} ms, starved {'yes' if t['starved'] else 'no'}, "
                        f"correct {fmt_num(100 * t['correct'], '.2f')} %, confident wrong "
                        f"{t['confident_wrong']}, svc CPU {r['svc_cpu']:.0f} %, load "
                        f"{r['load']:.2f} (prime {r['prime_s']:.1f} s, publisher lag p99 "
                        f"{fmt_num(r['pub_lag_p99'])} ms)"
                    )
                    if spec.k:
                        s = r["searchers"]
                        line += (
                            f"\n    searchers: answered {100 * s['answered_mean']:.1f} %, p50 "
                            f"{fmt_num(s['p50'])} p99 {fmt_num(s['p99'])} ms, searching "
                            f"{fmt_num(100 * s['searching_share'])} % of their poses, fixes "
                            f"{s['fixes']} ({s['fixes_correct']} correct)"
                        )
                    print(line, flush=True)
        finally:
            if rec is not None:
                rec.close()
            svc.stop(30.0)
    load_after = _load()
    worlds = []
    for s in specs:
        key = (s.world, s.map_kind)
        if any(w["key"] == key for w in worlds):
            continue
        pool = pools[key]
        worlds.append(
            {
                "key": key,
                "world": world_name(s.world),
                "map": s.map_kind,
                "map_id": pool.map_id,
                "scans": len(pool.ranges),
                "beams": pool.beams,
                **pool.motion,
            }
        )
    meta = {
        "command": "python -m bench.bench_service "
        + " ".join(shlex.quote(a) for a in argv_of(argv)),
        "commit": git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{os.cpu_count()} cores ({platform.machine()})",
        "method": args.method,
        "workers": workers,
        "budget": (
            f"{args.search_budget_ms:g} ms" if args.search_budget_ms is not None else "default"
        ),
        "odom": args.odom,
        "search_mode": args.search_mode,
        "window": duration - args.warmup,
        "warmup": args.warmup,
        "load_before": load_before,
        "load_after": load_after,
        "correct_m": args.correct_m,
        "correct_deg": args.correct_deg,
        "worlds": worlds,
        "note": args.note,
    }
    print()
    for w in worlds:
        print(
            f"# {w['world']} {w['map']}: {w['scans']} scans, {w['beams']} beams; step mean "
            f"{w['step_mean']:.3f} m p95 {w['step_p95']:.3f} m; turn mean "
            f"{w['turn_mean']:.1f} deg p95 {w['turn_p95']:.1f} deg"
        )
    print(text_table(ROW_HEAD, [row_cells(r) for r in results]))
    srch = [r for r in results if r["k"]]
    if srch:
        print()
        print(text_table(SEARCH_HEAD, [search_cells(r) for r in srch]))
        pairs = search_pairs(results)
        if pairs:
            print(text_table(PAIR_HEAD, [pair_cells(p) for p in pairs]))
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in results:
        groups.setdefault((r["world"], r["map"], r["rate"], r["k"]), []).append(r)
    for (w, mk, rt, k), rs in groups.items():
        if len(rs) > 1:
            best = max([r["n"] for r in rs if row_ok(r)], default=0)
            print(
                f"# {world_name(w)} {mk} {rt:g} Hz K={k}: largest N with p99 <= 50 ms, "
                f">= 99 % answered, none starved: {best}"
            )
    failed = False
    if args.acceptance:
        print("\n# acceptance (staggered fleet of 20 robots)")
        for name, ok, figs in acceptance_lines(results):
            failed |= not ok
            print(f"{'PASS' if ok else 'FAIL'}  {name}: {figs}")
    print(f"# load after: {load_after}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report(results, meta, args.acceptance))
        print(f"# wrote {args.out}")
    if args.json is not None:
        args.json.write_text(
            json.dumps({"meta": _jsonable(meta), "rows": _jsonable(results)}, indent=1)
        )
    return 2 if failed else 0


def argv_of(argv: list[str] | None) -> list[str]:
    return list(sys.argv[1:] if argv is None else argv)


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return None if math.isnan(f) else f
    if isinstance(v, np.integer):
        return int(v)
    return v


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


if __name__ == "__main__":
    sys.exit(main())
