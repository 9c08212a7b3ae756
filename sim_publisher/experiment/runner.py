"""Running the Table-1 experiment: each method over the scans of each setup.

:func:`run_method` feeds one setup's scans to one fresh localiser; :func:`run_experiment` runs
every (setup, method) pair, in this process or in a process pool (``_worker`` and
``_init_worker`` run in the pool's processes and are pickled by their qualified names here),
with a progress bar on stderr (tqdm), and writes the outputs (:mod:`.output`).
"""

from __future__ import annotations

import multiprocessing as mp
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from service.core.types import wrap_angle
from service.errors import LocalizationError
from sim_publisher.experiment.output import write_outputs
from sim_publisher.experiment.results import (
    EXPERIMENT_METHODS,
    PROXIMITY,
    ExperimentResult,
    MethodRun,
    SetupInfo,
)
from sim_publisher.results_page import Provenance
from sim_publisher.scenario import Setup, make_setup, run_stats

#: Relative cost per scan used only to start the slowest runs first.
_COST = {"shape": 6.0, "shape-paper": 6.0, "shape-tracker": 6.0, "icp": 1.0, "lines": 1.0}


def run_method(
    setup_obj: Any,
    setup_id: int,
    method: str,
    progress: Callable[[int], None] | None = None,
) -> MethodRun:
    """Run one method over all scans of one setup (``sim_publisher.scenario.Setup``)."""
    from service.core.factory import create_localizer

    truth = np.asarray(setup_obj.truth, dtype=np.float64)
    n = len(truth)
    if method == "shape-tracker":
        from service.core.tracking.localizer import ShapeLocalizer

        loc: Any = ShapeLocalizer(setup_obj.map_data, truth[0].copy(), None)
    elif method == "shape-paper":
        loc = create_localizer("shape", setup_obj.map_data, truth[0].copy(), laser_odometry=False)
    else:
        loc = create_localizer(method, setup_obj.map_data, truth[0].copy(), None)
    est = np.empty((n, 3), dtype=np.float64)
    statuses: list[str] = []
    seconds = 0.0
    failures = 0
    last = truth[0].copy()
    for i in range(n):
        ranges, angles = setup_obj.scan(i)
        t0 = time.perf_counter()
        try:
            e = loc.update(ranges, angles)
        except LocalizationError:
            failures += 1
            seconds += time.perf_counter() - t0
            est[i] = last
            statuses.append("lost")
        else:
            seconds += time.perf_counter() - t0
            last = np.asarray(e.pose, dtype=np.float64)
            est[i] = last
            statuses.append(str(e.status))
        if progress is not None and (i % 20 == 19 or i == n - 1):
            progress(i % 20 + 1)
    pos_err = np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1])
    head_err = np.abs(np.asarray(wrap_angle(est[:, 2] - truth[:, 2]), dtype=np.float64))
    searches = int(getattr(loc, "searches", 0) or 0)
    return MethodRun(
        setup_id, method, est, pos_err, head_err, tuple(statuses), seconds, failures, searches
    )


def _make_setup(setup_id: int, seed: int, max_scans: int | None) -> Setup:
    return make_setup(setup_id, seed=seed, max_scans=max_scans)


_COUNTER: Any = None


def _init_worker(counter: Any) -> None:
    global _COUNTER  # set once per worker process by the pool initializer
    _COUNTER = counter


def _bump(k: int) -> None:
    if _COUNTER is not None:
        with _COUNTER.get_lock():
            _COUNTER.value += k


def _worker(setup_id: int, method: str, seed: int, max_scans: int | None) -> MethodRun:
    return run_method(_make_setup(setup_id, seed, max_scans), setup_id, method, _bump)


def run_experiment(
    setups: Sequence[int] = (1, 2),
    methods: Sequence[str] = ("shape", "icp", "lines"),
    seed: int = 0,
    max_scans: int | None = None,
    out_dir: Path | None = Path("docs/results/experiment"),
    progress: bool = True,
    jobs: int = 2,
    plots: bool = True,
    command: str | None = None,
) -> ExperimentResult:
    """Run every ``method`` on every ``setup`` and write the results to ``out_dir``.

    ``max_scans`` shortens each run to its first scans. ``jobs`` > 1 runs the
    (setup, method) pairs in a process pool; results do not depend on it. ``out_dir`` ``None``
    writes nothing; ``command`` is the command line the results page names (default: this
    call). Raises :class:`LocalizationError` for an unknown setup or method.
    """
    setups = tuple(dict.fromkeys(int(s) for s in setups))
    methods = tuple(dict.fromkeys(methods))
    for s in setups:
        if s not in PROXIMITY:
            raise LocalizationError(f"unknown setup {s}; expected 1 or 2")
    for m in methods:
        if m not in EXPERIMENT_METHODS:
            raise LocalizationError(
                f"unknown method {m!r}; expected one of {', '.join(EXPERIMENT_METHODS)}"
            )
    if not setups or not methods:
        raise LocalizationError("nothing to run: no setup or no method selected")
    if max_scans is not None and max_scans < 1:
        raise LocalizationError(f"max_scans must be >= 1, got {max_scans}")
    if command is None:
        command = (
            f"sim_publisher.experiment.run_experiment(setups={setups}, methods={methods}, "
            f"seed={seed}, max_scans={max_scans})"
        )
    provenance = Provenance.capture(command)
    t_start = time.perf_counter()
    setup_objs = {s: _make_setup(s, seed, max_scans) for s in setups}
    infos = {s: _setup_info(s, o) for s, o in setup_objs.items()}
    result = ExperimentResult(seed=seed, max_scans=max_scans, setups=infos, provenance=provenance)
    tasks = [(s, m) for s in setups for m in methods]
    tasks.sort(key=lambda t: -infos[t[0]].scans * _COST.get(t[1], 1.0))
    total = sum(infos[s].scans for s, _ in tasks)
    bar = tqdm(total=total, unit="scan", desc="experiment", disable=not progress, file=sys.stderr)
    if jobs <= 1 or len(tasks) == 1:
        for s, m in tasks:
            result.runs[(s, m)] = run_method(setup_objs[s], s, m, bar.update)
    else:
        # fork where the platform has it (workers only run numpy code, and a script calling
        # run_experiment needs no __main__ guard); spawn elsewhere.
        method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
        ctx = mp.get_context(method)
        counter = ctx.Value("q", 0)
        with ProcessPoolExecutor(
            max_workers=min(jobs, len(tasks)),
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(counter,),
        ) as pool:
            futs: dict[Future, tuple[int, str]] = {
                pool.submit(_worker, s, m, seed, max_scans): (s, m) for s, m in tasks
            }
            pending = set(futs)
            while pending:
                finished, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                for f in finished:
                    result.runs[futs[f]] = f.result()
                bar.update(int(counter.value) - bar.n)
                bar.set_postfix(runs=f"{len(result.runs)}/{len(tasks)}")
    bar.close()
    result.wall_seconds = time.perf_counter() - t_start
    result.provenance = provenance.ended()
    if out_dir is not None:
        write_outputs(result, Path(out_dir), setup_objs if plots else None)
    return result


def _setup_info(setup_id: int, obj: Setup) -> SetupInfo:
    st = run_stats(obj.truth)
    return SetupInfo(
        setup=setup_id,
        name=str(getattr(obj, "name", f"setup {setup_id}")),
        map_id=obj.map_data.map_id,
        map_kind=obj.map_data.kind,
        scans=len(obj.truth),
        path_length_m=float(st["path_length_m"]),
        mean_step_mm=float(st["mean_step_mm"]),
        mean_rotation_deg=float(st["mean_rotation_deg"]),
    )
