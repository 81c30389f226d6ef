"""Copies of one request (issue 24): a re-sent copy at the robot, every copy answered once at the
node, and the node's in-flight count when its pool fails.  Each test failed on main 678dcbb (the
reproductions of a hostile review); no middleware, no worker processes.
"""

from __future__ import annotations

import threading
import time

import zenoh
from test_mesh_hedge import FRAME, FakeTier, _robot, _Sample

from scmr_mesh import keys, wire
from scmr_mesh.mesh.server import RecentRequests, Replier, Service, ServiceState, default_admission


# ---------------------------------------------------------------- robot side
class ServedOnce(FakeTier):
    """A node as RecentRequests makes it: it runs a request once, from its first copy's arrival,
    and answers every copy (joined or cached) when that run is done, ``slow_s`` after the first copy."""

    def __init__(self, *a, **kw) -> None:
        super().__init__(*a, **kw)
        self.first: dict[int, float] = {}

    def get(self, payload, *, encoding=None, cancellation_token=None):
        self.calls += 1
        req = wire.decode(payload, kind="request")
        t0 = self.first.setdefault(req["seq"], time.monotonic())
        left = t0 + self.slow_s - time.monotonic()
        if left > 0 and self._wait_cancel(cancellation_token, left):
            return iter([])
        key = keys.drivable_request(self.tier, self.node, self.robot)
        from test_mesh_hedge import _Reply

        rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n..", shape=(225, 300), threshold=1,
                              timings_ms={}, served_by=self.node, tier=self.tier, server_ms=1.0)
        return iter([_Reply(wire.encode(rep), key)])


def test_a_resent_copy_does_not_teach_the_tier_a_shorter_answer_time(tmp_path):
    """robot.py _finish_sent (line 583) learns answer_ms measured from the *re-sent* copy's send
    (_collect's t0): the copy joined the first copy's run, so the tier's answer time is learnt as
    (true time - hedge delay).  The learnt p95 drops, the hedge delay drops, more copies are re-sent
    (each teaching a still shorter time): the hedge budget goes on a node that is merely slow."""
    robot, fakes = _robot(tmp_path, "fast", "fast", deadline_ms=5000, hedge_ms=50)
    cloud = ServedOnce("r1", "cloud", "c1", slow_s=0.15)
    robot._queriers[keys.drivable_request("cloud", "c1", "r1")] = cloud
    robot.view.on_liveliness(_Sample(keys.alive("leader", "L1"), zenoh.SampleKind.DELETE))  # cloud alone
    try:
        recs = [robot.request(i, FRAME) for i in range(2)]  # the budget's 2 saved tokens; the 1st answer is not learnt
        assert all(r["ok"] and r["tier"] == "cloud" for r in recs), recs
        assert all(any(a.get("resend") for a in r["attempts"]) for r in recs)  # each copy re-sent at 50 ms
        learnt = robot._answer_times["cloud"].values()
        # every answer of this node took >= 150 ms from the request's send; learnt: ~100 ms
        assert learnt and min(learnt) >= 140, learnt
    finally:
        robot.close()


def test_a_primary_that_answered_while_the_hedge_target_was_sought_is_not_thrown_away(tmp_path):
    """robot.py _send_hedged (lines ~680-688): after the hedge delay the robot looks for a hedge
    target (_hedge_target: a snapshot and _matching, which waits up to MATCH_WAIT_S = 50 ms for a
    querier born just now, e.g. a leader elected this instant).  When none is found it gives the
    primary up (primary.give_up) without checking whether it answered meanwhile: a good answer in
    hand is cancelled, the same request is sent again and the node answers it a second time."""
    robot, fakes = _robot(tmp_path, "slow", "fast", deadline_ms=5000, hedge_ms=20)
    fakes["cloud"].slow_s = 0.03
    robot.view.on_liveliness(_Sample(keys.alive("leader", "L1"), zenoh.SampleKind.DELETE))
    seek, start, sent = robot._hedge_target, robot._start, []

    def start_recorded(*a, **kw):
        sent.append(start(*a, **kw))
        return sent[-1]

    def slow_seek(*a, **kw):
        # as _matching's wait for a querier declared moments ago: the primary answers meanwhile
        sent[0].fut.result(timeout=30)
        return seek(*a, **kw)

    robot._start, robot._hedge_target = start_recorded, slow_seek
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"]
        # the primary's answer came at 30 ms, before the re-send at ~80 ms: it should be used
        assert fakes["cloud"].calls == 1, rec["attempts"]
        assert not rec["hedged"] and rec["attempts"][0]["outcome"] == "ok", rec["attempts"]
    finally:
        robot.close()


# -------------------------------------------------------------- service side
class FakeQuery:
    def __init__(self, key: str, payload: bytes) -> None:
        self.key_expr = key
        self.payload = type("P", (), {"to_bytes": lambda _s: payload})()
        self.answers: list[tuple[str, bytes]] = []
        self.dropped = threading.Event()  # set when the service is done with the query

    def reply(self, key, payload, encoding=None, **qos):  # (receipts: congestion_control, express)
        self.answers.append(("ok", payload))

    def reply_err(self, payload, encoding=None):
        self.answers.append(("err", payload))

    def drop(self):
        self.dropped.set()


class FakePool:
    def __init__(self, fail: bool = False) -> None:
        from concurrent.futures import Future

        self.fail, self.futs, self._Future = fail, [], Future

    def submit(self, *a, **kw):
        if self.fail:
            raise RuntimeError("cannot schedule new futures after shutdown")
        f = self._Future()
        self.futs.append(f)
        return f

    def outstanding(self) -> int:
        return len([f for f in self.futs if not f.done()])

    def shutdown(self) -> None:
        pass


def _service(pool, *, workers: int = 1, max_inflight: int = 4) -> Service:
    """A Service without its worker processes or zenoh (the query path only)."""
    svc = Service.__new__(Service)
    svc.node, svc.tier, svc.max_request_bytes = "c1", "cloud", wire.MAX_REQUEST_BYTES
    svc.state = ServiceState("c1", "cloud", workers, max_inflight)
    svc.admission, svc.negotiator, svc.priority_cap, svc._capped = default_admission, None, None, set()
    svc.replier, svc.recent, svc.pool = Replier(1), RecentRequests(), pool
    svc.state.outstanding = pool.outstanding
    svc._error_log, svc._error_log_lock = {}, threading.Lock()
    return svc


def _query(seq: int, robot: str = "r1") -> FakeQuery:
    req = wire.make_request(robot, seq, b"\x89PNG frame %d" % seq, encoding="png")
    return FakeQuery(keys.drivable_request("cloud", "c1", robot), wire.encode(req))


def _answered(q: FakeQuery, timeout: float = 5.0) -> list:
    q.dropped.wait(timeout)
    return [(k, wire.decode(p, kind="reply" if k == "ok" else "error")) for k, p in q.answers]


def test_a_failed_submit_does_not_leak_an_inflight_slot():
    """server.py _on_query lines ~680-690 (pre-existing, untouched by 16308ff): inflight += 1, then
    pool.submit raises; the except branch answers 'internal' but never takes the slot back
    (_dispatch does).  max_inflight such failures and the default admission answers every request
    'busy' forever, though the pool (and WorkerPool.outstanding, which does undo its count) is idle."""
    svc = _service(FakePool(fail=True), max_inflight=4)
    try:
        for seq in range(4):
            q = _query(seq)
            svc._on_query(q)
            assert _answered(q)[0][1]["code"] == "internal"
        svc.pool.fail = False
        q = _query(99)
        svc._on_query(q)
        assert svc.state.inflight <= 1, f"inflight {svc.state.inflight} with nothing in the pool"
        assert not q.answers or q.answers[0][0] == "ok", _answered(q)
    finally:
        svc.replier.close()


def test_shutdown_answers_the_copies_that_joined_a_queued_request():
    """server.py shutdown (line 577): requests still in the negotiator's queue get 'unavailable',
    but only their first copy: the copies that joined them in RecentRequests are never answered
    (nor forgotten); a robot's re-sent copy waits for its querier's timeout instead of failing over."""
    from scmr_mesh.qos.negotiator import Negotiator

    svc = _service(FakePool())
    svc.negotiator = Negotiator(capacity=4, workers=1)  # no dispatcher: the request stays queued
    svc.state.queue_managed = True
    try:
        first, copy = _query(7), _query(7)
        copy.payload = first.payload
        svc._on_query(first)
        svc._on_query(copy)
        assert svc.negotiator.waiting == 1 and not copy.answers
        svc.shutdown()
        assert _answered(first, 2.0)[0][1]["code"] == "unavailable"
        assert copy.answers, "the joined copy was never answered"
    finally:
        svc.replier.close()


def test_a_request_in_service_is_never_forgotten_and_its_reply_never_counted_twice():
    """RecentRequests used to forget the oldest entry even while its first copy was served (more
    than ``size`` newer requests meanwhile): the copies waiting for it were dropped unanswered, a
    later copy was taken in as new (the pipeline ran twice), and the second run's reply was added to
    the byte budget again (kept bytes drifting up for good, down to keeping nothing)."""
    r = RecentRequests(size=1, max_reply_bytes=10)
    a, b = ("r1", 1, 10, b"d1", "cloud"), ("r1", 2, 11, b"d2", "cloud")
    assert r.admit(a)[0] == "new"            # first copy of a, in service
    assert r.admit(a, "qa")[0] == "joined"   # a copy waits for it
    assert r.admit(b)[0] == "new"            # over the size, but a is still served: not forgotten
    assert r.admit(a, "qb")[0] == "joined"   # so a copy of a waits too, never runs a second time
    assert r.complete(a, b"x" * 6) == ["qa", "qb"]
    r.complete(a, b"x" * 6)                  # a second answer of a (e.g. after a failed first): replaced
    assert r._kept_bytes == sum(r._kept.values()) == 6, (r._kept_bytes, dict(r._kept))
    r.complete(b, None)
    assert r.admit(("r1", 3, 12, b"d3", "cloud"))[0] == "new" and len(r._seen) <= 2  # answered ones go


def test_a_silent_cloud_node_is_hedged_to_the_other_live_cloud_node(tmp_path):
    """robot.py _hedge_target (line ~633) looks only at *later tiers* of the plan: with two cloud
    nodes and no leader (scmr up --clouds 2; DEPLOY.md 'several nodes per host'), a silent c1 is
    re-sent to c1 itself (ae5efbb) and the frame waits the whole deadline + 0.25 s before the
    normal failover tries the live c2.  A silent link to one node costs the deadline, not the hedge delay."""
    robot, fakes = _robot(tmp_path, "silent", "fast", deadline_ms=400, hedge_ms=20)
    robot.view.on_liveliness(_Sample(keys.alive("leader", "L1"), zenoh.SampleKind.DELETE))
    robot.view.on_liveliness(_Sample(keys.alive("cloud", "c2"), zenoh.SampleKind.PUT))
    c2 = FakeTier("r1", "cloud", "c2", "fast")
    robot._queriers[keys.drivable_request("cloud", "c2", "r1")] = c2
    fakes["cloud"].hold_s = 2.0
    robot.view._loads["c2"] = 0.1  # c1 first (otherwise the view's rotation picks it every other snapshot)
    try:
        rec = robot.request(0, FRAME)
        assert rec["ok"] and rec["served_by"] == "c2", rec
        assert rec["tor_ms"] < 200, ([(a["node"], a["outcome"], a.get("resend")) for a in rec["attempts"]],
                                     rec["tor_ms"])
    finally:
        robot.close()


def test_a_copy_on_another_tier_of_the_node_is_not_answered_with_the_first_tiers_reply():
    """server.py _ident (line 228) leaves out the tier, and RecentRequests outlives serve_as (a
    leader-capable node serves as peer, then as leader, with the same Service): a copy that comes on
    the node's new tier key gets the kept reply of the old tier, whose 'tier' field the robot
    checks (_reply_problem): refused as bad_reply and counted mismatched, a problem of the run."""
    svc = _service(FakePool())
    svc.tier = svc.state.tier = "peer"
    try:
        first = _query(3)
        first.key_expr = keys.drivable_request("peer", "c1", "r1")
        svc._on_query(first)
        svc.pool.futs[0].set_result({"mask_png": b"\x89PNG\r\n\x1a\n..", "shape": [225, 300], "threshold": 1,
                                     "worker_ms": 5.0})
        assert _answered(first)[0][1]["tier"] == "peer"
        svc.tier = svc.state.tier = "leader"  # serve_as("leader") after an election
        copy = FakeQuery(keys.drivable_request("leader", "c1", "r1"), first.payload.to_bytes())
        svc._on_query(copy)
        assert len(svc.pool.futs) == 2  # served afresh on the new tier, not from the peer tier's reply
        svc.pool.futs[1].set_result({"mask_png": b"\x89PNG\r\n\x1a\n..", "shape": [225, 300], "threshold": 1,
                                     "worker_ms": 5.0})
        kind, body = _answered(copy)[0]
        assert body["tier"] == "leader", f"{kind} reply on the leader key says tier {body['tier']!r}"
    finally:
        svc.replier.close()


def test_copies_of_one_request_are_bounded_while_it_is_served():
    """server.py RecentRequests.admit (lines ~185-188): every copy of a request in service joins its
    waiters, with no bound and before admission (no inflight slot, no busy, no per-robot quota).  A
    robot sends at most 3 copies; a hostile or looping one can park any number of queries, each
    holding its payload (up to --max-request-bytes, 32 MiB) until the first copy is answered.
    Before 16308ff each extra copy got 'duplicate' at once and was dropped."""
    svc = _service(FakePool())
    try:
        first = _query(5)
        svc._on_query(first)
        for _ in range(200):
            svc._on_query(FakeQuery(first.key_expr, first.payload.to_bytes()))
        (entry,) = [e for e in svc.recent._seen.values() if e.waiters]
        assert len(entry.waiters) <= 2, f"{len(entry.waiters)} copies parked on one request in service"
    finally:
        svc.replier.close()
