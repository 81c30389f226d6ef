"""The cloud's data tier in a process of its own (issue 23 item 2).

Measured on the 16-core device (docs/BENCHMARKS.md, "256 robots on the 16-core device"): with
128 robots at 5 Hz the cloud's Python threads used 0.89 of a core, one interpreter, for about 600
answers a second; ``py-spy record --gil`` of a cloud serving 32 robots (2-core box) put 28 % of
the lock-holding samples in the telemetry path (batch decode, signature checks, the store's
writer, the acks).  The frame path and the telemetry path shared one interpreter lock, so the
frames waited for the records.

So ``scmr cloud`` forks, before zenoh or any thread starts, one child that owns the
:class:`~scmr_mesh.mesh.data_cloud.CloudData` (the operational data store, the signature checks,
the quotas, the data buffer).  The parent keeps the zenoh session: its four data queryables
(``telemetry``, ``relay``, ``buffer``, ``sync``) only pass each query's key and payload down a
pipe and send back, from the service's reply threads, what the child answered.  The child runs
CloudData's own callbacks on a stand-in query (:class:`_PipeQuery`), unchanged.

Life cycle: the child has ``PR_SET_PDEATHSIG`` = SIGKILL, so it dies with a SIGKILLed cloud, as
the in-process data tier did (the pipe cannot tell it: the workers forked after it hold the
parent's end too); it ignores SIGINT and SIGTERM and stops when the parent sends it the stop,
after the queries queued before (then it writes its ingest stats).  If the child dies first, the
parent logs it once at ERROR, answers every data query busy (robots keep their records: nothing
is lost), and ``scmr cloud`` stops and exits 1, so a supervisor restarts it.  ``scmr cloud --data-process off`` keeps the old
layout (one process); ``auto``, the default, forks the child from 4 usable cores up.
"""

from __future__ import annotations

import itertools
import logging
import os
import queue
import signal
import threading
from typing import Any, Callable

from scmr_mesh import deathsig
from scmr_mesh.mesh.data_common import _answer, _drop, _payload

log = logging.getLogger(__name__)

#: threads sending the data tier's answers (apart from the frames' reply threads)
DATA_REPLY_THREADS = 2
#: queryables answered later (the store's ack, then ``drop``), not when their callback returns
ASYNC = frozenset({"telemetry", "relay"})
#: how long the cloud waits for its data process to open the store (PostgreSQL may be slow)
READY_TIMEOUT_S = 60.0
#: queries waiting to go down the pipe; beyond it a data query is answered busy at once, so a
#: stalled child never holds zenoh's callback thread (and with it the frames)
MAX_QUEUED = 1024


class DataProcessError(RuntimeError):
    """The data process could not start (its message says why)."""


class _Payload:
    __slots__ = ("_b",)

    def __init__(self, b: bytes) -> None:
        self._b = b

    def to_bytes(self) -> bytes:
        return self._b


class _PipeQuery:
    """What CloudData's callbacks use of a zenoh query, in the child: key, payload, replies, drop."""

    __slots__ = ("rid", "key_expr", "payload", "_out")

    def __init__(self, rid: int, key: str, payload: bytes, out: Callable[[tuple], None]) -> None:
        self.rid, self.key_expr, self._out = rid, key, out
        self.payload = _Payload(payload) if payload else None

    def reply(self, key, blob, *, encoding=None) -> None:  # the parent sets the (msgpack) encoding
        self._out(("reply", self.rid, str(key), bytes(blob)))

    def reply_err(self, blob, *, encoding=None) -> None:
        self._out(("err", self.rid, bytes(blob)))

    def drop(self) -> None:
        self._out(("done", self.rid))


def _die_with_parent() -> None:
    """PR_SET_PDEATHSIG = SIGKILL: the child must not outlive a SIGKILLed cloud (it holds the store).
    The pipe cannot tell it: the workers forked after it inherit the parent's end."""
    if not deathsig.set_in_this_process(signal.SIGKILL):
        log.warning("data process: cannot ask to die with the cloud (prctl PR_SET_PDEATHSIG failed or is "
                    "missing); if the cloud is killed, kill process %d too", os.getpid())


def _child_main(conn, parent_end, make_data: Callable[[], Any], parent: int) -> None:
    parent_end.close()  # only the parent reads and writes that end
    _die_with_parent()
    if os.getppid() != parent:  # the parent died before the prctl
        os._exit(0)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the cloud stops it by closing the pipe
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        data = make_data()
    except Exception as exc:
        conn.send(("failed", 0, str(exc) or type(exc).__name__))
        conn.close()
        os._exit(1)
    lock = threading.Lock()

    def out(msg: tuple) -> None:
        with lock:
            conn.send(msg)

    callbacks = {name: cb for name, _, cb in data.named_queryables()}
    out(("ready", 0, os.getpid()))
    data.after_ready()
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            break
        if msg is None:
            break
        rid, which, key, payload = msg
        q = _PipeQuery(rid, key, payload, out)
        try:
            callbacks[which](q)
        except Exception as exc:  # CloudData answers its own errors; this is a defect
            log.exception("data process: %s query failed", which)
            _answer(q, {"error": f"cloud data process: {exc}"}, error=True)
            _drop(q)
            continue
        if which not in ASYNC:
            q.drop()
    status = 0
    try:
        data.close()  # the ingest stats file, the store
    except Exception:
        log.exception("data process: closing the store failed")
        status = 1
    finally:
        conn.close()
        os._exit(status)


class DataProcess:
    """The parent's end: fork the child (:meth:`start`, before zenoh), then serve its queryables.

    Parameters
    ----------
    node : str
        The cloud node (log lines).
    make_data : callable
        ``() -> CloudData``, run in the child (it opens the store there).
    """

    def __init__(self, node: str, make_data: Callable[[], Any], *,
                 on_death: Callable[[], None] | None = None) -> None:
        self.node = node
        self._make_data = make_data
        #: called once when the child dies while the cloud runs (``scmr cloud``: stop, then exit 1)
        self._on_death = on_death
        self._replier = None  # its own reply threads: an ack stuck on a dead link holds no frame reply
        self._conn = None
        self.proc = None
        self.pid: int | None = None
        #: True once the child died while the cloud was running (the cloud then exits 1)
        self.failed = False
        self._closing = False
        self._svc = None
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._pending: dict[int, list] = {}  # rid -> [query, [(kind, key, blob)...]]
        self._reader: threading.Thread | None = None
        self._outq: queue.Queue = queue.Queue(MAX_QUEUED)

    # ------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Fork the child; call before zenoh starts and before any thread (fork keeps only this one)."""
        import multiprocessing

        if threading.current_thread() is not threading.main_thread():
            # PDEATHSIG fires when the forking *thread* ends: a worker thread's end would kill the child
            raise RuntimeError("DataProcess.start() must run on the main thread (scmr cloud forks it "
                               "before any other thread starts)")
        ctx = multiprocessing.get_context("fork")
        self._conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_child_main, args=(child, self._conn, self._make_data, os.getpid()),
                                name=f"scmr-data-{self.node}", daemon=False)
        self.proc.start()
        child.close()

    def wait_ready(self, timeout: float = READY_TIMEOUT_S) -> None:
        """Wait for the child to open the store; raise :class:`DataProcessError` with its reason."""
        if not self._conn.poll(timeout):
            raise DataProcessError(f"cloud {self.node}: its data process did not open the store within "
                                   f"{timeout:g} s")
        try:
            kind, _, detail = self._conn.recv()
        except (EOFError, OSError):
            self.proc.join(5)
            raise DataProcessError(f"cloud {self.node}: its data process exited at start "
                                   f"(status {self.proc.exitcode})") from None
        if kind != "ready":
            self.proc.join(5)
            raise DataProcessError(str(detail))
        self.pid = int(detail)
        log.info("cloud %s: data tier in process %d", self.node, self.pid)

    def attach(self, svc, keys: list[tuple[str, str]]) -> None:
        """Declare the data queryables ``[(name, key)]`` on ``svc`` and start reading the child's answers."""
        from scmr_mesh.mesh.server import Replier

        self._svc = svc
        self._replier = Replier(DATA_REPLY_THREADS)
        for name, key in keys:
            svc.add_queryable(key, lambda q, name=name: self._on_query(name, q))
        self._reader = threading.Thread(target=self._read, name=f"scmr-data-{self.node}", daemon=True)
        self._reader.start()
        threading.Thread(target=self._write, name=f"scmr-data-tx-{self.node}", daemon=True).start()

    def after_ready(self) -> None:  # the child warms its own verifier
        return None

    def close(self, timeout: float = 10.0) -> None:
        """Stop the child (it writes its stats and closes the store) and wait for it."""
        if self.proc is None or self._closing:
            return
        self._closing = True
        try:  # the writer thread sends the stop after the queries already queued
            self._outq.put(None, timeout=timeout)
        except queue.Full:  # the child stopped reading: it is killed below
            pass
        if self._reader is None:  # never attached: no writer thread
            try:
                self._conn.send(None)
            except (OSError, ValueError):
                pass
        self.proc.join(timeout)
        if self.proc.is_alive():
            log.warning("cloud %s: data process %s did not stop within %g s; killed", self.node, self.pid, timeout)
            self.proc.kill()
            self.proc.join(5)
        if self._reader is not None:  # the child's last answers (acks of stored batches) go out first
            self._reader.join(timeout)
        self._fail_pending("the cloud is stopping")
        if self._replier is not None:  # and are sent before close returns (the process exits next)
            self._replier.close(timeout)

    # ------------------------------------------------------------ queries
    def _on_query(self, which: str, query) -> None:
        if self.failed or self._closing:
            self._refuse(query, "its data process is gone" if self.failed else "the cloud is stopping")
            return
        rid = next(self._ids)
        with self._lock:
            self._pending[rid] = [query, []]
        try:  # zenoh's callback thread never waits for the pipe
            self._outq.put_nowait((rid, which, str(query.key_expr), _payload(query)))
        except queue.Full:
            with self._lock:
                self._pending.pop(rid, None)
            self._refuse(query, f"its data process has {MAX_QUEUED} queries waiting")

    def _write(self) -> None:
        while True:
            msg = self._outq.get()
            if msg is None:  # close(): after the queries queued before it, tell the child to stop
                try:
                    with self._send_lock:
                        self._conn.send(None)
                except (OSError, ValueError):
                    pass
                return
            try:
                with self._send_lock:
                    self._conn.send(msg)
            except (OSError, ValueError) as exc:
                with self._lock:
                    entry = self._pending.pop(msg[0], None)
                if entry is not None:
                    self._refuse(entry[0], f"cannot reach its data process ({exc})")

    def _refuse(self, query, why: str) -> None:
        _answer(query, {"error": f"cloud {self.node}: {why}; keep the records and retry", "busy": True,
                        "retry_after_ms": 1000.0}, error=True)
        _drop(query)

    def _read(self) -> None:
        while True:
            try:
                msg = self._conn.recv()
            except (EOFError, OSError):
                break
            kind, rid = msg[0], msg[1]
            with self._lock:
                entry = self._pending.get(rid) if kind != "done" else self._pending.pop(rid, None)
            if entry is None:
                continue
            if kind == "done":
                self._replier.send(lambda q=entry[0], out=entry[1]: self._send(q, out))
            else:
                entry[1].append(msg)
        if not self._closing:
            self.failed = True
            self.proc.join(1)
            log.error("cloud %s: its data process %s exited (status %s): telemetry is no longer stored here; "
                      "robots keep their records%s", self.node, self.pid,
                      self.proc.exitcode, "; the cloud stops and exits 1" if self._on_death else "")
            self._fail_pending("its data process is gone")
            if self._on_death is not None:
                self._on_death()

    def _send(self, query, out: list) -> None:
        from scmr_mesh.mesh.data_common import _msgpack_encoding

        try:
            for m in out:
                if m[0] == "reply":
                    query.reply(m[2], m[3], encoding=_msgpack_encoding())
                else:
                    query.reply_err(m[2], encoding=_msgpack_encoding())
        except Exception as exc:
            log.warning("data reply failed: %s", exc)
        finally:
            _drop(query)

    def _fail_pending(self, why: str) -> None:
        with self._lock:
            pending, self._pending = list(self._pending.values()), {}
        for query, _ in pending:
            self._refuse(query, why)


__all__ = ["ASYNC", "DataProcess", "DataProcessError"]
