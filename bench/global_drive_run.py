"""Running the drive benchmark of ``bench_global.py --drive``: the trial itself
(:func:`run_drive_trial`: feed the scans, time and score them), making each map's tour and
view index ready (:func:`prepare_drive_map`), the process pool (:func:`_pool_map`) and
:func:`drive_main` (starts, trials, tables, ``drive.md`` / ``drive.csv``). The functions given
to the pool (:func:`run_drive_trial`, :func:`_prepare_job`) are module-level, so spawned
workers import them from here.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import shlex
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from bench.global_drive import (
    DRIVE_MARGIN,
    FIX_DEG,
    FIX_DIST,
    GROUPS,
    HOLDS_RUN,
    REAL_LOGS,
    DriveMap,
    DriveSource,
    DriveTask,
    DriveTrial,
    choose_starts,
    classify,
    drive_localizer,
    drive_maps,
    drive_source,
    fed_scans,
    fix_ok,
    holds_from,
    hypotheses_of,
    load_average,
    map_stride,
    office_room,
    parse_worlds,
    pose_error,
    spread,
    trial_end,
)
from bench.global_drive_tables import (
    SHARE_SPLIT,
    drive_table,
    room_table,
    share_table,
    write_drive_csv,
)
from bench.plan_share import HOLDS_SHARE, PlanShare
from bench.results import publish
from service.core.factory import create_localizer

_PLANS: dict[DriveMap, PlanShare] = {}


def plan_share_of(m: DriveMap, src: DriveSource) -> PlanShare:
    """The plan-share test of ``m``'s map (kept in this process)."""
    if m not in _PLANS:
        _PLANS[m] = PlanShare(src.map_data)
    return _PLANS[m]


def prepare_drive_map(m: DriveMap, data: str, cache: str, stride: int) -> dict[str, Any]:
    """Load the tour and make its map's view index ready (built or loaded from ``cache``);
    returns the tour's travel and scored scans for the start choice, and the index figures."""
    t0 = time.perf_counter()
    src = drive_source(m, Path(data), stride)
    t1 = time.perf_counter()
    loc = drive_localizer(src.map_data, cache)
    idx = getattr(loc, "index", None)
    t2 = time.perf_counter()
    return {
        "map": m,
        "travel": src.travel,
        "scored": src.scored,
        "scans": len(src.travel),
        "tour_m": float(src.travel[-1]) if len(src.travel) else 0.0,
        "load_s": t1 - t0,
        "index_s": t2 - t1,
        "viewpoints": len(idx.viewpoints) if idx is not None else -1,
        "units": len(idx) if idx is not None else -1,
    }


def _prepare_job(args: tuple[DriveMap, str, str, int]) -> dict[str, Any]:
    return prepare_drive_map(*args)


_WARM: set[DriveMap] = set()


def _warm(m: DriveMap, src: DriveSource, cache: str) -> None:
    """Before the first timed trial of ``m`` in this process: its view index into memory (the
    service loads it once per map, not per robot) and, on this process' first map, a few
    untimed searching and tracking updates (numba kernels loaded from their on-disk cache, or
    compiled)."""
    if m in _WARM:
        return
    loc = drive_localizer(src.map_data, cache)
    getattr(loc, "index", None)
    if not _WARM:
        scored = np.flatnonzero(src.scored)
        i0 = int(scored[0]) if scored.size else 0
        n = min(3, len(src.travel) - i0)
        for i in range(i0, i0 + n):
            loc.update(*src.scan(i), src.odom(i))
        trk = create_localizer("shape", src.map_data, src.truth[i0].copy())
        for i in range(i0, i0 + n):
            trk.update(*src.scan(i), src.odom(i))
    _WARM.add(m)


#: A calibration trial ends once the true place's LLR reaches this (nats): below it, the trial
#: shows what every threshold does.
CALIBRATE_STOP = 80.0
#: The file in a calibration directory naming the command and commit that wrote its tables.
COMMAND_FILE = "command.txt"


def run_drive_trial(task: DriveTask) -> DriveTrial:
    """Run one trial (see the docstring of ``bench_global.py``)."""
    m = task.map
    src = drive_source(m, Path(task.data), task.stride)
    _warm(m, src, task.cache)
    need = m.limit + DRIVE_MARGIN
    end = trial_end(src.travel, task.start, need)
    idx = fed_scans(task.start, end, src.stride, src.scored)
    loc = drive_localizer(src.map_data, task.cache, task.budget)
    rows: list[tuple[float, ...]] = []
    if task.calibrate:
        loc.gconfig = loc.gconfig.model_copy(update={"fix_llr": math.inf})
    if task.calibrate_pass:
        loc.gconfig = loc.gconfig.model_copy(update={"pass_llr": math.inf})
    ends: list[tuple[float, ...]] = []
    nan = (math.nan, math.nan)  # a winner never seen on a scan with a reference
    winner = nan  # the probation's winner's error and heading error on its last scored scan
    status: list[str] = []
    work: list[float] = []
    close: list[bool | None] = []
    after: list[bool | None] = []
    travel: list[float] = []
    cpu: list[float] = []
    search_ms: list[float] = []
    hyps: list[float] = []
    flags: list[bool] = []
    shares: list[float] = []
    share_travel: list[float] = []
    plan = plan_share_of(m, src)
    prev = "initializing"
    t_start = time.perf_counter()
    t0_travel = float(src.travel[task.start])
    for i in idx:
        r, a = src.scan(i)
        searching = getattr(loc, "searching", None)
        if not isinstance(searching, bool):
            searching = prev != "tracking"
        c0 = time.process_time()
        w0 = time.perf_counter()
        est = loc.update(r, a, src.odom(i))
        w1 = time.perf_counter()
        cpu.append(time.process_time() - c0)
        prev = est.status
        status.append(est.status)
        travel.append(float(src.travel[i]) - t0_travel)
        t = src.truth[i]
        scored = bool(np.all(np.isfinite(t)))
        if scored:
            shares.append(plan.scan_share(t, r, a))
            share_travel.append(travel[-1])
        close.append(fix_ok(est.pose, t) if scored else None)
        after.append(bool(src.after(i, est.pose)) if scored else None)
        flags.append(searching)
        if task.calibrate and scored and "llr" in est.extras:
            x = est.extras
            cands = est.candidates if est.candidates is not None else np.zeros((0, 4))
            rows.append(
                (
                    travel[-1],
                    x["llr"],
                    *pose_error(est.pose, t),
                    x.get("lead_checked", 0.0),
                    x.get("lead_found", 0.0),
                    x.get("llr_unseen", math.nan),
                    float(any(fix_ok(c[:3], t) for c in cands)),  # one of the best 5 holds it
                )
            )
            if x["llr"] >= CALIBRATE_STOP and rows[-1][2] <= 0.5:
                break  # any threshold up to CALIBRATE_STOP would have fixed the true place
        x = est.extras
        if task.calibrate_pass and scored and "probation" in x:  # the winner's tracked pose
            winner = pose_error(est.pose, t)
        if task.calibrate_pass and "probation_llr" in x:
            ends.append((travel[-1], x["probation_llr"], *winner, x["probation_lead"]))
            if x["probation_llr"] >= CALIBRATE_STOP and winner[0] <= 0.5 and x["probation_lead"]:
                break  # any pass threshold up to CALIBRATE_STOP would have fixed it here
        if task.calibrate_pass and "probation_failed" in x:
            winner = nan
        if searching:
            search_ms.append(1e3 * (w1 - w0))
            work.append(float(getattr(loc, "work_ms", math.nan)))
            h = hypotheses_of(est)
            if h is not None:
                hyps.append(h)
    wall = time.perf_counter() - t_start
    if task.calibrate:
        Path(task.calibrate).mkdir(parents=True, exist_ok=True)
        tag = f"{m.group}_{m.world}_{m.kind}_{task.start}"
        np.save(
            Path(task.calibrate) / f"{tag}.npy", np.asarray(rows, dtype=np.float64).reshape(-1, 8)
        )
    if task.calibrate_pass:
        Path(task.calibrate_pass).mkdir(parents=True, exist_ok=True)
        tag = f"{m.group}_{m.world}_{m.kind}_{task.start}"
        ends_a = np.asarray(ends, dtype=np.float64).reshape(-1, 5)
        np.save(Path(task.calibrate_pass) / f"{tag}.npy", ends_a)
    out = classify(status, close, after, travel, m.limit)
    s0 = src.truth[task.start]
    sm = np.asarray(search_ms)
    return DriveTrial(
        group=m.group,
        world=m.world,
        map=m.kind,
        setup="" if m.setup is None else str(m.setup),
        trial=task.trial,
        start=task.start,
        start_x=float(s0[0]),
        start_y=float(s0[1]),
        room=office_room(float(s0[0]), float(s0[1])) if m.group == "office" else "",
        stride=src.stride,
        limit_m=m.limit,
        scans=len(idx),
        scored=sum(c is not None for c in close),
        travel_m=travel[-1],
        truncated=travel[-1] <= need,
        found=out.found,
        within_limit=out.within_limit,
        fix_scans=-1 if out.fix is None else out.fix + 1,
        fix_travel_m=out.fix_travel,
        cpu_to_fix_s=math.nan if out.fix is None else float(sum(cpu[: out.fix + 1])),
        cpu_total_s=float(sum(cpu)),
        first_fix_wrong=out.first_fix_wrong,
        wrong_before_fix=out.wrong_before_fix,
        wrong_after_fix=out.wrong_after_fix,
        tracking_after_fix=out.tracking_after_fix,
        search_after_fix=0 if out.fix is None else sum(flags[out.fix + 1 :]),
        search_scans=int(sm.size),
        search_ms_max=float(sm.max()) if sm.size else math.nan,
        search_ms_p99=float(np.percentile(sm, 99)) if sm.size else math.nan,
        work_max=float(np.nanmax(work)) if work and not np.all(np.isnan(work)) else math.nan,
        hyp_sum=float(sum(hyps)),
        hyp_scans=len(hyps),
        wall_s=wall,
        plan_share=float(np.nanmean(shares)) if np.any(np.isfinite(shares)) else math.nan,
        holds_from_m=holds_from(share_travel, shares),
        search_ms=search_ms,
    )


def _pool_map(
    fn: Callable[[Any], Any], items: Sequence[Any], jobs: int
) -> Iterator[tuple[int, Any]]:
    """``(position, fn(item))`` in completion order; in this process when ``jobs`` <= 1.
    Every process first compiles or loads the core's numba kernels
    (:func:`service.core.warmup.warm_up`), as the service does at start-up, so no trial's
    CPU counts it (after a kernel changes, compiling took ~5 s of the first trial per process)."""
    from service.core.warmup import warm_up

    if jobs <= 1:
        warm_up()
        for k, it in enumerate(items):
            yield k, fn(it)
        return
    from concurrent.futures import as_completed

    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=warm_up) as ex:
        futs = {ex.submit(fn, it): k for k, it in enumerate(items)}
        for f in as_completed(futs):
            yield futs[f], f.result()


def drive_main(args: argparse.Namespace, argv: Sequence[str]) -> int:
    """Run the drive trials and write the tables (see the docstring of ``bench_global.py``)."""
    from bench.bench_real import git_commit

    groups = [g.strip() for g in args.groups.split(",") if g.strip()]
    bad = [g for g in groups if g not in GROUPS]
    logs = [g.strip() for g in args.logs.split(",") if g.strip()]
    bad += [g for g in logs if g not in REAL_LOGS]
    if bad or not groups:
        raise SystemExit(f"unknown group or log: {bad or args.groups}")
    if "real" in groups and not Path(args.data).is_dir():
        raise SystemExit(f"{args.data}: no real-log directory (--data, or drop group 'real')")
    seeds = parse_worlds(args.worlds)
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    if not kinds or any(k not in ("metric", "schematic") for k in kinds):
        raise SystemExit(f"--kinds: metric and/or schematic, got {args.kinds!r}")
    maps = drive_maps(groups, seeds, logs, kinds, args.clutter)
    cap = args.quick if args.quick is not None else 1 << 30
    cache = str(Path(args.cache).resolve())
    data = str(Path(args.data).resolve())
    command = "python -m bench.bench_global " + shlex.join(argv)
    commit = git_commit()
    load0 = load_average()
    date = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    print(f"{command}\ncommit {commit}, {date}, load average at start: {load0}", flush=True)
    t_all = time.perf_counter()

    # 1. tours loaded and view indexes made ready, one task per map
    info: dict[DriveMap, dict[str, Any]] = {}
    strides = {m: map_stride(m, args.stride1, args.real_stride) for m in maps}
    prep = [(m, data, cache, strides[m]) for m in maps]
    for k, r in _pool_map(_prepare_job, prep, args.jobs):
        info[maps[k]] = r
        print(
            f"ready: {maps[k].label()}: {r['scans']} scans, {r['tour_m']:.1f} m tour, "
            f"index {r['index_s']:.1f} s ({r['viewpoints']} viewpoints)",
            flush=True,
        )
    t_prep = time.perf_counter() - t_all

    # 2. start scans
    per_world = {
        kind: dict(zip(seeds, spread(args.starts, len(seeds)), strict=True))
        for kind in ("metric", "schematic")
    }
    notes: list[str] = []
    tasks: list[DriveTask] = []
    for m in maps:
        if m.group == "office":
            want = args.starts
        elif m.group == "worlds":
            want = per_world[m.kind][m.seed]
        else:
            want = args.real_starts
        want = min(want, cap)
        r = info[m]
        need = m.limit + DRIVE_MARGIN
        rng = np.random.default_rng([args.seed, *m.code()])
        eligible = r["scored"] if m.group == "real" else None
        starts = choose_starts(r["travel"], need, want, rng, eligible)
        if want > 0 and starts.size == 0:
            notes.append(
                f"{m.label()}: SKIPPED, the tour ({r['tour_m']:.1f} m) leaves no start scan with "
                f"{need:.0f} m of travel after it"
            )
        elif starts.size < want:
            notes.append(f"{m.label()}: only {starts.size} distinct start scans (of {want})")
        budget = args.budget_ms if args.budget_ms > 0 else None
        tasks += [
            DriveTask(
                m, int(s), k, data, cache, strides[m], budget, args.calibrate, args.calibrate_pass
            )
            for k, s in enumerate(starts)
        ]
    for n in notes:
        print(n)
    for out in (args.calibrate, args.calibrate_pass):
        if out:
            # the threshold's page (bench/calibrate_llr.py) names the run its tables come from
            Path(out).mkdir(parents=True, exist_ok=True)
            (Path(out) / COMMAND_FILE).write_text(f"{command}\n{commit}\n", encoding="utf-8")

    # 3. trials: grouped by map, so that each process loads each index once; the longest
    # (real logs, then floor plans) first, so that both processes finish together
    order = {m: k for k, m in enumerate(maps)}
    rank = {"real": 0, "worlds": 1, "office": 1}
    tasks.sort(key=lambda t: (rank[t.map.group], t.map.kind == "metric", order[t.map], t.trial))
    trials: list[DriveTrial] = []
    t_run = time.perf_counter()
    for done, (_, t) in enumerate(_pool_map(run_drive_trial, tasks, args.jobs), 1):
        trials.append(t)
        fix = f"fixed at {t.fix_travel_m:.2f} m" if t.found else "NOT found"
        print(
            f"[{done}/{len(tasks)}] {DriveMap(t.group, t.world, t.map).label()} start {t.start}: "
            f"{fix}{' FIRST-FIX WRONG' if t.first_fix_wrong else ''}"
            f"{f' after-fix wrong {t.wrong_after_fix}' if t.wrong_after_fix else ''}, "
            f"{t.scans} scans, cpu {t.cpu_total_s:.1f} s, wall {t.wall_s:.1f} s "
            f"({time.perf_counter() - t_run:.0f} s)",
            flush=True,
        )
    wall = time.perf_counter() - t_all
    trials.sort(key=lambda t: (order[DriveMap(t.group, t.world, t.map)], t.trial))
    load1 = load_average()

    # 4. tables
    table = drive_table(trials, maps)
    rooms = room_table(trials)
    shares = share_table(trials, maps)
    idx_lines = [
        "| map | scans | tour m | index ready s | viewpoints | units |",
        "|---|---|---|---|---|---|",
    ]
    idx_lines += [
        f"| {m.label()} | {info[m]['scans']} | {info[m]['tour_m']:.1f} | "
        f"{info[m]['index_s']:.1f} | {info[m]['viewpoints']} | {info[m]['units']} |"
        for m in maps
    ]
    print("\n" + table)
    if rooms:
        print("Office, by room of the start pose: found <= limit / trials, median travel to fix")
        print(rooms)
    summary = (
        f"{len(trials)} trials in {wall:.0f} s wall ({t_prep:.0f} s loading tours and indexes) "
        f"with {args.jobs} process(es); load average at start {load0}, at end {load1}"
    )
    print("Found <= limit / trials by the drive's plan share (bench/plan_share.py):")
    print(shares)
    print(summary)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_drive_csv(out / "drive.csv", trials)
    md = [
        "# Global localisation while driving",
        "",
        f"Generated by `{command}` at commit {commit} on {date}, on the shared 2-core "
        f"machine: {summary}.",
        "",
        *(
            [
                f"**Smoke run** (`--quick {args.quick}`: at most {args.quick} starts per map and "
                "world): a check of the benchmark, too few trials for its figures.",
                "",
            ]
            if args.quick is not None
            else []
        ),
        "Each trial starts at a random scan of a tour with no initial pose and feeds every "
        "following scan with its odometry until the travel exceeds the limit + "
        f"{DRIVE_MARGIN:.0f} m. Found = the first `tracking` estimate within {FIX_DIST} m and "
        f"{FIX_DEG:.0f} deg of the truth; travel = true step lengths in simulation, odometry "
        "step lengths on the real logs (scored only on scans with a flag-1 reference); "
        "confident wrong first fix = a `tracking` estimate failing that test before the "
        "correct fix; after the fix = `tracking` estimates failing the tour's own test "
        "(setup 1: 100 mm / 45 deg, setup 2: 500 mm / 45 deg, real logs: 0.5 m); searching "
        "again = trials that lost the track after the correct fix and searched again; CPU = "
        "`time.process_time` of the updates up to the fix; percentiles over all trials, a "
        "trial not found counts as infinite (n/f). Full definitions: the docstring of "
        "`bench/bench_global.py`. One row per trial in `drive.csv`.",
        "",
        table,
    ]
    if notes:
        md += ["Notes:", "", *[f"- {n}" for n in notes], ""]
    md += [
        "Found <= limit / trials by the trial's plan share (`bench/plan_share.py`): the mean "
        "share of its returns within 0.3 m of a mapped wall at the reference pose. Below "
        f"{SHARE_SPLIT} the map shows less than half of what the robot sees (a hall drawn as "
        "its outline on a floor plan): a limit of the map rather than of the localiser. "
        "Each trial not fixed within the limit is listed by its start scan with the travel "
        f"from which the map holds (the first of {HOLDS_RUN} referenced scans in a row with a "
        f"share of at least {HOLDS_SHARE}) and the travel to its fix.",
        "",
        shares,
    ]
    if rooms:
        md += [
            "Office, by room of the start pose (`office_room`): found <= limit / trials, "
            "median travel to a fix (over all trials, n/f = not found), first-fix confident "
            "wrong if any.",
            "",
            rooms,
        ]
    md += ["Tours and view indexes (index ready: built, or loaded from the cache):", ""]
    md += [*idx_lines, ""]
    (out / "drive.md").write_text("\n".join(md), encoding="utf-8")
    print(f"wrote {out / 'drive.md'} and {out / 'drive.csv'}")
    publish(args.results, "drive", "\n".join(md), ["bench.bench_global", *argv])
    return 0
