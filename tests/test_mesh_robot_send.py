"""How a robot sends a frame query (issue 14, docs/ZENOH.md section 8): with
congestion control 'drop' (the reply inherits it), each tier from its own
thread, so a send held up on one tier's dead link cannot hold the others."""

from __future__ import annotations

import threading

import pytest
from conftest import free_port

from scmr_mesh import keys, wire
from scmr_mesh.mesh.config import MeshConfig, close_session, open_session
from scmr_mesh.mesh.robot import Robot, RobotOptions
from scmr_mesh.mesh.testing import STUB, spawn_peer, stop_peer, synthetic_png, wait_for


class Reply:
    def __init__(self, payload: bytes, key: str) -> None:
        self.ok = type("Sample", (), {"payload": type("Z", (), {"to_bytes": lambda s: payload})(), "key_expr": key})()
        self.err = None


class FakeQuerier:
    """A querier of ``robot``'s requests to ``node`` of ``tier``, answering as that node would."""

    def __init__(self, robot: str, node: str, tier: str, block: threading.Event | None = None) -> None:
        self.block, self.robot, self.node, self.tier, self.threads = block, robot, node, tier, []

    def get(self, payload, *, encoding=None, cancellation_token=None):
        self.threads.append(threading.current_thread().name)
        if self.block is not None:
            self.block.wait(30)  # a push waiting for queue space on a dead link
        req = wire.decode(payload, kind="request")
        rep = wire.make_reply(req, mask_png=b"\x89PNG\r\n\x1a\n..", shape=(225, 300), threshold=1,
                              timings_ms={}, served_by=self.node, tier=self.tier, server_ms=1.0)
        return iter([Reply(wire.encode(rep), keys.drivable_request(self.tier, self.node, self.robot))])


def test_a_held_up_tier_does_not_hold_the_request_or_the_other_tier(tmp_path):
    robot = Robot("r1", tmp_path, options=RobotOptions(deadline_ms=300))
    release = threading.Event()
    payload = wire.encode(wire.make_request("r1", 1, b"x", encoding="png"))
    cloud, leader = FakeQuerier("r1", "c1", "cloud", block=release), FakeQuerier("r1", "L1", "leader")
    try:
        att = {"tier": "cloud", "node": "c1", "outcome": "pending"}
        assert robot._tier_send(att, cloud, payload) is None
        assert att["outcome"] == "timeout"  # given up after the deadline, cloud thread still held
        att2 = {"tier": "leader", "node": "L1", "outcome": "pending"}
        winner = robot._tier_send(att2, leader, payload)
        assert winner is not None and (winner.tier, winner.node) == ("leader", "L1") and att2["outcome"] == "ok"
        assert cloud.threads[0].startswith("scmr-cloud") and leader.threads[0].startswith("scmr-leader")
        assert att["outcome"] == "timeout"  # the late cloud thread did not touch the record
    finally:
        release.set()
        robot.close()


def test_frame_queries_and_their_replies_use_drop(tmp_path):
    import zenoh

    port = free_port()
    ready = tmp_path / "c.ready"
    p = spawn_peer(["cloud", "--insecure", "--node", "c1", "--listen", f"tcp/127.0.0.1:{port}", "--workers", "1",
                    "--process", STUB, "--ready-file", str(ready)], log_path=tmp_path / "c.log")
    try:
        wait_for(lambda: ready.exists() or p.poll() is not None, timeout=120, what="cloud ready")
        session = open_session(MeshConfig(connect=[f"tcp/127.0.0.1:{port}"], lease_ms=300))
        robot = Robot("r1", tmp_path / "r1")
        try:
            robot._session = session
            q = robot._querier("cloud", "c1")
            wait_for(lambda: q.matching_status.matching, timeout=10, what="matching queryable")
            req = wire.make_request("r1", 1, synthetic_png(1), encoding="png")
            replies = list(q.get(payload=wire.encode(req)))
            assert len(replies) == 1 and replies[0].ok is not None
            assert replies[0].ok.congestion_control == zenoh.CongestionControl.DROP
        finally:
            robot._session = None
            close_session(session)
    finally:
        assert stop_peer(p) == 0


def test_the_outbox_write_does_not_delay_the_send_and_is_done_before_the_file_goes(tmp_path):
    """The frame goes out while its outbox file is written (about 0.18 ms of a 21 KB JPEG before the
    send, in every frame's time to mask, before); the delivery waits for the write, then removes the
    file: nothing is left in the outbox, and a write that is still going holds only the delivery."""
    from scmr_mesh.mesh.frames import Frame

    robot = Robot("r1", tmp_path / "r1", options=RobotOptions(process=STUB))  # no session: computed locally
    routed, seen = threading.Event(), []
    real_route, real_write = robot._route, robot._to_outbox

    def route(*a, **kw):
        routed.set()
        return real_route(*a, **kw)

    def write(outbox_file, data):
        seen.append(routed.wait(10))  # old code: the write came first, so nothing was routed yet
        return real_write(outbox_file, data)

    robot._route, robot._to_outbox = route, write
    try:
        rec = robot.request(7, Frame(name="f7", data=synthetic_png(), encoding="png"))
    finally:
        robot.close()
    assert rec["ok"] and seen == [True]
    assert list((tmp_path / "r1" / "outbox").iterdir()) == []


def _request_in_child(out_dir, conn):
    from scmr_mesh.mesh.frames import Frame

    robot = Robot("r2", out_dir, options=RobotOptions(process=STUB))
    try:
        rec = robot.request(1, Frame(name="f1", data=synthetic_png(), encoding="png"))
        conn.send(rec["ok"] and not any((out_dir / "outbox").iterdir()))
    finally:
        robot.close()


def test_a_forked_child_and_a_shutting_down_interpreter_still_write_the_outbox(tmp_path, monkeypatch):
    """A child forked after the process's outbox thread started inherits the executor without its
    thread: its requests got a write that never ran and waited forever; now the child makes its own.
    And when no thread can be started (interpreter shutdown) the write runs in the request's thread."""
    import multiprocessing

    from concurrent.futures import ThreadPoolExecutor

    from scmr_mesh.mesh import robot as robot_mod
    from scmr_mesh.mesh.frames import Frame

    parent = Robot("r1", tmp_path / "r1", options=RobotOptions(process=STUB))
    try:
        assert parent.request(1, Frame(name="f1", data=synthetic_png(), encoding="png"))["ok"]
        ctx = multiprocessing.get_context("fork")
        ours, theirs = ctx.Pipe()
        child = ctx.Process(target=_request_in_child, args=(tmp_path / "r2", theirs), daemon=True)
        child.start()
        try:
            got = ours.recv() if ours.poll(60) else "no answer in 60 s"
            child.join(30)
        finally:
            if child.is_alive():  # a hung child must not hold the test session at exit
                child.kill()
                child.join(10)
        assert got is True and child.exitcode == 0, (got, child.exitcode)

        def refuse(self, *a, **kw):
            raise RuntimeError("cannot schedule new futures after interpreter shutdown")

        monkeypatch.setattr(ThreadPoolExecutor, "submit", refuse)
        written = []
        real = Robot._to_outbox
        monkeypatch.setattr(Robot, "_to_outbox", staticmethod(lambda f, d: written.append(f.name) or real(f, d)))
        assert parent.request(2, Frame(name="f2", data=synthetic_png(), encoding="png"))["ok"]
        assert written == ["2.png"] and not any((tmp_path / "r1" / "outbox").iterdir())
        monkeypatch.undo()

        class NoThread:  # "can't start new thread": raised after the job was queued
            queued: list = []

            def submit(self, fn, *a):
                self.queued.append(fn)
                raise RuntimeError("can't start new thread")

        monkeypatch.setattr(robot_mod, "_OUTBOX", [NoThread()])
        assert parent.request(3, Frame(name="f3", data=synthetic_png(), encoding="png"))["ok"]
        assert len(NoThread.queued) == 1 and not any((tmp_path / "r1" / "outbox").iterdir())
        NoThread.queued[0]()  # a thread picks the queued job up later: the frame was delivered, no write
        assert not any((tmp_path / "r1" / "outbox").iterdir())
    finally:
        parent.close()
