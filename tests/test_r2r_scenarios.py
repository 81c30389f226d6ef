"""The shipped R2R scenarios, run for real (stub processing, so the mesh is what is measured).

netns: a silent drop of the leader and a split fleet (kernel blackhole routes
between namespaces); proxy: the gossip-discovery and leader-crash files.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import pytest

from scmr_mesh.scenario.report import build_report
from scmr_mesh.scenario.runner import run_scenario
from scmr_mesh.scenario.spec import load_scenario, parse_scenario

ROOT = Path(__file__).resolve().parents[1]
STUB = "scmr_mesh.mesh.testing:stub_process"

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces need root")


def _run(sc, backend, tmp_path):
    res = run_scenario(sc, backend=backend, out_dir=tmp_path, ready_timeout=120)
    rep = build_report(sc, res.records, res.metric_faults(), t0_unix_ns=res.t0_unix_ns, backend=backend,
                       notes=res.notes, telemetry=res.telemetry, leadership=res.leadership(),
                       topology=res.topology)
    return res, rep


def _shipped(name: str, *, faults_at: dict[int, dict] | None = None, **changes):
    """A shipped scenario with the stub service; ``faults_at``: fault index -> fields to change."""
    sc = load_scenario(ROOT / "peers" / "scenarios" / f"{name}.toml")
    if faults_at:
        changes["faults"] = tuple(dataclasses.replace(f, **faults_at.get(i, {})) for i, f in enumerate(sc.faults))
    return dataclasses.replace(sc, process=STUB, **changes)


# The proxy backend relays every link through Python threads of this process.  With its
# threads polling, a blackholed cloud's links held the GIL so long under stress-ng --cpu 2 that
# every link missed even a 1 s lease and the lead flapped; they now wait on events and 11 of 11
# runs under stress held with the shipped 150 ms lease as well as with 1 s.  The tests keep a 1 s
# lease as margin: what they check does not depend on it (a crash closes TCP, seen at once).
PROXY_LEASE_MS = 1000
# Expectations that are timing targets (a deadline, a budget): measured by `scmr bench scenario`,
# not asserted by tests, which check what must happen whatever the machine's load.
# (A starved robot may compute a frame locally when every tier answers busy over its 60 ms
# budget, or while its links flap: the admission rule and the fallback working, not a loss.)
TIMING = {"local_answers", "max_succession_ms", "max_failover_gap_ms", "max_failback_gap_ms", "tor_p50_ms",
          "tor_p99_ms", "max_leader_wait_ms", "converged_after_heal_ms"}


def _behaviour_held(rep) -> None:
    checked = [e for e in rep["expectations"] if e["metric"] not in TIMING]
    assert checked and not [e for e in checked if not e["held"]], [e for e in checked if not e["held"]]


@pytest.mark.netns
@needs_root
def test_silent_drop_of_the_leader_passes_the_lead(tmp_path):
    sc = parse_scenario({
        "name": "leader-drop", "seed": 21, "duration_s": 8, "lease_ms": 200, "process": STUB,
        "fleet": {"clouds": [], "robots": [
            {"id": "robot1", "synthetic": "stub", "rate_hz": 5, "leader_capable": True, "capability": "robot4"},
            {"id": "robot2", "synthetic": "stub", "rate_hz": 5, "leader_capable": True, "capability": "robot3"},
            {"id": "robot3", "synthetic": "stub", "rate_hz": 5}]},
        "faults": [{"kind": "partition", "at_s": 3.0, "groups": [["leader"], ["robot1", "robot2", "robot3"]]}],
    })
    res, rep = _run(sc, "netns", tmp_path)
    lead = rep["leadership"]
    moves = [c for c in lead["changes"] if c["from"] is not None]
    assert moves and moves[0]["from"] == "leader" and moves[0]["to"] == "robot1", lead
    assert moves[0]["cause"] == "link"
    assert moves[0]["succession_ms"] is not None and moves[0]["succession_ms"] > 0
    assert rep["summary"]["ror"] == 1.0
    # the lead moved on the robots' side: after the cut robot3 no longer asks the old leader and
    # asks robot1 as its leader.  A request may go to the spare peer first: default_placement does
    # that while robot1 reports itself saturated, which a stub service on a loaded box does now and
    # then (a fresh clone's quiet run: 6 of 10 such requests at t_cut + 1.5-3.5 s; 2 of 10 in 1 run
    # of 8 alone), so how many go each way is the machine's, not a check.
    t_cut = res.faults[0].start_unix_ns  # when the cut was applied
    late = [r for r in res.records if r["robot"] == "robot3" and t_cut + 1.5e9 < r["sent_unix_ns"] < t_cut + 3.5e9]
    assert late and all(r["served_by"] in ("robot1", "robot2") and r["tier"] in ("leader", "peer") for r in late)
    asked = [(a["tier"], a["node"]) for r in late for a in r["attempts"]]
    assert ("leader", "robot1") in asked, asked
    assert not [t for t in asked if t[1] == "leader"], asked
    # peers served the gap: no frame computed alone while both candidates were sending (at the
    # end, the leading robot's own frames run out and it leaves the tier; a robot still sending
    # then may compute its last frame alone until the other candidate takes the lead)
    t_first_done = min(max(r["sent_unix_ns"] for r in res.records if r["robot"] == c) for c in ("robot1", "robot2"))
    assert [r for r in res.records if r["tier"] == "local" and r["sent_unix_ns"] <= t_first_done] == []


@pytest.mark.netns
@needs_root
def test_split_fleet_elects_on_both_sides_and_one_leader_remains(tmp_path):
    # the shipped timeline compressed (15 s: split 4 s to 10 s): 3 s with one leader, 4 s split
    # (robot3 elects within a lease of 150 ms), 3 s after the heal to converge (2 s expected)
    sc = _shipped("split-fleet", duration_s=10.0, faults_at={0: {"at_s": 3.0, "for_s": 4.0}})
    res, rep = _run(sc, "netns", tmp_path)
    lead = rep["leadership"]
    during = [c for c in lead["changes"] if c["cause"] == "link"]
    assert during and during[0]["to"] == "robot3", lead  # the side without the leader elected its own
    assert len(lead["leaders_at_end"]) == 1, lead
    assert lead["converged_after_heal_ms"] is not None
    assert [c for c in lead["changes"] if c["cause"] == "heal"], lead
    assert rep["summary"]["ror"] == 1.0


def test_gossip_discovery_hands_each_robot_only_its_bootstrap(tmp_path):
    sc = _shipped("gossip-discovery", duration_s=10.0, lease_ms=PROXY_LEASE_MS, faults_at={0: {"at_s": 4.0}})
    res, rep = _run(sc, "proxy", tmp_path)
    handed = json.loads((tmp_path / "peers.json").read_text())

    def opt(argv, flag):
        return [argv[i + 1] for i, a in enumerate(argv) if a == flag]

    listen = {name: opt(argv, "--listen") for name, argv in handed.items()}
    for r in sc.robots:
        connect = opt(handed[r.id], "--connect")
        assert connect == listen[r.bootstrap], (r.id, connect, r.bootstrap)  # one endpoint: its bootstrap
    assert rep["topology"]["robot3"]["connect"] == ["robot2"]
    # every robot was served by the leader it found by gossip while the cloud was down (4 s to 8 s)
    t_crash = res.faults[0].start_unix_ns  # when the SIGKILL was sent
    for r in sc.robots:
        after = [x for x in res.records if x["robot"] == r.id and t_crash + 1e9 < x["sent_unix_ns"] < t_crash + 3.5e9]
        assert after and {x["tier"] for x in after} == {"leader"}, (r.id, {x["tier"] for x in after})
    _behaviour_held(rep)


def test_leader_crash_scenario_on_the_proxy_backend(tmp_path):
    # the shipped timeline compressed (14 s: cloud cut 3 s to 11 s, leader crash at 7 s): the cloud
    # is cut at 2 s, the leader serves 2.5 s and crashes, robot1 leads 3.5 s, the cloud is back 2.5 s
    sc = _shipped("leader-crash", lease_ms=PROXY_LEASE_MS, duration_s=10.5,
                  faults_at={0: {"at_s": 2.0, "for_s": 6.0}, 1: {"at_s": 4.5}})
    res, rep = _run(sc, "proxy", tmp_path)
    _behaviour_held(rep)
    crash = [c for c in rep["leadership"]["changes"] if c["cause"] == "crash"]
    assert crash and crash[0]["from"] == "leader" and crash[0]["to"] == "robot1"
    assert any("gossip off" in n for n in res.notes)  # link faults: every pair through its own proxy
