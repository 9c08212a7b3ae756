"""ROS ``map_server`` occupancy grids: read, write, and turn into polylines.

A map_server map is a YAML file naming an image (PGM, PNG, ...) whose pixels hold the
occupancy of each cell. Keys (all required except ``mode``; as documented for ROS 1
``map_server`` and kept by ROS 2 ``nav2_map_server``):

``image``
    image path, absolute or relative to the YAML file's directory.
``resolution``
    metres per cell (> 0).
``origin``
    ``[x, y, yaw]``: pose in the map frame (metres, radians CCW) of the **lower-left corner of
    the lower-left cell** of the image. The image's row 0 is its top row, so image row ``r``
    of an ``h``-row image is grid row ``h - 1 - r`` counted upwards from the origin; ``yaw``
    rotates the whole grid about the origin. (``costmap_2d`` and RViz put the cell corner at
    the origin, cell centres half a cell in; so do we.)
``occupied_thresh``, ``free_thresh``
    occupancy-probability thresholds in [0, 1].
``negate``
    0/1 (or false/true): whether white means occupied instead of free.
``mode``
    ``trinary`` (default), ``scale`` or ``raw``.

Each pixel's colour ``x`` in [0, 255] is the mean of its channels (16-bit and other maxvals
are scaled to 0..255; in ``trinary`` mode an alpha channel is averaged in with the colours, in
``scale`` and ``raw`` mode it is not). With ``negate`` 0 the occupancy probability is
``p = (255 - x) / 255``, with ``negate`` 1 it is ``p = x / 255``. Then, per mode:

* ``trinary``: ``p > occupied_thresh`` -> 100 (occupied), ``p < free_thresh`` -> 0 (free),
  otherwise -1 (unknown).
* ``scale``: any transparency (alpha < 255) -> -1; else as trinary, except that values between
  the thresholds become ``99 * (p - free_thresh) / (occupied_thresh - free_thresh)``
  (truncated to an integer).
* ``raw``: the cell value is the colour itself (``255 - x`` with ``negate``; truncated to an
  integer); as in ``nav2_map_server``, values 0..100 are occupancy percentages and values
  above 100 mean unknown (-1).

The cell values follow ``nav_msgs/OccupancyGrid``: -1 unknown, 0..100 occupancy in percent.

Writing (:func:`write_map_yaml`) follows ``map_saver``: an 8-bit binary PGM with 0 for
occupied cells (value >= ``rint(100 * occupied_thresh)``), 254 for free cells
(0 <= value <= ``rint(100 * free_thresh)``) and 205 for everything else, plus a YAML with
``negate: 0`` and the two thresholds (defaults 0.65 and 0.196: read back, 254 is free,
205 unknown and 0 occupied).

Images are read by Pillow: Netpbm (``P2``/``P5`` grey, ``P3``/``P6`` colour, 8 or 16 bit,
header comments), PNG, BMP and the rest. Pillow scales a Netpbm ``maxval`` other than 255 (8
bit) or 65535 (16 bit) to the full range and rounds to integers, so such a pixel's colour can
differ from the exact ``v * 255 / maxval`` by up to half a grey level (measured: maxval 100,
value 50 reads 128 instead of 127.5); a cell changes class only if its occupancy lies within
0.2 % of a threshold. Files are untrusted: every problem raises :class:`InvalidMessage`
naming the file and, where there is one, the key. Images larger than
:data:`MAX_IMAGE_CELLS` cells and YAML files larger than :data:`MAX_YAML_BYTES` are refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from service.adapters.maps.contours import marching_squares, simplify_polylines
from service.core import numeric
from service.core.types import MapData, MapKind
from service.errors import InvalidMessage

#: Largest image accepted (cells = width x height): 64 M cells, e.g. 8000 x 8000 (a 400 x 400 m
#: floor at 5 cm); its decoded arrays take about 1 GB while being converted.
MAX_IMAGE_CELLS = 64_000_000
#: Largest map YAML file accepted (bytes).
MAX_YAML_BYTES = 1_000_000
#: Defaults written by ``map_saver`` (and :func:`write_map_yaml`).
DEFAULT_OCCUPIED_THRESH = 0.65
DEFAULT_FREE_THRESH = 0.196
#: Pixel values written by ``map_saver``.
PIXEL_OCCUPIED, PIXEL_FREE, PIXEL_UNKNOWN = 0, 254, 205
MODES = ("trinary", "scale", "raw")


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """An occupancy grid in ``map_server`` layout.

    ``data`` ``(h, w)`` int8, ``nav_msgs/OccupancyGrid`` values: -1 unknown, 0..100 occupancy
    probability in percent. Row 0 is the **top** row of the image (the row farthest from the
    origin along the grid's y axis), column 0 the left column. ``resolution`` metres per cell.
    ``origin`` ``(x, y, yaw)`` is the map-frame pose (metres, radians) of the lower-left corner
    of the lower-left cell (image row ``h - 1``, column 0). Validated on construction
    (:class:`InvalidMessage`); ``data`` is made read-only.
    """

    data: np.ndarray
    resolution: float
    origin: tuple[float, float, float]

    def __post_init__(self) -> None:
        d = np.asarray(self.data)
        if d.ndim != 2 or d.shape[0] < 1 or d.shape[1] < 1:
            raise InvalidMessage(f"occupancy grid: expected a non-empty 2-D array, got {d.shape}")
        if d.dtype != np.int8:
            if not np.issubdtype(d.dtype, np.integer):
                raise InvalidMessage(f"occupancy grid: data must be integer, got {d.dtype}")
            if d.size and (d.min() < -1 or d.max() > 100):
                raise InvalidMessage("occupancy grid: values must lie in -1..100")
            d = d.astype(np.int8)
        elif d.size and (d.min() < -1 or d.max() > 100):
            raise InvalidMessage("occupancy grid: values must lie in -1..100")
        if d.size > MAX_IMAGE_CELLS:
            raise InvalidMessage(f"occupancy grid: {d.size} cells > limit {MAX_IMAGE_CELLS}")
        d = np.array(d, dtype=np.int8, copy=True)
        d.setflags(write=False)
        object.__setattr__(self, "data", d)
        res = _finite("occupancy grid", "resolution", self.resolution)
        if res <= 0.0:
            raise InvalidMessage(f"occupancy grid: resolution must be > 0, got {res}")
        object.__setattr__(self, "resolution", res)
        o = self.origin
        if not isinstance(o, (tuple, list, np.ndarray)) or len(o) != 3:
            raise InvalidMessage(f"occupancy grid: origin must be (x, y, yaw), got {o!r}")
        object.__setattr__(self, "origin", tuple(_finite("occupancy grid", "origin", v) for v in o))

    # ------------------------------------------------------------------ construction
    @staticmethod
    def from_probability(
        prob: np.ndarray, resolution: float, origin: tuple[float, float, float]
    ) -> OccupancyGrid:
        """Grid from occupancy probabilities ``(h, w)`` in [0, 1] (NaN = unknown), row 0 = top.

        Values are rounded to whole percent.
        """
        p = np.asarray(prob, dtype=np.float64)
        if p.ndim != 2:
            raise InvalidMessage(f"occupancy grid: expected a 2-D array, got {p.shape}")
        known = np.isfinite(p)
        if np.any(known & ((p < 0.0) | (p > 1.0))):
            raise InvalidMessage("occupancy grid: probabilities must lie in [0, 1]")
        data = np.full(p.shape, -1, dtype=np.int8)
        data[known] = np.rint(p[known] * 100.0).astype(np.int8)
        return OccupancyGrid(data, resolution, origin)

    # ------------------------------------------------------------------ views
    @property
    def height(self) -> int:
        """Number of rows (image height)."""
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        """Number of columns (image width)."""
        return int(self.data.shape[1])

    def probability(self) -> np.ndarray:
        """Occupancy probability ``(h, w)`` float64 in [0, 1], NaN where unknown."""
        p = self.data.astype(np.float64) / 100.0
        p[self.data < 0] = np.nan
        return p

    def occupied(self, threshold: float = DEFAULT_OCCUPIED_THRESH) -> np.ndarray:
        """Cells whose occupancy is at least ``threshold`` (probability, compared in whole
        percent: value >= ``rint(100 * threshold)``), ``(h, w)`` bool."""
        return self.data >= int(np.rint(100.0 * threshold))

    def index_to_world(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Map-frame points ``(n, 2)`` (metres) of fractional image indices.

        Integer ``(row, col)`` is the centre of that cell; ``(h - 0.5, -0.5)`` is the origin.
        """
        r = np.asarray(rows, dtype=np.float64)
        c = np.asarray(cols, dtype=np.float64)
        u = (c + 0.5) * self.resolution
        v = (self.height - 0.5 - r) * self.resolution
        x0, y0, yaw = self.origin
        cs, sn = math.cos(yaw), math.sin(yaw)
        return np.column_stack((x0 + cs * u - sn * v, y0 + sn * u + cs * v))

    def world_to_index(self, points: np.ndarray) -> np.ndarray:
        """Fractional image indices ``(n, 2)`` ``(row, col)`` of map-frame points ``(n, 2)``;
        inverse of :meth:`index_to_world` (the cell containing a point is ``rint`` of it)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        x0, y0, yaw = self.origin
        cs, sn = math.cos(yaw), math.sin(yaw)
        dx, dy = p[:, 0] - x0, p[:, 1] - y0
        u = cs * dx + sn * dy
        v = -sn * dx + cs * dy
        return np.column_stack((self.height - 0.5 - v / self.resolution, u / self.resolution - 0.5))


# ---------------------------------------------------------------------- reading
def read_map_yaml(path: str | Path) -> OccupancyGrid:
    """Read a ``map_server`` map: the YAML file at ``path`` and the image it names.

    Honours ``image``, ``resolution``, ``origin``, ``occupied_thresh``, ``free_thresh``,
    ``negate`` and ``mode`` exactly as described in the module docstring. Raises
    :class:`InvalidMessage` naming the file (and key) for a missing or malformed key, an
    unreadable or malformed image, an image over :data:`MAX_IMAGE_CELLS` cells, or non-finite
    numbers.
    """
    import yaml

    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_YAML_BYTES:
            raise InvalidMessage(f"{p}: file too large ({size} bytes > {MAX_YAML_BYTES})")
        text = p.read_text(encoding="utf-8")
    except InvalidMessage:
        raise
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidMessage(f"{p}: unreadable map YAML ({exc})") from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise InvalidMessage(f"{p}:{where} bad YAML ({problem})") from exc
    if not isinstance(doc, dict):
        raise InvalidMessage(f"{p}: top level must be a mapping of map_server keys")

    def need(key: str) -> Any:
        if key not in doc:
            raise InvalidMessage(f"{p}: missing key '{key}'")
        return doc[key]

    image = need("image")
    if not isinstance(image, str) or not image.strip():
        raise InvalidMessage(f"{p}: key 'image' must be a non-empty file name, got {image!r}")
    resolution = _finite(str(p), "resolution", need("resolution"))
    if resolution <= 0.0:
        raise InvalidMessage(f"{p}: key 'resolution' must be > 0, got {resolution}")
    origin_raw = need("origin")
    if not isinstance(origin_raw, list) or len(origin_raw) != 3:
        raise InvalidMessage(f"{p}: key 'origin' must be a list [x, y, yaw], got {origin_raw!r}")
    origin = tuple(_finite(str(p), "origin", v) for v in origin_raw)
    occ_th = _finite(str(p), "occupied_thresh", need("occupied_thresh"))
    free_th = _finite(str(p), "free_thresh", need("free_thresh"))
    for key, v in (("occupied_thresh", occ_th), ("free_thresh", free_th)):
        if not 0.0 <= v <= 1.0:
            raise InvalidMessage(f"{p}: key '{key}' must lie in [0, 1], got {v}")
    if not free_th < occ_th:
        raise InvalidMessage(
            f"{p}: key 'free_thresh' ({free_th}) must be below 'occupied_thresh' ({occ_th})"
        )
    negate_raw = need("negate")
    if isinstance(negate_raw, bool):
        negate = negate_raw
    elif isinstance(negate_raw, int) and negate_raw in (0, 1):
        negate = bool(negate_raw)
    else:
        raise InvalidMessage(f"{p}: key 'negate' must be 0 or 1, got {negate_raw!r}")
    mode = doc.get("mode", "trinary")
    if mode not in MODES:
        raise InvalidMessage(f"{p}: key 'mode' must be one of {', '.join(MODES)}; got {mode!r}")

    img_path = Path(image)
    if not img_path.is_absolute():
        img_path = p.parent / img_path
    channels, alpha = _read_image(img_path)
    data = _pixels_to_cells(channels, alpha, negate, occ_th, free_th, mode)
    try:
        return OccupancyGrid(data, resolution, origin)  # type: ignore[arg-type]
    except InvalidMessage as exc:
        raise InvalidMessage(f"{p}: {exc}") from exc


def _finite(where: str, key: str, v: Any) -> float:
    """A finite float from a YAML scalar (bool and strings refused)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise InvalidMessage(f"{where}: key '{key}' must be a number, got {v!r}")
    f = float(v)
    if not math.isfinite(f):
        raise InvalidMessage(f"{where}: key '{key}' must be finite, got {v!r}")
    return f


def _pixels_to_cells(
    channels: np.ndarray,
    alpha: np.ndarray | None,
    negate: bool,
    occ_th: float,
    free_th: float,
    mode: str,
) -> np.ndarray:
    """map_server's pixel interpretation. ``channels`` ``(h, w, c)`` colour values scaled to
    [0, 255] (float); ``alpha`` ``(h, w)`` in [0, 255] or None. Returns int8 cell values."""
    if mode == "trinary" and alpha is not None:
        colour = (channels.sum(axis=2) + alpha) / (channels.shape[2] + 1)
    else:
        colour = channels.mean(axis=2)
    if negate:
        colour = 255.0 - colour
    if mode == "raw":
        raw = np.floor(colour).astype(np.int64)
        return np.where(raw <= 100, raw, -1).astype(np.int8)
    occ = (255.0 - colour) / 255.0
    out = np.full(colour.shape, -1, dtype=np.int8)
    if mode == "scale":
        mid = (occ >= free_th) & (occ <= occ_th)
        out[mid] = np.floor(99.0 * (occ[mid] - free_th) / (occ_th - free_th)).astype(np.int8)
    out[occ > occ_th] = 100
    out[occ < free_th] = 0
    if mode == "scale" and alpha is not None:
        out[alpha < 255.0] = -1
    return out


# ---------------------------------------------------------------------- images
def _read_image(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Colour channels ``(h, w, c)`` float64 scaled to [0, 255] and alpha ``(h, w)`` or None
    (Pillow; see the module docstring)."""
    return _read_pillow(path)


def _read_pillow(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    try:
        from PIL import Image
    except ImportError as exc:  # pragma: no cover - Pillow is a declared dependency
        raise InvalidMessage(f"{path}: reading this image format needs Pillow") from exc
    try:
        with Image.open(path) as im:
            w, h = im.size
            if w * h > MAX_IMAGE_CELLS:
                raise InvalidMessage(
                    f"{path}: image {w} x {h} exceeds the limit of {MAX_IMAGE_CELLS} cells"
                )
            mode = im.mode
            if mode == "P":
                im2 = im.convert("RGBA" if "transparency" in im.info else "RGB")
            elif mode in ("1", "L", "LA", "RGB", "RGBA", "I;16", "I;16B", "I;16L", "I"):
                im2 = im
            elif mode == "PA":
                im2 = im.convert("RGBA")
            else:
                im2 = im.convert("RGBA" if "A" in mode else "RGB")
            im2.load()
            arr = np.asarray(im2)
            mode = im2.mode
    except InvalidMessage:
        raise
    except Exception as exc:  # Pillow raises assorted errors on bad files
        raise InvalidMessage(f"{path}: unreadable image (key 'image'): {exc}") from exc
    if mode == "1":
        chans = arr.astype(np.float64)[..., None] * 255.0
        return chans, None
    if mode.startswith("I"):  # 16-bit grey (Pillow's "I;16*", or "I" holding 16-bit values)
        a = arr.astype(np.float64)
        if a.size and (a.min() < 0 or a.max() > 65535):
            raise InvalidMessage(f"{path}: 32-bit image values outside 0..65535")
        return (a * (255.0 / 65535.0))[..., None], None
    a = arr.astype(np.float64)
    if a.ndim == 2:
        return a[..., None], None
    if mode in ("LA", "RGBA"):
        return a[..., :-1], a[..., -1]
    return a, None


# ---------------------------------------------------------------------- writing
def write_map_yaml(
    grid: OccupancyGrid,
    path_yaml: str | Path,
    *,
    occupied_thresh: float = DEFAULT_OCCUPIED_THRESH,
    free_thresh: float = DEFAULT_FREE_THRESH,
) -> Path:
    """Write ``grid`` as ``map_saver`` does: ``path_yaml`` plus ``<stem>.pgm`` beside it.

    The PGM is binary 8-bit: 0 where value >= ``rint(100 * occupied_thresh)``, 254 where
    0 <= value <= ``rint(100 * free_thresh)``, 205 elsewhere (unknown and in-between). The YAML
    names the image relative to itself and carries ``resolution``, ``origin`` (full float
    precision), ``negate: 0`` and the two thresholds. Returns the image path. Raises
    :class:`InvalidMessage` for thresholds outside 0 <= free < occupied <= 1 and for write
    errors.
    """
    if not (0.0 <= free_thresh < occupied_thresh <= 1.0):
        raise InvalidMessage(
            f"write_map_yaml: need 0 <= free_thresh < occupied_thresh <= 1, got "
            f"{free_thresh}, {occupied_thresh}"
        )
    py = Path(path_yaml)
    img = py.with_suffix(".pgm")
    occ_int = int(np.rint(100.0 * occupied_thresh))
    free_int = int(np.rint(100.0 * free_thresh))
    d = grid.data
    pix = np.full(d.shape, PIXEL_UNKNOWN, dtype=np.uint8)
    pix[(d >= 0) & (d <= free_int)] = PIXEL_FREE
    pix[d >= occ_int] = PIXEL_OCCUPIED
    header = (
        f"P5\n# CREATOR: shapeloc write_map_yaml {grid.resolution!r} m/pix\n"
        f"{grid.width} {grid.height}\n255\n"
    ).encode("ascii")
    x, y, yaw = grid.origin
    text = (
        f"image: {img.name}\n"
        f"resolution: {grid.resolution!r}\n"
        f"origin: [{x!r}, {y!r}, {yaw!r}]\n"
        f"negate: 0\n"
        f"occupied_thresh: {occupied_thresh!r}\n"
        f"free_thresh: {free_thresh!r}\n"
    )
    try:
        img.write_bytes(header + np.ascontiguousarray(pix).tobytes())
        py.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise InvalidMessage(f"{py}: cannot write map ({exc})") from exc
    return img


# ---------------------------------------------------------------------- polylines
def grid_to_map(
    grid: OccupancyGrid,
    map_id: str,
    *,
    kind: MapKind = "metric",
    occupied_threshold: float = DEFAULT_OCCUPIED_THRESH,
    tolerance: float | None = None,
    min_blob_cells: int = 2,
) -> MapData:
    """Polylines along the faces of the occupied cells of ``grid`` (map frame, metres).

    * Occupied cells: value >= ``rint(100 * occupied_threshold)`` (unknown cells count as not
      occupied).
    * Noise: 8-connected groups of occupied cells with fewer than ``min_blob_cells`` cells are
      dropped (default 2: isolated single cells go).
    * Faces: the 0.5 iso-contour of the occupied mask sampled at cell centres (marching
      squares), which runs exactly along the shared face of an occupied and a free cell and
      cuts a cell corner diagonally at a convex or concave corner; diagonal neighbours join.
      Every blob becomes a closed ring (clockwise in the map frame: occupied on the right);
      a thick wall yields one ring around both faces.
    * Staircases of slanted walls are removed by Douglas-Peucker simplification with
      ``tolerance`` metres (default one cell, ``resolution``: the steps of a rasterised slanted
      face zigzag about one cell peak to peak around its line. Measured on a 3-cell thick,
      4 m long wall at 5-45 degrees, whose ring has 5 vertices (first repeated): half a cell
      leaves 7-43, one cell 5-9). Every dropped vertex stays within the tolerance of the
      result.
    * ``origin`` yaw and the image row order are applied exactly (see
      :meth:`OccupancyGrid.index_to_world`).

    Raises :class:`InvalidMessage` if no occupied cell survives.
    """
    if min_blob_cells < 1:
        raise InvalidMessage(f"grid_to_map: min_blob_cells must be >= 1, got {min_blob_cells}")
    tol = grid.resolution if tolerance is None else float(tolerance)
    if not (math.isfinite(tol) and tol >= 0.0):
        raise InvalidMessage(f"grid_to_map: tolerance must be finite and >= 0, got {tolerance}")
    occ = grid.occupied(occupied_threshold)
    if min_blob_cells > 1 and occ.any():
        labels, n = ndimage.label(occ, structure=np.ones((3, 3), dtype=bool))
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        keep = sizes >= min_blob_cells
        keep[0] = False
        occ = keep[labels]
    if not occ.any():
        raise InvalidMessage(
            f"grid_to_map: map {map_id!r} has no occupied cells (threshold {occupied_threshold}, "
            f"min_blob_cells {min_blob_cells})"
        )
    padded = np.pad(occ.astype(np.float64), 1)
    contours = marching_squares(padded, 0.5)
    # (row, col) of the padded grid -> metres in the grid frame (u right, v up), then simplify
    h = grid.height
    res = grid.resolution
    local = [
        np.column_stack(((c[:, 1] - 1 + 0.5) * res, (h - 0.5 - (c[:, 0] - 1)) * res))
        for c in contours
    ]
    if tol > 0.0:
        local = simplify_polylines(local, tol)
    x0, y0, yaw = grid.origin
    cs, sn = math.cos(yaw), math.sin(yaw)
    rot = np.array([[cs, sn], [-sn, cs]])
    polys = [numeric.matmul(q, rot) + np.array([x0, y0]) for q in local if q.shape[0] >= 2]
    return MapData.from_lists(map_id, kind, polys)
