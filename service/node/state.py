"""Persistent state of the localizer service: one SQLite database (WAL) in the state directory.

Layout (``<state_dir>/shapeloc.sqlite3``, schema version in ``PRAGMA user_version``):

* ``maps(map_id PRIMARY KEY, payload BLOB, updated REAL)``: the validated wire map (msgpack).
* ``robots(robot_id PRIMARY KEY, payload BLOB, updated REAL)``: the validated wire config.
* ``poses(robot_id PRIMARY KEY, map_id, x, y, theta, seq, stamp, status, updated REAL,
  odom_x, odom_y, odom_theta)``: the last estimate per robot in the map frame (metres,
  radians), saved periodically and on shutdown, with the odometry pose of the scan that
  produced it (odometry frame; all three ``NULL`` if that scan carried none), so a restarted
  localiser measures the next scan's odometry increment from it.

Schema versions: 1 had no ``odom_*`` columns; 2 adds them (nullable). A version-1 file is
migrated in place when opened (one transaction; its saved poses get ``NULL`` odometry).

Every write is committed before the call returns, so a caller may log "stored" afterwards. A
``<state_dir>/shapeloc.lock`` file held with ``flock`` keeps two services off one directory.
Anything unreadable (including an empty, i.e. truncated, database file, which SQLite alone
would take for a new one) raises :class:`~service.errors.StateError`. The store never resets
itself: only ``reset=True`` (``--reset-state``) moves a bad file aside, to
``shapeloc.sqlite3.bad-<UTC time>``, and starts an empty one (listed in ``quarantined``).
"""

from __future__ import annotations

import fcntl
import math
import os
import sqlite3
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from service.errors import StateError

SCHEMA_VERSION = 2
DB_NAME = "shapeloc.sqlite3"
LOCK_NAME = "shapeloc.lock"

_TABLES = {
    "maps": "CREATE TABLE maps (map_id TEXT PRIMARY KEY, payload BLOB NOT NULL, "
    "updated REAL NOT NULL)",
    "robots": "CREATE TABLE robots (robot_id TEXT PRIMARY KEY, payload BLOB NOT NULL, "
    "updated REAL NOT NULL)",
    "poses": "CREATE TABLE poses (robot_id TEXT PRIMARY KEY, map_id TEXT NOT NULL, "
    "x REAL NOT NULL, y REAL NOT NULL, theta REAL NOT NULL, seq INTEGER NOT NULL, "
    "stamp REAL NOT NULL, status TEXT NOT NULL, updated REAL NOT NULL, "
    "odom_x REAL, odom_y REAL, odom_theta REAL)",
}

#: Columns each schema version adds to ``poses`` (applied in order by :meth:`StateStore._open`).
_MIGRATIONS: dict[int, list[str]] = {
    2: [
        "ALTER TABLE poses ADD COLUMN odom_x REAL",
        "ALTER TABLE poses ADD COLUMN odom_y REAL",
        "ALTER TABLE poses ADD COLUMN odom_theta REAL",
    ],
}
_POSE_COLUMNS = (
    "robot_id, map_id, x, y, theta, seq, stamp, status, updated, odom_x, odom_y, odom_theta"
)


@dataclass(frozen=True)
class SavedPose:
    """Last estimate of one robot: ``(x, y, theta)`` in the map frame of ``map_id``
    (metres, metres, radians); ``odom``: the odometry pose ``(x, y, theta)`` (odometry frame)
    of the scan that produced it, ``None`` if that scan carried none."""

    map_id: str
    x: float
    y: float
    theta: float
    seq: int
    stamp: float
    status: str
    odom: tuple[float, float, float] | None = None

    @property
    def pose(self) -> tuple[float, float, float]:
        """``(x, y, theta)`` metres, metres, radians."""
        return (self.x, self.y, self.theta)


class StateStore:
    """Maps, robot configurations and last poses under ``state_dir`` (thread-safe).

    Raises :class:`StateError` if the directory cannot be created or locked, or the database
    is corrupt, foreign, or from a newer schema version.
    """

    def __init__(self, state_dir: str | os.PathLike[str], reset: bool = False) -> None:
        self.state_dir = Path(state_dir)
        self.path = self.state_dir / DB_NAME
        self._lock = threading.Lock()
        #: ``(moved_to, reason)`` of every state file moved aside by :meth:`quarantine`.
        self.quarantined: list[tuple[Path, str]] = []
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise StateError(f"cannot create state directory {self.state_dir}: {e}") from e
        if not self.state_dir.is_dir():
            raise StateError(f"state directory {self.state_dir} is not a directory")
        self._lock_fd = self._acquire_dir_lock()  # a held lock is never a reason to reset
        self._keep_file = False  # set when the file is fine but not ours to reset (newer schema)
        try:
            if self.path.exists() and not os.access(self.path, os.R_OK | os.W_OK):
                raise StateError(f"state file {self.path} is not readable and writable")
            try:
                self._db = self._open()
            except StateError as e:
                if not reset or self._keep_file:
                    raise
                self._db = None  # type: ignore[assignment]
                self._move_aside(str(e))
                self._db = self._open()
        except BaseException:
            self._release_dir_lock()
            raise

    # ----------------------------------------------------------------- opening
    def _acquire_dir_lock(self) -> int:
        lock_path = self.state_dir / LOCK_NAME
        try:
            fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise StateError(f"cannot open lock file {lock_path}: {e}") from e
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            raise StateError(
                f"state directory {self.state_dir} is in use by another shapeloc service "
                f"(lock {lock_path} is held)"
            ) from e
        return fd

    def _release_dir_lock(self) -> None:
        if self._lock_fd >= 0:
            fcntl.flock(self._lock_fd, fcntl.LOCK_UN)
            os.close(self._lock_fd)
            self._lock_fd = -1

    def _open(self) -> sqlite3.Connection:
        wal = self.path.with_name(self.path.name + "-wal")
        if self.path.exists() and self.path.stat().st_size == 0:
            # SQLite would take an empty file for a new database and serve an empty state.
            raise StateError(f"state file {self.path} is empty (0 bytes): truncated?")
        if not self.path.exists() and wal.exists():
            raise StateError(
                f"state file {self.path} is missing but its write-ahead log {wal} exists"
            )
        try:
            db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        except sqlite3.Error as e:
            raise StateError(f"cannot open state file {self.path}: {e}") from e
        try:
            version = db.execute("PRAGMA user_version").fetchone()[0]
            check = db.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise StateError(f"state file {self.path} is corrupt (quick_check: {check})")
            tables = {
                r[0]
                for r in db.execute(
                    "SELECT name FROM sqlite_master WHERE type='table' AND name NOT LIKE 'sqlite_%'"
                )
            }
            if version == 0:
                if tables:
                    raise StateError(
                        f"state file {self.path} is not a shapeloc state database "
                        f"(unversioned, tables {sorted(tables)})"
                    )
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("BEGIN")
                for ddl in _TABLES.values():
                    db.execute(ddl)
                db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
                db.execute("COMMIT")
            elif version > SCHEMA_VERSION:
                self._keep_file = True
                raise StateError(
                    f"state file {self.path} has schema version {version}, newer than the "
                    f"supported {SCHEMA_VERSION}; upgrade shapeloc"
                )
            else:
                missing = set(_TABLES) - tables
                if missing:
                    raise StateError(
                        f"state file {self.path} (schema {version}) lacks tables {sorted(missing)}"
                    )
                db.execute("PRAGMA journal_mode=WAL")
                if version < SCHEMA_VERSION:
                    self._migrate(db, version)
                self._check_pose_columns(db)
            db.execute("PRAGMA synchronous=FULL")
        except sqlite3.DatabaseError as e:
            db.close()
            raise StateError(
                f"state file {self.path} is corrupt or not a shapeloc state database: {e}"
            ) from e
        except StateError:
            db.close()
            raise
        return db

    def _migrate(self, db: sqlite3.Connection, version: int) -> None:
        """Bring a file of schema ``version`` to :data:`SCHEMA_VERSION` in one transaction
        (nothing changes if any step fails)."""
        db.execute("BEGIN IMMEDIATE")
        try:
            for v in range(version + 1, SCHEMA_VERSION + 1):
                for sql in _MIGRATIONS.get(v, []):
                    db.execute(sql)
            db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            db.execute("COMMIT")
        except sqlite3.Error as e:
            db.execute("ROLLBACK")
            raise StateError(
                f"state file {self.path}: migration from schema {version} to "
                f"{SCHEMA_VERSION} failed: {e}"
            ) from e

    def _check_pose_columns(self, db: sqlite3.Connection) -> None:
        have = {r[1] for r in db.execute("PRAGMA table_info(poses)")}
        missing = [c for c in _POSE_COLUMNS.split(", ") if c not in have]
        if missing:
            raise StateError(
                f"state file {self.path} (schema {SCHEMA_VERSION}): table poses lacks "
                f"columns {missing}"
            )

    def _side_files(self) -> list[Path]:
        return [self.path.with_name(self.path.name + sfx) for sfx in ("", "-wal", "-shm")]

    def _move_aside(self, reason: str) -> Path:
        """Rename the database (and its -wal/-shm files) to ``<name>.bad-<UTC time>[-wal]``."""
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        target = self.path.with_name(f"{self.path.name}.bad-{stamp}")
        n = 1
        while target.exists():
            n += 1
            target = self.path.with_name(f"{self.path.name}.bad-{stamp}-{n}")
        for src in self._side_files():
            if src.exists():
                dst = target.with_name(target.name + src.name[len(self.path.name) :])
                try:
                    src.rename(dst)
                except OSError as e:
                    raise StateError(f"cannot move bad state file {src} aside: {e}") from e
        self.quarantined.append((target, reason))
        return target

    def quarantine(self, reason: str) -> Path:
        """Move the current database aside (``reason`` is why) and start an empty one in its
        place; the directory lock stays held. Returns where the old file went. Used by
        ``--reset-state`` when the stored content itself is invalid."""
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None  # type: ignore[assignment]
            target = self._move_aside(reason)
            self._db = self._open()
        return target

    def close(self) -> None:
        """Close the database and release the directory lock (idempotent)."""
        with self._lock:
            try:
                if self._db is not None:
                    self._db.close()
            finally:
                self._db = None  # type: ignore[assignment]
                self._release_dir_lock()

    def __enter__(self) -> StateStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- helpers
    def _write(self, sql_params: list[tuple[str, tuple[Any, ...]]]) -> None:
        with self._lock:
            if self._db is None:
                raise StateError("state store is closed")
            try:
                self._db.execute("BEGIN IMMEDIATE")
                for sql, params in sql_params:
                    self._db.execute(sql, params)
                self._db.execute("COMMIT")
            except sqlite3.Error as e:
                if self._db.in_transaction:
                    self._db.execute("ROLLBACK")
                raise StateError(f"cannot write state file {self.path}: {e}") from e

    def _read(self, sql: str) -> list[tuple[Any, ...]]:
        with self._lock:
            if self._db is None:
                raise StateError("state store is closed")
            try:
                return list(self._db.execute(sql))
            except sqlite3.Error as e:
                raise StateError(f"cannot read state file {self.path}: {e}") from e

    def _unpack(self, table: str, key: str, blob: Any) -> dict[str, Any]:
        try:
            obj = msgpack.unpackb(bytes(blob), raw=False, strict_map_key=True)
        except Exception as e:
            raise StateError(f"state file {self.path}: {table} row {key!r} is corrupt: {e}") from e
        if not isinstance(obj, dict):
            raise StateError(f"state file {self.path}: {table} row {key!r} is not a map")
        return obj

    # ----------------------------------------------------------------- maps
    def put_map(self, map_id: str, wire: Mapping[str, Any]) -> None:
        """Store (replace) a map given as its wire dict; committed on return."""
        blob = msgpack.packb(dict(wire), use_bin_type=True)
        self._write(
            [
                (
                    "INSERT OR REPLACE INTO maps(map_id, payload, updated) VALUES (?, ?, ?)",
                    (map_id, blob, time.time()),
                )
            ]
        )

    def delete_map(self, map_id: str) -> bool:
        """Remove a map; robots configured on it are kept. Returns whether it existed."""
        existed = bool(self._read_one("SELECT 1 FROM maps WHERE map_id=?", (map_id,)))
        self._write([("DELETE FROM maps WHERE map_id=?", (map_id,))])
        return existed

    def maps(self) -> dict[str, dict[str, Any]]:
        """All stored maps as wire dicts, by map id."""
        rows = self._read("SELECT map_id, payload FROM maps ORDER BY map_id")
        return {k: self._unpack("maps", k, b) for k, b in rows}

    def _read_one(self, sql: str, params: tuple[Any, ...]) -> list[tuple[Any, ...]]:
        with self._lock:
            if self._db is None:
                raise StateError("state store is closed")
            try:
                return list(self._db.execute(sql, params))
            except sqlite3.Error as e:
                raise StateError(f"cannot read state file {self.path}: {e}") from e

    # ----------------------------------------------------------------- robots
    def put_robot(self, robot_id: str, config: Mapping[str, Any]) -> None:
        """Store (replace) a robot's wire config and forget its saved pose (a config put
        resets the robot); committed on return."""
        blob = msgpack.packb(dict(config), use_bin_type=True)
        self._write(
            [
                (
                    "INSERT OR REPLACE INTO robots(robot_id, payload, updated) VALUES (?, ?, ?)",
                    (robot_id, blob, time.time()),
                ),
                ("DELETE FROM poses WHERE robot_id=?", (robot_id,)),
            ]
        )

    def delete_robot(self, robot_id: str) -> None:
        """Forget a robot's configuration and saved pose; committed on return."""
        self._write(
            [
                ("DELETE FROM robots WHERE robot_id=?", (robot_id,)),
                ("DELETE FROM poses WHERE robot_id=?", (robot_id,)),
            ]
        )

    def robots(self) -> dict[str, dict[str, Any]]:
        """All stored robot configurations as wire dicts, by robot id."""
        rows = self._read("SELECT robot_id, payload FROM robots ORDER BY robot_id")
        return {k: self._unpack("robots", k, b) for k, b in rows}

    # ----------------------------------------------------------------- poses
    def save_poses(self, poses: Mapping[str, SavedPose]) -> None:
        """Upsert the last pose of each given robot in one transaction."""
        now = time.time()
        ops = []
        for rid, p in poses.items():
            if not all(math.isfinite(v) for v in (p.x, p.y, p.theta)):
                continue
            odom: tuple[float | None, ...] = (None, None, None)
            if p.odom is not None and all(math.isfinite(float(v)) for v in p.odom):
                odom = tuple(float(v) for v in p.odom)
            ops.append(
                (
                    f"INSERT OR REPLACE INTO poses({_POSE_COLUMNS}) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (rid, p.map_id, p.x, p.y, p.theta, int(p.seq), p.stamp, p.status, now, *odom),
                )
            )
        if ops:
            self._write(ops)

    def poses(self) -> dict[str, SavedPose]:
        """Last saved pose per robot (``odom`` is ``None`` unless all three columns hold
        finite numbers)."""
        rows = self._read(
            "SELECT robot_id, map_id, x, y, theta, seq, stamp, status, odom_x, odom_y, "
            "odom_theta FROM poses ORDER BY robot_id"
        )
        out: dict[str, SavedPose] = {}
        for rid, map_id, x, y, th, seq, stamp, status, ox, oy, oth in rows:
            try:
                odom = None
                if None not in (ox, oy, oth):
                    odom = (float(ox), float(oy), float(oth))
                    if not all(math.isfinite(v) for v in odom):
                        odom = None
                out[rid] = SavedPose(
                    str(map_id),
                    float(x),
                    float(y),
                    float(th),
                    int(seq),
                    float(stamp),
                    str(status),
                    odom,
                )
            except (TypeError, ValueError) as e:
                raise StateError(f"state file {self.path}: poses row {rid!r} is corrupt") from e
        return out
