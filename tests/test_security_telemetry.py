"""Issue #28 items 3 and 6 (and issue #25 item 10), with real secured peers: the attacker holds one
valid fleet certificate, r9 (a leader-capable robot, so the ACL lets it query the cloud's relay key).

One cloud (``--telemetry-quota 20``) and one honest robot r1; r9, from its own session:

* relays r1's "future" records 1..40 to the cloud: unsigned, signed with r9's own key, and one with
  seq 2^62 (before: all 40 stored as received from the cloud, r1's genuine records were then acked as
  duplicates and deleted from its queue, and the huge seq pinned ``state/r1`` in the cloud's buffer);
* floods its own telemetry key with its own signed records (before: no quota at all);

and a plain robot r8 sends the leader one record of its own with seq 2^63, then good ones (item 4:
before, the leader never forwarded anything again).

After r1 stops: every record of r1 in the store is r1's own (digest of what r1 sent), none of the
forgeries, r1 lost nothing and left nothing queued; the relay answer counted the refusals; r9 got busy
answers past its quota; the cloud's buffer holds r1's genuine last state.  Run with ``pytest -m security``.
"""

from __future__ import annotations

import dataclasses
import json

import msgpack
import pytest
from conftest import free_port

from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.data.record import MAX_SEQ, encode_records, make_record
from scmr_mesh.data.signing import RecordSigner
from scmr_mesh.mesh.data_common import buffer_key, relay_key, telemetry_key
from scmr_mesh.mesh.testing import STUB, spawn_peer, stop_peer, wait_for
from scmr_mesh.security.credentials import create_credentials

pytestmark = pytest.mark.security


def _get(session, key: str, payload: bytes) -> tuple[str, dict]:
    for r in session.get(key, payload=payload, timeout=5.0):
        if r.ok is not None:
            return "ok", msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)
        return "err", msgpack.unpackb(r.err.payload.to_bytes(), raw=False)
    return "none", {}


def test_a_leader_capable_identity_cannot_store_records_as_another_robot(tmp_path, repo_root):
    from test_security_default import _session

    creds = tmp_path / "certs"
    create_credentials(creds, "c1=cloud,leader0=leader,r1,r8,r9=robot+leader-capable")
    profile = str(repo_root / "peers" / "secure" / "mtls.toml")
    sec = ["--security", profile, "--credentials", str(creds)]
    ep = f"tcp/127.0.0.1:{free_port()}"
    cloud = spawn_peer(["cloud", "--node", "c1", "--listen", ep, "--workers", "1", "--process", STUB, *sec,
                        "--ready-file", str(tmp_path / "c1.ready"), "--ods", str(tmp_path / "ods.sqlite"),
                        "--telemetry-quota", "20"], log_path=tmp_path / "c1.log")
    robot = leader = None
    s = s8 = None
    try:
        wait_for(lambda: (tmp_path / "c1.ready").exists() or cloud.poll() is not None, timeout=90, what="cloud")
        assert cloud.poll() is None, (tmp_path / "c1.log").read_text()[-2000:]
        lep = f"tcp/127.0.0.1:{free_port()}"
        leader = spawn_peer(["leader", "--node", "leader0", "--workers", "1", "--process", STUB, *sec, "--listen",
                             lep, "--connect", ep, "--relay-dir", str(tmp_path / "relay"),
                             "--ready-file", str(tmp_path / "leader0.ready")], log_path=tmp_path / "leader0.log")
        robot = spawn_peer(["robot", "--id", "r1", "--synthetic", "stub", "--process", STUB, "--rate", "10",
                            "--duration", "4", "--quiet", "--out", str(tmp_path / "r1"), "--connect", ep,
                            "--telemetry-queue", str(tmp_path / "q-r1"), *sec], log_path=tmp_path / "r1.log")
        s = _session(creds, profile, "r9", ep)
        wait_for(lambda: _get(s, buffer_key("cloud", "c1"), msgpack.packb({"sel": "x"}))[0] == "ok", timeout=30,
                 what="r9 linked to the cloud")
        mine = RecordSigner(creds / "r9" / "key.pem")
        unsigned = [make_record("r1", n, battery=0.01, health="forged") for n in range(1, 21)]
        signed = [dataclasses.replace(r, sig=mine.sign(r.digest()))
                  for r in [make_record("r1", n, battery=0.01, health="forged") for n in range(21, 41)]]
        huge = make_record("r1", MAX_SEQ, battery=0.01, health="forged")
        huge = dataclasses.replace(huge, sig=mine.sign(huge.digest()))
        kind, ans = _get(s, relay_key("c1"), encode_records([*unsigned, *signed, huge], via="leader"))
        assert kind == "ok" and ans["refused"] == 41 and ans["stored"] == 0, ans  # before: stored 41

        # r9's own telemetry past its quota (20 records/s, a burst of 600): busy answers, the rest refused
        answers = []
        for b in range(12):
            own = [make_record("r9", 1 + b * 64 + i) for i in range(64)]
            own = [dataclasses.replace(r, sig=mine.sign(r.digest())) for r in own]
            answers.append(_get(s, telemetry_key("cloud", "c1", "r9"), encode_records(own)))
        busy = [a for k, a in answers if k == "err" and a.get("quota")]
        assert busy and all(k == "ok" for k, _ in answers[:9]), answers  # 9 x 64 = 576 <= 600 fit

        # issue #28 item 4: plain robot r8 sends the leader one record of its own with seq 2^63, then
        # good ones: the bad one is refused, the rest relayed to the cloud (before: the leader never
        # forwarded anything again)
        wait_for(lambda: (tmp_path / "leader0.ready").exists() or leader.poll() is not None, timeout=90,
                 what="leader")
        s8 = _session(creds, profile, "r8", lep)  # straight to the leader (no wait on gossip under load)
        lkey = telemetry_key("leader", "leader0", "r8")
        wait_for(lambda: _get(s8, buffer_key("leader", "leader0"), msgpack.packb({"sel": "x"}))[0] == "ok",
                 timeout=30, what="r8 linked to the leader")
        bad = {"records": [{"robot": "r8", "seq": 2**63, "t_unix_ns": 1, "health": "ok", "results": {}}]}
        assert _get(s8, lkey, msgpack.packb(bad))[0] == "err"
        r8 = RecordSigner(creds / "r8" / "key.pem")
        good = [make_record("r8", n) for n in (1, 2, 3)]
        kind, ans = _get(s8, lkey, encode_records([dataclasses.replace(r, sig=r8.sign(r.digest())) for r in good]))
        assert kind == "ok" and ans["acked"] == 3, ans

        def relayed() -> bool:
            with OperationalDataStore(tmp_path / "ods.sqlite", readonly=True) as o:
                return o.seqs("r8") == [1, 2, 3]

        wait_for(relayed, timeout=30, what="r8's records relayed by the leader to the cloud")

        assert robot.wait(timeout=60) == 0, (tmp_path / "r1.log").read_text()[-2000:]
        _, buf = _get(s, buffer_key("cloud", "c1"), msgpack.packb({"sel": "state/r1"}))
    finally:
        for sess in (s, s8):
            if sess is not None:
                sess.close()
        for p in (robot, leader):
            if p is not None:
                stop_peer(p, timeout=10)
        stop_peer(cloud, timeout=20)
    summary = json.loads((tmp_path / "r1" / "telemetry.json").read_text())
    assert summary["lost"] == 0 and summary["queued"] == 0 and summary["sent"] >= 20, summary
    with OperationalDataStore(tmp_path / "ods.sqlite", readonly=True) as ods:
        rows = ods.range(robot="r1")
        assert {r["health"] for r in rows} == {"ok"} and len(rows) == summary["sent"], rows[:3]
        assert ods.seqs("r1") == list(range(1, summary["sent"] + 1))
        assert {r["inc"] for r in rows} == {summary["incarnation"]} != {0}
        assert ods.counts()["r9"]["stored"] == 576
    assert buf["items"]["state/r1"]["seq"] == summary["sent"] and buf["items"]["state/r1"]["health"] == "ok"
    ingest = json.loads((tmp_path / "ingest-c1.json").read_text())  # the cloud's counters, written at exit
    assert ingest["refused"]["signature"] == 41 and ingest["refused"]["quota"] >= 64, ingest
    assert ingest["quota"]["refused"]["r9"]["batches"] >= 1 and "r1" not in ingest["quota"]["refused"], ingest
