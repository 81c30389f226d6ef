"""Zenoh glue of the data tier: telemetry storage, data-buffer queries, leader sync.

The pure parts live in :mod:`scmr_mesh.data` (ODS, on-disk queue, buffer);
this module puts them on the mesh.  Keys (all under :func:`scmr_mesh.keys.data`):

==============================================  ===================  =====================================
key                                             queryable of         payload -> reply
==============================================  ===================  =====================================
``scmr/data/cloud/<node>/telemetry/<robot>``    cloud                robot's batch -> ack (stored in ODS)
``scmr/data/leader/<node>/telemetry/<robot>``   leader               robot's batch -> ack (relay queue)
``scmr/data/cloud/<node>/relay``                cloud                leader's relayed batch -> ack (ODS)
``scmr/data/<tier>/<node>/buffer``              cloud and leader     ``{"sel": selector}`` -> items
``scmr/data/cloud/<node>/sync``                 cloud                ``{"epoch", "since"}`` -> delta
``scmr/data/leader/<node>/sync``                the leader           the same, for the other candidates
==============================================  ===================  =====================================

Identity: the robot id is in the telemetry key, and a tier refuses (error
reply) a batch holding records of any other robot, so the access-control rules
(:mod:`scmr_mesh.security.acl`), which allow robot X only
``.../telemetry/X``, bind stored records to the sender's certificate.  The
relay key takes batches of any robots and is allowed to servers only.

Flow ("nothing lost"):

1. A robot's :class:`TelemetryAgent` wraps ``Robot.publish_telemetry``: each
   message gets the next per-robot seq and is appended (fsync) to the robot's
   on-disk :class:`~scmr_mesh.data.queue.TelemetryQueue` *before* anything is sent.
2. A flusher thread sends the oldest unacknowledged records, in order, as a
   query to the first alive cloud node, else to the leader, exactly like frame
   requests fail over (live view of liveliness tokens + querier matching +
   deadline).  The tier answers only after the records are durable (ODS commit
   on the cloud; fsynced relay queue on the leader); then the robot acks its
   queue.  No answer: the records stay queued and are replayed later, also
   after a robot restart (the queue is on disk).
3. The leader relays what it stored to the cloud once a cloud node is alive
   again (on ``scmr/data/cloud/<node>/relay``, ``via="leader"``), and acks its
   relay queue on the cloud's answer.
4. The ODS stores each ``(robot, seq)`` once (``INSERT OR IGNORE``); replays
   and relays are counted as duplicates, never stored twice.
5. The leader pulls the data buffer of every live cloud node every
   ``--sync-period`` seconds (delta since the last revision it saw of that
   node) and serves the same buffer queries when the cloud is gone.
6. The R2R tier (docs/R2R.md): every leader-capable node keeps a
   :class:`LeaderData`.  While another node leads it pulls the leader's buffer
   (``scmr/data/leader/<leader>/sync``) every sync period (anti-entropy), so a
   successor serves buffer reads at most one period old.  Robots keep each
   telemetry record until a *cloud* has stored it (end to end): a leader's ack
   only means "relayed", so records relayed through a leader that dies are
   sent again to the cloud later, and the ODS counts them as duplicates.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import json
import logging
import os
import random
import threading
import time
from pathlib import Path
from typing import Any, Callable

import msgpack

from scmr_mesh import cliargs as ca
from scmr_mesh import keys
from scmr_mesh.data.buffer import BufferSync, DataBuffer
from scmr_mesh.data.errors import QueueError, QueueFullError, TelemetryError
from scmr_mesh.data.ods import DEFAULT_FILENAME, OperationalDataStore
from scmr_mesh.data.queue import TelemetryQueue, seq_ranges
from scmr_mesh.data.record import TelemetryRecord, batch_size, decode_batch, encode_records
from scmr_mesh.errors import InputError, MeshError

log = logging.getLogger(__name__)

#: Records per telemetry query.
BATCH = 64
#: Seconds between flush attempts while records are queued and no tier answers.
RETRY_PERIOD_S = 0.2
#: Longest wait between attempts while every tier answers busy (backoff doubles up to it).
MAX_BACKOFF_S = 5.0
#: Largest telemetry batch a tier takes: records per batch and payload bytes
#: (robots and the leader send at most :data:`BATCH`).  Larger ones are refused
#: before they are decoded (payload bytes) or stored (records).
MAX_BATCH_RECORDS = 256
MAX_BATCH_BYTES = 256 << 10
#: Records a tier holds that are not yet durable (waiting for the ODS writer or
#: the relay's fsync); beyond it a batch gets a busy answer and the sender keeps
#: its records and retries later (issue #12, item 4).
MAX_PENDING_RECORDS = 4096


def telemetry_key(tier: str, node: str, robot: str | None = None) -> str:
    """``scmr/data/<tier>/<node>/telemetry/<robot>`` (``robot=None``: ``.../telemetry/*``, the queryable)."""
    return keys.data_telemetry(tier, node, robot)


def relay_key(node: str) -> str:
    """``scmr/data/cloud/<node>/relay``: the leader's forwarded batches (servers only)."""
    return keys.data_relay(node)


def check_sender(key: Any, records: list[TelemetryRecord]) -> str:
    """Return the robot named by telemetry ``key``; raise unless every record is that robot's.

    Parameters
    ----------
    key : str or zenoh.KeyExpr
        The query's key, ``scmr/data/<tier>/<node>/telemetry/<robot>``.
    records : list of TelemetryRecord

    Raises
    ------
    TelemetryError
        The key names no single robot (a wildcard), or a record's ``robot``
        differs from it.  Nothing of the batch is stored.
    """
    robot = keys.telemetry_robot(str(key))
    if robot is None:
        raise TelemetryError(
            f"telemetry key {str(key)!r} names no robot; send a robot's batch on "
            "scmr/data/<tier>/<node>/telemetry/<robot id>")
    others = sorted({r.robot for r in records} - {robot})
    if others:
        raise TelemetryError(
            f"telemetry batch on {str(key)!r} (robot {robot!r}) holds records of robot(s) {others}: "
            f"a robot may store only its own telemetry; nothing of this batch was stored")
    return robot


def buffer_key(tier: str, node: str) -> str:
    """``scmr/data/<tier>/<node>/buffer``."""
    return keys.data(tier, node, "buffer")


def sync_key(node: str, tier: str = "cloud") -> str:
    """``scmr/data/<tier>/<node>/sync``: buffer deltas of a cloud node, or of the leader for its successors."""
    return keys.data(tier, node, "sync")


def _pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _unpack(data: bytes) -> Any:
    try:
        return msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as exc:
        raise TelemetryError(f"data message is not msgpack ({len(data)} bytes): {exc}") from None


def _payload(query) -> bytes:
    p = query.payload
    return b"" if p is None else p.to_bytes()


class IngestGate:
    """Bounds what a tier takes in: batch size, and records waiting to become durable.

    :meth:`admit` answers whether a batch of ``nbytes`` may be decoded; after
    decoding, :meth:`take` reserves its records (False: busy) and
    :meth:`release` returns them once stored or refused.  Thread-safe.

    Parameters
    ----------
    max_pending : int
        Records admitted but not yet durable.
    max_batch_records, max_batch_bytes : int
        Largest batch.
    """

    def __init__(self, *, max_pending: int = MAX_PENDING_RECORDS, max_batch_records: int = MAX_BATCH_RECORDS,
                 max_batch_bytes: int = MAX_BATCH_BYTES) -> None:
        self.max_pending = int(max_pending)
        self.max_batch_records = int(max_batch_records)
        self.max_batch_bytes = int(max_batch_bytes)
        self.pending = 0
        self.peak_pending = 0
        self.busy = 0
        self.too_large = 0
        self._lock = threading.Lock()

    def check_size(self, payload: bytes) -> str | None:
        """Why a batch is refused before it is decoded (None: it may be decoded; "" means busy).

        Reads only its length and its headers (:func:`~scmr_mesh.data.record.batch_size`).
        """
        nbytes = len(payload)
        n = batch_size(payload) if nbytes <= self.max_batch_bytes else None
        if nbytes > self.max_batch_bytes or (n is not None and n > self.max_batch_records):
            with self._lock:
                self.too_large += 1
            what = f"{nbytes} bytes" if n is None else f"{n} records ({nbytes} bytes)"
            return (f"telemetry batch of {what} exceeds the limit of {self.max_batch_records} records and "
                    f"{self.max_batch_bytes} bytes; send smaller batches")
        with self._lock:
            if self.pending >= self.max_pending:
                self.busy += 1
                return ""  # busy: decided before decoding anything
        return None

    def take(self, n: int) -> str | None:
        """Reserve ``n`` records; None when admitted, else why not ("" means busy)."""
        if n > self.max_batch_records:
            with self._lock:
                self.too_large += 1
            return f"telemetry batch of {n} records exceeds {self.max_batch_records}; send smaller batches"
        with self._lock:
            if self.pending + n > self.max_pending and self.pending > 0:
                self.busy += 1
                return ""
            self.pending += n
            self.peak_pending = max(self.peak_pending, self.pending)
        return None

    def release(self, n: int) -> None:
        with self._lock:
            self.pending -= n

    def retry_after_ms(self) -> float:
        """A hint for the busy answer: longer the fuller the queue."""
        return round(RETRY_PERIOD_S * 1e3 * (1 + self.pending / max(1, self.max_pending)), 1)

    def stats(self) -> dict:
        with self._lock:
            return {"pending": self.pending, "peak_pending": self.peak_pending, "busy": self.busy,
                    "too_large": self.too_large, "max_pending": self.max_pending,
                    "max_batch_records": self.max_batch_records, "max_batch_bytes": self.max_batch_bytes}


def _busy(query, gate: IngestGate, who: str) -> None:
    """Answer busy (the sender keeps its records and retries after ``retry_after_ms``)."""
    _answer(query, {"error": f"{who} busy: {gate.pending} telemetry records waiting to be stored (limit "
                             f"{gate.max_pending}); keep the records and retry later",
                    "busy": True, "retry_after_ms": gate.retry_after_ms()}, error=True)
    _drop(query)


#: Wire version of the data tier's replies (the ``v`` of their envelope).
DATA_VERSION = 1


def _concrete(query) -> str | None:
    """The query's key when it names one key (no ``*``, ``**`` or ``$*``), else None."""
    key = str(query.key_expr)
    return None if ("*" in key or "$" in key) else key


def _reply(query, blob: bytes) -> None:
    """Reply ``blob`` on the concrete key the query came on; a wildcard selector gets an error instead."""
    key = _concrete(query)
    if key is None:
        _answer(query, {"error": f"query key {str(query.key_expr)!r} is not concrete; query one node's key, "
                                 "e.g. scmr/data/cloud/<node>/buffer (docs/protocol.md)"}, error=True)
        return
    query.reply(key, blob, encoding=_msgpack_encoding())


def _answer(query, obj: Any, *, error: bool = False, kind: str | None = None) -> None:
    """Reply (or reply_err) ``obj``; maps get the ``{"v": 1, "kind": ...}`` envelope of every scmr message."""
    if isinstance(obj, dict):
        obj = {"v": DATA_VERSION, "kind": kind or ("data_error" if error else "data"), **obj}
    try:
        if error:
            query.reply_err(_pack(obj), encoding=_msgpack_encoding())
        else:
            _reply(query, _pack(obj))
    except Exception as exc:
        log.warning("data reply failed: %s", exc)


def _msgpack_encoding():
    from scmr_mesh.mesh.encoding import msgpack

    return msgpack()


def _drop(query) -> None:
    """Finalise a query answered outside its callback (zenoh facts sheet, gotcha 4)."""
    try:
        query.drop()
    except Exception:
        pass


def record_from_message(msg: dict, seq: int) -> TelemetryRecord:
    """A store record from a mesh telemetry message (``wire.make_telemetry``) and a telemetry seq.

    The message's own ``seq`` (the last finished request) goes to
    ``results["request_seq"]``.
    """
    results = dict(msg.get("results") or {})
    results["request_seq"] = msg.get("seq")
    return TelemetryRecord.from_dict({
        "robot": msg["robot"], "seq": seq, "t_unix_ns": msg.get("t_unix_ns", time.time_ns()),
        "pose": msg.get("pose"), "battery": msg.get("battery"), "health": msg.get("health", "ok"),
        "results": results,
    })


def serve_buffer(buffer: DataBuffer, tier: str, node: str) -> Callable:
    """Queryable callback answering ``{"sel": selector}`` with the matching buffer items."""

    def on_query(query) -> None:
        try:
            req = _unpack(_payload(query)) if _payload(query) else {}
            sel = req.get("sel", "**") if isinstance(req, dict) else None
            if not isinstance(sel, str):
                raise TelemetryError(f"buffer query must be {{'sel': str}}, got {req!r}")
            _answer(query, {"tier": tier, "node": node, "rev": buffer.rev, "items": buffer.query(sel)}, kind="buffer")
        except Exception as exc:
            _answer(query, {"error": str(exc)}, error=True)

    return on_query


# ---------------------------------------------------------------------- cloud
class CloudData:
    """The cloud's data tier: ODS ingest, data buffer, sync source.

    Parameters
    ----------
    node : str
        Cloud node name.
    ods_path : path or str
        The SQLite file (shared by the cloud nodes of one host given the same
        path) or a ``postgresql://`` URL (shared by cloud nodes on any host).
    params : dict, optional
        Initial buffer entries (``maps/...``, ``params/...``).
    """

    def __init__(self, node: str, ods_path: str | Path, *, params: dict | None = None,
                 gate: IngestGate | None = None) -> None:
        self.node = node
        self.gate = gate or IngestGate()
        self.ods = OperationalDataStore(ods_path)
        self.buffer = DataBuffer(node)
        for rec in self.ods.latest().values():  # a restarted cloud serves the last states at once
            self.buffer.record_telemetry(rec)
        for k, v in (params or {}).items():
            self.buffer.put(k, v)
        self.ingested = 0

    def queryables(self) -> list[tuple[str, Callable]]:
        return [(telemetry_key("cloud", self.node), self._on_telemetry),
                (relay_key(self.node), self._on_relay),
                (buffer_key("cloud", self.node), serve_buffer(self.buffer, "cloud", self.node)),
                (sync_key(self.node), self._on_sync)]

    def _on_telemetry(self, query) -> None:
        """A robot's own batch on ``.../telemetry/<robot>``: every record must be that robot's."""
        self._ingest(query, relay=False)

    def _on_relay(self, query) -> None:
        """The leader's relayed batch (any robots) on ``.../relay``; the ACL admits servers only."""
        self._ingest(query, relay=True)

    def _ingest(self, query, *, relay: bool) -> None:
        # zenoh's thread only decodes; the ODS writer thread commits and then acks,
        # so a slow fsync never holds up the session's other traffic (frame queries).
        # Bounded (IngestGate): an oversized batch is refused unread, and beyond
        # MAX_PENDING_RECORDS records waiting for the store the answer is busy.
        gate = self.gate
        taken = 0
        try:
            payload = _payload(query)
            why = gate.check_size(payload)
            if why == "":
                _busy(query, gate, f"cloud {self.node}")
                return
            if why is not None:
                raise TelemetryError(why)
            records, via = decode_batch(payload)
            del payload
            if relay:
                source = via or "leader"
            else:
                check_sender(query.key_expr, records)
                source = "cloud"  # a robot's batch came straight to the cloud, whatever it claims
            why = gate.take(len(records))
            if why == "":
                _busy(query, gate, f"cloud {self.node}")
                return
            if why is not None:
                raise TelemetryError(why)
            taken = len(records)
            fut = self.ods.insert_async(records, received_from=source)
        except Exception as exc:  # not stored: no ack, the sender keeps the records
            gate.release(taken)
            log.warning("cloud %s: telemetry not stored: %s", self.node, exc)
            _answer(query, {"error": str(exc)}, error=True)
            _drop(query)
            return
        fut.add_done_callback(lambda f: self._ack(query, records, f))

    def _ack(self, query, records: list[TelemetryRecord], fut) -> None:
        self.gate.release(len(records))
        try:
            res = fut.result()
        except Exception as exc:
            log.warning("cloud %s: telemetry not stored: %s", self.node, exc)
            _answer(query, {"error": str(exc)}, error=True)
            _drop(query)
            return
        try:
            for r in records:
                self.buffer.record_telemetry(r.to_dict())
            self.ingested += len(records)
        finally:
            _answer(query, {"acked": len(records), "stored": len(res.stored), "duplicates": len(res.duplicates),
                            "contiguous": res.contiguous}, kind="data_ack")
            _drop(query)

    def _on_sync(self, query) -> None:
        try:
            req = _unpack(_payload(query)) if _payload(query) else {}
            blob = self.buffer.delta(int(req.get("since", 0)), epoch=req.get("epoch"))
            _reply(query, blob)
        except Exception as exc:
            _answer(query, {"error": str(exc)}, error=True)

    def close(self) -> None:
        self.ods.close()


# --------------------------------------------------------------------- leader
class LeaderData:
    """The leader's data tier: relay queue, buffer copy, sync and forwarding.

    Parameters
    ----------
    node : str
        Leader node name.
    relay_dir : path
        On-disk queue of telemetry the leader stored for robots while the
        cloud was gone; forwarded to the cloud after failback.
    sync_period_s : float
        Seconds between buffer pulls from the cloud (scheduled batches).  Each
        pull asks every live cloud node for its delta, each node with its own
        cursor (:attr:`syncs`), so the leader's copy is the merge of every
        node's buffer (last writer wins per key) and keeps growing from the
        nodes that are left when any of them is gone.
    relay_max_bytes : int
        Bound of the relay queue; a full relay refuses (robots keep theirs).
    """

    def __init__(self, node: str, relay_dir: str | Path, *, sync_period_s: float = 1.0,
                 relay_max_bytes: int = 64 << 20, deadline_s: float = 1.0, gate: IngestGate | None = None,
                 leading: bool = True) -> None:
        self.node = node
        self.gate = gate or IngestGate()
        #: True while this node holds the lead: sync from the clouds; else from ``leader_of()``
        self.leading = leading
        #: ``fn() -> node or None``: the current leader (standby candidates sync from it)
        self.leader_of: Callable[[], str | None] = lambda: None
        self.buffer = DataBuffer(node)
        self.relay = TelemetryQueue(relay_dir, max_bytes=relay_max_bytes)
        self.deadline_s = float(deadline_s)
        self._lock = threading.Lock()
        for _, payload in self.relay.pending():
            self.buffer.record_telemetry(_unpack(payload))
        if not sync_period_s > 0:
            raise TelemetryError(f"sync period must be > 0 s, got {sync_period_s!r}")
        self.sync_period_s = float(sync_period_s)
        #: One scheduled pull (and cursor) per cloud node seen alive.
        self.syncs: dict[str, BufferSync] = {}
        self.session = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.forwarded = 0
        self.received = 0
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="leader-relay")

    def queryables(self) -> list[tuple[str, Callable]]:
        return [(telemetry_key("leader", self.node), self._on_telemetry),
                (buffer_key("leader", self.node), serve_buffer(self.buffer, "leader", self.node)),
                (sync_key(self.node, "leader"), self._on_sync)]

    def _on_sync(self, query) -> None:
        """Deltas of this leader's buffer, for the candidates that may succeed it."""
        try:
            req = _unpack(_payload(query)) if _payload(query) else {}
            _reply(query, self.buffer.delta(int(req.get("since", 0)), epoch=req.get("epoch")))
        except Exception as exc:
            _answer(query, {"error": str(exc)}, error=True)
        finally:
            _drop(query)

    def _on_telemetry(self, query) -> None:
        # the fsync'd append runs on the leader's own thread, never on zenoh's; the backlog
        # of batches waiting for that thread is bounded like the cloud's (IngestGate)
        payload = _payload(query)
        why = self.gate.check_size(payload)
        if why == "":
            _busy(query, self.gate, f"leader {self.node}")
            return
        if why is not None:
            _answer(query, {"error": why}, error=True)
            _drop(query)
            return
        # reserve before decoding, by size: a robot's record is ~200-300 bytes on the wire
        est = max(1, min(self.gate.max_batch_records, len(payload) // 128))
        if self.gate.take(est) is not None:
            _busy(query, self.gate, f"leader {self.node}")
            return
        try:
            self._pool.submit(self._store, query, est)
        except RuntimeError as exc:  # shutting down: no ack, the robot keeps its records
            self.gate.release(est)
            _answer(query, {"error": f"leader {self.node} is stopping ({exc})"}, error=True)
            _drop(query)

    def _store(self, query, reserved: int = 0) -> None:
        try:
            self._store_and_ack(query)
        finally:
            self.gate.release(reserved)
            _drop(query)

    def _store_and_ack(self, query) -> None:
        try:
            records, _via = decode_batch(_payload(query))
            if len(records) > self.gate.max_batch_records:
                raise TelemetryError(f"telemetry batch of {len(records)} records exceeds "
                                     f"{self.gate.max_batch_records}; send smaller batches")
            check_sender(query.key_expr, records)
            blobs = [_pack(r.to_dict()) for r in records]
            with self._lock:
                if sum(map(len, blobs)) > self.relay.free_bytes():
                    raise QueueFullError(
                        f"leader {self.node}: relay queue full ({self.relay.stats().depth} records waiting "
                        "for the cloud); the robot keeps its records")
                for b in blobs:
                    self.relay.append(b)
        except Exception as exc:
            log.warning("leader %s: telemetry not stored: %s", self.node, exc)
            _answer(query, {"error": str(exc)}, error=True)
            return
        for r in records:
            self.buffer.record_telemetry(r.to_dict())
        self.received += len(records)
        _answer(query, {"acked": len(records), "stored": len(records), "duplicates": 0}, kind="data_ack")

    # -- background: sync + forward
    def _clouds(self) -> list[str]:
        s = self.session
        if s is None:
            return []
        nodes = set()
        for reply in s.liveliness().get(f"{keys.ALIVE}/cloud/*", timeout=self.deadline_s):
            if reply.ok is not None:
                nodes.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return sorted(nodes)

    def _query(self, key: str, payload: bytes) -> bytes | None:
        s = self.session
        if s is None:
            return None
        for reply in s.get(key, payload=payload, encoding=_msgpack_encoding(), timeout=self.deadline_s):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
        return None

    def _fetch_from(self, node: str, epoch: str | None, since: int, tier: str = "cloud") -> bytes | None:
        return self._query(sync_key(node, tier), _pack({"epoch": epoch, "since": since}))

    def sync_once(self) -> dict[str, bool]:
        """Pull a delta from every live cloud node while leading, from the leader while standing by;
        return ``{node: answered}``."""
        if self.leading:
            sources = [("cloud", node, node) for node in self._clouds()]
        else:  # a standby candidate keeps a copy of the leader's buffer (anti-entropy)
            lead = self.leader_of()
            sources = [] if not lead or lead == self.node else [("leader", lead, f"leader:{lead}")]
        out = {}
        for tier, node, name in sources:
            sync = self.syncs.get(name)
            if sync is None:
                sync = self.syncs[name] = BufferSync(
                    self.buffer, lambda epoch, since, node=node, tier=tier: self._fetch_from(node, epoch, since, tier),
                    period_s=self.sync_period_s)
            res = sync.pull_once()
            out[node] = res is not None
            if tier == "leader" and res is not None and res.applied:
                shared = sorted(k for k in self.buffer.items() if not k.startswith(("state/", "results/")))
                log.info("%s: standby copy of leader %s's buffer: +%d entries (%d in all; shared: %s)",
                         self.node, node, res.applied, len(self.buffer.items()), ", ".join(shared[:8]) or "none")
        return out

    def forward_once(self) -> int:
        """Send the oldest relayed records to a cloud node; return how many were acknowledged."""
        batch = self.relay.pending(limit=BATCH)
        if not batch:
            return 0
        clouds = self._clouds()
        if not clouds:
            return 0
        records = [TelemetryRecord.from_dict(_unpack(p)) for _, p in batch]
        for node in clouds:
            raw = self._query(relay_key(node), encode_records(records, via="leader"))
            if raw is not None:
                self.relay.ack(batch[-1][0])
                self.forwarded += len(batch)
                log.info("leader %s: forwarded %d relayed records to cloud %s", self.node, len(batch), node)
                return len(batch)
        return 0

    def _loop(self, svc) -> None:
        while self.session is None and not self._stop.is_set():
            self.session = getattr(svc, "session", None)
            self._stop.wait(0.05)
        next_sync = 0.0
        while not self._stop.is_set():
            if svc is not None and getattr(svc, "session", None) is None:
                break
            now = time.monotonic()
            try:
                if now >= next_sync:
                    next_sync = now + self.sync_period_s
                    self.sync_once()
                while self.forward_once() and not self._stop.is_set():
                    pass
            except Exception as exc:  # the session closing under us at shutdown
                log.debug("leader data loop: %s", exc)
            self._stop.wait(RETRY_PERIOD_S)

    def start(self, svc=None, *, session=None) -> None:
        """Sync and forward in a daemon thread once ``svc`` is attached to a session
        (or, for an R2R candidate whose service changes role, on ``session`` for good)."""
        if session is not None:
            self.session = session
        self._thread = threading.Thread(target=self._loop, args=(svc,), name="leader-data", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3)
        self._pool.shutdown(wait=True)
        self.session = None
        self.relay.close()


# ---------------------------------------------------------------------- robot
class TelemetryAgent:
    """A robot's side: on-disk queue, ordered replay, acks, data requests.

    Parameters
    ----------
    robot : scmr_mesh.mesh.robot.Robot
        The robot (attached to a session); its ``publish_telemetry`` is wrapped.
    queue_dir : path
        The robot's telemetry queue folder (kept across restarts).
    max_bytes : int
        Queue bound; when full, new telemetry is refused and counted.
    deadline_ms : float
        Per-attempt deadline of telemetry and data queries.
    autostart : bool
        Start the flusher thread (tests call :meth:`flush_once` themselves).
    """

    def __init__(self, robot, queue_dir: str | Path, *, max_bytes: int = 16 << 20,
                 deadline_ms: float = 1000.0, autostart: bool = True) -> None:
        self.robot = robot
        # a refused record keeps its seq (it is in the record already): the store sees the
        # gap and every report counts it as lost
        self.queue = TelemetryQueue(queue_dir, max_bytes=max_bytes, refusals_use_seqs=True)
        self.deadline_s = deadline_ms / 1e3
        self.acked_by = {"cloud": 0, "leader": 0}
        #: records up to this seq were relayed by a leader but not yet stored by a cloud (kept queued)
        self._relayed_upto = 0
        self.refused_logged = 0
        self.publish_errors = 0
        self.busy_answers = 0      # batches a tier answered busy (kept, retried after a backoff)
        self._busy_streak = 0
        self._not_before = 0.0     # monotonic time before which the flusher does not retry
        self._replay_upto = 0  # records with seq <= this waited through a failed attempt
        self._queriers: dict[str, Any] = {}
        self._qlock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        robot.add_telemetry_handler(self._handle)
        self._thread = threading.Thread(target=self._loop, name=f"telemetry-{robot.id}", daemon=True)
        if autostart:  # tests drive flush_once() themselves
            self._thread.start()
        st = self.queue.stats()
        if st.depth:
            log.info("robot %s: %d telemetry records queued from before; replaying", robot.id, st.depth)
            self._replay_upto = st.next_seq - 1

    # -- producer side
    def publish(self, message: dict) -> int | None:
        """Publish ``message`` and queue it for the store (as the robot's handler does); return its seq."""
        return self._handle(message, self.robot.publish_telemetry)

    def _handle(self, message: dict, forward: Callable[[dict], Any]) -> int | None:
        """The robot's telemetry handler: ``forward`` (publish) ``message``, queue it; return its telemetry seq.

        Never raises for a refusal: a full queue or a file system that refuses
        the write (full, read-only, immutable) counts the record as refused
        with its seq (``refused``, ``refused_seqs`` in :meth:`summary`), logs
        it, and returns None, so the robot keeps sending frames.
        """
        try:
            forward(message)
        except Exception as exc:
            self.publish_errors += 1
            log.debug("telemetry publish failed: %s", exc)
        seq = self.queue.next_seq
        rec = record_from_message(message, seq)
        try:
            self.queue.append(_pack(rec.to_dict()), seq=seq)
        except QueueError as exc:  # QueueFullError, QueueWriteError: refused, counted with its seq
            self.refused_logged += 1
            if self.refused_logged in (1, 10, 100) or self.refused_logged % 1000 == 0:
                log.error("robot %s: telemetry record %d refused (%d so far): %s", self.robot.id, seq,
                          self.refused_logged, exc)
            return None
        self._wake.set()
        return seq

    # -- sending
    def _querier(self, key: str):
        import zenoh

        with self._qlock:
            q = self._queriers.get(key)
            if q is None:
                q = self.robot._session.declare_querier(
                    key, target=zenoh.QueryTarget.BEST_MATCHING,
                    consolidation=zenoh.ConsolidationMode.NONE, timeout=self.deadline_s)
                self._queriers[key] = q
            return q

    def _ask(self, key: str, payload: bytes) -> tuple[str, Any] | None:
        """One query; ``("ok", reply)``, ``("err", message)`` or None (unreachable/no reply)."""
        q = self._querier(key)
        if not q.matching_status.matching:
            return None
        for reply in q.get(payload=payload, encoding=_msgpack_encoding()):
            if reply.ok is not None:
                return "ok", _unpack(reply.ok.payload.to_bytes())
            try:
                return "err", _unpack(reply.err.payload.to_bytes())
            except TelemetryError:
                return "err", reply.err.payload.to_bytes().decode("utf-8", "replace")
        return None

    def _targets(self) -> list[tuple[str, str]]:
        view = self.robot.view.snapshot(local=False)
        return [("cloud", n) for n in view.cloud] + [("leader", n) for n in view.leader]

    def flush_once(self) -> int:
        """Send the oldest queued records to a tier that takes them; return how many it took.

        A cloud's ack (records stored in the ODS) removes them from the queue.
        A leader's ack only means *relayed*: the records stay queued (end to
        end: a leader that dies with them loses nothing) and are not sent to a
        leader again; they go to a cloud once one is alive.  A busy answer
        keeps the records and backs off (doubling, jittered).
        """
        targets = self._targets()
        clouds = [t for t in targets if t[0] == "cloud"]
        leaders = [t for t in targets if t[0] == "leader"]
        busy_hint_ms = None
        for tier_targets, after in ((clouds, 0), (leaders, self._relayed_upto)):
            if not tier_targets:
                continue
            batch = self.queue.pending(limit=BATCH, after=after)
            if not batch:
                continue
            payload = encode_records([TelemetryRecord.from_dict(_unpack(p)) for _, p in batch])
            for tier, node in tier_targets:
                try:
                    ans = self._ask(telemetry_key(tier, node, self.robot.id), payload)
                except Exception as exc:
                    log.debug("telemetry to %s/%s failed: %s", tier, node, exc)
                    continue
                if ans is None:
                    continue
                kind, body = ans
                if kind == "ok":
                    upto = batch[-1][0]
                    if tier == "cloud":
                        replayed = sum(1 for s, _ in batch if s <= self._replay_upto)
                        self.queue.ack(upto)
                        if replayed:
                            self.queue.note_replayed(replayed)
                    else:
                        self._relayed_upto = upto
                    self.acked_by[tier] += len(batch)
                    self._busy_streak = 0
                    self._not_before = 0.0
                    return len(batch)
                if isinstance(body, dict) and body.get("busy"):
                    self.busy_answers += 1
                    busy_hint_ms = max(busy_hint_ms or 0.0, float(body.get("retry_after_ms") or 0.0))
                    log.info("robot %s: %s/%s busy: %s", self.robot.id, tier, node, body.get("error"))
                    continue
                log.warning("robot %s: %s/%s did not store telemetry: %s", self.robot.id, tier, node, body)
        self._replay_upto = self.queue.next_seq - 1
        if busy_hint_ms is not None:  # kept; back off (doubling, jittered) before the next attempt
            self._busy_streak += 1
            wait = min(MAX_BACKOFF_S, max(busy_hint_ms / 1e3, RETRY_PERIOD_S * 2 ** self._busy_streak))
            self._not_before = time.monotonic() + wait * random.uniform(0.75, 1.0)
        return 0

    @property
    def backoff_s(self) -> float:
        """Seconds until the flusher tries again after busy answers (0 when it is not backing off)."""
        return max(0.0, self._not_before - time.monotonic())

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()
            if self.backoff_s > 0:  # a tier said busy: new records wait too
                self._stop.wait(self.backoff_s)
                continue
            try:
                sent = self.flush_once()
            except Exception as exc:  # session closing at shutdown
                log.debug("telemetry flush: %s", exc)
                sent = 0
            if sent and len(self.queue):
                continue
            self._wake.wait(RETRY_PERIOD_S if len(self.queue) else 1.0)

    # -- data requests (fail over like frame requests)
    def fetch(self, selector: str) -> tuple[str, str, dict]:
        """Items of the data buffer matching ``selector``, from the cloud, else the leader.

        Returns
        -------
        (tier, node, items)

        Raises
        ------
        MeshError
            No tier answered.
        """
        tried = []
        for tier, node in self._targets():
            ans = self._ask(buffer_key(tier, node), _pack({"sel": selector}))
            tried.append(f"{tier}/{node}={'no reply' if ans is None else ans[0]}")
            if ans is not None and ans[0] == "ok":
                return tier, node, ans[1]["items"]
        raise MeshError(f"no tier answered the data request {selector!r} ({', '.join(tried) or 'no tier alive'})")

    def _drainable(self) -> bool:
        """Whether a live tier could take some of the queued records now."""
        if not len(self.queue):
            return False
        targets = self._targets()
        if any(t == "cloud" for t, _ in targets):
            return True
        return bool(targets) and bool(self.queue.pending(limit=1, after=self._relayed_upto))

    # -- end
    def summary(self) -> dict:
        """The robot's telemetry counters (``OUT/telemetry.json``).

        ``sent`` counts every seq handed out (refused ones included), ``lost``
        the records that can never reach the store: ``refused`` (refused with
        their seq, listed as ranges in ``refused_seqs``) plus ``lost_seqs``
        found on disk at start (corruption, records cut off).
        """
        st = self.queue.stats()
        lost = sorted(set(st.refused_seqs) | set(st.lost_seqs))
        relayed = len(self.queue.pending(limit=None)) - len(self.queue.pending(limit=None, after=self._relayed_upto))
        return {"robot": self.robot.id, "sent": st.next_seq - 1, "queued": st.depth, "refused": st.refused,
                "refused_seqs": seq_ranges(st.refused_seqs, limit=20), "lost": len(lost),
                "relayed_unstored": relayed,
                "replayed": st.replayed, "acked_by": dict(self.acked_by), "busy_answers": self.busy_answers,
                "torn_bytes": st.torn_bytes,
                "corruptions": len(st.corruptions), "lost_seqs": st.lost_seqs[:100],
                "error": st.last_error}

    def close(self, *, drain_s: float = 2.0, summary_path: str | Path | None = None) -> dict:
        """Stop the flusher (after up to ``drain_s`` of draining), write the summary, close the queue."""
        end = time.monotonic() + drain_s
        started = self._thread.is_alive()
        while started and self._drainable() and time.monotonic() < end:
            self._wake.set()
            time.sleep(0.05)
        self._stop.set()
        self._wake.set()
        if started:
            self._thread.join(timeout=5)
        for q in list(self._queriers.values()):
            try:
                q.undeclare()
            except Exception:
                pass
        self._queriers = {}
        self.robot.remove_telemetry_handler(self._handle)
        out = self.summary()
        if summary_path is not None:
            tmp = Path(f"{summary_path}.tmp")
            try:
                tmp.write_text(json.dumps(out) + "\n")
                os.replace(tmp, summary_path)
            except OSError as exc:  # the counts still reach the log and the exit status
                log.error("robot %s: cannot write %s (%s); telemetry summary: %s", self.robot.id, summary_path,
                          exc, json.dumps(out))
        if out["lost"]:
            log.error("robot %s: %d telemetry record(s) lost (refused %s; lost on disk %s): %s", self.robot.id,
                      out["lost"], ",".join(out["refused_seqs"]) or "none",
                      ",".join(seq_ranges(out["lost_seqs"], limit=20)) or "none", out["error"] or "see above")
        if out["queued"]:
            log.warning("robot %s: %d telemetry records still queued at exit (kept on disk in %s; "
                        "replayed at the next start)", self.robot.id, out["queued"], self.queue.path)
        self.queue.close()
        return out


# ------------------------------------------------------------ CLI plumbing
def _run_dir_from(args) -> Path | None:
    if os.environ.get("SCMR_RUN_DIR"):
        return Path(os.environ["SCMR_RUN_DIR"])
    ready = getattr(args, "ready_file", None)
    if ready:  # the fleet layout is <run dir>/ready/<peer>.ready; else the ready file's folder
        folder = Path(ready).resolve().parent
        return folder.parent if folder.name == "ready" else folder
    return None


def add_arguments(parser, role: str) -> None:
    """Add the data-tier flags of ``role`` ("cloud", "leader" or "robot") to a peer's parser."""
    g = parser.add_argument_group("data tier")
    if role == "cloud":
        g.add_argument("--ods", type=ca.PathArg("out-file", url=True, what="an ODS file path or a postgresql:// URL"), metavar="FILE|URL",
                       help="operational data store: a SQLite file (one cloud node, or several on one "
                            "host), or a postgresql:// URL that several cloud nodes share (e.g. "
                            "postgresql://scmr@db.site:5432/scmr); default $SCMR_ODS, else "
                            "$SCMR_RUN_DIR/ods.sqlite, else RUN/ods.sqlite where RUN is the folder of "
                            "--ready-file (its parent when that folder is named 'ready'), else "
                            "runs/ods.sqlite")
        g.add_argument("--data-params", type=ca.PathArg("in-file", what="a JSON file of buffer entries"), metavar="FILE",
                       help="JSON object of shared entries for the data buffer (keys like "
                            "'maps/site' or 'params/speed')")
    if role in ("leader", "robot"):
        extra = "" if role == "leader" else "with --leader-capable: "
        g.add_argument("--sync-period", type=ca.positive("seconds", hi=3600, example="1"), default=1.0, metavar="S",
                       help=extra + "seconds between pulls of the data buffer: from the clouds while leading, from "
                            "the leader otherwise (default 1)")
        g.add_argument("--relay-dir", type=ca.PathArg("out-dir"), metavar="DIR",
                       help=extra + "on-disk queue of telemetry held for the cloud while leading "
                            "(default <run dir>/relay-NODE)")
    if role in ("cloud", "leader"):
        g.add_argument("--ingest-queue", type=ca.count("records", hi=10**7, example="4096"),
                       default=MAX_PENDING_RECORDS, metavar="N",
                       help="telemetry records held until they are durable (ODS commit, relay fsync); beyond "
                            "them a batch gets a busy answer and the robot keeps it and retries (default "
                            f"{MAX_PENDING_RECORDS})")
        g.add_argument("--ingest-batch", type=ca.count("records", hi=10**5, example="256"),
                       default=MAX_BATCH_RECORDS, metavar="N",
                       help=f"largest telemetry batch taken, in records (and N KiB); larger ones are refused "
                            f"(default {MAX_BATCH_RECORDS}; robots send {BATCH})")
    if role in ("robot", "leader"):
        g.add_argument("--telemetry-queue", type=ca.PathArg("out-dir"), metavar="DIR",
                       help="the robot's on-disk telemetry queue, kept across restarts (default "
                            "RUN/queues/ID when a run dir is known from $SCMR_RUN_DIR or --ready-file, "
                            "else OUT/telemetry-queue)")
        g.add_argument("--telemetry-max-bytes", type=ca.count("bytes", lo=1024, hi=1 << 40, example="16777216"), default=16 << 20, metavar="N",
                       help="bound of the telemetry queue; beyond it new telemetry is refused and "
                            "counted (default 16 MiB)")


def service_setup(args, tier: str) -> Callable:
    """The ``setup`` hook for :func:`~scmr_mesh.mesh.peers.run_service`: installs the data tier."""

    def setup(svc) -> None:
        if data_tier_off():
            log.warning("%s %s: data tier off (SCMR_DATA_TIER=off): telemetry is not stored", tier, svc.node)
            return
        run_dir = _run_dir_from(args)
        if tier == "cloud":
            from scmr_mesh.data.ods import default_db_path, store_target

            if getattr(args, "ods", None):
                path = store_target(args.ods)
            elif os.environ.get("SCMR_ODS") or run_dir is None:
                path = default_db_path()
            else:
                path = run_dir / DEFAULT_FILENAME
            params = None
            if getattr(args, "data_params", None):
                try:
                    params = json.loads(Path(args.data_params).read_text())
                except (OSError, ValueError) as exc:
                    raise InputError(f"--data-params {args.data_params}: not a readable JSON file ({exc})") from None
                if not isinstance(params, dict):
                    raise InputError(f"--data-params {args.data_params}: must hold a JSON object, "
                                     f"got {type(params).__name__}")
            data = CloudData(svc.node, path, params=params, gate=_gate(args))
            log.info("cloud %s: operational data store %s (%s)", svc.node, data.ods.name, data.ods.backend)
        else:
            if not getattr(args, "sync_period", 1.0) > 0:
                raise InputError(f"--sync-period must be > 0 s, got {args.sync_period}")
            relay = getattr(args, "relay_dir", None) or (run_dir or Path("runs")) / f"relay-{svc.node}"
            data = LeaderData(svc.node, relay, sync_period_s=getattr(args, "sync_period", 1.0), gate=_gate(args))
            data.start(svc)
        for key, cb in data.queryables():
            svc.add_queryable(key, cb)
        svc.data = data
        atexit.register(data.close)

    return setup


def _gate(args) -> IngestGate:
    """The ingest bounds of ``--ingest-queue`` and ``--ingest-batch``."""
    batch = int(getattr(args, "ingest_batch", None) or MAX_BATCH_RECORDS)
    return IngestGate(max_pending=int(getattr(args, "ingest_queue", None) or MAX_PENDING_RECORDS),
                      max_batch_records=batch, max_batch_bytes=batch << 10)


def data_tier_off() -> bool:
    """True when ``SCMR_DATA_TIER=off``: peers run without the data tier (to measure its cost)."""
    return os.environ.get("SCMR_DATA_TIER", "").lower() in ("off", "0", "no")


def attach_robot(robot, args) -> TelemetryAgent | None:
    """Wrap ``robot``'s telemetry with a :class:`TelemetryAgent` configured from ``args``.

    Returns None (nothing wrapped) when :func:`data_tier_off`.
    """
    if data_tier_off():
        return None
    qdir = getattr(args, "telemetry_queue", None)
    if not qdir:
        run_dir = _run_dir_from(args)
        # in a run dir the queue is per robot id, so a restarted robot (new --out) keeps it
        qdir = run_dir / "queues" / robot.id if run_dir is not None else Path(args.out) / "telemetry-queue"
    return TelemetryAgent(robot, qdir, max_bytes=getattr(args, "telemetry_max_bytes", 16 << 20),
                          deadline_ms=getattr(args, "deadline_ms", 1000.0))


__all__ = [
    "CloudData", "IngestGate", "LeaderData", "TelemetryAgent", "add_arguments", "attach_robot", "buffer_key",
    "check_sender", "record_from_message", "relay_key", "service_setup", "sync_key", "telemetry_key",
]


def fetch_once(selector: str, mesh, *, wait_s: float = 3.0, deadline_ms: float = 1000.0) -> tuple[str, str, dict]:
    """One data-buffer request from a fresh session, routed like a robot's (cloud, else leader).

    Parameters
    ----------
    selector : str
        ``state/r1``, ``state/**``, ``maps/*``, ``**``.
    mesh : scmr_mesh.mesh.config.MeshConfig
        Where to connect.
    wait_s : float
        How long to wait for a cloud or leader liveliness token.

    Returns
    -------
    (tier, node, items)

    Raises
    ------
    MeshError
        No tier alive after ``wait_s``, or none answered.
    """
    from scmr_mesh.mesh.config import close_session, open_session

    session = open_session(mesh)
    try:
        # a liveliness query answers with every token alive now (complete when it returns), so
        # a cloud is never passed over for a leader whose token happened to arrive first
        end = time.monotonic() + wait_s
        alive: dict[str, set[str]] = {"cloud": set(), "leader": set()}
        while True:
            left = end - time.monotonic()
            for reply in session.liveliness().get(keys.ALIVE_ALL, timeout=max(0.05, min(1.0, left))):
                if reply.ok is not None:
                    try:
                        _, tier, node = keys.parse(str(reply.ok.key_expr))
                    except Exception:
                        continue
                    if tier in alive:
                        alive[tier].add(node)
            if alive["cloud"] or alive["leader"]:
                break
            if time.monotonic() >= end:
                raise MeshError(f"no cloud or leader alive after {wait_s:g} s (connect={mesh.connect}); "
                                "check --connect and that the peers run" + (
                                    "; a secured mesh (the default of scmr up) admits only holders of its "
                                    "certificates: add --security RUN/certs/mtls.toml --id ROBOT"
                                    if not mesh.security else ""))
            time.sleep(0.05)
        tried = []
        for tier, node in [("cloud", n) for n in sorted(alive["cloud"])] + [("leader", n) for n in sorted(alive["leader"])]:
            got = None
            for reply in session.get(buffer_key(tier, node), payload=_pack({"sel": selector}),
                                     timeout=deadline_ms / 1e3):
                got = reply
                break
            if got is not None and got.ok is not None:
                return tier, node, _unpack(got.ok.payload.to_bytes())["items"]
            tried.append(f"{tier}/{node}={'no reply' if got is None else 'error'}")
        raise MeshError(f"no tier answered the data request {selector!r} ({', '.join(tried) or 'no tier'})")
    finally:
        close_session(session)

