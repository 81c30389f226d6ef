"""The robot client: what ``scmr robot`` runs (and ``scmr leader`` with robot flags).

Modules: this one (:class:`Robot`: the session, the request path, the send loop),
:mod:`scmr_mesh.mesh.liveview` (the live view of the mesh and the placement rule) and
:mod:`scmr_mesh.mesh.frames` (frame sources); their public names are importable from here.

A :class:`Robot` takes frames from a source (a folder of images or a synthetic
scene), puts each in its outbox, sends it as a request to a serving tier and
writes the result to its inbox and one line of ``records.jsonl``.

Routing
-------
The robot keeps a live view (:class:`LiveView`) of which nodes are alive,
from a liveliness subscriber on ``scmr/alive/**`` (``history=True``), of
their load (``scmr/load/**``) and of who leads the R2R tier (candidacies on
``scmr/r2r/candidate/*``, docs/R2R.md).  For each frame the *placement*
function returns the tiers to try, in order; the default
(:func:`default_placement`) is ``cloud`` if a cloud node is alive, then the
elected ``leader``, then (no cloud alive) ``peer`` robots with spare
capacity, then ``local`` when local fallback is on.  Within the cloud tier the
least loaded alive node is tried first (then one more); within the peer tier
the least loaded, then fastest.  Each attempt is gated on the
querier's matching status (a queryable is really there) and bounded by the
per-request deadline (``--deadline-ms``): when it passes, or the server dies
mid-request (no reply), or it answers with an error, the request is re-sent
at once to the next candidate, so requests in flight when a link dies are
still answered.  When nothing answers the robot runs the pipeline itself
(``--local-fallback``, default) or writes an explicit failure record: it never
hangs.  ``--redundant`` sends each frame to the best cloud node and a leader at
once and keeps the first good reply (``bytes_up`` counts both sends).

Hedged requests (issue 24, docs/R2R.md): when the tier tried first has not
answered within a hedge delay learnt from its recent answers
(:mod:`scmr_mesh.qos.hedge`; ``--hedge-ms``), the same request goes to the first
node of the next live tier; the first good answer wins and the other query is
cancelled.  A hedge as silent as the first copy is sent once more to its node
(a starved sender can drop a query or its reply; the node serves a request once
and answers every copy).  A ``busy`` answer never triggers a hedge, no hedge goes
to a saturated node, and hedges and re-sends are rationed (a token bucket per robot).

Output (``--out DIR``)
----------------------
* ``DIR/outbox/<seq>.<ext>``: frames waiting for an answer (written while the request is
  out, removed when done).
* ``DIR/inbox/<seq>.mask.png``: the (225, 300) mask, 255 = drivable.
* ``DIR/records.jsonl``: one JSON object per finished request, flushed per
  line: ``robot, seq, image, bytes_up, bytes_down, sent_unix_ns,
  received_unix_ns, tor_ms, ok, tier ("cloud"|"leader"|"peer"|"local"|null),
  served_by, attempts [{tier, node, outcome, t_unix_ns, hedge?, resend?}], error, server_ms,
  hedged, hedge_won, confidence, abstained`` (``confidence`` and ``abstained``: the road
  model's trust in the mask and why it shrank it, issue 27; null from servers that do not
  send them and in ``thesis`` mode).
  ``sent_unix_ns`` is when the first attempt was sent.  Attempt outcomes:
  ``ok``, ``timeout``, ``no_reply`` (server gone mid-request), ``unreachable``
  (no matching queryable), ``error:<code>``, ``superseded`` (redundant mode, or another copy of the request
  answered first, or the copy was given up for its re-send),
  ``bad_reply``, ``mismatched`` (the node's reply did not echo this request's robot, seq and frame digest:
  a replayed or wrong answer, never used; the attempt's ``mismatched`` counts such replies, and the record's
  ``mismatched`` sums them).

Hooks
-----
* :meth:`Robot.add_observer` ``fn(record: dict, rgb: ndarray, mask: ndarray | None)``
  is called after each request (rgb is the (H, W, 3) uint8 frame, mask the
  (225, 300) uint8 mask or None).  The viz engineer logs overlays from it.
* ``Robot.placement``: ``fn(view: Reachable, frame: FrameInfo) -> sequence of
  "cloud" | "leader" | "peer" | "local"``, the tiers to try in order (energy policy).
* ``Robot.annotators``: ``fn(record: dict, reply: dict | None)`` called before each
  record is written; may add keys (the energy placer adds ``energy_j`` and
  ``energy``).  ``reply`` is the decoded reply, or for local runs
  ``{"mask_png", "cpu_ms", "timings_ms"}`` (``cpu_ms``: thread CPU time).
* ``Robot.publish_telemetry(message: dict)``: publishes one telemetry message on
  ``scmr/telemetry/<robot>``; wrap or replace it to also store telemetry.
  :meth:`Robot.make_telemetry` builds the message.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import queue
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

from scmr_mesh import keys, wire
from scmr_mesh.data.retention import DEFAULT_KEEP_MASKS, Retention
from scmr_mesh.errors import InputError
from scmr_mesh.mesh.attempts import BUSY, Outcome, Reply, error_outcome
from scmr_mesh.mesh.resources import undeclare_all
from scmr_mesh.qos.schedule import Schedule
from scmr_mesh.vocab import Tier

from scmr_mesh.mesh.frames import (  # noqa: F401 - re-exported: importers of the robot module
    ENCODE_CACHE_FILES, IMAGE_SUFFIXES, JPEG_QUALITY, SYNTHETIC_SET, Frame, check_jpeg_quality,
    frames_from_args, image_frames, pick_seed, synthetic_frames,
)
from scmr_mesh.mesh.liveview import FrameInfo, LiveView, Placement, Reachable, default_placement  # noqa: F401

log = logging.getLogger(__name__)


#: Threads of the process's outbox writer, shared by all its robots (a swarm holds up to 256):
#: a few, so one slow write does not hold every robot's delivery behind it.
OUTBOX_THREADS = 4
_OUTBOX_LOCK = threading.Lock()
_OUTBOX: list = [None]  # the process's outbox writer, made on first use


def _outbox_reset_in_child() -> None:
    """A forked child inherits the executor without its threads, and maybe the lock held: start afresh."""
    global _OUTBOX_LOCK
    _OUTBOX_LOCK = threading.Lock()
    _OUTBOX[0] = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_outbox_reset_in_child)


def _outbox_submit(fn, *args):
    """Run ``fn(*args)`` once, on the process's outbox threads; a future of its result.

    When the executor refuses it (the interpreter is shutting down: "cannot schedule new
    futures", or a thread limit: "can't start new thread", raised after the job was queued),
    ``fn`` runs here and the future is done.  The job and that fallback share a flag under a
    lock, so whichever comes first writes and the other does nothing: a queued job that a
    thread picks up later never writes a frame that was already delivered and removed.
    """
    from concurrent.futures import Future, ThreadPoolExecutor

    once, ran = threading.Lock(), [False]

    def job():
        with once:
            if ran[0]:
                return args[0] if args else None
            ran[0] = True
            return fn(*args)

    with _OUTBOX_LOCK:
        if _OUTBOX[0] is None:
            _OUTBOX[0] = ThreadPoolExecutor(OUTBOX_THREADS, thread_name_prefix="scmr-outbox")
        ex = _OUTBOX[0]
    try:
        return ex.submit(job)
    except RuntimeError:
        done: Future = Future()
        done.set_result(job())
        return done


#: File suffix of a frame in the outbox, by encoding.
FRAME_SUFFIX = {"png": ".png", "jpeg": ".jpg", "raw": ".rgb"}


@dataclass
class _Trip:
    """One request's way through the tiers: its attempts, the nodes tried, bytes sent, the winner."""

    attempts: list[dict] = field(default_factory=list)
    tried: set[tuple[str, str]] = field(default_factory=set)
    bytes_up: int = 0
    winner: Reply | None = None
    hedged: bool = False     # a second copy went to another tier (at most one per request)
    hedge_won: bool = False  # and it answered first
    #: what a reply must echo to answer this request: robot, seq, frame digest (wire.asked_of)
    asked: dict = field(default_factory=dict)


@dataclass
class _Sent:
    """One query sent on its node's thread: its attempt record, its future, its cancellation token."""

    att: dict
    fut: Any
    token: Any
    #: the copy of ``att`` the tier's thread writes; read back when the query is given up on
    scratch: dict = field(default_factory=dict)
    #: ``time.perf_counter()`` when the request was first sent to this node (a re-sent copy keeps its
    #: first copy's): its answer time counts from there
    t0: float = 0.0
    #: set when the node's receipt for this copy came, or the copy finished (whichever first)
    heard: threading.Event = field(default_factory=threading.Event)

    def cancel(self) -> None:
        try:
            self.token.cancel()
        except Exception:  # already finished
            pass

    def give_up(self, outcome: str) -> None:
        """Cancel the query and set its attempt's ``outcome``, keeping the replies it refused so far.

        A node that sent a mismatched or untrusted reply and then held its query open
        (e.g. a hedge answered first) is still counted in the record, and so is the receipt
        of a node that had the request (``receipt_ms``).
        """
        self.cancel()
        self.att["outcome"] = outcome
        n = self.scratch.get("mismatched")
        if n:
            self.att["mismatched"] = n
            self.att.setdefault("message", self.scratch.get("message"))
        receipt_ms = self.scratch.get("receipt_ms")
        if receipt_ms is not None:  # its node had it, yet never answered in time
            self.att["receipt_ms"] = receipt_ms
            self.att["receipt_bytes"] = self.scratch.get("receipt_bytes", 0)


@dataclass
class RobotOptions:
    """Settings of a :class:`Robot` (the ``scmr robot`` flags)."""

    deadline_ms: float = 1000.0
    redundant: bool = False
    local_fallback: bool = True
    priority: int = 0
    mode: str = "best"
    process: str = "scmr_mesh.mesh.work:process_frame"
    max_nodes_per_tier: int = 2
    #: hedged requests (docs/R2R.md "Hedged requests"): a silent tier is hedged to the next live one
    hedge: bool = True
    #: a fixed hedge delay (ms); None: learnt per tier from its recent answers (scmr_mesh.qos.hedge)
    hedge_ms: float | None = None
    #: masks kept in OUT/inbox, newest first (older ones are deleted); None keeps every mask
    keep_masks: int | None = DEFAULT_KEEP_MASKS


class Robot:
    """A robot peer: sends frames to the mesh and records what happened.

    Parameters
    ----------
    robot_id : str
        Robot id (a key chunk).
    out_dir : path
        Output folder (outbox/, inbox/, records.jsonl).
    options : RobotOptions, optional
    placement : callable, optional
        Replaces :func:`default_placement`.

    Notes
    -----
    Call :meth:`attach` with an open zenoh session, then :meth:`request` per
    frame or :meth:`run` for a paced loop; :meth:`close` flushes the records.
    """

    def __init__(self, robot_id: str, out_dir: str | Path, *, options: RobotOptions | None = None,
                 placement: Placement | None = None) -> None:
        self.id = keys.check_name(robot_id, what="robot id")
        self.options = options or RobotOptions()
        self.placement: Placement = placement or default_placement
        self.view = LiveView(self.id)
        self.out = Path(out_dir)
        self.outbox = self.out / "outbox"
        self.inbox = self.out / "inbox"
        try:
            self.outbox.mkdir(parents=True, exist_ok=True)
            self.inbox.mkdir(parents=True, exist_ok=True)
            self._records = open(self.out / "records.jsonl", "a", buffering=1, encoding="utf-8")
            self.masks = Retention(self.inbox, keep=self.options.keep_masks)
        except OSError as exc:
            raise InputError(f"--out {self.out}: cannot create the robot's folders ({exc})") from None
        self._observers: list[Callable] = []
        self.annotators: list[Callable[[dict, Any], None]] = []
        self._queriers: dict[str, Any] = {}
        self._born: dict[str, float] = {}  # querier key -> when it was declared (monotonic s)
        self._node_threads: dict[tuple[str, str], Any] = {}  # (tier, node) -> its sender threads (_start)
        self._session = None
        self._subs: list[Any] = []
        self._token = None
        self._tele_pub = None
        self._res_pub = None
        self._local_fn = None
        self._local_ok: bool | None = None
        self.stats = {"requests": 0, "succeeded": 0, "by_tier": {"cloud": 0, "leader": 0, "peer": 0, "local": 0},
                      "last_tor_ms": None, "last_tier": None, "mismatched": 0}
        #: replies refused because they did not answer the request they came for (robot, seq, frame
        #: digest: wire.reply_mismatch), by "tier/node" of the node that sent them
        self.mismatched: dict[str, int] = {}
        self._mismatch_lock = threading.Lock()
        self._t0 = time.monotonic()
        self._last_seq = 0
        self._health = "ok"
        #: telemetry messages whose publishing raised (counted; the robot keeps sending frames)
        self.telemetry_errors = 0
        self._telemetry_handlers: list[Callable[[dict, Callable[[dict], Any]], Any]] = []
        from scmr_mesh.qos.hedge import AnswerTimes, HedgeBudget

        self._answer_times = {t: AnswerTimes() for t in keys.TIERS}
        #: the time from a copy's send to its node's receipt, by (tier, node), and over every node (a
        #: node not heard from enough yet, e.g. the leader at the cloud's loss, uses the pooled one)
        self._receipt_times: defaultdict[tuple[str, str], AnswerTimes] = defaultdict(lambda: AnswerTimes(warmup=0))
        self._receipt_all = AnswerTimes(warmup=0)
        #: answers in a row that came with no receipt, by (tier, node): a node that sends none
        #: (a server outside the project, or one whose receipts are lost) is not expected to
        self._unreceipted: dict[tuple[str, str], int] = {}
        self._hedge_budget = HedgeBudget()

    # ------------------------------------------------------------ hooks
    def add_observer(self, fn: Callable[[dict, Any, Any], None]) -> None:
        """Call ``fn(record, rgb, mask)`` after each request (see module docstring)."""
        self._observers.append(fn)

    def publish_telemetry(self, message: dict) -> None:
        """Publish one telemetry message on ``scmr/telemetry/<robot>``."""
        if self._tele_pub is not None:
            self._tele_pub.put(wire.encode(message), encoding=_msgpack())

    def add_telemetry_handler(self, fn: Callable[[dict, Callable[[dict], Any]], Any]) -> None:
        """Hand each telemetry message to ``fn(message, forward)`` instead of publishing it.

        ``forward(message)`` passes it on to the handler added before (or to
        :meth:`publish_telemetry` for the first), so handlers chain in the
        order they were added: the data tier's queue (``TelemetryAgent``), the
        rerun sink, ...  No attribute is replaced; :meth:`remove_telemetry_handler` undoes it.
        """
        self._telemetry_handlers.append(fn)

    def remove_telemetry_handler(self, fn: Callable) -> None:
        """Undo :meth:`add_telemetry_handler` (a handler not added is ignored)."""
        if fn in self._telemetry_handlers:
            self._telemetry_handlers.remove(fn)

    def emit_telemetry(self, message: dict) -> Any:
        """Send one telemetry message through the handlers (last added first), then publish it."""
        def through(i: int) -> Callable[[dict], Any]:
            if i < 0:
                return self.publish_telemetry
            return lambda m: self._telemetry_handlers[i](m, through(i - 1))

        return through(len(self._telemetry_handlers) - 1)(message)

    def battery(self) -> float:
        """Simulated state of charge, 0..1: two hours of driving, and each local pipeline run costs 0.02 %."""
        t = time.monotonic() - self._t0
        return max(0.0, 1.0 - t / 7200.0 - 2e-4 * self.stats["by_tier"]["local"])

    def make_telemetry(self) -> dict:
        """The current telemetry message (simulated pose and battery, real results)."""
        t = time.monotonic() - self._t0
        pose = {"x": 10.0 * math.cos(0.05 * t), "y": 10.0 * math.sin(0.05 * t), "theta": (0.05 * t + math.pi / 2) % (2 * math.pi)}
        battery = self.battery()
        return wire.make_telemetry(self.id, self._last_seq, pose=pose, battery=battery, health=self._health,
                                   results=dict(self.stats, by_tier=dict(self.stats["by_tier"])))

    # ------------------------------------------------------- life cycle
    def attach(self, session) -> None:
        """Subscribe to liveliness and load, declare publishers and the robot's token."""
        self._session = session
        self._subs.append(session.liveliness().declare_subscriber(keys.ALIVE_ALL, self.view.on_liveliness, history=True))
        self._subs.append(session.declare_subscriber(keys.LOAD_ALL, self.view.on_load))
        self._subs.append(session.declare_subscriber(keys.CANDIDATES_ALL, self.view.on_candidate))
        self._tele_pub = session.declare_publisher(keys.telemetry(self.id))
        self._res_pub = session.declare_publisher(keys.results(self.id))
        self._token = session.liveliness().declare_token(keys.alive("robot", self.id))

    def __enter__(self):
        """``with`` owns the Zenoh resources this object declares: leaving it calls :meth:`close`."""
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything this robot declared and close the records file."""
        for ex in self._node_threads.values():
            ex.shutdown(wait=False, cancel_futures=True)
        undeclare_all([self._token, *self._subs, *self._queriers.values(), self._tele_pub, self._res_pub])
        self._subs, self._queriers, self._token = [], {}, None
        self._tele_pub = self._res_pub = None
        try:
            self._records.close()
        except Exception:
            pass

    # ------------------------------------------------------------ work
    def _querier(self, tier: str, node: str):
        key = keys.drivable_request(tier, node, self.id)
        q = self._queriers.get(key)
        if q is None:
            import zenoh

            q = self._session.declare_querier(
                key,
                target=zenoh.QueryTarget.BEST_MATCHING,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=self.options.deadline_ms / 1e3,
                # drop, not block: a frame sent into a silently dead link must not wait for
                # queue space (block waited up to wait_before_close holding the link's
                # pipeline lock); the reply inherits it (docs/ZENOH.md section 8)
                congestion_control=zenoh.CongestionControl.DROP,
            )
            self._queriers[key] = q
            self._born[key] = time.monotonic()
        return q

    def _matching(self, tier: str, node: str, q) -> bool:
        """Whether a queryable matches ``q``; a querier declared moments ago gets a short wait.

        A client of a router (topology shape ``routers``) learns what matches a new querier
        from its router, one round trip later: measured on loopback, zenoh 1.10.2, a new
        querier was never matching at once and was after 0.9-1.1 ms (docs/ZENOH.md section
        13).  Without this wait the first request to a new leader was "unreachable".
        """
        if q.matching_status.matching:
            return True
        key = keys.drivable_request(tier, node, self.id)
        until = self._born.get(key, 0.0) + self.MATCH_WAIT_S
        while time.monotonic() < until:
            time.sleep(0.0005)
            if q.matching_status.matching:
                return True
        return False

    def prepare(self) -> None:
        """Declare queriers for the nodes alive now and warm zenoh's query path.

        Takes the one-off cost of the first query (tens of ms under load) out of
        the first request's ToR.
        """
        wire.warm()
        view = self.view.snapshot()
        for tier in keys.TIERS:
            for node in view.nodes(tier):
                self._querier(tier, node)
        try:
            for _ in self._session.liveliness().get(keys.ALIVE_ALL, timeout=1.0):
                pass
        except Exception as exc:
            log.debug("liveliness warm-up get failed: %s", exc)

    def _local_available(self) -> bool:
        if not self.options.local_fallback:
            return False
        if self._local_ok is None:
            try:
                from scmr_mesh.mesh.work import resolve

                self._local_fn = resolve(self.options.process)
                self._local_ok = True
            except Exception as exc:
                log.warning("local execution unavailable: %s", exc)
                self._local_ok = False
        return bool(self._local_ok)

    def warm_local(self) -> None:
        """Load (and JIT-warm) the local pipeline now rather than at the first fallback."""
        if self._local_available():
            from scmr_mesh.mesh.work import warm

            try:
                warm(self._local_fn)
            except Exception as exc:
                log.warning("local warm-up failed: %s", exc)
                self._local_ok = False

    def _judge(self, att: dict, reply, asked: dict, t_send: float | None = None) -> Reply | None:
        """Set ``att["outcome"]`` from one zenoh reply; return the :class:`Reply` if it is good.

        A good reply came on this robot's own request key of the node it was sent to,
        names that node in ``served_by`` and that tier, comes from a node the fleet's
        policy lets serve the tier and, on a direct TLS link, from the identity
        (certificate CN) of that node (else ``bad_reply``); and it answers the request
        ``asked``: its robot, seq and frame digest are the request's
        (:func:`scmr_mesh.wire.reply_mismatch`; else ``mismatched``, counted per node in
        :attr:`mismatched` and in the attempt, and never used).
        """
        if reply.ok is not None:
            data = reply.ok.payload.to_bytes()
            try:
                msg = wire.decode(data, kind=("reply", "receipt"))
            except wire.WireProblem as exc:
                return self._refuse(att, Outcome.BAD_REPLY, f"not a reply: {exc}", asked)
            problem = self._reply_problem(att, str(reply.ok.key_expr), msg, reply)
            if problem:
                return self._refuse(att, Outcome.BAD_REPLY, problem, asked)
            why = wire.reply_mismatch(asked, msg)
            if why:
                return self._refuse(att, Outcome.MISMATCHED, why, asked)
            if msg["kind"] == "receipt":  # the node has the request; its answer follows
                if "receipt_ms" not in att:
                    att["receipt_bytes"] = len(data)  # (in the record's bytes_down: energy counts it)
                    att["receipt_ms"] = round((time.perf_counter() - t_send) * 1e3, 3) if t_send is not None else None
                return None
            att["outcome"] = Outcome.OK
            return Reply(att["tier"], att["node"], msg, len(data))
        raw = reply.err.payload.to_bytes()
        if raw == b"Timeout":  # zenoh's own reply at the querier's timeout: not a message to decode
            att["outcome"] = Outcome.TIMEOUT
            return None
        try:
            err = wire.decode(raw, kind="error")
            att["outcome"] = error_outcome(err["code"])
            att["message"] = err["message"][:200]
            if err.get("served_by") == att["node"] and err.get("seq") in (None, asked.get("seq")):
                att["_final"] = True  # its node's answer: nothing more comes on this copy (_collect)
        except wire.WireProblem:
            text = raw.decode("utf-8", "replace")[:200]
            att["outcome"] = Outcome.TIMEOUT if text == "Timeout" else error_outcome(text)
        return None

    def _refuse(self, att: dict, outcome: str, why: str, asked: dict) -> None:
        """A reply of ``att``'s node that is not the answer to ``asked``: never used, counted in the
        attempt's ``mismatched`` and :attr:`mismatched` by node; its first and every 100th logged."""
        att["outcome"] = outcome
        att["mismatched"] = att.get("mismatched", 0) + 1
        att["message"] = why[:200]
        where = f"{att['tier']}/{att['node']}"
        with self._mismatch_lock:
            n = self.mismatched[where] = self.mismatched.get(where, 0) + 1
        if n == 1 or n % 100 == 0:
            log.error("robot %s: %s sent a reply that does not answer request %s (%s); not used, "
                      "%d such repl%s from it so far", self.id, where, asked.get("seq"), why, n,
                      "y" if n == 1 else "ies")

    def _reply_problem(self, att: dict, key: str, msg: dict, reply) -> str | None:
        """Why a decoded reply cannot be trusted as the answer of ``att``'s node (None: it can); see :meth:`_judge`.

        Whether it answers this request (robot, seq, frame digest) is
        :func:`scmr_mesh.wire.reply_mismatch`'s question, asked after this one.
        """
        tier, node = att["tier"], att["node"]
        expected = keys.drivable_request(tier, node, self.id)
        if key != expected:
            return f"reply came on {key!r}, expected {expected!r}"
        if msg["served_by"] != node or msg["tier"] != tier:
            return f"reply on {expected!r} says served_by {msg['served_by']!r} tier {msg['tier']!r}"
        if self.view.trust is not None and not self.view.trust(tier, node):
            return f"the fleet's policy does not let {node!r} serve the {tier} tier"
        who = self._link_identity(reply)
        if who is not None and who != node:
            return f"reply on {node!r}'s key came from the certificate of {who!r}"
        return None

    def _link_identity(self, reply) -> str | None:
        """Certificate CN of the direct link the reply's sender is on (None: not direct, or no TLS)."""
        try:
            zid = str(reply.replier_id.zid)
            for link in self._session.info.links():
                if str(link.zid) == zid:
                    return link.auth_identifier
        except Exception as exc:  # replier_id unknown (older zenoh), session closing
            log.debug("replier identity unknown: %s", exc)
        return None

    def _send(self, targets: list[tuple[str, str]], payload: bytes, attempts: list, asked: dict) -> Reply | None:
        """Send ``payload`` to every target at once; return the first good reply.

        Returns the winning :class:`Reply` or None.  Appends one
        attempt per target to ``attempts``.  One target uses a FIFO channel
        (fastest: 0.16 ms median vs 0.36 ms for a Python-thread callback, see
        docs/ZENOH.md); several use direct callbacks feeding a queue.
        """
        import zenoh

        sendable = []
        for tier, node in targets:
            att = {"tier": tier, "node": node, "outcome": Outcome.PENDING, "t_unix_ns": time.time_ns()}
            attempts.append(att)
            q = self._querier(tier, node)
            if not self._matching(tier, node, q):
                att["outcome"] = Outcome.UNREACHABLE
                continue
            sendable.append((att, q))
        if len(sendable) == 1:
            att, q = sendable[0]
            return self._tier_send(att, q, payload, asked)
        results: queue.Queue = queue.Queue()
        live = []
        for att, q in sendable:
            token = zenoh.CancellationToken()

            def on_reply(reply, _att=att):
                results.put((_att, reply))

            def on_done(_att=att):
                results.put((_att, None))

            try:
                q.get(zenoh.handlers.Callback(on_reply, on_done, indirect=False), payload=payload,
                      encoding=_msgpack(), cancellation_token=token)
            except Exception as exc:
                att["outcome"] = error_outcome(f"send ({exc})")
                continue
            live.append((att, token))
        pending = {id(a) for a, _ in live}
        deadline = time.monotonic() + self.options.deadline_ms / 1e3
        winner = None
        while pending and winner is None:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                att, reply = results.get(timeout=left)
            except queue.Empty:
                break
            if reply is None:  # that query finished
                pending.discard(id(att))
                if att["outcome"] == Outcome.PENDING:
                    att["outcome"] = Outcome.NO_REPLY
                continue
            winner = self._judge(att, reply, asked)
            att.pop("_final", None)  # (the query ends by itself here: its callback sends None)
        for att, token in live:
            if att["outcome"] == Outcome.PENDING:
                att["outcome"] = Outcome.SUPERSEDED if winner is not None else Outcome.TIMEOUT
            if att["outcome"] != Outcome.OK:
                try:
                    token.cancel()
                except Exception:
                    pass
        return winner

    # ------------------------------------------- one sender thread per node
    def _node_executor(self, tier: str, node: str):
        from concurrent.futures import ThreadPoolExecutor

        ex = self._node_threads.get((tier, node))
        if ex is None:
            ex = self._node_threads[(tier, node)] = ThreadPoolExecutor(
                self.SENDERS_PER_NODE, thread_name_prefix=f"scmr-{tier}-{node}")
        return ex

    def _start(self, att: dict, q, payload: bytes, asked: dict, t0: float | None = None) -> _Sent:
        """Send one query on its node's own thread (:meth:`_collect`); the outcome is read later.

        Queries to two nodes never share a thread: a send held up by one node's
        dead link holds that node's thread, and the request gives up on it after
        the deadline and goes on to the next node or tier (issue 14, docs/ZENOH.md
        section 8), and a hedge to a second node of the same tier (a second cloud
        node) never waits behind the silent first.  The attempt record is only
        written on the request thread.
        """
        import zenoh

        token = zenoh.CancellationToken()
        scratch = dict(att)
        t0 = time.perf_counter() if t0 is None else t0
        heard = threading.Event()
        fut = self._node_executor(att["tier"], att["node"]).submit(self._collect, scratch, q, payload, token, asked,
                                                                   t0, heard)
        fut.add_done_callback(lambda _f: heard.set())
        return _Sent(att, fut, token, scratch, t0, heard)

    def _finish_sent(self, sent: _Sent, *, wait_s: float) -> Reply | None:
        """Wait up to ``wait_s`` for one sent query; write its outcome to its attempt; learn its answer time."""
        from concurrent.futures import TimeoutError as FutureTimeout

        att = sent.att
        try:
            scratch, winner, answer_ms = sent.fut.result(timeout=max(0.0, wait_s))
        except FutureTimeout:
            sent.give_up(Outcome.TIMEOUT)  # the tier's thread is still held by zenoh
            return None
        except RuntimeError as exc:  # closed while sending
            att["outcome"] = error_outcome(f"send ({exc})")
            return None
        att.update(scratch)
        if winner is not None and answer_ms is not None:
            self._answer_times[str(att["tier"])].add(answer_ms)
        where = (str(att["tier"]), str(att["node"]))
        receipt_ms = scratch.get("receipt_ms")
        if receipt_ms is not None:
            self._receipt_times[where].add(receipt_ms)
            self._receipt_all.add(receipt_ms)
            self._unreceipted[where] = 0
        elif winner is not None and self._receipts_asked():
            self._unreceipted[where] = self._unreceipted.get(where, 0) + 1
        return winner

    def _tier_send(self, att: dict, q, payload: bytes, asked: dict | None = None) -> Reply | None:
        """Send one query on its tier's thread and wait (deadline + 0.25 s) for its outcome.

        ``asked``: what a reply must echo (:func:`scmr_mesh.wire.asked_of`); read from ``payload`` when not given.
        """
        asked = _asked_of(payload) if asked is None else asked
        return self._finish_sent(self._start(att, q, payload, asked), wait_s=self.options.deadline_ms / 1e3 + 0.25)

    def _collect(self, att: dict, q, payload: bytes, token, asked: dict,
                 t0: float | None = None, heard: threading.Event | None = None
                 ) -> tuple[dict, Reply | None, float | None]:
        """Run one query on the tier's thread; its answer time counts from ``t0`` (default: now).

        The node's receipt (it has the request, the answer follows) sets ``heard`` and
        ``att["receipt_ms"]``, counted from this copy's own send.
        """
        winner = None
        answer_ms = None
        t_send = time.perf_counter()
        t0 = t_send if t0 is None else t0
        try:
            kw = {} if token is None else {"cancellation_token": token}
            # ends at the querier timeout = deadline, or when the token is cancelled (a hedge won)
            for reply in q.get(payload=payload, encoding=_msgpack(), **kw):
                had = "receipt_ms" in att
                w = self._judge(att, reply, asked, t_send)
                if not had and "receipt_ms" in att and heard is not None:
                    heard.set()
                if w is not None:
                    winner, answer_ms = w, (time.perf_counter() - t0) * 1e3
                if w is not None or att.pop("_final", False):
                    # the node's answer or its error is in: the copy ends here, not when the node
                    # finalises the query (a node whose final is late held a busy copy for its
                    # whole deadline, 1 s, before the robot fell back)
                    if token is not None:
                        token.cancel()
                    break
        except Exception as exc:
            att["outcome"] = error_outcome(f"send ({exc})")
        if att["outcome"] == Outcome.PENDING:
            att["outcome"] = Outcome.NO_REPLY
        return att, winner, answer_ms

    # ----------------------------------------------------------- hedging
    def hedge_delay_ms(self, tier: str, elapsed_ms: float = 0.0) -> float | None:
        """When to hedge a request sent to ``tier`` (ms from its start), or None: no hedge.

        ``--hedge-ms MS`` fixes it; by default it is learnt from the tier's
        recent answers (:func:`scmr_mesh.qos.hedge.hedge_delay_ms`).
        """
        from scmr_mesh.qos.hedge import hedge_delay_ms

        opts = self.options
        if not opts.hedge:
            return None
        if opts.hedge_ms is not None:
            return opts.hedge_ms if elapsed_ms + opts.hedge_ms < opts.deadline_ms else None
        return hedge_delay_ms(self._answer_times[str(tier)].values(), deadline_ms=opts.deadline_ms,
                              elapsed_ms=elapsed_ms)

    #: Answers in a row without a receipt after which a node is no longer expected to send one.
    UNRECEIPTED_MAX = 2

    def _receipts_asked(self) -> bool:
        """Whether requests ask for receipts: only when something uses them (learnt hedging; not
        ``--hedge-ms MS``, not ``--redundant``, which sends to both tiers at once anyway)."""
        opts = self.options
        return bool(opts.hedge and opts.hedge_ms is None and not opts.redundant)

    def receipt_delay_ms(self, tier: str, node: str, elapsed_ms: float = 0.0) -> float | None:
        """How long a copy sent to ``node`` may go without its receipt (ms), or None: not judged.

        Learnt from the node's recent receipts, or from every node's while it has too few
        (a leader at the cloud's loss): :func:`scmr_mesh.qos.hedge.receipt_delay_ms`.  None
        when receipts are not asked for (:meth:`_receipts_asked`), before enough receipts
        came, or for a node whose last :attr:`UNRECEIPTED_MAX` answers came without one.
        """
        from scmr_mesh.qos.hedge import RECEIPT_RULE, receipt_delay_ms

        if not self._receipts_asked():
            return None
        where = (str(tier), str(node))
        if self._unreceipted.get(where, 0) >= self.UNRECEIPTED_MAX:
            return None
        own = self._receipt_times.get(where)
        xs = own.values() if own is not None and len(own) >= RECEIPT_RULE.min_samples else self._receipt_all.values()
        return receipt_delay_ms(xs, deadline_ms=self.options.deadline_ms, elapsed_ms=elapsed_ms)

    def _hedge_target(self, plan: list, tier: str, tried: set, *, lost: bool = False
                      ) -> tuple[tuple[str, str], Any] | None:
        """Where a hedge of a request silent at ``tier`` goes: another live node of the same tier (a
        second cloud node), else the first node of the next live tier in ``plan``; never a node tried
        or without a matching queryable, and not a saturated one, unless the copy was ``lost`` (no
        receipt: its node may be gone) and only saturated nodes are left.  At the cloud's loss every
        robot hedges to the leader at once, so its load says saturated to the last of them; a re-send
        to the silent cloud then waited out the lease (136 and 291 ms in 2 of 20 runs of
        cloud-link-drop), where the leader's admission answers at once, ``busy`` at worst."""
        later = plan[plan.index(tier) + 1:] if tier in plan else []
        fresh = self.view.snapshot(local=False)
        options = [(tier, n) for n in fresh.nodes(tier)]
        options += [(t, n) for t in later if t not in (Tier.LOCAL, tier) for n in fresh.nodes(t)[:1]]
        options = [(t, n) for t, n in options if (t, n) not in tried]
        # a busy node is not hedged to (its admission stays in charge), unless the copy was lost
        for saturated in ((False, True) if lost else (False,)):
            for t, node in options:
                if fresh.saturated(node) != saturated:
                    continue
                q = self._querier(t, node)
                if self._matching(t, node, q):
                    return (t, node), q
        return None

    def _send_hedged(self, tier: str, node: str, payload: bytes, trip: _Trip, plan: list, seq: int,
                     t_start: float) -> Reply | None:
        """One attempt at ``tier``/``node``, hedged when it is silent too long.

        The primary's own outcome decides when it answers before the hedge delay
        (an error or ``busy`` answer goes on to the normal failover, never to a
        hedge).  Past the delay the same request goes to another live node
        (:meth:`_hedge_target`) or, with none, once more to the same node: a copy
        or its answer can be lost on the way (a starved sender drops what it
        cannot queue; a link that misses its lease under load takes its queries
        with it), and a node serves a request once and answers every copy
        (:class:`scmr_mesh.mesh.server.RecentRequests`).  A hedge as silent as the
        primary was is sent once more to its node.  A re-sent copy runs beside
        the first (each node has :attr:`SENDERS_PER_NODE` sender threads), so whichever answer comes first
        is used.  When a serving node is seen leaving while a copy waits (zenoh
        re-routes as the link closes, and copies in flight then were lost), the
        waiting copy is sent once more, at once.  The first good answer wins; the
        other copies are cancelled and their attempts marked ``superseded``
        (``timeout`` when nothing answered).  At most one hedge (a budget token)
        and two re-sends per request: one when the copy stays silent (no token:
        the node it goes to serves a request once), one when a node leaves.
        """
        from concurrent.futures import FIRST_COMPLETED, wait

        att = {"tier": tier, "node": node, "outcome": Outcome.PENDING, "t_unix_ns": time.time_ns()}
        trip.attempts.append(att)
        trip.tried.add((tier, node))
        q = self._querier(tier, node)
        if not self._matching(tier, node, q):
            att["outcome"] = Outcome.UNREACHABLE
            return None
        trip.bytes_up += len(payload)
        primary = self._start(att, q, payload, trip.asked)
        limit = time.monotonic() + self.options.deadline_ms / 1e3 + 0.25
        elapsed_ms = (time.perf_counter() - t_start) * 1e3
        delay = None if trip.hedged else self.hedge_delay_ms(tier, elapsed_ms)
        target = None
        silence = "silent for"
        if delay is not None:
            # no receipt in time: the copy or its node is lost, known long before the answer is late
            rdelay = self.receipt_delay_ms(tier, node, elapsed_ms)
            if rdelay is not None and rdelay < delay and not primary.heard.wait(rdelay / 1e3):
                silent, delay, silence = True, rdelay, "no receipt in"
            else:
                left = delay / 1e3 - (time.perf_counter() - primary.t0)
                silent = not wait([primary.fut], timeout=max(0.0, left))[0]
            if silent:
                target = self._hedge_target(plan, tier, trip.tried, lost=silence == "no receipt in") or (
                    (tier, node), q)  # (may wait for a matching)
        if target is None or primary.fut.done() or not self._hedge_budget.take():
            w = self._finish_sent(primary, wait_s=limit - time.monotonic())
            if w is None and att["outcome"] == BUSY:
                self.view.mark_busy(node)
            return w
        (htier, hnode), hq = target
        resend = (htier, hnode) == (tier, node)  # no other live node: the same one once more
        live = {primary.fut: primary}  # (a re-sent copy runs beside the first: either answer will do)
        if not resend:
            trip.tried.add((htier, hnode))
        trip.hedged = True
        departures = self.view.departures  # (before the send: a node leaving from now on counts)
        hedge = self._copy(trip, payload, htier, hnode, hq, after=primary if resend else None)
        log.info("robot %s: %s/%s %s %.0f ms on request %s: %s %s/%s", self.id, tier, node, silence, delay, seq,
                 "sent again to" if resend else "hedged to", htier, hnode)
        live[hedge.fut] = hedge
        # a hedge as silent as the primary was: its copy or its answer may have been lost too.  With
        # receipts it is silent when its receipt is late; a hedge whose node has it waits for the
        # answer as long as the primary did
        hedge_sent = time.monotonic()
        hreceipt = self.receipt_delay_ms(htier, hnode, (time.perf_counter() - t_start) * 1e3)
        # (the hedge's own tier's answer delay: a leader answers slower than the cloud it stands in for)
        answer_due = hedge_sent + max(delay, self.hedge_delay_ms(htier, 0.0) or delay) / 1e3
        resend_at = None if resend else hedge_sent + (delay if hreceipt is None else min(hreceipt, delay)) / 1e3
        if resend_at is not None and resend_at + self.RESEND_MIN_LEFT_S > limit:
            resend_at = None
        # a serving node seen leaving while a copy is pending elsewhere: that copy once more (zenoh
        # re-routes when a link closes; copies in flight then were lost, docs/ZENOH.md section 17)
        after_departure = False
        winner = None
        hatts = [hedge.att]
        while live and winner is None:
            now = time.monotonic()
            left = limit - now
            if left <= 0:
                break
            wake = left if resend_at is None else min(left, max(0.0, resend_at - now))
            if not after_departure:
                wake = min(wake, self.DEPARTURE_POLL_S)
            done_futs, _ = wait(list(live), timeout=wake, return_when=FIRST_COMPLETED)
            for fut in done_futs:
                sent = live.pop(fut)
                w = self._finish_sent(sent, wait_s=0)
                if w is not None and winner is None:
                    winner = w
                    trip.hedge_won = sent is not primary
                elif w is not None:  # both copies answered at once: one answer is used, once
                    sent.att["outcome"] = Outcome.SUPERSEDED
            if (winner is None and resend_at is not None and time.monotonic() >= resend_at
                    and hedge.fut in live and hedge.heard.is_set() and not hedge.fut.done()
                    and time.monotonic() < answer_due):
                resend_at = answer_due  # its node has it: wait for the answer as the primary was waited for
                if resend_at + self.RESEND_MIN_LEFT_S > limit:
                    resend_at = None
            if (winner is None and resend_at is not None and time.monotonic() >= resend_at
                    and hedge.fut in live and not hedge.fut.done()):
                # no budget token: a copy to the node that already has (or lost) this request adds
                # no pipeline run there (it serves a request once), and at most two go per request
                resend_at = None
                departures = self.view.departures  # (before the send: a node leaving from now on counts)
                silence = "no answer in" if hedge.heard.is_set() else "no receipt in"
                waited = (time.monotonic() - hedge_sent) * 1e3
                hedge = self._copy(trip, payload, htier, hnode, hq, after=hedge)
                log.info("robot %s: hedge to %s/%s %s %.0f ms on request %s: sent again", self.id,
                         htier, hnode, silence, waited, seq)
                live[hedge.fut] = hedge
                hatts.append(hedge.att)
            if (winner is None and not after_departure and self.view.departures != departures
                    and hedge.fut in live and not hedge.fut.done()
                    and time.monotonic() + self.RESEND_MIN_LEFT_S < limit):
                after_departure, resend_at = True, None  # (this copy replaces a timed re-send still due)
                hedge = self._copy(trip, payload, htier, hnode, hq, after=hedge)
                log.info("robot %s: a node left while request %s waited for %s/%s: sent again", self.id, seq,
                         htier, hnode)
                live[hedge.fut] = hedge
                hatts.append(hedge.att)
        for sent in live.values():  # the losers (or all, past the deadline)
            sent.give_up(Outcome.SUPERSEDED if winner is not None else Outcome.TIMEOUT)
        for a in (att, *hatts):
            if winner is None and a["outcome"] == BUSY:
                self.view.mark_busy(a["node"])
        return winner

    def _copy(self, trip: _Trip, payload: bytes, tier: str, node: str, q, *, after: _Sent | None = None) -> _Sent:
        """Send another copy of the request: a hedge, or (``after``: the copy it repeats) once more to
        the same node, beside that copy, its answer time counted from the first copy's send."""
        att = {"tier": tier, "node": node, "outcome": Outcome.PENDING, "t_unix_ns": time.time_ns(), "hedge": True}
        if after is not None:
            att["resend"] = True
        trip.attempts.append(att)
        trip.bytes_up += len(payload)
        return self._start(att, q, payload, trip.asked, t0=None if after is None else after.t0)

    def request(self, seq: int, frame: Frame) -> dict:
        """Process one frame through the mesh (or locally); return its record.

        The steps: keep the frame in the outbox, route the request (placement,
        attempts, failover, local), make the record, deliver it (inbox,
        ``records.jsonl``, ``scmr/results/<robot>``, telemetry, observers).

        The outbox write (about 0.18 ms for a 21 KB JPEG on ext4, more for a raw frame) runs
        on the process's outbox threads (:func:`_outbox_submit`) while the request is out, so it
        no longer delays the send; the request's delivery waits for it before it removes the file.
        """
        outbox_file = self.outbox / f"{seq}{FRAME_SUFFIX[frame.encoding]}"  # a bad encoding fails before the send
        outbox_write = _outbox_submit(self._to_outbox, outbox_file, frame.data)
        sent_ns = time.time_ns()
        t_start = time.perf_counter()
        req = self._request_message(seq, frame, sent_ns)
        trip = self._route(seq, frame, wire.encode(req), t_start, asked=wire.asked_of(req))
        tor_ms = (time.perf_counter() - t_start) * 1e3
        record = self._make_record(seq, frame, trip, sent_ns, time.time_ns(), tor_ms)
        self._deliver(seq, frame, record, trip.winner, outbox_write)
        return record

    # ------------------------------------------------ the steps of a request
    @staticmethod
    def _to_outbox(outbox_file: Path, data: bytes) -> Path:
        """Write a frame to the outbox; a failure is logged, never raised (the frame is being served)."""
        try:
            outbox_file.write_bytes(data)
        except Exception as exc:  # a full disk, a removed folder: the request goes on without its outbox copy
            log.warning("outbox write failed: %s", exc)
        return outbox_file

    def _request_message(self, seq: int, frame: Frame, sent_ns: int) -> dict:
        """The request of frame ``seq`` (with its frame digest, :func:`scmr_mesh.wire.frame_digest`)."""
        opts = self.options
        return wire.make_request(self.id, seq, frame.data, encoding=frame.encoding, shape=frame.shape,
                                 priority=opts.priority, mode=opts.mode, sent_unix_ns=sent_ns,
                                 deadline_ms=opts.deadline_ms, receipt=self._receipts_asked())

    def _request_payload(self, seq: int, frame: Frame, sent_ns: int) -> bytes:
        return wire.encode(self._request_message(seq, frame, sent_ns))

    def _route(self, seq: int, frame: Frame, payload: bytes, t_start: float | None = None,
               asked: dict | None = None) -> _Trip:
        """Try the placement's tiers in order (all at once with ``redundant``) until one answers.

        Only a reply that echoes ``asked`` (robot, seq, frame digest; read from ``payload``
        when not given) is taken; any other goes on as a failed attempt would.
        """
        opts = self.options
        trip = _Trip(asked=_asked_of(payload) if asked is None else asked)
        view = self.view.snapshot(local=self._local_available())
        info = FrameInfo(self.id, seq, len(frame.data), frame.encoding)
        plan = [t for t in self.placement(view, info) if t in keys.PLACEMENTS]
        if opts.redundant:
            targets = [(t, view.nodes(t)[0]) for t in (Tier.CLOUD, Tier.LEADER) if t in plan and view.nodes(t)]
            if targets:
                trip.bytes_up += len(payload) * len(targets)
                trip.winner = self._send(targets, payload, trip.attempts, trip.asked)
            plan = [t for t in plan if t == Tier.LOCAL] if trip.winner is None else []
        t_end = time.monotonic() + opts.deadline_ms / 1e3
        t_start = time.perf_counter() if t_start is None else t_start
        self._hedge_budget.earn()

        def attempt(tier: str, node: str) -> Reply | None:
            trip.tried.add((tier, node))
            before = len(trip.attempts)
            w = self._send([(tier, node)], payload, trip.attempts, trip.asked)
            if trip.attempts[before]["outcome"] != Outcome.UNREACHABLE:
                trip.bytes_up += len(payload)
            if w is None and trip.attempts[before]["outcome"] == BUSY:
                self.view.mark_busy(node)
            return w

        for tier in plan:
            if trip.winner is not None:
                break
            if tier == Tier.LOCAL:
                # the view may have changed while the plan was tried (a new leader was elected, a peer
                # freed up): try what is new before computing alone; in an election, wait for it briefly.
                # Not when the placement chose local while remote nodes were there (the energy policy).
                nothing_remote = not (view.cloud or view.leader or view.peer)
                if any(a["tier"] != Tier.LOCAL for a in trip.attempts) or nothing_remote:
                    trip.winner = self._retry_fresh(attempt, trip.tried, t_end, trip.attempts)
                if trip.winner is None:
                    trip.winner = self._run_local(frame, trip.attempts)
                continue
            nodes = self.view.snapshot(local=False).nodes(tier) or view.nodes(tier)
            for node in nodes[: opts.max_nodes_per_tier]:
                if (tier, node) in trip.tried:  # a hedge already went there
                    continue
                trip.winner = self._send_hedged(tier, node, payload, trip, plan, seq, t_start)
                if trip.winner is not None:
                    break
        return trip

    def _make_record(self, seq: int, frame: Frame, trip: _Trip, sent_ns: int, received_ns: int,
                     tor_ms: float) -> dict:
        w = trip.winner
        error = None
        if w is None:
            error = ("no serving tier alive and local execution off or unavailable" if not trip.attempts else
                     "no tier answered: " + ", ".join(f"{a['tier']}/{a['node']}={a['outcome']}" for a in trip.attempts))
        return {
            "robot": self.id, "seq": int(seq), "image": frame.name, "bytes_up": int(trip.bytes_up),
            "bytes_down": (int(w.nbytes) if w is not None else 0)
            + sum(int(a.get("receipt_bytes", 0)) for a in trip.attempts), "sent_unix_ns": sent_ns,
            "received_unix_ns": received_ns, "tor_ms": round(tor_ms, 3), "ok": w is not None,
            "tier": None if w is None else str(w.tier), "served_by": None if w is None else w.node,
            "attempts": trip.attempts, "error": error, "hedged": trip.hedged, "hedge_won": trip.hedge_won,
            "server_ms": round(float(w.body.get("server_ms", 0.0)), 3) if w is not None and w.tier != Tier.LOCAL
            else None,
            "confidence": None if w is None else w.body.get("confidence"),
            "abstained": None if w is None else w.body.get("abstained"),
            "mismatched": sum(int(a.get("mismatched", 0)) for a in trip.attempts),
        }

    def _deliver(self, seq: int, frame: Frame, record: dict, winner: Reply | None, outbox_write) -> None:
        """The annotators (the ROS bridge publishes its mask there), the mask to the inbox, the frame out of
        the outbox (``outbox_write``: the future of its write, waited for here), the record to its file and
        topic, telemetry, then the observers."""
        mask_png = winner.body["mask_png"] if winner is not None else None
        for fn in list(self.annotators):  # first: the ROS bridge publishes the mask from here
            try:
                fn(record, winner.body if winner is not None else None)
            except Exception:
                log.exception("annotator %r failed", fn)
        if mask_png is not None:
            try:
                path = self.inbox / f"{seq}.mask.png"
                path.write_bytes(mask_png)
                self.masks.add(path)
            except OSError as exc:
                log.warning("inbox write failed: %s", exc)
        try:
            outbox_write.result().unlink()
        except OSError:
            pass
        self._records.write(json.dumps(record, separators=(",", ":")) + "\n")
        self._records.flush()
        self._account(record)
        if self._res_pub is not None:
            try:
                self._res_pub.put(json.dumps(record, separators=(",", ":")).encode(), encoding=_json())
            except Exception as exc:
                log.debug("results publish failed: %s", exc)
        try:
            self.emit_telemetry(self.make_telemetry())
        except Exception as exc:  # counted: the robot keeps sending frames, its exit status says so
            self.telemetry_errors += 1
            log.error("telemetry of request %s failed (%d so far): %s: %s", seq, self.telemetry_errors,
                      type(exc).__name__, exc)
        if self._observers:
            mask = None
            if mask_png is not None:
                import cv2
                import numpy as np

                mask = cv2.imdecode(np.frombuffer(mask_png, np.uint8), cv2.IMREAD_GRAYSCALE)
            rgb = frame.pixels()
            for fn in list(self._observers):
                try:
                    fn(record, rgb, mask)
                except Exception:
                    log.exception("observer %r failed", fn)

    #: Longest a robot waits for an election in progress before computing a frame alone (s).
    ELECTION_WAIT_S = 0.3
    #: How long a querier declared just now may take to learn what matches it (:meth:`_matching`).
    MATCH_WAIT_S = 0.05
    #: A silent hedge is sent again only with this much of the request's deadline left (s).
    RESEND_MIN_LEFT_S = 0.05
    #: Sender threads per node: a copy sent once more runs beside the first, never behind it
    #: (a request has at most three copies at one node: the first and two re-sends).
    SENDERS_PER_NODE = 3
    #: How often a request waiting for a copy checks whether a serving node left (s).
    DEPARTURE_POLL_S = 0.01

    def _retry_fresh(self, attempt, tried: set, t_end: float, attempts: list) -> Reply | None:
        """Before local execution: try remote nodes that appeared since the plan was made.

        When no untried node is alive but leader-capable nodes are, and a lead
        is passing on (no leader alive, or the leader did not answer), wait up
        to :data:`ELECTION_WAIT_S` (within the request's deadline) for the new
        leader or a free peer; nodes that appeared are tried first, and one that
        vanished meanwhile (a peer that is turning leader drops its peer queryable)
        does not end the wait.  A leader and peers that answer ``busy`` do not
        make it wait: the frame runs locally at once.
        """
        waited = False
        while True:
            fresh = self.view.snapshot(local=False)
            new = [(t, n) for t in ("cloud", "leader", "peer") for n in fresh.nodes(t)[:2] if (t, n) not in tried]
            for t, n in new:
                w = attempt(t, n)
                if w is not None:
                    return w
            # wait only while a lead is passing on: no leader alive, or the leader just failed to answer
            lead_lost = not fresh.leader or any(
                # (a leader that answered with a wrong reply is alive: no new lead will come to wait for)
                a["tier"] == Tier.LEADER and a["outcome"] in (Outcome.NO_REPLY, Outcome.UNREACHABLE, Outcome.TIMEOUT)
                for a in attempts)
            # a node tried just now that answered busy: run locally at once; one that vanished
            # (a peer turning leader drops its peer queryable: no_reply) does not end the wait
            busy = any(a["outcome"] == BUSY for a in attempts[-len(new):]) if new else False
            if busy or waited or not self.view.candidates() or not lead_lost:
                return None
            waited = True
            left = min(self.ELECTION_WAIT_S, t_end - time.monotonic())
            if left <= 0 or not self.view.wait_for_server(tried, left):
                return None

    def _run_local(self, frame: Frame, attempts: list) -> Reply | None:
        att = {"tier": Tier.LOCAL, "node": self.id, "outcome": Outcome.PENDING, "t_unix_ns": time.time_ns()}
        attempts.append(att)
        try:
            c0 = time.thread_time()
            out = self._local_fn(frame.data, encoding=frame.encoding, shape=frame.shape, mode=self.options.mode)
            cpu_ms = (time.thread_time() - c0) * 1e3
        except Exception as exc:
            att["outcome"] = error_outcome(type(exc).__name__)
            att["message"] = str(exc)[:200]
            return None
        att["outcome"] = Outcome.OK
        return Reply(Tier.LOCAL, self.id, {"mask_png": out["mask_png"], "cpu_ms": cpu_ms,
                                           "timings_ms": out.get("timings_ms", {}),
                                           "confidence": out.get("confidence"), "abstained": out.get("abstained")}, 0)

    def _account(self, record: dict) -> None:
        self._last_seq = record["seq"]
        s = self.stats
        s["requests"] += 1
        s["mismatched"] += record["mismatched"]
        if record["ok"]:
            s["succeeded"] += 1
            s["by_tier"][record["tier"]] += 1
            s["last_tor_ms"] = record["tor_ms"]
        s["last_tier"] = record["tier"]
        self._health = "fault" if not record["ok"] else "ok" if record["tier"] == "cloud" else "degraded"

    def run(self, frames: Iterator[Frame], *, rate_hz: float = 5.0, count: int | None = None,
            duration_s: float | None = None, stop: threading.Event | None = None,
            progress: Callable[[dict], None] | None = None) -> dict:
        """Send frames at ``rate_hz`` until ``count`` frames, ``duration_s`` or ``stop``.

        Returns
        -------
        dict
            The robot's stats: requests, succeeded, by_tier, last_tor_ms, last_tier, mismatched.
        """
        stop = stop or threading.Event()
        # frame k due at t0 + k x period, from integers (a float-accumulated schedule sent a frame past the end)
        sched = Schedule(time.monotonic_ns(), rate_hz or 0.0, duration_s)
        for seq in itertools.count():
            if stop.is_set() or (count is not None and seq >= count):
                break
            # the time this frame would go out: none at or after t0 + duration (was one period over)
            if sched.ended(time.monotonic_ns()):
                break
            wait_ns = sched.next_due_ns() - time.monotonic_ns()
            if wait_ns > 0 and stop.wait(wait_ns / 1e9):
                break
            if sched.ended(time.monotonic_ns()):  # the wait overslept past the end
                break
            sched.advance(time.monotonic_ns())
            frame = next(frames)
            rec = self.request(seq, frame)
            if progress is not None:
                progress(rec)
        return dict(self.stats)


def _asked_of(payload: bytes) -> dict:
    """What a reply must echo of the encoded request ``payload`` (:func:`scmr_mesh.wire.asked_of`)."""
    import msgpack

    try:
        req = msgpack.unpackb(payload, raw=False)
    except Exception:
        req = None
    return wire.asked_of(req if isinstance(req, dict) else {})


def _msgpack():
    from scmr_mesh.mesh.encoding import msgpack

    return msgpack()


def _json():
    from scmr_mesh.mesh.encoding import json as json_encoding

    return json_encoding()
