"""``scmr up --profiles``: Table 4.3 profiles dealt to robots, energy placement on, energy in the summary."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from scmr_mesh.energy.measure import energy_by_robot
from scmr_mesh.errors import InputError
from scmr_mesh.fleet.output import format_energy, format_summary
from scmr_mesh.fleet.plan import TABLE_4_3_ROBOTS, FleetConfig, plan_fleet, robot_ids, robot_profiles


def _ports(config: FleetConfig) -> dict[str, int]:
    names = ["cloud", "leader", *robot_ids(config.robots)]
    return {n: 7000 + i for i, n in enumerate(names)}


def _flag(argv: list[str], flag: str) -> str | None:
    return argv[argv.index(flag) + 1] if flag in argv else None


def test_profiles_are_dealt_round_robin_and_turn_on_the_energy_policy(tmp_path):
    cfg = FleetConfig(robots=6, profiles=TABLE_4_3_ROBOTS)
    specs = plan_fleet(cfg, tmp_path, _ports(cfg))
    got = {rid: _flag(specs[rid].argv, "--profile") for rid in robot_ids(6)}
    assert got == {"r1": "robot1", "r2": "robot2", "r3": "robot3", "r4": "robot4", "r5": "robot1", "r6": "robot2"}
    assert got == robot_profiles(cfg)
    assert _flag(specs["cloud"].argv, "--profile") is None


def test_without_profiles_no_robot_runs_the_energy_model(tmp_path):
    cfg = FleetConfig(robots=3)
    specs = plan_fleet(cfg, tmp_path, _ports(cfg))
    assert not any("--profile" in specs[r].argv for r in robot_ids(3))
    assert robot_profiles(cfg) == {}
    assert "not modelled" in format_energy(None)[0]


@pytest.mark.parametrize("kw, msg", [
    (dict(profiles=("robot9",)), "unknown profile 'robot9'"),
    (dict(bootstrap="nowhere"), "--bootstrap must name a peer"),
])
def test_config_check(kw, msg):
    with pytest.raises(InputError, match=msg):
        FleetConfig(robots=2, **kw).check()


def test_energy_by_robot_counts_where_tasks_ran_and_sums_energy():
    recs = [
        {"robot": "r1", "ok": True, "tier": "cloud", "energy_j": 1.5, "energy": {"planned_tier": "cloud"}},
        {"robot": "r1", "ok": True, "tier": "leader", "energy_j": 2.0, "energy": {"planned_tier": "cloud"}},
        {"robot": "r1", "ok": True, "tier": "local", "energy_j": 4.0,
         "energy": {"planned_tier": "local", "deadline_missed": True, "probe": False}},
        {"robot": "r1", "ok": False, "tier": None, "energy_j": 0.5, "energy": {"planned_tier": "cloud"}},
        {"robot": "r2", "ok": True, "tier": "cloud"},  # no energy_j: counted, not costed
        {"robot": "r9", "ok": True, "tier": "cloud", "energy_j": 99.0},  # no profile: ignored
    ]
    e = energy_by_robot(recs, {"r1": "robot1", "r2": "robot2"})
    assert e["r1"]["total_j"] == pytest.approx(8.0)
    assert {t: v["tasks"] for t, v in e["r1"]["ran"].items()} == {"cloud": 1, "leader": 1, "local": 1, "failed": 1}
    assert e["r1"]["ran"]["local"]["energy_j"] == 4.0
    assert e["r1"]["planned_elsewhere"] == 2 and e["r1"]["deadline_missed"] == 1
    assert e["r2"] == {"profile": "robot2", "total_j": 0.0, "tasks": 1, "ran": {"cloud": {"tasks": 1, "energy_j": 0.0}},
                       "planned_elsewhere": 0, "deadline_missed": 0, "probes": 0, "costed": 0}
    lines = format_energy({"placement": "energy model", "per_robot": e})
    assert "r1" in lines[1] and "8.00 J" in lines[1] and "local 1 (4.00 J)" in lines[1]
    assert "2 ran elsewhere than planned" in lines[1]
    assert "1 not costed" in lines[2]


STUB = ["--synthetic", "stub", "--server-arg=--process", "--server-arg=scmr_mesh.mesh.testing:stub_process", "--quiet"]


@pytest.mark.timeout(120)
def test_up_with_profiles_reports_energy_per_robot(tmp_path):
    run_dir = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "up", "--robots", "2", "--profiles", "--duration", "3",
                        "--rate", "4", "--run-dir", str(run_dir), *STUB],
                       capture_output=True, text=True, timeout=110)
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.loads((run_dir / "report.json").read_text())
    per = rep["energy"]["per_robot"]
    assert {k: v["profile"] for k, v in per.items()} == {"r1": "robot1", "r2": "robot2"}
    for rid, e in per.items():
        assert e["tasks"] == rep["per_robot"][rid]["requests"] > 0
        assert e["costed"] == e["tasks"] and e["total_j"] > 0  # every record carried the robot's energy_j
    assert "robot1" in r.stdout and " J " in r.stdout
    assert "energy (" in format_summary(rep)
    # each robot ran its energy policy (its records say how each was costed)
    rec = json.loads((run_dir / "robots" / "r1" / "records.jsonl").read_text().splitlines()[0])
    assert rec["energy"]["profile"] == "robot1" and "energy_j" in rec
    assert Path(rep["run_dir"]) == run_dir
