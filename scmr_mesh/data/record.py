"""The telemetry record a robot publishes, and its msgpack encoding.

A record is what the operational data store keeps per ``(robot, inc, seq)``:
pose, battery, health and a summary of the robot's recent results.  ``seq``
is assigned by the robot's on-disk queue (1, 2, 3, ... per robot, no gaps), so
the store can tell a duplicate (same ``(robot, inc, seq)`` and the same
:func:`record_digest`) from a new message and a report can tell exactly which
messages are missing.  ``inc`` is the queue folder's *incarnation* (a random
63-bit id chosen when the folder is created, :func:`scmr_mesh.data.queue.folder_incarnation`;
0 for records of older versions), so a robot whose queue was wiped starts a new
history instead of colliding with the stored one.  ``sig`` is the robot's
signature of the digest with its own key (:mod:`scmr_mesh.data.signing`), so a
relay cannot make up another robot's records.
"""

from __future__ import annotations

import copy
import hashlib
import math
import time
from dataclasses import dataclass, field
from typing import Any, Mapping

import msgpack

from scmr_mesh.data.errors import TelemetryError

#: Tiers a record can reach the store through.
TIERS: tuple[str, ...] = ("cloud", "leader", "local")
#: Largest ``seq`` (= ``wire.MAX_SEQ``): ``seq + 1`` always fits a signed 64-bit column.
MAX_SEQ = 2**62
#: Largest incarnation (a signed 64-bit column holds it).
MAX_INC = 2**63 - 1
#: Largest signature kept (an ECDSA P-256 DER signature is 70-72 bytes).
MAX_SIG_BYTES = 256


@dataclass(frozen=True)
class TelemetryRecord:
    """One telemetry message of one robot.

    Parameters
    ----------
    robot : str
        Robot name (non-empty, no ``/``).
    seq : int
        Per-robot sequence number, ``>= 1``.
    t_unix_ns : int
        When the robot took the reading (robot clock, ns since the epoch).
    pose : tuple of 3 float or None
        ``(x, y, theta)`` in metres and radians.
    battery : float or None
        State of charge in ``[0, 1]``.
    health : str
        Free-form status word (``"ok"``, ``"degraded"``, ...).
    results : dict
        Summary of the robot's recent results (msgpack-able values).
    inc : int
        The robot's queue incarnation (0: unknown, a record of an older version).
    sig : bytes or None
        The robot's signature of :func:`record_digest` (None: unsigned).
    """

    robot: str
    seq: int
    t_unix_ns: int
    pose: tuple[float, float, float] | None = None
    battery: float | None = None
    health: str = "ok"
    results: dict[str, Any] = field(default_factory=dict)
    inc: int = 0
    sig: bytes | None = None

    @property
    def key(self) -> tuple[str, int, int]:
        """The record's identity in the store: ``(robot, inc, seq)``."""
        return (self.robot, self.inc, self.seq)

    def digest(self) -> bytes:
        """SHA-256 of the record's content (every field but ``sig``; maps in key order): the identity
        of its content.  The store acks a repeated ``(robot, inc, seq)`` as a duplicate only when
        the digests match, a robot deletes a queued record only when the store's ack names its
        digest, and the robot signs it (:mod:`scmr_mesh.data.signing`).

        Computed once per record object and kept (the record is frozen; its ``results`` map must
        not be changed once it is made): the cloud asks for it three times per record (the
        signature check, the store's insert, the ack; issue 23)."""
        cached = self.__dict__.get("_digest")
        if cached is None:
            body = ["scmr-record/1", self.robot, self.inc, self.seq, self.t_unix_ns,
                    None if self.pose is None else list(self.pose), self.battery, self.health, _canon(self.results)]
            cached = hashlib.sha256(msgpack.packb(body, use_bin_type=True)).digest()
            object.__setattr__(self, "_digest", cached)  # not a field: eq, hash, repr, replace() ignore it
        return cached

    def to_dict(self, *, signed: bool = True) -> dict[str, Any]:
        """The record as a plain dict (``pose`` as a list or None; ``sig`` only when signed and ``signed``)."""
        # what dataclasses.asdict gave (a fresh copy of ``results``), without its per-value dataclass checks
        d = {"robot": self.robot, "seq": self.seq, "t_unix_ns": self.t_unix_ns,
             "pose": list(self.pose) if self.pose is not None else None, "battery": self.battery,
             "health": self.health, "results": _copy(self.results), "inc": self.inc}
        if self.sig is not None and signed:
            d["sig"] = self.sig
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "TelemetryRecord":
        """Validate and build a record from a dict.

        Raises
        ------
        TelemetryError
            A field is missing or has the wrong type; the message names it.
        """
        if not isinstance(d, Mapping):
            raise TelemetryError(f"telemetry record must be a map, got {type(d).__name__}")
        robot = d.get("robot")
        if not isinstance(robot, str) or not robot or "/" in robot:
            raise TelemetryError(f"telemetry 'robot' must be a non-empty name without '/', got {robot!r}")
        seq = d.get("seq")
        if not isinstance(seq, int) or isinstance(seq, bool) or not 1 <= seq <= MAX_SEQ:
            raise TelemetryError(f"telemetry 'seq' must be an integer 1..2^62, got {seq!r}")
        inc = d.get("inc", 0)
        if not isinstance(inc, int) or isinstance(inc, bool) or not 0 <= inc <= MAX_INC:
            raise TelemetryError(f"telemetry 'inc' must be an integer 0..2^63-1, got {inc!r}")
        sig = d.get("sig")
        if sig is not None and (not isinstance(sig, bytes) or not 0 < len(sig) <= MAX_SIG_BYTES):
            raise TelemetryError(f"telemetry 'sig' must be bytes (1..{MAX_SIG_BYTES}) or absent, "
                                 f"got {type(sig).__name__}")
        t = d.get("t_unix_ns", 0)
        if not isinstance(t, int) or isinstance(t, bool) or not -(2**63) <= t < 2**63:
            raise TelemetryError(f"telemetry 't_unix_ns' must be an integer, got {t!r}")
        pose = d.get("pose")
        if pose is not None:
            if isinstance(pose, Mapping):
                pose = (pose.get("x"), pose.get("y"), pose.get("theta"))
            try:
                pose = tuple(float(v) for v in pose)
            except (TypeError, ValueError):
                raise TelemetryError(f"telemetry 'pose' must be [x, y, theta] numbers, got {pose!r}") from None
            if len(pose) != 3 or not all(math.isfinite(v) for v in pose):
                raise TelemetryError(f"telemetry 'pose' must be 3 finite numbers, got {pose!r}")
        battery = d.get("battery")
        if battery is not None:
            if not isinstance(battery, (int, float)) or isinstance(battery, bool) or not math.isfinite(battery):
                raise TelemetryError(f"telemetry 'battery' must be a number, got {battery!r}")
            battery = float(battery)
        health = d.get("health", "ok")
        if not isinstance(health, str):
            raise TelemetryError(f"telemetry 'health' must be a string, got {health!r}")
        results = d.get("results") or {}
        if not isinstance(results, Mapping):
            raise TelemetryError(f"telemetry 'results' must be a map, got {type(results).__name__}")
        return cls(robot, seq, t, pose, battery, health, dict(results), inc, sig)


#: Types :func:`_canon` and :func:`_copy` pass through as they are (immutable scalars).
_SCALARS = frozenset((str, int, float, bool, bytes, type(None)))


def _copy(obj: Any) -> Any:
    """A copy of a record's ``results`` as ``dataclasses.asdict`` makes it (dicts, lists and
    tuples rebuilt, immutable scalars shared, anything else deep-copied), only faster."""
    t = type(obj)
    if t in _SCALARS:
        return obj
    if t is dict:
        return {_copy(k): _copy(v) for k, v in obj.items()}
    if t is list or t is tuple:
        return t(_copy(v) for v in obj)
    if isinstance(obj, dict):
        return type(obj)((_copy(k), _copy(v)) for k, v in obj.items())
    if isinstance(obj, (list, tuple)):
        return type(obj)(_copy(v) for v in obj)
    return copy.deepcopy(obj)


def _canon(obj: Any) -> Any:
    t = type(obj)  # the common exact types first: isinstance(x, typing.Mapping) is an ABC check
    if t in _SCALARS:
        return obj
    if t is dict:
        return [[k, _canon(obj[k])] for k in sorted(obj, key=repr)]
    if t is list or t is tuple:
        return [_canon(v) for v in obj]
    if isinstance(obj, Mapping):
        return [[k, _canon(obj[k])] for k in sorted(obj, key=repr)]
    if isinstance(obj, (list, tuple)):
        return [_canon(v) for v in obj]
    return obj  # scalars (and bytes) as they are


def record_digest(d: Mapping[str, Any]) -> bytes:
    """:meth:`TelemetryRecord.digest` of a record dict (validated first; ``sig`` does not count)."""
    return TelemetryRecord.from_dict(d).digest()


def make_record(
    robot: str,
    seq: int,
    *,
    pose: tuple[float, float, float] | None = None,
    battery: float | None = None,
    health: str = "ok",
    results: Mapping[str, Any] | None = None,
    t_unix_ns: int | None = None,
    inc: int = 0,
) -> TelemetryRecord:
    """Build a validated record, stamping it with the current time by default."""
    return TelemetryRecord.from_dict(
        {
            "robot": robot,
            "seq": seq,
            "t_unix_ns": time.time_ns() if t_unix_ns is None else t_unix_ns,
            "pose": pose,
            "battery": battery,
            "health": health,
            "results": dict(results or {}),
            "inc": inc,
        }
    )


def encode_records(records: list[TelemetryRecord], *, via: str | None = None) -> bytes:
    """msgpack ``{"records": [...], "via": tier}`` for the wire (``via``: relaying tier)."""
    msg: dict[str, Any] = {"records": [r.to_dict() for r in records]}
    if via is not None:
        msg["via"] = via
    return msgpack.packb(msg, use_bin_type=True)


def batch_size(payload: bytes) -> int | None:
    """How many records an :func:`encode_records` payload holds, read from its headers only.

    Cheap (decodes no record), so a tier can refuse an oversized batch before
    decoding it.  None when the payload is not such a map (:func:`decode_batch`
    then says why).
    """
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=max(len(payload), 1))
    try:
        unpacker.feed(payload)
        for _ in range(unpacker.read_map_header()):
            if unpacker.unpack() == "records":
                return int(unpacker.read_array_header())
            unpacker.skip()
    except Exception:  # not a map, truncated...
        return None
    return None


def decode_batch(payload: bytes) -> tuple[list[TelemetryRecord], str | None]:
    """Decode an :func:`encode_records` payload into ``(records, via)``."""
    from scmr_mesh.wire import head_hex

    fix = "send a batch made by scmr_mesh.data.record.encode_records (docs/DATA.md)"
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types
        raise TelemetryError(f"telemetry payload of {len(payload)} bytes is not msgpack (it starts with "
                             f"{head_hex(payload)}; {type(exc).__name__}: {exc}); {fix}") from None
    if not isinstance(msg, dict) or not isinstance(msg.get("records"), list):
        got = type(msg).__name__ if not isinstance(msg, dict) else f"a map with keys {sorted(map(str, msg))[:8]}"
        raise TelemetryError(f"telemetry payload must be a map with a 'records' list, got {got}; {fix}")
    via = msg.get("via")
    if via is not None and via not in TIERS:
        raise TelemetryError(f"telemetry 'via' must be one of {TIERS}, got {via!r}")
    return [TelemetryRecord.from_dict(d) for d in msg["records"]], via


def decode_batch_lenient(payload: bytes) -> tuple[list[TelemetryRecord], str | None, list[str]]:
    """Like :func:`decode_batch`, but one bad record does not refuse the batch: it is left out and its
    problem listed (``(records, via, problems)``); a relayed batch mixes robots, and one robot's bad
    record must not hold up the others' (issue #28 item 4).  Raises only when the batch itself is bad."""
    from scmr_mesh.wire import head_hex

    fix = "send a batch made by scmr_mesh.data.record.encode_records (docs/DATA.md)"
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception as exc:
        raise TelemetryError(f"telemetry payload of {len(payload)} bytes is not msgpack (it starts with "
                             f"{head_hex(payload)}; {type(exc).__name__}: {exc}); {fix}") from None
    if not isinstance(msg, dict) or not isinstance(msg.get("records"), list):
        raise TelemetryError(f"telemetry payload must be a map with a 'records' list; {fix}")
    via = msg.get("via")
    if via is not None and via not in TIERS:
        raise TelemetryError(f"telemetry 'via' must be one of {TIERS}, got {via!r}")
    records, problems = [], []
    for i, d in enumerate(msg["records"]):
        try:
            records.append(TelemetryRecord.from_dict(d))
        except TelemetryError as exc:
            problems.append(f"record {i}: {exc}")
    return records, via, problems


def decode_records(payload: bytes) -> list[TelemetryRecord]:
    """Inverse of :func:`encode_records` (records only); raises :class:`TelemetryError`."""
    return decode_batch(payload)[0]


__all__ = ["MAX_SEQ", "TIERS", "TelemetryRecord", "record_digest", "decode_batch", "decode_records", "decode_batch_lenient", "encode_records",
           "make_record"]
