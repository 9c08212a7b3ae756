"""View index files (service.adapters.maps.index_files): the store the core loads a map's view
index from before building it, a stale or corrupt file rebuilt and never trusted."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from service.adapters.maps.index_files import IndexFiles, load_index, save_index
from service.core.reloc import view_index as vi
from service.core.reloc.view_index import cache as view_index_cache
from service.core.types import MapData
from service.errors import LocalizationError


def _ring(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]], dtype=float)


def _room_map(box_at: float = 1.5) -> MapData:
    """A 6 x 4 m room with a 0.8 m box and an L-shaped alcove wall (not symmetric)."""
    walls = np.array([[0, 0], [6, 0], [6, 4], [2.5, 4], [2.5, 3.2], [0, 3.2], [0, 0]], float)
    return MapData.from_lists(
        "room", "metric", [walls, _ring(box_at, 1.0, box_at + 0.8, 1.8), _ring(4, 2, 4.3, 2.3)]
    )


def test_index_files_round_trip_invalidation_and_corrupt_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    md = _room_map()
    store = IndexFiles(tmp_path)
    vi.clear_memory_cache()
    built = vi.load_or_build_index(md, store=store)
    files = sorted(tmp_path.glob("viewindex-*.npz"))
    assert len(files) == 1 and files[0].name.startswith("viewindex-room-")
    assert len(built) > 0 and len(built.viewpoints) > 10

    # a fresh process (memory cleared) loads the file and never builds
    vi.clear_memory_cache()

    def no_build(*_a: object, **_k: object) -> vi.ViewIndex:
        raise AssertionError("index rebuilt although a valid index file exists")

    # load_or_build_index looks build_index up in its own module
    monkeypatch.setattr(view_index_cache, "build_index", no_build)
    loaded = vi.load_or_build_index(md, store=store)
    assert loaded.key == built.key
    saved, back = built.to_arrays(), loaded.to_arrays()
    assert saved.keys() == back.keys()
    for name in saved:
        np.testing.assert_array_equal(back[name], saved[name], err_msg=name)
    assert loaded.sensor is not None  # the map model is attached, not stored
    monkeypatch.undo()

    # the map changes (the box moved): new key, rebuilt, the stale file replaced
    vi.clear_memory_cache()
    md2 = _room_map(box_at=3.0)
    changed = vi.load_or_build_index(md2, store=store)
    assert changed.key != built.key
    files2 = sorted(tmp_path.glob("viewindex-*.npz"))
    assert len(files2) == 1 and files2[0] != files[0]

    # a corrupt file is rebuilt with a warning, never trusted
    vi.clear_memory_cache()
    files2[0].write_bytes(b"PK\x03\x04 this is not an index")
    with caplog.at_level(logging.WARNING, logger="shapeloc.global"):
        again = vi.load_or_build_index(md2, store=store)
    assert any("not usable" in r.getMessage() for r in caplog.records)
    np.testing.assert_array_equal(again.viewpoints, changed.viewpoints)
    vi.clear_memory_cache()
    assert load_index(files2[0], changed.key).key == changed.key  # rewritten, valid


def test_index_file_with_wrong_key_or_bad_arrays_is_refused(tmp_path: Path) -> None:
    md = _room_map()
    idx = vi.build_index(md)
    path = save_index(idx, tmp_path)
    with pytest.raises(LocalizationError, match="mismatch"):
        load_index(path, "0" * 64)
    arrays = idx.to_arrays()
    arrays["unit_view"] = arrays["unit_view"] + 10_000  # points past the viewpoints
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(LocalizationError, match="inconsistent"):
        load_index(bad, idx.key)


def test_an_unwritable_directory_is_reported_and_the_index_still_served(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("a file where the index directory should be")
    vi.clear_memory_cache()
    with caplog.at_level(logging.WARNING, logger="shapeloc.global"):
        idx = vi.load_or_build_index(_room_map(), store=IndexFiles(blocker / "viewcache"))
    assert len(idx) > 0 and idx.sensor is not None
    assert any("not saved" in r.getMessage() for r in caplog.records)
    vi.clear_memory_cache()
