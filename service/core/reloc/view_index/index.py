"""The per-map view index of global localisation (:class:`ViewIndex`): per candidate viewpoint
the map view's units, the lookups the search makes on them, and the plain arrays the on-disk
cache stores (versioned by :data:`FORMAT_VERSION`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.core.sensor.scoring import SensorModel
from service.core.shapes.similarity import ShapeArcs, prepare
from service.errors import LocalizationError

#: Version of the on-disk index format; bump when the file layout or its meaning changes.
FORMAT_VERSION = 3
#: The arrays of an index file and their types.
_ARRAYS = {
    "viewpoints": np.float64,
    "unit_view": np.int64,
    "unit_rmin": np.float64,
    "unit_rmax": np.float64,
    "unit_complexity": np.float64,
    "unit_group": np.int64,
    "unit_anchor": np.float64,
    "unit_vert_off": np.int64,
    "unit_verts": np.float64,
}


@dataclass(eq=False)
class ViewIndex:
    """Everything global search needs about one map, precomputed (:func:`.build.build_index`).

    ``viewpoints`` ``(v, 2)`` map frame. Units (a view feature or two consecutive ones) are
    stored flat: ``unit_view`` (viewpoint), ``unit_rmin`` / ``unit_rmax`` (nearest and farthest
    vertex from it, m), ``unit_complexity`` (m·rad), ``unit_group`` (units with the same anchor,
    the same physical corner, share it), ``unit_anchor`` ``(u, 4)`` the anchor vertex x, y,
    the direction of the edge leaving it and its turn (rad), vertices
    ``unit_verts[unit_vert_off[u]:unit_vert_off[u+1]]`` (map frame). ``sensor``: the map's
    sensor model (segments, distance field, ray casting), attached, not stored.
    """

    key: str
    map_id: str
    kind: str
    viewpoints: np.ndarray
    unit_view: np.ndarray
    unit_rmin: np.ndarray
    unit_rmax: np.ndarray
    unit_complexity: np.ndarray
    unit_group: np.ndarray
    unit_anchor: np.ndarray
    unit_vert_off: np.ndarray
    unit_verts: np.ndarray
    build_seconds: float = 0.0
    sensor: SensorModel | None = field(default=None, repr=False)
    _arcs: list[ShapeArcs | None] = field(default_factory=list, repr=False)

    def __len__(self) -> int:
        return int(self.unit_view.size)

    def arcs(self, u: int) -> ShapeArcs:
        """Unit ``u``'s vertices prepared for S* (lazily, kept)."""
        if not self._arcs:
            self._arcs = [None] * len(self)
        a = self._arcs[u]
        if a is None:
            a = prepare(self.unit_verts[self.unit_vert_off[u] : self.unit_vert_off[u + 1]])
            self._arcs[u] = a
        return a

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for :func:`numpy.savez` (no pickled objects)."""
        meta = {"format": FORMAT_VERSION, "key": self.key, "map_id": self.map_id}
        meta.update(kind=self.kind, build_seconds=self.build_seconds)
        return {"meta": np.array(json.dumps(meta)), **{k: getattr(self, k) for k in _ARRAYS}}

    @staticmethod
    def from_arrays(arrays: Any, expect_key: str) -> ViewIndex:
        """Rebuild from :meth:`to_arrays` output, checking every field (never trusted)."""
        try:
            meta = json.loads(str(arrays["meta"][()]))
            if meta.get("format") != FORMAT_VERSION or meta.get("key") != expect_key:
                raise LocalizationError("cache key or format version mismatch")
            got = {k: np.asarray(arrays[k], dtype=t) for k, t in _ARRAYS.items()}
        except LocalizationError:
            raise
        except Exception as exc:  # any malformed content: not trusted
            raise LocalizationError(f"malformed index: {exc}") from exc
        vp, uv, off, verts = (
            got[k] for k in ("viewpoints", "unit_view", "unit_vert_off", "unit_verts")
        )
        u = uv.size
        per_unit = ("unit_rmin", "unit_rmax", "unit_complexity", "unit_group")
        ok = all(got[k].shape == (u,) for k in per_unit) and got["unit_anchor"].shape == (u, 4)
        ok = ok and vp.ndim == 2 and vp.shape[1] == 2 and verts.ndim == 2 and verts.shape[1] == 2
        ok = ok and off.shape == (u + 1,) and (u == 0 or (uv.min() >= 0 and uv.max() < len(vp)))
        ok = ok and off[0] == 0 and off[-1] == len(verts) and bool(np.all(np.diff(off) >= 2))
        floats = [got[k] for k, t in _ARRAYS.items() if t is np.float64]
        ok = ok and all(bool(np.all(np.isfinite(a))) for a in floats)
        if not ok:
            raise LocalizationError("index arrays are inconsistent")
        return ViewIndex(
            key=expect_key,
            map_id=str(meta["map_id"]),
            kind=str(meta["kind"]),
            build_seconds=float(meta.get("build_seconds", 0.0)),
            **got,
        )
