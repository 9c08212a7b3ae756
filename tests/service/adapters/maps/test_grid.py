"""ROS map_server grids: reading (PGM P2/P5 8/16 bit, PNG, modes, negate, thresholds),
writing like map_saver, round trips, origin yaw and row flip, polylines along the faces, errors;
and the marching-squares contours underneath."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import shapely

from service.adapters.maps import grid as grid_mod
from service.adapters.maps.contours import join_polylines, marching_squares, simplify_polylines
from service.adapters.maps.grid import OccupancyGrid, grid_to_map, read_map_yaml, write_map_yaml
from service.errors import InvalidMessage

RES = 0.1

# An asymmetric L-shaped room (grid frame, metres, origin at the lower-left image corner):
# free inside the L, walls one cell thick around it. The L's long arm runs up the left side,
# its short arm along the bottom; mirrored or flipped it would not match.
L_FREE = [(0.5, 0.5), (3.5, 0.5), (3.5, 1.5), (1.5, 1.5), (1.5, 2.5), (0.5, 2.5)]
W_CELLS, H_CELLS = 42, 30  # 4.2 m x 3.0 m image


def _l_room_mask() -> np.ndarray:
    """Occupied cells (row 0 = top): the one-cell band just outside the free L."""
    free = shapely.Polygon(np.array(L_FREE) * 1.0)
    band = free.buffer(RES, join_style="mitre").difference(free)
    rows, cols = np.mgrid[0:H_CELLS, 0:W_CELLS]
    u = (cols + 0.5) * RES
    v = (H_CELLS - 0.5 - rows) * RES
    inside = shapely.contains_xy(band, u.ravel(), v.ravel()).reshape(rows.shape)
    return inside


def _write_pgm_p5(path: Path, pix: np.ndarray, maxval: int = 255) -> None:
    h, w = pix.shape
    dtype = ">u2" if maxval > 255 else np.uint8
    path.write_bytes(
        f"P5\n# test image\n{w} {h}\n{maxval}\n".encode() + pix.astype(dtype).tobytes()
    )


def _write_yaml(path: Path, image: str, **kw: object) -> Path:
    d = {
        "resolution": RES,
        "origin": "[0.0, 0.0, 0.0]",
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    d.update(kw)
    lines = [f"image: {image}"] + [f"{k}: {v}" for k, v in d.items() if v is not None]
    path.write_text("\n".join(lines) + "\n")
    return path


def _expected_rings(origin: tuple[float, float, float]) -> list[np.ndarray]:
    """The faces: the free L's outline and the band's outer outline, in the map frame."""
    free = shapely.Polygon(L_FREE)
    outer = free.buffer(RES, join_style="mitre")
    x0, y0, yaw = origin
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for g in (free, outer):
        q = np.asarray(g.exterior.coords)
        out.append(
            np.column_stack((x0 + c * q[:, 0] - s * q[:, 1], y0 + s * q[:, 0] + c * q[:, 1]))
        )
    return out


def _check_l_room(grid: OccupancyGrid, origin: tuple[float, float, float]) -> None:
    m = grid_to_map(grid, "l-room")
    assert m.kind == "metric"
    assert len(m.polylines) == 2  # the band is one blob: its outer and inner faces
    truth = _expected_rings(origin)
    true_lines = shapely.MultiLineString([shapely.LineString(r) for r in truth])
    verts = np.vstack(m.polylines)
    # every vertex lies on a true face (within a cell) ...
    d = shapely.distance(true_lines, shapely.points(verts))
    assert d.max() < RES
    # ... and every true corner has a vertex within a cell
    for ring in truth:
        for corner in ring[:-1]:
            assert np.hypot(*(verts - corner).T).min() < RES, corner
    # both rings closed, few vertices (staircase-free: 6 and 6 corners, chamfered)
    for p in m.polylines:
        assert np.allclose(p[0], p[-1])
        assert len(p) <= 14


def test_l_room_pgm_to_polylines_yaw_zero(tmp_path: Path) -> None:
    occ = _l_room_mask()
    pix = np.where(occ, 0, 254)
    _write_pgm_p5(tmp_path / "room.pgm", pix)
    g = read_map_yaml(_write_yaml(tmp_path / "room.yaml", "room.pgm"))
    assert (g.height, g.width) == (H_CELLS, W_CELLS)
    assert np.array_equal(g.data == 100, occ)
    assert np.all(g.data[~occ] == 0)
    _check_l_room(g, (0.0, 0.0, 0.0))


def test_l_room_origin_with_yaw_and_offset(tmp_path: Path) -> None:
    occ = _l_room_mask()
    _write_pgm_p5(tmp_path / "room.pgm", np.where(occ, 0, 254))
    origin = (-3.25, 7.5, 0.6)
    g = read_map_yaml(
        _write_yaml(tmp_path / "room.yaml", "room.pgm", origin=f"[{origin[0]}, {origin[1]}, 0.6]")
    )
    assert g.origin == pytest.approx(origin)
    _check_l_room(g, origin)


def test_row_flip_and_origin_mapping() -> None:
    data = np.zeros((3, 4), dtype=np.int8)
    g = OccupancyGrid(data, 0.5, (1.0, 2.0, math.pi / 2))
    # lower-left cell (image row h-1, col 0) has its centre a quarter cell... half a cell in
    ll = g.index_to_world(np.array([2.0]), np.array([0.0]))[0]
    assert ll == pytest.approx([1.0 - 0.25, 2.0 + 0.25])
    # top-right cell centre: u = 3.5 * 0.5, v = 2.5 * 0.5, rotated by +90 deg
    tr = g.index_to_world(np.array([0.0]), np.array([3.0]))[0]
    assert tr == pytest.approx([1.0 - 1.25, 2.0 + 1.75])
    # the origin itself is the outer corner of the lower-left cell
    assert g.index_to_world(np.array([2.5]), np.array([-0.5]))[0] == pytest.approx([1.0, 2.0])
    pts = np.array([[0.3, 2.9], [-0.7, 3.1]])
    back = g.index_to_world(*g.world_to_index(pts).T)
    assert back == pytest.approx(pts)


def test_negate_gives_the_same_grid(tmp_path: Path) -> None:
    occ = _l_room_mask()
    _write_pgm_p5(tmp_path / "a.pgm", np.where(occ, 0, 254))
    _write_pgm_p5(tmp_path / "b.pgm", np.where(occ, 255, 1))  # white = occupied
    a = read_map_yaml(_write_yaml(tmp_path / "a.yaml", "a.pgm"))
    b = read_map_yaml(_write_yaml(tmp_path / "b.yaml", "b.pgm", negate=1))
    assert np.array_equal(a.data, b.data)
    c = read_map_yaml(_write_yaml(tmp_path / "c.yaml", "b.pgm", negate="true"))
    assert np.array_equal(a.data, c.data)
    # without negate the white walls are free and the dark room occupied
    d = read_map_yaml(_write_yaml(tmp_path / "d.yaml", "b.pgm"))
    assert np.all(d.data[occ] == 0) and np.all(d.data[~occ] == 100)


def test_trinary_scale_raw_and_thresholds(tmp_path: Path) -> None:
    # colours x: p = (255 - x) / 255 -> 0: 1.0, 50: 0.804, 100: 0.608, 128: 0.498,
    # 205: 0.196 (just above 0.196), 230: 0.098, 254: 0.004
    pix = np.array([[0, 50, 100, 128, 205, 230, 254]])
    _write_pgm_p5(tmp_path / "g.pgm", pix)
    tri = read_map_yaml(_write_yaml(tmp_path / "t.yaml", "g.pgm"))
    assert tri.data.tolist() == [[100, 100, -1, -1, -1, 0, 0]]
    low = read_map_yaml(_write_yaml(tmp_path / "l.yaml", "g.pgm", occupied_thresh=0.4))
    assert low.data.tolist() == [[100, 100, 100, 100, -1, 0, 0]]
    sc = read_map_yaml(_write_yaml(tmp_path / "s.yaml", "g.pgm", mode="scale"))
    # between the thresholds: floor(99 * (p - 0.196) / (0.65 - 0.196))
    p = (255.0 - np.array([100, 128, 205])) / 255.0
    mid = np.floor(99.0 * (p - 0.196) / (0.65 - 0.196)).astype(int).tolist()
    assert sc.data.tolist() == [[100, 100, *mid, 0, 0]]
    raw_pix = np.array([[0, 37, 100, 101, 255]])
    _write_pgm_p5(tmp_path / "r.pgm", raw_pix)
    raw = read_map_yaml(_write_yaml(tmp_path / "r.yaml", "r.pgm", mode="raw"))
    assert raw.data.tolist() == [[0, 37, 100, -1, -1]]
    rawn = read_map_yaml(_write_yaml(tmp_path / "rn.yaml", "r.pgm", mode="raw", negate=1))
    assert rawn.data.tolist() == [[-1, -1, -1, -1, 0]]


def test_plain_p2_and_16_bit_p5(tmp_path: Path) -> None:
    (tmp_path / "p2.pgm").write_text("P2\n# comment\n3 2\n# another\n15\n0 15 7\n15 0 15\n")
    g = read_map_yaml(_write_yaml(tmp_path / "p2.yaml", "p2.pgm"))
    # 7/15 of white -> p = 0.533: unknown
    assert g.data.tolist() == [[100, 0, -1], [0, 100, 0]]
    pix16 = np.array([[0, 65535, 30000]])
    _write_pgm_p5(tmp_path / "s16.pgm", pix16, maxval=65535)
    g16 = read_map_yaml(_write_yaml(tmp_path / "s16.yaml", "s16.pgm"))
    assert g16.data.tolist() == [[100, 0, -1]]


def test_netpbm_maxval_other_than_full_range(tmp_path: Path) -> None:
    """Pillow scales a maxval other than 255 / 65535 to the full range and rounds: value 35 of
    maxval 100 reads as grey 89, not 89.25, so its occupancy is 0.651 instead of exactly
    occupied_thresh 0.65 and the cell is occupied rather than unknown (the only kind of cell
    the rounding changes: within 0.2 % of a threshold). 16-bit maxval 1000 reads as well."""
    _write_pgm_p5(tmp_path / "m100.pgm", np.array([[0, 35, 50, 100]]), maxval=100)
    g = read_map_yaml(_write_yaml(tmp_path / "m100.yaml", "m100.pgm"))
    assert g.data.tolist() == [[100, 100, -1, 0]]
    _write_pgm_p5(tmp_path / "m1000.pgm", np.array([[0, 500, 1000]]), maxval=1000)
    g = read_map_yaml(_write_yaml(tmp_path / "m1000.yaml", "m1000.pgm"))
    assert g.data.tolist() == [[100, -1, 0]]


def test_png_through_pillow_with_alpha(tmp_path: Path) -> None:
    from PIL import Image

    rgba = np.zeros((1, 4, 4), dtype=np.uint8)
    rgba[0, 0] = (0, 0, 0, 255)  # opaque black: occupied
    rgba[0, 1] = (254, 254, 254, 255)  # opaque white: free
    rgba[0, 2] = (120, 120, 120, 0)  # transparent grey: unknown in scale mode
    rgba[0, 3] = (255, 0, 0, 255)  # red: mean 85 of the colours -> p = 0.667 -> occupied
    Image.fromarray(rgba, "RGBA").save(tmp_path / "m.png")
    sc = read_map_yaml(_write_yaml(tmp_path / "s.yaml", "m.png", mode="scale"))
    assert sc.data.tolist() == [[100, 0, -1, 100]]
    # trinary averages alpha in with the colours: red -> (255 + 0 + 0 + 255) / 4 = 127.5
    tri = read_map_yaml(_write_yaml(tmp_path / "t.yaml", "m.png"))
    assert tri.data.tolist()[0][:2] == [100, 0]
    assert tri.data[0, 3] == -1
    grey = np.array([[0, 254]], dtype=np.uint8)
    Image.fromarray(grey, "L").save(tmp_path / "g.png")
    assert read_map_yaml(_write_yaml(tmp_path / "g.yaml", "g.png")).data.tolist() == [[100, 0]]


def test_block_style_yaml_and_absolute_image(tmp_path: Path) -> None:
    _write_pgm_p5(tmp_path / "a.pgm", np.array([[0, 254]]))
    (tmp_path / "sub").mkdir()
    y = tmp_path / "sub" / "m.yaml"
    y.write_text(
        f"# a map\nimage: '{tmp_path / 'a.pgm'}'\nresolution: 0.05\norigin:\n  - -1.5\n"
        "  - 2\n  - 0.0\nnegate: false\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    g = read_map_yaml(y)
    assert g.origin == (-1.5, 2.0, 0.0) and g.resolution == 0.05
    assert g.data.tolist() == [[100, 0]]


def test_write_read_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    data = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(17, 23))
    g = OccupancyGrid(data, 0.05, (-12.5, 3.125, -0.3))
    img = write_map_yaml(g, tmp_path / "out.yaml")
    assert img == tmp_path / "out.pgm"
    assert img.read_bytes()[:2] == b"P5"
    back = read_map_yaml(tmp_path / "out.yaml")
    assert np.array_equal(back.data, g.data)
    assert back.origin == g.origin and back.resolution == g.resolution
    # in-between values take map_saver's classes: <= 20 free, >= 65 occupied, else unknown
    mixed = OccupancyGrid(np.array([[0, 20, 21, 64, 65, 99, -1]], dtype=np.int8), 0.1, (0, 0, 0))
    write_map_yaml(mixed, tmp_path / "mixed.yaml")
    pgm = (tmp_path / "mixed.pgm").read_bytes()
    assert list(pgm[-7:]) == [254, 254, 205, 205, 0, 0, 205]
    assert read_map_yaml(tmp_path / "mixed.yaml").data.tolist() == [[0, 0, -1, -1, 100, 100, -1]]


def test_from_probability_and_views() -> None:
    p = np.array([[0.0, 0.5, np.nan], [1.0, 0.654, 0.2]])
    g = OccupancyGrid.from_probability(p, 0.1, (0, 0, 0))
    assert g.data.tolist() == [[0, 50, -1], [100, 65, 20]]
    assert np.isnan(g.probability()[0, 2]) and g.probability()[1, 1] == pytest.approx(0.65)
    assert g.occupied().tolist() == [[False, False, False], [True, True, False]]
    assert not g.data.flags.writeable


def test_small_blobs_dropped_and_no_occupied_cells_raises() -> None:
    data = np.zeros((20, 20), dtype=np.int8)
    data[5:8, 5:15] = 100  # a 3 x 10 cell wall
    data[15, 15] = 100  # a single noise cell
    g = OccupancyGrid(data, 0.05, (0, 0, 0))
    assert len(grid_to_map(g, "x").polylines) == 1
    assert len(grid_to_map(g, "x", min_blob_cells=1).polylines) == 2
    with pytest.raises(InvalidMessage, match="no occupied cells"):
        grid_to_map(OccupancyGrid(np.zeros((4, 4), dtype=np.int8), 0.05, (0, 0, 0)), "empty")


def test_slanted_wall_staircase_removed() -> None:
    h, w = 80, 120
    rr, cc = np.mgrid[0:h, 0:w]
    u, v = (cc + 0.5) * 0.05, (h - 0.5 - rr) * 0.05
    a = math.radians(20)
    dist = np.abs(-(u - 1) * math.sin(a) + (v - 1) * math.cos(a))
    t = (u - 1) * math.cos(a) + (v - 1) * math.sin(a)
    data = np.where((dist < 0.075) & (t > 0) & (t < 4), 100, 0).astype(np.int8)
    m = grid_to_map(OccupancyGrid(data, 0.05, (0, 0, 0)), "slant")
    (ring,) = m.polylines
    assert len(ring) <= 9  # a 4-corner ring, a couple of staircase vertices left at most
    # the long sides run at 20 degrees
    seg = np.diff(ring, axis=0)
    longest = seg[np.argmax(np.hypot(*seg.T))]
    ang = math.degrees(math.atan2(longest[1], longest[0])) % 180.0
    assert ang == pytest.approx(20.0, abs=1.5)


@pytest.mark.parametrize(
    ("yaml_text", "message"),
    [
        (
            "resolution: 0.1\norigin: [0,0,0]\nnegate: 0\noccupied_thresh: 0.65\n"
            "free_thresh: 0.2\n",
            "missing key 'image'",
        ),
        (
            "image: a.pgm\norigin: [0,0,0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.2\n",
            "missing key 'resolution'",
        ),
        (
            "image: a.pgm\nresolution: .nan\norigin: [0,0,0]\nnegate: 0\noccupied_thresh: 0.65\n"
            "free_thresh: 0.2\n",
            "'resolution' must be finite",
        ),
        (
            "image: a.pgm\nresolution: -1\norigin: [0,0,0]\nnegate: 0\noccupied_thresh: 0.65\n"
            "free_thresh: 0.2\n",
            "'resolution' must be > 0",
        ),
        (
            "image: a.pgm\nresolution: 0.1\norigin: [0,0]\nnegate: 0\noccupied_thresh: 0.65\n"
            "free_thresh: 0.2\n",
            "'origin' must be a list",
        ),
        (
            "image: a.pgm\nresolution: 0.1\norigin: [0,.inf,0]\nnegate: 0\noccupied_thresh: 0.65\n"
            "free_thresh: 0.2\n",
            "'origin' must be finite",
        ),
        (
            "image: a.pgm\nresolution: 0.1\norigin: [0,0,0]\nnegate: 2\noccupied_thresh: 0.65\n"
            "free_thresh: 0.2\n",
            "'negate' must be 0 or 1",
        ),
        (
            "image: a.pgm\nresolution: 0.1\norigin: [0,0,0]\nnegate: 0\noccupied_thresh: 0.1\n"
            "free_thresh: 0.2\n",
            "'free_thresh'",
        ),
        (
            "image: a.pgm\nresolution: 0.1\norigin: [0,0,0]\nnegate: 0\noccupied_thresh: 0.65\n"
            "free_thresh: 0.2\nmode: fuzzy\n",
            "'mode'",
        ),
        ("image: a.pgm\nresolution: [0.1\n", "bad YAML"),
        ("- image\n- a.pgm\n", "top level must be a mapping"),
        (
            "image: missing.pgm\nresolution: 0.1\norigin: [0,0,0]\nnegate: 0\n"
            "occupied_thresh: 0.65\n"
            "free_thresh: 0.2\n",
            "missing.pgm.*unreadable image",
        ),
    ],
)
def test_yaml_errors_name_file_and_key(tmp_path: Path, yaml_text: str, message: str) -> None:
    _write_pgm_p5(tmp_path / "a.pgm", np.array([[0, 254]]))
    y = tmp_path / "m.yaml"
    y.write_text(yaml_text)
    with pytest.raises(InvalidMessage, match=message) as info:
        read_map_yaml(y)
    assert "m.yaml" in str(info.value) or "missing.pgm" in str(info.value)


@pytest.mark.parametrize(
    ("blob", "message"),
    [
        # Pillow reads the images; its reasons follow "unreadable image (key 'image'): "
        (b"P5\n4 2\n255\n\x00\x00\x00", "truncated"),
        (b"P5\n4 x\n255\n", "unreadable image"),  # a non-numeric height
        (b"P5\n4 2\n70000\n", "maxval"),
        (b"P2\n2 1\n10\n5 11\n", "too large"),  # a sample above maxval
        (b"P2\n3 1\n255\n5 6\n", "not enough image data"),
        (b"PX\n1 1\n255\n\x00", "unreadable image"),
    ],
)
def test_bad_images(tmp_path: Path, blob: bytes, message: str) -> None:
    (tmp_path / "a.pgm").write_bytes(blob)
    y = _write_yaml(tmp_path / "m.yaml", "a.pgm")
    with pytest.raises(InvalidMessage, match=message) as info:
        read_map_yaml(y)
    assert "a.pgm" in str(info.value)


def test_image_size_limit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _write_pgm_p5(tmp_path / "a.pgm", np.zeros((10, 10)))
    y = _write_yaml(tmp_path / "m.yaml", "a.pgm")
    monkeypatch.setattr(grid_mod, "MAX_IMAGE_CELLS", 99)
    with pytest.raises(InvalidMessage, match="exceeds the limit of 99 cells"):
        read_map_yaml(y)


def test_grid_validation() -> None:
    with pytest.raises(InvalidMessage, match=r"-1\.\.100"):
        OccupancyGrid(np.array([[101]]), 0.1, (0, 0, 0))
    with pytest.raises(InvalidMessage, match="resolution"):
        OccupancyGrid(np.zeros((2, 2), dtype=np.int8), 0.0, (0, 0, 0))
    with pytest.raises(InvalidMessage, match="origin"):
        OccupancyGrid(np.zeros((2, 2), dtype=np.int8), 0.1, (0, math.nan, 0))
    with pytest.raises(InvalidMessage, match="free_thresh < occupied_thresh"):
        write_map_yaml(
            OccupancyGrid(np.zeros((2, 2), dtype=np.int8), 0.1, (0, 0, 0)),
            "x.yaml",
            occupied_thresh=0.2,
            free_thresh=0.3,
        )


# ---------------------------------------------------------------------- contours
def test_marching_squares_ring_orientation_and_open_contours() -> None:
    f = np.zeros((5, 6))
    f[2, 2] = 1.0
    (ring,) = marching_squares(f, 0.5)
    assert np.allclose(ring[0], ring[-1]) and len(ring) == 5
    # (x, y) = (col, row): the region >= level (the cell centre) is on the left: CCW in that
    # plane, positive signed area
    x, y = ring[:, 1], ring[:, 0]
    area = 0.5 * np.sum(x[:-1] * y[1:] - x[1:] * y[:-1])
    assert area == pytest.approx(0.5)
    ramp = np.tile(np.arange(5.0), (4, 1))  # increases with col
    (line,) = marching_squares(ramp, 2.5)
    assert np.allclose(line[:, 1], 2.5) and line[0, 0] == 3 and line[-1, 0] == 0
    # a mask cuts the contour
    ramp6 = np.tile(np.arange(5.0), (6, 1))
    mask = np.ones_like(ramp6, dtype=bool)
    mask[2, :] = False  # squares touching row 2 go: rows 0-1 and 3-5 remain
    pieces = marching_squares(ramp6, 2.5, mask)
    assert sorted(len(p) for p in pieces) == [2, 3]


def test_marching_squares_saddle_joins_above() -> None:
    f = np.zeros((4, 4))
    f[1, 1] = f[2, 2] = 1.0  # diagonal neighbours: one 8-connected blob
    assert len(marching_squares(f, 0.5)) == 1
    g = -f  # the diagonal pair is now below: the above region stays connected, two holes
    assert len(marching_squares(g, -0.5)) == 2


def test_simplify_and_join_polylines() -> None:
    zig = np.column_stack((np.arange(0, 2.01, 0.1), 0.01 * (-1) ** np.arange(21)))
    (s,) = simplify_polylines([zig], 0.02)
    assert len(s) == 2 and np.allclose(s[[0, -1]], zig[[0, -1]])
    a = np.array([[0.0, 0.0], [1.0, 0.0]])
    b = np.array([[2.0, 0.0], [1.2, 0.01]])  # reversed, facing a across 0.2
    c = np.array([[1.1, 0.5], [1.1, 1.5]])  # off to the side: not joined
    out = join_polylines([a, b, c], max_gap=0.3, max_angle=15.0, snap=0.01, end_window=0.5)
    assert len(out) == 2
    joined = next(p for p in out if len(p) == 4)
    assert np.allclose(joined[[0, -1]], [[0, 0], [2, 0]]) or np.allclose(
        joined[[0, -1]], [[2, 0], [0, 0]]
    )
    apart = join_polylines([a, b], max_gap=0.1, max_angle=15.0, snap=0.01, end_window=0.5)
    assert len(apart) == 2
