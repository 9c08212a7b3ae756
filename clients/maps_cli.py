"""``shapeloc map import|build|schematize|fidelity``: map tools that run locally (no service).

* ``import MAP.yaml --id ID [--out FILE] [--put]``: a ROS ``map_server`` map (YAML + PGM/PNG)
  as polylines along its occupied cells' faces (:func:`service.adapters.maps.grid.grid_to_map`);
  writes ``FILE`` (``.geojson`` or wire ``.json``) and with ``--put`` stores it on the service.
* ``build LOG [--poses REFERENCE] --out PREFIX [--id ID]``: a map drawn from a laser log at its
  reference poses (:func:`service.adapters.maps.build.build_map`): ``PREFIX.yaml`` + ``PREFIX.pgm``
  (occupancy grid) and ``PREFIX.geojson`` (wall polylines, kind ``metric``); prints the map's
  fidelity on the scans with trusted (flag-1) poses.
* ``schematize MAP --out FILE [parameter flags]``: the schematic map
  (:func:`service.adapters.maps.schematize.schematize`; one flag per
  :class:`~service.adapters.maps.schematize.SchematizeParams` field).
* ``fidelity MAP LOG [--poses REFERENCE]``: median / p90 / mean distance of the returns of the
  scans with trusted reference poses to the map's polylines
  (:func:`service.adapters.maps.fidelity.map_fidelity`).

The typed functions (:func:`import_map`, :func:`build_from_log`, :func:`schematize_file`,
:func:`fidelity_of`, :func:`load_logged_scans`) do the work; :func:`add_parsers` and
:func:`run` wire them into the ``shapeloc map`` argument parser of :mod:`clients.__main__`.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from service.adapters.logs import attach_reference, load_reference, read_log
from service.adapters.maps.build import BuiltMap, build_map
from service.adapters.maps.fidelity import Fidelity, map_fidelity
from service.adapters.maps.files import load_map_file, save_map_file, save_map_geojson
from service.adapters.maps.grid import write_map_yaml
from service.adapters.maps.schematize import SchematizeParams, schematize
from service.core.types import MapData
from service.errors import InvalidMessage

#: ``shapeloc map`` actions handled here, without a service.
LOCAL_ACTIONS = frozenset({"import", "build", "schematize", "fidelity"})

#: Default for :func:`build_from_log`'s ``max_carried`` (m): scans whose reference pose was
#: carried by odometry (flag 0) are drawn when the robot moved at most this far since the last
#: corrected pose; ``0`` (the default) draws the corrected scans only. Carried scans improve
#: the held-out *fidelity* on intel a little (median / p90 1.79 / 8.01 cm with corrected scans
#: only, 1.73 / 6.06 cm at 0.5 m, 1.90 / 6.44 cm with every scan; docs/maps.md) but they add
#: faint doubled walls where the carried pose had drifted, and a tracker locks onto those:
#: ``shape`` with odometry on the whole intel log (tuning split) keeps 99.9 % of scored scans
#: within 0.3 m on the corrected-only map, 98.1 % with every scan, and only 50 % at 0.5 m.
#: Localisation is what the map is for, so the default is 0 (fr079's carried poses never
#: moved, so it cannot tell; mit-csail is held out).
DEFAULT_MAX_CARRIED = 0.0

#: Metres of travel charged per radian turned when measuring how far a carried pose has
#: drifted from its corrected origin (a turn in place degrades an odometry pose too).
TURN_WEIGHT = 0.3


@dataclass(frozen=True, eq=False)
class LoggedScans:
    """Scans of a log with their reference poses.

    ``scans``: ``(ranges, angles)`` pairs in the laser frame (m, rad; NaN = no return);
    ``poses``: ``(n, 3)`` laser poses in the reference's map frame (NaN rows: no reference);
    ``ok``: ``(n,)`` True for a trusted (flag-1, corrected) pose; ``carried``: ``(n,)`` metres
    driven (plus :data:`TURN_WEIGHT` m per radian turned) since the last trusted pose, 0 for a
    trusted one, ``inf`` before the first.
    """

    scans: list[tuple[np.ndarray, np.ndarray]]
    poses: np.ndarray
    ok: np.ndarray
    carried: np.ndarray

    def usable(self, max_carried: float) -> np.ndarray:
        """Indices of the scans to draw a map from: every trusted pose, and carried ones with
        ``carried <= max_carried`` (``0`` = trusted only, ``inf`` = every scan with a pose)."""
        fin = np.all(np.isfinite(self.poses), axis=1)
        if max_carried <= 0.0:
            return np.nonzero(fin & self.ok)[0]
        return np.nonzero(fin & (self.ok | (self.carried <= max_carried)))[0]

    def trusted(self) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
        """The scans with trusted poses and those poses (what fidelity is scored on)."""
        idx = np.nonzero(self.ok)[0]
        return [self.scans[i] for i in idx], self.poses[idx]


def load_logged_scans(
    log: str | Path, poses: str | Path | None = None, *, limit: int | None = None
) -> LoggedScans:
    """Read every scan of ``log`` (any format :func:`service.adapters.logs.read_log` reads) with its
    reference pose: from ``poses`` (a ``*.gfs_reference_per_scan.txt`` file,
    :func:`service.adapters.logs.load_reference`) or, without it, the log's own (a
    GMapping-corrected
    CARMEN log). Raises :class:`InvalidMessage` when no scan has a trusted pose."""
    info, it = read_log(log, limit=limit)
    if poses is not None:
        it = attach_reference(it, load_reference(poses), scan_count=info.scan_count)
    scans: list[tuple[np.ndarray, np.ndarray]] = []
    rows: list[np.ndarray] = []
    ok: list[bool] = []
    nan3 = np.full(3, np.nan)
    for s in it:
        scans.append((np.asarray(s.ranges), s.angles))
        rows.append(nan3 if s.reference is None else np.asarray(s.reference, dtype=np.float64))
        ok.append(bool(s.reference_ok and s.reference is not None))
    P = np.array(rows).reshape(-1, 3)
    okv = np.array(ok, dtype=bool)
    if not okv.any():
        where = poses if poses is not None else f"{log} (no --poses given)"
        raise InvalidMessage(f"{where}: no scan of {log} has a trusted reference pose")
    carried = np.full(P.shape[0], np.inf)
    d = math.inf
    for i in range(P.shape[0]):
        if okv[i]:
            d = 0.0
        elif i > 0 and math.isfinite(d) and np.all(np.isfinite(P[i - 1 : i + 1])):
            step = P[i] - P[i - 1]
            turn = abs((step[2] + math.pi) % (2.0 * math.pi) - math.pi)
            d += math.hypot(step[0], step[1]) + TURN_WEIGHT * turn
        elif not np.all(np.isfinite(P[i])):
            d = math.inf
        carried[i] = d
    return LoggedScans(scans=scans, poses=P, ok=okv, carried=carried)


def write_map(map_data: MapData, path: str | Path) -> Path:
    """Write a map as GeoJSON (``.geojson``) or wire JSON (``.json``), by the suffix."""
    p = Path(path)
    if p.suffix.lower() == ".geojson":
        return save_map_geojson(map_data, p)
    if p.suffix.lower() == ".json":
        return save_map_file(map_data, p)
    raise InvalidMessage(f"{p}: write maps to a .geojson or .json file")


def describe(m: MapData) -> str:
    """One line: id, kind, polylines, vertices, extent (m)."""
    x0, y0, x1, y1 = m.bounds()
    nv = sum(p.shape[0] for p in m.polylines)
    return (
        f"{m.map_id} ({m.kind}): {len(m.polylines)} polylines, {nv} vertices, "
        f"x [{x0:.2f}, {x1:.2f}] y [{y0:.2f}, {y1:.2f}] m"
    )


def format_fidelity(f: Fidelity) -> str:
    return (
        f"fidelity: median {100 * f.median:.1f} cm, p90 {100 * f.p90:.1f} cm, "
        f"mean {100 * f.mean:.1f} cm over {f.n_points} returns"
    )


def import_map(yaml_path: str | Path, map_id: str | None = None) -> MapData:
    """A ROS ``map_server`` map (YAML + image) as polylines (kind ``metric``)."""
    p = Path(yaml_path)
    if p.suffix.lower() not in (".yaml", ".yml"):
        raise InvalidMessage(f"{p}: map import reads a map_server .yaml file")
    return load_map_file(p, map_id=map_id)


def build_from_log(
    logged: LoggedScans,
    prefix: str | Path,
    map_id: str,
    *,
    max_carried: float = DEFAULT_MAX_CARRIED,
    resolution: float = 0.025,
) -> tuple[BuiltMap, Fidelity]:
    """Build a map from ``logged`` (scans selected by :meth:`LoggedScans.usable`), write
    ``PREFIX.yaml`` + ``PREFIX.pgm`` + ``PREFIX.geojson``, and measure its fidelity on the
    trusted scans."""
    idx = logged.usable(max_carried)
    built = build_map(
        [logged.scans[i] for i in idx],
        logged.poses[idx],
        map_id=map_id,
        resolution=resolution,
    )
    pre = Path(prefix)
    write_map_yaml(built.grid, pre.with_name(pre.name + ".yaml"))
    save_map_geojson(built.map_data, pre.with_name(pre.name + ".geojson"))
    scans, poses = logged.trusted()
    return built, map_fidelity(built.map_data, scans, poses)


def schematize_file(
    map_path: str | Path,
    out_path: str | Path,
    params: SchematizeParams | None = None,
    map_id: str | None = None,
) -> MapData:
    """Read a map file, schematise it, write the result (``.geojson`` / ``.json``)."""
    src = load_map_file(map_path, map_id=map_id)
    sch = schematize(src, params)
    write_map(sch, out_path)
    return sch


def fidelity_of(map_path: str | Path, logged: LoggedScans, stride: int = 1) -> Fidelity:
    """Fidelity of a map file on the trusted scans of ``logged``."""
    scans, poses = logged.trusted()
    return map_fidelity(load_map_file(map_path), scans, poses, stride=stride)


# ------------------------------------------------------------------ argument parsing
def _nonneg(text: str) -> float:
    v = float(text)
    if not v >= 0.0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def add_parsers(msub: Any, add: Any = None) -> None:
    """Add ``import``, ``build``, ``schematize`` and ``fidelity`` to ``shapeloc map``;
    ``add(msub, name, help=...)`` makes each parser (default ``msub.add_parser``)."""
    if add is None:

        def add(sub: Any, name: str, **kw: Any) -> argparse.ArgumentParser:
            return sub.add_parser(name, **kw)

    imp = add(msub, "import", help="a ROS map_server map (YAML + PGM/PNG) as polylines")
    imp.add_argument("file", help="map_server .yaml")
    imp.add_argument("--id", dest="map_id", help="map id (default: the file's stem)")
    imp.add_argument("--out", help="write the polylines (.geojson or wire .json)")
    imp.add_argument("--put", action="store_true", help="store the map on the service")

    bld = add(msub, "build", help="draw a map from a laser log at its reference poses")
    bld.add_argument("log", help="ROS 1/2 bag or CARMEN log")
    bld.add_argument(
        "--poses", help="per-scan reference (*.gfs_reference_per_scan.txt); default: the log's"
    )
    bld.add_argument("--out", required=True, help="PREFIX of PREFIX.yaml/.pgm/.geojson")
    bld.add_argument("--id", dest="map_id", help="map id (default: PREFIX's name)")
    bld.add_argument("--resolution", type=float, default=0.025, help="cell size, m")
    bld.add_argument(
        "--max-carried",
        type=_nonneg,
        default=DEFAULT_MAX_CARRIED,
        help="also draw flag-0 scans carried at most this far (m) from a corrected pose "
        "(0 = corrected scans only; inf = every scan)",
    )

    sch = add(msub, "schematize", help="a floor-plan-like map from a metric one (DCE)")
    sch.add_argument("file", help="map file (.geojson, .json, .yaml, .wkt)")
    sch.add_argument("--out", required=True, help="output .geojson or wire .json")
    sch.add_argument("--id", dest="map_id", help="map id (default: the input's)")
    for name, field in SchematizeParams.model_fields.items():
        sch.add_argument(
            f"--{name.replace('_', '-')}",
            dest=f"sp_{name}",
            type=float,
            default=None,
            help=f"see docs/maps.md (default: {field.default})",
        )

    fid = add(msub, "fidelity", help="distances of a log's returns to a map's polylines")
    fid.add_argument("file", help="map file")
    fid.add_argument("log", help="ROS 1/2 bag or CARMEN log")
    fid.add_argument("--poses", help="per-scan reference; default: the log's own")
    fid.add_argument("--stride", type=int, default=1, help="every N-th trusted scan")


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Execute ``shapeloc map import|build|schematize|fidelity``; errors propagate as
    :class:`~service.errors.ShapelocError`."""
    out = out or sys.stdout
    act = args.map_command
    if act == "import":
        m = import_map(args.file, args.map_id)
        print(f"imported {describe(m)}", file=out)
        if args.out:
            print(f"wrote {write_map(m, args.out)}", file=out)
        if args.put:
            from clients.client import DEFAULT_CONNECT, ShapelocClient

            endpoints = args.connect or [DEFAULT_CONNECT]
            with ShapelocClient(endpoints, prefix=args.prefix, timeout=args.timeout) as c:
                c.health()
                c.put_map(m, ready=True, within=120.0)
            print(f"stored map {m.map_id} on the service (ready)", file=out)
    elif act == "build":
        t0 = time.perf_counter()
        logged = load_logged_scans(args.log, args.poses)
        built, fid = build_from_log(
            logged,
            args.out,
            args.map_id or Path(args.out).name,
            max_carried=args.max_carried,
            resolution=args.resolution,
        )
        dt = time.perf_counter() - t0
        print(
            f"built {describe(built.map_data)} from {built.n_scans} of {len(logged.scans)} "
            f"scans ({int(logged.ok.sum())} corrected) in {dt:.1f} s",
            file=out,
        )
        print(f"wrote {args.out}.yaml, {args.out}.pgm, {args.out}.geojson", file=out)
        print(format_fidelity(fid), file=out)
    elif act == "schematize":
        given = {k[3:]: v for k, v in vars(args).items() if k.startswith("sp_") and v is not None}
        try:
            params = SchematizeParams(**given)
        except ValueError as exc:  # pydantic's ValidationError
            raise InvalidMessage(f"schematize parameters: {exc}") from None
        m = schematize_file(args.file, args.out, params, args.map_id)
        print(f"wrote {args.out}: {describe(m)}", file=out)
    elif act == "fidelity":
        if args.stride < 1:
            raise InvalidMessage(f"--stride must be >= 1, got {args.stride}")
        logged = load_logged_scans(args.log, args.poses)
        print(format_fidelity(fidelity_of(args.file, logged, args.stride)), file=out)
    else:
        raise InvalidMessage(f"unknown map action {act!r}")
    return 0
