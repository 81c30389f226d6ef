"""Metrics from hand-made request records: percentiles, RoR, tiers, gaps."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.qos import metrics

MS = 1_000_000  # ns per ms
T0 = 1_700_000_000_000_000_000


def rec(robot, sent_ms, recv_ms, tier, ok=True):
    """A record sent at T0 + sent_ms and answered at T0 + recv_ms."""
    return {
        "robot": robot,
        "sent_unix_ns": T0 + int(sent_ms * MS),
        "received_unix_ns": None if recv_ms is None else T0 + int(recv_ms * MS),
        "tor_ms": None if recv_ms is None else recv_ms - sent_ms,
        "ok": ok,
        "tier": tier if ok else None,
    }


def cloud_crash(start_ms, end_ms=None, **kw):
    return {"kind": "crash", "target": "cloud0", "tier": "cloud",
            "start_unix_ns": T0 + start_ms * MS,
            "end_unix_ns": None if end_ms is None else T0 + end_ms * MS, **kw}


# --- percentiles, ToR, RoR, tiers -----------------------------------------

def test_percentile_analytic():
    assert metrics.percentile([1, 2, 3, 4], 50) == 2.5
    assert metrics.percentile([4, 1, 3, 2], 0) == 1
    assert metrics.percentile([1, 2, 3, 4], 100) == 4
    # (N-1) q = 10 * 0.9 = 9 -> exactly the 10th smallest of 0..10
    assert metrics.percentile(list(range(11)), 90) == 9
    assert metrics.percentile([0, 10], 99) == pytest.approx(9.9)
    assert metrics.percentile([7.0], 99) == 7.0


def test_percentile_rejects_bad_input():
    with pytest.raises(ValueError, match="empty"):
        metrics.percentile([], 50)
    with pytest.raises(ValueError, match="got 101"):
        metrics.percentile([1], 101)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=50),
       st.floats(0, 100))
def test_percentile_matches_numpy(values, q):
    assert metrics.percentile(values, q) == pytest.approx(np.percentile(values, q), rel=1e-9, abs=1e-6)


def test_tor_ror_and_tiers_count_only_what_they_should():
    recs = [rec("a", 0, 10, "cloud"), rec("a", 200, 220, "cloud"), rec("b", 0, 30, "leader"),
            rec("b", 200, None, None, ok=False), rec("c", 0, 40, "local")]
    s = metrics.summarize(recs)
    assert s["requests"] == 5 and s["succeeded"] == 4 and s["ror"] == 0.8
    # ToR of the 4 succeeded requests: 10, 20, 30, 40
    assert s["tor_ms"]["p50"] == 25 and s["tor_ms"]["max"] == 40 and s["tor_ms"]["mean"] == 25
    assert s["tor_ms"]["p90"] == pytest.approx(37)
    assert s["by_tier"] == {"cloud": 2, "leader": 1, "peer": 0, "local": 1, "failed": 1}
    assert s["robots"] == 3
    assert s["per_robot"]["b"]["ror"] == 0.5 and s["per_robot"]["b"]["tor_ms"]["p50"] == 30
    assert s["per_tier"]["cloud"]["max"] == 20
    assert s["failover_gaps_ms"] == [] and s["failback_gaps_ms"] == [] and s["faults"] == []


def test_empty_run():
    s = metrics.summarize([], robots=4)
    assert s["robots"] == 4 and s["requests"] == 0 and s["ror"] is None
    assert s["tor_ms"]["p50"] is None


def test_tor_derived_from_timestamps_when_missing():
    r = rec("a", 0, 12, "cloud")
    r["tor_ms"] = None
    assert metrics.tor_values_ms([r]) == [12.0]


# --- failover / failback gaps ---------------------------------------------

def test_failover_gap_request_sent_after_fault():
    # fault at 1000; robot a's next request at 1100 goes to the leader, answered at 1130
    recs = [rec("a", 900, 910, "cloud"), rec("a", 1100, 1130, "leader"), rec("a", 1300, 1320, "leader")]
    gaps = metrics.failover_gaps_ms(recs, cloud_crash(1000))
    assert gaps == {"a": pytest.approx(30)}  # from the send (later than the fault), not the fault


def test_failover_gap_request_in_flight_at_fault():
    # sent at 990, cloud killed at 1000, re-sent to the leader after a deadline: answered at 1045
    recs = [rec("a", 990, 1045, "leader")]
    assert metrics.failover_gaps_ms(recs, cloud_crash(1000)) == {"a": pytest.approx(45)}


def test_failover_gap_is_per_robot_and_report_keeps_largest():
    recs = [rec("a", 1010, 1020, "leader"), rec("b", 1150, 1200, "leader"),
            rec("c", 900, 950, "cloud")]  # c finished before the fault and sent nothing during it
    s = metrics.summarize(recs, [cloud_crash(1000, 2000)])
    assert s["faults"][0]["failover_by_robot"] == {"a": pytest.approx(10), "b": pytest.approx(50)}
    assert s["failover_gaps_ms"] == [pytest.approx(50)]


def test_failover_gap_counts_failures_until_the_leader_answers():
    # the first request after the fault failed outright; the gap runs to the leader answer
    recs = [rec("a", 1010, None, None, ok=False), rec("a", 1210, 1230, "leader")]
    assert metrics.failover_gaps_ms(recs, cloud_crash(1000)) == {"a": pytest.approx(220)}


def test_fault_with_no_leader_answer():
    recs = [rec("a", 1010, None, None, ok=False), rec("a", 1210, None, None, ok=False),
            rec("b", 1010, 1030, "leader")]
    s = metrics.summarize(recs, [cloud_crash(1000, 2000)])
    assert s["faults"][0]["failover_by_robot"]["a"] is None
    assert s["failover_gaps_ms"] == [None]  # one robot never failed over: no bound


def test_no_fault_no_gaps_and_cloud_answers_are_not_failovers():
    recs = [rec("a", 0, 10, "cloud"), rec("a", 1010, 1020, "cloud")]
    assert metrics.summarize(recs)["failover_gaps_ms"] == []
    # a fault the robot never noticed (the cloud answered everything) gives no gap
    assert metrics.failover_gaps_ms(recs, cloud_crash(1000)) == {}


def test_requests_after_restore_do_not_count():
    recs = [rec("a", 2100, 2150, "leader")]  # sent after the cloud came back at 2000
    assert metrics.failover_gaps_ms(recs, cloud_crash(1000, 2000)) == {}


def test_fault_limited_to_some_robots():
    recs = [rec("a", 1010, 1020, "leader"), rec("b", 1010, 1090, "leader")]
    gaps = metrics.failover_gaps_ms(recs, cloud_crash(1000, robots=["a"]))
    assert gaps == {"a": pytest.approx(10)}


def test_fault_taking_no_tier_has_no_gaps():
    f = {"kind": "delay", "target": "r0", "tier": None, "start_unix_ns": T0, "end_unix_ns": T0 + 5 * MS}
    s = metrics.summarize([rec("a", 1, 2, "cloud")], [f])
    assert s["failover_gaps_ms"] == [] and s["failback_gaps_ms"] == []


def test_failback_gap():
    recs = [rec("a", 1500, 1520, "leader"), rec("a", 2010, 2030, "leader"),
            rec("b", 2100, 2340, "cloud"), rec("a", 2200, 2210, "cloud")]
    f = cloud_crash(1000, 2000)
    assert metrics.failback_gap_ms(recs, f) == pytest.approx(210)  # a's answer at 2210 is first
    assert metrics.summarize(recs, [f])["failback_gaps_ms"] == [pytest.approx(210)]


def test_failback_never_or_not_applicable():
    recs = [rec("a", 2010, 2030, "leader")]
    assert metrics.failback_gap_ms(recs, cloud_crash(1000, 2000)) is None
    s = metrics.summarize(recs, [cloud_crash(1000, 2000), cloud_crash(3000)])
    assert s["failback_gaps_ms"] == [None]  # the second fault never ended: no failback entry
    assert len(s["failover_gaps_ms"]) == 2


def test_leader_fault_falls_back_to_nothing_by_default():
    f = {"kind": "crash", "target": "leader", "tier": "leader", "start_unix_ns": T0}
    recs = [rec("a", 10, 20, "cloud")]
    assert metrics.failover_gaps_ms(recs, f) == {}  # the cloud served: nothing noticed
    recs.append(rec("a", 30, None, None, ok=False))  # both down: noticed, and no fallback
    assert metrics.failover_gaps_ms(recs, f) == {"a": None}
    assert metrics.failover_gaps_ms(recs, {**f, "fallback": ["local"]}) == {"a": None}
    recs.append(rec("a", 230, 240, "local"))
    assert metrics.failover_gaps_ms(recs, {**f, "fallback": ["local"]}) == {"a": pytest.approx(210)}


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.sampled_from("abc"), st.integers(0, 3000), st.integers(1, 200),
                          st.sampled_from(["cloud", "leader", "local", None])), max_size=40),
       st.integers(0, 3000), st.integers(1, 2000))
def test_gaps_are_bounded_by_the_records(rows, start, length):
    recs = [rec(r, s, s + d, t, ok=t is not None) for r, s, d, t in rows]
    f = cloud_crash(start, start + length)
    gaps = metrics.failover_gaps_ms(recs, f)
    for robot, g in gaps.items():
        if g is not None:
            assert g >= 0
            # the gap ends at a leader answer received by that robot
            # ... and starts at the fault or at one of that robot's sending times
            mine = [r for r in recs if r["robot"] == robot]
            starts = {start} | {(r["sent_unix_ns"] - T0) / MS for r in mine}
            ends = [(r["received_unix_ns"] - T0) / MS for r in mine if r["tier"] == "leader"]
            assert any(abs(e - g - s0) < 1e-6 for e in ends for s0 in starts)
    fb = metrics.failback_gap_ms(recs, f)
    if fb is not None:
        assert fb >= 0
        assert any(r["tier"] == "cloud" and r["received_unix_ns"] == T0 + (start + length) * MS + int(round(fb * MS))
                   for r in recs)
    s = metrics.summarize(recs, [f])
    assert s["succeeded"] == sum(s["by_tier"][t] for t in ("cloud", "leader", "local"))
    assert s["requests"] == s["succeeded"] + s["by_tier"]["failed"]
