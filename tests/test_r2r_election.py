"""The election rule of the R2R tier (pure: scmr_mesh/mesh/election.py's decide/rank_key/outranks).

Analytic cases first, then a simulation: candidates on a network that is cut
and healed at random, each deciding on its own view only.  After every heal
and a few rounds exactly one leader remains, terms never go down, and a live
leader is never preempted by a better candidate.
"""

from __future__ import annotations

import dataclasses

import itertools
import random

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.mesh.election import (
    LOW_BATTERY,
    Candidacy,
    current_leader,
    decide,
    outranks,
    rank_key,
)

L = Candidacy("leader0", clock_hz=3.5e9, power_w=177)
R1 = Candidacy("r1", clock_hz=2.83e9, power_w=106)
R2 = Candidacy("r2", clock_hz=2.5e9, power_w=93)


def test_rank_prefers_clock_then_power_then_battery_then_load_then_id():
    assert sorted([R2, L, R1], key=rank_key) == [L, R1, R2]
    same = dict(clock_hz=2e9, power_w=80)
    assert rank_key(Candidacy("a", power_w=50, clock_hz=2e9)) < rank_key(Candidacy("b", **same))
    assert rank_key(Candidacy("b", battery=0.9, **same)) < rank_key(Candidacy("a", battery=0.5, **same))
    assert rank_key(Candidacy("b", load=0.0, **same)) < rank_key(Candidacy("a", load=2.0, **same))
    assert rank_key(Candidacy("a", **same)) < rank_key(Candidacy("b", **same))  # ties by id


def test_small_changes_of_battery_or_load_do_not_reorder():
    a = Candidacy("a", clock_hz=2e9, battery=0.81, load=0.1)
    b = Candidacy("b", clock_hz=2e9, battery=0.89, load=0.2)
    assert rank_key(a) < rank_key(b)  # same tenth of battery, same quarter of load: by id


def test_low_battery_ranks_after_any_charged_candidate():
    weak = Candidacy("fast", clock_hz=9e9, battery=LOW_BATTERY - 0.01)
    assert sorted([weak, R2], key=rank_key) == [R2, weak]


def test_outranks_is_term_then_rank():
    assert outranks(Candidacy("r2", term=5, clock_hz=1e9), Candidacy("leader0", term=4, clock_hz=9e9))
    assert outranks(Candidacy("leader0", term=4, clock_hz=9e9), Candidacy("r2", term=4, clock_hz=1e9))


def test_vacancy_best_claims_others_wait():
    d = decide(L, [R1, R2], vacancy_s=0.0)
    assert (d.action, d.term) == ("claim", 1)
    assert decide(R1, [L, R2], vacancy_s=0.0).action == "stay"
    assert decide(R2, [L, R1], vacancy_s=0.0).action == "stay"


def test_the_kth_candidate_claims_after_k_waits():
    assert decide(R2, [L, R1], vacancy_s=0.59, claim_wait_s=0.3).action == "stay"
    assert decide(R2, [L, R1], vacancy_s=0.61, claim_wait_s=0.3).action == "claim"
    assert decide(R1, [L, R2], vacancy_s=0.31, claim_wait_s=0.3).action == "claim"


def test_no_preemption_of_a_live_leader():
    lead = Candidacy("r2", term=3, leading=True, clock_hz=2.5e9)
    assert decide(L, [lead, R1], vacancy_s=None).action == "stay"
    assert decide(lead, [L, R1], vacancy_s=None).action == "stay"


def test_a_claim_takes_one_above_the_highest_term_seen():
    d = decide(R1, [Candidacy("r2", term=7)], vacancy_s=10.0)
    assert (d.action, d.term) == ("claim", 8)


def test_two_leaders_the_lower_term_steps_down():
    old = Candidacy("leader0", term=1, leading=True, clock_hz=3.5e9)
    new = Candidacy("r1", term=2, leading=True, clock_hz=2.8e9)
    assert decide(old, [new], vacancy_s=None).action == "step_down"
    assert decide(new, [old], vacancy_s=None).action == "stay"
    assert current_leader([old, new]) == new


def test_a_blinking_leader_token_moves_the_lead_once():
    """The leader's token blinks off: r1 claims term 2; the old leader returns with term 1 and yields."""
    lead = Candidacy("leader0", term=1, leading=True, clock_hz=3.5e9)
    d = decide(Candidacy("r1", term=1, clock_hz=2.8e9), [R2], vacancy_s=0.0)  # leader0 invisible
    assert (d.action, d.term) == ("claim", 2)
    r1 = Candidacy("r1", term=2, leading=True, clock_hz=2.8e9)
    assert decide(lead, [r1, R2], vacancy_s=None).action == "step_down"   # back: it yields
    back = Candidacy("leader0", term=2, clock_hz=3.5e9)
    assert decide(back, [r1, R2], vacancy_s=None).action == "stay"        # and does not take it back
    assert decide(r1, [back, R2], vacancy_s=None).action == "stay"


# ------------------------------------------------------------ simulation
class Node:
    def __init__(self, c: Candidacy) -> None:
        self.c = c
        self.vacant_since: float | None = None

    def view(self, others: list[Candidacy]) -> list[Candidacy]:
        return others


def _with_follows(c: Candidacy, visible: list[Candidacy]) -> Candidacy:
    """``c`` as it publishes itself: following the leader it sees (none while it leads)."""
    lead = None if c.leading else current_leader(visible)
    return Candidacy(c.node, term=c.term, leading=c.leading, clock_hz=c.clock_hz, power_w=c.power_w,
                     follows=None if lead is None else lead.node)


def run_rounds(nodes: dict[str, Node], component_of, now: float, rounds: int = 6, dt: float = 0.35):
    """Each round every node decides on the candidacies of its component, as they were at the round start."""
    for _ in range(rounds):
        raw = {n: x.c for n, x in nodes.items()}
        snapshot = {n: _with_follows(c, [raw[m] for m in nodes if m != n and component_of(m) == component_of(n)])
                    for n, c in raw.items()}
        for n, x in nodes.items():
            others = [snapshot[m] for m in nodes if m != n and component_of(m) == component_of(n)]
            leading_seen = x.c.leading or any(o.leading for o in others)
            if leading_seen:
                x.vacant_since = None
            elif x.vacant_since is None:
                x.vacant_since = now
            vac = None if x.vacant_since is None else now - x.vacant_since
            d = decide(x.c, others, vacancy_s=vac, claim_wait_s=0.3)
            old_term = x.c.term
            if d.action == "claim":
                x.c = Candidacy(n, term=d.term, leading=True, clock_hz=x.c.clock_hz, power_w=x.c.power_w)
                x.vacant_since = None
            elif d.action == "step_down":
                x.c = Candidacy(n, term=d.term, leading=False, clock_hz=x.c.clock_hz, power_w=x.c.power_w)
            elif d.term > x.c.term and not x.c.leading:
                x.c = Candidacy(n, term=d.term, leading=False, clock_hz=x.c.clock_hz, power_w=x.c.power_w)
            assert x.c.term >= old_term, "a term went down"
        now += dt
    return now


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(2, 6),
    splits=st.lists(st.lists(st.integers(0, 1), min_size=6, max_size=6), min_size=1, max_size=4),
    seed=st.integers(0, 10_000),
)
def test_partitions_each_side_elects_and_one_leader_remains_after_the_heal(n, splits, seed):
    rng = random.Random(seed)
    names = [f"c{i}" for i in range(n)]
    nodes = {m: Node(Candidacy(m, clock_hz=rng.choice([1e9, 2.5e9, 3.5e9]), power_w=rng.choice([50.0, 100.0])))
             for m in names}
    now = run_rounds(nodes, lambda m: 0, 0.0)
    assert sum(x.c.leading for x in nodes.values()) == 1
    for split in splits:
        side = {m: split[i] for i, m in enumerate(names)}
        before = {m: x.c for m, x in nodes.items()}
        now = run_rounds(nodes, side.get, now)
        for s in set(side.values()):  # during the partition, each side has exactly one leader
            assert sum(nodes[m].c.leading for m in names if side[m] == s) == 1
        for m in names:  # no preemption: a leader that kept its side kept the lead
            if before[m].leading and all(not nodes[k].c.leading or k == m for k in names if side[k] == side[m]):
                assert nodes[m].c.leading
        now = run_rounds(nodes, lambda m: 0, now)  # heal
        leaders = [m for m, x in nodes.items() if x.c.leading]
        assert len(leaders) == 1, leaders


def test_one_link_down_keeps_one_leader():
    """L - r1 cut, both linked to r2: r1 sees no leader, but r2 follows L, so r1 does not claim."""
    lead = Candidacy("L", term=1, leading=True, clock_hz=3.5e9)
    r2 = Candidacy("r2", term=1, clock_hz=2.5e9, follows="L")
    d = decide(Candidacy("r1", term=1, clock_hz=2.8e9), [r2], vacancy_s=5.0)
    assert d.action == "stay" and "L leads" in d.reason
    # and a leader that claimed before it knew steps down when a follower reports a newer leader
    r2_following_r1 = Candidacy("r2", term=2, clock_hz=2.5e9, follows="r1")
    assert decide(lead, [r2_following_r1], vacancy_s=None).action == "step_down"


def test_leaders_at_one_term_compare_on_what_does_not_change():
    """Load and battery are not compared between leaders (each sees the other's stale values)."""
    a = Candidacy("a", term=2, leading=True, clock_hz=2e9, load=0.0)
    b = Candidacy("b", term=2, leading=True, clock_hz=2e9, load=3.0)
    a_busy = Candidacy("a", term=2, leading=True, clock_hz=2e9, load=3.0)
    assert decide(a_busy, [b], vacancy_s=None).action == "stay"      # a < b by id, whatever the loads
    assert decide(b, [a], vacancy_s=None).action == "step_down"


def test_simulation_detects_a_broken_rule(monkeypatch):
    """The simulation can fail: with leaders that never yield, two leaders survive a heal."""
    import scmr_mesh.mesh.election as election

    monkeypatch.setattr(election, "outranks", lambda a, b: False)
    nodes = {m: Node(Candidacy(m, clock_hz=2e9)) for m in ("a", "b")}
    now = run_rounds(nodes, lambda m: 0, 0.0)
    now = run_rounds(nodes, {"a": 0, "b": 1}.get, now)
    run_rounds(nodes, lambda m: 0, now)
    assert sum(x.c.leading for x in nodes.values()) == 2


@pytest.mark.parametrize("order", list(itertools.permutations(range(3))))
def test_the_surviving_leader_does_not_depend_on_who_looks_first(order):
    leaders = [Candidacy("a", term=2, leading=True, clock_hz=1e9), Candidacy("b", term=2, leading=True, clock_hz=2e9),
               Candidacy("c", term=1, leading=True, clock_hz=9e9)]
    survivors = set()
    for i in order:
        me = leaders[i]
        if decide(me, [x for x in leaders if x is not me], vacancy_s=None).action == "stay":
            survivors.add(me.node)
    assert survivors == {"b"}


def test_an_isolated_candidate_does_not_claim_until_it_is_linked():
    from scmr_mesh.mesh.election import Candidate, Capability

    links = {"up": False}
    led = []
    c = Candidate("leader0", Capability(3.5e9, 177.0, "leader"), on_lead=led.append, on_step_down=lambda r: None,
                  grace_s=0.0, linked=lambda: links["up"])
    assert c.evaluate() is False and not c.leading and led == []  # nobody to lead
    links["up"] = True
    assert c.evaluate() is True and c.leading and led == [1]


def test_a_candidacy_that_stops_following_wakes_the_election_at_once():
    """r2 following the dead leader holds r1's claim; r2's next candidacy (follows nobody) must make
    r1 decide again at once, not at its next half heartbeat."""
    from scmr_mesh import keys
    from scmr_mesh.mesh.election import Candidacy, Candidate, Capability

    c = Candidate("r1", Capability(3.0e9, 10.0, "robot4"), on_lead=lambda t: None, on_step_down=lambda r: None)
    r2 = Candidacy("r2", term=1, leading=False, clock_hz=2.0e9, power_w=5.0, battery=1.0, load=0.0,
                   since_unix_ns=0, capability="robot3", follows="leader0")
    c._take(r2, key=keys.candidate("r2"))
    c._wake.clear()
    c._take(dataclasses.replace(r2, load=0.5), key=keys.candidate("r2"))
    assert not c._wake.is_set()  # a load change alone does not change the decision
    c._take(dataclasses.replace(r2, follows=None), key=keys.candidate("r2"))
    assert c._wake.is_set()


# ------------------------------------------------------- the robot's and the node's side (no zenoh)
class _FakeService:
    """Enough of mesh.server.Service for R2RNode: serve_as/attach/detach record what is declared."""

    def __init__(self, fail_tier=None):
        self.node, self.tier, self.session, self.fail_tier = "r1", "peer", None, fail_tier
        self.declared: list[str] = []
        self.capability = None

        class _State:
            inflight, workers = 0, 1
        self.state = _State()

    def serve_as(self, tier, extra=None):
        self.tier = tier

    def attach(self, session, *, clock=None, warm=True):
        if self.tier == self.fail_tier:
            self.session = session  # half-declared, as a real failure could leave it
            raise RuntimeError("declare failed")
        self.session = session
        self.declared.append(self.tier)

    def detach(self, *, drain_s=2.0):
        self.session = None


class _FakeData:
    leading = False

    def queryables(self):
        return []


def test_a_failed_claim_leaves_the_node_serving_peers_not_half_switched():
    from scmr_mesh.mesh.election import Capability
    from scmr_mesh.mesh.r2r import R2RNode

    svc, data = _FakeService(fail_tier="leader"), _FakeData()
    node = R2RNode(svc, data, capability=Capability(2e9, 80.0, "test"), events_path=None)
    node.session = object()
    node._serve("peer")
    with pytest.raises(RuntimeError):
        node._lead(2)
    assert node.role == "peer" and svc.tier == "peer" and svc.session is not None and not data.leading


def test_stopping_does_not_declare_the_peer_service_again():
    from scmr_mesh.mesh.election import Capability
    from scmr_mesh.mesh.r2r import R2RNode

    svc, data = _FakeService(), _FakeData()
    node = R2RNode(svc, data, capability=Capability(2e9, 80.0, "test"), events_path=None)
    node.session = object()
    node._lead(1)
    node.candidate.closing = True  # what Candidate.close() sets: the step-down is the process stopping
    node._step_down("stopping")
    assert svc.declared == ["leader"] and svc.session is None and node.role == "standby"


def test_busy_answers_do_not_make_a_robot_wait_for_an_election(tmp_path, monkeypatch):
    from scmr_mesh.mesh.robot import Reachable, Robot

    robot = Robot("r9", tmp_path)
    monkeypatch.setattr(robot.view, "snapshot", lambda local=False: Reachable(leader=("L",), peer=("r2",)))
    monkeypatch.setattr(robot.view, "candidates", lambda: ["L", "r2"])

    def no_wait(*a, **k):
        raise AssertionError("waited for an election although the leader answered busy")

    monkeypatch.setattr(robot.view, "wait_for_server", no_wait)
    attempts = [{"tier": "leader", "node": "L", "outcome": "error:busy"},
                {"tier": "peer", "node": "r2", "outcome": "error:busy"}]
    tried = {("leader", "L"), ("peer", "r2")}
    assert robot._retry_fresh(lambda t, n: None, tried, 1e12, attempts) is None
    # a leader that did not answer (it died) does make it wait for the next one
    waited = []
    monkeypatch.setattr(robot.view, "wait_for_server", lambda tried, t: waited.append(t) or False)
    robot._retry_fresh(lambda t, n: None, tried, 1e12, [{"tier": "leader", "node": "L", "outcome": "no_reply"}])
    assert waited
    robot.close()


@pytest.mark.parametrize("view,expected", [
    # a cloud: no peers, whatever else is alive
    (dict(cloud=("c",), leader=("L",), peer=("p",)), ["cloud", "leader", "local"]),
    # no cloud: the leader, then peers (a busy leader answers busy: then a peer)
    (dict(leader=("L",), peer=("p",)), ["leader", "peer", "local"]),
    # no cloud, the leader published saturation: a peer with spare capacity first
    (dict(leader=("L",), peer=("p",), loads={"L": 1.0}), ["peer", "leader", "local"]),
    # no cloud, no leader (a lead is passing on): peers serve the gap
    (dict(peer=("p",)), ["peer", "local"]),
    # saturated peers are still tried after the leader, never before it
    (dict(leader=("L",), peer=("p",), loads={"L": 1.0, "p": 2.0}), ["leader", "peer", "local"]),
])
def test_default_placement_uses_peers_only_without_a_cloud(view, expected):
    from scmr_mesh.mesh.robot import FrameInfo, Reachable, default_placement

    assert default_placement(Reachable(local=True, **view), FrameInfo("r1", 0, 1000, "jpeg")) == expected


def test_the_view_never_offers_this_robot_as_its_own_peer():
    from scmr_mesh.mesh.robot import LiveView

    v = LiveView("r1")

    class Sample:
        def __init__(self, key):
            self.key_expr, self.kind = key, zenoh.SampleKind.PUT

    for key in ("scmr/alive/peer/r1", "scmr/alive/peer/r2", "scmr/alive/peer/r3"):
        v.on_liveliness(Sample(key))
    v.mark_busy("r3", 2.0)
    assert v.snapshot().peer == ("r2", "r3")  # spare capacity first; never itself


def test_an_r2r_node_used_with_with_stops_serving_once():
    from scmr_mesh.mesh.election import Capability
    from scmr_mesh.mesh.r2r import R2RNode

    svc, data = _FakeService(), _FakeData()
    data.close = lambda: setattr(data, "closed", getattr(data, "closed", 0) + 1)
    with R2RNode(svc, data, capability=Capability(2e9, 80.0, "test"), events_path=None) as node:
        node.session = object()
        node._lead(1)
        assert node.role == "leader" and svc.declared == ["leader"]
    assert svc.session is None and node.role == "stopped" and data.closed == 1
    node.close()  # idempotent: the data copy is not closed twice
    assert data.closed == 1


class _Decl:
    def __init__(self, log, name):
        self.log, self.name = log, name

    def undeclare(self):
        self.log.append(self.name)

    def put(self, *a, **k):
        pass


class _FakeSession:
    """Records what a Candidate declares and what it gives up (one linked peer)."""

    def __init__(self):
        self.undeclared: list[str] = []
        session = self

        class _Live:
            def declare_subscriber(self, key, cb, history=False):
                return _Decl(session.undeclared, "liveliness subscriber")

            def declare_token(self, key):
                return _Decl(session.undeclared, "token")

        class _Info:
            def peers_zid(self):
                return iter(["z"])

            def routers_zid(self):
                return iter([])

        self._live, self.info = _Live(), _Info()

    def liveliness(self):
        return self._live

    def declare_subscriber(self, key, cb):
        return _Decl(self.undeclared, "subscriber")

    def declare_queryable(self, key, cb):
        return _Decl(self.undeclared, "queryable")

    def declare_publisher(self, key):
        return _Decl(self.undeclared, "publisher")

    def get(self, key, timeout=None):
        return []


def test_a_candidate_used_with_with_gives_up_the_lead_and_every_declaration(tmp_path):
    from scmr_mesh.mesh.election import Candidate, Capability
    from scmr_mesh.mesh.testing import wait_for
    from scmr_mesh.qos.leadership import read_events
    from scmr_mesh.qos.roles import RoleChange, RoleEvent, Why

    session = _FakeSession()
    with Candidate("leader0", Capability(3.5e9, 177.0, "leader"), on_lead=lambda t: None,
                   on_step_down=lambda r: None, grace_s=0.0, events_path=tmp_path / "leader0.jsonl",
                   heartbeat_s=10.0) as c:
        c.attach(session)
        wait_for(lambda: c.leading, timeout=10, what="the lone linked candidate leads")
    assert sorted(session.undeclared) == ["liveliness subscriber", "liveliness subscriber", "publisher", "queryable", "subscriber", "token"]
    assert not c.leading
    events = [RoleChange.from_json(e) for e in read_events(tmp_path)]
    assert [(e.event, e.why) for e in events] == [(RoleEvent.LEAD, Why.VACANCY), (RoleEvent.STEP_DOWN, Why.STOPPING)]


def test_candidate_liveliness_is_read_by_the_sample_kind():
    from scmr_mesh import keys
    from scmr_mesh.mesh.election import Candidacy, Candidate, Capability

    class Sample:
        def __init__(self, kind):
            self.key_expr, self.kind = keys.alive("candidate", "r2"), kind

    c = Candidate("r1", Capability(3.0e9, 10.0, "robot4"), on_lead=lambda t: None, on_step_down=lambda r: None)
    c._on_token(Sample(zenoh.SampleKind.PUT))
    c._take(Candidacy("r2", term=1, leading=True), key=keys.candidate("r2"))
    assert c.leader() == "r2"
    c._on_token(Sample(zenoh.SampleKind.DELETE))
    assert c.leader() is None and c.live_others() == []


def test_a_liar_at_the_maximum_term_does_not_freeze_the_election():
    """Issue #28 item 2: a candidacy far beyond the term window (a liar at wire.MAX_TERM) counts for
    nothing: the honest best candidate claims the vacancy at its own term + 1 (before, it adopted the
    liar's term, and its claim at MAX_TERM + 1 was refused by every peer: no leader ever again)."""
    from scmr_mesh import keys, wire
    from scmr_mesh.mesh.election import TERM_WINDOW, Candidate, Capability

    liar = Candidacy("r9", term=wire.MAX_TERM, leading=True, clock_hz=1e12, power_w=1.0)
    d = decide(dataclasses.replace(L, term=7), [liar, dataclasses.replace(R1, term=7)], vacancy_s=0.0)
    assert (d.action, d.term) == ("claim", 8)
    near = dataclasses.replace(liar, term=7 + TERM_WINDOW)  # within the window: a leader like any other
    assert decide(dataclasses.replace(L, term=7), [near], vacancy_s=0.0).action == "stay"

    led = []
    c = Candidate("leader0", Capability(3.5e9, 177.0, "leader"), on_lead=led.append,
                  on_step_down=lambda r: None, grace_s=0.0, linked=lambda: True)
    c._take(liar, key=keys.candidate("r9"))
    assert c.term == 0 and c.refused_terms == 1 and c.live_others() == []
    # a ratchet one window at a time: one jump per heartbeat, the next one in the same beat refused
    c._take(dataclasses.replace(liar, term=TERM_WINDOW, leading=False), key=keys.candidate("r9"))
    c._take(dataclasses.replace(liar, term=TERM_WINDOW + 5, leading=False), key=keys.candidate("r9"))
    assert c.term == TERM_WINDOW
    c._tokens.add("r9")
    c._take(dataclasses.replace(liar, term=wire.MAX_TERM), key=keys.candidate("r9"))
    assert c.evaluate() is True and c.leading and led == [TERM_WINDOW + 1]
