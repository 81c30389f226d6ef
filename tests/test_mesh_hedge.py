"""Hedged requests in the robot's routing (issue 24), with fake queriers: no middleware, <3 s.

A cloud that never answers (a silent link) is hedged to the leader and the leader's answer
wins; a ``busy`` cloud is failed over from, never hedged; hedges are rationed; a reply to
another frame is refused; and, for any mix of silent, slow, busy and fast tiers, every
request is answered at most once in the records.
"""

from __future__ import annotations

import threading
import time

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scmr_mesh import keys, wire
from scmr_mesh.mesh.frames import Frame
from scmr_mesh.mesh.robot import Robot, RobotOptions
from scmr_mesh.qos.metrics import hedge_counts


class _Sample:
    def __init__(self, key: str, kind) -> None:
        self.key_expr, self.kind = key, kind


class _Payload:
    def __init__(self, data: bytes) -> None:
        self._d = data

    def to_bytes(self) -> bytes:
        return self._d


class _Reply:
    def __init__(self, payload: bytes, key: str, *, error: bool = False) -> None:
        sample = type("Sample", (), {"payload": _Payload(payload), "key_expr": key})()
        self.ok, self.err = (None, sample) if error else (sample, None)
        self.replier_id = None


class FakeTier:
    """A querier of one node: ``behaviour`` is ``fast``, ``slow`` (answers after ``slow_s`` unless
    cancelled), ``silent`` (never answers; the query ends when cancelled or at ``hold_s``), ``busy``
    or ``loses_first`` (its first query is lost on the way, as ``silent``; later ones are ``fast``)."""

    def __init__(self, robot: str, tier: str, node: str, behaviour: str = "fast", *, slow_s: float = 0.05,
                 hold_s: float = 5.0, seq_offset: int = 0) -> None:
        self.robot, self.tier, self.node, self.behaviour = robot, tier, node, behaviour
        self.slow_s, self.hold_s, self.seq_offset = slow_s, hold_s, seq_offset
        self.matching_status = type("M", (), {"matching": True})()
        self.calls = 0

    def _wait_cancel(self, token, s: float) -> bool:
        """Hold the query up to ``s`` (a link that carries nothing); True if the robot cancelled it."""
        end = time.monotonic() + s
        while time.monotonic() < end:
            if token is not None and token.is_cancelled:
                return True
            time.sleep(0.001)
        return False

    def get(self, payload, *, encoding=None, cancellation_token=None):
        self.calls += 1
        key = keys.drivable_request(self.tier, self.node, self.robot)
        req = wire.decode(payload, kind="request")
        if self.behaviour == "silent" or (self.behaviour == "loses_first" and self.calls == 1):
            self._wait_cancel(cancellation_token, self.hold_s)
            return iter([])
        if self.behaviour == "busy":
            err = wire.make_error("busy", "server too busy", served_by=self.node, tier=self.tier, request=req)
            return iter([_Reply(wire.encode(err), key, error=True)])
        if self.behaviour == "slow" and self._wait_cancel(cancellation_token, self.slow_s):
            return iter([])
        req = dict(req, seq=req["seq"] + self.seq_offset)
        rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n..", shape=(225, 300), threshold=1,
                              timings_ms={}, served_by=self.node, tier=self.tier, server_ms=1.0)
        return iter([_Reply(wire.encode(rep), key)])


def _robot(tmp_path, cloud: str, leader: str, **opts):
    r = Robot("r1", tmp_path, options=RobotOptions(local_fallback=False, **opts))
    for role, node in (("cloud", "c1"), ("leader", "L1")):
        r.view.on_liveliness(_Sample(keys.alive(role, node), zenoh.SampleKind.PUT))
    fakes = {"cloud": FakeTier("r1", "cloud", "c1", cloud), "leader": FakeTier("r1", "leader", "L1", leader)}
    r._queriers[keys.drivable_request("cloud", "c1", "r1")] = fakes["cloud"]
    r._queriers[keys.drivable_request("leader", "L1", "r1")] = fakes["leader"]
    return r, fakes


FRAME = Frame("f.png", b"\x89PNG....", "png")


def test_a_silent_cloud_is_hedged_to_the_leader_and_the_leader_wins(tmp_path):
    robot, fakes = _robot(tmp_path, "silent", "fast", deadline_ms=5000, hedge_ms=20)
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"] and rec["tier"] == "leader" and rec["served_by"] == "L1"
        assert rec["hedged"] and rec["hedge_won"]
        cloud, leader = rec["attempts"]
        assert (cloud["tier"], cloud["outcome"]) == ("cloud", "superseded") and "hedge" not in cloud
        assert (leader["tier"], leader["outcome"], leader["hedge"]) == ("leader", "ok", True)
        assert rec["bytes_up"] == 2 * len(robot._request_payload(0, FRAME, rec["sent_unix_ns"]))
        assert fakes["leader"].calls == 1
        # the cancelled cloud query freed the cloud's sender thread: the next frame's cloud query runs
        fakes["cloud"].behaviour = "fast"
        rec2 = robot.request(1, FRAME)
        assert rec2["tier"] == "cloud" and not rec2["hedged"]
    finally:
        robot.close()


def test_a_hedge_lost_on_the_way_is_sent_once_more_and_that_copy_answers(tmp_path):
    # issue 24 under 2 CPU hogs: the hedge query to a live leader was never answered (lost on the way)
    # and the frame waited for the 1 s deadline; now a hedge as silent as the first copy is sent again
    robot, fakes = _robot(tmp_path, "silent", "loses_first", deadline_ms=5000, hedge_ms=20)
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"] and rec["tier"] == "leader" and rec["hedged"] and rec["hedge_won"], rec
        assert [(a["tier"], a["outcome"], bool(a.get("hedge")), bool(a.get("resend"))) for a in rec["attempts"]] == [
            ("cloud", "superseded", False, False), ("leader", "superseded", True, False),
            ("leader", "ok", True, True)]
        assert fakes["leader"].calls == 2
        assert rec["bytes_up"] == 3 * len(robot._request_payload(0, FRAME, rec["sent_unix_ns"]))
        h = hedge_counts([rec])
        assert h["resent"] == 1 and h["duplicates_by_tier"] == {"cloud": 1}  # the leader served it once
    finally:
        robot.close()


def test_a_silent_cloud_with_no_other_tier_alive_is_sent_again_once(tmp_path):
    # cloud-link-drop under 2 CPU hogs: a query to the leader (the only tier alive) was lost and the
    # frame waited for the deadline (1 s); now it is sent once more after the hedge delay
    robot, fakes = _robot(tmp_path, "loses_first", "fast", deadline_ms=5000, hedge_ms=20)
    robot.view.on_liveliness(_Sample(keys.alive("leader", "L1"), zenoh.SampleKind.DELETE))
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"] and rec["tier"] == "cloud" and rec["hedged"] and rec["hedge_won"], rec
        assert [(a["outcome"], a.get("resend", False)) for a in rec["attempts"]] == [
            ("superseded", False), ("ok", True)]
        assert fakes["cloud"].calls == 2 and fakes["leader"].calls == 0
    finally:
        robot.close()


def test_a_node_leaving_while_a_copy_waits_sends_that_copy_once_more(tmp_path):
    # cloud-link-drop, quiet box: a hedge to the leader and its timed re-send were both sent just
    # before the cloud's link closed (zenoh re-routes then) and neither was ever answered (1 s, then
    # computed alone); the leader answered every other robot.  Now the copy goes once more when a
    # node is seen leaving.
    robot, fakes = _robot(tmp_path, "silent", "silent", deadline_ms=5000, hedge_ms=20)
    leader = fakes["leader"]
    real_get = leader.get

    def get(payload, **kw):  # the copies before the departure are lost; the one after answers
        if leader.calls >= 2:
            leader.behaviour = "fast"
        elif leader.calls == 1:
            robot.view.on_liveliness(_Sample(keys.alive("cloud", "c1"), zenoh.SampleKind.DELETE))
        return real_get(payload, **kw)

    leader.get = get
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"] and rec["tier"] == "leader", rec
        assert [(a["tier"], a["outcome"], a.get("resend", False)) for a in rec["attempts"]] == [
            ("cloud", "superseded", False), ("leader", "superseded", False), ("leader", "superseded", True),
            ("leader", "ok", True)], rec["attempts"]
    finally:
        robot.close()


def test_a_silent_hedge_is_sent_again_only_once(tmp_path):
    robot, fakes = _robot(tmp_path, "silent", "silent", deadline_ms=400, hedge_ms=20)
    for f in fakes.values():
        f.hold_s = 2.0
    try:
        rec = robot.request(0, FRAME)
        assert not rec["ok"] and fakes["leader"].calls == 2
        # the hedge given up for its re-send is a timeout too: nothing answered
        assert [a["outcome"] for a in rec["attempts"]] == ["timeout", "timeout", "timeout"]
    finally:
        robot.close()


def test_a_fast_cloud_is_never_hedged_and_teaches_the_delay(tmp_path):
    robot, fakes = _robot(tmp_path, "fast", "fast", deadline_ms=5000)
    try:
        recs = [robot.request(i, FRAME) for i in range(8)]
        assert all(r["tier"] == "cloud" and not r["hedged"] for r in recs)
        assert fakes["leader"].calls == 0
        assert len(robot._answer_times["cloud"]) == 7  # the first answer (one-off costs) is not learnt
        # learnt: p95 of these answers + margin, at least the floor (fast answers: the floor on a quiet
        # box; under CPU hogs their times, and so the delay, can be a little higher: that is the rule
        # working, so the expectation comes from the recorded times, not from the wall clock)
        from scmr_mesh.qos.hedge import DEFAULT_RULE, _quantile

        times = list(robot._answer_times["cloud"].values())
        learnt = max(DEFAULT_RULE.floor_ms, _quantile(times, DEFAULT_RULE.quantile) + DEFAULT_RULE.margin_ms)
        assert robot.hedge_delay_ms("cloud") == learnt
        assert robot.hedge_delay_ms("leader") == 150.0  # no answers yet: the cold delay
    finally:
        robot.close()


def test_a_busy_answer_fails_over_without_a_hedge(tmp_path):
    robot, fakes = _robot(tmp_path, "busy", "fast", deadline_ms=5000, hedge_ms=1000)
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"] and rec["tier"] == "leader" and not rec["hedged"] and not rec["hedge_won"]
        assert [a["outcome"] for a in rec["attempts"]] == ["error:busy", "ok"]
        assert all("hedge" not in a for a in rec["attempts"])
    finally:
        robot.close()


def test_no_hedge_to_a_saturated_leader(tmp_path):
    robot, fakes = _robot(tmp_path, "slow", "fast", deadline_ms=5000, hedge_ms=5)
    fakes["cloud"].slow_s = 0.1
    robot.view.mark_busy("L1")  # the leader said busy before: its admission stays in charge
    try:
        rec = robot.request(0, FRAME)
        assert rec["tier"] == "cloud" and fakes["leader"].calls == 0
        # no other tier to hedge to: the silent cloud got its copy once more (a node serves it once);
        # the two run side by side and the first answer is used
        assert sorted((a["tier"], a["outcome"], a.get("resend", False)) for a in rec["attempts"]) in (
            [("cloud", "ok", False), ("cloud", "superseded", True)],
            [("cloud", "ok", True), ("cloud", "superseded", False)])
    finally:
        robot.close()


def test_hedges_are_rationed_no_storm_when_the_cloud_is_slow(tmp_path):
    robot, fakes = _robot(tmp_path, "slow", "slow", deadline_ms=5000, hedge_ms=1)
    fakes["cloud"].slow_s = fakes["leader"].slow_s = 0.03
    try:
        n = 20
        recs = [robot.request(i, FRAME) for i in range(n)]
        hedged = sum(r["hedged"] for r in recs)
        budget = robot._hedge_budget
        assert 1 <= hedged <= budget.ratio * n + budget.burst
        assert all(r["ok"] for r in recs)
    finally:
        robot.close()


def test_a_reply_to_another_frame_is_refused(tmp_path):
    robot, fakes = _robot(tmp_path, "fast", "fast", deadline_ms=2000, hedge=False)
    fakes["cloud"].seq_offset = -1  # a late answer to the frame before
    try:
        rec = robot.request(5, FRAME)
        assert rec["tier"] == "leader"
        assert rec["attempts"][0]["outcome"] == "mismatched" and "frame 4" in rec["attempts"][0]["message"]
        assert rec["mismatched"] == 1 and robot.mismatched == {"cloud/c1": 1}
    finally:
        robot.close()


def test_hedge_off_waits_for_the_silent_cloud(tmp_path):
    robot, fakes = _robot(tmp_path, "silent", "fast", deadline_ms=300, hedge=False)
    fakes["cloud"].hold_s = 0.05  # the query ends without a reply (as at a lease expiry)
    try:
        rec = robot.request(0, FRAME)
        assert rec["tier"] == "leader" and not rec["hedged"]
        assert [a["outcome"] for a in rec["attempts"]] == ["no_reply", "ok"]
    finally:
        robot.close()


BEHAVIOURS = st.sampled_from(["fast", "slow", "silent", "busy"])


@given(st.lists(st.tuples(BEHAVIOURS, BEHAVIOURS), min_size=1, max_size=4))
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_every_request_is_answered_at_most_once(tmp_path, plan):
    robot, fakes = _robot(tmp_path, "fast", "fast", deadline_ms=400, hedge_ms=2)
    for f in fakes.values():
        f.slow_s, f.hold_s = 0.01, 0.03
    try:
        recs = []
        for i, (c, l) in enumerate(plan):
            fakes["cloud"].behaviour, fakes["leader"].behaviour = c, l
            recs.append(robot.request(i, FRAME))
        for r in recs:
            oks = [a for a in r["attempts"] if a["outcome"] == "ok"]
            assert len(oks) == (1 if r["ok"] else 0), r
            if r["ok"]:
                assert (oks[0]["tier"], oks[0]["node"]) == (r["tier"], r["served_by"])
            hedges = [a for a in r["attempts"] if a.get("hedge")]
            # at most one hedge and two re-sends (one timed, one when a node left) per request
            assert bool(hedges) == r["hedged"] and len(hedges) <= 3
            assert sum(not a.get("resend") for a in hedges) <= 1 and sum(bool(a.get("resend")) for a in hedges) <= 2
            assert not r["hedge_won"] or (r["hedged"] and oks[0].get("hedge"))
            assert all(a["outcome"] != "pending" for a in r["attempts"])
        h = hedge_counts(recs)
        assert h["hedged"] == sum(r["hedged"] for r in recs) and h["hedge_won"] <= h["hedged"]
        assert [r["seq"] for r in recs] == list(range(len(plan)))  # one record per request
    finally:
        robot.close()


def test_a_service_remembers_recent_requests_boundedly():
    from scmr_mesh.mesh.server import RecentRequests

    r = RecentRequests(size=3)
    assert r.add(("r1", 1, 10)) and not r.add(("r1", 1, 10)) and r.duplicates == 1
    assert r.admit(("r1", 1, 10), "q")[0] == "joined" and r.complete(("r1", 1, 10), None) == ["q"]
    assert r.admit(("r1", 1, 10), "q")[0] == "duplicate"  # the first copy failed: its answer is not kept
    assert r.add(("r1", 1, 11))  # the same seq from a restarted robot (another sending time) is new
    assert r.forget(("r1", 1, 11)) == []  # refused busy: a later copy may be taken in
    assert r.add(("r1", 1, 11))
    for seq in range(2, 6):
        assert r.add(("r1", seq, 10))
    # beyond the size the oldest answered request is forgotten, but none still being served
    # (those are bounded by the node's in-flight limit) ...
    assert ("r1", 1, 10) not in r._seen and len(r._seen) == 5 and not r.add(("r1", 1, 11))
    for ident in list(r._seen):
        r.complete(ident, None)
    assert r.add(("r1", 9, 10)) and len(r._seen) == 3  # ... once answered, they are
    assert r.add(("r1", 1, 11))  # a copy of a forgotten one is new


def test_a_service_keeps_answers_for_later_copies_within_its_byte_budget():
    from scmr_mesh.mesh.server import RecentRequests

    r = RecentRequests(size=10, max_reply_bytes=10)
    for seq in range(3):
        assert r.admit(("r1", seq, 1))[0] == "new"
        r.complete(("r1", seq, 1), b"x" * 4)
    # 12 bytes > 10: the oldest answer is no longer kept; its later copy is refused as before
    assert r.admit(("r1", 0, 1)) == ("duplicate", None)
    assert r.admit(("r1", 2, 1)) == ("cached", b"xxxx") and r._kept_bytes == 8
    assert r.forget(("r1", 2, 1)) == [] and r._kept_bytes == 4


class LieAndHold(FakeTier):
    """A lying cloud: answers at once with a reply to another frame, then keeps its query open
    (never finalises it) until the robot cancels it."""

    def get(self, payload, *, encoding=None, cancellation_token=None):
        self.calls += 1
        key = keys.drivable_request(self.tier, self.node, self.robot)
        req = wire.decode(payload, kind="request")
        stale = wire.make_request(req["robot"], req["seq"], b"last run's frame")
        rep = wire.make_reply(stale, mask_png=b"\x89PNG\r\n\x1a\n..", shape=(225, 300), threshold=1,
                              timings_ms={}, served_by=self.node, tier=self.tier, server_ms=1.0)

        def gen():
            yield _Reply(wire.encode(rep), key)
            self.judged.set()  # the robot asked for the next reply: the lie is judged
            self._wait_cancel(cancellation_token, self.hold_s)

        return gen()


class AnswersAfter(FakeTier):
    """A fast node that answers only once ``event`` is set (orders a race deterministically)."""

    def __init__(self, *a, event: threading.Event, **kw) -> None:
        super().__init__(*a, **kw)
        self.event = event

    def get(self, payload, **kw):
        assert self.event.wait(30), "the other node's reply was never judged"
        return super().get(payload, **kw)


def test_a_mismatched_reply_of_a_hedged_loser_is_in_the_record(tmp_path):
    """A lying primary that holds its query open after a replayed reply, beaten by the hedge: its
    mismatched reply is in the record and the robot's stats, not only in Robot.mismatched (review
    of issue 25 item 8: the loser's attempt was marked superseded without what its query saw)."""
    robot, fakes = _robot(tmp_path, "fast", "fast", deadline_ms=3000, hedge_ms=50)
    liar = LieAndHold("r1", "cloud", "c1", hold_s=3.0)
    liar.judged = threading.Event()
    robot._queriers[keys.drivable_request("cloud", "c1", "r1")] = liar
    # the hedge (the leader) answers only after the lie was judged, however the threads are scheduled
    robot._queriers[keys.drivable_request("leader", "L1", "r1")] = AnswersAfter("r1", "leader", "L1",
                                                                               event=liar.judged)
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"] and rec["tier"] == "leader" and rec["hedged"]
        assert robot.mismatched == {"cloud/c1": 1}
        assert rec["mismatched"] == robot.stats["mismatched"] == 1, rec["attempts"]
    finally:
        robot.close()


class ForgedServedBy(FakeTier):
    """A lying cloud c1: answers this very frame (robot, seq, digest right) but names another
    server in served_by, or sends bytes that are no reply at all."""

    garbage = False

    def get(self, payload, *, encoding=None, cancellation_token=None):
        self.calls += 1
        key = keys.drivable_request(self.tier, self.node, self.robot)
        req = wire.decode(payload, kind="request")
        rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n..", shape=(225, 300), threshold=1,
                              timings_ms={}, served_by="c9", tier=self.tier, server_ms=1.0)
        return iter([_Reply(b"\xc1not msgpack" if self.garbage else wire.encode(rep), key)])


@pytest.mark.parametrize("garbage", [False, True])
def test_a_lying_servers_refused_replies_are_counted_somewhere(tmp_path, garbage):
    """A reply refused as bad_reply (another server's name in served_by, bytes that are no reply)
    is never used and counted like a mismatched one: record, Robot.mismatched, the report (before:
    counted nowhere, the run looked like an ordinary failover to the leader)."""
    from scmr_mesh.qos import metrics

    robot, fakes = _robot(tmp_path, "fast", "fast", deadline_ms=2000, hedge=False)
    liar = ForgedServedBy("r1", "cloud", "c1")
    liar.garbage = garbage
    robot._queriers[keys.drivable_request("cloud", "c1", "r1")] = liar
    try:
        recs = [robot.request(i, FRAME) for i in range(3)]
    finally:
        robot.close()
    assert [r["tier"] for r in recs] == ["leader"] * 3
    assert [r["attempts"][0]["outcome"] for r in recs] == ["bad_reply"] * 3
    summary = metrics.summarize(recs, robots=1)
    assert robot.mismatched == {"cloud/c1": 3} and summary["mismatched"] == 3
    assert summary["mismatched_by_node"] == {"cloud/c1": 3}


def test_zenohs_timeout_reply_is_a_timeout_not_a_refused_message(tmp_path):
    """At the querier's timeout zenoh replies the 7 bytes "Timeout": an outcome, not a malformed
    scmr error message (it was counted as a refused message and logged as one)."""
    robot, _ = _robot(tmp_path, "fast", "fast")
    try:
        before = wire.rejected().get("error", {})
        att = {"tier": "leader", "node": "L1", "outcome": "pending"}
        assert robot._judge(att, _Reply(b"Timeout", "k", error=True), {}) is None
        assert att["outcome"] == "timeout" and wire.rejected().get("error", {}) == before
    finally:
        robot.close()
