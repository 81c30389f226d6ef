"""Robots accept a reply only from a node allowed to serve its tier, on the key it was sent to
(issue #13 item 3).  Pure: fake replies and sessions, no Zenoh traffic."""

from __future__ import annotations

from types import SimpleNamespace as NS

import pytest
import zenoh

from scmr_mesh import wire
from scmr_mesh.mesh.robot import Robot
from scmr_mesh.security.credentials import Fleet, Peer

FLEET = Fleet((Peer("cloud0", "cloud"), Peer("leader0", "leader", leader_capable=True),
               Peer("r1", "robot"), Peer("r2", "robot", leader_capable=True)))


def _reply(robot="r1", served_by="cloud0", tier="cloud"):
    req = wire.make_request(robot, 1, b"\x89PNG", encoding="png")
    return wire.make_reply(req, mask_png=b"x", shape=[225, 300], threshold=1.0, timings_ms={},
                           served_by=served_by, tier=tier, server_ms=1.0, queue_ms=0.0)


def _zreply(zid="z1"):
    return NS(replier_id=NS(zid=zid))


@pytest.fixture
def robot(tmp_path):
    r = Robot("r1", tmp_path / "r1")
    r.view.trust = FLEET.may_serve
    r._session = NS(info=NS(links=lambda: [NS(zid="z1", auth_identifier="cloud0"),
                                           NS(zid="z2", auth_identifier="r2"), NS(zid="z3", auth_identifier=None)]))
    yield r
    r.close()


@pytest.mark.parametrize("tier,node,key,msg,zid,problem", [
    ("cloud", "cloud0", "scmr/drivable/cloud/cloud0/r1", _reply(), "z1", None),
    ("leader", "r2", "scmr/drivable/leader/r2/r1", _reply(served_by="r2", tier="leader"), "z2", None),  # elected
    ("peer", "r2", "scmr/drivable/peer/r2/r1", _reply(served_by="r2", tier="peer"), "z2", None),
    ("cloud", "cloud0", "scmr/drivable/cloud/cloud0/r1", _reply(), "z9", None),  # not a direct link: no check
    ("cloud", "cloud0", "scmr/drivable/**", _reply(), "z1", "came on 'scmr/drivable/\\*\\*'"),
    ("cloud", "cloud0", "scmr/drivable/cloud/cloud0/r2", _reply(), "z1", "expected"),
    ("cloud", "cloud0", "scmr/drivable/cloud/cloud0/r1", _reply(served_by="aaa"), "z1", "served_by 'aaa'"),
    ("cloud", "cloud0", "scmr/drivable/cloud/cloud0/r1", _reply(tier="leader"), "z1", "tier 'leader'"),
    ("cloud", "aaa", "scmr/drivable/cloud/aaa/r1", _reply(served_by="aaa"), "z3", "does not let 'aaa' serve"),
    ("cloud", "r2", "scmr/drivable/cloud/r2/r1", _reply(served_by="r2"), "z2", "does not let 'r2' serve the cloud"),
    ("peer", "leader0", "scmr/drivable/peer/leader0/r1", _reply(served_by="leader0", tier="peer"), "z2",
     "certificate of 'r2'"),  # r2 answering on leader0's key
])
def test_a_reply_must_come_from_the_node_and_tier_it_was_sent_to(robot, tier, node, key, msg, zid, problem):
    got = robot._reply_problem({"tier": tier, "node": node}, key, msg, _zreply(zid))
    if problem is None:
        assert got is None
    else:
        assert got is not None
        import re

        assert re.search(problem, got), got


def test_the_live_view_ignores_tokens_of_nodes_the_fleet_does_not_let_serve(robot):
    for key in ("scmr/alive/cloud/aaa", "scmr/alive/cloud/r2", "scmr/alive/leader/r1", "scmr/alive/peer/r1",
                "scmr/alive/cloud/cloud0", "scmr/alive/leader/r2", "scmr/alive/peer/leader0"):
        robot.view.on_liveliness(NS(key_expr=key, kind=zenoh.SampleKind.PUT))
    snap = robot.view.snapshot()
    assert snap.cloud == ("cloud0",) and snap.leader == ("r2",) and snap.peer == ("leader0",)


def test_a_candidacy_counts_only_on_its_own_key(robot):
    from scmr_mesh.mesh.election import Candidacy

    forged = Candidacy("leader0", term=99, leading=True).to_message()
    robot.view.on_candidate(NS(key_expr="scmr/r2r/candidate/r2", payload=NS(to_bytes=lambda: wire.encode(forged))))
    assert "leader0" not in robot.view._cands
    robot.view.on_candidate(NS(key_expr="scmr/r2r/candidate/leader0", payload=NS(to_bytes=lambda: wire.encode(forged))))
    assert robot.view._cands["leader0"].term == 99


@pytest.mark.timeout(120)
def test_a_lying_cloud_with_a_real_certificate_is_counted_and_never_used(tmp_path):
    """Issue 25 item 8, with real processes: ``cloud0`` (its own certificate, the fleet's rules) answers
    a real ``scmr robot``'s frames with an earlier reply for the same robot and seq but another frame
    (a replay from the robot's last run) and with replies whose seq is off by 1,000.  The robot takes
    none of them as a mask, counts all 24 against cloud0 and exits 1.  On the old code the 12 replays
    were taken (the reply was matched on robot and seq only) and the seq+1000 replies were plain
    ``bad_reply`` attempts, counted nowhere."""
    import json as _json
    import os
    import subprocess
    import sys
    from pathlib import Path

    from conftest import free_port

    from scmr_mesh import keys
    from scmr_mesh.mesh.security import secure_config
    from scmr_mesh.security.credentials import create_credentials
    from scmr_mesh.security.profile import SecurityProfile

    root = Path(__file__).resolve().parents[1]
    creds = tmp_path / "certs"
    create_credentials(creds, "cloud0,robot1")
    port = free_port()
    conf = secure_config(SecurityProfile(kind="tls", credentials=creds, acl=True), identity="cloud0",
                         listen=[f"tcp/127.0.0.1:{port}"])
    asked: list[int] = []

    def lie(q) -> None:
        req = wire.decode(q.payload.to_bytes(), kind="request")
        asked.append(req["seq"])
        if req["seq"] % 2 == 0:  # the reply this robot got for its frame `seq` in an earlier run
            old = wire.make_request(req["robot"], req["seq"], b"last run's frame " + bytes([req["seq"]]))
        else:
            old = dict(req, seq=req["seq"] + 1000)
        rep = wire.make_reply(old, mask_png=b"\x89PNG\r\n\x1a\n-stale-", shape=(225, 300), threshold=1, timings_ms={},
                              served_by="cloud0", tier="cloud", server_ms=0.1)
        q.reply(str(q.key_expr), wire.encode(rep))

    with zenoh.open(conf) as s:
        keep = [s.liveliness().declare_token(keys.alive("cloud", "cloud0")),
                s.declare_queryable(keys.drivable_request("cloud", "cloud0", "robot1"), lie, complete=True)]
        out = tmp_path / "robot1"
        proc = subprocess.run(
            [sys.executable, "-m", "scmr_mesh", "robot", "--id", "robot1", "--security",
             str(root / "peers" / "secure" / "mtls.toml"), "--credentials", str(creds),
             "--connect", f"tls/127.0.0.1:{port}", "--synthetic", "stub", "--count", "24", "--rate", "100",
             "--no-local-fallback", "--deadline-ms", "2000", "--wait-ms", "30000", "--drain-s", "0", "--out", str(out),
             "--quiet"],
            capture_output=True, text=True, timeout=100, env={**os.environ, "PYTHONPATH": str(root)})
        del keep
    recs = [_json.loads(line) for line in (out / "records.jsonl").read_text().splitlines()]
    assert sorted(asked) == list(range(24)), (asked, proc.stderr[-2000:])
    assert [r["ok"] for r in recs] == [False] * 24, proc.stderr[-2000:]
    assert not list((out / "inbox").glob("*.mask.png"))  # no stale map was driven on
    assert all([a["outcome"] for a in r["attempts"]] == ["mismatched"] and r["mismatched"] == 1 for r in recs)
    assert "another frame" in recs[0]["attempts"][0]["message"] and "frame 1001" in recs[1]["attempts"][0]["message"]
    summary = _json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["mismatched"] == 24 and summary["mismatched_by_node"] == {"cloud/cloud0": 24}
    assert proc.returncode == 1 and "24 replies did not answer the request they came for" in proc.stderr
