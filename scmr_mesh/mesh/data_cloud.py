"""The cloud node's data service: telemetry ingest into the ODS, relayed batches, buffer sync
(:class:`CloudData`; see :mod:`scmr_mesh.mesh.data_service`).
"""

from __future__ import annotations

import collections
import concurrent.futures
import json
import logging
import os
from pathlib import Path
from typing import Callable


from scmr_mesh.data.buffer import DataBuffer
from scmr_mesh.data.errors import StoreError, TelemetryError
from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.data.quota import Quota
from scmr_mesh.data.record import TelemetryRecord, decode_batch, decode_batch_lenient
from scmr_mesh.mesh.data_common import IngestGate, Verdict, _answer, _busy, _drop, _payload, _reply, _unpack, buffer_key, check_sender, relay_key, serve_buffer, sync_key, telemetry_key

log = logging.getLogger(__name__)


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
    verifier : scmr_mesh.data.signing.RecordVerifier, optional
        Checks each record's signature against its robot's certificate; records
        without a valid one are refused on their own (the rest of a batch is
        stored).  None (an insecure mesh): records are not checked.
    quota : Quota, optional
        Per-robot records/bytes per second (default :class:`~scmr_mesh.data.quota.Quota`).
    """

    def __init__(self, node: str, ods_path: str | Path, *, params: dict | None = None,
                 gate: IngestGate | None = None, verifier=None, quota: Quota | None = None) -> None:
        self.node = node
        self.gate = gate or IngestGate()
        self.verifier = verifier
        self.quota = quota if quota is not None else Quota()
        #: records refused one by one: {"malformed", "signature", "quota", "conflict"} -> count
        self.refused = {"malformed": 0, "signature": 0, "quota": 0, "conflict": 0}
        self._checker = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"ingest-{node}")
        #: where :meth:`close` writes :meth:`stats` (JSON), or None
        self.stats_path: Path | None = None
        self.ods = OperationalDataStore(ods_path)
        self.buffer = DataBuffer(node)
        for rec in self.ods.latest().values():  # a restarted cloud serves the last states at once
            self.buffer.record_telemetry(rec)
        for k, v in (params or {}).items():
            self.buffer.put(k, v)
        self.ingested = 0
        self._unstored = 0  # batches not stored since the last one that was (one log line per streak)

    def after_ready(self) -> None:
        """Parse the fleet CA on the checker thread once the cloud is ready (kept off its start-up,
        35-45 ms: docs/SECURITY.md); a CA that does not parse is said at once, not at the first record."""
        if self.verifier is not None:
            self._checker.submit(self._warm_verifier)

    def _warm_verifier(self) -> None:
        why = self.verifier.warm()
        if why:
            log.error("cloud %s: %s; every telemetry record will be refused until the cloud restarts with a CA that loads", self.node, why)

    def queryables(self) -> list[tuple[str, Callable]]:
        return [(key, cb) for _, key, cb in self.named_queryables()]

    def named_queryables(self) -> list[tuple[str, str, Callable]]:
        """``(name, key, callback)``: ``telemetry`` and ``relay`` answer later (the store's ack, then
        a drop), ``buffer`` and ``sync`` within the callback."""
        cbs = {"telemetry": self._on_telemetry, "relay": self._on_relay,
               "buffer": serve_buffer(self.buffer, "cloud", self.node), "sync": self._on_sync}
        return [(name, key, cbs[name]) for name, key in cloud_queryable_keys(self.node)]


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
        # Untrusted (issue #28): each record must carry its robot's signature (when a verifier is set);
        # a relayed batch's bad records are refused one by one, the rest stored; per-robot quotas.
        gate = self.gate
        taken = 0
        try:
            payload = _payload(query)
            ans = gate.check_size(payload)
            if ans.verdict is Verdict.BUSY:
                _busy(query, gate, f"cloud {self.node}")
                return
            if not ans.admitted:
                raise TelemetryError(ans.reason)
            nbytes = len(payload)
            if relay:
                records, via, problems = decode_batch_lenient(payload)
                source = via or "leader"
            else:
                records, via = decode_batch(payload)
                problems = []
                check_sender(query.key_expr, records)
                source = "cloud"  # a robot's batch came straight to the cloud, whatever it claims
            del payload
            refusals: list[list] = [[None, None, p] for p in problems]
            self._count("malformed", len(problems))
            if not relay and records and not self.quota.take(records[0].robot, len(records), nbytes):
                # the sender is this robot (the ACL binds its key): charge it before any costly check
                self._over_quota(query, records[0].robot, len(records), nbytes)
                return
            ans = gate.take(len(records))  # reserved until acked: the checks and the store run off zenoh's thread
            if ans.verdict is Verdict.BUSY or not ans.admitted:
                self._unspend(records, relay, nbytes)
                if ans.verdict is Verdict.BUSY:
                    _busy(query, gate, f"cloud {self.node}")
                    return
                raise TelemetryError(ans.reason)
            taken = len(records)
            self._checker.submit(self._check_and_store, query, records, refusals, relay, source, nbytes)
        except Exception as exc:  # not stored: no ack, the sender keeps the records
            gate.release(taken)
            if taken:  # a refusal before the gate was given back there
                self._unspend(records, relay, nbytes)
            self._not_stored(exc)
            _answer(query, {"error": str(exc)}, error=True)
            _drop(query)

    def _check_and_store(self, query, records: list[TelemetryRecord], refusals: list, relay: bool, source: str,
                         nbytes: int) -> None:
        """Signatures (ECDSA verify, ~0.13 ms a record) and relayed quotas, then the store; on the
        checker thread, so zenoh's thread only decodes."""
        try:
            good: list[int] = []  # indices into records
            for i, r in enumerate(records):
                why = None if self.verifier is None else (
                    f"record of {r.robot} is not signed" if r.sig is None else  # refused before any hashing
                    self.verifier.check(r.robot, r.digest(), r.sig))
                if why is None:
                    good.append(i)
                else:
                    refusals.append([r.robot, r.seq, why])
                    self._count("signature")
            fut = self.ods.insert_async([records[i] for i in good], received_from=source)
        except Exception as exc:  # not stored: no ack, the sender keeps the records
            self.gate.release(len(records))
            self._unspend(records, relay, nbytes)
            self._not_stored(exc)
            _answer(query, {"error": str(exc)}, error=True)
            _drop(query)
            return
        if refusals:
            log.warning("cloud %s: refused %d of %d telemetry records (%s), e.g. %s", self.node, len(refusals),
                        len(records) + sum(r[0] is None for r in refusals), "relayed" if relay else "direct",
                        refusals[0])
        fut.add_done_callback(lambda f: self._ack(query, records, good, refusals, f, relay=relay, nbytes=nbytes))

    def _over_quota(self, query, robot: str, n: int, nbytes: int) -> None:
        """A busy answer: the robot keeps its records and retries after the hint."""
        self._count("quota", n)
        wait_ms = round(1e3 * max(0.05, self.quota.retry_after_s(robot, n, nbytes)), 1)
        _answer(query, {"error": f"cloud {self.node}: robot {robot} is over its telemetry quota "
                                 f"({self.quota.records_per_s:g} records/s, {self.quota.bytes_per_s:g} bytes/s); "
                                 "keep the records and retry", "busy": True, "quota": True,
                        "retry_after_ms": wait_ms}, error=True)
        _drop(query)

    def _unspend(self, records: list[TelemetryRecord], relay: bool, nbytes: int) -> None:
        """A robot's own batch that was not stored (busy gate, store error): its quota is given back.
        Relayed batches are charged only once stored (:meth:`_ack`), so there is nothing to undo."""
        if not relay and records:
            self.quota.give_back(records[0].robot, len(records), nbytes)

    def _count(self, why: str, n: int = 1) -> None:
        self.refused[why] += n

    def _ack(self, query, records: list[TelemetryRecord], good: list[int], refusals: list, fut, *,
             relay: bool = False, nbytes: int = 0) -> None:
        self.gate.release(len(records))
        try:
            res = fut.result()
        except Exception as exc:
            self._unspend(records, relay, nbytes)
            self._not_stored(exc)
            _answer(query, {"error": str(exc)}, error=True)
            _drop(query)
            return
        if self._unstored:
            log.warning("cloud %s: telemetry stored again after %d batch(es) were not", self.node, self._unstored)
            self._unstored = 0
        if relay and res.stored:
            # relayed records are charged to their robot once newly stored: forgeries (refused by their
            # signature) and replays of stored records (duplicates) cannot spend a robot's quota
            per = max(1, nbytes // max(1, len(records)))
            for robot, n in collections.Counter(robot for robot, _ in res.stored).items():
                self.quota.charge(robot, n, per * n)
        digests: list[str | None] = [None] * len(records)
        try:
            for j, i in enumerate(good):
                digests[i] = res.digests[j]
                r = records[i]
                if res.digests[j] == r.digest().hex():  # stored or the identical record: never a conflict
                    self.buffer.record_telemetry(r.to_dict(signed=False))
            self._count("conflict", len(res.conflicts))
            self.ingested += len(good)
        finally:
            # "digests": per record of the batch, what the store holds for its (robot, inc, seq): a robot
            # deletes a queued record only when it is its own digest
            _answer(query, {"acked": len(good) - len(res.conflicts), "stored": len(res.stored),
                            "duplicates": len(res.duplicates), "conflicts": len(res.conflicts),
                            "refused": len(refusals), "refusals": refusals[:8], "contiguous": res.contiguous,
                            "digests": digests}, kind="data_ack")
            _drop(query)

    def _not_stored(self, exc: BaseException) -> None:
        """Log a batch not stored.  A store failure: the first of a streak (and every 1000th) at WARNING,
        the rest at DEBUG; anything else (a bad batch) at WARNING each time.

        While the store is down every robot's every retry fails the same way (850 lines per cloud in
        a run whose database died); the store logs its own loss and return once (scmr_mesh.data.ods_pg).
        """
        if not isinstance(exc, StoreError):
            log.warning("cloud %s: telemetry not stored: %s", self.node, exc)
            return
        self._unstored += 1
        n = self._unstored
        log.log(logging.WARNING if n == 1 or n % 1000 == 0 else logging.DEBUG,
                "cloud %s: telemetry not stored%s: %s", self.node, f" ({n} batches in a row)" if n > 1 else "", exc)

    def stats(self) -> dict:
        """Ingest counters: records refused one by one (by reason), quota and gate state."""
        return {"node": self.node, "ingested": self.ingested, "refused": dict(self.refused),
                "quota": self.quota.stats(), "gate": self.gate.stats()}

    def _on_sync(self, query) -> None:
        try:
            req = _unpack(_payload(query)) if _payload(query) else {}
            blob = self.buffer.delta(int(req.get("since", 0)), epoch=req.get("epoch"))
            _reply(query, blob)
        except Exception as exc:
            _answer(query, {"error": str(exc)}, error=True)

    def __enter__(self):
        """``with`` owns the Zenoh resources this object declares: leaving it calls :meth:`close`."""
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if any(self.refused.values()):
            log.warning("cloud %s: telemetry records refused: %s (quota refusals per robot: %s)", self.node,
                        self.refused, self.quota.stats()["refused"])
        if self.stats_path is not None:  # RUN/ingest-<node>.json: the refusals for reports and operators
            try:
                tmp = Path(f"{self.stats_path}.tmp")
                tmp.write_text(json.dumps(self.stats()) + "\n")
                os.replace(tmp, self.stats_path)
            except OSError as exc:
                log.error("cloud %s: cannot write %s (%s); ingest counters: %s", self.node, self.stats_path, exc,
                          json.dumps(self.stats()))
        self._checker.shutdown(wait=True)
        self.ods.close()


# --------------------------------------------------------------------- leader


def cloud_queryable_keys(node: str) -> list[tuple[str, str]]:
    """``(name, key)`` of a cloud node's data queryables (:meth:`CloudData.named_queryables`)."""
    return [("telemetry", telemetry_key("cloud", node)), ("relay", relay_key(node)),
            ("buffer", buffer_key("cloud", node)), ("sync", sync_key(node))]
