"""``scmr tap KEYEXPR``: print every scmr message on a key expression, decoded.

zenoh-python's stock ``z_sub``/``z_get`` print payloads as UTF-8 text and crash on
msgpack.  ``scmr tap`` subscribes (and with ``--get`` also queries) with the
operator's credentials and prints one JSON line per message::

    {"key": "scmr/load/cloud/cloud0", "kind": "load", "bytes": 93, "msg": {...}}

Byte strings inside a message (images, masks) are shown as ``"<bin N bytes>"``, long
lists and strings are cut, and a payload that is neither msgpack nor JSON is shown
as its length and first bytes in hex (``"kind": "undecodable"``), never a crash.
:func:`render` is the pure part (no zenoh).
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from typing import Any

#: At most this many items of a list or map, characters of a string, levels of nesting.
MAX_ITEMS = 16
MAX_CHARS = 200
MAX_DEPTH = 8
#: Bytes of an undecodable payload shown in hex.
HEX_HEAD = 16


def _readable(value: Any, depth: int = 0) -> Any:
    """``value`` made printable as JSON: bytes as their length, big containers cut, bounded depth."""
    if depth > MAX_DEPTH:
        return "<...>"
    if isinstance(value, (bytes, bytearray, memoryview)):
        return f"<bin {len(value)} bytes>"
    if isinstance(value, str):
        return value if len(value) <= MAX_CHARS else value[:MAX_CHARS] + f"...<{len(value)} chars>"
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)  # JSON has no NaN/inf: show them as text
    if isinstance(value, (bool, int, float)) or value is None:
        return value
    if isinstance(value, dict):
        out = {}
        for i, (k, v) in enumerate(value.items()):
            if i == MAX_ITEMS:
                out["..."] = f"<{len(value)} keys>"
                break
            out[k if isinstance(k, str) else repr(_readable(k, depth + 1))] = _readable(v, depth + 1)
        return out
    if isinstance(value, (list, tuple)):
        items = [_readable(v, depth + 1) for v in value[:MAX_ITEMS]]
        if len(value) > MAX_ITEMS:
            items.append(f"<{len(value)} items>")
        return items
    return repr(value)[:MAX_CHARS]


def decode_payload(payload: bytes, encoding: str = "") -> tuple[str, Any]:
    """``(kind, message)`` of one payload (pure, never raises).

    msgpack first (every scmr message), then JSON (``scmr/results/*``); the kind is the
    message's ``"kind"`` (``"msgpack"``/``"json"`` when it has none, ``"undecodable"``
    with ``{"hex": ...}`` when it is neither).
    """
    import msgpack

    data = bytes(payload)
    if "json" not in encoding:
        try:
            msg = msgpack.unpackb(data, raw=False, strict_map_key=False, max_bin_len=len(data),
                                  max_str_len=len(data), max_array_len=len(data), max_map_len=len(data))
            return _kind(msg, "msgpack"), msg
        except Exception:
            pass
    try:
        msg = json.loads(data.decode("utf-8"))
        return _kind(msg, "json"), msg
    except Exception:
        pass
    if "json" in encoding:  # labelled JSON but is not: try msgpack anyway
        try:
            msg = msgpack.unpackb(data, raw=False, strict_map_key=False)
            return _kind(msg, "msgpack"), msg
        except Exception:
            pass
    return "undecodable", {"hex": data[:HEX_HEAD].hex() + ("..." if len(data) > HEX_HEAD else "")}


def _kind(msg: Any, default: str) -> str:
    kind = msg.get("kind") if isinstance(msg, dict) else None
    return kind[:40] if isinstance(kind, str) and kind else default


def render(key: str, payload: bytes, *, encoding: str = "", what: str = "sample") -> str:
    """One readable JSON line for one message on ``key`` (pure, never raises).

    >>> render("scmr/load/cloud/c", b"\\x82\\xa4kind\\xa4load\\xa5image\\xc4\\x03abc")
    '{"key": "scmr/load/cloud/c", "kind": "load", "bytes": 22, "msg": {"kind": "load", "image": "<bin 3 bytes>"}}'
    >>> render("scmr/x", b"\\xc1\\xff")
    '{"key": "scmr/x", "kind": "undecodable", "bytes": 2, "msg": {"hex": "c1ff"}}'
    """
    kind, msg = decode_payload(payload, encoding)
    line: dict[str, Any] = {"key": str(key), "kind": kind, "bytes": len(payload)}
    if what != "sample":
        line["from"] = what
    try:
        line["msg"] = _readable(msg)
        return json.dumps(line, ensure_ascii=False)
    except Exception as exc:  # e.g. RecursionError on a hostile nesting: show the size only
        line["msg"] = f"<unprintable: {type(exc).__name__}>"
        return json.dumps(line, ensure_ascii=False)


#: ``--cfg`` the tap opens its session with: ``open()`` returns once the endpoints it was handed
#: are linked and their declarations received (at most ``scouting/delay``, 500 ms).  scmr's
#: default (false) returns at once, and a ``--get`` sent then reached nobody: 0 replies in 10 of
#: 10 tries, against 10 of 10 with this (docs/ZENOH.md section 14).
OPEN_CFG = "open/return_conditions/connect_scouted:true"


def run_tap(session, keyexpr: str, *, get: bool, count: int | None, duration_s: float | None,
            stop: threading.Event, out=None) -> int:
    """Print messages on ``keyexpr`` until ``count`` were printed, ``duration_s`` passed or ``stop``.

    Returns how many were printed.
    """
    out = out or sys.stdout
    lock = threading.Lock()
    printed = [0]
    done = threading.Event()

    def emit(line: str) -> None:
        with lock:
            if done.is_set():
                return
            print(line, file=out, flush=True)
            printed[0] += 1
            if count is not None and printed[0] >= count:
                done.set()

    def on_sample(sample) -> None:
        try:
            emit(render(str(sample.key_expr), sample.payload.to_bytes(), encoding=str(sample.encoding),
                        what="delete" if str(sample.kind).endswith("DELETE") else "sample"))
        except Exception as exc:  # a callback must never raise into zenoh
            emit(json.dumps({"key": str(getattr(sample, "key_expr", "?")), "kind": "undecodable",
                             "error": type(exc).__name__}))

    t_end = None if duration_s is None else time.monotonic() + duration_s
    sub = session.declare_subscriber(keyexpr, on_sample)
    try:
        if get:
            # the session was opened with open/return_conditions/connect_scouted (OPEN_CFG): its
            # links are up and their queryables known, so the query reaches them
            timeout = 10.0 if t_end is None else max(0.1, t_end - time.monotonic())
            for reply in session.get(keyexpr, timeout=timeout):
                if done.is_set() or stop.is_set():
                    break
                if reply.ok is not None:
                    s = reply.ok
                    emit(render(str(s.key_expr), s.payload.to_bytes(), encoding=str(s.encoding), what="reply"))
                else:
                    e = reply.err
                    emit(render(keyexpr, e.payload.to_bytes(), encoding=str(e.encoding), what="reply-error"))
        while not (done.is_set() or stop.is_set()):
            left = None if t_end is None else t_end - time.monotonic()
            if left is not None and left <= 0:
                break
            stop.wait(0.1 if left is None else min(0.1, left))
    finally:
        done.set()
        try:
            sub.undeclare()
        except Exception:
            pass
    return printed[0]
