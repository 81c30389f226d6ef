"""Receipts (issue 24): a node says at once that it has a request, so a robot knows a copy is lost
within a few ms of its send, long before the answer is late.  Fake queriers and a Service without
zenoh or worker processes: no middleware, < 2 s."""

from __future__ import annotations


import pytest
import zenoh
from test_mesh_copies import FakePool, FakeQuery, _service
from test_mesh_hedge import FRAME, FakeTier, _Reply, _robot, _Sample

from scmr_mesh import keys, wire
from scmr_mesh.qos.hedge import RECEIPT_RULE, receipt_delay_ms

ANSWER_HEDGE_S = 30.0  # the answer's hedge delay in these tests: far beyond what any test waits


class Receipting(FakeTier):
    """A node of this version: a receipt at once, then the answer after ``slow_s`` (or never:
    ``behaviour="silent"``, a node whose link went silent; ``receipt=False``, a node that got
    the request but never says so, as one lost on the way)."""

    def __init__(self, *a, receipt: bool = True, **kw) -> None:
        super().__init__(*a, **kw)
        self.receipt = receipt
        self.asked_receipt: list[bool] = []

    def get(self, payload, *, encoding=None, cancellation_token=None):
        self.calls += 1
        req = wire.decode(payload, kind="request")
        self.asked_receipt.append(bool(req.get("receipt")))
        key = keys.drivable_request(self.tier, self.node, self.robot)
        if self.behaviour == "silent":
            self._wait_cancel(cancellation_token, self.hold_s)
            return
        if self.receipt and req.get("receipt"):
            yield _Reply(wire.encode(wire.make_receipt(req, served_by=self.node, tier=self.tier)), key)
        if self._wait_cancel(cancellation_token, self.slow_s):
            return
        rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n..", shape=(225, 300), threshold=1,
                              timings_ms={}, served_by=self.node, tier=self.tier, server_ms=1.0)
        yield _Reply(wire.encode(rep), key)


def _receipting_robot(tmp_path, **cloud_kw):
    robot, fakes = _robot(tmp_path, "fast", "fast", deadline_ms=60_000)
    cloud = Receipting("r1", "cloud", "c1", "fast", slow_s=0.0, **cloud_kw)
    leader = Receipting("r1", "leader", "L1", "fast", slow_s=0.0)
    robot._queriers[keys.drivable_request("cloud", "c1", "r1")] = cloud
    robot._queriers[keys.drivable_request("leader", "L1", "r1")] = leader
    robot.hedge_delay_ms = lambda tier, elapsed_ms=0.0: ANSWER_HEDGE_S * 1e3  # the answer is never late here
    return robot, cloud, leader


def _learn_receipts(robot, n: int = RECEIPT_RULE.min_samples) -> None:
    for seq in range(n):
        rec = robot.request(seq, FRAME)
        assert rec["ok"] and rec["tier"] == "cloud" and not rec["hedged"], rec
        assert rec["attempts"][0]["receipt_ms"] >= 0, rec["attempts"]
    assert len(robot._receipt_times["cloud", "c1"]) == n


def test_a_copy_with_no_receipt_is_hedged_at_the_receipt_delay_not_the_answers(tmp_path):
    robot, cloud, leader = _receipting_robot(tmp_path)
    try:
        _learn_receipts(robot)
        assert RECEIPT_RULE.floor_ms <= robot.receipt_delay_ms("cloud", "c1") < ANSWER_HEDGE_S * 1e3
        cloud.behaviour = "silent"  # the cloud's link goes silent: no receipt, no answer
        rec = robot.request(10, FRAME)
        # hedged on the missing receipt (15 ms), not after the answer's 30 s delay
        assert rec["ok"] and rec["tier"] == "leader" and rec["hedged"] and rec["hedge_won"], rec
        assert rec["tor_ms"] < ANSWER_HEDGE_S * 1e3 / 2, rec["tor_ms"]
        assert all(leader.asked_receipt) and all(cloud.asked_receipt)
    finally:
        robot.close()


def test_a_copy_whose_node_sent_its_receipt_waits_for_the_answer(tmp_path):
    robot, cloud, leader = _receipting_robot(tmp_path)
    try:
        _learn_receipts(robot)
        cloud.slow_s = 0.3  # a long frame: the receipt comes at once, the answer 300 ms later
        rec = robot.request(10, FRAME)
        assert rec["ok"] and rec["tier"] == "cloud" and not rec["hedged"], rec["attempts"]
        assert leader.calls == 0
        receipt = rec["attempts"][0]["receipt_bytes"]
        assert 0 < receipt < rec["bytes_down"]  # the energy model pays for the receipt too
    finally:
        robot.close()


def test_a_node_that_never_sends_receipts_is_judged_by_its_answers_only(tmp_path):
    # a node of an older version (or one that lost every receipt): no receipt delay is learnt
    robot, cloud, leader = _receipting_robot(tmp_path, receipt=False)
    try:
        for seq in range(RECEIPT_RULE.min_samples + 1):
            assert robot.request(seq, FRAME)["tier"] == "cloud"
        assert robot.receipt_delay_ms("cloud", "c1") is None
        assert "receipt_ms" not in robot.request(9, FRAME)["attempts"][0]
        cloud.slow_s = 0.3
        rec = robot.request(10, FRAME)
        assert rec["tier"] == "cloud" and not rec["hedged"], rec["attempts"]
    finally:
        robot.close()


@pytest.mark.parametrize("opts", [{"hedge": False}, {"hedge_ms": 40.0}, {"redundant": True}])
def test_receipts_are_asked_for_only_when_learnt_hedging_uses_them(tmp_path, opts):
    # --hedge-ms off / MS: nothing judges receipts; --redundant sends to both tiers at once
    robot, fakes = _robot(tmp_path, "fast", "fast", **opts)
    try:
        req = wire.decode(robot._request_payload(0, FRAME, 1), kind="request")
        assert "receipt" not in req and robot.receipt_delay_ms("cloud", "c1") is None
    finally:
        robot.close()
    robot, fakes = _robot(tmp_path / "auto", "fast", "fast")
    try:
        assert wire.decode(robot._request_payload(0, FRAME, 1), kind="request")["receipt"] is True
    finally:
        robot.close()


def test_a_receipt_is_never_taken_as_the_answer(tmp_path):
    """A node that sends its receipt and then nothing (it died in service): the request is not
    'ok' on the receipt; it is hedged after the answer's delay (here: the deadline's failover)."""
    robot, cloud, leader = _receipting_robot(tmp_path)
    robot.hedge_delay_ms = lambda tier, elapsed_ms=0.0: 50.0
    robot.view.on_liveliness(_Sample(keys.alive("leader", "L1"), zenoh.SampleKind.DELETE))
    try:
        _learn_receipts(robot)
        cloud.slow_s, cloud.hold_s = 60.0, 60.0
        robot.options.deadline_ms = 400
        rec = robot.request(10, FRAME)
        assert not rec["ok"], rec
        assert all(a["outcome"] != "ok" for a in rec["attempts"]), rec["attempts"]
        assert all("receipt_ms" in a for a in rec["attempts"] if a["node"] == "c1"), rec["attempts"]
    finally:
        robot.close()


# -------------------------------------------------------------- service side
def _kinds(q: FakeQuery, n: int = 0, timeout: float = 5.0) -> list[str]:
    """The kinds of what ``q`` got, once it got at least ``n`` messages (they go from sender threads)."""
    from scmr_mesh.mesh.testing import wait_for

    wait_for(lambda: len(q.answers) >= n, timeout=timeout, what=f"{n} messages on the query")
    return [wire.decode(p, kind=("reply", "receipt", "error"))["kind"] for _k, p in q.answers]


@pytest.mark.parametrize("asked", [True, False])
def test_a_service_sends_the_receipt_first_only_when_asked(asked):
    svc = _service(FakePool())
    try:
        req = wire.make_request("r1", 5, b"\x89PNG frame", encoding="png", receipt=asked)
        q = FakeQuery(keys.drivable_request("cloud", "c1", "r1"), wire.encode(req))
        svc._on_query(q)
        if asked:  # at once, before any work
            assert _kinds(q, 1) == ["receipt"]
            rc = wire.decode(q.answers[0][1], kind="receipt")
            assert wire.reply_mismatch(wire.asked_of(req), rc) is None and rc["served_by"] == "c1"
        svc.pool.futs[0].set_result({"mask_png": b"\x89PNG\r\n\x1a\n..", "shape": [225, 300], "threshold": 1,
                                     "worker_ms": 5.0})
        assert q.dropped.wait(5.0)
        assert _kinds(q, 2 if asked else 1) == (["receipt", "reply"] if asked else ["reply"])
    finally:
        svc.replier.close()


def test_a_copy_that_joins_gets_its_own_receipt_and_a_refused_request_none_after_a_malformed_one():
    svc = _service(FakePool())
    try:
        req = wire.make_request("r1", 6, b"\x89PNG frame", encoding="png", receipt=True)
        first = FakeQuery(keys.drivable_request("cloud", "c1", "r1"), wire.encode(req))
        copy = FakeQuery(keys.drivable_request("cloud", "c1", "r1"), wire.encode(req))
        svc._on_query(first)
        svc._on_query(copy)
        assert _kinds(first, 1) == ["receipt"] and _kinds(copy, 1) == ["receipt"]  # the copy waits for the first's run
        bad = FakeQuery(keys.drivable_request("cloud", "c1", "r1"), b"\x81\xa1v\x01")  # not a request
        svc._on_query(bad)
        assert bad.dropped.wait(5.0) and _kinds(bad) == ["error"]  # no receipt for what it could not read
    finally:
        svc.replier.close()


def test_the_receipt_delay_rule():
    assert receipt_delay_ms([1.0] * (RECEIPT_RULE.min_samples - 1), deadline_ms=1000) is None
    assert receipt_delay_ms([1.0] * 20, deadline_ms=1000) == RECEIPT_RULE.floor_ms
    xs = [float(i) for i in range(1, 21)]  # p95 of 1..20 = 19.05
    assert receipt_delay_ms(xs, deadline_ms=1000) == pytest.approx(19.05 + RECEIPT_RULE.margin_ms)
    assert receipt_delay_ms(xs, deadline_ms=60, elapsed_ms=0) is None  # too little of the deadline left


def test_a_receipt_from_another_node_does_not_count(tmp_path):
    """A receipt is trusted as a reply is: one that names another node is refused and counted."""
    robot, cloud, leader = _receipting_robot(tmp_path)
    try:
        key = keys.drivable_request("cloud", "c1", "r1")
        req = wire.decode(robot._request_payload(3, FRAME, 1), kind="request")
        forged = _Reply(wire.encode(wire.make_receipt(req, served_by="L1", tier="cloud")), key)
        att = {"tier": "cloud", "node": "c1", "outcome": "pending"}
        assert robot._judge(att, forged, wire.asked_of(req), t_send=0.0) is None
        assert att["outcome"] == "bad_reply" and "receipt_ms" not in att
    finally:
        robot.close()


def test_receipt_schema_round_trip():
    req = wire.make_request("r1", 1, b"x", receipt=True)
    assert wire.decode(wire.encode(req), kind="request")["receipt"] is True
    rc = wire.make_receipt(req, served_by="c1", tier="leader")
    assert wire.decode(wire.encode(rc), kind="receipt") == rc
    with pytest.raises(wire.WireProblem):
        wire.decode(wire.encode({**rc, "mask_png": b"x"}), kind="receipt")  # a receipt carries no answer




def test_a_silent_hedge_is_sent_again_without_a_budget_token(tmp_path):
    """cloud-link-drop at load 6-14: a fault-free hedge and its re-send 1.4 s before the cut spent both
    saved tokens, so the frame sent 68 ms after the cut was not hedged at all (98 ms, the run's
    largest failover).  A re-send goes to the node that already has (or lost) the request: no
    pipeline run, no token; the hedge itself still takes one."""
    from test_mesh_hedge import _robot as hedge_robot

    robot, fakes = hedge_robot(tmp_path, "silent", "loses_first", deadline_ms=5000, hedge_ms=20)
    robot._hedge_budget.tokens = 1.0  # one hedge left, as after a fault-free hedge
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"] and rec["tier"] == "leader" and rec["hedged"], rec["attempts"]
        assert [bool(a.get("resend")) for a in rec["attempts"]] == [False, False, True], rec["attempts"]
        assert robot._hedge_budget.tokens < 1.0  # the hedge took the token; the re-send none
    finally:
        robot.close()


def test_the_scenario_bench_counts_hedges_of_fault_free_requests_only():
    from scmr_mesh.bench.scenario import _hedged, fault_free_rows

    att = [{"tier": "cloud", "outcome": "superseded"}, {"tier": "leader", "outcome": "ok", "hedge": True}]
    rep = {"faults": [{"started_at_s": 4.0, "ended_at_s": 10.0}, {"started_at_s": 14.0, "ended_at_s": None}],
           "request_log": [{"sent_s": t, "attempts": att if t in (3.5, 12.0) else att[:1]}
                           for t in (0.5, 3.5, 6.0, 10.5, 12.0, 13.5, 20.0)]}
    rows = fault_free_rows(rep)
    assert [q["sent_s"] for q in rows] == [0.5, 12.0]  # 1 s around each fault; the last never ends
    assert [_hedged(q) for q in rows] == [False, True]


# -------------------------------------------- the hostile review's reproductions (all failed on b8c218c)
def test_a_node_without_receipts_stops_being_expected_to_send_them(tmp_path):
    """Windows were per tier and pooled: once the cloud had sent receipts, a leader that sends none
    (an outside server, or one whose receipts are lost) was 'silent' after every send, each frame
    copied again and the budget drained.  Now receipts are learnt per node, and a node whose last
    UNRECEIPTED_MAX answers came without one is judged by its answers only."""
    robot, cloud, leader = _receipting_robot(tmp_path)
    leader.receipt, leader.slow_s = False, 0.05  # answers in 50 ms, never a receipt
    try:
        _learn_receipts(robot)
        robot.view.on_liveliness(_Sample(keys.alive("cloud", "c1"), zenoh.SampleKind.DELETE))  # cloud gone
        recs = [robot.request(20 + i, FRAME) for i in range(5)]
        assert all(r["ok"] and r["tier"] == "leader" for r in recs)
        late = recs[robot.UNRECEIPTED_MAX:]
        assert all(len(r["attempts"]) == 1 for r in late), [r["attempts"] for r in recs]
        assert leader.calls <= len(recs) + robot.UNRECEIPTED_MAX
    finally:
        robot.close()


def test_a_hedge_whose_node_sent_its_receipt_waits_for_its_own_tiers_answer_delay(tmp_path):
    """answer_due used the primary tier's answer delay for the hedge's node: a leader (slower than the
    cloud) that had receipted the hedge got the whole frame again after the cloud's 50 ms."""
    robot, cloud, leader = _receipting_robot(tmp_path)
    try:
        _learn_receipts(robot)
        robot.hedge_delay_ms = lambda tier, elapsed_ms=0.0: {"cloud": 50.0, "leader": 1000.0}.get(tier)
        cloud.behaviour = "silent"
        leader.slow_s = 0.25  # receipt at once, answer at 250 ms: inside the leader's own 1 s delay
        rec = robot.request(10, FRAME)
        assert rec["ok"] and rec["tier"] == "leader"
        assert leader.calls == 1, rec["attempts"]
    finally:
        robot.close()


def test_a_receipt_read_where_a_reply_may_come_has_the_receipt_size_cap():
    req = wire.make_request("r1", 1, b"x", receipt=True)
    big = wire.encode(wire.make_receipt(req, served_by="c1" * 5000, tier="cloud"))
    assert len(big) > wire.MAX_BYTES["receipt"]
    with pytest.raises(wire.WireProblem) as exc:
        wire.decode(big, kind=("reply", "receipt"))
    assert exc.value.code == "oversized"


class BusyAfterReceipt(Receipting):
    """A node that takes the request in (receipt), is then made to refuse it (displaced by a request of
    higher priority: ``busy``) and finalises the query late: ``hold_s`` or the robot's cancel."""

    def get(self, payload, *, encoding=None, cancellation_token=None):
        self.calls += 1
        self.token = cancellation_token
        req = wire.decode(payload, kind="request")
        key = keys.drivable_request(self.tier, self.node, self.robot)
        yield _Reply(wire.encode(wire.make_receipt(req, served_by=self.node, tier=self.tier)), key)
        err = wire.make_error("busy", f"server too busy, try later: request r1/{req['seq']} with priority 0 "
                              "displaced", served_by=self.node, tier=self.tier, request=req)
        yield _Reply(wire.encode(err), key, error=True)
        self._wait_cancel(cancellation_token, self.hold_s)  # the query ends late (or when cancelled)


def test_a_busy_answer_after_the_receipt_ends_the_copy_at_once(tmp_path):
    """Seen in CI on a loaded box: the cloud sent r2/10 its receipt, then displaced it (busy), and its
    query ended a second later; the robot waited for that end (its 1 s deadline), recorded a timeout
    and only then went to the leader.  The node's error is its answer: the copy ends there."""
    robot, cloud, leader = _receipting_robot(tmp_path)
    try:
        _learn_receipts(robot)
        busy = BusyAfterReceipt("r1", "cloud", "c1", "fast", hold_s=20.0)
        robot._queriers[keys.drivable_request("cloud", "c1", "r1")] = busy
        rec = robot.request(10, FRAME)
        assert rec["ok"] and rec["tier"] == "leader", rec
        first = rec["attempts"][0]
        assert (first["tier"], first["outcome"]) == ("cloud", "error:busy"), rec["attempts"]
        assert "displaced" in first["message"] and "_final" not in first
        assert rec["tor_ms"] < 10_000, rec["tor_ms"]  # not the node's 20 s hold (nor the 30 s answer delay)
        assert busy.token.is_cancelled, "the robot did not cancel the copy its node had answered"
    finally:
        robot.close()


def test_a_lost_copy_is_hedged_even_to_a_saturated_leader(tmp_path):
    """At the cloud's loss every robot hedges to the leader, so its load says saturated to the last of
    them; a copy with no receipt (its node may be gone) still goes there rather than once more to
    the silent cloud, which waited out the lease (136 and 291 ms in 2 of 20 cloud-link-drop runs).
    A copy whose node has it (receipt) is not hedged to a saturated node: test_mesh_hedge's
    test_no_hedge_to_a_saturated_leader."""
    robot, cloud, leader = _receipting_robot(tmp_path)
    try:
        _learn_receipts(robot)
        robot.view.mark_busy("L1")  # its load sample: saturated
        assert robot.view.snapshot(local=False).saturated("L1")
        cloud.behaviour = "silent"
        rec = robot.request(10, FRAME)
        assert rec["ok"] and rec["tier"] == "leader" and rec["hedged"] and rec["hedge_won"], rec["attempts"]
        assert [(a["tier"], a.get("hedge", False)) for a in rec["attempts"]] == [("cloud", False), ("leader", True)]
        assert rec["tor_ms"] < ANSWER_HEDGE_S * 1e3 / 2, rec["tor_ms"]
    finally:
        robot.close()
