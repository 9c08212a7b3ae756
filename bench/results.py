"""The results pages under ``docs/results/``: one per benchmark, written by the benchmark
itself (``--results DIR``), overwritten on every run (no history): the command, the commit,
the machine and its load, then the benchmark's own page."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def commit() -> str:
    """The short commit of HEAD, ``+uncommitted`` when ``service/`` has changes."""
    try:
        head = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(REPO), "status", "--porcelain", "--", "service"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        return head + ("+uncommitted" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> str:
    """CPU model, cores and the load averages now."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        load = "n/a"
    return f"{cpu}, {os.cpu_count()} cores, load average {load}"


def publish(results: Path | None, name: str, body: str, argv: list[str] | None = None) -> None:
    """Write ``results/name.md`` (nothing when ``results`` is ``None``): a header naming the
    command, commit, time and machine, then ``body``."""
    if results is None:
        return
    module = f"bench.{Path(sys.argv[0]).stem}" if argv is None else argv[0]
    cmd = " ".join(["python", "-m", module, *(sys.argv[1:] if argv is None else argv[1:])])
    head = (
        f"Command: `{cmd}`  \nCommit: {commit()}, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  \nMachine: {machine()}\n\n"
    )
    results.mkdir(parents=True, exist_ok=True)
    (results / f"{name}.md").write_text(head + body, encoding="utf-8")
    print(f"wrote {results / (name + '.md')}")
