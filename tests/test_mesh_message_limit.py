"""Zenoh's own per-message limit in every peer's config (issue #12, item 5).

Before: a 300 MB query was reassembled by zenoh and copied into Python before
the service's size check refused it; the cloud's peak RSS rose by ~600 MB.
Now ``transport/link/rx/max_message_size`` (40 MiB) makes the transport drop
it: the sender sees no reply, the cloud's peak RSS rises by about the limit,
and the cloud keeps serving.  A request just over the service's own limit
still gets the explicit ``oversized`` reply.  One real cloud process; ~15 s.
"""

from __future__ import annotations

import json

import pytest
import zenoh
from conftest import free_port

from scmr_mesh import keys, wire
from scmr_mesh.mesh.config import MAX_MESSAGE_BYTES, MAX_MESSAGE_KEY, MeshConfig, build_config
from scmr_mesh.mesh.testing import STUB, spawn_peer, stop_peer, synthetic_png, wait_for


def _limit(conf) -> int:
    return json.loads(conf.get_json(MAX_MESSAGE_KEY))


def test_every_peer_config_carries_the_limit():
    assert _limit(build_config(MeshConfig())) == MAX_MESSAGE_BYTES == 40 << 20
    assert _limit(build_config(MeshConfig(max_message_bytes=100 << 20))) == 100 << 20  # a larger request limit
    assert _limit(build_config(MeshConfig(max_message_bytes=1 << 20))) == MAX_MESSAGE_BYTES  # never lowered
    pinned = MeshConfig(cfg=[f"{MAX_MESSAGE_KEY}:2097152"])
    assert _limit(build_config(pinned)) == 2 << 20  # --cfg still wins over the default


def _vm(pid: int, field: str) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    raise AssertionError(field)


@pytest.mark.timeout(180)
def test_a_300_mb_query_is_dropped_by_the_transport_with_bounded_memory(tmp_path):
    port = free_port()
    ready = tmp_path / "c.ready"
    p = spawn_peer(["cloud", "--insecure", "--node", "c1", "--listen", f"tcp/127.0.0.1:{port}", "--workers", "1",
                    "--process", STUB, "--ready-file", str(ready), "--ods", str(tmp_path / "ods.sqlite")],
                   log_path=tmp_path / "c.log")
    try:
        wait_for(lambda: ready.exists() or p.poll() is not None, timeout=120, what="cloud ready")
        assert p.poll() is None, (tmp_path / "c.log").read_text()
        # a stranger: zenoh's own defaults (1 GiB limit on its side), shared memory off like ours
        conf = zenoh.Config()
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/shared_memory/enabled", "false")
        with zenoh.open(conf) as s:
            key = keys.drivable_request("cloud", "c1", "t1")
            q = s.declare_querier(key, timeout=30.0)
            wait_for(lambda: q.matching_status.matching, timeout=10, what="the cloud's queryable")
            good = wire.encode(wire.make_request("t1", 1, synthetic_png(1)))
            assert [r.ok is not None for r in q.get(payload=good)] == [True]
            before = _vm(p.pid, "VmHWM")
            big = bytes(300 << 20)
            replies = list(s.get(key, payload=big, timeout=5.0))
            del big
            # dropped in the transport: no answer from the service at all (zenoh's own timeout)
            assert not any(r.ok is not None for r in replies)
            assert all(r.err.payload.to_bytes() == b"Timeout" for r in replies)
            rise = _vm(p.pid, "VmHWM") - before
            assert rise < 100 << 20, f"the cloud's peak RSS rose by {rise >> 20} MB"
            # a request over the service's 32 MiB limit but under the transport's: explicit refusal
            over = wire.encode(wire.make_request("t1", 2, bytes(33 << 20), encoding="png"))
            (r,) = list(q.get(payload=over))
            err = wire.decode(r.err.payload.to_bytes(), kind="error")
            assert err["code"] == "oversized" and (err["robot"], err["seq"]) == (None, None)
            # still serving (a new frame: the same request again would be answered "duplicate", issue 24)
            again = wire.encode(wire.make_request("t1", 3, synthetic_png(1)))
            assert [r.ok is not None for r in q.get(payload=again)] == [True]
        assert p.poll() is None
    finally:
        assert stop_peer(p) == 0
