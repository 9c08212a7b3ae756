"""Arrays derived from a configuration, stacked once and kept on it.

The matcher's compiled kernels take a configuration's features as one stacked array with row
offsets per feature (points, vertices, sampled points, a view's segments in a cut order, the
scan's angular intervals); they are built on first use and cached in the configuration's
``__dict__`` (a configuration's features do not change). Also the evenly spaced row samples
the matcher takes of a polyline's points (memoised per size).
"""

from __future__ import annotations

import numpy as np

from service.core import kernels
from service.core.kernels import shape as shape_kernels
from service.core.shapes.configuration import Configuration, Feature

_SAMPLE_ROWS: dict[tuple[int, int], np.ndarray] = {}


def sample_rows(n: int, k: int) -> np.ndarray:
    """``k`` evenly spaced rows of ``n`` (``np.linspace`` rounded), memoised per ``(n, k)``."""
    idx = _SAMPLE_ROWS.get((n, k))
    if idx is None:
        if len(_SAMPLE_ROWS) >= 4096:
            _SAMPLE_ROWS.clear()
        idx = np.linspace(0, n - 1, k).round().astype(int)
        idx.setflags(write=False)
        _SAMPLE_ROWS[(n, k)] = idx
    return idx


def subsample(points: np.ndarray, k: int) -> np.ndarray:
    """At most ``k`` evenly spaced rows of ``points`` (all of them when there are no more)."""
    if len(points) <= k:
        return points
    return points[sample_rows(len(points), k)]


def _stacked(C: Configuration, attr: str) -> tuple[np.ndarray, np.ndarray]:
    """The features' ``attr`` arrays of ``C`` stacked ``(N, 2)`` and the row offsets per
    feature, cached on the configuration under ``_stacked_<attr>``."""
    key = f"_stacked_{attr}"
    got = C.__dict__.get(key)
    if got is None:
        rows = [getattr(f, attr) for f in C.features]
        arr = np.ascontiguousarray(np.vstack(rows), dtype=np.float64)
        off = np.concatenate(([0], np.cumsum([len(x) for x in rows])))
        got = (arr, off.astype(np.intp))
        C.__dict__[key] = got
    return got


def stacked_points(C: Configuration) -> tuple[np.ndarray, np.ndarray]:
    """All feature points of ``C`` stacked ``(N, 2)`` and the row offsets per feature
    (cached on the configuration)."""
    return _stacked(C, "points")


def stacked_vertices(C: Configuration) -> tuple[np.ndarray, np.ndarray]:
    """All feature vertices of ``C`` stacked ``(N, 2)`` and the row offsets per feature
    (cached on the configuration)."""
    return _stacked(C, "vertices")


def scan_intervals(P: Configuration) -> np.ndarray:
    """``(n, 2)`` rows ``(bearing_start, angular_size)`` of the scan's features (cached)."""
    got = P.__dict__.get("_intervals")
    if got is None:
        got = np.array([(f.bearing_start, f.angular_size) for f in P.features]).reshape(-1, 2)
        P.__dict__["_intervals"] = got
    return got


def feature_sample(f: Feature, k: int) -> np.ndarray:
    """:func:`subsample` of a feature's points (cached on the feature)."""
    pts = f.cache.get(("sample", k))
    if pts is None:
        pts = subsample(f.points, k)
        f.cache[("sample", k)] = pts
    return pts


def scan_samples(P: Configuration, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Every scan feature's points subsampled to at most ``k``, stacked ``(N, 2)``, and the
    row offsets per feature (cached on the configuration)."""
    key = ("_samples", k)
    got = P.__dict__.get(key)
    if got is None:
        samples = [feature_sample(f, k) for f in P.features]
        off = np.concatenate(([0], np.cumsum([len(x) for x in samples])))
        got = (np.vstack(samples), off)
        P.__dict__[key] = got
    return got


def view_segments(Q: Configuration, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The map segments of the view's features in ``order``, stacked ``(S, 4)``, and the row
    offsets per position in the order (cached on the view per order)."""
    store = Q.__dict__.setdefault("_segments_by_order", {})
    key = order.tobytes()
    got = store.get(key)
    if got is None:
        segs = [Q.features[j].segments for j in order.tolist()]
        segs = [x if x is not None else np.zeros((0, 4)) for x in segs]
        off = np.concatenate(([0], np.cumsum([len(x) for x in segs])))
        got = (np.vstack(segs), off)
        store[key] = got
    return got


def piece_means(C: Configuration, pieces: np.ndarray) -> np.ndarray:
    """``(R, 2)``: per row of ``pieces`` (feature indices, ``-1`` padded) the mean point of
    those features' points joined, exactly ``np.vstack(points).mean(axis=0)`` (which sums
    the rows in order): in one compiled call with numba, else that expression per row."""
    if not kernels.HAVE_NUMBA:
        rows = [[C.features[f].points for f in row if f >= 0] for row in pieces.tolist()]
        return np.array([np.vstack(r).mean(axis=0) for r in rows]).reshape(-1, 2)
    pts, off = stacked_points(C)
    return shape_kernels.piece_means(pts, off, np.ascontiguousarray(pieces, dtype=np.intp))
