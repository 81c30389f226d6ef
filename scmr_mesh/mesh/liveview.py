"""A robot's view of the mesh and its routing rule: which nodes serve, their load, who leads,
and the default placement (cloud, then the leader, then peers, then itself); split out of
:mod:`scmr_mesh.mesh.robot`, whose docstring describes the routing.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from scmr_mesh import keys, wire
from scmr_mesh.errors import InputError
from scmr_mesh.mesh.resources import appeared

log = logging.getLogger(__name__)

#: Most decoded load and candidacy payloads kept (see :func:`_decoded_once`).
DECODED_MAX = 512
_decoded: dict[tuple[str, bytes], Any] = {}


def _decoded_once(kind: str, data: bytes, parse: Callable[[dict], Any]) -> Any:
    """``parse(wire.decode(data, kind=kind))``, kept by the payload's bytes for the whole process.

    Every serving node publishes its load at 10 Hz and every candidate a heartbeat at 4 Hz,
    and every robot receives each one; the robots a ``scmr swarm`` plays receive the very
    same bytes, each on its own session.  Checking a message against its schema took 15 us
    (load) and 29 us (candidacy with its Candidacy) of the interpreter, which 64 robots paid
    about 3,300 times a second (issue 23: the robots' CPU at 1 Hz fell 21 % without it).
    Now the first member to receive a payload checks it and the others reuse the result:
    the same bytes give the same message, and what is kept is immutable (a tuple, a frozen
    Candidacy).  Each robot still receives every sample and keeps its own view; a payload
    that fails the check is not kept (each receiver logs and counts it as before).  A real
    robot's process gets no hits and pays one dict lookup.
    """
    key = (kind, data)
    hit = _decoded.get(key)
    if hit is not None:
        return hit
    value = parse(wire.decode(data, kind=kind))
    if len(_decoded) >= DECODED_MAX:  # bounded: a load's 'served' changes with every message
        _decoded.clear()
    _decoded[key] = value
    return value


def _load_entry(msg: dict) -> tuple[str, float, float | None]:
    """(node, inflight / workers, clock Hz or None) of a load message."""
    return (msg["node"], msg["inflight"] / max(1, msg["workers"]),
            float(msg["clock_hz"]) if "clock_hz" in msg else None)


def _candidacy(msg: dict):
    from scmr_mesh.mesh.election import Candidacy

    return Candidacy.from_message(msg)


# ------------------------------------------------------------------ view
@dataclass(frozen=True)
class Reachable:
    """A snapshot of the live view handed to the placement function.

    Attributes
    ----------
    cloud, leader, peer : tuple of str
        Alive nodes of each tier.  Cloud nodes least loaded first; leaders
        the elected one first (highest term, then rank: normally exactly one);
        peers (robots serving robots; never this robot) with spare capacity
        first, least loaded, then fastest.
    loads : dict
        node -> (inflight / workers) from the last load message.
    local : bool
        Whether this robot can run the pipeline itself.
    clocks : dict
        node -> clock (Hz) of its energy profile, from its load messages.
    """

    cloud: tuple[str, ...] = ()
    leader: tuple[str, ...] = ()
    loads: dict = field(default_factory=dict)
    local: bool = False
    peer: tuple[str, ...] = ()
    clocks: dict = field(default_factory=dict)

    def nodes(self, tier: str) -> tuple[str, ...]:
        return getattr(self, tier, ()) if tier in keys.TIERS else ()

    def saturated(self, node: str) -> bool:
        """Whether ``node`` published a load of at least one request per worker."""
        return self.loads.get(node, 0.0) >= 1.0


@dataclass(frozen=True)
class FrameInfo:
    """What the placement function knows about a frame."""

    robot: str
    seq: int
    bytes: int
    encoding: str


Placement = Callable[[Reachable, FrameInfo], Sequence[str]]


def default_placement(view: Reachable, frame: FrameInfo) -> list[str]:
    """The tiers to try, in order.

    Cloud if a cloud node is alive; then the leader; then, only when no cloud
    is alive, peer robots with spare capacity (before the leader when the
    leader is saturated, and in the gap while a new leader is elected); then
    local execution if this robot can run it.
    """
    order = []
    if view.cloud:
        order.append("cloud")
    spare_peers = [p for p in view.peer if not view.saturated(p)]
    if not view.cloud and spare_peers and (not view.leader or view.saturated(view.leader[0])):
        order.append("peer")
    if view.leader:
        order.append("leader")
    if not view.cloud and view.peer and "peer" not in order:
        order.append("peer")  # a busy leader answers "busy": then a peer
    if view.local:
        order.append("local")
    return order


class LiveView:
    """Which serving nodes are alive, how loaded, and who leads, from liveliness,
    load samples and candidacies (the R2R election, :mod:`scmr_mesh.mesh.election`)."""

    def __init__(self, me: str | None = None) -> None:
        self.me = me
        #: ``fn(tier, node) -> bool``: whether the fleet's policy lets ``node`` serve ``tier``
        #: (set from the security profile); nodes it refuses are never routed to
        self.trust: Callable[[str, str], bool] | None = None
        self._lock = threading.Lock()
        self._alive: dict[str, set[str]] = {t: set() for t in keys.ROLES}
        self._loads: dict[str, float] = {}
        self._clocks: dict[str, float] = {}
        self._cands: dict[str, Any] = {}  # node -> election.Candidacy
        self.changed = threading.Condition(self._lock)
        #: serving nodes seen leaving so far (a robot re-sends a copy pending elsewhere: Robot._send_hedged)
        self.departures = 0
        self._rr = itertools.count()

    def on_liveliness(self, sample) -> None:
        """Liveliness subscriber callback (PUT = alive, DELETE = gone)."""
        try:
            _, role, node = keys.parse(str(sample.key_expr))
        except InputError:
            return
        alive = appeared(sample)
        if alive and role in keys.TIERS and self.trust is not None and not self.trust(role, node):
            log.warning("liveliness: ignoring %s %s: the fleet's policy does not let %s serve the %s tier",
                        role, node, node, role)
            return
        with self._lock:
            bucket = self._alive.setdefault(role, set())
            if alive:
                bucket.add(node)
            else:
                if node in bucket and role in keys.TIERS:
                    self.departures += 1
                bucket.discard(node)
                if role != "candidate":
                    self._loads.pop(node, None)
                else:
                    self._cands.pop(node, None)
            self.changed.notify_all()
        log.info("liveliness: %s %s %s", role, node, "up" if alive else "down")

    def on_load(self, sample) -> None:
        """Load subscriber callback."""
        try:
            node, load, clock_hz = _decoded_once("load", sample.payload.to_bytes(), _load_entry)
        except wire.WireProblem as exc:
            log.debug("ignoring load sample: %s", exc)
            return
        with self._lock:
            self._loads[node] = load
            if clock_hz is not None:
                self._clocks[node] = clock_hz

    def on_candidate(self, sample) -> None:
        """Candidacy subscriber callback: who claims the lead, with which term."""
        try:
            c = _decoded_once("candidate", sample.payload.to_bytes(), _candidacy)
        except wire.WireProblem as exc:
            log.debug("ignoring candidacy: %s", exc)
            return
        if c.node != keys.candidate_node(str(sample.key_expr)):
            log.warning("ignoring a candidacy of %s published on %s (a candidate speaks only for itself)",
                        c.node, sample.key_expr)
            return
        with self._lock:
            self._cands[c.node] = c

    def mark_busy(self, node: str, amount: float = 1.0) -> None:
        """Raise a node's load estimate locally (until its next load message)."""
        with self._lock:
            self._loads[node] = self._loads.get(node, 0.0) + amount

    def _leaders(self) -> list[str]:
        """Alive leaders, the elected one first: highest term, then rank (unknown terms last).

        A leader whose term is more than ``election.TERM_WINDOW`` above the lowest term of the
        alive leaders goes after those within it (issue #28: a liar claiming the largest term,
        which the candidates refuse, does not draw the robots' frames while an elected leader lives).
        """
        from scmr_mesh.mesh.election import TERM_WINDOW, rank_key

        terms = [c.term for n in self._alive["leader"] if (c := self._cands.get(n)) is not None and c.leading]
        lo = min(terms, default=0)

        def key(n: str):
            c = self._cands.get(n)
            if c is None or not c.leading:
                return (1, 0, 0, (), n)
            return (0, int(c.term > lo + TERM_WINDOW), -c.term, rank_key(c), n)

        return sorted(self._alive["leader"], key=key)

    def snapshot(self, *, local: bool = False) -> Reachable:
        with self._lock:
            loads = dict(self._loads)
            rr = next(self._rr)
            clouds = sorted(self._alive["cloud"])
            # least loaded first; ties broken by rotation so robots spread out
            if clouds:
                k = rr % len(clouds)
                clouds = clouds[k:] + clouds[:k]
            clouds.sort(key=lambda n: loads.get(n, 0.0))
            peers = sorted((p for p in self._alive["peer"] if p != self.me),
                           key=lambda n: (loads.get(n, 0.0) >= 1.0, loads.get(n, 0.0),
                                          -self._clocks.get(n, 0.0), n))
            return Reachable(tuple(clouds), tuple(self._leaders()), loads, local, tuple(peers),
                             dict(self._clocks))

    def leader(self) -> str | None:
        """The elected leader as this robot sees it (None when none is alive)."""
        with self._lock:
            leaders = self._leaders()
        return leaders[0] if leaders else None

    def candidates(self) -> list[str]:
        """Live leader-capable nodes other than this robot."""
        with self._lock:
            return sorted(n for n in self._alive["candidate"] if n != self.me)

    def wait_for_server(self, tried: set, timeout: float) -> bool:
        """Wait up to ``timeout`` s until a serving node not in ``tried`` ((tier, node) pairs) is alive
        (this robot's own node counts as a leader, not as a peer)."""
        end = time.monotonic() + timeout
        with self._lock:
            while True:
                # this robot itself counts once it leads (a leader-capable robot cut off with its
                # part serves itself as the part's leader; waiting for another wasted the wait)
                if any((t, n) not in tried and (n != self.me or t == "leader") for t in ("cloud", "leader", "peer")
                       for n in self._alive.get(t, ())):
                    return True
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self.changed.wait(left)

    def wait_for_tier(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s until some cloud or leader node is alive."""
        end = time.monotonic() + timeout
        with self._lock:
            while not (self._alive["cloud"] or self._alive["leader"]):
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self.changed.wait(left)
            return True
