"""Local data buffer and the leader's scheduled sync of it.

Thesis 3.3.1/3.3.6: the cloud keeps frequently requested data (latest state
per robot, recent results, shared maps and parameters) in a local data buffer;
the robot leader downloads the buffer in scheduled batch jobs so that it can
serve the same data when the cloud is lost.

Model
-----
* A buffer is a map ``key -> entry``; keys are ``/``-separated, by convention
  ``state/<robot>``, ``results/<robot>``, ``maps/<name>``, ``params/<name>``.
* Each entry carries a *stamp* ``(order, origin)``: ``order`` is the robot's
  ``seq`` for ``state/...`` and a time in ns otherwise.  Merging keeps, per
  key, the entry with the greater stamp (last writer wins), so merge is
  idempotent, commutative and associative: pulling the same batch twice, or
  batches in any order, ends in the same buffer.
* Each buffer also numbers its own changes with a revision ``rev`` inside an
  ``epoch`` (a random id chosen when the buffer is created), so a puller asks
  for "what changed since rev R of epoch E" and gets a small *delta*; when the
  epoch differs (the source restarted) it gets a full *snapshot*.
* Deletions are tombstones (kept, so a delta carries them).

Wire format (msgpack map): ``{"format": "scmr-buffer/1", "epoch": str,
"rev": int, "since": int, "full": bool, "entries": [[key, value, order,
origin, deleted], ...]}``.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import msgpack

from scmr_mesh.data.errors import TelemetryError

log = logging.getLogger(__name__)

FORMAT = "scmr-buffer/1"
#: Results kept per robot under ``results/<robot>``.
RECENT_RESULTS = 16


def state_key(robot: str) -> str:
    """Buffer key of a robot's latest state."""
    return f"state/{robot}"


def results_key(robot: str) -> str:
    """Buffer key of a robot's recent results."""
    return f"results/{robot}"


@dataclass(frozen=True)
class Entry:
    """One buffer entry."""

    value: Any
    order: int
    origin: str
    rev: int
    deleted: bool = False

    @property
    def stamp(self) -> tuple[int, str]:
        return (self.order, self.origin)


@dataclass(frozen=True)
class MergeResult:
    """What :meth:`DataBuffer.merge` did with one batch."""

    applied: int
    ignored: int
    source_epoch: str
    source_rev: int
    full: bool


class DataBuffer:
    """A versioned key-value buffer with snapshot/delta export and LWW merge.

    Parameters
    ----------
    origin : str
        Name of the node that owns this buffer (tie-breaker of equal orders).

    Examples
    --------
    >>> cloud, leader = DataBuffer("cloud"), DataBuffer("leader")
    >>> _ = cloud.put("params/speed", 1.5)
    >>> leader.merge(cloud.snapshot()).applied, leader.merge(cloud.snapshot()).applied
    (1, 0)
    >>> leader.get("params/speed")
    1.5
    """

    def __init__(self, origin: str) -> None:
        self.origin = origin
        self.epoch = secrets.token_hex(8)
        self._rev = 0
        self._entries: dict[str, Entry] = {}
        self._lock = threading.Lock()

    # ---------------------------------------------------------------- writes
    @property
    def rev(self) -> int:
        """This buffer's latest revision (0 when empty)."""
        return self._rev

    def _set(self, key: str, value: Any, order: int, origin: str, deleted: bool) -> bool:
        old = self._entries.get(key)
        if old is not None and old.stamp >= (order, origin):
            return False
        self._rev += 1
        self._entries[key] = Entry(value, order, origin, self._rev, deleted)
        return True

    def put(self, key: str, value: Any, *, order: int | None = None) -> bool:
        """Set ``key`` unless the buffer holds a newer stamp; return whether it changed.

        ``order`` defaults to the current time in ns.
        """
        if not isinstance(key, str) or not key or key.startswith("/") or key.endswith("/"):
            raise TelemetryError(f"buffer key must be a non-empty relative path, got {key!r}")
        with self._lock:
            return self._set(key, value, time.time_ns() if order is None else int(order), self.origin, False)

    def delete(self, key: str, *, order: int | None = None) -> bool:
        """Delete ``key`` (a tombstone that deltas carry)."""
        with self._lock:
            return self._set(key, None, time.time_ns() if order is None else int(order), self.origin, True)

    def record_telemetry(self, record: dict[str, Any], *, keep: int = RECENT_RESULTS) -> None:
        """Update ``state/<robot>`` (ordered by seq) and ``results/<robot>`` from a telemetry dict."""
        robot, seq = record["robot"], int(record["seq"])
        self.put(state_key(robot), dict(record), order=seq)
        if record.get("results"):
            with self._lock:
                old = self._entries.get(results_key(robot))
                recent = [] if old is None or old.deleted else list(old.value)
                if all(r.get("seq") != seq for r in recent):
                    recent.append({"seq": seq, "t_unix_ns": record.get("t_unix_ns"), **record["results"]})
                    recent.sort(key=lambda r: r["seq"])
                    self._set(results_key(robot), recent[-keep:], seq, self.origin, False)

    # ---------------------------------------------------------------- reads
    def get(self, key: str, default: Any = None) -> Any:
        """The value at ``key`` (``default`` if missing or deleted)."""
        e = self._entries.get(key)
        return default if e is None or e.deleted else e.value

    def entry(self, key: str) -> Entry | None:
        return self._entries.get(key)

    def items(self, prefix: str = "") -> dict[str, Any]:
        """Live ``key -> value`` whose key starts with ``prefix``."""
        with self._lock:
            return {k: e.value for k, e in sorted(self._entries.items())
                    if k.startswith(prefix) and not e.deleted}

    def query(self, selector: str) -> dict[str, Any]:
        """Items matching a selector: an exact key, ``prefix/**``, ``prefix/*`` or ``**``."""
        if selector in ("", "**", "*"):
            return self.items()
        if selector.endswith("/**"):
            return self.items(selector[:-2])
        if selector.endswith("/*"):
            base = selector[:-1]
            return {k: v for k, v in self.items(base).items() if "/" not in k[len(base):]}
        v = self.get(selector, _MISSING)
        return {} if v is _MISSING else {selector: v}

    # ---------------------------------------------------------------- export / merge
    def delta(self, since: int = 0, *, epoch: str | None = None) -> bytes:
        """Entries changed after revision ``since`` of ``epoch`` (a full snapshot if the epoch differs)."""
        with self._lock:
            full = epoch != self.epoch or since <= 0 or since > self._rev
            since = 0 if full else since
            entries = [[k, e.value, e.order, e.origin, e.deleted]
                       for k, e in sorted(self._entries.items(), key=lambda kv: kv[1].rev) if e.rev > since]
            msg = {"format": FORMAT, "epoch": self.epoch, "rev": self._rev, "since": since,
                   "full": full, "entries": entries}
        return msgpack.packb(msg, use_bin_type=True, default=_default)

    def snapshot(self) -> bytes:
        """Every entry (tombstones included)."""
        return self.delta(0)

    def merge(self, blob: bytes) -> MergeResult:
        """Merge a snapshot or delta from another buffer (idempotent).

        Raises
        ------
        TelemetryError
            ``blob`` is not a buffer batch.
        """
        msg = decode_batch(blob)
        applied = ignored = 0
        with self._lock:
            for key, value, order, origin, deleted in msg["entries"]:
                if self._set(key, value, int(order), str(origin), bool(deleted)):
                    applied += 1
                else:
                    ignored += 1
        return MergeResult(applied, ignored, msg["epoch"], msg["rev"], msg["full"])


_MISSING = object()


def _default(obj: Any) -> Any:
    if isinstance(obj, tuple):
        return list(obj)
    raise TypeError(f"buffer values must be msgpack-able, got {type(obj).__name__}")


def decode_batch(blob: bytes) -> dict[str, Any]:
    """Decode and check a buffer batch (:class:`TelemetryError` when malformed)."""
    try:
        msg = msgpack.unpackb(blob, raw=False, strict_map_key=False)
    except Exception as exc:
        raise TelemetryError(f"buffer batch is not msgpack ({len(blob)} bytes): {exc}") from None
    if not isinstance(msg, dict) or msg.get("format") != FORMAT:
        got = msg.get("format") if isinstance(msg, dict) else type(msg).__name__
        raise TelemetryError(f"buffer batch must have format {FORMAT!r}, got {got!r}")
    entries = msg.get("entries")
    if not isinstance(entries, list) or not all(isinstance(e, list) and len(e) == 5 for e in entries):
        raise TelemetryError("buffer batch 'entries' must be a list of [key, value, order, origin, deleted]")
    return msg


@dataclass
class SyncStats:
    """Counters of a :class:`BufferSync`."""

    pulls: int = 0
    failures: int = 0
    applied: int = 0
    full_pulls: int = 0
    source_epoch: str | None = None
    source_rev: int = 0
    last_ok_unix_ns: int = 0


class BufferSync:
    """The leader's scheduled batch pull of the cloud's buffer.

    Parameters
    ----------
    buffer : DataBuffer
        The leader's copy.
    fetch : callable ``(epoch or None, since) -> bytes or None``
        Asks the source for a delta; returns None when the source is
        unreachable (the Zenoh glue passes a query here; tests pass a function).
    period_s : float
        Seconds between pulls when running in the background.
    """

    def __init__(self, buffer: DataBuffer, fetch: Callable[[str | None, int], bytes | None], *,
                 period_s: float = 1.0) -> None:
        if not period_s > 0:
            raise TelemetryError(f"sync period must be > 0 s, got {period_s!r}")
        self.buffer = buffer
        self.fetch = fetch
        self.period_s = float(period_s)
        self.stats = SyncStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def pull_once(self) -> MergeResult | None:
        """One pull: fetch a delta since the last seen revision and merge it."""
        st = self.stats
        st.pulls += 1
        try:
            blob = self.fetch(st.source_epoch, st.source_rev)
        except Exception as exc:  # a failed pull is retried at the next period
            log.warning("buffer sync: fetch failed: %s", exc)
            blob = None
        if blob is None:
            st.failures += 1
            return None
        try:
            res = self.buffer.merge(blob)
        except TelemetryError as exc:
            log.error("buffer sync: bad batch from the source: %s", exc)
            st.failures += 1
            return None
        st.applied += res.applied
        st.full_pulls += int(res.full)
        st.source_epoch, st.source_rev = res.source_epoch, res.source_rev
        st.last_ok_unix_ns = time.time_ns()
        return res

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.pull_once()
            self._stop.wait(self.period_s)

    def start(self) -> "BufferSync":
        """Pull every ``period_s`` in a daemon thread until :meth:`stop`."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="buffer-sync", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None


__all__ = [
    "FORMAT", "BufferSync", "DataBuffer", "Entry", "MergeResult", "SyncStats", "decode_batch",
    "results_key", "state_key",
]
