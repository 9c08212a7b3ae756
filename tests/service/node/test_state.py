"""SQLite state store: round trip, reset-on-config, corrupt/foreign/newer files, directory lock.
Pure file I/O in tmp_path; well under a second."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import msgpack
import pytest

from service.errors import StateError
from service.node.state import DB_NAME, SCHEMA_VERSION, SavedPose, StateStore

MAP = {"map_id": "m1", "kind": "metric", "polylines": [[[0.0, 0.0], [1.0, 0.0]]]}
CFG = {"map_id": "m1", "method": "shape", "initial_pose": [1.0, 2.0, 0.5]}


def test_missing_dir_is_created_and_versioned(tmp_path: Path) -> None:
    d = tmp_path / "a" / "b"
    with StateStore(d) as st:
        assert st.maps() == {} and st.robots() == {} and st.poses() == {}
    db = sqlite3.connect(d / DB_NAME)
    assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    db.close()


def test_round_trip_across_reopen(tmp_path: Path) -> None:
    with StateStore(tmp_path) as st:
        st.put_map("m1", MAP)
        st.put_map("m2", {**MAP, "map_id": "m2", "kind": "schematic"})
        st.put_robot("r1", CFG)
        st.save_poses({"r1": SavedPose("m1", 1.5, -2.0, 3.0, 42, 12.5, "tracking")})
        assert st.delete_map("m2") is True
        assert st.delete_map("nope") is False
    with StateStore(tmp_path) as st:
        assert st.maps() == {"m1": MAP}
        assert st.robots() == {"r1": CFG}
        p = st.poses()["r1"]
        assert p.pose == (1.5, -2.0, 3.0)
        assert (p.map_id, p.seq, p.stamp, p.status) == ("m1", 42, 12.5, "tracking")


def test_odom_saved_with_the_pose(tmp_path: Path) -> None:
    with StateStore(tmp_path) as st:
        st.save_poses(
            {
                "r1": SavedPose("m1", 1.0, 2.0, 0.5, 7, 3.0, "tracking", (10.0, -4.0, 2.9)),
                "r2": SavedPose("m1", 1.0, 2.0, 0.5, 8, 3.0, "tracking"),
                "r3": SavedPose("m1", 1.0, 2.0, 0.5, 9, 3.0, "tracking", (0.0, float("inf"), 0)),
            }
        )
    with StateStore(tmp_path) as st:
        saved = st.poses()
    assert saved["r1"].odom == (10.0, -4.0, 2.9)
    assert saved["r2"].odom is None
    assert saved["r3"].odom is None  # a non-finite odometry pose is not kept
    assert saved["r3"].pose == (1.0, 2.0, 0.5)


# The schema-1 layout as released (no odom columns), to check that such a file still opens.
_V1_DDL = [
    "CREATE TABLE maps (map_id TEXT PRIMARY KEY, payload BLOB NOT NULL, updated REAL NOT NULL)",
    "CREATE TABLE robots (robot_id TEXT PRIMARY KEY, payload BLOB NOT NULL, updated REAL NOT NULL)",
    "CREATE TABLE poses (robot_id TEXT PRIMARY KEY, map_id TEXT NOT NULL, "
    "x REAL NOT NULL, y REAL NOT NULL, theta REAL NOT NULL, seq INTEGER NOT NULL, "
    "stamp REAL NOT NULL, status TEXT NOT NULL, updated REAL NOT NULL)",
]


def _write_v1(path: Path) -> None:
    db = sqlite3.connect(path)
    for ddl in _V1_DDL:
        db.execute(ddl)
    db.execute("INSERT INTO maps VALUES ('m1', ?, 1.0)", (msgpack.packb(MAP),))
    db.execute("INSERT INTO robots VALUES ('r1', ?, 1.0)", (msgpack.packb(CFG),))
    db.execute("INSERT INTO poses VALUES ('r1', 'm1', 1.5, -2.0, 3.0, 42, 12.5, 'tracking', 1.0)")
    db.execute("PRAGMA user_version=1")
    db.commit()
    db.close()


def test_schema_1_file_is_migrated(tmp_path: Path) -> None:
    assert SCHEMA_VERSION == 2
    _write_v1(tmp_path / DB_NAME)
    with StateStore(tmp_path) as st:
        assert st.maps() == {"m1": MAP} and st.robots() == {"r1": CFG}
        p = st.poses()["r1"]
        assert (p.pose, p.seq, p.status, p.odom) == ((1.5, -2.0, 3.0), 42, "tracking", None)
        st.save_poses({"r1": SavedPose("m1", 2.0, -2.0, 3.0, 43, 13.0, "tracking", (1, 2, 3))})
    db = sqlite3.connect(tmp_path / DB_NAME)
    assert db.execute("PRAGMA user_version").fetchone()[0] == 2
    cols = [r[1] for r in db.execute("PRAGMA table_info(poses)")]
    assert cols[-3:] == ["odom_x", "odom_y", "odom_theta"]
    db.close()
    with StateStore(tmp_path) as st:  # the migrated file reopens as a current one
        assert st.poses()["r1"].odom == (1.0, 2.0, 3.0)


def test_failed_migration_leaves_the_schema_1_file_untouched(tmp_path: Path) -> None:
    _write_v1(tmp_path / DB_NAME)
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.execute("ALTER TABLE poses ADD COLUMN odom_x REAL")  # a half-done foreign change
    db.commit()
    db.close()
    with pytest.raises(StateError, match="migration from schema 1 to 2 failed"):
        StateStore(tmp_path)
    db = sqlite3.connect(tmp_path / DB_NAME)
    assert db.execute("PRAGMA user_version").fetchone()[0] == 1
    assert "odom_y" not in [r[1] for r in db.execute("PRAGMA table_info(poses)")]
    db.close()


def test_current_schema_without_odom_columns_raises(tmp_path: Path) -> None:
    _write_v1(tmp_path / DB_NAME)
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
    db.commit()
    db.close()
    with pytest.raises(StateError, match="poses lacks columns"):
        StateStore(tmp_path)


def test_config_put_forgets_saved_pose(tmp_path: Path) -> None:
    with StateStore(tmp_path) as st:
        st.put_robot("r1", CFG)
        st.save_poses({"r1": SavedPose("m1", 1.0, 1.0, 0.0, 1, 1.0, "tracking")})
        st.put_robot("r1", {**CFG, "initial_pose": None})
        assert st.poses() == {}
        assert st.robots()["r1"]["initial_pose"] is None
        st.delete_robot("r1")
        assert st.robots() == {}


def test_non_finite_pose_not_saved(tmp_path: Path) -> None:
    with StateStore(tmp_path) as st:
        st.save_poses({"r1": SavedPose("m1", float("nan"), 0.0, 0.0, 1, 1.0, "lost")})
        assert st.poses() == {}


def test_garbage_file_raises_state_error(tmp_path: Path) -> None:
    (tmp_path / DB_NAME).write_bytes(b"this is definitely not an sqlite database" * 100)
    with pytest.raises(StateError, match="corrupt or not a shapeloc state database"):
        StateStore(tmp_path)
    # the lock was released: a valid directory can be opened by the same process afterwards
    (tmp_path / DB_NAME).unlink()
    StateStore(tmp_path).close()


def test_foreign_database_raises(tmp_path: Path) -> None:
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.execute("CREATE TABLE customers (id INTEGER)")
    db.commit()
    db.close()
    with pytest.raises(StateError, match="not a shapeloc state database"):
        StateStore(tmp_path)


def test_newer_schema_raises(tmp_path: Path) -> None:
    StateStore(tmp_path).close()
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.execute(f"PRAGMA user_version={SCHEMA_VERSION + 1}")
    db.commit()
    db.close()
    with pytest.raises(StateError, match="newer than the supported"):
        StateStore(tmp_path)


def test_missing_table_raises(tmp_path: Path) -> None:
    StateStore(tmp_path).close()
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.execute("DROP TABLE poses")
    db.commit()
    db.close()
    with pytest.raises(StateError, match="lacks tables"):
        StateStore(tmp_path)


def test_corrupt_row_raises(tmp_path: Path) -> None:
    with StateStore(tmp_path) as st:
        st.put_map("m1", MAP)
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.execute("UPDATE maps SET payload=? WHERE map_id='m1'", (b"\xc1\xc1\xc1",))
    db.commit()
    db.close()
    with StateStore(tmp_path) as st, pytest.raises(StateError, match="maps row 'm1'"):
        st.maps()
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.execute("UPDATE maps SET payload=? WHERE map_id='m1'", (msgpack.packb([1, 2]),))
    db.commit()
    db.close()
    with StateStore(tmp_path) as st, pytest.raises(StateError, match="not a map"):
        st.maps()


def test_second_store_on_same_dir_refused(tmp_path: Path) -> None:
    with StateStore(tmp_path), pytest.raises(StateError, match="in use by another"):
        StateStore(tmp_path)
    StateStore(tmp_path).close()  # released after close


def test_state_dir_is_a_file(tmp_path: Path) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(StateError, match="state directory"):
        StateStore(f)


def test_closed_store_raises(tmp_path: Path) -> None:
    st = StateStore(tmp_path)
    st.close()
    st.close()
    with pytest.raises(StateError, match="closed"):
        st.maps()


def test_empty_file_is_an_error_not_a_new_database(tmp_path: Path) -> None:
    """SQLite takes a 0-byte file for a new, empty database: a truncated state file must not
    silently become an empty map set."""
    (tmp_path / DB_NAME).write_bytes(b"")
    with pytest.raises(StateError, match=r"shapeloc\.sqlite3 is empty"):
        StateStore(tmp_path)


def test_missing_file_with_leftover_wal_is_an_error(tmp_path: Path) -> None:
    (tmp_path / (DB_NAME + "-wal")).write_bytes(b"\x00" * 64)
    with pytest.raises(StateError, match="write-ahead log"):
        StateStore(tmp_path)


@pytest.mark.parametrize("cut", ["100", "page", "half", "minus_page"])
def test_truncated_file_raises_and_reset_moves_it_aside(tmp_path: Path, cut: str) -> None:
    src = tmp_path / "src"
    with StateStore(src) as s:
        for i in range(5):
            s.put_map(f"m{i}", {"map_id": f"m{i}", "polylines": [[[0, 0], [i, 1]]] * 200})
    data = (src / DB_NAME).read_bytes()
    assert len(data) >= 4 * 4096
    n = {"100": 100, "page": 4096, "half": len(data) // 2, "minus_page": len(data) - 4096}[cut]
    d = tmp_path / "cut"
    d.mkdir()
    (d / DB_NAME).write_bytes(data[:n])
    with pytest.raises(StateError, match=str(d / DB_NAME)):
        StateStore(d)
    with StateStore(d, reset=True) as s:
        assert s.maps() == {}
        [(moved, why)] = s.quarantined
        assert moved.name.startswith(DB_NAME + ".bad-") and moved.read_bytes() == data[:n]
        assert "shapeloc.sqlite3" in why


def test_reset_never_touches_a_newer_schema_or_a_locked_dir(tmp_path: Path) -> None:
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.execute("PRAGMA user_version=99")
    db.close()
    with pytest.raises(StateError, match="newer"):
        StateStore(tmp_path, reset=True)
    assert not list(tmp_path.glob("*.bad-*"))
    other = tmp_path / "other"
    with StateStore(other), pytest.raises(StateError, match="in use"):
        StateStore(other, reset=True)
    assert not list(other.glob("*.bad-*"))


def test_quarantine_keeps_the_lock_and_starts_empty(tmp_path: Path) -> None:
    with StateStore(tmp_path) as s:
        s.put_map("m", {"map_id": "m"})
        moved = s.quarantine("stored map 'm' is invalid")
        assert s.maps() == {} and moved.exists()
        with pytest.raises(StateError, match="in use"):
            StateStore(tmp_path)
        s.put_map("n", {"map_id": "n"})
    with StateStore(tmp_path) as s2:
        assert set(s2.maps()) == {"n"}
