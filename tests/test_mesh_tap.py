"""``scmr tap``: the pure renderer, and one real tap process against a real peer (~2 s)."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import msgpack
from conftest import free_port

from scmr_mesh import wire
from scmr_mesh.mesh.tap import render


def test_render_decodes_scmr_messages_and_never_raises_on_garbage():
    load = wire.encode(wire.make_load("c0", "cloud", workers=1, inflight=0, served=3))
    line = json.loads(render("scmr/load/cloud/c0", load))
    assert line["kind"] == "load" and line["bytes"] == len(load) and line["msg"]["served"] == 3
    big = msgpack.packb({"kind": "reply", "mask": b"\0" * 5000, "xs": list(range(100)), "t": float("nan")})
    line = json.loads(render("k", big))
    assert line["msg"]["mask"] == "<bin 5000 bytes>" and line["msg"]["xs"][-1] == "<100 items>"
    assert line["msg"]["t"] == "nan"
    assert json.loads(render("k", b'{"ok": true}', encoding="application/json"))["kind"] == "json"
    for junk in (b"\xc1" * 40, b"", b"\x91" * 5000, msgpack.packb({1: {2: [3]}})):
        out = json.loads(render("k", junk))
        assert out["bytes"] == len(junk)
    assert json.loads(render("k", b"\xc1" * 40)) == {"key": "k", "kind": "undecodable", "bytes": 40,
                                                      "msg": {"hex": "c1" * 16 + "..."}}


def test_a_tap_process_prints_a_real_peers_messages_decoded(tmp_path):
    import zenoh

    from scmr_mesh.mesh.config import MeshConfig, close_session, open_session

    port = free_port()
    session = open_session(MeshConfig(listen=[f"tcp/127.0.0.1:{port}"]))
    load = wire.encode(wire.make_load("c0", "cloud", workers=2, inflight=0, served=7))

    import threading

    queried = threading.Event()

    def answer(query):  # replied before the test publishes: the reply is among the first 4 lines
        query.reply("scmr/tapq", msgpack.packb({"v": 1, "kind": "reply", "mask": b"\1" * 300}))
        queried.set()

    qable = session.declare_queryable("scmr/tapq", answer)
    tap = subprocess.Popen([sys.executable, "-m", "scmr_mesh", "tap", "scmr/**", "--get", "--insecure",
                            "--connect", f"tcp/127.0.0.1:{port}", "--count", "4", "--duration", "20"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        # publish once the tap has queried (its reply goes first on the link), until it has seen 4
        while tap.poll() is None and time.monotonic() < deadline:
            if queried.is_set():
                session.put("scmr/load/cloud/c0", load, encoding=zenoh.Encoding(wire.MSGPACK_ENCODING))
                session.put("scmr/junk", b"\xc1\xc1\xc1")
            try:
                tap.wait(timeout=0.05)
            except subprocess.TimeoutExpired:
                pass
        out, err = tap.communicate(timeout=30)
    finally:
        if tap.poll() is None:
            tap.kill()
        qable.undeclare()
        close_session(session)
    assert tap.returncode == 0, err
    lines = [json.loads(x) for x in out.splitlines()]
    assert len(lines) == 4, out
    by_kind = {x["kind"]: x for x in lines}
    assert by_kind["load"]["key"] == "scmr/load/cloud/c0" and by_kind["load"]["msg"]["served"] == 7
    assert by_kind["undecodable"] == {"key": "scmr/junk", "kind": "undecodable", "bytes": 3, "msg": {"hex": "c1c1c1"}}
    assert by_kind["reply"]["from"] == "reply" and by_kind["reply"]["msg"]["mask"] == "<bin 300 bytes>"
