"""The leader's data service: relay of robots' telemetry to the cloud, its data-buffer copy
(:class:`LeaderData`; see :mod:`scmr_mesh.mesh.data_service`).
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
import time
from pathlib import Path
from typing import Callable


from scmr_mesh import keys
from scmr_mesh.data.buffer import BufferSync, DataBuffer
from scmr_mesh.data.errors import QueueFullError, TelemetryError
from scmr_mesh.data.queue import TelemetryQueue
from scmr_mesh.data.quota import Quota
from scmr_mesh.data.record import TelemetryRecord, decode_batch, encode_records
from scmr_mesh.mesh.data_common import BATCH, IngestGate, Verdict, RETRY_PERIOD_S, _answer, _busy, _drop, _msgpack_encoding, _pack, _payload, _reply, _unpack, buffer_key, check_sender, relay_key, serve_buffer, sync_key, telemetry_key

log = logging.getLogger(__name__)


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
                 leading: bool = True, quota: Quota | None = None) -> None:
        self.node = node
        self.gate = gate or IngestGate()
        #: per-robot records/bytes per second taken into the relay (over: a busy answer, the robot keeps them)
        self.quota = quota if quota is not None else Quota()
        #: relayed records dropped one by one: unreadable in the relay queue, or refused by the cloud
        self.skipped = 0
        self.cloud_refused = 0
        #: True while this node holds the lead: sync from the clouds; else from ``leader_of()``
        self.leading = leading
        #: ``fn() -> node or None``: the current leader (standby candidates sync from it)
        self.leader_of: Callable[[], str | None] = lambda: None
        self.buffer = DataBuffer(node)
        self.relay = TelemetryQueue(relay_dir, max_bytes=relay_max_bytes)
        self.deadline_s = float(deadline_s)
        self._lock = threading.Lock()
        for _, payload in self.relay.pending():
            try:  # an unreadable one is skipped (and counted) when forwarding
                self.buffer.record_telemetry(TelemetryRecord.from_dict(_unpack(payload)).to_dict(signed=False))
            except TelemetryError:
                pass
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
        ans = self.gate.check_size(payload)
        if ans.verdict is Verdict.BUSY:
            _busy(query, self.gate, f"leader {self.node}")
            return
        if not ans.admitted:
            _answer(query, {"error": ans.reason}, error=True)
            _drop(query)
            return
        # reserve before decoding, by size: a robot's record is ~200-300 bytes on the wire
        est = max(1, min(self.gate.max_batch_records, len(payload) // 128))
        if not self.gate.take(est).admitted:
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
            robot = check_sender(query.key_expr, records)
            blobs = [_pack(r.to_dict()) for r in records]
            if not self.quota.take(robot, len(records), sum(map(len, blobs))):
                wait_ms = round(1e3 * max(0.05, self.quota.retry_after_s(robot, len(records), sum(map(len, blobs)))), 1)
                _answer(query, {"error": f"leader {self.node}: robot {robot} is over its telemetry quota; keep "
                                         "the records and retry", "busy": True, "quota": True,
                                "retry_after_ms": wait_ms}, error=True)
                return
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
            self.buffer.record_telemetry(r.to_dict(signed=False))
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

    def _readable(self, seq: int, payload: bytes) -> TelemetryRecord | None:
        """The relayed record at ``seq``, or None (counted, logged) when it cannot be read back."""
        try:
            return TelemetryRecord.from_dict(_unpack(payload))
        except TelemetryError as exc:
            self.skipped += 1
            if self.skipped in (1, 10, 100) or self.skipped % 1000 == 0:
                log.error("leader %s: relayed record %d skipped (%d so far): %s", self.node, seq, self.skipped, exc)
            return None

    def forward_once(self) -> int:
        """Send the oldest relayed records to a cloud node; return how many left the relay queue.

        One bad record never stops the relay (issue #28 item 4): a record that cannot be read back
        is skipped and counted (``skipped``); the cloud refuses bad records one by one (bad
        signature, quota) and stores the rest, and its answer acknowledges the whole batch
        (``cloud_refused`` counts its refusals; the robots keep their own records until a cloud
        stores them, so nothing is lost here).
        """
        batch = self.relay.pending(limit=BATCH)
        if not batch:
            return 0
        records = [r for r in (self._readable(s, p) for s, p in batch) if r is not None]
        if not records:  # nothing readable: past them at once
            self.relay.ack(batch[-1][0])
            return len(batch)
        clouds = self._clouds()
        if not clouds:
            return 0
        for node in clouds:
            raw = self._query(relay_key(node), encode_records(records, via="leader"))
            if raw is not None:
                self.relay.ack(batch[-1][0])
                self.forwarded += len(records)
                try:
                    body = _unpack(raw)
                    refused = int(body.get("refused") or 0) if isinstance(body, dict) else 0
                except (TelemetryError, TypeError, ValueError):
                    refused = 0
                if refused:
                    self.cloud_refused += refused
                    log.warning("leader %s: cloud %s refused %d of %d relayed records: %s", self.node, node,
                                refused, len(records), body.get("refusals", [])[:2])
                log.info("leader %s: forwarded %d relayed records to cloud %s", self.node, len(records), node)
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

    def __enter__(self):
        """``with`` owns the Zenoh resources this object declares: leaving it calls :meth:`close`."""
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3)
        self._pool.shutdown(wait=True)
        self.session = None
        self.relay.close()


# ---------------------------------------------------------------------- robot
