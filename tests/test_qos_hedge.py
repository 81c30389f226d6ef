"""The hedge-delay rule and the hedge budget (scmr_mesh.qos.hedge, issue 24): pure, analytic cases. <1 s."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.qos.hedge import AnswerTimes, HedgeBudget, HedgeRule, hedge_delay_ms


def test_delay_is_p95_plus_margin():
    # 20 answers 1..20 ms: p95 (type 7) = 1 + 0.95 x 19 = 19.05; + margin 20
    xs = [float(i) for i in range(1, 21)]
    assert hedge_delay_ms(xs, deadline_ms=1000) == pytest.approx(39.05)
    rule = HedgeRule(margin_ms=5.0, floor_ms=0.0, quantile=0.5)
    assert hedge_delay_ms(xs, deadline_ms=1000, rule=rule) == pytest.approx(10.5 + 5.0)


def test_floor_and_cold_start():
    assert hedge_delay_ms([1.0] * 50, deadline_ms=1000) == 30.0  # 1 + 20 < floor 30
    assert hedge_delay_ms([1.0] * 4, deadline_ms=1000) == 150.0  # fewer than min_samples: cold_ms
    assert hedge_delay_ms([], deadline_ms=1000, rule=HedgeRule(cold_ms=10.0, floor_ms=25.0)) == 25.0


def test_one_slow_answer_in_a_window_moves_the_delay_only_as_far_as_the_p95():
    w = AnswerTimes(window=20, warmup=0)
    for _ in range(19):
        w.add(5.0)
    w.add(900.0)  # one stall in 20: the p95 (rank 18.05) interpolates 5 and 900 at 0.05
    d = hedge_delay_ms(w.values(), deadline_ms=1000)
    assert d == pytest.approx(5.0 + 0.05 * 895.0 + 20.0)
    for _ in range(20):  # the window forgets it
        w.add(5.0)
    assert hedge_delay_ms(w.values(), deadline_ms=1000) == 30.0


def test_bounded_by_the_deadline():
    # delay 30 + min_left 50 = 80: fits in 80, not in 79.9; time already spent counts
    assert hedge_delay_ms([1.0] * 10, deadline_ms=80) == 30.0
    assert hedge_delay_ms([1.0] * 10, deadline_ms=79.9) is None
    assert hedge_delay_ms([1.0] * 10, deadline_ms=200, elapsed_ms=121) is None
    assert hedge_delay_ms([1.0] * 10, deadline_ms=200, elapsed_ms=120) == 30.0


def test_bad_values_are_refused_with_what_was_given():
    with pytest.raises(ValueError, match="deadline_ms must be a finite number > 0, got 0"):
        hedge_delay_ms([1.0], deadline_ms=0)
    with pytest.raises(ValueError, match="floor_ms .* got -1"):
        HedgeRule(floor_ms=-1)
    with pytest.raises(ValueError, match="quantile must be in"):
        HedgeRule(quantile=1.5)
    with pytest.raises(ValueError, match="ratio must be in"):
        HedgeBudget(ratio=2.0)


def test_non_finite_samples_are_ignored():
    assert hedge_delay_ms([float("nan"), float("inf"), -1.0] + [1.0] * 5, deadline_ms=1000) == 30.0


@given(st.lists(st.booleans(), max_size=400), st.floats(0.0, 1.0), st.integers(1, 5))
@settings(max_examples=200)
def test_budget_never_allows_more_than_ratio_times_requests_plus_burst(wants, ratio, burst):
    b = HedgeBudget(ratio=ratio, burst=burst)
    taken = 0
    for want in wants:  # one request each: it earns, then may want a hedge
        b.earn()
        taken += want and b.take()
    assert taken <= ratio * len(wants) + burst + 1e-9


@given(st.lists(st.floats(0.0, 1e4), min_size=5, max_size=100), st.floats(1.0, 1e5))
@settings(max_examples=200)
def test_delay_is_at_least_the_floor_and_leaves_time_for_the_hedge(xs, deadline):
    rule = HedgeRule()
    d = hedge_delay_ms(xs, deadline_ms=deadline, rule=rule)
    if d is not None:
        assert d >= rule.floor_ms
        assert d + rule.min_left_ms <= deadline
        assert d >= sorted(xs)[int(0.95 * (len(xs) - 1))] + rule.margin_ms - 1e-6


def test_hedge_ms_flag_values():
    from scmr_mesh.mesh.commands import _hedge_ms

    assert [_hedge_ms(v) for v in ("auto", "OFF", "40", "0.5")] == ["auto", "off", 40.0, 0.5]
    for bad, why in (("abc", "not auto, off or a number"), ("4000000", "more than an hour")):
        with pytest.raises(ValueError, match=why):
            _hedge_ms(bad)


def test_the_first_answer_of_a_tier_is_not_learnt():
    w = AnswerTimes(window=64)  # warmup 1 by default
    for ms in [100.0] + [10.0] * 8:  # a cold first answer, then a steady tier
        w.add(ms)
    assert len(w) == 8 and hedge_delay_ms(w.values(), deadline_ms=1000) == 30.0
    w0 = AnswerTimes(window=64, warmup=0)
    for ms in [100.0] + [10.0] * 8:
        w0.add(ms)
    assert hedge_delay_ms(w0.values(), deadline_ms=1000) > 80.0  # control: the cold answer sets the p95


def test_hedges_reach_the_summary_and_the_expectation_metrics():
    from scmr_mesh.qos.metrics import summarize
    from scmr_mesh.scenario.report import _metric_values

    def rec(seq, tier, hedged=False, won=False):
        atts = [{"tier": "cloud", "node": "c", "outcome": "ok" if tier == "cloud" else "superseded"}]
        if hedged:
            atts.append({"tier": "leader", "node": "L", "outcome": "ok" if won else "superseded", "hedge": True})
        return {"robot": "r1", "seq": seq, "ok": True, "tier": tier, "sent_unix_ns": seq * 10**9,
                "received_unix_ns": seq * 10**9 + 10**7, "tor_ms": 10.0, "attempts": atts,
                "hedged": hedged, "hedge_won": won}

    recs = [rec(0, "cloud"), rec(1, "leader", True, True), rec(2, "cloud", True, False), rec(3, "cloud")]
    s = summarize(recs)
    assert s["hedges"] == {"hedged": 2, "hedge_won": 1, "hedge_rate": 0.5, "resent": 0,
                           "duplicates_by_tier": {"cloud": 1, "leader": 1}}
    assert (s["per_robot"]["r1"]["hedged"], s["per_robot"]["r1"]["hedge_won"]) == (2, 1)
    m = _metric_values(s)
    assert (m["hedged"], m["hedge_rate"]) == (2, 0.5)
