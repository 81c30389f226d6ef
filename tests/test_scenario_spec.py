"""Scenario files: the shipped ones validate; each kind of bad field is a ConfigError naming file, field, fix."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import pytest

from scmr_mesh.errors import ConfigError
from scmr_mesh.scenario.spec import Expectation, load_scenario, parse_scenario

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted((REPO / "peers" / "scenarios").glob("*.toml"))

GOOD = {
    "name": "t", "seed": 1, "duration_s": 10,
    "image_sets": {"s1": ["images/a.png"]},
    "fleet": {"robots": [{"id": "robot1", "image_set": "s1"}, {"id": "robot2", "synthetic": "stub"}]},
    "faults": [{"kind": "link_down", "at_s": 1, "for_s": 2, "link": ["robot1", "cloud"]},
               {"kind": "crash", "at_s": 2, "for_s": 1, "peer": "cloud"}],
    "expectations": [{"metric": "ror", "op": ">=", "value": 1.0}],
}


def test_shipped_scenarios_are_the_six_and_valid():
    names = {p.stem for p in SHIPPED}
    multihop = {"tunnel-chain", "relay-loss", "mine-mobility"}
    assert names == {"baseline", "cloud-link-drop", "cloud-crash", "partition", "flapping-link", "bandwidth-sweep",
                     "leader-crash", "split-fleet", "gossip-discovery", "cascade"} | multihop
    for p in SHIPPED:
        sc = load_scenario(p)
        assert sc.name == p.stem
        if p.stem in multihop:  # the multi-hop tier (issue 22): routers on a radio topology, real mine frames
            assert sc.shape == "routers" and sc.radio is not None
            assert all(len(sc.image_sets[r.image_set]) == 5 for r in sc.robots)
            continue
        assert sc.shape == "clique"
        # Table 4.2: four robots with five images each
        assert len(sc.robots) == 4
        assert all(len(sc.image_sets[r.image_set]) == 5 for r in sc.robots)


def test_defaults_links_and_roles():
    sc = parse_scenario(GOOD)
    assert sc.peer_names == ("cloud", "leader", "robot1", "robot2")
    assert ("robot1", "cloud") in sc.links and ("leader", "cloud") in sc.links
    assert sc.role("leader") == "leader" and sc.role("robot2") == "robot"
    assert [f.kind for f in sc.faults] == ["link_down", "crash"]
    assert sc.faults[0].end_s == 3.0


def _mut(path, value=None, delete=False):
    d = copy.deepcopy(GOOD)
    cur = d
    for k in path[:-1]:
        cur = cur[k]
    if delete:
        del cur[path[-1]]
    else:
        cur[path[-1]] = value
    return d


BAD = [
    # (mutated doc, field named in the message, words of the fix)
    (_mut(["seed"], delete=True), "(top level)", "add the missing field"),
    (_mut(["seed"], "x"), "seed", "type integer"),
    (_mut(["duration_s"], -1), "duration_s", "range"),
    (_mut(["bogus"], 1), "(top level)", "allowed here"),
    (_mut(["faults", 0, "kind"], "explode"), "faults[0].kind", "use one of"),
    (_mut(["faults", 0, "link"], delete=True), "faults[0]", "add the missing field"),
    (_mut(["faults", 0, "peer"], "cloud"), "faults[0]", "allowed here"),
    (_mut(["faults", 0, "link"], ["robot1", "mars"]), "faults[0].link", "use one of"),
    (_mut(["faults", 0, "link"], ["robot1", "robot2"]) | {"topology": {"links": [["robot1", "cloud"]]}},
     "faults[0].link", "topology.links"),
    (_mut(["fleet", "robots", 0, "bootstrap"], "mars"), "fleet.robots[0].bootstrap", "use one of"),
    (_mut(["fleet", "robots", 0, "bootstrap"], "robot1"), "fleet.robots[0].bootstrap", "another peer"),
    (_mut(["fleet", "robots", 0, "bootstrap"], "robot2") | {"fleet": {**GOOD["fleet"], "robots": [
        {**GOOD["fleet"]["robots"][0], "bootstrap": "robot2"}, {**GOOD["fleet"]["robots"][1], "bootstrap": "robot1"}]}},
     "fleet.robots[0].bootstrap", "ring"),
    (_mut(["faults", 0, "at_s"], 10), "faults[0].at_s", "below duration_s"),
    (_mut(["faults", 1, "for_s"], delete=True) | {"faults": GOOD["faults"] + [
        {"kind": "crash", "at_s": 5, "peer": "cloud"}, {"kind": "crash", "at_s": 6, "peer": "cloud"}]},
     "faults[3]", "first crash end"),
    (_mut(["faults"], [{"kind": "crash", "at_s": 1, "peer": "cloud"}, {"kind": "crash", "at_s": 0, "for_s": 0.5,
                                                                        "peer": "cloud"},
                       {"kind": "crash", "at_s": 1, "peer": "cloud"}]),  # found by Hypothesis: out of file order
     "faults[2]", "first crash end"),
    (_mut(["faults"], [{"kind": "partition", "at_s": 1, "groups": [["cloud", "robot1"], ["robot1"]]}]),
     "faults[0].groups", "disjoint"),
    (_mut(["fleet", "robots", 0, "image_set"], "nope"), "fleet.robots[0].image_set", "[image_sets]"),
    (_mut(["fleet", "robots", 1, "image_set"], "s1"), "fleet.robots[1]", "exactly one"),
    (_mut(["fleet", "robots", 1, "id"], "robot1"), "fleet", "own name"),
    (_mut(["fleet", "robots", 1, "id"], "Robot-2"), "fleet.robots[1].id", "lower-case"),
    (_mut(["expectations", 0, "op"], "=>"), "expectations[0].op", "use one of"),
    (_mut(["topology"], {"links": [["robot1", "robot1"]]}), "topology.links[0]", "two different peers"),
]


@pytest.mark.parametrize("doc,field,fix", BAD, ids=[f"{i}-{b[1]}" for i, b in enumerate(BAD)])
def test_bad_fields_name_file_field_and_fix(doc, field, fix):
    with pytest.raises(ConfigError) as ei:
        parse_scenario(doc, source="bad.toml")
    msg = str(ei.value)
    assert "bad.toml" in msg and f"'{field}'" in msg and fix in msg and "fix:" in msg


def test_load_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_scenario(tmp_path / "missing.toml")
    p = tmp_path / "broken.toml"
    p.write_text("name = \n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(p)


def test_expectation_ops():
    assert Expectation("ror", ">=", 1.0).holds(1.0)
    assert not Expectation("ror", ">=", 1.0).holds(0.99)
    assert Expectation("max_failover_gap_ms", "<=", 300).holds(299.9)
    assert not Expectation("max_failover_gap_ms", "<=", 300).holds(None)  # never measured: fails
    assert Expectation("leader_answers", "==", 0).name == "leader_answers == 0"


def test_cli_check_one_line_error_no_traceback(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('name = "x"\nseed = 1\nduration_s = 5\n[fleet]\nrobots = [{ id = "robot1" }]\n')
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "scenario", "check", str(p)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1
    assert r.stderr.startswith("scmr: error: scenario ") and "Traceback" not in r.stderr
    assert "fleet.robots[0]" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    ok = subprocess.run([sys.executable, "-m", "scmr_mesh", "scenario", "check", *map(str, SHIPPED)],
                        capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0 and ok.stdout.count(": ok - ") == len(SHIPPED)
