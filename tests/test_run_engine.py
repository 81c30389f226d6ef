"""The one run engine (issue 21): fleets are scenarios, one command-line builder, one fault type.

Pure checks (no processes) of what ``scmr up``/``scmr demo`` hand the scenario
engine, plus the loopback backend's refusal of link faults from the CLI.  <2 s.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, strategies as st

from scmr_mesh.errors import ScenarioError
from scmr_mesh.fleet import FleetConfig, plan_fleet
from scmr_mesh.fleet.plan import fleet_options, fleet_scenario
from scmr_mesh.qos.faults import FaultRecord
from scmr_mesh.scenario.loopback import LoopbackBackend, free_ports
from scmr_mesh.scenario.plan import PEER_DIALS_CFG, compile_timeline, peer_command
from scmr_mesh.scenario.report import request_rows, run_problems
from scmr_mesh.scenario.runner import fault_tier
from scmr_mesh.scenario.spec import WHOEVER_LEADS, Fault, parse_scenario
from scmr_mesh.vocab import Tier


def test_cloud_outage_is_a_crash_of_every_cloud_node_restarted_at_its_end():
    sc = fleet_scenario(FleetConfig(robots=2, clouds=3, cloud_outage=(6, 10), duration_s=20))
    (f,) = sc.faults
    assert (f.kind, f.at_s, f.end_s, f.crashed) == ("crash", 6.0, 10.0, ("cloud", "cloud1", "cloud2"))
    events = [(e.at_s, e.op, e.target) for e in compile_timeline(sc)]
    assert events == [(6.0, "kill", ("cloud",)), (6.0, "kill", ("cloud1",)), (6.0, "kill", ("cloud2",)),
                      (10.0, "start", ("cloud",)), (10.0, "start", ("cloud1",)), (10.0, "start", ("cloud2",))]
    assert fault_tier(sc, f) == ("cloud", None)


def test_kill_cloud_and_leader_crash_stay_down():
    sc = fleet_scenario(FleetConfig(robots=3, clouds=2, kill_cloud=(1, 5), leader_crash_s=8, duration_s=20))
    kill, lead = sc.faults
    assert kill.crashed == ("cloud1",) and not kill.restart and kill.end_s is None
    assert lead.crashed == (WHOEVER_LEADS,) and not lead.restart
    assert [e.op for e in compile_timeline(sc)] == ["kill", "kill"]  # no restart at the end of the run
    assert fault_tier(sc, kill) == (None, None)  # the other cloud node still serves: no tier lost
    assert fault_tier(sc, lead) == ("leader", None)
    one = fleet_scenario(FleetConfig(robots=1, kill_cloud=(0, 2), duration_s=5))
    assert fault_tier(one, one.faults[0]) == ("cloud", None)  # the only cloud node: the tier is gone


def test_fleet_peers_keep_their_names_and_run_as_nodes():
    cfg = FleetConfig(robots=3, clouds=2, leader_capable=1, profiles=("robot2",))
    sc = fleet_scenario(cfg)
    assert [p.name for p in sc.peers] == ["cloud", "cloud1", "leader", "r1", "r2", "r3"]
    assert [sc.node_of(p.name) for p in sc.peers] == ["cloud0", "cloud1", "leader0", "r1", "r2", "r3"]
    assert sc.peer_of("leader0") == "leader" and sc.peer_of("r2") == "r2"
    r1, r2, _ = sc.robots
    assert r1.leader_capable and r1.capability == "robot4" and not r2.leader_capable
    assert r2.profile == "robot2" and r2.energy_placement
    assert all(b == ("cloud",) for n, b in sc.bootstraps.items() if n not in ("cloud",))
    # each also dials every peer started before it (zenoh re-dials only those after a cut)
    assert sc.dials("r2") == ("cloud", "cloud1", "leader", "r1") and sc.dials("cloud1") == ("cloud",)
    # every pair is dialled by its later peer, so gossip dials no peer (two links per pair otherwise)
    assert sc.dials_every_pair and PEER_DIALS_CFG in peer_command(sc, "r1", run_dir=Path("run")).argv
    chain = parse_scenario({"name": "c", "seed": 1, "duration_s": 5, "fleet": {"robots": [
        {"id": "robot1", "synthetic": "road"}, {"id": "robot2", "synthetic": "road", "bootstrap": "robot1"}]}})
    assert not chain.dials_every_pair and chain.dials("robot2") == ("robot1",)
    assert PEER_DIALS_CFG not in peer_command(chain, "robot1", run_dir=Path("run")).argv  # gossip links it


def test_scmr_up_and_the_engine_build_the_same_command_lines(tmp_path):
    """plan_fleet (what the tests and docs show) is the engine's builder on loopback ports."""
    cfg = FleetConfig(robots=2, lease_ms=250, workers=1, server_args=["--process", "m:f"], robot_args=["--x"])
    ports = {"cloud": 7001, "leader": 7002, "r1": 7003, "r2": 7004}
    specs = plan_fleet(cfg, tmp_path, ports)
    sc, opts = fleet_scenario(cfg), fleet_options(cfg)
    for name, spec in specs.items():
        cmd = peer_command(sc, name, run_dir=tmp_path, listen=[f"tcp/127.0.0.1:{ports[name]}"],
                           connect=[f"tcp/127.0.0.1:{ports[b]}" for b in sc.dials(name)], options=opts)
        assert list(cmd.argv) == list(spec.argv) and cmd.log_path == spec.log_path
    r2 = specs["r2"].argv
    assert r2[-1] == "--x" and "--start-file" in r2 and r2[r2.index("--start-file") + 1].endswith("fleet.ready")
    assert "-v" in r2 and "--quiet" not in r2 and "--seed" not in r2  # scmr up's robots log each request


def test_a_restart_is_renamed_in_scenarios_and_keeps_its_name_in_fleets(tmp_path):
    sc = parse_scenario({"name": "t", "seed": 1, "duration_s": 5,
                         "fleet": {"robots": [{"id": "robot1", "synthetic": "road"}]}})
    assert peer_command(sc, "cloud", run_dir=tmp_path, start=2).name == "cloud-2"
    fleet = fleet_scenario(FleetConfig(robots=1))
    again = peer_command(fleet, "cloud", run_dir=tmp_path, start=2, options=fleet_options(FleetConfig(robots=1)))
    assert again.name == "cloud" and again.log_path == tmp_path / "logs" / "cloud.log"


def test_the_loopback_backend_refuses_link_faults_in_one_line():
    sc = parse_scenario({"name": "cut", "seed": 1, "duration_s": 5,
                         "fleet": {"robots": [{"id": "robot1", "synthetic": "road"}]},
                         "faults": [{"kind": "link_down", "at_s": 1, "link": ["robot1", "cloud"]}]})
    with pytest.raises(ScenarioError, match=r"loopback backend cannot cut or shape links \(link_down "
                                            r"robot1-cloud @1s\); run it with --backend netns \(root\) or --backend proxy"):
        LoopbackBackend(sc)
    crash = parse_scenario({"name": "crash", "seed": 1, "duration_s": 5,
                            "fleet": {"robots": [{"id": "robot1", "synthetic": "road"}]},
                            "faults": [{"kind": "crash", "at_s": 1, "for_s": 1, "peer": "cloud"}]})
    be = LoopbackBackend(crash)
    # its bootstrap, then the peers started before it: zenoh re-dials only those after a cut
    assert be.connect("robot1") == [be.endpoint("cloud"), be.endpoint("leader")]
    assert be.connect_names("robot1") == ["cloud", "leader"]


def test_scenario_run_on_loopback_with_a_link_fault_is_one_error_line(tmp_path):
    sc = tmp_path / "cut.toml"
    sc.write_text('name = "cut"\nseed = 1\nduration_s = 5\n[fleet]\nrobots = [ { id = "robot1", synthetic = "road" } ]\n'
                  '[[faults]]\nkind = "link_down"\nat_s = 1\nlink = ["robot1", "cloud"]\n')
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "scenario", "run", str(sc), "--backend", "loopback",
                        "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("scmr: error:")]
    assert len(errors) == 1 and "loopback backend cannot cut or shape links" in errors[0], r.stderr


def test_free_ports_are_distinct():
    ports = free_ports([f"p{i}" for i in range(20)])
    assert len(set(ports.values())) == 20


def test_free_ports_lie_outside_the_ephemeral_range():
    """A robot's port once went to a link proxy's ``bind(0)`` or an outgoing connection before the
    robot bound it (both draw from the ephemeral range): the ports are picked outside it."""
    from scmr_mesh.ports import _ephemeral_range

    lo, hi = _ephemeral_range()
    if lo - 10000 < 1000 and hi > 64535:
        pytest.skip(f"this host's ephemeral range {lo}-{hi} leaves no room outside it (bind(0) is used)")
    ports = free_ports([f"p{i}" for i in range(50)]).values()
    assert all(not lo <= p <= hi for p in ports)


def test_a_fault_record_is_frozen_and_reads_like_its_json():
    f = FaultRecord("crash", "cloud0,cloud1", start_unix_ns=10, end_unix_ns=20, tier="cloud",
                    killed=["cloud", "cloud1"], restarted=["cloud", "cloud1"], label="crash cloud,cloud1 @1s")
    assert f.tier is Tier.CLOUD and f["tier"] == "cloud" and f["killed"] == ["cloud", "cloud1"]
    assert dict(f)["restarted"] == ["cloud", "cloud1"] and "peer" not in f and f.get("groups") is None
    assert FaultRecord.from_mapping(f.as_dict()) == f
    with pytest.raises(AttributeError):
        f.end_unix_ns = 30  # type: ignore[misc]


@given(st.lists(st.sampled_from(["cloud", "cloud1", "cloud2", "leader", "r1"]), min_size=1, max_size=5, unique=True))
def test_a_group_crash_takes_the_cloud_tier_only_when_every_cloud_node_is_in_it(crashed):
    sc = fleet_scenario(FleetConfig(robots=1, clouds=3))
    tier, robots = fault_tier(sc, Fault("crash", at_s=1.0, peers=tuple(crashed)))
    if "leader" in crashed:
        assert tier == "leader"
    elif {"cloud", "cloud1", "cloud2"} <= set(crashed):
        assert tier == "cloud"
    else:
        assert tier is None
    assert robots is None


def test_problems_name_a_restart_that_never_came_up_but_not_a_healed_link():
    peers = {"cloud": {"exit": -9, "log": "c.log", "ready_unix_ns": 5},
             "cloud-2": {"exit": None, "log": "c2.log", "ready_unix_ns": None}}
    rep = {"started_unix_ns": 0, "peers": peers, "telemetry": {"sent": 1, "stored": 1, "lost": 0},
           "faults": [{"kind": "link_down", "target": "robot1-cloud", "start_unix_ns": 1, "end_unix_ns": 2},
                      {"kind": "crash", "target": "cloud", "start_unix_ns": 1_000_000_000,
                       "end_unix_ns": 2_000_000_000, "ready_unix_ns": None, "killed": ["cloud"],
                       "restarted": ["cloud-2"]}]}
    problems = run_problems(rep)
    assert problems == ["cloud was restarted at 2.00 s but never became ready; see c2.log"]


def test_request_rows_of_a_run_report_and_of_the_scenario_view():
    assert request_rows({"requests": 3, "request_log": [{"seq": 0}]}) == [{"seq": 0}]
    assert request_rows({"requests": [{"seq": 1}]}) == [{"seq": 1}]
    assert request_rows({"requests": 3}) == []
