"""Hedged requests: when to send a second copy of a request (pure; no middleware, no clock).

A robot sends a frame to its preferred tier.  When that tier has not answered
within a *hedge delay* learnt from its recent answers, the robot sends the same
request to the next live tier and keeps the first good answer (Dean and Barroso,
"The Tail at Scale", CACM 56(2), 2013).  A silent link then costs the hedge
delay (tens of ms), not the liveliness lease (hundreds).

The rule (:func:`hedge_delay_ms`)::

    delay = max(floor_ms, p95(recent answer times of the tier) + margin_ms)

with the p95 over the last ``window`` good answers of that tier (its very first
answer, which carries one-off costs, left out: :class:`AnswerTimes`); with fewer
than ``min_samples`` answers the delay is ``cold_ms``.  No hedge (``None``) when the
delay leaves the hedge less than ``min_left_ms`` of the request's deadline.

Hedges are rationed (:class:`HedgeBudget`, a token bucket): each request earns
``ratio`` of a hedge, a hedge spends one, at most ``burst`` are saved.  A slow or
overloaded tier (its answers grow, so does its p95) therefore cannot make every
robot send every frame twice: no hedge storm.  A *busy* answer is an answer: it
never triggers a hedge (the robot fails over to the next tier, as before).

>>> w = AnswerTimes(window=8, warmup=0)
>>> for ms in (5, 6, 7, 5, 6, 8, 6, 40):
...     w.add(ms)
>>> round(hedge_delay_ms(w.values(), deadline_ms=1000), 1)  # p95 28.8 + 20
48.8
>>> hedge_delay_ms([], deadline_ms=1000)   # cold: the rule's cold_ms
150.0
>>> hedge_delay_ms([5] * 20, deadline_ms=40) is None  # 30 ms delay, 10 ms left: too late to help
True
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["AnswerTimes", "HedgeBudget", "HedgeRule", "RECEIPT_RULE", "hedge_delay_ms", "receipt_delay_ms"]


@dataclass(frozen=True)
class HedgeRule:
    """The settings of :func:`hedge_delay_ms` (ms)."""

    floor_ms: float = 30.0     # never hedge sooner: a node's scheduling hiccup is not a dead link
    margin_ms: float = 20.0    # above the p95: hedges stay rare in fault-free runs
    quantile: float = 0.95
    min_samples: int = 5       # fewer answers than this: ``cold_ms``
    cold_ms: float = 150.0     # before a tier has answered enough (conservative)
    min_left_ms: float = 50.0  # the hedge must have this much of the deadline left

    def __post_init__(self) -> None:
        for name in ("floor_ms", "margin_ms", "cold_ms", "min_left_ms"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"HedgeRule.{name} must be a finite number >= 0, got {v!r}")
        if not 0.0 < self.quantile <= 1.0:
            raise ValueError(f"HedgeRule.quantile must be in (0, 1], got {self.quantile!r}")
        if self.min_samples < 1:
            raise ValueError(f"HedgeRule.min_samples must be >= 1, got {self.min_samples!r}")


DEFAULT_RULE = HedgeRule()
#: The rule for a copy's *receipt* (docs/R2R.md "Hedged requests"): a node sends it the moment
#: the request is taken in, so it measures the way there and back, not the pipeline; a copy
#: with no receipt past p95 + 10 ms (at least 20 ms) of its node's recent receipts is
#: silent.  No cold delay (:func:`receipt_delay_ms`): with fewer than ``min_samples`` receipts (none
#: yet, or a node that sends none) only the answer's delay (:data:`DEFAULT_RULE`) applies.
RECEIPT_RULE = HedgeRule(floor_ms=20.0, margin_ms=10.0)


def _quantile(values: Sequence[float], q: float) -> float:
    """Linear interpolation between closest ranks (type 7, as :func:`scmr_mesh.qos.metrics.percentile`)."""
    xs = sorted(values)
    pos = q * (len(xs) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (pos - lo)


def hedge_delay_ms(recent_ms: Sequence[float], *, deadline_ms: float, elapsed_ms: float = 0.0,
                   rule: HedgeRule = DEFAULT_RULE) -> float | None:
    """How long to wait for a tier before hedging (ms from the request's start), or None: no hedge.

    Parameters
    ----------
    recent_ms : sequence of float
        The tier's recent good answer times (ToR of its answers), ms.
    deadline_ms : float
        The request's deadline (ms from its start).
    elapsed_ms : float
        Time the request has already spent (a hedge delay of a second tier counts from its start).
    rule : HedgeRule

    Returns
    -------
    float or None
        ``max(floor, p95 + margin)`` (``cold_ms`` with fewer than ``min_samples``
        answers), or None when the hedge would have less than ``min_left_ms`` left.
    """
    if not (math.isfinite(deadline_ms) and deadline_ms > 0):
        raise ValueError(f"deadline_ms must be a finite number > 0, got {deadline_ms!r}")
    xs = [float(x) for x in recent_ms if math.isfinite(x) and x >= 0]
    if len(xs) < rule.min_samples:
        delay = max(rule.floor_ms, rule.cold_ms)
    else:
        delay = max(rule.floor_ms, _quantile(xs, rule.quantile) + rule.margin_ms)
    if elapsed_ms + delay + rule.min_left_ms > deadline_ms:
        return None
    return delay


def receipt_delay_ms(recent_ms: Sequence[float], *, deadline_ms: float, elapsed_ms: float = 0.0,
                     rule: HedgeRule = RECEIPT_RULE) -> float | None:
    """How long to wait for a copy's receipt before the copy counts as silent (ms), or None.

    ``max(floor, p95 + margin)`` of the tier's recent receipt times (ms from the send to
    the receipt), like :func:`hedge_delay_ms`; None with fewer than ``rule.min_samples``
    receipts (no receipt to expect) or when the hedge would have too little of the deadline left.

    >>> receipt_delay_ms([2.0, 3.0, 2.5, 4.0, 3.5, 2.0], deadline_ms=1000)  # p95 3.9 + 10, floor 20
    20.0
    >>> receipt_delay_ms([2.0] * 4, deadline_ms=1000) is None  # too few receipts: none expected
    True
    """
    xs = [float(x) for x in recent_ms if math.isfinite(x) and x >= 0]
    if len(xs) < rule.min_samples:
        return None
    return hedge_delay_ms(xs, deadline_ms=deadline_ms, elapsed_ms=elapsed_ms, rule=rule)


class AnswerTimes:
    """The last ``window`` good answer times of one tier (ms), without its first ``warmup`` answers.

    A tier's first answer carries one-off costs (the querier's route, the first
    frame through a cold pipeline: 75-106 ms where the next took 10-40 ms in
    ``cloud-link-drop`` at load 5); with the 8 answers a robot has before a fault
    at 4 s, the p95 is about the largest of them, so one cold answer would
    set the hedge delay.

    >>> w = AnswerTimes(window=3, warmup=1)
    >>> for ms in (90, 5, 6, 7, 8):
    ...     w.add(ms)
    >>> w.values(), len(w)
    ([6.0, 7.0, 8.0], 3)
    """

    def __init__(self, window: int = 64, *, warmup: int = 1) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window!r}")
        if warmup < 0:
            raise ValueError(f"warmup must be >= 0, got {warmup!r}")
        self._xs: deque[float] = deque(maxlen=window)
        self._skip = int(warmup)

    def add(self, ms: float) -> None:
        if self._skip > 0:
            self._skip -= 1
            return
        self._xs.append(float(ms))

    def values(self) -> list[float]:
        return list(self._xs)

    def __len__(self) -> int:
        return len(self._xs)


class HedgeBudget:
    """A token bucket of hedges: each request earns ``ratio``, a hedge spends 1, at most ``burst`` saved.

    Starts full, so the first requests after start can be hedged (a fault at
    time 0).  Over any long run hedges are at most ``ratio`` of the requests plus ``burst``.

    >>> b = HedgeBudget(ratio=0.5, burst=1)
    >>> [b.take() for _ in range(2)], b.earn(), b.earn(), b.take()
    ([True, False], None, None, True)
    """

    def __init__(self, ratio: float = 0.1, burst: float = 2.0) -> None:
        if not (0.0 <= ratio <= 1.0):
            raise ValueError(f"hedge budget ratio must be in [0, 1], got {ratio!r}")
        if not burst >= 1.0:
            raise ValueError(f"hedge budget burst must be >= 1, got {burst!r}")
        self.ratio = float(ratio)
        self.burst = float(burst)
        self.tokens = float(burst)

    def earn(self) -> None:
        """One request was made."""
        self.tokens = min(self.burst, self.tokens + self.ratio)

    def take(self) -> bool:
        """Spend one hedge if there is one."""
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False
