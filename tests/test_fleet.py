"""Fleet planning, record following, report schema and output (no processes). <1 s."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from scmr_mesh.bench.mesh import bench_targets
from scmr_mesh.errors import InputError, MeshError
from scmr_mesh.fleet import (
    FleetConfig,
    RecordTail,
    check_ror,
    format_summary,
    parse_outage,
    plan_fleet,
    validate_report,
)
from scmr_mesh.qos import metrics


def test_plan_wires_robots_to_cloud_and_leader(tmp_path):
    cfg = FleetConfig(robots=3, duration_s=7, rate_hz=2.5, synthetic=["a", "b"], lease_ms=250,
                      server_args=["--process", "m:f"])
    ports = {"cloud": 7001, "leader": 7002, "r1": 7003, "r2": 7004, "r3": 7005}
    specs = plan_fleet(cfg, tmp_path, ports)
    assert list(specs) == ["cloud", "leader", "r1", "r2", "r3"]
    cloud = specs["cloud"].argv
    assert cloud[cloud.index("--listen") + 1] == "tcp/127.0.0.1:7001"
    assert cloud[-2:] == ["--process", "m:f"] and "--lease-ms" in cloud
    r2 = specs["r2"].argv
    assert r2[r2.index("--listen") + 1] == "tcp/127.0.0.1:7004"
    connects = [r2[i + 1] for i, a in enumerate(r2) if a == "--connect"]
    # the bootstrap (the cloud), then the peers started before it: zenoh re-dials only those after a cut
    assert connects == ["tcp/127.0.0.1:7001", "tcp/127.0.0.1:7002", "tcp/127.0.0.1:7003"]
    leader = specs["leader"].argv
    assert [leader[i + 1] for i, a in enumerate(leader) if a == "--connect"] == ["tcp/127.0.0.1:7001"]
    # the first two robots run for the lead, ranked by Table 4.3 profiles; r3 does not
    assert "--leader-capable" in specs["r1"].argv and r2[r2.index("--capability") + 1] == "robot3"
    assert "--leader-capable" not in specs["r3"].argv
    assert r2[r2.index("--synthetic") + 1] == "b"  # kinds dealt round-robin
    assert specs["r3"].argv[specs["r3"].argv.index("--synthetic") + 1] == "a"
    assert r2[r2.index("--duration") + 1] == "7" and r2[r2.index("--rate") + 1] == "2.5"
    assert specs["r2"].log_path == tmp_path / "logs" / "r2.log"
    assert specs["r2"].ready_file.name == "r2.ready" and str(specs["r2"].ready_file) in r2
    # every port distinct -> every endpoint distinct
    eps = {s.argv[s.argv.index("--listen") + 1] for s in specs.values()}
    assert len(eps) == 5


def test_plan_with_several_clouds(tmp_path):
    cfg = FleetConfig(robots=2, clouds=3)
    ports = {"cloud": 7001, "cloud1": 7002, "cloud2": 7003, "leader": 7004, "r1": 7005, "r2": 7006}
    specs = plan_fleet(cfg, tmp_path, ports)
    assert list(specs) == ["cloud", "cloud1", "cloud2", "leader", "r1", "r2"]
    nodes = [specs[n].argv[specs[n].argv.index("--node") + 1] for n in ("cloud", "cloud1", "cloud2", "leader")]
    assert nodes == ["cloud0", "cloud1", "cloud2", "leader0"]
    assert specs["cloud2"].log_path == tmp_path / "logs" / "cloud2.log"

    def connects(argv):
        return [argv[i + 1] for i, a in enumerate(argv) if a == "--connect"]

    first = ["tcp/127.0.0.1:7001"]  # the bootstrap, then every peer started before it (one side per pair)
    assert connects(specs["leader"].argv) == first + ["tcp/127.0.0.1:7002", "tcp/127.0.0.1:7003"]
    assert connects(specs["r2"].argv) == first + [f"tcp/127.0.0.1:{p}" for p in (7002, 7003, 7004, 7005)]
    assert connects(specs["cloud1"].argv) == first and connects(specs["cloud"].argv) == []


@pytest.mark.parametrize("n", [0, 17])
def test_config_rejects_cloud_count(n):
    with pytest.raises(InputError, match=f"--clouds must be between 1 and 16, got {n}"):
        FleetConfig(clouds=n).check()


def test_plan_with_images(tmp_path):
    specs = plan_fleet(FleetConfig(robots=1, images=tmp_path), tmp_path, {"cloud": 1, "leader": 2, "r1": 3})
    argv = specs["r1"].argv
    assert argv[argv.index("--images") + 1] == str(tmp_path) and "--synthetic" not in argv


@pytest.mark.parametrize("text, want", [("8:14", (8.0, 14.0)), ("0:0.5", (0.0, 0.5))])
def test_parse_outage(text, want):
    assert parse_outage(text) == want


@pytest.mark.parametrize("text", ["8", "a:b", "5:3", "3:3", "-1:2"])
def test_parse_outage_rejects(text):
    with pytest.raises(InputError, match=repr(text).replace("(", r"\(")):
        parse_outage(text)


@pytest.mark.parametrize("kw, msg", [
    ({"robots": 0}, "--robots must be at least 1, got 0"),
    ({"duration_s": 0}, "--duration must be positive"),
    ({"rate_hz": -1}, "--rate must be positive"),
    ({"cloud_outage": (5, 12), "duration_s": 10}, "got 5:12"),
])
def test_config_check(kw, msg):
    with pytest.raises(InputError, match=msg):
        FleetConfig(**kw).check()


def test_record_tail_reads_only_complete_lines(tmp_path):
    f = tmp_path / "records.jsonl"
    tail = RecordTail(f)
    assert tail.read_new() == []  # not there yet
    f.write_bytes(b'{"seq": 0}\n{"seq": 1')
    assert tail.read_new() == [{"seq": 0}]
    with open(f, "ab") as fh:
        fh.write(b'}\nnot json\n{"seq": 2}\n')
    assert tail.read_new() == [{"seq": 1}, {"seq": 2}]
    assert tail.bad_lines == 1 and tail.read_new() == []


T0 = 1_700_000_000_000_000_000


def _report():
    recs = [{"robot": "r1", "seq": i, "sent_unix_ns": T0 + i * 10**8, "received_unix_ns": T0 + i * 10**8 + 5 * 10**6,
             "tor_ms": 5.0, "ok": True, "tier": "cloud" if i < 5 else "leader"} for i in range(10)]
    fault = {"kind": "crash", "target": "cloud0", "tier": "cloud", "start_unix_ns": T0 + 450_000_000,
             "end_unix_ns": None, "robots": None}
    rep = {"v": 1, "kind": "report", **metrics.summarize(recs, [fault], robots=1),
           "rate_hz": 10.0, "duration_s": 1.0, "started_unix_ns": T0, "run_dir": "/x"}
    return rep


def test_summary_validates_against_schema_and_prints():
    rep = _report()
    validate_report(rep)
    json.dumps(rep)  # serialisable
    text = format_summary(rep)
    assert "r1" in text and "crash cloud0 at 0.45 s, never restarted" in text
    assert "failover gap 5.0 ms" in text  # first leader answer 5 ms after seq 5 was sent at 0.5 s
    assert "failback" not in text  # a peer never restarted has no way back to measure
    assert "telemetry: NOT COUNTED" in text  # the line is always there


@pytest.mark.parametrize("by_robot, says", [
    ({}, "no request failed on it (no failover gap)"),  # a successor took over between two frames
    ({"r1": 4.0, "r2": None}, "NO FALLBACK ANSWER for r2 (failover gap missing)"),
])
def test_summary_says_why_a_fault_has_no_failover_gap(by_robot, says):
    rep = _report()
    rep["faults"][0].update(failover_by_robot=by_robot, failover_gap_ms=None)
    text = format_summary(rep)
    assert says in text and "failover gap - ms" not in text


def _telemetry(lost: int = 0, **extra) -> dict:
    per = {"r1": {"sent": 10, "stored": 10 - lost, "duplicates": 1, "conflicts": 0, "lost": lost,
                  "missing": ["8-10"] if lost else [], "unexpected": 0, "queued": 0}}
    return {"sent": 10, "stored": 10 - lost, "duplicates": 1, "lost": lost, "conflicts": 0, "per_robot": per,
            "ods": "/x/ods.sqlite", **extra}


def test_the_summary_always_has_the_telemetry_line_and_the_verdict_counts_it():
    """Issue #12, item 3: sent, stored, duplicates, lost printed; a loss is a failed run (exit 1)."""
    from scmr_mesh.fleet import check_fleet, fleet_problems

    rep = _report()
    rep["peers"] = {"cloud": {"exit": 0, "log": "/x/logs/cloud.log"}, "r1": {"exit": 0, "log": "/x/logs/r1.log"}}
    rep["telemetry"] = _telemetry()
    rep["problems"] = fleet_problems(rep)
    assert rep["problems"] == [] and check_fleet(rep, 1.0) == 0
    assert "telemetry: 10 sent, 10 stored, 1 duplicates, 0 lost" in format_summary(rep)
    rep["telemetry"] = _telemetry(3)
    rep["problems"] = fleet_problems(rep)
    assert rep["problems"] == ["3 of 10 telemetry records lost: r1 3 (seqs 8-10)"]
    text = format_summary(rep)
    assert "telemetry: 10 sent, 7 stored, 1 duplicates, 3 lost" in text and "PROBLEM: 3 of 10" in text
    with pytest.raises(MeshError, match="3 of 10 telemetry records lost"):
        check_fleet(rep, 1.0)
    rep["telemetry"] = _telemetry(10, stored=0, error="the store could not be read (StoreError: not a database)")
    rep["problems"] = fleet_problems(rep)
    assert any("could not be read" in p for p in rep["problems"])
    del rep["telemetry"]
    assert fleet_problems(rep) == ["telemetry was not counted (see the log of scmr up)"]


def test_a_restart_that_never_came_up_is_printed_and_fails_the_run():
    from scmr_mesh.fleet import check_fleet, fleet_problems

    rep = _report()
    rep["faults"][0]["end_unix_ns"] = T0 + 900_000_000
    rep["faults"][0]["ready_unix_ns"] = None
    rep["peers"] = {"cloud": {"exit": 1, "log": "/x/logs/cloud.log"}}
    rep["telemetry"] = _telemetry()
    rep["problems"] = fleet_problems(rep)
    assert rep["problems"][0] == ("cloud0 was restarted at 0.90 s but never became ready (it exited with "
                                  "status 1); see /x/logs/cloud.log")
    assert "peer cloud exited with status 1; see /x/logs/cloud.log" in rep["problems"]
    text = format_summary(rep)
    assert "restarted 0.90 s but NEVER BECAME READY" in text and "restored" not in text
    with pytest.raises(MeshError, match="never became ready"):
        check_fleet(rep, 0.0)


def test_schema_rejects_a_broken_report():
    rep = _report()
    del rep["tor_ms"]["p99"]
    with pytest.raises(MeshError, match="tor_ms.*p99"):
        validate_report(rep)
    rep = _report()
    rep["ror"] = 1.5
    with pytest.raises(MeshError, match="at ror"):
        validate_report(rep)


def test_check_ror():
    rep = _report()
    assert check_ror(rep, 1.0) == 0
    rep["succeeded"] = 9
    with pytest.raises(MeshError, match=r"1 of 10 requests failed \(RoR 0.900"):
        check_ror(rep, 1.0)
    assert check_ror(rep, 0.9) == 0
    rep["requests"] = rep["succeeded"] = 0
    with pytest.raises(MeshError, match="no request finished"):
        check_ror(rep, 1.0)


def test_bench_targets():
    from scmr_mesh.bench.mesh import _stat

    run4 = {"robots": 4, "rate_hz": 5.0, "tor_ms": {"p50": 10.0, "p99": 60.0}, "tor_admitted_ms": {"p99": 90.0}}
    run16 = {"robots": 16, "rate_hz": 5.0, "tor_ms": {"p50": 30.0, "p99": 260.0}, "tor_admitted_ms": {"p99": 120.0}}
    crash = {"ror_min": 1.0, "failover_gap_ms": _stat([12.0, 15.0, 30.0]), "failback_gap_ms": _stat([300.0, 520.0])}
    t = bench_targets([run4], crash)
    assert t["tor_p50_4x5hz_ok"] is True and t["tor_p99_4x5hz_ok"] is False and t["tor_admitted_p99_ok"] is True
    assert t["crash_ror_ok"] and t["failover_ok"] and t["failback_ok"] is False  # median 15 ms; max 520 ms
    assert bench_targets([run4, run16], None)["tor_admitted_p99_ok"] is False
    assert t["hedge_rate_ok"] is None  # not measured
    assert bench_targets([dict(run4, hedge_rate=0.01), dict(run16, hedge_rate=0.03)], None)["hedge_rate_ok"] is False
    assert bench_targets([dict(run4, hedge_rate=0.02)], None)["hedge_rate_ok"] is True
    hogs = {"ror_min": 1.0, "failover_gap_ms": _stat([40.0, 900.0]), "failback_gap_ms": _stat([800.0, None])}
    t = bench_targets([], {"ror_min": 0.99, "failover_gap_ms": _stat([None]), "failback_gap_ms": _stat([])}, hogs)
    assert t["tor_p50_4x5hz_ok"] is None and not t["crash_ror_ok"] and not t["failover_ok"] and not t["failback_ok"]
    assert t["hogs_failover_ok"] is True and t["hogs_failback_ok"] is False  # a run never failed back


def test_schema_file_is_valid_json_schema(repo_root: Path):
    import jsonschema

    schema = json.loads((repo_root / "schemas" / "report.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)


def test_progress_line_puts_alive_tiers_first():
    from scmr_mesh.fleet import Progress, format_progress

    line = format_progress(Progress(10.6, 20, 4, 3, 7.5, 40.0, {"cloud": 2, "leader": 1, "failed": 1},
                                    {"cloud": False, "leader": True}, leaders=["r1"]))
    assert line.startswith("[ 10.6/20 s] cloud DOWN, leader r1 | 4 req, RoR 0.750, ToR p50/p99 7.5/40.0 ms")
    assert line.endswith("cloud 2 leader 1 peer 0 local 0 failed 1")
    none = format_progress(Progress(1, 20, 0, 0, None, None, {}, {"cloud": True, "leader": False}))
    assert "cloud up, leader NONE |" in none
    split = format_progress(Progress(1, 20, 0, 0, None, None, {}, {"cloud": False, "leader": True},
                                     leaders=["leader0", "r3"]))
    assert "leader leader0+r3 (SPLIT)" in split
    assert "starting" in format_progress(Progress(0, 20, 0, 0, None, None, {}, {}, phase="starting"))


@pytest.mark.parametrize("text, want", [("cloud0@5", (0, 5.0)), ("cloud3@2.5", (3, 2.5))])
def test_parse_kill(text, want):
    from scmr_mesh.fleet.plan import parse_kill

    assert parse_kill(text) == want


def test_kill_cloud_checks():
    from scmr_mesh.fleet.plan import parse_kill

    with pytest.raises(InputError, match="cloudI@SECONDS"):
        parse_kill("c1@5")
    with pytest.raises(InputError, match="must name cloud0..cloud1"):
        FleetConfig(clouds=2, kill_cloud=(2, 1.0)).check()
    with pytest.raises(InputError, match="either --kill-cloud or --cloud-outage"):
        FleetConfig(clouds=2, duration_s=10, kill_cloud=(1, 1.0), cloud_outage=(2, 3)).check()


def test_bench_scale_window_counts_cloud_answers_only(tmp_path):
    from scmr_mesh.bench.scale import served_in_window

    (tmp_path / "robots" / "r1").mkdir(parents=True)
    t0 = 10**18
    recs = [{"ok": True, "tier": "cloud", "served_by": f"cloud{i % 2}", "received_unix_ns": t0 + i * 10**8}
            for i in range(100)]  # 10 s at 10/s
    recs += [{"ok": True, "tier": "leader", "served_by": "leader0", "received_unix_ns": t0 + 5 * 10**9},
             {"ok": False, "tier": None, "received_unix_ns": t0 + 5 * 10**9}]
    (tmp_path / "robots" / "r1" / "records.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    w = served_in_window({"started_unix_ns": t0, "run_dir": str(tmp_path)}, duration_s=10)
    assert w["window_s"] == 7.0 and w["served"] == 70 and w["served_per_s"] == 10.0  # 2 s warm-up, 1 s tail
    assert w["other"] == 2 and w["by_node"] == {"cloud0": 35, "cloud1": 35}


def test_bench_scale_pipeline_runs_the_real_pipeline_on_every_scene_kind(tmp_path):
    """``--pipeline``: no sleeping stub, no stub scenes; the robots' plans deal every synthetic kind."""
    from scmr_mesh.bench.scale import FIXED, _config
    from scmr_mesh.cli import build_parser
    from scmr_mesh.fleet.plan import fleet_scenario

    args = build_parser().parse_args(["bench", "scale", "--quick", "--json", str(tmp_path / "s.json")])
    assert args.pipeline is False
    stub = _config(args, 2, tmp_path / "a", 10.0)
    assert FIXED in stub.server_args and list(stub.synthetic) == ["stub"]
    args = build_parser().parse_args(["bench", "scale", "--pipeline", "--workers", "1", "--robots", "6",
                                      "--json", str(tmp_path / "s.json")])
    cfg = _config(args, 2, tmp_path / "b", 10.0)
    assert FIXED not in cfg.server_args and "--process" not in cfg.server_args
    assert cfg.server_args == ("--queue", "64") and cfg.workers == 1 and cfg.clouds == 2
    kinds = {r.synthetic for r in fleet_scenario(cfg).robots}
    assert "stub" not in kinds and len(kinds) > 1, kinds


def test_the_runs_postgresql_is_restarted_when_it_dies_and_a_failed_start_is_retried():
    """FleetHooks supervises the run's PostgreSQL (issue 25 item 9), here with a stand-in server."""
    from types import SimpleNamespace

    from scmr_mesh.fleet.pgserver import PgServerError
    from scmr_mesh.fleet.run import FleetHooks
    from scmr_mesh.scenario.report import run_problems

    class Server:
        def __init__(self):
            self.proc, self.up, self.starts, self.fail = SimpleNamespace(returncode=-9), False, 0, 1
            self.log_path = "postgres.log"

        def alive(self):
            return self.up

        def stop(self, timeout=None):
            pass

        def start(self, timeout=None):
            self.starts += 1
            if self.fail:
                self.fail -= 1
                raise PgServerError("pre-existing shared memory block is still in use")
            self.up = True

    hooks, run = FleetHooks(FleetConfig(clouds=2)), SimpleNamespace(elapsed_s=lambda: 3.5)
    hooks.pg = pg = Server()
    def watch():  # the restart runs off the run's loop; wait for it here
        hooks._watch_ods(run)
        if hooks._pg_future is not None:
            hooks._pg_future.result(10)

    watch()
    (out,) = hooks.ods_outages  # seen, the first start failed: retried later, not at once
    assert pg.starts == 1 and out["exit"] == -9 and out["gap_ms"] is None and "shared memory" in out["error"]
    assert run_problems({"ods": {"outages": [out]}, "telemetry": {"lost": 0}}) == [
        "the run's PostgreSQL data store was killed by signal 9 at 3.50 s; it could not be restarted "
        "(pre-existing shared memory block is still in use)"]
    watch()
    assert pg.starts == 1  # within PG_RETRY_S of the failure
    hooks._pg_retry_at = 0.0
    watch()
    watch()  # alive again: nothing to do
    assert pg.starts == 2 and len(hooks.ods_outages) == 1 and out["gap_ms"] is not None and out["error"] is None
    assert run_problems({"ods": {"outages": [out]}, "telemetry": {"lost": 0}}) == [
        f"the run's PostgreSQL data store was killed by signal 9 at 3.50 s; restarted after {out['gap_ms']:.0f} ms"]


def test_cpu_per_request_counts_a_shared_process_once_and_clips_to_the_window():
    from scmr_mesh.bench.mesh import cpu_per_request

    S = 10**9  # the sampler's times are unix ns
    cpu = {"pgids": {"cloud0": 10, "leader0": 11, "router0": 12, "r1": 20, "r2": 20, "r3": 30},
           "series": {"cloud0": [[0, 0.0], [10 * S, 2.0], [20 * S, 4.0]],
                      "leader0": [[0, 0.0], [20 * S, 1.0]],
                      "router0": [[5 * S, 0.0], [10 * S, 0.5]],  # stopped before the window
                      "r1": [[0, 0.0], [20 * S, 8.0]], "r2": [[0, 0.0], [20 * S, 8.0]],  # one swarm process
                      "r3": [[0, 0.0], [15 * S, 1.5], [30 * S, 3.0]],  # covers the window: clipped to it
                      "r4": []}}
    out = cpu_per_request(cpu, 10 * S, 20 * S, 500, cores=2)
    assert out["cpu_s"]["robots"] == 5.0  # the swarm's 4 s once (not 8), r3's 1 s of the window
    assert out["ms_per_request"] == {"cloud": 4.0, "leader": 1.0, "router": 0.0, "robots": 10.0, "total": 15.0}
    assert out["window_s"] == 10.0 and out["host_share"] == 0.375
    assert cpu_per_request(cpu, 10 * S, 20 * S, 0)["ms_per_request"]["total"] is None


def test_mismatched_replies_are_in_the_report_the_console_and_fail_the_run():
    """Issue 25 item 8: replies refused as not answering their request are counted by node; any fails the run."""
    from scmr_mesh.fleet import check_fleet, fleet_problems

    rep = _report()
    rep["request_log"] = []
    liar = {"tier": "cloud", "node": "cloud0", "outcome": "mismatched", "mismatched": 2, "message": "frame 1005"}
    recs = [{"robot": "r1", "ok": True, "tier": "leader", "sent_unix_ns": T0, "received_unix_ns": T0 + 5_000_000,
             "attempts": [liar, {"tier": "leader", "node": "L", "outcome": "ok"}]}]
    rep.update({k: v for k, v in metrics.summarize(recs, robots=1).items() if k.startswith("mismatched")})
    rep["per_robot"]["r1"]["mismatched"] = 2
    rep["telemetry"] = _telemetry()
    assert rep["mismatched"] == 2 and rep["mismatched_by_node"] == {"cloud/cloud0": 2}
    validate_report(rep)
    rep["problems"] = fleet_problems(rep)
    assert rep["problems"] == ["2 replies did not answer the request they came for (robot, seq or frame digest "
                               "not the request's, or not a trusted reply of the node asked: a replayed, forged or wrong answer, "
                               "never used): cloud/cloud0 2"]
    assert "PROBLEM: 2 replies did not answer" in format_summary(rep)
    with pytest.raises(MeshError, match="did not answer the request"):
        check_fleet(rep, 0.0)


def test_ingress_knee_is_the_last_step_before_the_first_busy_answer():
    # issue 23 item 2: served frames/s before any busy answer, over the workers' capacity
    from scmr_mesh.bench.ingress import cpu_delta, knee

    steps = [{"offered_fps": 50, "served_fps": 50, "busy": 0}, {"offered_fps": 90, "served_fps": 90, "busy": 0},
             {"offered_fps": 95, "served_fps": 93, "busy": 2, "sender_late_max_ms": 31.0},
             {"offered_fps": 99, "served_fps": 99, "busy": 0}]  # a clean step after a busy one does not count
    k = knee(100.0, steps)
    assert (k["served_at_first_busy_ratio"], k["first_busy_offered_fps"], k["first_busy_sender_late_ms"]) == (0.9, 95, 31.0)
    assert k["ok"] is True and knee(100.0, steps[:1] + steps[2:])["ok"] is False
    none = knee(100.0, steps[:2])
    assert none["first_busy_offered_fps"] is None and none["served_at_first_busy_ratio"] == 0.9
    assert knee(100.0, [{"offered_fps": 50, "served_fps": 49, "busy": 1}])["served_at_first_busy_ratio"] == 0.0
    assert cpu_delta({"rx": 1.0, "gone": 2.0}, {"rx": 1.25, "workers": 0.5}) == {"rx": 0.25, "workers": 0.5}
    t = bench_targets([], None, None, {"served_at_first_busy_ratio": 0.84})
    assert t["served_at_first_busy_ok"] is False and bench_targets([], None)["served_at_first_busy_ok"] is None
