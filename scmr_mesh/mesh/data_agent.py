"""The robot's telemetry agent: a durable queue flushed to a live tier, data requests with
failover (:class:`TelemetryAgent`, :func:`fetch_once`; see :mod:`scmr_mesh.mesh.data_service`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import random
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterable


from scmr_mesh import keys
from scmr_mesh.data.errors import QueueError, TelemetryError
from scmr_mesh.data.queue import TelemetryQueue, folder_incarnation, seq_ranges
from scmr_mesh.data.record import TelemetryRecord, encode_records
from scmr_mesh.errors import MeshError
from scmr_mesh.mesh.data_common import BATCH, MAX_BACKOFF_S, RETRY_PERIOD_S, _msgpack_encoding, _pack, _unpack, buffer_key, record_from_message, telemetry_key
from scmr_mesh.vocab import Tier

log = logging.getLogger(__name__)

#: Payload bytes of telemetry a robot keeps in memory when its disk queue refuses a record (full
#: disk, any OSError on write, or the queue's own bound): delivered from there while a store
#: acknowledges; only beyond this are records dropped (counted in ``dropped``).  4 MiB holds
#: about 14,000 records (~300 B each), 45 minutes of one robot at 5 Hz.
MEMORY_BUFFER_BYTES = 4 << 20

#: Least time between two telemetry batches the flusher sends while the backlog is short (s): the
#: records of that period go in one query and one ack (one query, one reply, one ack write per
#: period instead of per record: about 2.5 records per batch at 5 Hz).  Records are queued on disk
#: as soon as they are made; only their trip to the store waits (at most this long).  A full batch
#: (a replay after an outage) and the drain at close never wait.  Issue 23, docs/BENCHMARKS.md
#: "CPU per request".
FLUSH_PERIOD_S = 0.5


def failover_order(clouds: Iterable[str], leaders: Iterable[str]) -> list[tuple[str, str]]:
    """Where a data request goes, in order: every live cloud node, then the leader(s).

    >>> failover_order(["c1"], ["L"])
    [('cloud', 'c1'), ('leader', 'L')]
    """
    return [(Tier.CLOUD.value, n) for n in clouds] + [(Tier.LEADER.value, n) for n in leaders]


def fetch_buffer(targets: Iterable[tuple[str, str]], ask: Callable[[str, bytes], tuple[str, Any] | None],
                 selector: str) -> tuple[str, str, dict]:
    """Items of the data buffer matching ``selector`` from the first target that answers ``ok``.

    ``ask(key, payload)`` returns ``("ok", reply)``, ``("err", ...)`` or None (no reply).  The one
    failover of data requests: a robot's agent (:meth:`TelemetryAgent.fetch`) and ``scmr ods
    fetch`` (:func:`fetch_once`) both use it.

    Raises
    ------
    MeshError
        No target answered ``ok`` (the message lists what each said).
    """
    tried = []
    payload = _pack({"sel": selector})
    for tier, node in targets:
        ans = ask(buffer_key(tier, node), payload)
        tried.append(f"{tier}/{node}={'no reply' if ans is None else ans[0]}")
        if ans is not None and ans[0] == "ok":
            return tier, node, ans[1]["items"]
    raise MeshError(f"no tier answered the data request {selector!r} ({', '.join(tried) or 'no tier alive'})")


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
    memory_bytes : int
        Bound on the in-memory buffer of records the disk queue refused
        (:data:`MEMORY_BUFFER_BYTES`; 0 turns the buffer off).
    signer : scmr_mesh.data.signing.RecordSigner, optional
        Signs each record with the robot's own key (a secured mesh: the store
        refuses unsigned records); None: records go unsigned.
    flush_period_s : float
        Least time between two batches while the backlog is short
        (:data:`FLUSH_PERIOD_S`; 0 sends each record as soon as it is queued).
    """

    def __init__(self, robot, queue_dir: str | Path, *, max_bytes: int = 16 << 20,
                 deadline_ms: float = 1000.0, autostart: bool = True,
                 memory_bytes: int = MEMORY_BUFFER_BYTES, signer=None,
                 flush_period_s: float = FLUSH_PERIOD_S) -> None:
        self.robot = robot
        self.flush_period_s = max(0.0, float(flush_period_s))
        self._next_flush = 0.0     # monotonic time before which a short backlog waits (flush_period_s)
        self._draining = threading.Event()  # close(): send what is queued now, no waiting
        self.signer = signer
        #: the queue folder's incarnation: every record carries it (a wiped folder starts a new history)
        self.incarnation = folder_incarnation(queue_dir)
        #: records a cloud answered for with another digest (a conflict) or refused: kept, never deleted
        self._not_acked: set[int] = set()  # seqs a cloud answered for with another digest or refused
        self._bad_acks = 0  # answers of a cloud without per-record digests (an older cloud)
        # a refused record keeps its seq (it is in the record already) and waits in memory
        # (_mem); one never delivered leaves a gap the store sees, and every report counts it lost
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
        # records the disk queue refused, kept in memory (seq -> payload) until a cloud stores them
        self.memory_bytes = max(0, int(memory_bytes))
        self._mem: dict[int, bytes] = {}
        self._mem_size = 0
        self._mem_lock = threading.Lock()
        self.mem_held = 0          # records the disk refused that the memory buffer took
        self.mem_delivered = 0     # of those, stored by a cloud
        self.dropped = 0           # refused by the disk and beyond the memory bound: lost
        self.ack_write_errors = 0  # acks the disk would not record (the records were stored all the same)
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
        it, and keeps it in the bounded memory buffer (delivered from there
        while a cloud stores telemetry; counted in ``dropped`` when the buffer
        is full too), so the robot keeps sending frames.  Returns the seq when
        the record is kept (on disk or in memory), None when it was dropped.
        """
        try:
            forward(message)
        except Exception as exc:
            self.publish_errors += 1
            log.debug("telemetry publish failed: %s", exc)
        seq = self.queue.next_seq
        rec = dataclasses.replace(record_from_message(message, seq), inc=self.incarnation)
        if self.signer is not None:
            rec = dataclasses.replace(rec, sig=self.signer.sign(rec.digest()))
        payload = _pack(rec.to_dict())
        try:
            self.queue.append(payload, seq=seq)
        except QueueError as exc:  # QueueFullError, QueueWriteError: refused, counted with its seq
            self.refused_logged += 1
            kept = self._keep_in_memory(seq, payload)
            if self.refused_logged in (1, 10, 100) or self.refused_logged % 1000 == 0:
                log.error("robot %s: telemetry record %d not written to disk (%d so far): %s; %s", self.robot.id,
                          seq, self.refused_logged, exc,
                          f"kept in memory ({len(self._mem)} records, {self._mem_size} of {self.memory_bytes} "
                          "bytes) until a cloud stores it" if kept else
                          f"DROPPED: the memory buffer is full too ({self.dropped} dropped so far)")
            if not kept:
                return None
        self._wake.set()
        return seq

    def _keep_in_memory(self, seq: int, payload: bytes) -> bool:
        """Keep a record the disk refused in the bounded memory buffer; False (dropped) when it is full."""
        with self._mem_lock:
            if self._mem_size + len(payload) > self.memory_bytes:
                self.dropped += 1
                return False
            self._mem[seq] = payload
            self._mem_size += len(payload)
            self.mem_held += 1
            return True

    def _backlog(self) -> int:
        """Records waiting for a cloud: on disk and in memory."""
        return len(self.queue) + len(self._mem)

    def _pending(self, after: int) -> list[tuple[int, bytes]]:
        """The oldest waiting records with ``seq > after`` (disk queue and memory buffer merged), at most BATCH."""
        batch = self.queue.pending(limit=BATCH, after=after)
        if self._mem:
            with self._mem_lock:
                mem = [(s, p) for s, p in self._mem.items() if s > after]
            batch = sorted(batch + mem)[:BATCH]
        return batch

    def _stored_upto(self, upto: int) -> None:
        """A cloud stored every waiting record with ``seq <= upto``: acknowledge the queue, free the memory.

        The queue drops the records from its pending list before it writes its ``ack`` file; when the
        file system refuses that write (a full disk) the records are still stored, and the file on disk
        lags behind (a restart replays them; the store de-duplicates).
        """
        try:
            self.queue.ack(upto)
        except OSError as exc:
            self.ack_write_errors += 1
            if self.ack_write_errors in (1, 100) or self.ack_write_errors % 10000 == 0:
                log.warning("robot %s: cannot record the ack of seq %d on disk (%s; %d so far); the records are "
                            "stored, a restart would send them again", self.robot.id, upto, exc, self.ack_write_errors)
        if self._mem:
            with self._mem_lock:
                for s in [s for s in self._mem if s <= upto]:
                    self._mem_size -= len(self._mem.pop(s))
                    self.mem_delivered += 1

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
        return failover_order(view.cloud, view.leader)

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
            batch = self._pending(after)
            if not batch:
                continue
            recs = [TelemetryRecord.from_dict(_unpack(p)) for _, p in batch]
            payload = encode_records(recs)
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
                    n = len(batch) if tier != "cloud" else self._stored_prefix(recs, body, node)
                    self._busy_streak = 0
                    self._not_before = 0.0
                    if not n:
                        continue
                    upto = batch[n - 1][0]
                    if tier == "cloud":
                        replayed = sum(1 for s, _ in batch[:n] if s <= self._replay_upto)
                        self._stored_upto(upto)
                        if replayed:
                            self.queue.note_replayed(replayed)
                    else:
                        self._relayed_upto = upto
                    self.acked_by[tier] += n
                    return n
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

    def _stored_prefix(self, recs: list[TelemetryRecord], body: Any, node: str) -> int:
        """How many leading records of a batch the cloud's ack shows stored as sent: the ack's
        ``digests`` must name each record's own digest (a conflict or a refusal stops the prefix; the
        record stays queued, counted once in ``not_acked``, and is never deleted)."""
        digests = body.get("digests") if isinstance(body, dict) else None
        if not isinstance(digests, list) or len(digests) != len(recs):
            self._bad_acks += 1
            if self._bad_acks in (1, 10, 100) or self._bad_acks % 1000 == 0:  # not a line per flush
                log.error("robot %s: cloud %s acked telemetry without per-record digests (%d such answers; a "
                          "cloud older than this robot? upgrade the clouds first); nothing deleted",
                          self.robot.id, node, self._bad_acks)
            return 0
        n = 0
        for r, d in zip(recs, digests):
            if d != r.digest().hex():
                first = r.seq not in self._not_acked
                self._not_acked.add(r.seq)
                if first:
                    why = "refused it" if d is None else "holds other content under its (robot, incarnation, seq)"
                    log.error("robot %s: cloud %s %s for record %d (%s); kept in the queue", self.robot.id, node,
                              why, r.seq, (body.get("refusals") or ["no reason given"])[0])
                break
            n += 1
        return n

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
            linger = self._next_flush - time.monotonic()
            if linger > 0 and not self._draining.is_set():  # gather this period's records into one batch
                self._draining.wait(linger)
                continue
            try:
                sent = self.flush_once()
            except Exception as exc:  # session closing at shutdown
                log.debug("telemetry flush: %s", exc)
                sent = 0
            if sent:
                self._next_flush = time.monotonic() + (0.0 if sent >= BATCH else self.flush_period_s)
            if sent and self._backlog():
                continue
            self._wake.wait(RETRY_PERIOD_S if self._backlog() else 1.0)

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
        return fetch_buffer(self._targets(), self._ask, selector)

    def _drainable(self) -> bool:
        """Whether a live tier could take some of the queued records now."""
        if not self._backlog():
            return False
        targets = self._targets()
        if any(t == "cloud" for t, _ in targets):
            return True
        return bool(targets) and bool(self._pending(self._relayed_upto))

    # -- end
    def summary(self) -> dict:
        """The robot's telemetry counters (``OUT/telemetry.json``).

        ``sent`` counts every seq handed out (refused ones included).
        ``refused`` counts the records the disk queue refused (listed as ranges
        in ``refused_seqs``); each went to the memory buffer (``memory``:
        ``held`` in all, ``delivered`` of them stored by a cloud, ``unsent``
        still there now, which die with the process) unless that was full too
        (``dropped``).  ``lost`` counts the records that can never reach the
        store: refused and not delivered from memory, plus ``lost_seqs`` found
        on disk at start (corruption, records cut off).  ``queued`` counts the
        records on disk waiting for a cloud (kept across restarts).
        """
        st = self.queue.stats()
        with self._mem_lock:
            unsent = len(self._mem)
            mem = {"held": self.mem_held, "delivered": self.mem_delivered, "unsent": unsent,
                   "bytes": self._mem_size, "max_bytes": self.memory_bytes}
        # every refused record was delivered from memory, is still there (dies with the process) or was dropped
        lost = self.dropped + unsent + len(set(st.lost_seqs))
        relayed = len(self.queue.pending(limit=None)) - len(self.queue.pending(limit=None, after=self._relayed_upto))
        return {"robot": self.robot.id, "incarnation": self.incarnation, "not_acked": len(self._not_acked),
                "acks_without_digests": self._bad_acks,
                "sent": st.next_seq - 1, "queued": st.depth, "refused": st.refused,
                "refused_seqs": seq_ranges(st.refused_seqs, limit=20), "lost": lost,
                "dropped": self.dropped, "memory": mem,
                "relayed_unstored": relayed,
                "replayed": st.replayed, "acked_by": dict(self.acked_by), "busy_answers": self.busy_answers,
                "torn_bytes": st.torn_bytes,
                "corruptions": len(st.corruptions), "lost_seqs": st.lost_seqs[:100],
                "error": st.last_error}

    def __enter__(self):
        """``with`` owns the Zenoh resources this object declares: leaving it calls :meth:`close`."""
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self, *, drain_s: float = 2.0, summary_path: str | Path | None = None) -> dict:
        """Stop the flusher (after up to ``drain_s`` of draining), write the summary, close the queue."""
        end = time.monotonic() + drain_s
        self._draining.set()
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
            m = out["memory"]
            log.error("robot %s: %d telemetry record(s) lost (refused by the disk %s, of which %d delivered from "
                      "memory, %d dropped with the memory buffer full, %d still in memory at exit; lost on disk "
                      "%s): %s", self.robot.id, out["lost"], ",".join(out["refused_seqs"]) or "none",
                      m["delivered"], out["dropped"], m["unsent"],
                      ",".join(seq_ranges(out["lost_seqs"], limit=20)) or "none", out["error"] or "see above")
        elif out["refused"]:
            log.warning("robot %s: the disk refused %d telemetry record(s) (%s); all were delivered from memory",
                        self.robot.id, out["refused"], out["error"])
        if out["queued"]:
            log.warning("robot %s: %d telemetry records still queued at exit (kept on disk in %s; "
                        "replayed at the next start)", self.robot.id, out["queued"], self.queue.path)
        self.queue.close()
        return out


# ------------------------------------------------------------ CLI plumbing

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
        def ask(key: str, payload: bytes) -> tuple[str, Any] | None:
            for reply in session.get(key, payload=payload, timeout=deadline_ms / 1e3):
                return ("ok", _unpack(reply.ok.payload.to_bytes())) if reply.ok is not None else ("err", None)
            return None

        return fetch_buffer(failover_order(sorted(alive["cloud"]), sorted(alive["leader"])), ask, selector)
    finally:
        close_session(session)
