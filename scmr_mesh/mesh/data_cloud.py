"""The cloud node's data service: telemetry ingest into the ODS, relayed batches, buffer sync
(:class:`CloudData`; see :mod:`scmr_mesh.mesh.data_service`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable


from scmr_mesh.data.buffer import DataBuffer
from scmr_mesh.data.errors import TelemetryError
from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.data.record import TelemetryRecord, decode_batch
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
            ans = gate.check_size(payload)
            if ans.verdict is Verdict.BUSY:
                _busy(query, gate, f"cloud {self.node}")
                return
            if not ans.admitted:
                raise TelemetryError(ans.reason)
            records, via = decode_batch(payload)
            del payload
            if relay:
                source = via or "leader"
            else:
                check_sender(query.key_expr, records)
                source = "cloud"  # a robot's batch came straight to the cloud, whatever it claims
            ans = gate.take(len(records))
            if ans.verdict is Verdict.BUSY:
                _busy(query, gate, f"cloud {self.node}")
                return
            if not ans.admitted:
                raise TelemetryError(ans.reason)
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
                self.buffer.record_telemetry(r.to_dict(signed=False))
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

    def __enter__(self):
        """``with`` owns the Zenoh resources this object declares: leaving it calls :meth:`close`."""
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.ods.close()


# --------------------------------------------------------------------- leader
