"""Results pages of the benchmarks: the header every page carries and Markdown table helpers.

Every benchmark that publishes figures (``bench/`` and the paper's experiment,
:mod:`sim_publisher.experiment`, which is why this module lives in an installed package) writes
one page under ``docs/results/`` and overwrites it on each run: a title, one paragraph saying
what is measured on which data, how the numbers were produced (the exact command, the git
commit, the machine, the 1-minute load average when the run started, the date) and the
tables. A page says nothing about earlier runs; the
history of the figures is the git log of the page.

A benchmark captures its :class:`Provenance` when it starts (the load average is only
meaningful before the benchmark itself loads the machine), stores it with its rows when it
keeps a CSV (:meth:`Provenance.as_row`, :meth:`Provenance.from_row`), so that a page can be
rendered again from the CSV alone, and renders the page with :func:`page`.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import math
import os
import platform
import shlex
import subprocess
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: The code an offline benchmark runs: uncommitted changes there are named in its commit.
BENCHED_CODE = ("service/core", "service/adapters", "sim_publisher")
#: CSV columns of :meth:`Provenance.as_row`.
PROVENANCE_FIELDS = ("command", "commit", "machine", "load1", "load_end", "date")
#: Options that only say where a benchmark writes or caches (left out of a page's command).
OUTPUT_OPTIONS = ("--out", "--cache")


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (the platform's processor name
    elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8").splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def machine() -> str:
    """CPU model, cores, Python and numpy versions, e.g. ``Intel(R) Xeon(R) Processor, 2
    cores; Python 3.11.7, numpy 2.4.6``."""
    import numpy

    cores = os.cpu_count() or 0
    return (
        f"{cpu_model()}, {cores} core{'s' if cores != 1 else ''}; "
        f"Python {platform.python_version()}, numpy {numpy.__version__}"
    )


def load_average() -> float:
    """The 1-minute load average (NaN where the platform has none)."""
    try:
        return float(os.getloadavg()[0])
    except OSError:
        return math.nan


def today() -> str:
    """Today's date (UTC), ISO format."""
    return datetime.datetime.now(datetime.UTC).date().isoformat()


def git_commit(paths: Sequence[str] = ("service",)) -> str:
    """HEAD's short hash; with ``+diff-HASH`` appended when ``paths`` have uncommitted
    changes (HASH names that diff), so that a figure is never credited to a commit that did
    not produce it."""
    try:
        head = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        diff = subprocess.run(
            ["git", "-C", str(REPO), "diff", "HEAD", "--", *paths],
            capture_output=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    if not diff:
        return head
    return f"{head}+diff-{hashlib.sha1(diff).hexdigest()[:8]}"


def command_line(module: str, argv: Sequence[str]) -> str:
    """The command that reproduces a run: ``python -m MODULE ARGS``."""
    return " ".join(["python -m", module, *([shlex.join(argv)] if argv else [])])


@dataclass(frozen=True)
class Provenance:
    """How a set of rows was produced."""

    command: str
    commit: str
    machine: str
    load1: float  # 1-minute load average when the run started
    date: str  # ISO date (UTC)
    #: 1-minute load average when the run ended (NaN: not recorded). The start alone can
    #: understate the load a timing was taken under: other work may start meanwhile.
    load_end: float = math.nan

    @classmethod
    def capture(cls, command: str, paths: Sequence[str] = BENCHED_CODE) -> Provenance:
        """The provenance of a run starting now (call it before the run loads the machine)."""
        return cls(command, git_commit(paths), machine(), load_average(), today())

    def ended(self, load_end: float | None = None) -> Provenance:
        """This provenance with the load average at the run's end (now, unless given)."""
        end = load_average() if load_end is None else load_end
        return dataclasses.replace(self, load_end=end)

    def as_row(self) -> dict[str, str]:
        """The CSV columns :data:`PROVENANCE_FIELDS`."""
        return {
            "command": self.command,
            "commit": self.commit,
            "machine": self.machine,
            "load1": f"{self.load1:.2f}",
            "load_end": "" if not math.isfinite(self.load_end) else f"{self.load_end:.2f}",
            "date": self.date,
        }

    @classmethod
    def from_row(cls, row: dict[str, object], fallback: Provenance | None = None) -> Provenance:
        """The provenance stored in a CSV row; a column the row lacks is taken from
        ``fallback`` (a CSV written before the column existed)."""

        def get(name: str) -> str:
            v = row.get(name)
            if v is None or v == "":
                if fallback is None:
                    raise KeyError(f"CSV row without {name!r} and no fallback")
                return str(getattr(fallback, name))
            return str(v)

        def number(v: object) -> float:
            try:
                return float(v)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                return math.nan

        return cls(
            get("command"),
            get("commit"),
            get("machine"),
            number(get("load1")),
            get("date"),
            number(row.get("load_end")),
        )


def shown_command(command: str) -> str:
    """``command`` without its output locations (:data:`OUTPUT_OPTIONS`): they change where
    the figures go, not the figures, and the published page is the default output."""
    try:
        words = shlex.split(command)
    except ValueError:
        return command
    if not any(w.split("=", 1)[0] in OUTPUT_OPTIONS for w in words):
        return command  # as written (a call in Python, a command without output options)
    out: list[str] = []
    skip = False
    for w in words:
        if skip:
            skip = False
            continue
        if w in OUTPUT_OPTIONS:
            skip = True
            continue
        if any(w.startswith(o + "=") for o in OUTPUT_OPTIONS):
            continue
        out.append(w)
    return " ".join(shlex.quote(w) if w != "-m" else w for w in out)


def _span(values: Sequence[float]) -> str | None:
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return None
    lo, hi = min(finite), max(finite)
    return f"{lo:.2f}" if abs(hi - lo) < 0.005 else f"{lo:.2f}–{hi:.2f}"


def _loads(starts: Sequence[float], ends: Sequence[float]) -> str:
    start, end = _span(starts), _span(ends)
    if start is None:
        return "load average unknown"
    several = len(starts) > 1 and "–" in start
    when, until = ("the runs' starts", "their ends") if several else ("start", "the end")
    text = f"load average {start} at {when}"
    if end is not None:
        text += f", {end} at {until}"
    return text


def provenance_block(runs: Sequence[tuple[Provenance, str]]) -> str:
    """How the page's rows were produced: one line per distinct command, commit and date
    (``runs``: each run's provenance and a label of the rows it produced, may be empty).
    Commands are shown without their output locations (:func:`shown_command`)."""
    groups: dict[tuple[str, str, str, str], tuple[list[float], list[float], list[str]]] = {}
    for prov, label in runs:
        key = (shown_command(prov.command), prov.commit, prov.date, prov.machine)
        starts, ends, labels = groups.setdefault(key, ([], [], []))
        starts.append(prov.load1)
        ends.append(prov.load_end)
        if label and label not in labels:
            labels.append(label)
    machines = {k[3] for k in groups}
    one_machine = len(machines) == 1
    lines = []
    if len(groups) == 1:
        (command, commit, date, mach), (starts, ends, _labels) = next(iter(groups.items()))
        lines += [
            f"- Command: `{command}`",
            f"- Commit: {commit}",
            f"- Machine: {mach}; {_loads(starts, ends)}",
            f"- Date: {date}",
        ]
        return "\n".join(lines) + "\n"
    for (command, commit, date, mach), (starts, ends, labels) in groups.items():
        rows = f" ({', '.join(labels)})" if labels else ""
        where = "" if one_machine else f", {mach}"
        lines.append(f"- `{command}`{rows}: commit {commit}, {date}{where}, {_loads(starts, ends)}")
    if one_machine:
        lines.append(f"- Machine: {machines.pop()}")
    return "\n".join(lines) + "\n"


def page(
    title: str, paragraph: str, runs: Sequence[tuple[Provenance, str]], body: Iterable[str]
) -> str:
    """A results page: title, the paragraph, the provenance block, then ``body`` (tables,
    their headings and figures), separated by blank lines."""
    parts = [f"# {title}", paragraph.strip(), provenance_block(runs).rstrip(), *body]
    return "\n\n".join(p.rstrip("\n") for p in parts if p.strip()) + "\n"


def md_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """A Markdown pipe table (cells converted with ``str``, pipes escaped)."""

    def cell(v: object) -> str:
        return str(v).replace("|", "\\|").replace("\n", " ")

    lines = [
        "| " + " | ".join(cell(h) for h in header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def fmt(value: object, spec: str, missing: str = "–") -> str:
    """``value`` as a number formatted with ``spec``; ``missing`` for NaN, inf or a
    non-number."""
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return missing
    return format(x, spec) if math.isfinite(x) else missing


def write_page(path: Path, text: str) -> Path:
    """Write (overwrite) a results page, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return path
