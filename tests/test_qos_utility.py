"""Eq 3.14 as an optional ranking of the request negotiator (utility of time and expense)."""

from __future__ import annotations

import argparse
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.errors import InputError
from scmr_mesh.qos.negotiator import (
    REASON_DISPLACED,
    Negotiator,
    ServiceTimeModel,
    UtilityRanking,
    utility,
)
from scmr_mesh.mesh.negotiation import add_arguments, service_setup  # the CLI glue left the pure core


def test_eq_3_14_by_hand():
    # 1 / (w_t * max t + w_e * sum e) = 1 / (2 * 0.5 + 0.25 * (1 + 3)) = 0.5
    assert utility([0.2, 0.5], [1.0, 3.0], w_time=2.0, w_expense=0.25) == pytest.approx(0.5)
    assert utility([0.1], [0.0], w_time=0.0, w_expense=1.0) == math.inf
    with pytest.raises(ValueError):
        utility([1.0], [1.0], w_time=0.0, w_expense=0.0)


def test_service_time_model_learns_a_line_and_forgets():
    m = ServiceTimeModel(prior_s=0.07)
    assert m.predict(123) == 0.07
    m.observe(1000, 0.009)
    assert m.predict(99999) == pytest.approx(0.009)  # one size seen: the mean
    for size in (2000, 4000, 8000):
        m.observe(size, 0.008 + size * 1e-6)
    assert m.predict(16000) == pytest.approx(0.024, rel=1e-6)
    short = ServiceTimeModel(memory=10)
    for _ in range(20):
        short.observe(1000, 0.5)
    for _ in range(100):  # the server got faster: old observations fade
        short.observe(1000, 0.01)
        short.observe(3000, 0.03)
    assert short.predict(2000) == pytest.approx(0.02, rel=1e-3)


def _trained(n: Negotiator) -> None:
    # service time = 5 ms + 1 ms per 100 kB, learnt from finished requests
    for i, size in enumerate((50_000, 400_000, 100_000, 800_000)):
        assert n.offer(("warm", i), 1, size=size).admitted
        e = n.take(timeout=0)
        n.done(e, service_s=0.005 + size * 1e-8)


def test_utility_ranking_serves_the_shortest_predicted_job_first():
    n = Negotiator(capacity=8, workers=1, ranking=UtilityRanking(w_time=1.0, w_expense=0.0))
    _trained(n)
    blocker = n.offer("busy", 1, size=1000)
    assert blocker.admitted and n.take(timeout=0).request_id == "busy"  # the worker is busy now
    for rid, size in (("big", 2_000_000), ("small", 20_000), ("mid", 300_000)):
        assert n.offer(rid, 1, size=size).admitted
    assert [e.request_id for e in n.waiting_entries()] == ["small", "mid", "big"]
    small = next(e for e in n.waiting_entries() if e.request_id == "small")
    assert small.utility == pytest.approx(1 / (0.005 + 20_000 * 1e-8), rel=1e-3)  # Eq 3.14, w_e = 0


def test_by_priority_the_same_requests_go_first_come_first_served():
    """The regression the option guards: without a ranking, sizes do not matter (Table 3.6)."""
    n = Negotiator(capacity=8, workers=1)
    _trained(n)
    n.offer("busy", 1, size=1000)
    n.take(timeout=0)
    for rid, size in (("big", 2_000_000), ("small", 20_000), ("mid", 300_000)):
        n.offer(rid, 1, size=size)
    assert [e.request_id for e in n.waiting_entries()] == ["big", "small", "mid"]


def test_bandwidth_price_changes_the_order():
    # two requests of equal predicted CPU time; the one with more megabytes costs more
    r = UtilityRanking(w_time=1.0, w_expense=1.0, price_per_s=0.0, price_per_mb=2.0)
    assert r.score(0.01, 1048576) == pytest.approx(1 / (0.01 + 2.0))
    assert r.score(0.01, 0) > r.score(0.01, 1048576)


def test_a_full_queue_displaces_the_lowest_utility():
    n = Negotiator(capacity=1, workers=1, ranking=UtilityRanking(w_time=1.0, w_expense=0.0))
    _trained(n)
    n.offer("busy", 1, size=1000)
    n.take(timeout=0)
    assert n.offer("big", 9, size=2_000_000).admitted  # high willingness to pay, low utility
    d = n.offer("small", 1, size=10_000)
    assert d.admitted and [(e.request_id, e.reason) for e in d.refused] == [("big", REASON_DISPLACED)]


@settings(max_examples=50, deadline=None)
@given(sizes=st.lists(st.integers(1, 5_000_000), min_size=1, max_size=12))
def test_waiting_order_is_by_decreasing_utility(sizes):
    n = Negotiator(capacity=32, workers=1, ranking=UtilityRanking(w_time=1.0, w_expense=0.5))
    _trained(n)
    n.offer("busy", 1, size=1)
    n.take(timeout=0)
    for i, s in enumerate(sizes):
        n.offer(i, 1, size=s)
    us = [e.utility for e in n.waiting_entries()]
    assert us == sorted(us, reverse=True)


def _args(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_arguments(p)
    return p.parse_args(list(argv))


def test_cli_wires_the_ranking():
    class Svc:
        class state:
            workers = 2

        def use_negotiator(self, neg):
            self.neg = neg

    svc = Svc()
    service_setup(_args("--queue", "4", "--rank", "utility", "--w-expense", "0", "--price-mb", "3"))(svc)
    assert svc.neg.ranking == UtilityRanking(w_time=1.0, w_expense=0.0, price_per_s=1.0, price_per_mb=3.0)
    service_setup(_args("--queue", "4"))(svc)
    assert svc.neg.ranking is None
    with pytest.raises(InputError, match="--queue"):
        service_setup(_args("--rank", "utility"))
    with pytest.raises(InputError, match="w-time"):
        service_setup(_args("--queue", "4", "--rank", "utility", "--w-time", "0", "--w-expense", "0"))
