"""Priority request negotiator with bounded admission (thesis 3.4.6, Table 3.6).

The thesis's request negotiator ranks robot requests by their *willingness to pay*
``p_i``, keeps a sorted ``current_priority_list`` up to a threshold ``n_threshold`` and
answers what does not fit: its prototype told a client "Server too busy. Try later."
This module is that negotiator, made precise so that memory is bounded under any
request rate:

* at most ``workers`` requests are *in service* and at most ``capacity`` *wait*;
* a request below ``min_priority`` is refused at once (the thesis's "records that do not
  meet the minimum requirements");
* a request arriving to a full queue either **displaces** the lowest-priority waiting
  request, if its own priority is strictly higher, or is refused at once; a request is
  never displaced by one of lower or equal priority;
* an optional ``per_robot`` quota bounds how many waiting requests one robot may hold,
  so one robot flooding the cloud cannot fill the queue;
* free workers take the highest priority first, oldest first among equals;
* optionally (``ranking=UtilityRanking(...)``) requests are ranked instead by their
  **utility** of thesis Eq 3.14, ``u_i = 1 / (w_t * max_j t_ij + w_e * sum_j e_ij)``, with
  ``t_ij`` the request's predicted service time here (learnt online from its size,
  :class:`ServiceTimeModel`) and ``e_ij`` its expense at this server's prices (CPU seconds
  and megabytes); willingness to pay then breaks ties.

Every refused or displaced request must get an explicit "busy" answer at once
(:class:`Decision` lists them), so a robot falls back to the leader or to local
execution instead of waiting.

The negotiator is pure Python (no Zenoh): the server calls :meth:`Negotiator.offer`
from its query callback and :meth:`Negotiator.take` / :meth:`Negotiator.done` from its
workers.  All methods are thread-safe.

References
----------
Thesis 3.4.6 and Table 3.6 (pseudo-code of the request negotiator); Appendix B (the
prototype's ``maxClientsCount`` and "Server too busy. Try later.").

Examples
--------
>>> n = Negotiator(capacity=1, workers=1)      # room for 1 in service + 1 waiting
>>> n.offer("a", 5).admitted, n.offer("b", 1).admitted
(True, True)
>>> [e.request_id for e in n.offer("c", 9).refused]  # full: c displaces the lowest, b
['b']
>>> [e.request_id for e in n.offer("d", 0).refused]  # d is lower than all: refused
['d']
>>> n.take(timeout=0).request_id                     # highest priority first
'c'
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable, Sequence


log = logging.getLogger(__name__)

#: Why a request was not served.
REASON_FULL = "full"            # queue full of requests of equal or higher priority
REASON_DISPLACED = "displaced"  # pushed out of the queue by a higher-priority request
REASON_MINIMUM = "minimum"      # priority below the negotiator's minimum
REASON_QUOTA = "quota"          # the robot already holds its share of the queue
REASON_CLOSED = "closed"        # the negotiator was closed


def utility(times_s: Sequence[float], expenses: Sequence[float], *, w_time: float, w_expense: float) -> float:
    """Utility of a task (thesis Eq 3.14): ``1 / (w_t * max_j t_ij + w_e * sum_j e_ij)``.

    Parameters
    ----------
    times_s : sequence of float
        ``t_ij``: completion time of each of the task's requests (s); the task
        completes with its slowest request.
    expenses : sequence of float
        ``e_ij``: expense of the task on each resource ``j`` (price x amount used).
    w_time, w_expense : float, keyword-only
        ``omega_t`` and ``omega_e``: how much completion time and expense weigh (>= 0,
        not both 0).

    Returns
    -------
    float
        The utility (``inf`` for a task that costs nothing).

    Examples
    --------
    >>> utility([0.2, 0.5], [1.0, 3.0], w_time=2.0, w_expense=0.25)   # 1 / (2*0.5 + 0.25*4)
    0.5
    """
    if w_time < 0 or w_expense < 0 or (w_time == 0 and w_expense == 0):
        raise ValueError(f"weights must be >= 0 and not both 0, got w_time={w_time}, w_expense={w_expense}")
    cost = w_time * max(times_s, default=0.0) + w_expense * sum(expenses)
    return math.inf if cost <= 0 else 1.0 / cost


class ServiceTimeModel:
    """Predicts a request's service time from its size: an online least-squares line.

    ``t = a + b * bytes``, fitted with exponential forgetting (``memory`` requests)
    from the service times :meth:`Negotiator.done` reports.  Until two sizes have
    been seen it predicts the mean (``prior_s`` before any observation).

    Examples
    --------
    >>> m = ServiceTimeModel(prior_s=0.05)
    >>> for size, t in [(1000, 0.011), (3000, 0.013), (2000, 0.012)]:
    ...     m.observe(size, t)
    >>> round(m.predict(5000), 4)
    0.015
    """

    def __init__(self, *, prior_s: float = 0.05, memory: float = 200.0) -> None:
        self.prior_s = float(prior_s)
        self._decay = 1.0 - 1.0 / max(float(memory), 1.0)
        self._n = self._sx = self._sy = self._sxx = self._sxy = 0.0

    def observe(self, size: float, service_s: float) -> None:
        """One finished request of ``size`` bytes that took ``service_s``."""
        d = self._decay
        x, y = float(size), float(service_s)
        self._n = d * self._n + 1.0
        self._sx = d * self._sx + x
        self._sy = d * self._sy + y
        self._sxx = d * self._sxx + x * x
        self._sxy = d * self._sxy + x * y

    def predict(self, size: float | None) -> float:
        """Predicted service time of a request of ``size`` bytes (s, >= 0)."""
        if self._n <= 0:
            return self.prior_s
        mean_y = self._sy / self._n
        var = self._sxx / self._n - (self._sx / self._n) ** 2
        if size is None or var <= 1e-9 * max(1.0, (self._sx / self._n) ** 2):
            return max(0.0, mean_y)
        b = (self._sxy / self._n - (self._sx / self._n) * mean_y) / var
        a = mean_y - b * self._sx / self._n
        return max(0.0, a + b * float(size))


@dataclass(frozen=True)
class UtilityRanking:
    """Rank requests by their Eq 3.14 utility at this server (the thesis's CPU and bandwidth elements).

    A request here is a task of one request on one resource (this server), so
    ``max_j t_ij`` is its predicted service time ``t`` and ``sum_j e_ij`` its
    expense ``price_per_s * t + price_per_mb * megabytes``.  Higher utility is
    served first; willingness to pay breaks ties.  With ``price_per_mb = 0`` the
    ranking is shortest-predicted-job first.

    Parameters
    ----------
    w_time, w_expense : float
        ``omega_t``, ``omega_e`` of Eq 3.14.
    price_per_s : float
        This resource's price per second of service (``p_j`` for CPU).
    price_per_mb : float
        Its price per megabyte (2**20 bytes) received (bandwidth).
    """

    w_time: float = 1.0
    w_expense: float = 1.0
    price_per_s: float = 1.0
    price_per_mb: float = 0.0

    def __post_init__(self) -> None:
        for name in ("w_time", "w_expense", "price_per_s", "price_per_mb"):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v}")
        if self.w_time == 0 and self.w_expense == 0:
            raise ValueError("w_time and w_expense cannot both be 0")

    def score(self, est_s: float, size: float | None) -> float:
        """The utility of serving a request predicted to take ``est_s`` seconds, of ``size`` bytes."""
        mb = (size or 0) / 1048576.0
        return utility([est_s], [self.price_per_s * est_s + self.price_per_mb * mb],
                       w_time=self.w_time, w_expense=self.w_expense)


@dataclass(order=False)
class Entry:
    """One request known to the negotiator.

    Attributes
    ----------
    request_id : hashable
        Caller's id (unique among live requests).
    priority : int
        Willingness to pay; higher is served first.
    robot : str or None
        Who sent it (for the per-robot quota and fairness reports).
    payload : Any
        Opaque caller data (for example the Zenoh query to answer).
    arrived : float
        Clock time of :meth:`Negotiator.offer`.
    seq : int
        Arrival order (ties between equal priorities go to the lower ``seq``).
    reason : str or None
        Set when the request is refused or displaced.
    """

    request_id: Hashable
    priority: int
    robot: str | None = None
    payload: Any = None
    arrived: float = 0.0
    seq: int = 0
    reason: str | None = None
    size: int | None = None
    #: Eq 3.14 utility when the negotiator ranks by utility (None: ranked by priority).
    utility: float | None = None

    @property
    def key(self) -> tuple:
        """What ranks the entry (higher first): ``(utility, priority)`` or ``(priority,)``."""
        return (self.priority,) if self.utility is None else (self.utility, self.priority)


@dataclass
class Decision:
    """Outcome of :meth:`Negotiator.offer`.

    Attributes
    ----------
    entry : Entry
        The offered request.
    admitted : bool
        True if it waits in the queue (or was handed to a free worker).
    refused : list of Entry
        Requests that must be answered "busy" now: the offered one if not admitted,
        and any waiting request it displaced.
    retry_after_ms : float
        Suggested wait before trying this server again (0 when admitted).
    """

    entry: Entry
    admitted: bool
    refused: list[Entry] = field(default_factory=list)
    retry_after_ms: float = 0.0


@dataclass
class Stats:
    """Counters since the negotiator was made."""

    offered: int = 0
    admitted: int = 0
    served: int = 0
    refused: Counter = field(default_factory=Counter)
    max_waiting: int = 0
    max_in_service: int = 0


class Negotiator:
    """Bounded priority queue of requests with explicit refusals.

    Parameters
    ----------
    capacity : int, keyword-only
        Most requests that may wait for a busy worker (>= 0); with 0 a request is
        admitted only when a worker is idle.  Always ``waiting + in_service <=
        capacity + workers``.
    workers : int, keyword-only
        Most requests in service at once (>= 1): the server's pool size.
    min_priority : int, keyword-only
        Requests below this priority are refused at once.
    per_robot : int or None, keyword-only
        Most waiting requests per robot (None: no quota).
    ranking : UtilityRanking or None, keyword-only
        Rank by Eq 3.14 utility instead of by priority (None: by priority, Table 3.6).
    clock : callable, keyword-only
        Monotonic clock in seconds (injectable for tests).

    Raises
    ------
    ValueError
        On a negative capacity, fewer than one worker or a per-robot quota below one.
    """

    def __init__(
        self,
        *,
        capacity: int,
        workers: int = 1,
        min_priority: int = 0,
        per_robot: int | None = None,
        ranking: UtilityRanking | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if capacity < 0:
            raise ValueError(f"capacity must be >= 0, got {capacity}")
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if per_robot is not None and per_robot < 1:
            raise ValueError(f"per_robot must be >= 1 or None, got {per_robot}")
        self.capacity = int(capacity)
        self.workers = int(workers)
        self.min_priority = int(min_priority)
        self.per_robot = per_robot
        self.ranking = ranking
        self.service_model = ServiceTimeModel()
        self._clock = clock
        self._cond = threading.Condition()
        self._seq = itertools.count()
        # Two heaps over the same waiting entries, lazily cleaned: ``_best`` pops the
        # next to serve (max priority, then oldest), ``_worst`` finds the one to displace
        # (min priority, then newest).  ``_waiting`` maps seq -> entry for live ones.
        self._best: list[tuple[tuple, int, Entry]] = []
        self._worst: list[tuple[tuple, int, Entry]] = []
        self._waiting: dict[int, Entry] = {}
        self._per_robot: Counter = Counter()
        self._in_service = 0
        self._service_s = 0.05  # EWMA of service time, for retry_after_ms
        self._closed = False
        self.stats = Stats()

    # -- queries ---------------------------------------------------------------------
    @property
    def waiting(self) -> int:
        """Number of requests waiting."""
        return len(self._waiting)

    @property
    def in_service(self) -> int:
        """Number of requests taken by workers and not yet done."""
        return self._in_service

    def waiting_entries(self) -> list[Entry]:
        """Waiting requests in service order (highest priority, then oldest)."""
        with self._cond:
            return sorted(self._waiting.values(), key=lambda e: (tuple(-k for k in e.key), e.seq))

    def retry_after_ms(self) -> float:
        """Estimated time until a worker could take a newly queued request, in ms."""
        with self._cond:
            return self._retry_after_locked()

    def _retry_after_locked(self) -> float:
        backlog = len(self._waiting) + self._in_service
        return round(1000.0 * self._service_s * max(1.0, backlog / self.workers), 1)

    # -- internals -------------------------------------------------------------------
    def _push(self, e: Entry) -> None:
        self._waiting[e.seq] = e
        heapq.heappush(self._best, (tuple(-k for k in e.key), e.seq, e))
        heapq.heappush(self._worst, (e.key, -e.seq, e))
        if e.robot is not None:
            self._per_robot[e.robot] += 1
        self.stats.max_waiting = max(self.stats.max_waiting, len(self._waiting))

    def _forget(self, e: Entry) -> None:
        del self._waiting[e.seq]
        if e.robot is not None:
            self._per_robot[e.robot] -= 1
            if self._per_robot[e.robot] <= 0:
                del self._per_robot[e.robot]
        # Heaps are cleaned lazily; compact when stale entries dominate (bounded memory).
        if len(self._best) > 2 * len(self._waiting) + 16:
            self._best = [t for t in self._best if t[1] in self._waiting]
            heapq.heapify(self._best)
            self._worst = [t for t in self._worst if -t[1] in self._waiting]
            heapq.heapify(self._worst)

    def _peek_worst(self) -> Entry | None:
        while self._worst and -self._worst[0][1] not in self._waiting:
            heapq.heappop(self._worst)
        return self._worst[0][2] if self._worst else None

    def _pop_best(self) -> Entry | None:
        while self._best:
            _, seq, e = heapq.heappop(self._best)
            if seq in self._waiting:
                self._forget(e)
                return e
        return None

    def _refuse(self, e: Entry, reason: str) -> Entry:
        e.reason = reason
        self.stats.refused[reason] += 1
        return e

    # -- the protocol ----------------------------------------------------------------
    def offer(
        self, request_id: Hashable, priority: int, *, robot: str | None = None, payload: Any = None,
        size: int | None = None,
    ) -> Decision:
        """Rank a new request: admit it (maybe displacing a lower one) or refuse it.

        Parameters
        ----------
        request_id : hashable
        priority : int
            Willingness to pay (higher first).
        robot : str, optional, keyword-only
        payload : Any, optional, keyword-only
            Kept on the entry (for example the query to answer later).
        size : int, optional, keyword-only
            The request's size in bytes (predicts its service time for the utility ranking).

        Returns
        -------
        Decision
            ``refused`` lists every entry that must be answered "busy" now.
        """
        with self._cond:
            e = Entry(request_id, int(priority), robot, payload, self._clock(), next(self._seq), size=size)
            if self.ranking is not None:
                e.utility = self.ranking.score(self.service_model.predict(size), size)
            self.stats.offered += 1
            retry = self._retry_after_locked()
            if self._closed:
                return Decision(e, False, [self._refuse(e, REASON_CLOSED)], retry)
            if e.priority < self.min_priority:
                return Decision(e, False, [self._refuse(e, REASON_MINIMUM)], retry)
            # Room for ``capacity`` waiting requests plus one per idle worker (an idle
            # worker takes its request at once), so waiting + in service never exceeds
            # capacity + workers.
            idle = self.workers - self._in_service
            limit = self.capacity + idle
            contended = len(self._waiting) >= idle
            if contended and self.per_robot is not None and robot is not None \
                    and self._per_robot[robot] >= self.per_robot:
                return Decision(e, False, [self._refuse(e, REASON_QUOTA)], retry)
            refused: list[Entry] = []
            if len(self._waiting) >= limit:
                worst = self._peek_worst()
                if worst is None or worst.key >= e.key:
                    return Decision(e, False, [self._refuse(e, REASON_FULL)], retry)
                self._forget(worst)
                refused.append(self._refuse(worst, REASON_DISPLACED))
            self._push(e)
            self.stats.admitted += 1
            self._cond.notify()
            return Decision(e, True, refused, 0.0)

    def take(self, *, timeout: float | None = None) -> Entry | None:
        """Hand the best waiting request to a worker (blocks up to ``timeout`` seconds).

        Returns
        -------
        Entry or None
            None on timeout, when closed, or when all ``workers`` are busy.
        """
        deadline = None if timeout is None else self._clock() + timeout
        with self._cond:
            while True:
                if self._closed:
                    return None
                if self._waiting and self._in_service < self.workers:
                    e = self._pop_best()
                    assert e is not None
                    self._in_service += 1
                    self.stats.max_in_service = max(self.stats.max_in_service, self._in_service)
                    return e
                if deadline is not None:
                    left = deadline - self._clock()
                    if left <= 0:
                        return None
                    self._cond.wait(left)
                else:
                    self._cond.wait()

    def done(self, entry: Entry | None = None, *, service_s: float | None = None) -> None:
        """A worker finished a request taken with :meth:`take`.

        Parameters
        ----------
        entry : Entry, optional
        service_s : float, optional, keyword-only
            How long it took (feeds the ``retry_after_ms`` estimate).

        Raises
        ------
        RuntimeError
            If no request is in service.
        """
        with self._cond:
            if self._in_service <= 0:
                raise RuntimeError("done() called with no request in service")
            self._in_service -= 1
            self.stats.served += 1
            if service_s is not None and service_s >= 0:
                self._service_s = 0.8 * self._service_s + 0.2 * service_s
                if entry is not None and entry.size is not None:
                    self.service_model.observe(entry.size, service_s)
            self._cond.notify()

    def close(self) -> list[Entry]:
        """Stop admitting; return the waiting requests (answer them "busy") and wake workers."""
        with self._cond:
            self._closed = True
            left = sorted(self._waiting.values(), key=lambda e: e.seq)
            for e in left:
                self._forget(e)
                self._refuse(e, REASON_CLOSED)
            self._cond.notify_all()
            return left


def jain_index(values) -> float:
    """Jain's fairness index ``(sum x)^2 / (n * sum x^2)``: 1 is perfectly fair, 1/n worst.

    Parameters
    ----------
    values : iterable of float
        Per-robot amounts (for example requests served).  Empty or all-zero gives 1.0.

    Examples
    --------
    >>> jain_index([5, 5, 5, 5])
    1.0
    >>> jain_index([4, 0, 0, 0])
    0.25
    """
    xs = [float(v) for v in values]
    top = max((abs(x) for x in xs), default=0.0)
    if top == 0:
        return 1.0
    xs = [x / top for x in xs]  # scale-free; tiny values would underflow x * x
    return min(1.0, sum(xs) ** 2 / (len(xs) * sum(x * x for x in xs)))
