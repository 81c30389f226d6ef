"""Leadership of the R2R tier as a role: a deterministic election over live candidates.

No external coordinator: every leader-capable node (a robot started with
``--leader-capable`` or the dedicated ``scmr leader``) runs a
:class:`Candidate`.  It holds the liveliness token
``scmr/alive/candidate/<node>``, publishes its candidacy on
``scmr/r2r/candidate/<node>`` (on every change and every heartbeat; the same
key is a queryable answering it, so a newcomer learns every state at once) and
applies the rule below whenever a token or a candidacy changes.  The holder of
the lead declares the leader queryable and token (through the ``on_lead``
callback); it gives them up through ``on_step_down``.

The rule (pure: :func:`decide`, :func:`rank_key`, :func:`outranks`)
------------------------------------------------------------------
* **Rank** of a candidate, best first: eligible (battery >= :data:`LOW_BATTERY`)
  before not; higher clock; lower compute power; higher battery (tenths);
  lower load (quarters of a worker); then the smaller node id.  Buckets keep a
  small change of battery or load from reordering candidates.
* **Term**: every claim takes a term one above the highest term its claimant
  has seen.  Between two leaders the higher term wins; at equal terms the
  better rank wins.  The loser steps down at once.
* **Terms cannot jump without bound** (issue #28): a candidacy whose term is
  more than :data:`TERM_WINDOW` above this node's term is refused (counted in
  ``refused_terms``, its sender counts as no candidate here), and this node
  adopts a term more than one above its own at most once per heartbeat.  A
  liar publishing ``wire.MAX_TERM`` is ignored; ratcheting the others up by
  one window per heartbeat would take 2^33 heartbeats (68 years) to exhaust
  the terms.
* **No preemption**: a live leader keeps the lead even when a better
  candidate appears.  Only a vacancy (no live candidate claims the lead)
  starts an election: the best-ranked live candidate claims at once; the
  k-th best claims only after the vacancy has lasted ``k * claim_wait_s``
  (covers a best candidate that cannot act).
* **An isolated node does not claim**: a candidate with no Zenoh link to any
  other node (its bootstrap unreachable) has nobody to lead and waits until
  it is linked (a restarted leader whose bootstrap is cut off would otherwise
  claim alone and then yield after the heal).  A client of a router (topology
  shape ``routers``) is always linked to its own router, so there "linked"
  means that some other node's liveliness token reaches it.
* **A blinking token does not make the lead flap**: when the leader's token
  blinks off, the best other candidate claims term T+1; when the old leader
  comes back with term T it sees T+1 and steps down.  The lead moved once
  and stays; it never moves back because the old leader is better.

Why it converges: candidates that see the same live set agree on the best,
so at most one claims.  Views that differ (a partition, a half-open link)
can make several claim; every pair of leaders that see each other compares
(term, rank), a total order, so each sees the other's claim and all but the
greatest step down.  During a partition each side keeps its own leader
(that keeps each side served); after the heal the sides see each other again
and one leader remains.  docs/R2R.md has the measured figures.

Events
------
Each change of this node's role is appended as one JSON line to
``events_path`` (``{"t_unix_ns", "node", "event": "lead" | "step_down",
"term", "cause", "leaders_seen"}``); fleet and scenario reports derive the
``leadership`` block from them (:mod:`scmr_mesh.qos.leadership`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Mapping

from scmr_mesh import keys, wire
from scmr_mesh.mesh.resources import appeared, undeclare_all
from scmr_mesh.qos.roles import RoleChange, RoleEvent, Why

log = logging.getLogger(__name__)

#: Below this battery level a candidate is ranked after every candidate above it.
LOW_BATTERY = 0.2
#: Seconds between candidacy heartbeats.
HEARTBEAT_S = 0.25
#: The k-th best candidate claims a vacancy only after ``k * CLAIM_WAIT_S``.
CLAIM_WAIT_S = 0.3
#: After start, watch this long before claiming (let gossip connect the mesh).
STARTUP_GRACE_S = 0.3
#: Largest jump above this node's term that another node's candidacy may make (more: refused).
#: Honest terms rise by one per election: 2^20 is a million elections ahead of this node.
TERM_WINDOW = 2**20


# ------------------------------------------------------------------ pure rule
@dataclass(frozen=True)
class Candidacy:
    """What a candidate tells the others (one ``candidate`` message)."""

    node: str
    term: int = 0
    leading: bool = False
    clock_hz: float = 1e9
    power_w: float | None = None
    battery: float = 1.0
    load: float = 0.0
    since_unix_ns: int | None = None
    capability: str = ""
    follows: str | None = None

    @classmethod
    def from_message(cls, msg: Mapping) -> Candidacy:
        return cls(node=msg["node"], term=int(msg["term"]), leading=bool(msg["leading"]),
                   clock_hz=float(msg["clock_hz"]), power_w=msg.get("power_w"),
                   battery=float(msg["battery"]), load=float(msg["load"]),
                   since_unix_ns=msg.get("since_unix_ns"), capability=msg.get("capability", ""),
                   follows=msg.get("follows"))

    def to_message(self) -> dict:
        return wire.make_candidate(self.node, term=self.term, leading=self.leading, clock_hz=self.clock_hz,
                                   power_w=self.power_w, battery=self.battery, load=self.load,
                                   since_unix_ns=self.since_unix_ns, capability=self.capability,
                                   follows=self.follows)


def term_admissible(mine: int, theirs: int, *, window: int = TERM_WINDOW) -> bool:
    """Whether a candidacy at term ``theirs`` may count for a node at term ``mine``.

    >>> term_admissible(5, 6), term_admissible(5, 5 + TERM_WINDOW + 1)
    (True, False)
    """
    return theirs <= mine + window


def rank_key(c: Candidacy) -> tuple:
    """Sort key of a candidate: the smallest key is the best candidate.

    Examples
    --------
    >>> a = Candidacy("r1", clock_hz=2.5e9, power_w=93)
    >>> b = Candidacy("r2", clock_hz=3.5e9, power_w=177)
    >>> sorted([a, b], key=rank_key)[0].node
    'r2'
    """
    return (
        c.battery < LOW_BATTERY,
        -round(c.clock_hz / 1e6),                       # MHz: capability from the energy profile
        math.inf if c.power_w is None else round(c.power_w, 1),
        -math.floor(c.battery * 10 + 1e-9),             # tenths of battery
        math.floor(c.load * 4 + 1e-9),                  # quarters of a worker
        c.node,
    )


def static_key(c: Candidacy) -> tuple:
    """The part of the rank that does not change while a node runs: clock, power, id (best first)."""
    return (-round(c.clock_hz / 1e6), math.inf if c.power_w is None else round(c.power_w, 1), c.node)


def outranks(a: Candidacy, b: Candidacy) -> bool:
    """Whether leader ``a`` wins over leader ``b``: higher term, else better static rank.

    Battery and load are left out on purpose: each leader would compare its own
    current load with the other's last published one, and both could yield (or
    both stay).
    """
    if a.term != b.term:
        return a.term > b.term
    return static_key(a) < static_key(b)


@dataclass(frozen=True)
class Decision:
    """What :func:`decide` tells a candidate to do."""

    action: str  # "claim", "step_down" or "stay"
    term: int = 0
    reason: str = ""  # for people (logs, the events' ``cause``); code reads ``why`` and ``by``
    why: Why = Why.OTHER
    by: str | None = None  # the leader that outranked this one (step_down)


def decide(me: Candidacy, others: Iterable[Candidacy], *, vacancy_s: float | None,
           claim_wait_s: float = CLAIM_WAIT_S) -> Decision:
    """Apply the election rule for ``me`` given the live ``others``.

    Parameters
    ----------
    me : Candidacy
        This node's candidacy (its ``term`` is the highest term it has seen).
    others : iterable of Candidacy
        Every other live candidate whose candidacy is known; those more than
        :data:`TERM_WINDOW` above ``me.term`` are left out (:func:`term_admissible`).
    vacancy_s : float or None
        How long no live leader has been seen (None: there is one).
    claim_wait_s : float
        The k-th best candidate claims after ``k * claim_wait_s``.

    Returns
    -------
    Decision
        ``claim`` (with the new term), ``step_down`` or ``stay``.
    """
    # a candidacy beyond the term window is a liar's (or from a fleet a million elections ahead):
    # it counts for nothing, so a maximal term cannot freeze the election
    others = [o for o in others if o.node != me.node and term_admissible(me.term, o.term)]
    max_term = max([me.term, *(o.term for o in others)])
    leaders = [o for o in others if o.leading]
    if me.leading:
        better = [lead for lead in leaders if outranks(lead, me)]
        if better:
            top = better[0]
            for b in better[1:]:
                if outranks(b, top):
                    top = b
            return Decision("step_down", max_term, f"outranked by {top.node} (term {top.term} vs {me.term})",
                            Why.OUTRANKED, top.node)
        # a leader this node cannot see, with a newer term, that another candidate follows
        via = [o for o in others if o.follows and o.follows != me.node and o.term > me.term]
        if via:
            v = max(via, key=lambda o: o.term)
            return Decision("step_down", max_term,
                            f"outranked by {v.follows} (term {v.term} vs {me.term}, seen by {v.node})",
                            Why.OUTRANKED, v.follows)
        return Decision("stay", me.term, "leading")
    if leaders:
        return Decision("stay", max_term, "following " + ",".join(sorted(o.node for o in leaders)))
    # no leader in sight here; if another candidate follows one, it lives (a link is down, not the
    # leader): no claim, so one leader stays (robots reach it; this node is served by peers)
    seen = sorted((o for o in others if o.follows and o.follows != me.node), key=lambda o: o.node)
    if seen:
        return Decision("stay", max_term, f"{seen[0].follows} leads (seen by {seen[0].node}, not from here)")
    ranked = sorted([me, *others], key=rank_key)
    k = ranked.index(me)
    if k == 0:
        return Decision("claim", max_term + 1, "vacancy; best-ranked live candidate", Why.VACANCY)
    if vacancy_s is not None and vacancy_s >= k * claim_wait_s:
        return Decision("claim", max_term + 1,
                        f"vacancy for {vacancy_s * 1e3:.0f} ms; {ranked[0].node} (ranked above) did not claim",
                        Why.VACANCY)
    return Decision("stay", max_term, f"vacancy; waiting for {ranked[0].node}")


def current_leader(candidacies: Iterable[Candidacy]) -> Candidacy | None:
    """The leader robots should use among ``candidacies`` that claim the lead (highest term, then rank)."""
    best = None
    for c in candidacies:
        if c.leading and (best is None or outranks(c, best)):
            best = c
    return best


# ---------------------------------------------------------------- the agent
@dataclass(frozen=True)
class Capability:
    """A candidate's serving capability, from an energy profile or the host."""

    clock_hz: float
    power_w: float | None
    source: str

    @classmethod
    def from_profile(cls, name: str | None, *, profiles_file: str | None = None) -> Capability:
        """From an energy profile (Table 4.3 or a user file); ``None``: this host's clock, power unknown."""
        if name:
            from scmr_mesh.energy import get_profile

            p = get_profile(name, profiles_file=profiles_file)
            return cls(float(p.clock_hz), float(p.p_compute_w), name)
        from scmr_mesh.energy.measure import host_clock_hz

        hz, _src = host_clock_hz()
        return cls(float(hz), None, "host")


class Candidate:
    """One node's side of the election (see the module docstring).

    Parameters
    ----------
    node : str
        The candidate's name (a robot id or the leader's node name).
    capability : Capability
    on_lead : callable
        ``fn(term)``: declare the leader queryable and token now.  Raising
        aborts the claim (logged; the node stays a follower).
    on_step_down : callable
        ``fn(reason)``: give up the leader queryable and token now.
    battery, load : callable, optional
        Current battery (0..1) and load (in-flight per worker).
    events_path : path, optional
        JSON lines of this node's role changes.
    grace_s, heartbeat_s, claim_wait_s : float
        See :data:`STARTUP_GRACE_S`, :data:`HEARTBEAT_S`, :data:`CLAIM_WAIT_S`.
    """

    def __init__(self, node: str, capability: Capability, *, on_lead: Callable[[int], None],
                 on_step_down: Callable[[str], None], battery: Callable[[], float] | None = None,
                 load: Callable[[], float] | None = None, events_path: str | os.PathLike | None = None,
                 grace_s: float = STARTUP_GRACE_S, heartbeat_s: float = HEARTBEAT_S,
                 claim_wait_s: float = CLAIM_WAIT_S, linked: Callable[[], bool] | None = None) -> None:
        self.node = keys.check_name(node)
        self.capability = capability
        self.on_lead = on_lead
        self.on_step_down = on_step_down
        self.closing = False  # set by close(): a step-down now is the process stopping
        self._battery = battery or (lambda: 1.0)
        #: ``fn() -> bool``: whether this node has a link to any other node (default: the session's peers)
        self._linked = linked
        self._load = load or (lambda: 0.0)
        self.events_path = Path(events_path) if events_path else None
        self.grace_s = grace_s
        self.heartbeat_s = heartbeat_s
        self.claim_wait_s = claim_wait_s
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._tokens: set[str] = set()          # live candidate tokens (other nodes)
        self._others_alive: set[str] = set()    # every live token of another node (scmr/alive/**)
        self._states: dict[str, Candidacy] = {}  # latest candidacy per other node
        self.term = 0
        self.leading = False
        self.since_unix_ns: int | None = None
        self._vacant_since: float | None = time.monotonic()
        self._started = time.monotonic()
        self._linked_since: float | None = None  # when this node last became linked to another
        self._rejoined = False
        self._said: tuple | None = None  # (leading, term, follows) last published
        self.refused_terms = 0  # candidacies refused for a term beyond the window
        self._jumped_at: float | None = None  # when this node last adopted a term more than one above its own
        self._session = None
        self._decl: list = []
        self._token = None
        self._pub = None
        self._thread: threading.Thread | None = None
        self.changes = 0

    # ---------------------------------------------------------- state
    def me(self) -> Candidacy:
        follows = None
        if not self.leading:
            lead = current_leader(self.live_others())
            follows = None if lead is None else lead.node
        return Candidacy(self.node, term=self.term, leading=self.leading, clock_hz=self.capability.clock_hz,
                         power_w=self.capability.power_w, battery=float(self._battery()),
                         load=float(self._load()), since_unix_ns=self.since_unix_ns,
                         capability=self.capability.source, follows=follows)

    def live_others(self) -> list[Candidacy]:
        with self._lock:
            return [s for n, s in self._states.items() if n in self._tokens]

    def leader(self) -> str | None:
        """The node this candidate currently considers the leader (itself included)."""
        with self._lock:
            if self.leading:
                return self.node
            lead = current_leader(self.live_others())
            return None if lead is None else lead.node

    # ------------------------------------------------------- callbacks
    def _on_token(self, sample) -> None:
        try:
            _, role, node = keys.parse(str(sample.key_expr))
        except Exception:
            return
        if role != "candidate" or node == self.node:
            return
        alive = appeared(sample)
        with self._lock:
            if alive:
                self._tokens.add(node)
            else:
                self._tokens.discard(node)
                self._states.pop(node, None)
        log.info("candidate %s: %s %s", self.node, node, "up" if alive else "gone")
        self._wake.set()

    def _on_any_token(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            _, _, node = keys.parse(key)
        except Exception:
            return
        if node == self.node:
            return
        with self._lock:
            (self._others_alive.add if appeared(sample) else self._others_alive.discard)(key)
        self._wake.set()

    def _on_state(self, sample) -> None:
        try:
            msg = wire.decode(sample.payload.to_bytes(), kind="candidate")
        except wire.WireProblem as exc:
            log.debug("ignoring candidacy: %s", exc)
            return
        self._take(Candidacy.from_message(msg), key=str(sample.key_expr))

    def _take(self, c: Candidacy, *, key: str) -> None:
        if c.node != keys.candidate_node(key):
            # access control lets X publish only on scmr/r2r/candidate/X; a candidacy naming
            # another node on it is a forgery (or a bug): it counts for nobody
            log.warning("candidate %s: ignoring a candidacy of %s that came on %s", self.node, c.node, key)
            return
        if c.node == self.node:
            return
        with self._lock:
            if not term_admissible(self.term, c.term):
                # a term beyond the window: the sender counts as no candidate here (issue #28)
                self.refused_terms += 1
                if self.refused_terms in (1, 10, 100) or self.refused_terms % 1000 == 0:
                    log.warning("candidate %s: refused %d candidacies with a term more than %d above ours "
                                "(%d), e.g. %s at term %d", self.node, self.refused_terms, TERM_WINDOW,
                                self.term, c.node, c.term)
                old = self._states.pop(c.node, None)
                if old is not None:
                    self._wake.set()
                return
            old = self._states.get(c.node)
            self._states[c.node] = c
            if not self.leading:  # a leader keeps its own term until it yields
                self._adopt(c.term)
        # decide again at once when what the rule reads changes: a candidate that stops following a
        # dead leader releases the claim of the best one (waking only on lead/term changes left that
        # to the next half heartbeat: crash -> claim took 138-154 ms in 9 of 10 scenario runs instead of ~20)
        if old is None or old.leading != c.leading or old.term != c.term or old.follows != c.follows:
            self._wake.set()

    def _on_query(self, query) -> None:
        try:
            query.reply(keys.candidate(self.node), wire.encode(self.me().to_message()), encoding=_msgpack())
        except Exception as exc:
            log.debug("candidacy reply failed: %s", exc)
        finally:
            try:
                query.drop()
            except Exception:
                pass

    # ------------------------------------------------------- life cycle
    def attach(self, session) -> None:
        """Declare the candidacy (token, publisher, queryable), learn the others, start deciding."""
        self._session = session
        ls = session.liveliness()
        self._decl.append(ls.declare_subscriber(f"{keys.ALIVE}/candidate/*", self._on_token, history=True))
        self._decl.append(ls.declare_subscriber(keys.ALIVE_ALL, self._on_any_token, history=True))
        self._decl.append(session.declare_subscriber(keys.CANDIDATES_ALL, self._on_state))
        self._decl.append(session.declare_queryable(keys.candidate(self.node), self._on_query))
        self._pub = session.declare_publisher(keys.candidate(self.node))
        self._token = ls.declare_token(keys.alive("candidate", self.node))
        self.refresh()
        self._started = time.monotonic()
        self._thread = threading.Thread(target=self._loop, name=f"election-{self.node}", daemon=True)
        self._thread.start()

    def refresh(self, timeout: float = 0.5) -> None:
        """Ask every candidate for its candidacy now (a newcomer's catch-up)."""
        try:
            for reply in self._session.get(keys.CANDIDATES_ALL, timeout=timeout):
                if reply.ok is None:
                    continue
                try:
                    self._take(Candidacy.from_message(
                        wire.decode(reply.ok.payload.to_bytes(), kind="candidate")), key=str(reply.ok.key_expr))
                except wire.WireProblem:
                    continue
        except Exception as exc:
            log.debug("candidacy refresh failed: %s", exc)

    def __enter__(self):
        """``with`` owns the Zenoh resources this object declares: leaving it calls :meth:`close`."""
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self, *, reason: str = "stopping") -> None:
        """Give up the lead (if held) and every declaration."""
        self._stop.set()
        self._wake.set()
        self.closing = True
        if self._thread is not None:
            self._thread.join(timeout=5)
        with self._lock:
            if self.leading:
                self._step_down(reason, Why.STOPPING)
        undeclare_all([self._token, self._pub, *self._decl])
        self._token = self._pub = None
        self._decl = []

    # ---------------------------------------------------------- deciding
    def _loop(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            self._wake.wait(self.heartbeat_s / 2)
            self._wake.clear()
            if self._stop.is_set():
                break
            changed = False
            if self._rejoined and self._session is not None:
                self._rejoined = False
                self.refresh(timeout=0.2)
            try:
                changed = self.evaluate()
            except Exception:  # never let the election thread die
                log.exception("candidate %s: election step failed", self.node)
            now = time.monotonic()
            me = self.me()
            # on any change of what it says (whom it follows, its term), at once: others wait on it
            said = (me.leading, me.term, me.follows)
            if changed or now >= next_beat or said != self._said:
                next_beat = now + self.heartbeat_s
                self._publish()

    def evaluate(self, now: float | None = None) -> bool:
        """Apply :func:`decide` once; act on it.  Returns True when this node's role changed."""
        now = time.monotonic() if now is None else now
        with self._lock:
            others = self.live_others()
            if self.leading or any(o.leading for o in others):
                self._vacant_since = None
            elif self._vacant_since is None:
                self._vacant_since = now
            if not self.leading and now - self._started < self.grace_s:
                return False
            vacancy = None if self._vacant_since is None else now - self._vacant_since
            linked = self._is_linked()
            if not linked:
                self._linked_since = None
            elif self._linked_since is None:  # (re)joined: learn the others before deciding
                self._linked_since = now
                self._rejoined = True
            d = decide(self.me(), others, vacancy_s=vacancy, claim_wait_s=self.claim_wait_s)
            if d.action == "claim":
                if not linked:
                    log.debug("candidate %s: vacancy, but no link to any node: not claiming", self.node)
                    return False
                if now - self._linked_since < self.grace_s and now - self._started >= self.grace_s:
                    return False  # just (re)linked: wait one grace for the others' candidacies
                return self._claim(d, others)
            if d.action == "step_down":
                self.term = d.term
                self._step_down(d.reason, d.why, d.by)
                return True
            if not self.leading:
                self._adopt(d.term, now)
            return False

    def _adopt(self, term: int, now: float | None = None) -> None:
        """Take ``term`` if higher: one above ours at any time, a bigger (bounded) jump once per heartbeat."""
        if term <= self.term:
            return
        if term > self.term + 1:
            now = time.monotonic() if now is None else now
            if self._jumped_at is not None and now - self._jumped_at < self.heartbeat_s:
                return
            self._jumped_at = now
        self.term = term

    def _is_linked(self) -> bool:
        if self._linked is not None:
            return bool(self._linked())
        s = self._session
        if s is None:
            return True
        try:
            if any(True for _ in s.info.peers_zid()):
                return True
            if not any(True for _ in s.info.routers_zid()):
                return False
        except Exception:
            return True
        # a client of a router (topology shape "routers"): the link to its own router says nothing
        # about the rest of the fleet; linked means some other node's token reaches it
        with self._lock:
            return bool(self._others_alive)

    def _claim(self, d: Decision, others: list[Candidacy]) -> bool:
        try:
            self.on_lead(d.term)
        except Exception as exc:
            log.error("candidate %s: could not take the lead (term %d): %s", self.node, d.term, exc)
            return False
        self.term = d.term
        self.leading = True
        self.since_unix_ns = time.time_ns()
        self._vacant_since = None
        self.changes += 1
        log.warning("candidate %s: leading (term %d): %s", self.node, d.term, d.reason)
        self._event(RoleEvent.LEAD, d.reason, others, d.why)
        self._publish()
        return True

    def _step_down(self, reason: str, why: Why = Why.OTHER, by: str | None = None) -> None:
        self.leading = False
        self.since_unix_ns = None
        self.changes += 1
        try:
            self.on_step_down(reason)
        except Exception as exc:
            log.error("candidate %s: stepping down failed: %s", self.node, exc)
        log.warning("candidate %s: stepped down (term %d): %s", self.node, self.term, reason)
        self._event(RoleEvent.STEP_DOWN, reason, self.live_others(), why, by)
        self._publish()

    def _publish(self) -> None:
        pub = self._pub
        if pub is None:
            return
        me = self.me()
        self._said = (me.leading, me.term, me.follows)
        try:
            pub.put(wire.encode(me.to_message()), encoding=_msgpack())
        except Exception as exc:
            log.debug("candidacy publish failed: %s", exc)

    def _event(self, event: RoleEvent, cause: str, others: list[Candidacy], why: Why = Why.OTHER,
               by: str | None = None) -> None:
        """One structured role change (:class:`~scmr_mesh.qos.roles.RoleChange`) in ``events_path``."""
        if self.events_path is None:
            return
        line = RoleChange(time.time_ns(), self.node, event, self.term, why, by, cause,
                          tuple(sorted(o.node for o in others if o.leading))).to_json()
        try:
            self.events_path.parent.mkdir(parents=True, exist_ok=True)
            with open(self.events_path, "a", encoding="utf-8") as f:
                f.write(json.dumps(line) + "\n")
        except OSError as exc:
            log.warning("candidate %s: cannot write %s: %s", self.node, self.events_path, exc)


__all__ = [
    "CLAIM_WAIT_S", "Candidacy", "Candidate", "Capability", "Decision", "HEARTBEAT_S", "LOW_BATTERY",
    "STARTUP_GRACE_S", "current_leader", "decide", "outranks", "rank_key",
]


def _msgpack():
    from scmr_mesh.mesh.encoding import msgpack

    return msgpack()
