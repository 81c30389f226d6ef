"""Per-identity telemetry quotas: records and bytes per second, with a burst (issue #28 item 6).

One robot certificate could store ~20,000 records a second (198,784 records,
45.9 MB in 10 s) and fill the store for everyone.  A tier (the cloud's store,
the leader's relay) keeps one token bucket per identity (the robot a record
belongs to): ``records_per_s`` and ``bytes_per_s`` refill continuously up to
``burst_s`` seconds' worth; a batch that would overdraw either is refused
whole and counted (:attr:`Quota.refused`), and the sender keeps its records
and retries after :meth:`Quota.retry_after_s` (a busy answer).

Pure (no I/O); time comes from ``clock`` (monotonic seconds) so tests drive it.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from dataclasses import dataclass
from typing import Callable

#: Default records per second per identity: 20x a robot's 10 Hz telemetry.
RECORDS_PER_S = 200.0
#: Default bytes per second per identity (a record is ~200-300 bytes on the wire).
BYTES_PER_S = 128 << 10
#: Seconds of quota a bucket holds: a robot back from an outage replays this much at once.
BURST_S = 30.0


@dataclass
class _Bucket:
    records: float
    nbytes: float
    t: float


class Quota:
    """Token buckets per identity; :meth:`take` says whether a batch fits.  Thread-safe.

    Parameters
    ----------
    records_per_s, bytes_per_s : float
        Sustained rate per identity (0 or less: no limit on that quantity).
    burst_s : float
        Bucket size in seconds of rate.
    clock : callable
        Monotonic seconds.

    Examples
    --------
    >>> t = [0.0]
    >>> q = Quota(10, 1000, burst_s=1, clock=lambda: t[0])
    >>> q.take("r1", 10, 100), q.take("r1", 1, 10), q.refused["r1"]
    (True, False, {'records': 1, 'bytes': 10, 'batches': 1})
    >>> t[0] = 0.5; q.take("r1", 5, 50)
    True
    """

    def __init__(self, records_per_s: float = RECORDS_PER_S, bytes_per_s: float = BYTES_PER_S, *,
                 burst_s: float = BURST_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.records_per_s = float(records_per_s)
        self.bytes_per_s = float(bytes_per_s)
        self.burst_s = float(burst_s)
        self.clock = clock
        self._buckets: dict[str, _Bucket] = {}
        self.refused: dict[str, dict[str, int]] = defaultdict(lambda: {"records": 0, "bytes": 0, "batches": 0})
        self._lock = threading.Lock()

    @property
    def limited(self) -> bool:
        return self.records_per_s > 0 or self.bytes_per_s > 0

    def take(self, who: str, records: int, nbytes: int) -> bool:
        """Charge ``records`` and ``nbytes`` to ``who``; False (charged nothing, counted) when over."""
        if not self.limited:
            return True
        now = self.clock()
        cap_r, cap_b = self.records_per_s * self.burst_s, self.bytes_per_s * self.burst_s
        with self._lock:
            b = self._buckets.get(who)
            if b is None:
                b = self._buckets[who] = _Bucket(cap_r, cap_b, now)
            dt = max(0.0, now - b.t)
            b.records = min(cap_r, b.records + dt * self.records_per_s)
            b.nbytes = min(cap_b, b.nbytes + dt * self.bytes_per_s)
            b.t = now
            ok_r = self.records_per_s <= 0 or records <= b.records
            ok_b = self.bytes_per_s <= 0 or nbytes <= b.nbytes
            if ok_r and ok_b:
                b.records -= records if self.records_per_s > 0 else 0
                b.nbytes -= nbytes if self.bytes_per_s > 0 else 0
                return True
            r = self.refused[who]
            r["records"] += records
            r["bytes"] += nbytes
            r["batches"] += 1
            return False

    def give_back(self, who: str, records: int, nbytes: int) -> None:
        """Undo a :meth:`take` whose records were not stored (a busy gate, a store error)."""
        self._adjust(who, records, nbytes)

    def charge(self, who: str, records: int, nbytes: int) -> None:
        """Debit what was stored already (relayed records: charged once stored, never refused)."""
        self._adjust(who, -records, -nbytes)

    def _adjust(self, who: str, records: int, nbytes: int) -> None:
        if not self.limited:
            return
        cap_r, cap_b = self.records_per_s * self.burst_s, self.bytes_per_s * self.burst_s
        with self._lock:
            b = self._buckets.get(who)
            if b is None:
                b = self._buckets[who] = _Bucket(cap_r, cap_b, self.clock())
            if self.records_per_s > 0:
                b.records = min(cap_r, b.records + records)
            if self.bytes_per_s > 0:
                b.nbytes = min(cap_b, b.nbytes + nbytes)

    def retry_after_s(self, who: str, records: int, nbytes: int) -> float:
        """How long until a batch this size would fit (an estimate for the busy answer)."""
        with self._lock:
            b = self._buckets.get(who)
            if b is None:
                return 0.0
            waits = [0.0]
            if self.records_per_s > 0:
                waits.append((records - b.records) / self.records_per_s)
            if self.bytes_per_s > 0:
                waits.append((nbytes - b.nbytes) / self.bytes_per_s)
            return max(waits)

    def stats(self) -> dict:
        with self._lock:
            return {"records_per_s": self.records_per_s, "bytes_per_s": self.bytes_per_s, "burst_s": self.burst_s,
                    "refused": {k: dict(v) for k, v in sorted(self.refused.items())}}


__all__ = ["BURST_S", "BYTES_PER_S", "RECORDS_PER_S", "Quota"]
