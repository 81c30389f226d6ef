"""Operational data store (ODS): robot telemetry in one SQLite file.

Thesis 3.3.1/3.3.6: the cloud keeps every robot's sensor data (position,
battery, health) in an operational data store.  Ours is one SQLite file in WAL
mode (default ``<run dir>/ods.sqlite``) with

* a ``telemetry`` table, ``UNIQUE (robot, seq)``: a message is stored with
  ``INSERT OR IGNORE``, so replays and relays through the leader are stored
  exactly once, and every ignored insert is counted as a duplicate;
* a ``robot_stats`` table: per robot the duplicate count and the highest
  contiguous ``seq`` stored (the acknowledgement a robot's queue can rely on);
* schema versioning through ``PRAGMA user_version`` and a list of migrations.

Concurrency: every write goes through one writer thread (one connection,
``busy_timeout``); readers open their own connections (WAL lets them read
while the writer writes).  Any thread may call :meth:`OperationalDataStore.insert`.
"""

from __future__ import annotations

import concurrent.futures
import csv
import json
import logging
import os
import queue
import sqlite3
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

from scmr_mesh.data.errors import StoreError
from scmr_mesh.data.record import TIERS, TelemetryRecord

log = logging.getLogger(__name__)

#: Default file name inside a run directory.
DEFAULT_FILENAME = "ods.sqlite"
#: How long a connection waits for a lock before giving up (ms).
BUSY_TIMEOUT_MS = 5000

#: Schema migrations; ``MIGRATIONS[i]`` takes the schema from version i to i + 1.
MIGRATIONS: tuple[tuple[str, ...], ...] = (
    (
        """CREATE TABLE telemetry (
            id INTEGER PRIMARY KEY,
            robot TEXT NOT NULL,
            seq INTEGER NOT NULL,
            t_unix_ns INTEGER NOT NULL,
            x REAL, y REAL, theta REAL,
            battery REAL,
            health TEXT NOT NULL,
            results TEXT NOT NULL,
            received_from TEXT NOT NULL,
            stored_unix_ns INTEGER NOT NULL,
            UNIQUE (robot, seq)
        )""",
        """CREATE TABLE robot_stats (
            robot TEXT PRIMARY KEY,
            duplicates INTEGER NOT NULL DEFAULT 0,
            contiguous INTEGER NOT NULL DEFAULT 0
        )""",
    ),
    (
        "CREATE INDEX telemetry_time ON telemetry (t_unix_ns)",
        "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
        "INSERT INTO meta (key, value) VALUES ('created_unix_ns', CAST(strftime('%s','now') AS INTEGER) * 1000000000)",
    ),
    (
        # a repeated (robot, seq) whose content differs: a robot reusing seqs (fresh queue)
        "ALTER TABLE robot_stats ADD COLUMN conflicts INTEGER NOT NULL DEFAULT 0",
    ),
)
SCHEMA_VERSION = len(MIGRATIONS)



def default_db_path() -> Path:
    """``$SCMR_ODS``, else ``$SCMR_RUN_DIR/ods.sqlite``, else ``runs/ods.sqlite``."""
    if os.environ.get("SCMR_ODS"):
        return Path(os.environ["SCMR_ODS"])
    return Path(os.environ.get("SCMR_RUN_DIR", "runs")) / DEFAULT_FILENAME


COLUMNS = (
    "robot", "seq", "t_unix_ns", "x", "y", "theta", "battery", "health", "results",
    "received_from", "stored_unix_ns",
)


@dataclass(frozen=True)
class InsertResult:
    """What one :meth:`OperationalDataStore.insert` call did.

    ``stored`` and ``duplicates`` are ``(robot, seq)`` pairs; ``contiguous``
    maps each robot touched to its highest contiguous stored ``seq`` after the call.
    ``conflicts`` are the duplicates whose content (``t_unix_ns``) differs from
    the stored row: a robot that reused seqs (it started over with a fresh
    queue).  They are not stored; they are counted and logged.
    """

    stored: tuple[tuple[str, int], ...]
    duplicates: tuple[tuple[str, int], ...]
    contiguous: dict[str, int] = field(default_factory=dict)
    conflicts: tuple[tuple[str, int], ...] = ()


def _row_to_dict(row: Sequence[Any]) -> dict[str, Any]:
    d = dict(zip(COLUMNS, row))
    d["pose"] = None if d["x"] is None else [d["x"], d["y"], d["theta"]]
    for k in ("x", "y", "theta"):
        del d[k]
    d["results"] = json.loads(d["results"])
    return d


def _connect(path: Path, *, readonly: bool) -> sqlite3.Connection:
    uri = f"file:{path}?mode={'ro' if readonly else 'rwc'}"
    con = sqlite3.connect(uri, uri=True, timeout=BUSY_TIMEOUT_MS / 1000, check_same_thread=False,
                          isolation_level=None)
    con.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
    return con


class OperationalDataStore:
    """The operational data store on one SQLite file.

    Parameters
    ----------
    path : str or Path
        The database file (created with its parent folder unless ``readonly``).
    readonly : bool
        Open an existing store for queries only (no writer thread, no migration).

    Raises
    ------
    StoreError
        The file is missing (read-only), not a SQLite database, not an ODS or
        written by a newer scmr.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from scmr_mesh.data.record import make_record
    >>> with OperationalDataStore(pathlib.Path(tempfile.mkdtemp()) / "ods.sqlite") as ods:
    ...     r = ods.insert([make_record("r1", 1), make_record("r1", 1)], received_from="cloud")
    ...     (len(r.stored), len(r.duplicates), ods.counts()["r1"]["stored"])
    (1, 1, 1)
    """

    def __init__(self, path: str | Path, *, readonly: bool = False) -> None:
        self.path = Path(path)
        self.readonly = readonly
        self._closed = False
        self._queue: queue.Queue = queue.Queue()
        self._writer: threading.Thread | None = None
        if readonly:
            if not self.path.is_file():
                raise StoreError(
                    f"no operational data store at {str(self.path)!r}; pass --db the ods.sqlite "
                    "file a cloud peer wrote (default <run dir>/ods.sqlite)"
                )
            self._check_readable()
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            ready: concurrent.futures.Future = concurrent.futures.Future()
            self._writer = threading.Thread(target=self._write_loop, args=(ready,),
                                            name="ods-writer", daemon=True)
            self._writer.start()
            ready.result()  # re-raises a StoreError from the writer's open/migrate

    # ------------------------------------------------------------------ setup
    def _check_readable(self) -> None:
        try:
            con = _connect(self.path, readonly=True)
            try:
                version = con.execute("PRAGMA user_version").fetchone()[0]
                con.execute("SELECT count(*) FROM sqlite_master").fetchone()
            finally:
                con.close()
        except sqlite3.DatabaseError as exc:
            raise StoreError(
                f"{str(self.path)!r} is not a readable SQLite database ({exc}); "
                "pass --db an ods.sqlite written by a cloud peer"
            ) from None
        self._check_version(version)

    def _check_version(self, version: int) -> None:
        if version > SCHEMA_VERSION:
            raise StoreError(
                f"{str(self.path)!r} has ODS schema version {version}, newer than this "
                f"scmr's {SCHEMA_VERSION}; upgrade scmr-mesh to read it"
            )
        if self.readonly and version == 0:
            raise StoreError(
                f"{str(self.path)!r} is a SQLite file but not an operational data store "
                "(schema version 0); pass --db an ods.sqlite written by a cloud peer"
            )

    def _open_writer(self) -> sqlite3.Connection:
        try:
            con = _connect(self.path, readonly=False)
            mode = con.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if mode.lower() != "wal":
                log.warning("ODS %s: journal mode is %s, not WAL", self.path, mode)
            con.execute("PRAGMA synchronous = FULL")  # an ack means the row survives power loss
            while True:
                # each step re-reads the version inside its write lock: another process
                # (a second cloud node on the same file) may have migrated meanwhile
                con.execute("BEGIN IMMEDIATE")
                version = con.execute("PRAGMA user_version").fetchone()[0]
                if version >= SCHEMA_VERSION:
                    con.execute("COMMIT")
                    self._check_version(version)
                    break
                for stmt in MIGRATIONS[version]:
                    con.execute(stmt)
                con.execute(f"PRAGMA user_version = {version + 1}")
                con.execute("COMMIT")
                log.info("ODS %s: migrated schema to version %d", self.path, version + 1)
            return con
        except sqlite3.DatabaseError as exc:
            raise StoreError(
                f"cannot open {str(self.path)!r} as an operational data store ({exc}); "
                "move the file away or choose another --db path"
            ) from None

    # ------------------------------------------------------------------ writer
    def _write_loop(self, ready: concurrent.futures.Future) -> None:
        try:
            con = self._open_writer()
        except BaseException as exc:  # handed to the constructor
            ready.set_exception(exc)
            return
        ready.set_result(None)
        try:
            while True:
                item = self._queue.get()
                if item is None:
                    break
                fn, args, fut = item
                if not fut.set_running_or_notify_cancel():
                    continue
                try:
                    fut.set_result(fn(con, *args))
                except BaseException as exc:
                    try:
                        con.execute("ROLLBACK")
                    except sqlite3.Error:
                        pass
                    fut.set_exception(exc)
        finally:
            con.close()

    def _submit(self, fn, *args) -> concurrent.futures.Future:
        if self.readonly:
            raise StoreError(f"{str(self.path)!r} was opened read-only; it cannot be written")
        if self._closed:
            raise StoreError(f"the operational data store {str(self.path)!r} is closed")
        fut: concurrent.futures.Future = concurrent.futures.Future()
        self._queue.put((fn, args, fut))
        return fut

    def insert_async(self, records: Iterable[TelemetryRecord], *, received_from: str) -> concurrent.futures.Future:
        """:meth:`insert` without waiting: a Future of the :class:`InsertResult`.

        Done callbacks run on the writer thread once the transaction has
        committed (or failed), so keep them short (e.g. send an ack).
        """
        if received_from not in TIERS:
            raise StoreError(f"received_from must be one of {TIERS}, got {received_from!r}")
        return self._submit(self._insert, list(records), received_from)

    def insert(self, records: Iterable[TelemetryRecord], *, received_from: str) -> InsertResult:
        """Store records exactly once per ``(robot, seq)``; count the rest as duplicates.

        Parameters
        ----------
        records : iterable of TelemetryRecord
        received_from : {"cloud", "leader", "local"}
            The tier the records reached the store through.

        Returns
        -------
        InsertResult
            Which pairs were new, which were duplicates, and the contiguous
            ``seq`` per robot after the insert (the acknowledgement).
        """
        return self.insert_async(records, received_from=received_from).result()

    @staticmethod
    def _insert(con: sqlite3.Connection, records: list[TelemetryRecord], received_from: str) -> InsertResult:
        now = time.time_ns()
        stored: list[tuple[str, int]] = []
        dups: list[tuple[str, int]] = []
        conflicts: list[tuple[str, int]] = []
        con.execute("BEGIN IMMEDIATE")
        for r in records:
            pose = r.pose if r.pose is not None else (None, None, None)
            cur = con.execute(
                "INSERT OR IGNORE INTO telemetry (robot, seq, t_unix_ns, x, y, theta, battery, "
                "health, results, received_from, stored_unix_ns) VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                (r.robot, r.seq, r.t_unix_ns, *pose, r.battery, r.health,
                 json.dumps(r.results, sort_keys=True, default=str), received_from, now),
            )
            con.execute("INSERT OR IGNORE INTO robot_stats (robot) VALUES (?)", (r.robot,))
            if cur.rowcount == 1:
                stored.append((r.robot, r.seq))
            else:
                dups.append((r.robot, r.seq))
                con.execute("UPDATE robot_stats SET duplicates = duplicates + 1 WHERE robot = ?", (r.robot,))
                (t_old,) = con.execute("SELECT t_unix_ns FROM telemetry WHERE robot = ? AND seq = ?",
                                       (r.robot, r.seq)).fetchone()
                if t_old != r.t_unix_ns:
                    conflicts.append((r.robot, r.seq))
                    con.execute("UPDATE robot_stats SET conflicts = conflicts + 1 WHERE robot = ?", (r.robot,))
        contiguous: dict[str, int] = {}
        for robot in sorted({r.robot for r in records}):
            (c,) = con.execute("SELECT contiguous FROM robot_stats WHERE robot = ?", (robot,)).fetchone()
            while True:
                seqs = [s for (s,) in con.execute(
                    "SELECT seq FROM telemetry WHERE robot = ? AND seq > ? ORDER BY seq LIMIT 512",
                    (robot, c))]
                advanced = False
                for s in seqs:
                    if s != c + 1:
                        break
                    c, advanced = s, True
                if not advanced or len(seqs) < 512 or seqs[-1] != c:
                    break
            con.execute("UPDATE robot_stats SET contiguous = ? WHERE robot = ?", (c, robot))
            contiguous[robot] = c
        con.execute("COMMIT")
        if conflicts:
            log.error("ODS: %d record(s) reuse a stored (robot, seq) with different content, e.g. %s; "
                      "not stored (a robot started over with a fresh telemetry queue: give it its old "
                      "queue folder)", len(conflicts), conflicts[0])
        return InsertResult(tuple(stored), tuple(dups), contiguous, tuple(conflicts))

    # ------------------------------------------------------------------ reads
    def _read(self, sql: str, params: Sequence[Any] = ()) -> list[tuple]:
        if self._closed:
            raise StoreError(f"the operational data store {str(self.path)!r} is closed")
        try:
            con = _connect(self.path, readonly=True)
            try:
                return con.execute(sql, params).fetchall()
            finally:
                con.close()
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"cannot read the operational data store {str(self.path)!r}: {exc}") from None

    def counts(self) -> dict[str, dict[str, int]]:
        """Per robot: ``stored``, ``duplicates``, ``conflicts``, ``min_seq``, ``max_seq``, ``contiguous``."""
        rows = self._read(
            "SELECT s.robot, count(t.seq), s.duplicates, s.conflicts, min(t.seq), max(t.seq), s.contiguous "
            "FROM robot_stats s LEFT JOIN telemetry t ON t.robot = s.robot "
            "GROUP BY s.robot ORDER BY s.robot"
        )
        return {
            robot: {"stored": n, "duplicates": d, "conflicts": k, "min_seq": lo or 0, "max_seq": hi or 0,
                    "contiguous": c}
            for robot, n, d, k, lo, hi, c in rows
        }

    def contiguous(self, robot: str) -> int:
        """Highest ``seq`` such that ``1..seq`` of ``robot`` are all stored (0 if none)."""
        rows = self._read("SELECT contiguous FROM robot_stats WHERE robot = ?", (robot,))
        return rows[0][0] if rows else 0

    def seqs(self, robot: str) -> list[int]:
        """Every stored ``seq`` of ``robot``, ascending."""
        return [s for (s,) in self._read("SELECT seq FROM telemetry WHERE robot = ? ORDER BY seq", (robot,))]

    def latest(self) -> dict[str, dict[str, Any]]:
        """The record with the highest ``seq`` of each robot."""
        rows = self._read(
            f"SELECT {', '.join('t.' + c for c in COLUMNS)} FROM telemetry t JOIN "
            "(SELECT robot, max(seq) AS m FROM telemetry GROUP BY robot) l "
            "ON t.robot = l.robot AND t.seq = l.m ORDER BY t.robot"
        )
        return {r[0]: _row_to_dict(r) for r in rows}

    def range(self, *, since_ns: int | None = None, until_ns: int | None = None,
              robot: str | None = None) -> list[dict[str, Any]]:
        """Records with ``since_ns <= t_unix_ns < until_ns``, by time then robot and seq."""
        where, params = [], []
        if since_ns is not None:
            where.append("t_unix_ns >= ?")
            params.append(int(since_ns))
        if until_ns is not None:
            where.append("t_unix_ns < ?")
            params.append(int(until_ns))
        if robot is not None:
            where.append("robot = ?")
            params.append(robot)
        sql = f"SELECT {', '.join(COLUMNS)} FROM telemetry"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY t_unix_ns, robot, seq"
        return [_row_to_dict(r) for r in self._read(sql, params)]

    def export(self, out: str | Path, *, fmt: str = "csv", since_ns: int | None = None,
               until_ns: int | None = None) -> int:
        """Write the records (optionally a time range) to CSV or JSON; return the row count."""
        if fmt not in ("csv", "json"):
            raise StoreError(f"export format must be 'csv' or 'json', got {fmt!r}")
        rows = self.range(since_ns=since_ns, until_ns=until_ns)
        out = Path(out)
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            with out.open("w", newline="") as fh:
                if fmt == "json":
                    json.dump(rows, fh, indent=1)
                    fh.write("\n")
                else:
                    w = csv.writer(fh)
                    header = ["robot", "seq", "t_unix_ns", "x", "y", "theta", "battery", "health",
                              "results", "received_from", "stored_unix_ns"]
                    w.writerow(header)
                    for r in rows:
                        pose = r["pose"] or ["", "", ""]
                        w.writerow([r["robot"], r["seq"], r["t_unix_ns"], *pose,
                                    "" if r["battery"] is None else r["battery"], r["health"],
                                    json.dumps(r["results"], sort_keys=True), r["received_from"],
                                    r["stored_unix_ns"]])
        except OSError as exc:
            raise StoreError(f"cannot write the export file {str(out)!r}: {exc}") from None
        return len(rows)

    def schema_version(self) -> int:
        """The ``PRAGMA user_version`` of the file."""
        return self._read("PRAGMA user_version")[0][0]

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Finish pending writes and stop the writer thread (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._writer is not None:
            self._queue.put(None)
            self._writer.join()

    def __enter__(self) -> "OperationalDataStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["DEFAULT_FILENAME", "SCHEMA_VERSION", "InsertResult", "OperationalDataStore", "default_db_path"]
