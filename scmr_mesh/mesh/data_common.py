"""The data tier on the mesh, shared parts: keys, limits, the ingest gate, replies (split out of
:mod:`scmr_mesh.mesh.data_service`; its docstring describes the whole tier).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from enum import Enum
import time
from typing import Any, Callable

import msgpack

from scmr_mesh import keys
from scmr_mesh.data.buffer import DataBuffer
from scmr_mesh.data.errors import TelemetryError
from scmr_mesh.data.record import TelemetryRecord, batch_size

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


class Verdict(str, Enum):
    """What the ingest gate says of a batch."""

    ADMIT = "admit"          # decode (check_size) / store (take) it
    BUSY = "busy"            # too many records waiting to become durable: a busy answer, the sender retries
    TOO_LARGE = "too_large"  # over the batch limits: refused with the reason, never retried as is


@dataclass(frozen=True)
class GateAnswer:
    """The gate's answer: a :class:`Verdict` and, when refused, why (one line)."""

    verdict: Verdict
    reason: str = ""

    @property
    def admitted(self) -> bool:
        return self.verdict is Verdict.ADMIT


ADMIT = GateAnswer(Verdict.ADMIT)
BUSY = GateAnswer(Verdict.BUSY, "busy")


class IngestGate:
    """Bounds what a tier takes in: batch size, and records waiting to become durable.

    :meth:`check_size` answers whether a batch may be decoded; after decoding,
    :meth:`take` reserves its records; both return a :class:`GateAnswer`
    (admit, busy, or too large with the reason); :meth:`release` returns the
    records once stored or refused.  Thread-safe.

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

    def check_size(self, payload: bytes) -> GateAnswer:
        """Whether a batch may be decoded (refused unread when too large, busy when the tier is full).

        Reads only its length and its headers (:func:`~scmr_mesh.data.record.batch_size`).
        """
        nbytes = len(payload)
        n = batch_size(payload) if nbytes <= self.max_batch_bytes else None
        if nbytes > self.max_batch_bytes or (n is not None and n > self.max_batch_records):
            with self._lock:
                self.too_large += 1
            what = f"{nbytes} bytes" if n is None else f"{n} records ({nbytes} bytes)"
            return GateAnswer(Verdict.TOO_LARGE,
                              f"telemetry batch of {what} exceeds the limit of {self.max_batch_records} records "
                              f"and {self.max_batch_bytes} bytes; send smaller batches")
        with self._lock:
            if self.pending >= self.max_pending:
                self.busy += 1
                return BUSY  # decided before decoding anything
        return ADMIT

    def take(self, n: int) -> GateAnswer:
        """Reserve ``n`` records (admitted), or say why not (busy, too large)."""
        if n > self.max_batch_records:
            with self._lock:
                self.too_large += 1
            return GateAnswer(Verdict.TOO_LARGE, f"telemetry batch of {n} records exceeds {self.max_batch_records}; "
                                                 "send smaller batches")
        with self._lock:
            if self.pending + n > self.max_pending and self.pending > 0:
                self.busy += 1
                return BUSY
            self.pending += n
            self.peak_pending = max(self.peak_pending, self.pending)
        return ADMIT

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
