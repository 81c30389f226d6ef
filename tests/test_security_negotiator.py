"""The request negotiator (thesis Table 3.6): bounded, priority-ordered, explicit refusals.

Pure tests, about 3 s.
"""

from __future__ import annotations

import random
import threading

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
)

from scmr_mesh.qos.negotiator import (
    REASON_DISPLACED,
    REASON_FULL,
    REASON_MINIMUM,
    REASON_QUOTA,
    Negotiator,
    jain_index,
)


def test_burst_admits_exactly_the_top_priorities():
    cap, workers = 3, 2
    n = Negotiator(capacity=cap, workers=workers)
    prios = list(range(20))
    random.Random(1).shuffle(prios)
    admitted, refused = set(), set()
    for p in prios:
        d = n.offer(p, p)
        if d.admitted:
            admitted.add(p)
        refused.update(e.request_id for e in d.refused)
    live = {e.request_id for e in n.waiting_entries()}
    assert live == set(range(20 - cap - workers, 20))
    assert live | refused == set(prios) and not (live & refused)
    served = [n.take(timeout=0).request_id for _ in range(workers)]
    assert served == [19, 18]
    assert n.take(timeout=0) is None  # every worker busy


def test_equal_priority_is_fifo_and_never_displaced():
    n = Negotiator(capacity=2, workers=1)
    for i in range(3):
        assert n.offer(i, 7).admitted
    d = n.offer("late", 7)
    assert not d.admitted and d.refused[0].reason == REASON_FULL
    assert [n.take(timeout=0).request_id] == [0]


def test_minimum_priority_and_quota():
    n = Negotiator(capacity=4, workers=1, min_priority=3, per_robot=1)
    assert n.offer("low", 2).refused[0].reason == REASON_MINIMUM
    assert n.offer("r1-a", 5, robot="r1").admitted
    assert n.take(timeout=0).request_id == "r1-a"       # the worker is busy now
    assert n.offer("r1-b", 5, robot="r1").admitted      # r1 holds one waiting slot
    assert n.offer("r1-c", 9, robot="r1").refused[0].reason == REASON_QUOTA
    assert n.offer("r2-a", 5, robot="r2").admitted


def test_capacity_zero_serves_only_idle_workers():
    n = Negotiator(capacity=0, workers=2)
    assert n.offer("a", 1).admitted and n.offer("b", 1).admitted
    assert not n.offer("c", 1).admitted
    e = n.take(timeout=0)
    n.done(e, service_s=0.01)
    assert n.offer("d", 1).admitted


def test_done_without_take_is_an_error():
    with pytest.raises(RuntimeError, match="no request in service"):
        Negotiator(capacity=1).done()


@pytest.mark.parametrize("kw", [{"capacity": -1}, {"capacity": 1, "workers": 0}, {"capacity": 1, "per_robot": 0}])
def test_bad_parameters_are_named(kw):
    with pytest.raises(ValueError, match="got"):
        Negotiator(**kw)


def test_close_returns_waiting_and_refuses_new():
    n = Negotiator(capacity=3, workers=1)
    for i in range(4):
        n.offer(i, i)
    left = n.close()
    assert {e.request_id for e in left} == {0, 1, 2, 3}
    assert not n.offer("x", 99).admitted
    assert n.take(timeout=0) is None


def test_jain_index_cases():
    assert jain_index([3, 3, 3]) == pytest.approx(1.0)
    assert jain_index([1, 0, 0, 0]) == pytest.approx(0.25)
    assert jain_index([]) == 1.0
    assert 0.25 < jain_index([4, 2, 1, 1]) < 1.0


@given(st.lists(st.floats(0, 1e6, allow_nan=False), min_size=1, max_size=30))
@example([2.596206522714877e-161, 2.596206522714877e-161])  # x * x underflowed: index 1.0037
def test_jain_index_is_between_one_over_n_and_one(xs):
    j = jain_index(xs)
    assert 1.0 / len(xs) - 1e-9 <= j <= 1.0 + 1e-9


class NegotiatorMachine(RuleBasedStateMachine):
    """Random arrivals, takes and completions against a reference bookkeeping."""

    @initialize(cap=st.integers(0, 5), workers=st.integers(1, 3),
                per_robot=st.sampled_from([None, 1, 2]))
    def setup(self, cap, workers, per_robot):
        self.cap, self.workers, self.per_robot = cap, workers, per_robot
        self.n = Negotiator(capacity=self.cap, workers=self.workers, min_priority=1,
                            per_robot=self.per_robot)
        self.next_id = 0
        self.offered: dict[int, int] = {}
        self.fate: dict[int, str] = {}
        self.in_service: list = []

    @rule(priority=st.integers(0, 6), robot=st.sampled_from(["r1", "r2", "r3"]))
    def offer(self, priority, robot):
        rid = self.next_id
        self.next_id += 1
        waiting_before = self.n.waiting_entries()
        d = self.n.offer(rid, priority, robot=robot)
        self.offered[rid] = priority
        for e in d.refused:
            assert e.request_id not in self.fate
            self.fate[e.request_id] = e.reason
            if e.reason == REASON_DISPLACED:
                # only a strictly lower priority is displaced, and it was the lowest waiting
                assert e.priority < priority
                assert e.priority == min(w.priority for w in waiting_before)
            if e.reason == REASON_FULL:
                if waiting_before:
                    assert priority <= min(w.priority for w in waiting_before)
                else:  # no room at all: capacity 0 and every worker busy
                    assert self.cap == 0 and len(self.in_service) == self.workers
        assert d.admitted == (rid not in self.fate)
        if not d.admitted:
            assert d.retry_after_ms > 0

    @precondition(lambda self: len(self.in_service) < self.workers)
    @rule()
    def take(self):
        before = self.n.waiting_entries()
        e = self.n.take(timeout=0)
        if not before:
            assert e is None
            return
        best = before[0]
        assert (e.priority, e.seq) == (best.priority, best.seq)
        self.in_service.append(e)

    @precondition(lambda self: self.in_service)
    @rule(i=st.integers(0, 10), dt=st.floats(0, 0.2))
    def done(self, i, dt):
        e = self.in_service.pop(i % len(self.in_service))
        self.n.done(e, service_s=dt)
        self.fate[e.request_id] = "served"

    @invariant()
    def bounded(self):
        assert self.n.waiting + self.n.in_service <= self.cap + self.workers
        assert self.n.in_service == len(self.in_service) <= self.workers
        # heaps are compacted: memory stays proportional to what waits
        assert len(self.n._best) <= 2 * self.n.waiting + 17
        assert len(self.n._worst) <= 2 * self.n.waiting + 17

    @invariant()
    def conserved(self):
        waiting = {e.request_id for e in self.n.waiting_entries()}
        serving = {e.request_id for e in self.in_service}
        fated = set(self.fate)
        assert waiting | serving | fated == set(self.offered)
        assert not (waiting & serving) and not (waiting & fated) and not (serving & fated)
        s = self.n.stats
        assert s.offered == len(self.offered)
        assert s.served == sum(1 for f in self.fate.values() if f == "served")

    @invariant()
    def quota_holds_when_contended(self):
        if self.per_robot is None:
            return
        counts: dict[str, int] = {}
        for e in self.n.waiting_entries():
            counts[e.robot] = counts.get(e.robot, 0) + 1
        # a robot may exceed its quota only by requests taken straight by idle workers
        assert all(c <= self.per_robot + self.workers for c in counts.values())


TestNegotiatorMachine = NegotiatorMachine.TestCase
TestNegotiatorMachine.settings = settings(max_examples=int(__import__("os").environ.get("SCMR_NEG_EXAMPLES", "60")), stateful_step_count=40, deadline=None)


def test_threads_offer_take_done_conserve_requests():
    n = Negotiator(capacity=4, workers=2)
    served: list = []
    refused: list = []
    lock = threading.Lock()
    stop = threading.Event()

    def worker():
        while not stop.is_set():
            e = n.take(timeout=0.01)
            if e is not None:
                with lock:
                    served.append(e.request_id)
                n.done(e, service_s=0.0)

    def robot(k):
        rng = random.Random(k)
        for i in range(300):
            d = n.offer((k, i), rng.randint(0, 9), robot=f"r{k}")
            with lock:
                refused.extend(e.request_id for e in d.refused)

    workers = [threading.Thread(target=worker) for _ in range(2)]
    robots = [threading.Thread(target=robot, args=(k,)) for k in range(4)]
    for t in workers + robots:
        t.start()
    for t in robots:
        t.join()
    while n.waiting or n.in_service:
        threading.Event().wait(0.01)
    stop.set()
    for t in workers:
        t.join()
    assert len(served) + len(refused) == 1200
    assert len(set(served) | set(refused)) == 1200
    assert n.stats.max_waiting <= 4 + 2
