"""Malformed, oversized and wrong-version requests get error replies naming the
problem, and the service keeps serving.  One real cloud process; ~3 s."""

from __future__ import annotations


import msgpack
import pytest
from cloud_querier import ask, cloud_querier
from conftest import free_port

from scmr_mesh import keys, wire
from scmr_mesh.mesh.config import MeshConfig, close_session, open_session
from scmr_mesh.mesh.testing import STUB, spawn_peer, synthetic_png, wait_for

LIMIT = 60_000


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("malformed")
    with cloud_querier(tmp, "c1", "--workers", "1", "--process", STUB, "--max-request-bytes", str(LIMIT)) as (p, q):
        yield p, q


def _good(seq=1):
    return wire.make_request("t1", seq, synthetic_png(seq), encoding="png")


CASES = [
    ("not msgpack", b"\xc1\xc1\xc1", "malformed", "not msgpack"),
    ("not a map", msgpack.packb([1, 2, 3]), "malformed", "map"),
    ("empty", b"", "malformed", ""),
    ("wrong version", wire.encode({**_good(), "v": 99}), "wrong_version", "99"),
    ("missing field", wire.encode({k: v for k, v in _good().items() if k != "seq"}), "malformed", "seq"),
    ("bad encoding", wire.encode({**_good(), "encoding": "gif"}), "malformed", "encoding"),
    ("image not bytes", wire.encode({**_good(), "image": "abc"}), "malformed", "image"),
    ("oversized", wire.encode({**_good(), "image": b"\x00" * (LIMIT + 1)}), "oversized", str(LIMIT)),
    ("undecodable image", wire.encode({**_good(), "image": b"not an image at all"}), "malformed", "image"),
    ("raw without shape", wire.encode({**_good(), "encoding": "raw"}), "malformed", "shape"),
    ("raw of the wrong size", wire.encode(wire.make_request("t1", 1, bytes(10), encoding="raw", shape=(4, 4, 3))),
     "malformed", "48"),
]


def test_bad_requests_get_error_replies_and_service_keeps_serving(cloud):
    proc, q = cloud
    kind, rep = ask(q, wire.encode(_good(0)))
    assert kind == "ok" and rep["served_by"] == "c1" and rep["tier"] == "cloud" and rep["seq"] == 0
    for name, payload, code, needle in CASES:
        kind, msg = ask(q, payload)
        assert kind == "err", name
        assert msg["code"] == code, (name, msg)
        assert needle in msg["message"], (name, msg["message"])
        assert msg["served_by"] == "c1"
    # robot and seq are echoed when the request could be read
    kind, msg = ask(q, wire.encode({**_good(7), "image": b"junk"}))
    assert (msg["robot"], msg["seq"]) == ("t1", 7)
    for seq in range(2, 5):
        kind, rep = ask(q, wire.encode(_good(seq)))
        assert kind == "ok" and rep["seq"] == seq
    raw = wire.make_request("t1", 9, bytes(range(256)) * 9, encoding="raw", shape=(24, 32, 3))
    kind, rep = ask(q, wire.encode(raw))
    assert kind == "ok" and rep["shape"] == [225, 300]
    assert proc.poll() is None


def test_error_replies_name_what_was_received_and_the_fix(cloud):
    """Issue #12, item 7: a client reads what it sent, what is wrong, and what to send instead."""
    _, q = cloud
    _, msg = ask(q, b"\xc1\xc1\xc1")
    assert "payload of 3 bytes is not msgpack" in msg["message"] and "0xc1c1c1" in msg["message"]
    assert "wire.make_request" in msg["message"]
    # a schema violation: robot and seq were readable, so they come back
    for bad in ({**_good(5), "encoding": "gif"}, {k: v for k, v in _good(5).items() if k != "mode"},
                {**_good(5), "priority": -1}, {**_good(5), "v": 99}):
        _, msg = ask(q, wire.encode(bad))
        assert (msg["robot"], msg["seq"]) == ("t1", 5), msg
    _, msg = ask(q, wire.encode({**_good(5), "robot": "no spaces allowed", "encoding": "gif"}))
    assert (msg["robot"], msg["seq"]) == (None, 5)  # an unreadable robot id is never echoed
    # an undecodable image: the wire's terms ([H, W, 3]), not the decoder's Python API
    _, msg = ask(q, wire.encode({**_good(6), "image": b"not an image at all"}))
    assert "encoding 'png', 19 bytes" in msg["message"] and "[H, W, 3]" in msg["message"]
    assert "shape=(H, W)" not in msg["message"] and (msg["robot"], msg["seq"]) == ("t1", 6)
    raw = wire.make_request("t1", 8, bytes(10), encoding="raw", shape=(4, 4, 3))
    _, msg = ask(q, wire.encode(raw))
    assert "shape [4, 4, 3]" in msg["message"] and "48" in msg["message"] and "[H, W, 3]" in msg["message"]


def test_no_payload_is_an_error_reply(cloud):
    _, q = cloud
    replies = list(q.get())
    assert len(replies) == 1 and replies[0].err is not None
    assert wire.decode(replies[0].err.payload.to_bytes(), kind="error")["code"] == "malformed"


def test_robot_publishes_valid_telemetry_results_and_load(cloud, tmp_path):
    """Telemetry, results and load messages on the wire match their schemas and the records."""
    import json
    import threading

    from scmr_mesh.mesh.testing import read_records

    proc, q = cloud
    ep = None
    for arg_i, arg in enumerate(proc.args):
        if arg == "--listen":
            ep = proc.args[arg_i + 1]
    got: dict[str, list] = {"telemetry": [], "results": [], "load": []}
    lock = threading.Lock()

    def keep(kind):
        def cb(sample):
            with lock:
                got[kind].append(sample.payload.to_bytes())
        return cb

    # the test listens and the robot dials it: peers do not relay for each other, and a link found
    # by gossip could come up after the robot's first messages (the robot's publications reach
    # this session only over a direct link)
    mine = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(MeshConfig(connect=[ep], listen=[mine], lease_ms=300))
    try:
        subs = [session.declare_subscriber(keys.TELEMETRY_ALL, keep("telemetry")),
                session.declare_subscriber(keys.RESULTS_ALL, keep("results")),
                session.declare_subscriber(keys.LOAD_ALL, keep("load"))]
        # the link to the cloud is up once its token is seen, and our subscriber declarations, sent
        # on that link before the query, have reached it (declarations are delivered in order)
        wait_for(lambda: any(x.ok for x in session.liveliness().get(keys.ALIVE_ALL, timeout=1.0)), timeout=30,
                 what="the cloud's liveliness token")
        r = spawn_peer(["robot", "--insecure", "--id", "tr1", "--synthetic", "stub", "--count", "4", "--rate", "20",
                        "--out", str(tmp_path / "tr1"), "--connect", ep, "--connect", mine, "--no-local-fallback"],
                       log_path=tmp_path / "tr1.log")
        assert r.wait(timeout=60) == 0, (tmp_path / "tr1.log").read_text()
        wait_for(lambda: len(got["telemetry"]) >= 4 and len(got["results"]) >= 4, timeout=10,
                 what="4 telemetry and 4 results messages")
        for s in subs:
            s.undeclare()
    finally:
        close_session(session)
    tele = [wire.decode(b, kind="telemetry") for b in got["telemetry"]]
    assert [t["seq"] for t in tele] == [0, 1, 2, 3]
    assert tele[-1]["results"]["succeeded"] == 4 and tele[-1]["results"]["by_tier"]["cloud"] == 4
    assert all(0.0 <= t["battery"] <= 1.0 and t["health"] == "ok" for t in tele)
    results = [json.loads(b) for b in got["results"]]
    records = read_records(tmp_path / "tr1" / "records.jsonl")
    assert [x["seq"] for x in results] == [x["seq"] for x in records]
    assert [x["served_by"] for x in results] == ["c1"] * 4
    loads = [wire.decode(b, kind="load") for b in got["load"]]
    assert loads and all(ld["node"] == "c1" and ld["tier"] == "cloud" and ld["workers"] == 1 for ld in loads)
    assert max(ld["served"] for ld in loads) >= 1


def test_requests_past_their_deadline_are_not_processed(tmp_path):
    """With one slow worker, requests queued past their deadline get 'expired' without the work."""
    from scmr_mesh.mesh.testing import SLOW

    with cloud_querier(tmp_path, "slow", "--workers", "1", "--process", SLOW, "--budget-ms", "100000",
                       ready_timeout=60, query_timeout=10.0,
                       env={"SCMR_STUB_DELAY_MS": "1000"}) as (p, q):  # queue them: no busy
        pending = [q.get(payload=wire.encode(wire.make_request("t1", i, synthetic_png(i), deadline_ms=300)))
                   for i in range(3)]
        out = {}
        for i, h in enumerate(pending):
            r = list(h)[0]
            if r.ok is not None:
                out[i] = "ok"
            else:
                out[i] = wire.decode(r.err.payload.to_bytes(), kind="error")["code"]
    # the first starts at once (300 ms to reach the worker); the others wait >= 1 s for it
    assert out == {0: "ok", 1: "expired", 2: "expired"}
