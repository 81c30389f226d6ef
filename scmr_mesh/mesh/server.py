"""The drivable-region service: what ``scmr cloud`` and ``scmr leader`` run.

A :class:`Service` answers queries on ``scmr/drivable/<tier>/<node>/<robot>``
(one queryable on ``.../<node>/*``, ``complete=True``) with the pipeline run in a
:class:`~scmr_mesh.mesh.work.WorkerPool`, holds the liveliness token
``scmr/alive/<tier>/<node>`` and publishes its load on
``scmr/load/<tier>/<node>`` (robots spread requests over cloud nodes by it).

Life cycle (done for you by :func:`run_service`)::

    svc = Service("c1", tier="cloud", workers=2)   # forks + warms the workers
    session = open_session(mesh_config)             # only now open zenoh
    svc.attach(session)                             # queryable, token, load
    ...
    svc.detach(); close_session(session); svc.shutdown()

Per query: the key must be concrete and name the requesting robot
(``scmr/drivable/<tier>/<node>/<robot>``): a wildcard selector
(``scmr/drivable/**``) gets a cheap ``malformed`` error and no pipeline run, and a
request whose ``robot`` field names another robot than the key gets ``forbidden``
(access control lets robot X query only keys ending in ``/X``, so the key is the
sender's identity).  With a fleet policy (``Service.priority_cap``) the request's
priority is capped at the sender's.  Replies go out on the concrete key the
request came on, encoded ``application/msgpack``.  Then the payload is
size-checked and validated (``wire.decode``); a bad one gets an error reply (``malformed``, ``oversized``, ``wrong_version``) and
the service keeps serving.  Then the *admission function* decides; a refused
request gets its error reply (``busy`` by default when the request would
be answered later than the service's latency budget, :func:`default_admission`).  Admitted requests go to the
pool.  Every reply, good or error, is sent by a :class:`Replier` thread
(``query.reply`` then ``query.drop``), so neither zenoh's callback thread nor
the pool's waits for the pipeline or for a reply stuck on a dead link.

Hooks for other areas
---------------------
* ``Service.admission``: replaceable ``fn(request: dict, state: ServiceState)
  -> Refusal | None``.  Return ``None`` to admit, or a :class:`Refusal`
  (``code`` usually ``"busy"``, ``message``, ``retry_after_ms``).  The security
  engineer's priority negotiator plugs in here; :func:`default_admission` is
  the default.
* ``Service.use_negotiator(negotiator)``: rank admitted requests by priority
  in a bounded queue (:class:`scmr_mesh.qos.negotiator.Negotiator`): a dispatcher
  thread feeds the pool highest priority first, at most ``negotiator.workers``
  at a time; requests refused or displaced get a ``busy`` error reply at once.
* ``Service.add_queryable(key, callback, complete=False)``: extra queryables
  declared on the service's session (data-buffer queries under
  ``keys.data(tier, node)``); callable before or after :meth:`attach`.
* ``Service.session``: the zenoh session once attached.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from scmr_mesh import keys, wire
from scmr_mesh.errors import ImageDecodeError, InputError
from scmr_mesh.mesh.work import DEFAULT_PROCESS, Expired, WorkerPool

log = logging.getLogger(__name__)

#: How often (s) a service publishes its load.
LOAD_PERIOD_S = 0.1


#: Threads that send replies (see :class:`Replier`).
REPLY_THREADS = 4
#: error replies of one code are logged at INFO at most once per this many seconds (the rest at DEBUG)
ERROR_LOG_PERIOD_S = 1.0
#: the error log's clock (a test replaces this one, not ``time.monotonic`` itself)
_clock = time.monotonic


class Replier:
    """Sends replies from its own threads.

    A reply inherits its query's congestion control; to a robot whose link just
    died silently a ``block`` reply can wait for queue space until zenoh gives
    up on the link (``wait_before_close``).  Sent from zenoh's callback thread
    that would stall the reception of every other query; sent from the worker
    pool's callback thread it would hold every other finished frame.  So both
    only queue the send here, and ``threads`` senders work through the queue:
    one stuck reply holds one sender, not the service.
    """

    def __init__(self, threads: int = REPLY_THREADS) -> None:
        import queue as _queue

        self._q: _queue.SimpleQueue = _queue.SimpleQueue()
        self.pending = 0
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._run, name=f"scmr-reply-{i}", daemon=True)
                         for i in range(max(1, int(threads)))]
        for t in self._threads:
            t.start()

    def send(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` (which sends one reply) on a sender thread."""
        with self._lock:
            self.pending += 1
        self._q.put(fn)

    def _run(self) -> None:
        while True:
            fn = self._q.get()
            if fn is None:
                return
            try:
                fn()
            except Exception:  # a send never takes a sender down
                log.exception("reply failed")
            finally:
                # let go of the send, and with it its query, now: a sender idle until the next reply
                # would otherwise keep the query alive, and zenoh finalises a query when it is freed
                fn = None
                with self._lock:
                    self.pending -= 1

    def close(self, timeout: float = 2.0) -> None:
        """Send what is queued (up to ``timeout``), then stop the senders."""
        for _ in self._threads:
            self._q.put(None)
        end = time.monotonic() + timeout
        for t in self._threads:
            t.join(timeout=max(0.0, end - time.monotonic()))


class _Seen:
    """What a service remembers of one request it took in (:class:`RecentRequests`)."""

    __slots__ = ("waiters", "done", "reply")

    def __init__(self) -> None:
        self.waiters: list = []      # later copies waiting for the first copy's answer
        self.done = False            # the first copy was answered
        self.reply: bytes | None = None  # its good reply, kept while the byte budget allows


class RecentRequests:
    """The last ``size`` requests a service took in, by (robot, seq, sent time, frame digest): a bounded dedupe.

    A hedged or re-sent request (docs/R2R.md) can reach one node twice; the
    pipeline runs once.  A later copy is answered with the first copy's answer:
    it waits for it while the first copy is being served (:meth:`admit` returns
    ``"joined"``; at most :attr:`MAX_WAITERS` copies), or gets the kept reply at
    once (``"cached"``; the last good replies are kept up to ``max_reply_bytes``
    in all); a copy that waited for a first copy that failed gets that copy's
    error.  Otherwise (the reply no longer kept, the first copy failed, too many
    copies waiting) it is answered ``duplicate``.  The identity includes the tier
    the request came on: a node that changed tier answers a copy on its new tier
    afresh, never with a reply naming the old one.
    The robot's sending time is part of the identity, so a restarted robot's
    seq 0 is new.

    >>> r = RecentRequests(size=2)
    >>> r.admit(("r1", 3, 12)), r.admit(("r1", 3, 12), "q2"), r.admit(("r1", 3, 12), "q3")
    (('new', None), ('joined', None), ('joined', None))
    >>> r.admit(("r1", 3, 12), "q4")  # more copies than MAX_WAITERS: not parked
    ('duplicate', None)
    >>> r.complete(("r1", 3, 12), b"mask")  # the first copy's answer: to the copies that waited
    ['q2', 'q3']
    >>> r.admit(("r1", 3, 12), "q5")
    ('cached', b'mask')
    >>> for seq in (4, 5):
    ...     _ = r.admit(("r1", seq, 12)), r.complete(("r1", seq, 12), None)
    >>> r.admit(("r1", 3, 12))  # bounded: the oldest answered requests are forgotten
    ('new', None)
    """

    #: Copies of one request that may wait for its first copy's answer; a further copy is answered
    #: ``duplicate`` at once (a robot sends at most three; a looping or hostile one cannot park more).
    MAX_WAITERS = 2

    def __init__(self, size: int = 4096, max_reply_bytes: int = 8 << 20) -> None:
        from collections import OrderedDict

        self.size = int(size)
        self.max_reply_bytes = int(max_reply_bytes)
        self._seen: OrderedDict = OrderedDict()
        self._kept: OrderedDict = OrderedDict()  # ident -> reply size, oldest first
        self._kept_bytes = 0
        self._lock = threading.Lock()
        #: later copies of a request taken in (answered from the first copy, or refused ``duplicate``)
        self.duplicates = 0
        #: of those, answered with the first copy's answer
        self.shared = 0

    def admit(self, ident: tuple, query=None) -> tuple[str, bytes | None]:
        """Take in a copy of ``ident``: ``("new", None)``, ``("joined", None)`` (``query`` waits for
        :meth:`complete`), ``("cached", reply)`` or ``("duplicate", None)``."""
        with self._lock:
            e = self._seen.get(ident)
            if e is None:
                self._seen[ident] = _Seen()
                self._evict()
                return "new", None
            self.duplicates += 1
            if e.reply is not None:
                self.shared += 1
                return "cached", e.reply
            if not e.done and query is not None and len(e.waiters) < self.MAX_WAITERS:
                self.shared += 1
                e.waiters.append(query)
                return "joined", None
            return "duplicate", None

    def add(self, ident: tuple) -> bool:
        """Remember ``ident``; False (and counted) when it is already remembered."""
        return self.admit(ident)[0] == "new"

    def complete(self, ident: tuple, reply: bytes | None) -> list:
        """The first copy of ``ident`` was answered (``reply``: its good reply, or None): the copies that waited."""
        with self._lock:
            e = self._seen.get(ident)
            if e is None:
                return []
            waiters, e.waiters, e.done = e.waiters, [], True
            self._unkeep(ident)  # (a reply kept already: replaced, never counted twice)
            if reply is not None and len(reply) <= self.max_reply_bytes:
                e.reply = reply
                self._kept[ident] = len(reply)
                self._kept_bytes += len(reply)
                while self._kept_bytes > self.max_reply_bytes:
                    self._unkeep(next(iter(self._kept)))
            return waiters

    def forget(self, ident: tuple) -> list:
        """A request refused (busy): a later copy of it may be taken in.  Returns the copies that waited."""
        with self._lock:
            e = self._seen.pop(ident, None)
            self._unkeep(ident)
            return e.waiters if e is not None else []

    def _evict(self) -> None:
        """Forget the oldest answered requests beyond ``size``.  One still being served stays (its
        copies wait for it, and a copy of it must not run again): those are bounded by the
        node's in-flight limit."""
        while len(self._seen) > self.size:
            old = next((k for k, e in self._seen.items() if e.done), None)
            if old is None:
                return
            del self._seen[old]
            self._unkeep(old)

    def _unkeep(self, ident: tuple) -> None:
        n = self._kept.pop(ident, None)
        if n is not None:
            self._kept_bytes -= n
            e = self._seen.get(ident)
            if e is not None:
                e.reply = None


def _ident(req: dict) -> tuple:
    """A request's identity at a node: robot, seq, sending time, frame digest and the tier it came on."""
    return (req["robot"], req["seq"], req.get("sent_unix_ns"), req.get("digest"), req.get("_tier"))


@dataclass
class Refusal:
    """Why the admission function turned a request away (sent as an error reply)."""

    code: str = "busy"
    message: str = "server too busy, try later"
    retry_after_ms: float | None = None


#: Default budget (ms) of an admitted request's time in the service: the default
#: admission answers ``busy`` at once when the predicted queue wait plus the
#: frame's own processing would exceed it (robots' ToR p99 target 100 ms, less
#: transport, robot-side handling and the error of the prediction).
DEFAULT_BUDGET_MS = 60.0
#: Weight of the newest frame in the service-time average.
SERVICE_EWMA = 0.2


@dataclass
class ServiceState:
    """Live counters the admission function may read.

    Attributes
    ----------
    node, tier : str
    workers : int
    inflight : int
        Admitted requests not answered yet.
    max_inflight : int
        The default admission's hard limit.
    budget_ms : float
        The default admission's latency budget (see :func:`default_admission`).
    service_ms : float or None
        Moving average of a worker's time per frame (None before the first).
    queue_managed : bool
        A priority negotiator bounds the queue (``--queue``); the default
        admission then applies only its hard limit.
    outstanding : callable or None
        ``fn() -> int``: admitted frames no worker has finished yet, counted
        by the workers (:meth:`~scmr_mesh.mesh.work.WorkerPool.outstanding`);
        see :meth:`ahead`.
    served, errors, refused : int
        Totals since start.
    """

    node: str
    tier: str
    workers: int
    max_inflight: int
    inflight: int = 0
    served: int = 0
    errors: int = 0
    refused: int = 0
    budget_ms: float = DEFAULT_BUDGET_MS
    service_ms: float | None = None
    queue_managed: bool = False
    outstanding: Callable[[], int] | None = field(default=None, repr=False)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def ahead(self) -> int:
        """Admitted frames a new request would wait behind: :attr:`inflight`, less those a
        worker has finished whose result has not reached the service yet (issue 23 item 2).

        >>> st = ServiceState("c1", "cloud", workers=2, max_inflight=16, inflight=5)
        >>> st.ahead(), ServiceState("c1", "cloud", 2, 16, inflight=5, outstanding=lambda: 3).ahead()
        (5, 3)
        """
        fn = self.outstanding
        if fn is None:
            return self.inflight
        try:
            return min(self.inflight, int(fn()))
        except Exception:  # a pool being replaced: the service's own count
            return self.inflight

    def predicted_ms(self, inflight: int | None = None) -> float | None:
        """Time a request admitted now would spend here (None before any sample).

        With ``ahead`` requests in progress on ``W`` workers taking ``S`` ms a
        frame, a request that finds every worker busy waits until
        ``ahead - W + 1`` of them have finished; busy workers finish one every
        ``S / W`` ms on average, so it waits ``(ahead - W + 1) x S / W``, then
        takes its own ``S``.  (Counting a whole ``S`` for each round of ``W``
        ahead, as before issue 23, priced the first queued request at ``2 S``
        when one of ``W`` workers frees in about ``S / W``: with a frame over
        half the budget the node answered busy before any queue formed, at 80 %
        of its workers' capacity with 8 workers at 40 ms.)

        >>> st = ServiceState("c1", "cloud", workers=8, max_inflight=64, service_ms=40.0)
        >>> st.predicted_ms(7), st.predicted_ms(8), st.predicted_ms(11), st.predicted_ms(12)
        (40.0, 45.0, 60.0, 65.0)
        """
        if self.service_ms is None:
            return None
        ahead = self.ahead() if inflight is None else inflight
        workers = max(1, self.workers)
        return self.service_ms * (1.0 + max(0, ahead - workers + 1) / workers)

    def note_service(self, worker_ms: float) -> None:
        """Fold one frame's worker time into :attr:`service_ms` (call with the lock held)."""
        if worker_ms > 0:
            prev = self.service_ms
            self.service_ms = worker_ms if prev is None else prev + SERVICE_EWMA * (worker_ms - prev)


Admission = Callable[[dict, ServiceState], "Refusal | None"]


def default_admission(request: dict, state: ServiceState) -> Refusal | None:
    """Answer ``busy`` early instead of letting a queue grow.

    Refuses when ``state.inflight >= state.max_inflight``, or when every
    worker is busy and the request would be answered later than its budget:
    the predicted time here (:meth:`ServiceState.predicted_ms`: the frames
    ahead of it, finishing at the workers' rate, ``workers`` per recent average
    worker time, then its own) exceeds ``state.budget_ms``.  The average follows the machine's load (a frame takes
    longer when the cores are shared), so the queue a service accepts shrinks
    as it slows down and an admitted request's time stays near the budget at
    any offered load; the refused robot goes to the leader, a peer or runs the
    frame itself.  A request that finds a free worker is always admitted (it
    waits for nothing), and with a priority negotiator (``--queue``) only the
    hard limit applies: the negotiator bounds its own queue.
    The frames ahead are counted by the workers (:meth:`ServiceState.ahead`):
    a frame whose worker is done is not waited for, even if its result has not
    reached the service yet.
    ``retry_after_ms`` says when the queue should have drained enough.
    """
    if state.inflight >= state.max_inflight:
        return Refusal(
            "busy",
            f"server too busy, try later ({state.inflight} requests in progress, "
            f"limit {state.max_inflight})",
            retry_after_ms=50.0,
        )
    if state.queue_managed:
        return None
    ahead = state.ahead()
    if ahead < state.workers:
        return None
    predicted = state.predicted_ms(ahead)
    if predicted is None:
        return None
    limit = state.budget_ms
    if predicted > limit:
        return Refusal(
            "busy",
            f"server too busy, try later: {ahead} requests in progress on {state.workers} workers "
            f"at {state.service_ms:.0f} ms per frame would answer in about {predicted:.0f} ms, over the "
            f"{limit:.0f} ms budget; send it to another tier or run it locally",
            retry_after_ms=round(max(1.0, predicted - limit), 1),
        )
    return None


class Service:
    """One drivable-region service (cloud or leader tier) on one node.

    Parameters
    ----------
    node : str
        Node name (a key chunk).
    tier : {"cloud", "leader", "peer"}
        Can change while detached (:meth:`serve_as`): a leader-capable node
        serves as ``peer`` and as ``leader`` with the same warm pool.
    workers : int
        Worker processes (default: CPU count).
    process : str
        ``"module:function"`` process function (tests inject a stub).
    max_request_bytes : int
        Larger payloads get an ``oversized`` error reply.
    max_inflight : int, optional
        Limit of the default admission (default ``8 * workers``).
    admission : callable, optional
        Replaces :func:`default_admission`.
    budget_ms : float
        The default admission's latency budget (``scmr cloud --budget-ms``).
    clock : scmr_mesh.mesh.startup.StartupClock, optional
        Marks the start-up phases (``scmr -v cloud`` prints them).
    """

    def __init__(
        self,
        node: str,
        *,
        tier: str = "cloud",
        workers: int | None = None,
        process: str = DEFAULT_PROCESS,
        max_request_bytes: int = wire.MAX_REQUEST_BYTES,
        max_inflight: int | None = None,
        admission: Admission | None = None,
        budget_ms: float = DEFAULT_BUDGET_MS,
        clock=None,
    ) -> None:
        from scmr_mesh._cpu import usable_cores

        keys.check_name(node)
        if tier not in keys.TIERS:
            raise InputError(f"tier must be one of {keys.TIERS}, got {tier!r}")
        workers = int(workers or usable_cores())
        self.node = node
        self.tier = tier
        self.key = keys.drivable(tier, node)
        #: (clock_hz, power_w) of this server's energy profile, published with its load
        self.capability: tuple[float, float | None] | None = None
        self.max_request_bytes = int(max_request_bytes)
        if not budget_ms > 0:
            raise InputError(f"--budget-ms must be > 0, got {budget_ms}")
        self.state = ServiceState(node, tier, workers, int(max_inflight or 8 * workers), budget_ms=float(budget_ms))
        self.admission: Admission = admission or default_admission
        self.negotiator = None
        #: ``fn(robot) -> int | None``: the highest priority the fleet's policy grants a robot
        #: (None: no cap); set from the security profile's fleet (docs/SECURITY.md)
        self.priority_cap: Callable[[str], int | None] | None = None
        self._capped: set[str] = set()
        self.session = None
        self._extra: list[tuple[str, Callable, bool]] = []
        self._declared: list[Any] = []
        self._token = None
        self._load_pub = None
        self._stop = threading.Event()
        self._load_thread: threading.Thread | None = None
        self.replier = Replier()
        self._error_log: dict[str, tuple[float, int]] = {}  # code -> (INFO line at, replies since)
        self._error_log_lock = threading.Lock()
        #: requests taken in lately: a later copy of one gets the first copy's answer (hedged and re-sent requests)
        self.recent = RecentRequests()
        self.pool = WorkerPool(workers, process=process, clock=clock)
        self.state.outstanding = self.pool.outstanding
        self.worker_pids = self.pool.start()
        if clock is not None:
            clock.mark("worker pool", workers=workers)
        wire.warm()
        if clock is not None:
            clock.mark("wire validators")
        log.info("%s %s: %d workers ready %s", tier, node, workers, self.worker_pids)

    # ------------------------------------------------------------ hooks
    def add_queryable(self, key: str, callback: Callable, *, complete: bool = False) -> None:
        """Declare an extra queryable on this service's session (now or at attach)."""
        self._extra.append((key, callback, complete))
        if self.session is not None:
            self._declared.append(self.session.declare_queryable(key, callback, complete=complete))

    # ------------------------------------------------------- life cycle
    def serve_as(self, tier: str, extra: list[tuple[str, Callable]] | None = None) -> None:
        """Serve ``tier`` at the next :meth:`attach`, with these extra queryables (while detached)."""
        if self.session is not None:
            raise RuntimeError(f"{self.tier} {self.node}: detach before changing the tier")
        if tier not in keys.TIERS:
            raise InputError(f"tier must be one of {keys.TIERS}, got {tier!r}")
        self.tier = self.state.tier = tier
        self.key = keys.drivable(tier, self.node)
        self._extra = [(k, cb, False) for k, cb in (extra or [])]

    def attach(self, session, *, clock=None, warm: bool = True) -> None:
        """Declare the queryable, extra queryables, the load publisher, then the token.

        ``warm=False`` skips the warm-up query (the pool already served).
        """
        self.session = session
        self._stop.clear()
        self._declared.append(session.declare_queryable(keys.drivable_serve(self.tier, self.node), self._on_query,
                                                        complete=True))
        for key, cb, complete in self._extra:
            self._declared.append(session.declare_queryable(key, cb, complete=complete))
        self._load_pub = session.declare_publisher(keys.load(self.tier, self.node))
        if clock is not None:
            clock.mark("queryables")
        if warm:
            self._warm_path(session)
            if clock is not None:
                clock.mark("warm-up query")
        # the token last: a robot that sees it finds the queryable in place
        self._token = session.liveliness().declare_token(keys.alive(self.tier, self.node))
        if clock is not None:
            clock.mark("token")
        self._stop.clear()
        self._load_thread = threading.Thread(target=self._publish_load, name="scmr-load", daemon=True)
        self._load_thread.start()
        log.info("%s %s serving on %s", self.tier, self.node, self.key)

    def _warm_path(self, session) -> None:
        """Send one real request to ourselves (same session) before announcing.

        The first query of a process pays for zenoh's callback thread, the pool
        hand-off and the reply path (about 150 ms measured under load); paying
        it here keeps it out of the first robot's ToR and the failback gap.
        """
        from scmr_mesh.mesh.work import warm_png

        req = wire.make_request("warmup", 0, warm_png(), encoding="png")
        t0 = time.perf_counter()
        ok = False
        try:
            for reply in session.get(keys.drivable_request(self.tier, self.node, "warmup"), payload=wire.encode(req),
                                 encoding=_msgpack(), timeout=30.0):
                ok = reply.ok is not None
        except Exception as exc:
            log.warning("warm-up query failed: %s", exc)
        end = time.monotonic() + 5.0
        while self.replier.pending and time.monotonic() < end:  # its sender counts it as served
            time.sleep(0.001)
        with self.state.lock:
            self.state.served = 0
        log.info("%s %s warm-up query %s in %.1f ms", self.tier, self.node, "ok" if ok else "FAILED",
                 (time.perf_counter() - t0) * 1e3)

    def detach(self, *, drain_s: float = 2.0) -> None:
        """Undeclare everything: the token first (robots stop sending here), then
        wait up to ``drain_s`` for admitted requests to be answered, then the rest."""
        self._stop.set()
        tok, self._token = self._token, None
        if tok is not None:
            try:
                tok.undeclare()
            except Exception as exc:
                log.debug("undeclare token: %s", exc)
        end = time.monotonic() + drain_s
        while time.monotonic() < end and (self.state.inflight > 0 or self._waiting() > 0
                                          or self.replier.pending > 0):
            time.sleep(0.01)
        if drain_s > 0 and (self.state.inflight or self._waiting() or self.replier.pending):
            log.warning("%s %s: stopping with %d requests unanswered", self.tier, self.node,
                        self.state.inflight + self._waiting() + self.replier.pending)
        for obj in [*self._declared, self._load_pub]:
            if obj is None:
                continue
            try:
                obj.undeclare()
            except Exception as exc:  # already gone with the session
                log.debug("undeclare: %s", exc)
        self._token = None
        self._declared = []
        self._load_pub = None
        if self._load_thread is not None:
            self._load_thread.join(timeout=1.0)
        self.session = None

    def _waiting(self) -> int:
        neg = self.negotiator
        try:
            return int(getattr(neg, "waiting", 0) or 0) if neg is not None else 0
        except Exception:
            return 0

    def shutdown(self) -> None:
        """Stop the worker pool (and the negotiator, answering what still waits)."""
        if self.negotiator is not None:
            for e in self.negotiator.close():
                query, req, _ = e.payload
                self._fail_all(query, req, "unavailable", "service shutting down; send it to another tier")
        self.replier.close()
        self.pool.shutdown()

    # ------------------------------------------------------------ serving
    def _publish_load(self) -> None:
        last = None
        while not self._stop.wait(LOAD_PERIOD_S):
            st = self.state
            now = (st.inflight, st.served)
            pub = self._load_pub
            if pub is None:
                return
            if now == last and st.inflight == 0:
                continue  # idle: publish on change only
            last = now
            cap = self.capability or (None, None)
            msg = wire.make_load(self.node, self.tier, workers=st.workers, inflight=st.inflight, served=st.served,
                                 clock_hz=cap[0], power_w=cap[1])
            try:
                pub.put(wire.encode(msg), encoding=_msgpack())
            except Exception as exc:
                log.debug("load publish failed: %s", exc)

    def _reply_error(self, query, code: str, message: str, request=None, retry_after_ms=None,
                     tier: str | None = None) -> None:
        tier = tier or ((request or {}).get("_tier", self.tier) if isinstance(request, dict) else self.tier)
        msg = wire.make_error(
            code, message, served_by=self.node, tier=tier, request=request, retry_after_ms=retry_after_ms
        )
        with self.state.lock:
            if code == "busy":
                self.state.refused += 1
            else:
                self.state.errors += 1
        self._log_error_reply(code, msg, message)
        payload = wire.encode(msg)

        def send() -> None:
            try:
                query.reply_err(payload, encoding=_msgpack())
            except Exception as exc:
                log.warning("could not send error reply: %s", exc)
            finally:
                _drop(query)

        self.replier.send(send)

    def _log_error_reply(self, code: str, msg: dict, message: str) -> None:
        """Log an error reply: the first of each code in a second at INFO with how many the last
        second held, the rest at DEBUG.  Under overload a line per busy answer cost the service
        about a tenth of its interpreter time (py-spy --gil, 32 robots on 2 cores), the very time
        it was short of; the counts stay exact in the state (``refused``, ``errors``)."""
        now = _clock()
        with self._error_log_lock:
            since, n = self._error_log.get(code, (None, 0))
            first = since is None or now - since >= ERROR_LOG_PERIOD_S
            self._error_log[code] = (now, 0) if first else (since, n + 1)
        if first:
            more = f" ({n} more {code} replies since the last such line, at debug level)" if n else ""
            log.info("error reply %s to %s/%s: %s%s", code, msg["robot"], msg["seq"], message, more)
        else:
            log.debug("error reply %s to %s/%s: %s", code, msg["robot"], msg["seq"], message)

    def _on_query(self, query) -> None:
        t_arrival = time.perf_counter()
        seen = None
        try:
            key = str(query.key_expr)
            target = keys.request_target(key)
            if target is None or target[1] != self.node:
                # a wildcard selector would make every service run the pipeline, and the
                # replies would all be keyed alike: refuse it before reading the payload
                self._reply_error(query, "malformed",
                                  f"query key {key!r} does not name one service and one robot; send each "
                                  f"request to scmr/drivable/<tier>/<node>/<your robot id>, e.g. "
                                  f"{keys.drivable_request(self.tier, self.node, 'r1')} (docs/protocol.md)")
                return
            tier, _node, sender = target
            payload = query.payload
            if payload is None:
                self._reply_error(query, "malformed", "query carries no payload; send a msgpack request", tier=tier)
                return
            data = payload.to_bytes()
            try:
                req = wire.decode(data, kind="request", max_bytes=self.max_request_bytes)
            except wire.WireProblem as exc:  # robot and seq echoed when they could be read
                self._reply_error(query, exc.code, str(exc), exc.partial, tier=tier)
                return
            req["_tier"] = tier  # the tier it arrived on, even if the role changes meanwhile
            if req["robot"] != sender:
                self._reply_error(query, "forbidden",
                                  f"request names robot {req['robot']!r} but came on {key!r} (robot {sender!r}); "
                                  f"a robot sends only its own requests, on "
                                  f"{keys.drivable_request(tier, self.node, req['robot'])}", req)
                return
            self._cap_priority(req)
            seen, kept = self.recent.admit(_ident(req), query)
            if req.get("receipt") and seen in ("new", "joined"):
                self._send_receipt(query, req, tier)
            if seen == "joined":  # answered with the first copy's answer (_finish)
                return
            if seen == "cached":
                self._send_reply(query, kept, req)
                return
            if seen == "duplicate":
                self._reply_error(query, "duplicate",
                                  f"request {req['robot']}/{req['seq']} already reached {self.node} (a hedged copy) "
                                  "and its answer is no longer kept; it is served once: wait for the first "
                                  "copy's answer", req)
                return
            refusal = self.admission(req, self.state)
            if refusal is not None:
                self._refuse_copies(req, refusal.code, refusal.message, refusal.retry_after_ms)
                self._reply_error(query, refusal.code, refusal.message, req, refusal.retry_after_ms)
                return
            if self.negotiator is not None:
                self._negotiate(query, req, t_arrival)
                return
            with self.state.lock:
                self.state.inflight += 1
            t_sub = time.perf_counter()
            try:
                fut = self.pool.submit(req["image"], encoding=req["encoding"], shape=req["shape"], mode=req["mode"],
                                       expires_mono=_expiry(req, t_arrival))
            except BaseException:
                with self.state.lock:  # its slot back: a node whose pool failed to take frames must not stay busy
                    self.state.inflight -= 1
                raise
        except Exception as exc:  # never let a query go unanswered
            log.exception("query handling failed")
            if seen == "new":  # and none of the copies that joined it
                self._fail_all(query, req, "internal", f"{type(exc).__name__}: {exc}")
            else:
                self._reply_error(query, "internal", f"{type(exc).__name__}: {exc}")
            return
        fut.add_done_callback(lambda f: self._finish(query, req, f, t_arrival, t_sub))

    def _send_receipt(self, query, req: dict, tier: str) -> None:
        """Tell the robot that ``req`` is here (it asked: ``receipt``); its answer follows.

        Queued on the reply senders like every reply, never sent from zenoh's callback
        thread: a reply inherits its query's congestion control (zenoh 1.10 ignores a
        reply's own), and a client whose link is stuck would hold that thread, and with
        it the reception of every other query, up to ``wait_before_close``.  Queued at
        once, it goes out long before an answer that needs the pipeline; a copy that joins a
        run about to finish, or a request refused at once, may see its answer first (robots
        ignore a receipt after the answer; docs/protocol.md says clients must too).
        """
        try:
            payload = wire.encode(wire.make_receipt(req, served_by=self.node, tier=tier))
        except Exception as exc:  # the answer still follows; without the receipt the robot may hedge
            log.debug("receipt to %s/%s not built: %s", req.get("robot"), req.get("seq"), exc)
            return

        def send() -> None:
            try:
                query.reply(str(query.key_expr), payload, encoding=_msgpack())
            except Exception as exc:  # the query was answered and dropped meanwhile
                log.debug("receipt to %s/%s not sent: %s", req.get("robot"), req.get("seq"), exc)

        self.replier.send(send)

    def _cap_priority(self, req: dict) -> None:
        """Lower ``req["priority"]`` to the fleet's cap for its (key-bound) robot."""
        cap_of = self.priority_cap
        if cap_of is None:
            return
        cap = cap_of(req["robot"])
        if cap is not None and req["priority"] > cap:
            if req["robot"] not in self._capped:
                self._capped.add(req["robot"])
                log.info("%s %s: robot %s asks priority %d, the fleet grants at most %d: served at %d", self.tier,
                         self.node, req["robot"], req["priority"], cap, cap)
            req["priority"] = cap

    # ------------------------------------------------- priority negotiator
    def use_negotiator(self, negotiator) -> None:
        """Rank requests with ``negotiator`` (see :mod:`scmr_mesh.qos.negotiator`); before attach."""
        self.negotiator = negotiator
        self.state.queue_managed = True
        threading.Thread(target=self._dispatch, name="scmr-dispatch", daemon=True).start()

    def _negotiate(self, query, req: dict, t_arrival: float) -> None:
        neg = self.negotiator
        d = neg.offer((req["robot"], req["seq"]), req["priority"], robot=req["robot"],
                      payload=(query, req, t_arrival), size=len(req["image"]))
        for e in d.refused:
            q, r, _ = e.payload
            msg = (f"server too busy, try later: request {r['robot']}/{r['seq']} with priority {e.priority} "
                   f"{e.reason} ({neg.waiting} waiting, {neg.in_service} in service, queue {neg.capacity}); "
                   "send it to another tier or run it locally")
            retry = d.retry_after_ms or neg.retry_after_ms()
            self._refuse_copies(r, "busy", msg, retry)
            self._reply_error(q, "busy", msg, r, retry)

    def _dispatch(self) -> None:
        neg = self.negotiator
        while True:
            e = neg.take()
            if e is None:  # closed
                return
            query, req, t_arrival = e.payload
            with self.state.lock:
                self.state.inflight += 1
            t_sub = time.perf_counter()
            try:
                fut = self.pool.submit(req["image"], encoding=req["encoding"], shape=req["shape"], mode=req["mode"],
                                      expires_mono=_expiry(req, t_arrival))
            except Exception as exc:
                with self.state.lock:
                    self.state.inflight -= 1
                neg.done(e)
                self._fail_all(query, req, "internal", f"{type(exc).__name__}: {exc}")
                continue

            def finished(f, e=e, query=query, req=req, t_arrival=t_arrival, t_sub=t_sub):
                neg.done(e, service_s=time.perf_counter() - t_sub)
                self._finish(query, req, f, t_arrival, t_sub)

            fut.add_done_callback(finished)

    def _finish(self, query, req: dict, fut, t_arrival: float, t_sub: float) -> None:
        try:
            out = fut.result()
        except BaseException:
            out = None
        with self.state.lock:
            self.state.inflight -= 1
            if out is not None:
                self.state.note_service(float(out.get("worker_ms", 0.0)))
        try:
            out = fut.result()
        except (ImageDecodeError, InputError) as exc:
            self._fail_all(query, req, "malformed", _image_message(req, exc))
            return
        except Expired as exc:
            self._fail_all(query, req, "expired", f"not processed: {exc} (deadline {req.get('deadline_ms')} ms)")
            return
        except Exception as exc:
            log.error("worker failed on %s/%s: %s: %s", req["robot"], req["seq"], type(exc).__name__, exc)
            self._fail_all(query, req, "internal", f"{type(exc).__name__}: {exc}")
            return
        now = time.perf_counter()
        worker_ms = float(out.get("worker_ms", 0.0))
        try:
            reply = wire.make_reply(
                req,
                mask_png=out["mask_png"],
                shape=out["shape"],
                threshold=out["threshold"],
                timings_ms=out.get("timings_ms", {}),
                served_by=self.node,
                tier=req.get("_tier", self.tier),
                server_ms=(now - t_arrival) * 1e3,
                queue_ms=max(0.0, (now - t_sub) * 1e3 - worker_ms),
                confidence=out.get("confidence"),
                abstained=out.get("abstained"),
            )
            payload = wire.encode(reply)
        except Exception as exc:
            log.error("reply to %s/%s failed: %s", req["robot"], req["seq"], exc)
            self._fail_all(query, req, "internal", f"reply not built: {type(exc).__name__}: {exc}")
            return
        self._send_reply(query, payload, req, served=True)
        for q in self.recent.complete(_ident(req), payload):  # later copies that waited for this answer
            self._send_reply(q, payload, req)

    def _send_reply(self, query, payload: bytes, req: dict, *, served: bool = False) -> None:
        """Send a good reply to ``query`` on a sender thread (``served``: count it as a frame served)."""

        def send() -> None:
            try:
                query.reply(str(query.key_expr), payload, encoding=_msgpack())  # the concrete request key
                if served:
                    with self.state.lock:
                        self.state.served += 1
            except Exception as exc:
                log.error("reply to %s/%s failed: %s", req["robot"], req["seq"], exc)
            finally:
                _drop(query)

        self.replier.send(send)

    def _fail_all(self, query, req: dict, code: str, message: str) -> None:
        """The first copy of ``req`` failed with ``code``: that error to it and to every copy that waited."""
        for q in [query, *self.recent.complete(_ident(req), None)]:
            self._reply_error(q, code, message, req)

    def _refuse_copies(self, req: dict, code: str, message: str, retry_after_ms) -> None:
        """``req`` is refused (busy): forget it, so a later copy may be taken in, and refuse the copies that waited."""
        for q in self.recent.forget(_ident(req)):
            self._reply_error(q, code, message, req, retry_after_ms)


def _msgpack():
    from scmr_mesh.mesh.encoding import msgpack

    return msgpack()


def _image_message(req: dict, exc: Exception) -> str:
    """What a robot reads when its image does not decode: what was received and the fix, in wire terms.

    The decoder's own hint is about its Python API (``shape=(H, W)``); on the
    wire a raw frame carries ``shape: [H, W, 3]``, so the hint is replaced.
    """
    reason = str(exc).split("; pass ", 1)[0]
    shape = req.get("shape")
    got = f"encoding {req.get('encoding')!r}, {len(req.get('image') or b'')} bytes" + (
        f", shape {list(shape)}" if shape is not None else "")
    return (f"image unusable ({got}): {reason}; send PNG or JPEG bytes with encoding 'png'/'jpeg' and "
            "shape null, or raw RGB rows with encoding 'raw', shape [H, W, 3] and H*W*3 bytes")


def _expiry(req: dict, t_arrival: float) -> float | None:
    """``time.monotonic()`` after which the robot no longer waits (from ``deadline_ms``).

    Counted from the query's arrival here (``t_arrival`` is ``perf_counter``,
    converted), so no clock sync between robot and service is needed; transit
    time is ignored, which errs on the side of doing the work.
    """
    d = req.get("deadline_ms")
    if not d:
        return None
    return time.monotonic() - (time.perf_counter() - t_arrival) + float(d) / 1e3


#: How long :func:`_drop` tries to finalise a query whose other reply (its receipt) is being sent.
DROP_RETRY_S = 0.05


def _drop(query) -> None:
    """Finalise ``query`` (its robot's ``get`` ends).  zenoh-python refuses ``drop`` with "Already
    borrowed" while another thread is inside ``reply`` on the same query (a receipt on another reply
    sender; docs/ZENOH.md section 18): tried again until that send is over, at most
    :data:`DROP_RETRY_S`; then the query ends when it is freed."""
    deadline = time.monotonic() + DROP_RETRY_S
    while True:
        try:
            query.drop()
            return
        except RuntimeError as exc:
            if "borrow" not in str(exc) or time.monotonic() > deadline:
                return
            time.sleep(0.0002)  # a receipt is 90 bytes: its reply call takes microseconds
        except Exception:  # already finalised
            return
