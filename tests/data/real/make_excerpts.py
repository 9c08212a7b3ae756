"""Regenerate the real-log excerpts in this directory from the whole logs.

Usage (from the repository root; reads ``/work/shared/data/real`` or ``--source DIR``)::

    .venv/bin/python tests/data/real/make_excerpts.py [--source DIR] [--scans 300]
        [--maps-only | --windows-only]

Writes, for the first ``--scans`` scans of each log (see README.md beside this file):

- ``intel.300.bag``, ``fr079.300.bag``: ROS 1 bags (bz2 chunks) written with ``rosbags``' writer.
  The messages are copied byte for byte (no re-serialisation): every ``/scan`` message up to and
  including the last kept scan, and every ``/odom``, ``/tf`` and ``/tf_static`` message up to one
  second of bag time after it (so the last scan's odometry can still be interpolated), with the
  original connections (type, message definition, md5sum) and bag times.
- ``mit-csail.300.clf.gz``: the CARMEN log's lines up to and including the last kept ``FLASER``
  line, unchanged, gzipped (mtime 0, so the file is reproducible).
- ``<log>.300.gfs_reference_per_scan.txt``: the comment lines and the first ``--scans`` rows of
  the per-scan reference file (one row per raw scan, the same order).
- ``<log>.300.relations``: the relations whose two stamps are both among the kept scans'.
- ``fr079.300.map.json``: a wire map (``service.adapters.maps.files.save_map_file``) built by
  ``service.adapters.maps.build.build_map`` from the kept fr079 scans that have a flag-1 reference,
  each at its reference (laser) pose; its fidelity (median / p90 distance of those scans' points to
  the map's polylines) is printed.
- ``intel.300.map.json``, ``mit-csail.300.map.json``: the whole-log metric maps the real-data
  benchmark uses (``bench/data/maps/{log}.geojson``, written by ``bench/bench_maps.py``) clipped
  to the box around the excerpt's returns at its reference poses (plus :data:`CROP_MARGIN`);
  pieces shorter than :data:`CROP_MIN_LENGTH` are dropped. Not built from the excerpt's own
  flag-1 scans: intel's first 300 scans have only 12 of them and that map is too thin (fidelity
  p90 0.31 m; ``shape`` with odometry ends 0.53 m off on it). ``--maps-only`` rewrites just the
  three maps from the excerpts already here.

This script is the only place that reads the whole logs; the tests read the excerpts only.
"""

from __future__ import annotations

import argparse
import gzip
import shutil
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]
DEFAULT_SOURCE = Path("/work/shared/data/real")
BAGS = ("intel", "fr079")
#: Bag time (s) of odometry / tf kept after the last kept scan.
ODOM_TAIL_S = 1.0
#: Margin (m) around the excerpt's returns when clipping a whole-log map.
CROP_MARGIN = 1.0
#: Clipped map pieces shorter than this (m) are dropped.
CROP_MIN_LENGTH = 0.1
#: Returns farther than this (m) do not widen the clipping box.
CROP_MAX_RANGE = 30.0
#: Logs whose excerpt map is clipped from the whole-log map, and the excerpt's log file.
CLIPPED = {"intel": "intel.{n}.bag", "mit-csail": "mit-csail.{n}.clf.gz"}


def cut_bag(src: Path, dst: Path, scans: int) -> int:
    """Copy the first ``scans`` ``/scan`` messages of ``src`` and the other topics up to
    :data:`ODOM_TAIL_S` after the last one into ``dst``; returns the number of messages."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer

    dst.unlink(missing_ok=True)
    with AnyReader([src]) as reader:
        scan_ids = {c.id for c in reader.connections if c.topic == "/scan"}
        last_t = None
        for k, (_conn, t, _raw) in enumerate(
            reader.messages(connections=[c for c in reader.connections if c.id in scan_ids])
        ):
            if k == scans - 1:
                last_t = t
                break
        if last_t is None:
            raise SystemExit(f"{src}: fewer than {scans} scans")
        end = last_t + int(ODOM_TAIL_S * 1e9)
        writer = Writer(dst)
        writer.set_compression(Writer.CompressionFormat.BZ2)
        written = 0
        with writer:
            out = {
                c.id: writer.add_connection(
                    c.topic,
                    c.msgtype,
                    msgdef=c.msgdef.data,
                    md5sum=c.digest,
                    callerid=c.ext.callerid,
                    latching=c.ext.latching,
                )
                for c in reader.connections
            }
            n_scans = 0
            for conn, t, raw in reader.messages():
                if conn.id in scan_ids:
                    if n_scans >= scans:
                        continue
                    n_scans += 1
                elif t > end:
                    continue
                writer.write(out[conn.id], t, raw)
                written += 1
    return written


def cut_carmen(src: Path, dst: Path, scans: int) -> int:
    """Copy the lines of ``src`` up to the ``scans``-th laser line into gzipped ``dst``."""
    lines: list[str] = []
    n = 0
    with open(src, encoding="latin-1") as fh:
        for line in fh:
            lines.append(line)
            if line.startswith(("FLASER ", "ROBOTLASER1 ")):
                n += 1
                if n == scans:
                    break
    if n < scans:
        raise SystemExit(f"{src}: fewer than {scans} laser lines")
    with open(dst, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz:
        gz.write("".join(lines).encode("latin-1"))
    return len(lines)


def cut_reference(src: Path, dst: Path, scans: int) -> list[float]:
    """Copy the comment lines and the first ``scans`` rows; returns the kept stamps (s)."""
    out: list[str] = []
    stamps: list[float] = []
    with open(src, encoding="latin-1") as fh:
        for line in fh:
            if line.startswith("#"):
                out.append(line)
                continue
            if len(stamps) == scans:
                break
            out.append(line)
            stamps.append(float(line.split()[0]))
    dst.write_text("".join(out), encoding="latin-1")
    return stamps


def cut_relations(src: Path, dst: Path, stamps: list[float]) -> int:
    """Copy the relations whose two stamps are within 1e-5 s of kept scan stamps (mit-csail's
    relations print 5 decimals)."""
    known = np.sort(np.array(stamps))

    def kept(t: float) -> bool:
        k = int(np.searchsorted(known, t))
        near = known[max(k - 1, 0) : k + 1]
        return bool(near.size and np.min(np.abs(near - t)) <= 1e-5)

    out = []
    with open(src, encoding="latin-1") as fh:
        for line in fh:
            tok = line.split()
            if len(tok) == 8 and kept(float(tok[0])) and kept(float(tok[1])):
                out.append(line)
    dst.write_text("".join(out), encoding="latin-1")
    return len(out)


def build_fr079_map(bag: Path, reference: Path, dst: Path) -> None:
    """Build the fr079 excerpt's map from its flag-1 scans at their reference poses."""
    from service.adapters.logs import attach_reference, load_reference, read_log
    from service.adapters.maps.build import build_map
    from service.adapters.maps.fidelity import map_fidelity
    from service.adapters.maps.files import save_map_file

    info, it = read_log(bag)
    scans = [s for s in attach_reference(it, load_reference(reference)) if s.reference_ok]
    built = build_map(
        scans=[(s.ranges, s.angles) for s in scans],
        poses=np.array([s.reference for s in scans]),
        map_id="fr079-300",  # build_map's defaults (2.5 cm grid, 2 cm simplification)
    )
    save_map_file(built.map_data, dst, name="fr079, first 300 scans (GMapping reference poses)")
    n_lines = len(built.map_data.polylines)
    print(f"{dst.name}: {n_lines} polylines from {len(scans)} flag-1 scans of {info.path.name}")
    poses = np.array([s.reference for s in scans])
    fid = map_fidelity(built.map_data, [(s.ranges, s.angles) for s in scans], poses)
    print(f"  fidelity: median {fid.median:.4f} m, p90 {fid.p90:.4f} m over {fid.n_points} returns")


def clip_full_map(log: Path, reference: Path, full_map: Path, dst: Path, map_id: str) -> None:
    """Clip ``full_map`` to the box around ``log``'s returns at their reference poses (every
    scan with a reference row, flag 0 too) widened by :data:`CROP_MARGIN`; write it to ``dst``
    and print its fidelity on the excerpt's flag-1 scans."""
    from shapely.geometry import LineString, box

    from service.adapters.logs import attach_reference, load_reference, read_log
    from service.adapters.maps.fidelity import map_fidelity
    from service.adapters.maps.files import load_map_file, save_map_file
    from service.core.types import MapData

    info, it = read_log(log)
    scans = list(attach_reference(it, load_reference(reference), scan_count=info.scan_count))
    ends = []
    for s in scans:
        if s.reference is None:
            continue
        x, y, th = s.reference
        ok = np.isfinite(s.ranges) & (s.ranges < CROP_MAX_RANGE)
        r, a = s.ranges[ok], s.angles[ok] + th
        ends.append(np.column_stack([x + r * np.cos(a), y + r * np.sin(a)]))
    pts = np.vstack(ends)
    lo = pts.min(axis=0) - CROP_MARGIN
    hi = pts.max(axis=0) + CROP_MARGIN
    window = box(lo[0], lo[1], hi[0], hi[1])
    whole = load_map_file(full_map, kind="metric")
    pieces: list[np.ndarray] = []
    for line in whole.polylines:
        cut = LineString(line).intersection(window)
        for part in getattr(cut, "geoms", [cut]):
            if isinstance(part, LineString) and part.length >= CROP_MIN_LENGTH:
                pieces.append(np.asarray(part.coords, dtype=np.float64))
    clipped = MapData.from_lists(map_id, "metric", pieces)
    save_map_file(
        clipped, dst, name=f"{full_map.name} clipped to the first {len(scans)} scans' area"
    )
    ok_scans = [s for s in scans if s.reference_ok]
    fid = map_fidelity(
        clipped, [(s.ranges, s.angles) for s in ok_scans], np.array([s.reference for s in ok_scans])
    )
    print(
        f"{dst.name}: {len(pieces)} of {len(whole.polylines)} polylines of {full_map.name} in "
        f"[{lo[0]:.1f}, {hi[0]:.1f}] x [{lo[1]:.1f}, {hi[1]:.1f}] m; fidelity on "
        f"{len(ok_scans)} flag-1 scans: median {fid.median:.4f} m, p90 {fid.p90:.4f} m"
    )


def build_maps(n: int) -> None:
    """Write the three excerpt maps from the excerpts in this directory."""
    build_fr079_map(
        HERE / f"fr079.{n}.bag",
        HERE / f"fr079.{n}.gfs_reference_per_scan.txt",
        HERE / f"fr079.{n}.map.json",
    )
    for name, pattern in CLIPPED.items():
        clip_full_map(
            HERE / pattern.format(n=n),
            HERE / f"{name}.{n}.gfs_reference_per_scan.txt",
            REPO / "bench" / "data" / "maps" / f"{name}.geojson",
            HERE / f"{name}.{n}.map.json",
            map_id=f"{name}-{n}",
        )


#: Windows of a whole log kept as arrays (``log``, first scan, scans): fr079 scans 846-865,
#: where the robot backs up ~0.6 m (scans 854-859) while its odometry reports forward motion;
#: fr079 scans 1174-1329, a drive out of a small room at the west end along the corridor
#: (a start of the global search whose true place an alias 31 m away fits better on single
#: scans); fr079 scans 4361-4510 at the east end; fr079 scans 2871-2985, a start whose
#: probation, at a 45 ms search budget, goes to a place 18 m off that the drive's keyframes
#: explain worse than the true one; intel scans 8329-8648 fed one in four (``stride``: in each
#: block of 4 the first with a flag-1 reference, else the block's first, as
#: ``bench/bench_global.py --real-stride 4`` feeds them), a start whose evidence-rule winner
#: lies 1.37 m along a corridor from the true place; fr079 scans 4100-4199, the robot driving
#: into the east hall, which the floor plan draws as its outline (the track must be bridged by
#: the odometry there, GlobalConfig.collapse_violation); fr079 scans 4327-4539 fed one in three,
#: a start in the east hall whose winner is held through rejections on its probation; intel
#: scans 4870-4881, where the odometry stamps a 0.37 rad turn one scan before the scans show it.
WINDOWS = (
    ("fr079", 846, 20, 1),
    ("fr079", 1174, 156, 1),
    ("fr079", 4361, 150, 1),
    ("fr079", 2871, 115, 1),
    ("intel", 8329, 320, 4),
    ("fr079", 4100, 100, 1),
    ("fr079", 4327, 213, 3),
    ("intel", 4870, 12, 1),
)


def cut_window(
    src: Path, name: str, first: int, count: int, dst: Path, stride: int = 1
) -> tuple[int, int]:
    """Scans ``first .. first + count - 1`` of the whole log ``name`` as an ``.npz`` (with
    ``stride`` > 1 one scan per block of ``stride``: the first with a flag-1 reference, else
    the block's first): ``ranges`` / ``angles`` ``(n, beams)``, ``odom`` ``(n, 3)`` (the
    odometry pose each scan carries), ``reference`` ``(n, 3)``, ``flag`` ``(n,)`` (GMapping's
    per-scan reference and its flag) and ``scan`` ``(n,)`` (the scan's number in the whole
    log). Returns the number of scans kept and of flag-1 scans among them."""
    from service.adapters.logs import attach_reference, load_reference, read_log

    files = {"fr079": "fr079.orig.bag", "intel": "intel.orig.bag", "mit-csail": "mit-csail.clf"}
    info, it = read_log(src / files[name], limit=first + count)
    ref = load_reference(src / "corrected" / f"{name}.gfs_reference_per_scan.txt")
    window = list(attach_reference(it, ref, scan_count=info.scan_count))[first : first + count]
    numbers: list[int] = []
    for b in range(0, len(window), stride):
        block = window[b : b + stride]
        ok = [k for k, s in enumerate(block) if s.reference_ok and s.reference is not None]
        numbers.append(b + (ok[0] if ok else 0))
    scans = [window[k] for k in numbers]
    nan3 = np.full(3, np.nan)
    np.savez_compressed(
        dst,
        ranges=np.array([np.asarray(s.ranges, dtype=np.float64) for s in scans]),
        angles=np.array([np.asarray(s.angles, dtype=np.float64) for s in scans]),
        odom=np.array([np.asarray(s.odom, dtype=np.float64) for s in scans]),
        reference=np.array([nan3 if s.reference is None else s.reference for s in scans]),
        flag=np.array([bool(s.reference_ok and s.reference is not None) for s in scans]),
        scan=np.array([first + k for k in numbers]),
    )
    return len(scans), sum(bool(s.reference_ok) for s in scans)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--source", type=Path, default=DEFAULT_SOURCE)
    ap.add_argument("--scans", type=int, default=300)
    ap.add_argument(
        "--maps-only", action="store_true", help="rewrite only the maps, from the excerpts here"
    )
    ap.add_argument(
        "--windows-only",
        action="store_true",
        help="rewrite only the schematised maps and the scan windows (WINDOWS)",
    )
    args = ap.parse_args(argv)
    src: Path = args.source
    n: int = args.scans
    if args.maps_only:
        build_maps(n)
        return 0
    if args.windows_only:
        write_windows(src)
        return 0
    for name in BAGS:
        count = cut_bag(src / f"{name}.orig.bag", HERE / f"{name}.{n}.bag", n)
        print(f"{name}.{n}.bag: {count} messages")
    count = cut_carmen(src / "mit-csail.clf", HERE / f"mit-csail.{n}.clf.gz", n)
    print(f"mit-csail.{n}.clf.gz: {count} lines")
    for name in (*BAGS, "mit-csail"):
        ref = src / "corrected" / f"{name}.gfs_reference_per_scan.txt"
        stamps = cut_reference(ref, HERE / f"{name}.{n}.gfs_reference_per_scan.txt", n)
        k = cut_relations(src / f"{name}.relations", HERE / f"{name}.{n}.relations", stamps)
        print(f"{name}.{n}: {len(stamps)} reference rows, {k} relations")
    build_maps(n)
    write_windows(src)
    return 0


def write_windows(src: Path) -> None:
    """The schematised maps (as bench/bench_real.py writes them) and the windows of
    :data:`WINDOWS`, for the drive tests."""
    for name in ("fr079", "intel"):
        shutil.copyfile(
            REPO / "bench" / "data" / "maps" / f"{name}_schematic.geojson",
            HERE / f"{name}.schematic.geojson",
        )
    for name, first, count, stride in WINDOWS:
        every = "" if stride == 1 else f".every{stride}"
        dst = HERE / f"{name}.{first}-{first + count - 1}{every}.npz"
        n, k = cut_window(src, name, first, count, dst, stride)
        print(f"{dst.name}: {n} scans, {k} with a flag-1 reference")


if __name__ == "__main__":
    sys.exit(main())
