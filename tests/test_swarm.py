"""``scmr swarm``: several robots played by one process, each under its own identity (issue 23)."""

from __future__ import annotations

import json
import subprocess

import pytest

from scmr_mesh.cli import main
from scmr_mesh.scenario.plan import swarm_groups
from scmr_mesh.scenario.spec import parse_scenario
from test_fleet_e2e import STUB, kill_leftovers, scmr


def _scenario(faults=(), capable=()):
    return parse_scenario({"name": "t", "seed": 1, "duration_s": 5, "fleet": {"robots": [
        {"id": f"r{i}", "synthetic": "road", "leader_capable": f"r{i}" in capable} for i in range(1, 7)]},
        "faults": list(faults)})


def test_swarms_group_only_robots_no_fault_names_that_share_a_host():
    sc = _scenario([{"kind": "crash", "at_s": 1, "peer": "r2"},
                    {"kind": "link_down", "at_s": 1, "for_s": 1, "link": ["r4", "cloud"]}], capable=("r1",))
    assert swarm_groups(sc, 2, host_of=lambda p: "h") == [["r1"], ["r2"], ["r4"], ["r3", "r5"], ["r6"]]
    # each robot its own host (network namespaces): nothing to share
    assert swarm_groups(sc, 4) == [["r1"], ["r2"], ["r4"], ["r3"], ["r5"], ["r6"]]
    assert swarm_groups(_scenario(), 1, host_of=lambda p: "h") == [[f"r{i}"] for i in range(1, 7)]


@pytest.mark.parametrize("robots, says", [
    ([["--id", "a", "--synthetic", "stub", "--out", "o/a", "--insecure", "--leader-capable"]], "own process"),
    ([["--id", "a", "--synthetic", "stub", "--out", "o/a", "--insecure"]] * 2, "'a' twice"),
    ([["--id", "a", "--synthetic", "stub", "--out", "o/a", "--insecure", "--rate", "x"]], "member 1: --rate x: not a number"),
    ([["--id", "a", "--synthetic", "stub", "--out", "o/a"]], "--security"),
    ([], "at least one robot"),
])
def test_a_bad_swarm_plan_is_refused_before_anything_starts(tmp_path, capsys, robots, says):
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"robots": robots}))
    assert main(["swarm", "--plan", str(plan)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("scmr: error:") and says in err[0], err
    assert not (tmp_path / "o").exists()


@pytest.mark.timeout(150)
def test_a_secured_fleet_serves_robots_played_by_a_swarm(tmp_path):
    """Mutual TLS and the access rules are on: a member presenting another's certificate would be refused."""
    run_dir = tmp_path / "run"
    try:
        p = subprocess.run(scmr("up", "--robots", "3", "--leader-capable", "1", "--robots-per-process", "2",
                                "--duration", "2", "--run-dir", str(run_dir), *STUB),
                           capture_output=True, text=True, timeout=140)
        assert p.returncode == 0, (p.stdout[-2000:], p.stderr[-2000:])
        rep = json.loads((run_dir / "report.json").read_text())
        assert "swarm-r2" in rep["peers"] and "r2" not in rep["peers"] and "r3" not in rep["peers"]
        assert "r1" in rep["peers"]  # leader-capable: its own process
        assert json.loads((run_dir / "swarms" / "swarm-r2.json").read_text())["robots"][1][:2] == ["--id", "r3"]
        for rid in ("r2", "r3"):
            recs = [json.loads(x) for x in (run_dir / "robots" / rid / "records.jsonl").read_text().splitlines()]
            assert recs and all(r["ok"] and r["robot"] == rid for r in recs), recs[:3]
        assert rep["ror"] == 1.0 and rep["telemetry"]["lost"] == 0, rep["telemetry"]
        assert rep["peers"]["swarm-r2"]["exit"] == 0
        # each member is charged its share of the one process, not the whole process each
        hosts = rep["hosts"]["per_host"]
        assert hosts["r2"]["shared_by"] == hosts["r3"]["shared_by"] == 2 and "shared_by" not in hosts["r1"]
    finally:
        kill_leftovers(run_dir)
