"""Periodic schedules from integers: frame k is due at t0 + k x period.

A schedule kept by adding a float period to a float time (``next_t += period``)
drifts: on ``time.monotonic()`` values of a few hundred seconds the sixth due
time of a 5 Hz, 1 s window landed a hair under 1.0 s, so a robot sent a sixth
frame 1.0004 s after its start.  Here every due time is computed afresh from
the integer slot index, in integer nanoseconds, and the end of the window is
checked both before waiting and after the wait returns.

Pure: no clock is read here; callers pass ``now_ns``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

NS = 1_000_000_000


def due_ns(t0_ns: int, k: int, rate_hz: float) -> int:
    """The due time of slot ``k`` (``k`` >= 0) of a ``rate_hz`` schedule started at ``t0_ns``.

    >>> due_ns(0, 5, 5.0)
    1000000000
    >>> due_ns(100, 3, 3.0) - 100
    1000000000
    >>> due_ns(7, 9, 0.0)  # no rate: every slot is due at once
    7
    """
    if k < 0:
        raise ValueError(f"slot {k} < 0")
    if not rate_hz or rate_hz <= 0:
        return t0_ns
    return t0_ns + round(k * NS / rate_hz)


@dataclass
class Schedule:
    """Slots of a periodic sender with an optional end (``duration_s`` after ``t0_ns``).

    ``slot`` is the index of the next slot to send.  :meth:`advance` moves past
    a sent slot, skipping slots already more than one period in the past (no
    catch-up bursts after a stall: at most one late slot is sent at once).
    """

    t0_ns: int
    rate_hz: float
    duration_s: float | None = None
    slot: int = 0

    @property
    def end_ns(self) -> int | None:
        """``t0_ns`` + the duration, or None without one."""
        return None if self.duration_s is None else self.t0_ns + round(self.duration_s * NS)

    def next_due_ns(self) -> int:
        """When the next slot is due."""
        return due_ns(self.t0_ns, self.slot, self.rate_hz)

    def ended(self, now_ns: int) -> bool:
        """True when the next frame would go out at or after the end (it would be sent at max(due, now))."""
        end = self.end_ns
        return end is not None and max(self.next_due_ns(), now_ns) >= end

    def advance(self, now_ns: int) -> None:
        """Past the slot just sent; a sender more than one period late skips to the slot before now.

        >>> s = Schedule(0, 5.0)
        >>> s.advance(0); s.slot
        1
        >>> s.advance(1_000_000_000); s.slot  # a 1 s stall: slot 4 (0.8 s) next, not 1, 2, 3 in a burst
        4
        """
        nxt = self.slot + 1
        if self.rate_hz and self.rate_hz > 0 and now_ns > self.t0_ns:
            # the first slot due at or after now - period: sending it is at most one period late
            nxt = max(nxt, math.ceil((now_ns - self.t0_ns) * self.rate_hz / NS) - 1)
        self.slot = nxt
