"""The operational data store on PostgreSQL: what several cloud nodes share.

Same schema (:func:`scmr_mesh.data.ods.migrations` rendered for PostgreSQL),
same methods and the same exactly-once rule as the SQLite store: a telemetry
row is inserted with ``ON CONFLICT (robot, inc, seq) DO NOTHING`` against the
table's ``UNIQUE (robot, inc, seq)`` (``inc``: the incarnation of the robot's
telemetry queue), so the same batch stored through two cloud
nodes at once lands once and is counted once as duplicates.

Concurrency between nodes: each insert transaction first locks the
``robot_stats`` rows of its robots (``SELECT ... FOR UPDATE``, in robot order,
so two nodes never deadlock), which serialises the writes of one robot across
nodes and keeps the duplicate, conflict and contiguous counts exact.
Migrations run under a transaction-scoped advisory lock, so cloud nodes
starting together migrate once.

An unreachable server: opening a writable store fails at once with a
:class:`~scmr_mesh.data.errors.StoreError` naming the URL and the fix.  Once
open, an insert while the server is gone fails (the cloud then answers the
robot with an error and the robot keeps the records queued); the writer
reconnects at the next insert (at most one attempt per
:data:`RECONNECT_PERIOD_S`), and logs one line when the server goes and one
when it is back.
"""

from __future__ import annotations

import collections
import concurrent.futures
import json
import logging
import re
import threading
import time
from typing import Any, Sequence

from scmr_mesh.data.errors import StoreError
from scmr_mesh.data.ods import SCHEMA_VERSION, InsertResult, OperationalDataStore, current_incarnation, log_conflicts, migrations, same_content, serve_writes
from scmr_mesh.data.record import TelemetryRecord

log = logging.getLogger(__name__)

#: Seconds a connection attempt may take.
CONNECT_TIMEOUT_S = 3
#: At most one reconnection attempt per this many seconds while the server is gone.
RECONNECT_PERIOD_S = 0.5
#: Advisory lock key held while migrating ("scmr-ods").
_MIGRATE_LOCK = 0x73636D72_6F6473


def redact(dsn: str) -> str:
    """The URL without its password (``postgresql://u:***@host/db``)."""
    return re.sub(r"(://[^:/@?]*):[^@/?]*@", r"\1:***@", dsn)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


class PostgresStore(OperationalDataStore):
    """:class:`~scmr_mesh.data.ods.OperationalDataStore` on a PostgreSQL database.

    Parameters
    ----------
    path : str
        A ``postgresql://`` URL, e.g. ``postgresql://scmr@db.example:5432/scmr``
        or ``postgresql://scmr@/scmr?host=/run/postgresql`` (Unix socket).
    readonly : bool
        Queries only: the database must already hold an ODS.
    """

    backend = "postgresql"

    def __init__(self, path: str, *, readonly: bool = False) -> None:  # noqa: D107
        import queue

        self.path = str(path)
        self.readonly = readonly
        self._closed = False
        self._queue: queue.Queue = queue.Queue()
        self._writer: threading.Thread | None = None
        self._rlock = threading.Lock()
        self._rcon = None
        self._wcon = None
        self._down_since: float | None = None
        self._last_attempt = 0.0
        if readonly:
            self._check_readable()
        else:
            ready: concurrent.futures.Future = concurrent.futures.Future()
            self._writer = threading.Thread(target=self._write_loop, args=(ready,), name="ods-writer", daemon=True)
            self._writer.start()
            ready.result()

    @property
    def name(self) -> str:
        return redact(self.path)

    # ------------------------------------------------------------------ connections
    def _connect(self):
        import psycopg

        try:
            return psycopg.connect(self.path, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S,
                                   application_name="scmr-ods")
        except psycopg.Error as exc:
            raise StoreError(
                f"operational data store {self.name} unreachable ({_first_line(exc)}); start the "
                "PostgreSQL server or fix the URL (--ods / $SCMR_ODS)") from None

    def _version(self, con) -> int:
        row = con.execute("SELECT to_regclass('ods_version') IS NOT NULL").fetchone()
        if not row[0]:
            return 0
        row = con.execute("SELECT version FROM ods_version").fetchone()
        return int(row[0]) if row else 0

    def _check_readable(self) -> None:
        con = self._connect()
        try:
            version = self._version(con)
        finally:
            con.close()
        if version > SCHEMA_VERSION:
            raise StoreError(f"{self.name} has ODS schema version {version}, newer than this scmr's "
                             f"{SCHEMA_VERSION}; upgrade scmr-mesh to read it")
        if version == 0:
            raise StoreError(f"{self.name} holds no operational data store yet (no cloud node has "
                             "written to it); pass --db the database the cloud nodes use")

    def _migrate(self, con) -> None:
        steps = migrations("postgresql")
        with con.transaction():
            con.execute("SELECT pg_advisory_xact_lock(%s)", (_MIGRATE_LOCK,))
            con.execute("CREATE TABLE IF NOT EXISTS ods_version (version INTEGER NOT NULL)")
            version = self._version(con)
            if version == 0 and con.execute("SELECT count(*) FROM ods_version").fetchone()[0] == 0:
                con.execute("INSERT INTO ods_version (version) VALUES (0)")
            if version > SCHEMA_VERSION:
                raise StoreError(f"{self.name} has ODS schema version {version}, newer than this scmr's "
                                 f"{SCHEMA_VERSION}; upgrade scmr-mesh to write it")
            for v in range(version, SCHEMA_VERSION):
                for stmt in steps[v]:
                    con.execute(stmt)
                con.execute("UPDATE ods_version SET version = %s", (v + 1,))
                log.info("ODS %s: migrated schema to version %d", self.name, v + 1)

    # ------------------------------------------------------------------ writer
    def _write_loop(self, ready: concurrent.futures.Future) -> None:
        import psycopg

        try:
            self._wcon = self._connect()
            self._migrate(self._wcon)
        except StoreError as exc:
            ready.set_exception(exc)
            return
        except psycopg.Error as exc:
            ready.set_exception(StoreError(f"cannot open {self.name} as an operational data store "
                                           f"({_first_line(exc)})"))
            return
        ready.set_result(None)
        try:
            serve_writes(self._queue, self._writer_con, self._failed)
        finally:
            if self._wcon is not None:
                self._wcon.close()

    def _writer_con(self):
        """The writer's connection, reconnecting (at most once per RECONNECT_PERIOD_S) after a loss."""
        if self._wcon is not None and not self._wcon.closed and not self._wcon.broken:
            return self._wcon
        now = time.monotonic()
        if now - self._last_attempt < RECONNECT_PERIOD_S:
            raise StoreError(f"operational data store {self.name} unreachable (reconnecting); "
                             "the records stay with the sender")
        self._last_attempt = now
        self._wcon = self._connect()
        if self._down_since is not None:
            log.warning("ODS %s: reachable again after %.1f s", self.name, now - self._down_since)
            self._down_since = None
        return self._wcon

    def _failed(self, exc: BaseException) -> BaseException:
        """Turn a driver error into a one-line StoreError; note when the server went away."""
        import psycopg

        if isinstance(exc, psycopg.OperationalError) or (self._wcon is not None and self._wcon.broken):
            if self._wcon is not None:
                try:
                    self._wcon.close()
                except Exception:
                    pass
                self._wcon = None
            exc = StoreError(f"operational data store {self.name} unreachable ({_first_line(exc)}); "
                             "the records stay with the sender")
        elif isinstance(exc, psycopg.Error):
            exc = StoreError(f"operational data store {self.name}: {_first_line(exc)}")
        if isinstance(exc, StoreError) and "unreachable" in str(exc) and self._down_since is None:
            self._down_since = time.monotonic()
            log.error("ODS: %s", exc)
        return exc

    @staticmethod
    def _insert(con, records: list[TelemetryRecord], received_from: str) -> InsertResult:
        now = time.time_ns()
        if not records:
            return InsertResult((), (), {}, (), ())
        robots = sorted({r.robot for r in records})
        cols: dict[str, list] = {k: [] for k in ("robot", "inc", "seq", "t", "x", "y", "theta", "battery", "health",
                                                 "results", "digest")}
        mine = [r.digest().hex() for r in records]
        for r, digest in zip(records, mine):
            pose = r.pose if r.pose is not None else (None, None, None)
            for k, v in zip(cols, (r.robot, r.inc, r.seq, r.t_unix_ns, *pose, r.battery, r.health,
                                   json.dumps(r.results, sort_keys=True, default=str), digest)):
                cols[k].append(v)
        with con.transaction():
            con.execute("INSERT INTO robot_stats (robot) SELECT unnest(%s::text[]) ON CONFLICT (robot) DO NOTHING",
                        (robots,))
            stats = {robot: (int(c), int(inc)) for robot, c, inc in con.execute(
                "SELECT robot, contiguous, inc FROM robot_stats WHERE robot = ANY(%s) ORDER BY robot FOR UPDATE",
                (robots,)).fetchall()}
            cur = con.execute(
                "INSERT INTO telemetry (robot, inc, seq, t_unix_ns, x, y, theta, battery, health, results, digest, "
                "received_from, stored_unix_ns) "
                "SELECT r, i, s, t, x, y, th, b, h, res, dg, %s, %s FROM unnest(%s::text[], %s::bigint[], "
                "%s::bigint[], %s::bigint[], %s::float8[], %s::float8[], %s::float8[], %s::float8[], %s::text[], "
                "%s::text[], %s::text[]) AS u(r, i, s, t, x, y, th, b, h, res, dg) "
                "ON CONFLICT (robot, inc, seq) DO NOTHING RETURNING robot, inc, seq",
                (received_from, now, *cols.values()))
            new = collections.Counter(tuple(row) for row in cur.fetchall())
            stored: list[tuple[str, int]] = []
            again: list[int] = []
            fresh: dict[str, tuple[int, int]] = {}  # robot -> (reading time, inc) of its newest new record
            for i, r in enumerate(records):
                if new[r.key] > 0:
                    new[r.key] -= 1
                    stored.append((r.robot, r.seq))
                    if r.robot not in fresh or r.t_unix_ns > fresh[r.robot][0]:
                        fresh[r.robot] = (r.t_unix_ns, r.inc)
                else:
                    again.append(i)
            digests: list[str | None] = list(mine)
            dups: list[tuple[str, int]] = []
            conflicts: list[tuple[str, int]] = []
            if again:
                old = {(robot, int(inc), int(seq)): (t, d) for robot, inc, seq, t, d in con.execute(
                    "SELECT robot, inc, seq, t_unix_ns, digest FROM telemetry WHERE (robot, inc, seq) IN "
                    "(SELECT * FROM unnest(%s::text[], %s::bigint[], %s::bigint[]))",
                    ([records[i].robot for i in again], [records[i].inc for i in again],
                     [records[i].seq for i in again])).fetchall()}
                for i in again:
                    r = records[i]
                    t_old, d_old = old.get(r.key, (None, None))
                    if same_content(d_old, t_old, mine[i], r.t_unix_ns):
                        dups.append((r.robot, r.seq))
                    else:
                        conflicts.append((r.robot, r.seq))
                        digests[i] = d_old
                n_dup = collections.Counter(robot for robot, _ in dups)
                n_conf = collections.Counter(robot for robot, _ in conflicts)
                for robot in sorted(set(n_dup) | set(n_conf)):
                    con.execute("UPDATE robot_stats SET duplicates = duplicates + %s, conflicts = conflicts + %s "
                                "WHERE robot = %s", (n_dup[robot], n_conf[robot], robot))
            out: dict[str, int] = {}
            for robot in robots:
                c, c_inc = stats[robot]
                inc = current_incarnation(c_inc, fresh.get(robot), lambda: con.execute(
                    "SELECT MAX(t_unix_ns) FROM telemetry WHERE robot = %s AND inc = %s", (robot, c_inc)).fetchone()[0],
                    direct=received_from == "cloud")
                c = c if c_inc == inc else 0  # a new incarnation counts from its own seq 1
                while True:
                    seqs = [s for (s,) in con.execute(
                        "SELECT seq FROM telemetry WHERE robot = %s AND inc = %s AND seq > %s ORDER BY seq LIMIT 512",
                        (robot, inc, c)).fetchall()]
                    advanced = False
                    for s in seqs:
                        if s != c + 1:
                            break
                        c, advanced = s, True
                    if not advanced or len(seqs) < 512 or seqs[-1] != c:
                        break
                con.execute("UPDATE robot_stats SET contiguous = %s, inc = %s WHERE robot = %s", (c, inc, robot))
                out[robot] = c
        log_conflicts(conflicts)
        return InsertResult(tuple(stored), tuple(dups), out, tuple(conflicts), tuple(digests))

    # ------------------------------------------------------------------ reads
    def _read(self, sql: str, params: Sequence[Any] = ()) -> list[tuple]:
        import psycopg

        if self._closed:
            raise StoreError(f"the operational data store {self.name} is closed")
        with self._rlock:
            for attempt in (1, 2):  # a connection the server dropped is replaced once
                if self._rcon is None or self._rcon.closed or self._rcon.broken:
                    self._rcon = self._connect()
                try:
                    return self._rcon.execute(sql.replace("?", "%s"), params).fetchall()
                except psycopg.OperationalError as exc:
                    self._rcon = None
                    if attempt == 2:
                        raise StoreError(f"cannot read the operational data store {self.name}: "
                                         f"{_first_line(exc)}") from None
                except psycopg.Error as exc:
                    raise StoreError(f"cannot read the operational data store {self.name}: "
                                     f"{_first_line(exc)}") from None
        raise AssertionError("unreachable")  # pragma: no cover

    def schema_version(self) -> int:
        """The ``ods_version`` of the database."""
        return int(self._read("SELECT version FROM ods_version")[0][0])

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Finish pending writes, stop the writer, close the connections (idempotent)."""
        if self._closed:
            return
        super().close()
        with self._rlock:
            if self._rcon is not None:
                try:
                    self._rcon.close()
                except Exception:
                    pass
                self._rcon = None


__all__ = ["PostgresStore", "redact"]
