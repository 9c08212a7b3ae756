"""The decision's threshold from the false-fix rate on the tuning split.

``python -m bench.calibrate_llr DIR [DIR ...] [--results docs/results]``
``python -m bench.calibrate_llr --pass DIR [DIR ...] [--results docs/results]``

Reads the per-trial tables that ``python -m bench.bench_global --drive --calibrate DIR`` writes
(tuning maps only: the office, generated buildings below 1000, the logs intel and fr079): for
every searching scan with a reference, the travel (m), the decision's LLR (nats,
:mod:`service.core.reloc.decision`), the leader's position and heading error and whether its
self-similarity check ran and how many searches found it, its LLR against the unseen place
alone and whether one of the best 5 places kept holds the true place. In those runs nothing is
ever fixed, so each table shows what every threshold ``T`` would have done: the first scan
whose leader has been checked and reaches ``T`` is the fix; it is a false fix when the leader
is more than 0.5 m or 10 degrees off. (Counting every such leader
as a false fix is conservative: the tracker's confirmation and a floor plan's probation
catch some of them.)

Per map kind it prints, for a grid of thresholds, the false fixes, the trials fixed within the
travel limit and the median travel to the fix, and the smallest threshold with no false fix;
the rule for a preset's ``fix_llr`` is that threshold times :data:`SAFETY` (the held-out maps
are not the tuning maps). Where every threshold of the grid leaves some false ones, the rule
takes the smallest threshold at the fewest: those no threshold removes are the sensor model's
to remove, not the threshold's (docs/decisions/0029). It then counts why the slow first fixes
are slow (:func:`cause`). With ``--results`` it writes
``llr-threshold.md`` there, naming the command and commit that wrote the tables (the
directory's ``command.txt``) and each preset's ``fix_llr``.

With ``--pass`` it reads the tables of ``--calibrate-pass DIR`` instead: one row per judged
probation scan (a floor plan's winner, tracked ``probation_travel`` metres, judged on every scan
from then on; a calibration drive starts with no pose, so these are first fixes), where no
probation ever passed. A run whose probations never pass is, up to its first pass, the run of
every pass threshold ``P``; so the first judged scan whose winner leads at ``P`` or more is that
threshold's fix, false when the winner is more than 0.5 m or 10 degrees off, and the count is
exact. The rule for a preset's ``pass_llr`` is as for ``fix_llr``; the page is
``llr-probation.md``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.global_drive import FIX_DEG, FIX_DIST
from bench.global_drive_run import COMMAND_FILE
from bench.results import publish
from service.core.reloc.config import GlobalConfig

#: The preset's threshold is the smallest one without a false fix on the tuning split times
#: this: a margin for maps the tuning split has not seen.
SAFETY = 1.25
#: Travel limits (m) as the drive bench's: metric maps of the simulated buildings and office
#: 5 m, floor plans and the real logs 15 m.
GRID = (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 15.0, 20.0, 25.0, 30.0, 40.0, 60.0)
#: Pass thresholds: a probation passes at fix_llr or more, and a calibration drive ends once a
#: right winner leads at CALIBRATE_STOP (80), so every threshold up to it is counted exactly.
PASS_GRID = tuple(float(t) for t in range(25, 85, 5))
GRID_TOP = {False: GRID[-1], True: PASS_GRID[-1]}


def load(dirs: list[Path]) -> dict[str, list[tuple[str, np.ndarray]]]:
    out: dict[str, list[tuple[str, np.ndarray]]] = {"metric": [], "schematic": []}
    for d in dirs:
        for f in sorted(d.glob("*.npy")):
            group, world, kind, _start = f.stem.split("_")
            if group == "worlds" and int(world.split("@")[0]) >= 1000:
                continue  # held out: never calibrated on
            if group == "real" and world == "mit-csail":
                continue
            out[kind].append((f"{group}:{world}", np.load(f)))
    return out


def is_right(err: np.ndarray | float, dth: np.ndarray | float) -> np.ndarray:
    """Whether a leader ``err`` m and ``dth`` rad off is the true place: within the drive
    bench's FIX_DIST and FIX_DEG (``bench.global_drive.fix_ok``)."""
    return np.asarray((np.asarray(err) <= FIX_DIST) & (np.asarray(dth) <= np.deg2rad(FIX_DEG)))


def outcome(rows: np.ndarray, t: float) -> tuple[str, float]:
    """``("right" | "wrong" | "none", travel)`` of one trial at threshold ``t``."""
    for travel, llr, err, dth, checked, _found in rows[:, :6]:
        if llr >= t and checked >= 1.0:
            ok = bool(is_right(err, dth))
            return ("right" if ok else "wrong"), float(travel)
    return "none", float("inf")


def pass_outcome(rows: np.ndarray, p: float) -> tuple[str, float]:
    """``("right" | "wrong" | "unjudged" | "none", travel)`` of one trial whose probations
    pass at ``p``; unjudged: its winner was never on a scan with a reference."""
    for travel, llr, err, dth, lead in rows:  # p >= fix_llr: a winner short of it failed
        if lead >= 1.0 and llr >= p:
            if np.isnan(err):
                return "unjudged", float(travel)
            ok = bool(is_right(err, dth))
            return ("right" if ok else "wrong"), float(travel)
    return "none", float("inf")


#: A first fix later than this (m of travel) is slow; the causes are counted from this travel
#: on (a floor plan's probation_travel: before it no winner can be published).
SLOW = 8.0
CAUSES_FROM = 2.0
CAUSES = {
    "not found": "none of the best 5 places the search keeps holds the true place",
    "not leading": "one of them holds it, another leads",
    "places": "it leads; the other places found hold its LLR short",
    "unseen": "it leads; the unseen place alone holds its LLR short",
}


def cause(rows: np.ndarray, need: float, limit: float) -> str | None:
    """Why a trial's true place is fixed at ``need`` nats only after :data:`SLOW` m (``None``:
    it is not, or the table predates the LLR's split): the cause (:data:`CAUSES`) of most of
    its searching scans from :data:`CAUSES_FROM` m to that fix or ``limit``."""
    if rows.shape[1] < 8 or not rows.size:
        return None
    travel, llr, err, dth, unseen, held = rows[:, [0, 1, 2, 3, 6, 7]].T
    right = is_right(err, dth)
    fixed = travel[right & (llr >= need)]
    at = float(fixed[0]) if fixed.size else np.inf
    span = (travel >= CAUSES_FROM) & (travel < min(at, limit))
    if at <= SLOW or not span.any():
        return None
    per_scan = np.where(
        ~right,
        np.where(held >= 1.0, "not leading", "not found"),
        np.where(unseen < need, "unseen", "places"),
    )[span]
    names, counts = np.unique(per_scan, return_counts=True)
    return str(names[int(np.argmax(counts))])


def causes_lines(trials: list[tuple[str, np.ndarray]], kind: str, need: float) -> list[str]:
    """The page's account of the slow first fixes of ``kind`` at ``need`` nats."""
    if not any(r.ndim == 2 and r.shape[1] >= 8 for _, r in trials):
        return []  # tables written before the LLR's split
    slow = [c for n, r in trials if (c := cause(r, need, limit_of(n, kind))) is not None]
    parts = "; ".join(f"{CAUSES[c]}: {slow.count(c)}" for c in CAUSES)
    return [
        f"Slow first fixes (the true place fixed at {need:g} nats only after {SLOW:g} m or "
        f"never): {len(slow)} of {len(trials)}. By what held most of their scans "
        f"from {CAUSES_FROM:g} m on: {parts}.",
        "",
    ]


def limit_of(name: str, kind: str) -> float:
    return 15.0 if kind == "schematic" or name.startswith("real") else 5.0


def source(dirs: list[Path]) -> list[str]:
    """Each directory's command and commit (``command.txt``), as lines of the page."""
    out = []
    for d in dirs:
        f = d / COMMAND_FILE
        if f.is_file():
            cmd, _, rev = f.read_text(encoding="utf-8").partition("\n")
            out.append(f"- `{cmd.strip()}` at commit {rev.strip() or 'unknown'}")
        else:
            out.append(f"- {d} (no {COMMAND_FILE}: the command is not known)")
    return out


FIX_TEXT = (
    "Per-trial tables written by (`--calibrate`: the decision never fixes):",
    "At a threshold T the first scan whose leader was checked and reaches T counts as the "
    "fix, false when the leader is more than 0.5 m or 10 degrees off. On floor plans the "
    "preset then tracks the winner for `probation_travel` metres and fixes it at `pass_llr` "
    "(docs/results/llr-probation.md), which this count does not model: it counts more false "
    "fixes than the localiser makes. Definitions: `bench/calibrate_llr.py`.",
)
PASS_TEXT = (
    "Per-trial tables written by (`--calibrate-pass`: no probation ever passes):",
    "A winner enters probation at `fix_llr` and is tracked `probation_travel` metres; from "
    "then on each scan's decision passes it at P, fails it if it no longer leads at `fix_llr`, "
    "else goes on. At a pass threshold P the first such scan whose winner leads at P or "
    "more counts as the fix, false when the winner is more than 0.5 m or 10 degrees off "
    "(unjudged: its winner was never on a scan with a reference). Up to that end the run is "
    "the run at P, so the count is exact; the tracker's checks after a fix, which catch some "
    "wrong ones, are not counted. Definitions: `bench/calibrate_llr.py`.",
)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument(
        "--pass",
        dest="probation",
        action="store_true",
        help="the probation's pass from --calibrate-pass tables (llr-probation.md)",
    )
    ap.add_argument("--results", type=Path, default=None, help="write the page here")
    args = ap.parse_args(argv)
    data = load(args.dirs)
    judge, (intro, rule) = (pass_outcome, PASS_TEXT) if args.probation else (outcome, FIX_TEXT)
    what = "pass" if args.probation else "fix"
    lines = [
        "# The probation's pass from the tuning split"
        if args.probation
        else "# The decision's threshold from the tuning split",
        "",
        intro,
        "",
        *source(args.dirs),
        "",
        rule,
        "",
    ]
    for kind, trials in data.items():
        preset = GlobalConfig.for_kind(kind)
        if not trials or (args.probation and not preset.probation_travel):
            continue
        lines += [
            f"## {kind} ({len(trials)} tuning trials)",
            "",
            f"| T (nats) | false {what}es | fixed within limit | travel to fix p50 m |"
            + (" unjudged |" if args.probation else ""),
            "|---|---|---|---|" + ("---|" if args.probation else ""),
        ]
        counts: list[tuple[int, float]] = []
        for t in PASS_GRID if args.probation else GRID:
            res = [(judge(r, t), n) for n, r in trials]
            wrong = sum(o == "wrong" for (o, _), _ in res)
            within = sum(o == "right" and tr <= limit_of(n, kind) for (o, tr), n in res)
            travel = [tr for (o, tr), _ in res if o == "right"]
            p50 = float(np.median(travel)) if travel else float("nan")
            blind = sum(o == "unjudged" for (o, _), _ in res)
            lines.append(
                f"| {t:g} | {wrong} | {within}/{len(res)} | {p50:.2f} |"
                + (f" {blind} |" if args.probation else "")
            )
            counts.append((wrong, t))
        least, best = min(counts)  # the fewest false ones, at the smallest threshold
        pick = f"{best:g} x {SAFETY} = {best * SAFETY:g}"
        preset_line = (
            f"The preset's `pass_llr`: {max(preset.pass_llr, preset.fix_llr):g}, "
            f"entered at `fix_llr` {preset.fix_llr:g}."
            if args.probation
            else f"The preset's `fix_llr`: {preset.fix_llr:g}, probation "
            f"{preset.probation_travel:g} m."
        )
        head = (
            f"Smallest threshold without a false {what}"
            if least == 0
            else f"No threshold up to {GRID_TOP[args.probation]:g} is without a false {what}; "
            f"the smallest at the fewest ({least})"
        )
        lines += ["", f"{head}: {pick}. {preset_line}", ""]
        if not args.probation:  # at what the preset publishes: pass_llr on floor plans
            lines += causes_lines(trials, kind, max(preset.fix_llr, preset.pass_llr))
    text = "\n".join(lines) + "\n"
    print(text)
    page = "llr-probation" if args.probation else "llr-threshold"
    publish(args.results, page, text, ["bench.calibrate_llr", *(argv or sys.argv[1:])])
    return 0


if __name__ == "__main__":
    sys.exit(main())
