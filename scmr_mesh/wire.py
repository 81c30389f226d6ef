"""Versioned msgpack messages of the scmr mesh, validated against ``schemas/``.

Pure module (no Zenoh, no rerun).  Every message is a msgpack map with a wire
version ``"v"`` (:data:`WIRE_VERSION`) and a ``"kind"``: ``request``,
``reply``, ``error``, ``telemetry``, ``load`` or ``candidate``.  Each kind is described by
``schemas/<kind>.schema.json`` (JSON Schema 2020-12, plus one extra keyword,
``x-bytes``, for msgpack ``bin`` fields).  Both ends validate: the service
checks requests before admitting them, the robot checks replies before it
trusts them.  A good message is checked by :mod:`scmr_mesh._schema` (a few
microseconds, no jsonschema import); jsonschema, the reference, is loaded
only to explain a message that fails.

Example
-------
>>> req = make_request("r1", 7, b"\\x89PNG....", encoding="png")
>>> decode(encode(req), kind="request")["seq"]
7

Errors
------
:class:`WireProblem` (a :class:`~scmr_mesh.errors.WireError`) carries a
``code`` from :data:`ERROR_CODES` that the service sends back in an error
reply: ``malformed`` (not msgpack / not a map / schema violation),
``oversized`` (payload above the size limit), ``wrong_version``.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import re
import threading
import time
from pathlib import Path
from typing import Any, Mapping

import msgpack

from scmr_mesh.errors import WireError

#: Version written in every message; a peer rejects other versions.
WIRE_VERSION = 1
#: Message kinds, each with ``schemas/<kind>.schema.json``.
KINDS: tuple[str, ...] = ("request", "reply", "error", "telemetry", "load", "candidate", "receipt")
#: Codes of error replies.
ERROR_CODES: tuple[str, ...] = (
    "malformed", "oversized", "wrong_version", "busy", "internal", "unavailable", "expired", "forbidden",
    "duplicate",
)
#: Zenoh encoding of every scmr message (msgpack maps); JSON payloads (``scmr/results/*``)
#: declare ``application/json``, so generic Zenoh tools can show either.
MSGPACK_ENCODING = "application/msgpack"
JSON_ENCODING = "application/json"
#: Default largest request payload a service accepts (bytes): a 4K raw RGB
#: frame is 24.9 MB, so 32 MiB admits any sane frame and bounds memory.
MAX_REQUEST_BYTES = 32 * 1024 * 1024
#: Encodings a request may carry.
ENCODINGS: tuple[str, ...] = ("png", "jpeg", "raw")
#: Pipeline modes.
MODES: tuple[str, ...] = ("best", "thesis")

#: Largest election term a candidacy may carry (its schema's ``maximum``): far below
#: 2**63, so a candidate's ``term + 1`` always encodes and stays an exact float.
MAX_TERM = 2**53
#: Largest sequence number of a request, reply or telemetry message (schemas' ``maximum``):
#: ``seq + 1`` still encodes as a msgpack int64.
MAX_SEQ = 2**62
#: Bytes of a frame's digest (SHA-256 of the request's ``image``, its first 16 bytes): a request carries it as
#: ``digest``, every reply and error echoes it, and a robot accepts only a reply whose robot,
#: seq and digest are those of the request it sent (:func:`reply_mismatch`).
DIGEST_BYTES = 16
#: Largest magnitude of any number in a message, int or float (msgpack int64; clocks in ns fit).
MAX_WIRE_INT = 2**63 - 1
#: Default size caps of the small control messages (bytes), checked before parsing:
#: a real candidacy or load message is about 200-300 bytes.
MAX_BYTES: dict[str, int] = {"candidate": 4096, "load": 4096, "telemetry": 64 * 1024, "error": 16 * 1024,
                             "receipt": 4096}

SCHEMA_DIR = Path(__file__).resolve().parents[1] / "schemas"

log = logging.getLogger(__name__)


class WireProblem(WireError):
    """A message failed to decode or validate.

    Attributes
    ----------
    code : str
        One of :data:`ERROR_CODES` (``malformed``, ``oversized``, ``wrong_version``).
    """

    def __init__(self, code: str, message: str, *, partial: Mapping[str, Any] | None = None) -> None:
        super().__init__(message)
        self.code = code
        #: The decoded map when the payload was msgpack but broke the schema: its ``robot``
        #: and ``seq`` can still be echoed in the error reply (:func:`make_error`).
        self.partial = partial


# ---------------------------------------------------------------- validation
def _bytes_keyword(validator, spec, instance, schema):  # jsonschema keyword
    from jsonschema import ValidationError

    if not isinstance(instance, (bytes, bytearray)):
        yield ValidationError(f"expected msgpack bin (bytes), got {type(instance).__name__}")
        return
    if isinstance(spec, dict):
        lo = spec.get("minLength")
        hi = spec.get("maxLength")
        if lo is not None and len(instance) < lo:
            yield ValidationError(f"{len(instance)} bytes, fewer than the minimum {lo}")
        if hi is not None and len(instance) > hi:
            yield ValidationError(f"{len(instance)} bytes, more than the maximum {hi}")


def load_schema(kind: str) -> dict:
    """Return the parsed JSON Schema of message ``kind``.

    Raises
    ------
    WireError
        When ``kind`` is unknown or its schema file is missing.
    """
    if kind not in KINDS:
        raise WireError(f"unknown message kind {kind!r}; expected one of {KINDS}")
    path = SCHEMA_DIR / f"{kind}.schema.json"
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise WireError(f"schema file {path} unreadable ({exc}); reinstall scmr-mesh") from exc


@functools.lru_cache(maxsize=None)
def fast_check(kind: str):
    """``check(message) -> bool`` for ``kind`` (:mod:`scmr_mesh._schema`), or None
    when the schema needs a keyword it lacks (then only jsonschema is used)."""
    from scmr_mesh import _schema

    try:
        return _schema.compile_check(load_schema(kind))
    except _schema.Unsupported:
        return None


@functools.lru_cache(maxsize=None)
def validator(kind: str):
    """Compiled (cached) jsonschema validator of message ``kind`` (explains failures)."""
    from jsonschema import Draft202012Validator, validators

    cls = validators.extend(Draft202012Validator, validators={"x-bytes": _bytes_keyword})
    schema = load_schema(kind)
    Draft202012Validator.check_schema(schema)
    return cls(schema)


@functools.lru_cache(maxsize=None)
def strict_check(kind: str):
    """Like :func:`fast_check` with ``strict=True``: integers real ints, numbers finite."""
    from scmr_mesh import _schema

    return _schema.compile_check(load_schema(kind), strict=True)


def warm() -> None:
    """Compile every fast check now (about 1 ms); jsonschema loads only to explain a bad message."""
    for kind in KINDS:
        fast_check(kind)
        strict_check(kind)


def insane_number(value: Any, schema: Any = None, path: str = "") -> str | None:
    """Path and reason of the first number in ``value`` another node must not send
    (NaN or inf anywhere, a number beyond :data:`MAX_WIRE_INT`, a float where
    ``schema`` wants an integer), or None when all are sane."""
    if isinstance(value, bool) or value is None or isinstance(value, (str, bytes, bytearray)):
        return None
    if isinstance(value, float):
        if not math.isfinite(value):
            return f"{path or '(top level)'} is {value!r}, not a finite number"
        if abs(value) > MAX_WIRE_INT:
            return f"{path or '(top level)'} = {value!r} is beyond {MAX_WIRE_INT}"
        if isinstance(schema, dict):
            types = schema.get("type")
            types = types if isinstance(types, list) else [types]
            if "integer" in types and "number" not in types:
                return f"{path or '(top level)'} is the float {value!r}, not an integer"
        return None
    if isinstance(value, int):
        if abs(value) > MAX_WIRE_INT:
            return f"{path or '(top level)'} = {value} is beyond {MAX_WIRE_INT}"
        return None
    sub = schema if isinstance(schema, dict) else {}
    if isinstance(value, dict):
        props = sub.get("properties") or {}
        for k, v in value.items():
            why = insane_number(v, props.get(k, sub.get("additionalProperties")), f"{path}/{k}" if path else str(k))
            if why:
                return why
    elif isinstance(value, list):
        for i, v in enumerate(value):
            why = insane_number(v, sub.get("items"), f"{path}/{i}" if path else str(i))
            if why:
                return why
    return None


def validate(message: Mapping[str, Any], kind: str) -> Mapping[str, Any]:
    """Check ``message`` against the schema of ``kind``; return it unchanged.

    Raises
    ------
    WireProblem
        ``malformed`` naming the first offending field, or ``wrong_version``.
    """
    if not isinstance(message, Mapping):
        raise WireProblem("malformed", f"a {kind} must be a map, got {type(message).__name__}")
    v = message.get("v")
    if v != WIRE_VERSION:
        raise WireProblem(
            "wrong_version",
            f"{kind} has wire version {v!r}, this peer speaks {WIRE_VERSION}; "
            "run the same scmr-mesh version on every peer",
            partial=message,
        )
    if strict_check(kind)(message) and insane_number(message) is None:
        return message
    val = validator(kind)
    if val.is_valid(message):
        # jsonschema takes NaN, inf and 1e300 as an "integer"; another node's message may not
        why = insane_number(message, load_schema(kind)) or "a number is not finite or not a real integer"
        raise WireProblem("malformed", f"{kind} field {why} (see schemas/{kind}.schema.json)", partial=message)
    err = min(val.iter_errors(message), key=lambda e: len(e.path))
    where = "/".join(str(p) for p in err.absolute_path) or "(top level)"
    raise WireProblem("malformed", f"{kind} field {where}: {err.message[:300]} (see schemas/{kind}.schema.json)",
                      partial=message)


# ------------------------------------------------------------ encode / decode
def encode(message: Mapping[str, Any]) -> bytes:
    """Serialise a message map to msgpack bytes (no validation)."""
    return msgpack.packb(message, use_bin_type=True)


#: Messages :func:`decode` refused, by (expected kind, code); see :func:`rejected`.
_REJECTED: dict[tuple[str, str], int] = {}
_REJECTED_LOCK = threading.Lock()
_LAST_WARNING: dict[str, float] = {}
#: At most one WARNING per expected kind per this many seconds (the rest only counted).
WARN_EVERY_S = 10.0


def rejected() -> dict[str, dict[str, int]]:
    """How many received messages this process refused: ``{kind: {code: count}}``."""
    with _REJECTED_LOCK:
        out: dict[str, dict[str, int]] = {}
        for (k, code), n in _REJECTED.items():
            out.setdefault(k, {})[code] = n
        return out


def _count_rejection(kind: str, exc: WireProblem) -> None:
    now = time.monotonic()
    with _REJECTED_LOCK:
        _REJECTED[(kind, exc.code)] = _REJECTED.get((kind, exc.code), 0) + 1
        total = sum(n for (k, _), n in _REJECTED.items() if k == kind)
        last = _LAST_WARNING.get(kind)
        loud = last is None or now - last >= WARN_EVERY_S
        if loud:
            _LAST_WARNING[kind] = now
    if loud:
        log.warning("dropped a %s message (%s): %s [%d %s message(s) refused so far]",
                    kind, exc.code, str(exc)[:300], total, kind)


def decode(data: bytes | bytearray, *, kind: str | tuple[str, ...], max_bytes: int | None = None) -> dict:
    """Parse and validate msgpack ``data`` as a message of ``kind``.

    Every refused message is counted (:func:`rejected`) and logged at WARNING,
    at most once per kind every :data:`WARN_EVERY_S` seconds.

    Parameters
    ----------
    data : bytes
        The payload.
    kind : str or tuple of str
        Expected kind(s); the message's own ``kind`` picks the schema.
    max_bytes : int, optional
        Reject larger payloads with code ``oversized`` before parsing; default
        :data:`MAX_BYTES` of the (first) kind, no cap for requests and replies, and
        then the cap of the kind the message turned out to be (a receipt where a
        reply or a receipt may come).

    Returns
    -------
    dict
        The validated message.

    Raises
    ------
    WireProblem
        ``oversized``, ``malformed`` or ``wrong_version``.
    """
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    try:
        return _decode(data, kinds, max_bytes if max_bytes is not None else MAX_BYTES.get(kinds[0]),
                       per_kind=max_bytes is None)
    except WireProblem as exc:
        _count_rejection(kinds[0], exc)
        raise


def _decode(data: bytes | bytearray, kinds: tuple[str, ...], max_bytes: int | None, per_kind: bool = False) -> dict:
    if max_bytes is not None and len(data) > max_bytes:
        raise WireProblem(
            "oversized",
            f"payload of {len(data)} bytes exceeds the limit of {max_bytes} bytes; "
            + ("send a smaller or compressed (png/jpeg) frame" if kinds[0] == "request"
               else f"a {kinds[0]} message is a few hundred bytes"),
        )
    fix = _FIX.get(kinds[0], f"send a msgpack map made by scmr_mesh.wire (schemas/{kinds[0]}.schema.json)")
    try:
        msg = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises many types
        why = type(exc).__name__ + (f": {str(exc)[:120]}" if str(exc) else "")
        raise WireProblem("malformed", f"payload of {len(data)} bytes is not msgpack (it starts with "
                          f"{head_hex(data)}; {why}); {fix}") from None
    if not isinstance(msg, dict):
        raise WireProblem("malformed", f"payload must be a msgpack map, got a msgpack {type(msg).__name__} "
                          f"({len(data)} bytes, starting with {head_hex(data)}); {fix}")
    got = msg.get("kind")
    if got not in kinds:
        # check the version first: a future peer may rename kinds
        if msg.get("v") != WIRE_VERSION:
            validate(msg, kinds[0])
        raise WireProblem("malformed", f"expected a message of kind {'/'.join(kinds)}, got kind "
                          f"{str(got)[:60]!r}; {fix}", partial=msg)
    cap = MAX_BYTES.get(got) if per_kind and got != kinds[0] else None
    if cap is not None and len(data) > cap:  # e.g. a "receipt" read where a reply or a receipt may come
        raise WireProblem("oversized", f"payload of {len(data)} bytes exceeds the limit of {cap} bytes; "
                          f"a {got} message is a few hundred bytes")
    validate(msg, got)
    return msg


#: What a sender should do instead, per expected kind (in "malformed" messages).
_FIX = {
    "request": "send a msgpack map made by scmr_mesh.wire.make_request (docs/protocol.md, "
               "schemas/request.schema.json)",
}


def head_hex(data: bytes | bytearray, n: int = 16) -> str:
    """The first bytes of a payload as hex, for error messages (``0x89504e47...``)."""
    if not data:
        return "nothing (0 bytes)"
    return "0x" + bytes(data[:n]).hex() + ("..." if len(data) > n else "")


# ---------------------------------------------------------------- factories
def now_ns() -> int:
    """Wall-clock time in integer nanoseconds since the Unix epoch."""
    return time.time_ns()


def frame_digest(image: bytes | bytearray | memoryview) -> bytes:
    """The request's ``digest`` of a frame: the first :data:`DIGEST_BYTES` bytes of SHA-256 of its encoded bytes.

    SHA-256, not BLAKE2b: with the CPU's SHA instructions (x86 SHA-NI, ARMv8 crypto) it ran at
    1.7 GB/s against BLAKE2b's 0.8 GB/s here (docs/protocol.md "Frame digest").

    >>> frame_digest(b"abc").hex()
    'ba7816bf8f01cfea414140de5dae2223'
    """
    return hashlib.sha256(image).digest()[:DIGEST_BYTES]


def reply_mismatch(asked: Mapping[str, Any], reply: Mapping[str, Any]) -> str | None:
    """Why ``reply`` is not the answer to the request ``asked`` (None: it is).

    A reply answers a request only when its ``robot``, ``seq`` and ``digest`` are
    the request's: a replayed earlier reply, one for another frame or robot, or
    one without a digest (a server outside the project) is not.  Pure.

    >>> req = make_request("r1", 7, b"frame")
    >>> rep = {"robot": "r1", "seq": 7, "digest": frame_digest(b"frame")}
    >>> reply_mismatch(req, rep) is None, reply_mismatch(req, {**rep, "seq": 1007})
    (True, 'reply answers frame 1007, this request is frame 7')
    """
    if reply.get("robot") != asked.get("robot"):
        return f"reply answers robot {str(reply.get('robot'))[:64]!r}, this request is robot {asked.get('robot')!r}"
    if reply.get("seq") != asked.get("seq"):
        return f"reply answers frame {reply.get('seq')}, this request is frame {asked.get('seq')}"
    got, want = reply.get("digest"), asked.get("digest")
    if not isinstance(got, (bytes, bytearray)):
        return "reply echoes no frame digest (not a server of this version): not taken as this frame's"
    if not isinstance(want, (bytes, bytearray)) or bytes(got) != bytes(want):
        return (f"reply echoes frame digest {bytes(got).hex()[:16]}, this frame's is "
                f"{bytes(want).hex()[:16] if isinstance(want, (bytes, bytearray)) else 'unknown'}: "
                "an answer to another frame (a replay)")
    return None


def asked_of(request: Mapping[str, Any]) -> dict:
    """What a reply must echo of ``request``: ``{"robot", "seq", "digest"}`` (:func:`reply_mismatch`)."""
    return {"robot": request.get("robot"), "seq": request.get("seq"), "digest": request.get("digest")}


def make_request(
    robot: str,
    seq: int,
    image: bytes,
    *,
    encoding: str = "png",
    shape: tuple[int, int, int] | None = None,
    priority: int = 0,
    mode: str = "best",
    sent_unix_ns: int | None = None,
    attempt: int = 0,
    deadline_ms: float | None = None,
    digest: bytes | None = None,
    receipt: bool = False,
) -> dict:
    """Build a request message (see ``schemas/request.schema.json``).

    Parameters
    ----------
    robot : str
        Robot id.
    seq : int
        Per-robot sequence number, >= 0.
    image : bytes
        PNG/JPEG bytes, or raw RGB uint8 rows of ``shape`` (H, W, 3).
    encoding, shape, priority, mode, sent_unix_ns, attempt
        As in the schema; ``sent_unix_ns`` defaults to now.
    deadline_ms : float, optional
        How long the robot waits for this attempt; a service skips the work
        when no worker got to it in time (error ``expired``).
    receipt : bool
        Ask the service for a :func:`make_receipt` at once when the request
        arrives, before its answer (left out of the message when False).
    """
    msg = {
        "v": WIRE_VERSION,
        "kind": "request",
        "robot": robot,
        "seq": int(seq),
        "priority": int(priority),
        "encoding": encoding,
        "shape": list(shape) if shape is not None else None,
        "image": bytes(image),
        "digest": bytes(digest) if digest is not None else frame_digest(image),
        "sent_unix_ns": int(sent_unix_ns if sent_unix_ns is not None else now_ns()),
        "attempt": int(attempt),
        "mode": mode,
    }
    if deadline_ms is not None:
        msg["deadline_ms"] = float(deadline_ms)
    if receipt:
        msg["receipt"] = True
    return msg


def make_receipt(request: Mapping[str, Any], *, served_by: str, tier: str) -> dict:
    """Build a receipt (``schemas/receipt.schema.json``): ``request`` has reached ``served_by``.

    A service sends it at once when a request that asked for it (``receipt``)
    has arrived, decoded and been taken in; its answer follows on the same query.
    A robot that gets no receipt within a delay learnt from its tier's recent
    receipts hedges (the copy or the node is lost), far sooner than the
    answer's own delay allows (docs/R2R.md "Hedged requests").

    >>> r = make_receipt(make_request("r1", 7, b"frame"), served_by="cloud", tier="cloud")
    >>> r["kind"], r["seq"], reply_mismatch({"robot": "r1", "seq": 7, "digest": frame_digest(b"frame")}, r)
    ('receipt', 7, None)
    """
    return {"v": WIRE_VERSION, "kind": "receipt", "robot": request["robot"], "seq": request["seq"],
            **_digest_of(request), "served_by": served_by, "tier": tier}


def make_reply(
    request: Mapping[str, Any],
    *,
    mask_png: bytes,
    shape: tuple[int, int],
    threshold: int,
    timings_ms: Mapping[str, float],
    served_by: str,
    tier: str,
    server_ms: float,
    queue_ms: float = 0.0,
    confidence: float | None = None,
    abstained: str | None = None,
) -> dict:
    """Build a reply message answering ``request``: its ``robot``, ``seq`` and ``digest`` echoed.

    ``confidence`` (clamped to [0, 1]) and ``abstained`` are optional (issue 27): left out of
    the message when None, so replies stay valid for readers of the older schema's fields.
    """
    msg = {
        "v": WIRE_VERSION,
        "kind": "reply",
        "robot": request["robot"],
        "seq": request["seq"],
        **_digest_of(request),
        "mask_png": bytes(mask_png),
        "shape": [int(shape[0]), int(shape[1])],
        "threshold": int(threshold),
        "timings_ms": {str(k): float(max(0.0, v)) for k, v in timings_ms.items()},
        "served_by": served_by,
        "tier": tier,
        "server_ms": float(max(0.0, server_ms)),
        "queue_ms": float(max(0.0, queue_ms)),
    }
    if confidence is not None:
        msg["confidence"] = float(min(1.0, max(0.0, confidence)))
    if abstained is not None:
        msg["abstained"] = str(abstained)[:64]
    return msg


_ROBOT_ID = re.compile(r"[A-Za-z0-9_.\-]{1,64}")


def _digest_of(request: Mapping[str, Any] | None) -> dict:
    """``{"digest": ...}`` to echo from ``request`` (empty when it carries no well-formed one)."""
    d = request.get("digest") if isinstance(request, Mapping) else None
    return {"digest": bytes(d)} if isinstance(d, (bytes, bytearray)) and len(d) == DIGEST_BYTES else {}


def make_error(
    code: str,
    message: str,
    *,
    served_by: str,
    tier: str,
    request: Mapping[str, Any] | None = None,
    retry_after_ms: float | None = None,
) -> dict:
    """Build an error message (code from :data:`ERROR_CODES`)."""
    if code not in ERROR_CODES:
        raise ValueError(f"error code must be one of {ERROR_CODES}, got {code!r}")
    robot = request.get("robot") if isinstance(request, Mapping) else None
    seq = request.get("seq") if isinstance(request, Mapping) else None
    msg = {
        "v": WIRE_VERSION,
        "kind": "error",
        "code": code,
        "message": str(message)[:2000],
        # echoed whenever they were readable (also from a request that broke the schema elsewhere)
        "robot": robot if isinstance(robot, str) and _ROBOT_ID.fullmatch(robot) else None,
        "seq": seq if isinstance(seq, int) and not isinstance(seq, bool) and 0 <= seq < 2**63 else None,
        "served_by": served_by,
        "tier": tier,
        **_digest_of(request),
    }
    if retry_after_ms is not None:
        msg["retry_after_ms"] = float(retry_after_ms)
    return msg


def make_telemetry(
    robot: str,
    seq: int,
    *,
    pose: Mapping[str, float],
    battery: float,
    health: str,
    results: Mapping[str, Any],
    t_unix_ns: int | None = None,
) -> dict:
    """Build a telemetry message (see ``schemas/telemetry.schema.json``)."""
    return {
        "v": WIRE_VERSION,
        "kind": "telemetry",
        "robot": robot,
        "seq": int(seq),
        "t_unix_ns": int(t_unix_ns if t_unix_ns is not None else now_ns()),
        "pose": {k: float(pose[k]) for k in ("x", "y", "theta")},
        "battery": float(min(1.0, max(0.0, battery))),
        "health": health,
        "results": dict(results),
    }


def make_load(node: str, tier: str, *, workers: int, inflight: int, served: int,
              clock_hz: float | None = None, power_w: float | None = None) -> dict:
    """Build a load message (see ``schemas/load.schema.json``).

    ``clock_hz`` and ``power_w`` (the server's energy profile) let robots
    weigh a peer robot with the energy model before sending it a frame.
    """
    msg = {
        "v": WIRE_VERSION,
        "kind": "load",
        "node": node,
        "tier": tier,
        "workers": int(workers),
        "inflight": int(inflight),
        "served": int(served),
        "t_unix_ns": now_ns(),
    }
    if clock_hz is not None:
        msg["clock_hz"] = float(clock_hz)
    if power_w is not None:
        msg["power_w"] = float(power_w)
    return msg


def make_candidate(node: str, *, term: int, leading: bool, clock_hz: float, power_w: float | None,
                   battery: float, load: float, since_unix_ns: int | None = None,
                   capability: str = "", follows: str | None = None) -> dict:
    """Build a candidacy message of the R2R election (``schemas/candidate.schema.json``).

    Parameters
    ----------
    node : str
        The candidate.
    term : int
        The highest term it has seen (its own term while it leads).
    leading : bool
        Whether it holds the lead now.
    clock_hz, power_w : float
        Capability from its energy profile (``power_w`` None when unknown).
    battery : float
        0..1.
    load : float
        In-flight requests per worker.
    since_unix_ns : int, optional
        When it took the lead (while leading).
    capability : str
        Where the capability came from (profile name or ``host``).
    follows : str, optional
        The leader this candidate follows now (None while it leads or sees none).
    """
    return {
        "v": WIRE_VERSION,
        "kind": "candidate",
        "node": node,
        "term": int(term),
        "leading": bool(leading),
        "since_unix_ns": None if since_unix_ns is None else int(since_unix_ns),
        "clock_hz": float(clock_hz),
        "power_w": None if power_w is None else float(power_w),
        "battery": float(min(1.0, max(0.0, battery))),
        "load": float(max(0.0, load)),
        "capability": str(capability),
        "follows": follows,
        "t_unix_ns": now_ns(),
    }
