"""``make demo`` / ``python -m sim_publisher.demo``: the whole system on one machine, end to end.

Starts the localizer service, its live view in the browser (``shapeloc view``: the URL is
printed, the page is up while the demo runs) and the simulator as subprocesses on a free
loopback port, lets three simulated robots (two on the exact metric office map, one on the
schematic floor plan) drive a fixed stretch of the office tour, shows live progress, then
prints an accuracy table
computed only from what came over Zenoh (poses against the simulator's ground-truth topic),
writes a trajectory figure and shuts everything down. Errors are map-frame position error
(mm) and heading error (deg); the proximity test is the paper's (100 mm / 45 deg on the
metric map, 500 mm / 45 deg on the schematic map).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from clients.client import ShapelocClient, Stream
from clients.view import DEFAULT_PORT as VIEW_PORT
from schemas.messages import PoseMsg, Truth
from service.errors import ShapelocError, Unreachable
from sim_publisher.office import office_schematic_map, office_world
from sim_publisher.plot import figure_axes, plot_map, plot_path, plot_world

#: (robot id, map spec, proximity threshold mm); the simulator numbers robots sim-0..2.
ROBOTS: tuple[tuple[str, str, float], ...] = (
    ("sim-0", "metric", 100.0),
    ("sim-1", "schematic", 500.0),
    ("sim-2", "metric", 100.0),
)
#: Start of each robot as a fraction of the tour (a fixed, reproducible stretch).
STARTS = (0.3, 0.0, 0.6)
#: A fourth robot that speaks only ROS 2 (``shapeloc-sim run --ros2``, namespace ``/ros_0``,
#: served by the service's ``--ros2`` front; docs/ros2.md), and where it starts.
ROS2_ROBOT: tuple[str, str, float] = ("ros_0", "metric", 100.0)
ROS2_START = 0.45
PROXIMITY_DEG = 45.0


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Track:
    """What arrived over Zenoh for one robot: truth by seq, and the received estimates."""

    robot_id: str
    map_spec: str
    proximity_mm: float
    truth: dict[int, np.ndarray] = field(default_factory=dict)
    poses: list[PoseMsg] = field(default_factory=list)
    received: int = 0

    def errors(self) -> tuple[np.ndarray, np.ndarray]:
        """Position (mm) and heading (deg) errors of every estimate whose truth arrived."""
        pos, head = [], []
        for p in self.poses:
            t = self.truth.get(p.seq)
            if t is None:
                continue
            pos.append(1000.0 * math.hypot(p.pose[0] - t[0], p.pose[1] - t[1]))
            d = (p.pose[2] - t[2] + math.pi) % (2.0 * math.pi) - math.pi
            head.append(abs(math.degrees(d)))
        return np.asarray(pos), np.asarray(head)

    def row(self) -> dict[str, float]:
        """Summary numbers of this robot (NaN where nothing was measured)."""
        pos, head = self.errors()
        lat = np.asarray([p.latency_ms for p in self.poses])
        ok = (pos < self.proximity_mm) & (head < PROXIMITY_DEG)
        nan = float("nan")
        return {
            "scans": float(len(self.truth)),
            "poses": float(len(self.poses)),
            "pos_mm": float(pos.mean()) if pos.size else nan,
            "head_deg": float(head.mean()) if head.size else nan,
            "proximity": 100.0 * float(ok.mean()) if ok.size else nan,
            "p50": float(np.percentile(lat, 50)) if lat.size else nan,
            "p99": float(np.percentile(lat, 99)) if lat.size else nan,
        }


def accuracy_table(tracks: Sequence[Track]) -> str:
    """The accuracy table as text (one row per robot)."""
    head = (
        f"{'robot':<7} {'map':<10} {'scans':>6} {'poses':>6} {'pos err mm':>11} "
        f"{'head err deg':>12} {'proximity %':>12} {'lat p50 ms':>11} {'lat p99 ms':>11}"
    )
    lines = [head, "-" * len(head)]
    for t in tracks:
        r = t.row()
        lines.append(
            f"{t.robot_id:<7} {t.map_spec:<10} {r['scans']:>6.0f} {r['poses']:>6.0f} "
            f"{r['pos_mm']:>11.0f} {r['head_deg']:>12.1f} {r['proximity']:>12.1f} "
            f"{r['p50']:>11.1f} {r['p99']:>11.1f}"
        )
    return "\n".join(lines)


def _progress_lines(tracks: Sequence[Track], total: int) -> list[str]:
    out = []
    for t in tracks:
        last = t.poses[-1] if t.poses else None
        err = ""
        if last is not None and last.seq in t.truth:
            tr = t.truth[last.seq]
            e = 1000.0 * math.hypot(last.pose[0] - tr[0], last.pose[1] - tr[1])
            d = abs(math.degrees((last.pose[2] - tr[2] + math.pi) % (2 * math.pi) - math.pi))
            err = f"error {e:7.0f} mm {d:5.1f} deg"
        status = last.status if last is not None else "waiting"
        out.append(
            f"  {t.robot_id:<6} {t.map_spec:<10} scans {len(t.truth):>4}/{total:<4} "
            f"poses {len(t.poses):>4}  {status:<12} {err}"
        )
    return out


def plot_tracks(tracks: Sequence[Track], path: Path) -> Path:
    """Write true and estimated paths over the office world and the schematic map."""
    fig, ax = figure_axes(7.0, 9.0)
    plot_world(ax, office_world(), wall_color="0.75", obstacle_color="0.88")
    plot_map(ax, office_schematic_map(), color="0.45", linewidth=0.6, linestyle="--")
    colors = ("tab:blue", "tab:orange", "tab:green", "tab:red")
    for k, t in enumerate(tracks):
        c = colors[k % len(colors)]
        if t.truth:
            seqs = sorted(t.truth)
            plot_path(ax, np.array([t.truth[s] for s in seqs]), color=c, linewidth=1.0, alpha=0.6)
        if t.poses:
            est = np.array([p.pose for p in t.poses])
            ax.plot(
                est[:, 0],
                est[:, 1],
                ".",
                color=c,
                markersize=2.5,
                label=f"{t.robot_id} ({t.map_spec})",
            )
    ax.set_title("shapeloc demo: estimates (dots) vs truth (lines)")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="upper right", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def _stop(proc: subprocess.Popen[bytes] | None, name: str, grace: float = 10.0) -> int | None:
    """SIGINT a child, wait ``grace`` s, then kill it; returns its exit code."""
    if proc is None:
        return None
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            print(f"demo: {name} did not stop within {grace} s; killing it", file=sys.stderr)
            proc.kill()
            proc.wait(5)
    return proc.returncode


def _connect(endpoint: str, within: float, service: subprocess.Popen[bytes]) -> ShapelocClient:
    end = time.monotonic() + within
    while True:
        try:
            return ShapelocClient(endpoint, timeout=2.0)
        except Unreachable:
            if service.poll() is not None:
                raise ShapelocError(
                    f"the service exited with code {service.returncode} before listening"
                ) from None
            if time.monotonic() >= end:
                raise
            time.sleep(0.2)


def start_view(
    endpoint: str, port: int, log: Path, env: dict[str, str], within: float = 20.0
) -> tuple[subprocess.Popen[bytes] | None, str | None]:
    """Start the live view (``shapeloc view``) of the service at ``endpoint`` on ``port``, or
    on any free port if that one is taken; returns (process, page URL), or (None, None) if it
    did not start within ``within`` seconds (the demo runs on without it)."""
    for p in dict.fromkeys((port, 0)):
        start = log.stat().st_size if log.exists() else 0
        with open(log, "ab") as f:
            proc = subprocess.Popen(
                [sys.executable, "-m", "clients.view", "--connect", endpoint, "--port", str(p)],
                stdout=f,
                stderr=subprocess.STDOUT,
                env=env,
            )
        end = time.monotonic() + within
        while time.monotonic() < end:
            with open(log, "rb") as f:
                f.seek(start)
                text = f.read().decode(errors="replace")
            if "shapeloc view: " in text:
                return proc, text.split("shapeloc view: ", 1)[1].split()[0]
            if proc.poll() is not None:
                break
            time.sleep(0.1)
        _stop(proc, "view")
    return None, None


def run_demo(
    scans: int,
    rate: float,
    out: Path,
    workdir: Path,
    method: str = "shape",
    drain_s: float = 15.0,
    lockstep: bool = True,
    max_seconds: float = 90.0,
    view_port: int | None = VIEW_PORT,
) -> tuple[int, list[Track]]:
    """Run service + simulator, collect poses and truth; returns (exit code, tracks).

    With ``lockstep`` the simulator sends the next scans only when every robot's pose for the
    previous ones has arrived (nothing is skipped; slower than ``rate`` if the service is);
    otherwise it publishes at ``rate`` and the service may skip scans (latest wins). The
    simulator stops after ``scans`` scans or ``max_seconds``, whichever comes first. Unless
    ``view_port`` is ``None`` the live view runs beside them (its URL is printed) until the
    demo ends.
    """
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    svc_log = open(workdir / "service.log", "wb")  # noqa: SIM115 - closed in finally
    sim_log = open(workdir / "simulator.log", "wb")  # noqa: SIM115
    ros_log = open(workdir / "ros2-robot.log", "wb")  # noqa: SIM115
    service = sim = view = ros_sim = None
    tracks = [Track(rid, m, prox) for rid, m, prox in (*ROBOTS, ROS2_ROBOT)]
    by_id = {t.robot_id: t for t in tracks}
    code = 0
    tty = sys.stdout.isatty()
    try:
        service = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "service",
                "--listen",
                ep,
                "--state-dir",
                str(workdir / "state"),
                "--ros2",
            ],
            stdout=svc_log,
            stderr=subprocess.STDOUT,
            env=env,
        )
        print(f"demo: service pid {service.pid} listening on {ep} (log {svc_log.name})")
        with _connect(ep, 30.0, service) as client:
            client.wait_for_service(30.0)
            if view_port is not None:
                view, url = start_view(ep, view_port, workdir / "view.log", env)
                if url is not None:
                    print(
                        f"demo: live view at {url} (open it in a browser; up while the demo runs)"
                    )
                else:
                    print("demo: the live view did not start; see view.log", file=sys.stderr)
            ids = [t.robot_id for t in tracks]
            poses: Stream[PoseMsg] = client.watch_poses(ids)
            truth: Stream[Truth] = client.watch_truth(ids)
            sim = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "sim_publisher",
                    "run",
                    "--connect",
                    ep,
                    "--robots",
                    str(len(ROBOTS)),
                    "--map",
                    ",".join(m for _, m, _ in ROBOTS),
                    "--method",
                    method,
                    "--starts",
                    ",".join(str(s) for s in STARTS),
                    "--scans",
                    str(scans),
                    "--rate",
                    str(rate),
                    "--seed",
                    "7",
                    "--duration",
                    str(max_seconds),
                    *(["--lockstep"] if lockstep else []),
                ],
                stdout=sim_log,
                stderr=subprocess.STDOUT,
                env=env,
            )
            ros_sim = subprocess.Popen(
                [
                    sys.executable, "-m", "sim_publisher", "run", "--ros2", "--connect", ep,
                    "--robots", "1", "--id-prefix", "ros-", "--map", ROS2_ROBOT[1],
                    "--method", method, "--starts", str(ROS2_START), "--scans", str(scans),
                    "--rate", str(rate), "--seed", "8", "--duration", str(max_seconds),
                    *(["--lockstep"] if lockstep else []),
                ],
                stdout=ros_log,
                stderr=subprocess.STDOUT,
                env=env,
            )  # fmt: skip
            print(f"demo: ROS 2 robot /ros_0 pid {ros_sim.pid} (log {ros_log.name})")
            pace = "lockstep: every scan localised" if lockstep else "real time: may skip"
            print(
                f"demo: simulator pid {sim.pid}: {len(ROBOTS)} robots, {scans} scans each "
                f"at <= {rate:g} Hz ({pace}; at most {max_seconds:g} s; log {sim_log.name})"
            )
            last_print = 0.0
            printed = 0
            quiet_since = None
            while True:
                got_any = False
                for key, tr in truth.drain():
                    by_id[key.split("/")[-2]].truth[tr.seq] = np.asarray(tr.pose)
                    got_any = True
                for _, p in poses.drain():
                    by_id[p.robot_id].poses.append(p)
                    got_any = True
                if service.poll() is not None:
                    print(
                        f"demo: the service exited early (code {service.returncode})",
                        file=sys.stderr,
                    )
                    code = 1
                    break
                sim_done = sim.poll() is not None and ros_sim.poll() is not None
                if sim_done and sim.returncode != 0:
                    print(
                        f"demo: the simulator failed (code {sim.returncode}); see {sim_log.name}",
                        file=sys.stderr,
                    )
                    code = 1
                    break
                now = time.monotonic()
                if sim_done:
                    answered = all(t.poses and t.poses[-1].seq >= scans - 1 for t in tracks)
                    quiet_since = quiet_since if not got_any and quiet_since else now
                    if answered or now - quiet_since > drain_s:
                        break
                if now - last_print >= (0.5 if tty else 5.0):
                    lines = _progress_lines(tracks, scans)
                    if tty and printed:
                        sys.stdout.write(f"\x1b[{printed}F")
                    sys.stdout.write("\n".join(f"{ln}\x1b[K" if tty else ln for ln in lines))
                    sys.stdout.write("\n")
                    sys.stdout.flush()
                    printed = len(lines)
                    last_print = now
                time.sleep(0.05)
            with contextlib.suppress(ShapelocError):
                h = client.health()
                print(
                    f"demo: service health: {h.status}, {h.scans_processed} scans processed, "
                    f"{h.scans_rejected} rejected"
                )
    finally:
        rc_sim = _stop(sim, "simulator")
        rc_ros = _stop(ros_sim, "ROS 2 robot")
        ros_log.close()
        rc_sim = rc_sim if rc_ros in (None, 0, -signal.SIGINT, 130) else rc_ros
        _stop(view, "view")
        rc_svc = _stop(service, "service")
        svc_log.close()
        sim_log.close()
    if rc_sim not in (None, 0, -signal.SIGINT, 130):
        code = 1
    if rc_svc not in (None, 0):
        print(
            f"demo: the service exited with code {rc_svc}; see {workdir / 'service.log'}",
            file=sys.stderr,
        )
        code = 1
    for t in tracks:
        if not t.poses:
            print(f"demo: no pose received for {t.robot_id}", file=sys.stderr)
            code = 1
    return code, tracks


def cli(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m sim_publisher.demo`` (``make demo``)."""
    p = argparse.ArgumentParser(
        prog="python -m sim_publisher.demo", description=__doc__.split("\n")[0]
    )
    p.add_argument("--scans", type=int, default=120, help="scans per robot (default 120)")
    p.add_argument("--rate", type=float, default=4.0, help="scans per second per robot")
    p.add_argument("--method", choices=("shape", "icp", "lines"), default="shape")
    p.add_argument(
        "--realtime",
        action="store_true",
        help="publish at --rate regardless of the service (it may skip scans); default: "
        "lockstep, every scan is localised",
    )
    p.add_argument(
        "--max-seconds", type=float, default=90.0, help="stop the simulator after this long"
    )
    p.add_argument("--out", type=Path, default=Path("out/demo.png"), help="figure path")
    p.add_argument("--keep", action="store_true", help="keep the work directory (logs, state)")
    p.add_argument(
        "--view-port",
        type=int,
        default=VIEW_PORT,
        help=f"port of the live view in the browser (default {VIEW_PORT}; a taken port or 0: "
        "any free one)",
    )
    p.add_argument("--no-view", action="store_true", help="run without the live view")
    args = p.parse_args(argv)
    if args.scans < 1 or args.rate <= 0:
        p.error("--scans must be >= 1 and --rate > 0")
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="shapeloc-demo-") as tmp:
        workdir = Path(tmp)
        try:
            code, tracks = run_demo(
                args.scans,
                args.rate,
                args.out,
                workdir,
                args.method,
                lockstep=not args.realtime,
                max_seconds=args.max_seconds,
                view_port=None if args.no_view else args.view_port,
            )
        except ShapelocError as exc:
            print(f"demo: error: {exc}", file=sys.stderr)
            _dump_logs(workdir)
            return 1
        except KeyboardInterrupt:
            print("demo: interrupted", file=sys.stderr)
            return 130
        print()
        print(
            f"accuracy over Zenoh ({args.method}; proximity: metric 100 mm, schematic 500 mm, "
            f"{PROXIMITY_DEG:.0f} deg)"
        )
        print(accuracy_table(tracks))
        try:
            path = plot_tracks(tracks, args.out)
            print(f"\ntrajectory plot: {path}")
        except ImportError as exc:
            print(f"demo: no plot ({exc}); install the [plot] extra", file=sys.stderr)
        if code != 0:
            _dump_logs(workdir)
        if args.keep:
            import shutil

            keep = Path(tempfile.mkdtemp(prefix="shapeloc-demo-kept-"))
            shutil.copytree(workdir, keep, dirs_exist_ok=True)
            print(f"demo: logs and state kept in {keep}")
    print(f"demo: {'ok' if code == 0 else 'FAILED'} in {time.monotonic() - t0:.0f} s")
    return code


def _dump_logs(workdir: Path, lines: int = 15) -> None:
    for name in ("service.log", "simulator.log", "view.log"):
        f = workdir / name
        if f.exists():
            tail = f.read_text(errors="replace").splitlines()[-lines:]
            print(f"--- last lines of {name} ---", file=sys.stderr)
            print("\n".join(tail), file=sys.stderr)


if __name__ == "__main__":
    sys.exit(cli())
