"""Scenario reports count telemetry like the fleet report (docs/DATA.md, "Reports").

A real scenario on the proxy backend (no root): cloud, leader and two robots with the
stub service; the cloud is SIGKILLed for 1.5 s and restarted, so some telemetry goes
through the leader's relay.  The runner counts the data tier while the servers still
run; the report JSON and Markdown carry ``{"telemetry": {"sent", "stored",
"duplicates", "lost", "per_robot"}}``.  About 20 s.
"""

from __future__ import annotations

import json

from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.scenario.spec import parse_scenario


def test_scenario_report_counts_telemetry(tmp_path):
    from scmr_mesh.scenario.report import build_report, markdown, write_report
    from scmr_mesh.scenario.runner import run_scenario

    sc = parse_scenario({
        "name": "telemetry", "seed": 3, "duration_s": 5, "lease_ms": 300,
        "process": "scmr_mesh.mesh.testing:stub_process",
        "fleet": {"robots": [{"id": "robot1", "synthetic": "stub", "rate_hz": 6, "local_fallback": False},
                             {"id": "robot2", "synthetic": "stub", "rate_hz": 4, "local_fallback": False}]},
        "faults": [{"kind": "crash", "at_s": 1.5, "for_s": 1.5, "peer": "cloud"}],
    })
    res = run_scenario(sc, backend="proxy", out_dir=tmp_path, ready_timeout=90)
    tel = res.telemetry
    assert tel is not None, "the runner did not count telemetry"
    assert set(tel["per_robot"]) == {"robot1", "robot2"}
    # cross-check against the robots' own summaries and the store itself
    with OperationalDataStore(tmp_path / "ods.sqlite", readonly=True) as ods:
        for rid, row in tel["per_robot"].items():
            summary = json.loads(next((tmp_path / "robots").glob(f"{rid}*/telemetry.json")).read_text())
            assert row["sent"] == summary["sent"] > 0
            assert row["stored"] == len([s for s in ods.seqs(rid) if s <= row["sent"]])
            assert row["lost"] == row["sent"] - row["stored"]
        # the leader took records during the outage (relayed; robots keep them until a cloud
        # stores them, so whichever copy reached the cloud first was stored, once)
        assert {r["received_from"] for r in ods.range()} <= {"cloud", "leader"}
    acked = [json.loads(p.read_text())["acked_by"]["leader"] for p in (tmp_path / "robots").glob("*/telemetry.json")]
    assert sum(acked) > 0
    assert tel["sent"] == sum(r["sent"] for r in tel["per_robot"].values())
    assert tel["lost"] == 0, tel  # nothing lost across the cloud crash (leader relay + replay)
    assert json.loads((tmp_path / "telemetry.json").read_text()) == tel

    # robots start on OUT/ready/run.start, written at t0 (every robot ready)
    assert res.records and min(r["sent_unix_ns"] for r in res.records) >= res.t0_unix_ns
    assert max(r["sent_unix_ns"] for r in res.records) <= res.t0_unix_ns + sc.duration_s * 1e9

    # the report: passed in, or picked up from the run's telemetry.json by write_report
    rep = build_report(sc, res.records, res.metric_faults(), t0_unix_ns=res.t0_unix_ns, backend="proxy",
                       telemetry=tel)
    assert rep["telemetry"] == tel
    md = markdown(rep)
    assert "## Telemetry (data tier)" in md
    assert f"| robot1 | {tel['per_robot']['robot1']['sent']} | {tel['per_robot']['robot1']['stored']} |" in md
    plain = build_report(sc, res.records, res.metric_faults(), t0_unix_ns=res.t0_unix_ns, backend="proxy")
    assert plain["telemetry"] is None and "## Telemetry" not in markdown(plain)
    paths = write_report(plain, tmp_path)
    assert json.loads(paths["json"].read_text())["telemetry"] == tel
    assert "## Telemetry (data tier)" in paths["md"].read_text()


def test_the_count_waits_for_relayed_records_only_while_a_cloud_runs(tmp_path, monkeypatch):
    """Only a cloud stores records: with the leader alive and no cloud (none in the fleet, or all
    down at the end) the count does not wait (it waited 5 s for records that could not arrive)."""
    from scmr_mesh.data import report
    from scmr_mesh.scenario import runner

    waits = []
    monkeypatch.setattr(report, "fleet_telemetry", lambda *_a, wait, ods: waits.append(wait) or None)

    class Proc:
        def __init__(self, up):
            self.up = up

        def alive(self):
            return self.up

    class Sup:
        procs = {"leader": Proc(True), "cloud": Proc(False)}

    sc = parse_scenario({"name": "t", "seed": 1, "duration_s": 1,
                         "fleet": {"robots": [{"id": "robot1", "synthetic": "stub"}]}})
    names = {"leader": "leader", "cloud": "cloud"}
    runner._count_telemetry(tmp_path, sc, Sup(), names)
    Sup.procs["cloud"].up = True
    runner._count_telemetry(tmp_path, sc, Sup(), names)
    assert waits == [False, True]


def test_settling_waits_only_for_records_a_leader_may_hold(tmp_path, monkeypatch):
    """After the robots stopped, only records relayed to a leader can still reach the store: a robot
    that exited holding records it never relayed (no path to any server) is not waited for."""
    import time

    from scmr_mesh.data.report import settle_telemetry

    class Waited(Exception):
        pass

    def no_sleep(_s):
        raise Waited

    summary = tmp_path / "robots" / "r1" / "telemetry.json"
    summary.parent.mkdir(parents=True)
    monkeypatch.setattr(time, "sleep", no_sleep)
    for relayed, waits in ((0, False), (3, True)):
        summary.write_text(json.dumps({"sent": 5, "queued": 5, "lost": 0, "relayed_unstored": relayed}))
        try:
            tel = settle_telemetry(tmp_path, ["r1"], timeout_s=60)["telemetry"]
        except Waited:
            assert waits, relayed
        else:
            assert not waits and tel["sent"] == 5 and tel["stored"] == 0, (relayed, tel)


def test_a_robots_summary_from_an_earlier_life_is_removed_when_its_agent_starts(tmp_path):
    """A robot that exited cleanly (telemetry.json: relayed_unstored 0), then restarted in the same
    folder and killed, must not leave that old 0 for the run's telemetry count to read: it would stop
    waiting for the records a leader still holds (review of the settling change)."""
    from scmr_mesh.data.report import _leader_may_hold
    from scmr_mesh.mesh.commands import stale_telemetry_summary

    out = tmp_path / "robots" / "r1"
    out.mkdir(parents=True)
    (out / "telemetry.json").write_text('{"relayed_unstored": 0, "sent": 3}\n')
    assert _leader_may_hold(tmp_path, ["r1"]) is False  # what the old summary says
    stale_telemetry_summary(out)  # what the robot's start now does (commands._data_agent)
    assert not (out / "telemetry.json").exists() and _leader_may_hold(tmp_path, ["r1"]) is True
    stale_telemetry_summary(out)  # none there: nothing to do
