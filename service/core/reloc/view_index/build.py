"""Building a map's :class:`ViewIndex` (:func:`build_index`) and the content hash it is cached
by (:func:`index_key`)."""

from __future__ import annotations

import hashlib
import json
import time

import numpy as np

from service.core import numeric
from service.core.reloc.config import GlobalConfig
from service.core.reloc.view_index import viewpoints as vp
from service.core.reloc.view_index.index import FORMAT_VERSION, ViewIndex
from service.core.sensor.raycast import RayCaster
from service.core.sensor.scoring import sensor_model
from service.core.shapes.configuration import Configuration, map_view
from service.core.shapes.dce import dce
from service.core.shapes.similarity import shape_complexity
from service.core.tracking.localizer import ShapeConfig
from service.core.types import MapData


def index_key(map_data: MapData, config: ShapeConfig, gconfig: GlobalConfig) -> str:
    """Cache key: SHA-256 (hex) of the map content and every parameter the index depends on."""
    h = hashlib.sha256()
    h.update(f"shapeloc-viewindex-v{FORMAT_VERSION}\n{map_data.kind}\n".encode())
    for p in map_data.polylines:
        a = np.ascontiguousarray(p, dtype="<f8")
        h.update(len(a).to_bytes(8, "little"))
        h.update(a.tobytes())
    params = {
        "extraction": config.extraction().__dict__,
        "view_beams": config.view_beams,
        "view_max_range": config.view_max_range,
        "index": {
            "spacing": vp.SPACING,
            "min_clearance": vp.MIN_CLEARANCE,
            "enclosure_beams": vp.ENCLOSURE_BEAMS,
            "min_enclosed": gconfig.min_enclosed,
            "small_ring_area": vp.SMALL_RING_AREA,
        },
    }
    h.update(json.dumps(params, sort_keys=True).encode())
    return h.hexdigest()


def anchor(verts: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The unit's most salient vertex ``(2,)`` (largest ``|turn| * min(adjacent arm)``), the
    direction (rad) of the edge leaving it and its signed turn (rad). Many viewpoints see the
    same corner: the anchor identifies it, and two corresponding anchors fix a pose."""
    if len(verts) < 3:
        d = verts[-1] - verts[0]
        return verts.mean(axis=0), numeric.atan2(d[1], d[0]), 0.0
    d = np.diff(verts, axis=0)
    ln = np.hypot(d[:, 0], d[:, 1])
    ang = numeric.atan2(d[:, 1], d[:, 0])
    turn = np.mod(np.diff(ang) + np.pi, 2.0 * np.pi) - np.pi
    k = int(np.argmax(np.abs(turn) * np.minimum(ln[:-1], ln[1:])))
    return verts[1 + k], float(ang[1 + k]), float(turn[k])


def shape_units(C: Configuration, threshold: float, cyclic: bool) -> list[np.ndarray]:
    """Vertices of each feature and of each pair of consecutive features (``cyclic``: the last
    and the first too, as in a 360-degree view). A pair is re-simplified by DCE (eq. 2), so
    the short junction of a corner's two pieces does not hide the corner."""
    f, n = C.features, len(C.features)
    out = [x.vertices for x in f]
    for i in range(n if cyclic and n > 2 else max(n - 1, 0)):
        u = np.vstack([f[i].vertices, f[(i + 1) % n].vertices])
        out.append(u[dce(u, threshold)])
    return out


#: Anchor cell (m) and edge direction bucket (rad) that make units "the same corner".
_GROUP_CELL = 0.25
_GROUP_ANGLE = np.pi / 6.0


def build_index(
    map_data: MapData, config: ShapeConfig | None = None, gconfig: GlobalConfig | None = None
) -> ViewIndex:
    """The :class:`ViewIndex` of a map (no disk access): the units of the 360-degree map view
    from every :func:`candidate_viewpoints` point, extracted with the tracker's parameters."""
    config = config or ShapeConfig.for_kind(map_data.kind)
    gconfig = gconfig or GlobalConfig.for_kind(map_data.kind)
    t0 = time.perf_counter()
    caster = RayCaster(map_data.segments())
    params = config.extraction()
    vps = vp.candidate_viewpoints(
        map_data, min_enclosed=gconfig.min_enclosed, max_range=config.view_max_range, caster=caster
    )
    uview: list[int] = []
    rmin: list[float] = []
    rmax: list[float] = []
    ucomp: list[float] = []
    groups: dict[tuple[int, int, int], int] = {}
    ugroup: list[int] = []
    uanc: list[tuple[float, float, float, float]] = []
    verts: list[np.ndarray] = []
    for v, p in enumerate(vps):
        Q = map_view(
            caster,
            np.array([p[0], p[1], 0.0]),
            2.0 * np.pi,
            config.view_beams,
            config.view_max_range,
            params,
        )
        for uv in shape_units(Q, params.dce_threshold, cyclic=True):
            if len(uv) < 2:
                continue
            uview.append(v)
            d = np.hypot(uv[:, 0] - p[0], uv[:, 1] - p[1])
            rmin.append(float(d.min()))
            rmax.append(float(d.max()))
            ucomp.append(shape_complexity(uv))
            anc, direction, turn = anchor(uv)
            uanc.append((float(anc[0]), float(anc[1]), direction, turn))
            cell = np.floor(anc / _GROUP_CELL).astype(int)
            key = (int(cell[0]), int(cell[1]), int(np.floor(direction / _GROUP_ANGLE)))
            ugroup.append(groups.setdefault(key, len(groups)))
            verts.append(uv)
    off = np.zeros(len(verts) + 1, dtype=np.int64)
    if verts:
        off[1:] = np.cumsum([len(v) for v in verts])
    return ViewIndex(
        key=index_key(map_data, config, gconfig),
        map_id=map_data.map_id,
        kind=map_data.kind,
        viewpoints=vps,
        unit_view=np.asarray(uview, dtype=np.int64),
        unit_rmin=np.asarray(rmin, dtype=np.float64),
        unit_rmax=np.asarray(rmax, dtype=np.float64),
        unit_complexity=np.asarray(ucomp, dtype=np.float64),
        unit_group=np.asarray(ugroup, dtype=np.int64),
        unit_anchor=np.asarray(uanc, dtype=np.float64).reshape(-1, 4),
        unit_vert_off=off,
        unit_verts=np.vstack(verts) if verts else np.zeros((0, 2)),
        build_seconds=time.perf_counter() - t0,
        sensor=sensor_model(map_data),
    )
