"""Overload: the negotiated cloud answers "busy" at once, robots fall back to the leader.

Real processes: a cloud with a 150 ms stub service, one worker and ``--queue 0``; a
leader with the fast stub; three robots at 10 Hz (offered 30/s, cloud capacity ~6.7/s).
About 8 s.  Plus pure checks of the overload summary.
"""

from __future__ import annotations

import re

import pytest
from conftest import free_port

from scmr_mesh.bench.overload import summarize
from scmr_mesh.mesh.testing import (
    SLOW,
    STUB,
    read_records,
    spawn_peer,
    stop_peer,
    wait_for,
)


def _rec(ok, tor, outcomes):
    return {"ok": ok, "tor_ms": tor, "attempts": [{"outcome": o} for o in outcomes]}


def test_summary_counts_fairness_and_priority_shares():
    recs = {
        "a": [_rec(True, 900, ["ok"]), _rec(True, 10, ["ok"]), _rec(False, 1, ["error:busy"])],
        "b": [_rec(True, 20, ["ok"]), _rec(False, 2, ["error:busy"]), _rec(False, 1, ["error:busy"])],
        "c": [_rec(False, 1000, ["timeout"])],
    }
    s = summarize(recs, {"a": 10, "b": 0, "c": 0})
    assert (s["requests"], s["served"], s["rejected"], s["failed"]) == (7, 3, 3, 1)
    assert s["failures"] == {"timeout": 1}
    assert s["tor_admitted_ms"]["max"] == 10.0  # each robot's first request is left out
    assert s["by_priority"]["10"]["served_share"] == pytest.approx(2 / 3, abs=1e-3)
    assert s["by_priority"]["0"]["served_share"] == pytest.approx(1 / 4, abs=1e-3)
    assert s["jain_all"] == pytest.approx((2 + 1 + 0) ** 2 / (3 * (4 + 1 + 0)), abs=1e-4)


def test_busy_is_explicit_and_robots_fall_back_at_once(tmp_path):
    pc, pl = free_port(), free_port()
    cloud_ep, leader_ep = f"tcp/127.0.0.1:{pc}", f"tcp/127.0.0.1:{pl}"
    peers = []
    try:
        cloud = spawn_peer(["cloud", "--insecure", "--node", "c1", "--listen", cloud_ep, "--workers", "1", "--process", SLOW,
                            "--queue", "0", "--ready-file", str(tmp_path / "c.ready"),
                            "--ods", str(tmp_path / "ods.sqlite")],
                           log_path=tmp_path / "c.log", env={"SCMR_STUB_DELAY_MS": "150"})
        peers.append(cloud)
        leader = spawn_peer(["leader", "--insecure", "--node", "L", "--listen", leader_ep, "--connect", cloud_ep, "--workers", "1",
                             "--process", STUB, "--ready-file", str(tmp_path / "l.ready")],
                            log_path=tmp_path / "l.log")
        peers.append(leader)
        wait_for(lambda: (tmp_path / "c.ready").exists() and (tmp_path / "l.ready").exists()
                 or any(p.poll() is not None for p in peers), timeout=60, what="cloud and leader ready")
        assert all(p.poll() is None for p in peers), (tmp_path / "c.log").read_text()[-1500:]
        # a dedicated leader is ready serving the peer tier and takes the lead after its start-up
        # grace: robots sent before that found only a busy cloud (no leader to fall back to yet)
        wait_for(lambda: "leading (term" in (tmp_path / "l.log").read_text(), timeout=30, what="the leader leads")
        robots = []
        for k in range(3):
            robots.append(spawn_peer(
                ["robot", "--insecure", "--id", f"r{k}", "--connect", cloud_ep, "--connect", leader_ep, "--synthetic", "stub",
                 "--rate", "10", "--duration", "1.5", "--priority", str(10 * (k % 2)), "--no-local-fallback",
                 "--quiet", "--out", str(tmp_path / f"r{k}")],
                log_path=tmp_path / f"r{k}.log"))
        peers.extend(robots)
        wait_for(lambda: all(p.poll() is not None for p in robots), timeout=40, what="robots done")
        assert [p.returncode for p in robots] == [0, 0, 0]
    finally:
        for p in reversed(peers):
            stop_peer(p, timeout=5)
    records = [r for k in range(3) for r in read_records(tmp_path / f"r{k}" / "records.jsonl")]
    assert len(records) >= 10
    # every request answered: busy at the cloud sends it to the leader within the same request
    assert all(r["ok"] for r in records), [r["error"] for r in records if not r["ok"]]
    fell_back = [r for r in records
                 if [(a["tier"], a["outcome"]) for a in r["attempts"]] == [("cloud", "error:busy"), ("leader", "ok")]]
    by_cloud = [r for r in records if r["tier"] == "cloud"]
    assert fell_back and by_cloud
    # no request ever waited for a timeout: refusals are explicit replies; a request the cloud
    # admitted but took longer than the hedge delay to serve (its 150 ms service) was hedged to the
    # leader, and the slower copy is "superseded" (issue 24)
    outcomes = {a["outcome"] for r in records for a in r["attempts"]}
    assert outcomes <= {"ok", "error:busy", "superseded"}, outcomes
    assert all(r["hedged"] for r in records if any(a["outcome"] == "superseded" for a in r["attempts"]))
    # the busy message states the queue's bound: waiting + in service <= queue + workers
    for r in fell_back:
        msg = r["attempts"][0]["message"]
        m = re.search(r"\((\d+) waiting, (\d+) in service, queue (\d+)\)", msg)
        assert m, msg
        waiting, serving, queue = map(int, m.groups())
        assert queue == 0 and waiting + serving <= queue + 1
