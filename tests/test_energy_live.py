"""Live placement in the robot: EnergyPlacer as a pure hook, then real robot processes."""

from __future__ import annotations

import json
from dataclasses import dataclass

import pytest
from conftest import free_port

from scmr_mesh.energy import PROFILES, Profile
from scmr_mesh.energy.live import ASSUMED_LINK, EnergyPlacer
from scmr_mesh.mesh.testing import STUB, read_records, spawn_peer, stop_peer, wait_for


@dataclass
class View:
    cloud: tuple = ()
    leader: tuple = ()
    local: bool = True

    def nodes(self, tier):
        return self.cloud if tier == "cloud" else self.leader if tier == "leader" else ()


@dataclass
class Frame:
    seq: int
    bytes: int


def _remote_record(seq, tier, *, up=100_000, down=4_000, send_ns=0, recv_ns=60_000_000):
    return {"seq": seq, "ok": True, "tier": tier, "bytes_up": up, "bytes_down": down, "tor_ms": 60.0,
            "received_unix_ns": recv_ns, "attempts": [{"tier": tier, "outcome": "ok", "t_unix_ns": send_ns}]}


def test_never_plans_an_unreachable_tier():
    placer = EnergyPlacer(PROFILES["robot1"], host_hz=2e9)
    assert placer(View(), Frame(0, 100_000)) == ["local"]
    assert placer(View(), Frame(1, 100_000)) == ["local"]
    assert placer(View(leader=("L1",)), Frame(2, 100_000))[0] in ("leader", "local")
    assert "cloud" not in placer(View(leader=("L1",)), Frame(3, 100_000))
    assert "local" not in placer(View(cloud=("c1",), local=False), Frame(4, 100_000))


def test_peer_robots_are_weighed_with_their_own_clock_and_only_without_a_cloud():
    from scmr_mesh.energy.placement import LinkEstimate, Task, energy_terms
    from scmr_mesh.mesh.robot import Reachable

    placer = EnergyPlacer(PROFILES["robot1"], host_hz=2e9)
    no_cloud = Reachable(peer=("r4",), clocks={"r4": PROFILES["robot4"].clock_hz}, local=True)
    plan = placer(no_cloud, Frame(0, 100_000))
    assert "peer" in plan
    p, _ = placer._pending[0]
    peer = next(o for o in p.options if o["tier"] == "peer")
    assert peer["remote_hz"] == PROFILES["robot4"].clock_hz  # the peer's clock, from its load message
    want = energy_terms(Task(placer.task_for(100_000).cycles, 100_000, placer.task_for(100_000).bytes_down),
                        PROFILES["robot1"], LinkEstimate(ASSUMED_LINK.up_Bps, ASSUMED_LINK.down_Bps,
                                                         remote_hz=PROFILES["robot4"].clock_hz), tier="peer")
    assert peer["robot_energy_j"] == pytest.approx(want["e_cloud_j"])
    with_cloud = Reachable(cloud=("c1",), peer=("r4",), clocks={"r4": 2.83e9}, local=True)
    assert "peer" not in placer(with_cloud, Frame(1, 100_000))


def test_learns_link_cycles_and_reply_size_and_records_energy():
    prof = PROFILES["robot1"]
    placer = EnergyPlacer(prof, host_hz=2e9, robot_id="r1")
    order = placer(View(cloud=("c1",), leader=("L1",)), Frame(0, 100_000))
    assert order[0] == "cloud"  # assumed C = 5e9 cycles: 235 J locally vs ~3 J offloaded
    rec = _remote_record(0, "cloud")
    placer.annotate(rec, {"server_ms": 10.0, "timings_ms": {"pipeline": 40.0, "decode": 10.0}})
    # cycles = 50 ms of server work x 2 GHz; link = 104000 B / (60 - 10) ms
    assert rec["energy"]["cycles"] == pytest.approx(0.05 * 2e9)
    assert placer.links.estimate("cloud").up_Bps == pytest.approx(104_000 / 0.05)
    t = placer.task_for(100_000)
    assert t.cycles == pytest.approx(1e8) and t.bytes_down == 4000 and t.measured == {"cycles", "bytes_up", "bytes_down"}
    link = placer.links.estimate("cloud")
    expect = prof.p_idle_w * 1e8 / (300 * prof.clock_hz) + prof.p_up_w * 100_000 / link.up_Bps \
        + prof.p_down_w * 4000 / link.down_Bps
    assert rec["energy_j"] == pytest.approx(expect)
    assert "cloud.link" in rec["energy"]["measured"] and "leader.link" in rec["energy"]["assumed"]
    assert rec["energy"]["planned_tier"] == "cloud" and rec["energy"]["predicted_j"] > 0
    s = placer.summary()
    assert s["per_tier"]["cloud"]["requests"] == 1 and s["total_j"] == pytest.approx(expect)


def test_local_run_costed_from_its_cpu_time():
    placer = EnergyPlacer(PROFILES["robot2"], host_hz=3e9)
    placer(View(), Frame(7, 1000))
    rec = {"seq": 7, "ok": True, "tier": "local", "bytes_up": 0, "bytes_down": 0, "tor_ms": 30.0, "attempts": []}
    placer.annotate(rec, {"mask_png": b"", "cpu_ms": 20.0})
    assert rec["energy"]["cycles"] == pytest.approx(0.02 * 3e9)
    assert rec["energy_j"] == pytest.approx(83.0 * 0.02 * 3e9 / 2.3e9)
    assert rec["energy"]["cycles_source"] == "measured (this run)"


def test_failed_request_still_costs_sending_and_waiting():
    placer = EnergyPlacer(PROFILES["robot1"], host_hz=2e9)
    placer(View(cloud=("c1",)), Frame(0, 50_000))
    rec = {"seq": 0, "ok": False, "tier": None, "bytes_up": 50_000, "bytes_down": 0, "tor_ms": 1000.0,
           "attempts": [{"tier": "cloud", "outcome": "timeout", "t_unix_ns": 0}]}
    placer.annotate(rec, None)
    assert rec["energy_j"] == pytest.approx(83.54 * 50_000 / ASSUMED_LINK.up_Bps + 25.0 * 1.0)
    assert placer.summary()["per_tier"]["failed"]["requests"] == 1


def test_probes_an_unmeasured_tier_when_local_keeps_winning():
    # transfer is dear (P_u, P_d huge), compute cheap: local wins on energy
    prof = Profile("dear-radio", p_compute_w=1.0, p_idle_w=0.5, p_up_w=1e4, p_down_w=1e4, clock_hz=1e9, source="t")
    placer = EnergyPlacer(prof, host_hz=2e9, probe_every=3, probe_until=1, assumed_cycles=1e6)
    plans = [placer(View(cloud=("c1",)), Frame(i, 100_000)) for i in range(6)]
    firsts = [p[0] for p in plans]
    assert firsts == ["local", "local", "cloud", "local", "local", "cloud"]
    rec = _remote_record(2, "cloud")
    placer.annotate(rec, {"server_ms": 1.0, "timings_ms": {"p": 1.0}})
    assert rec["energy"]["probe"] is True
    # once measured, no more probing
    assert [placer(View(cloud=("c1",)), Frame(10 + i, 100_000))[0] for i in range(6)] == ["local"] * 6


# ----------------------------------------------------------- real processes
def _robot(tmp, rid, connect, extra):
    args = ["robot", "--insecure", "--id", rid, "--synthetic", "stub", "--out", str(tmp / rid), "--process", STUB,
            "--lease-ms", "300", *extra]
    for ep in connect:
        args += ["--connect", ep]
    return spawn_peer(args, log_path=tmp / f"{rid}.log")


def test_robot_with_profile_offloads_and_records_energy(tmp_path):
    """Cloud + robot processes on loopback: the energy policy offloads and every record has energy_j."""
    port = free_port()
    ready = tmp_path / "c1.ready"
    procs = []
    try:
        cloud = spawn_peer(["cloud", "--insecure", "--node", "c1", "--listen", f"tcp/127.0.0.1:{port}", "--workers", "1",
                            "--process", STUB, "--lease-ms", "300", "--ready-file", str(ready)],
                           log_path=tmp_path / "c1.log")
        procs.append(cloud)
        wait_for(lambda: ready.exists() or cloud.poll() is not None, timeout=30, what="cloud ready")
        robot = _robot(tmp_path, "r1", [f"tcp/127.0.0.1:{port}"],
                       ["--count", "8", "--rate", "20", "--profile", "robot1", "--deadline-ms", "5000"])
        procs.append(robot)
        assert robot.wait(timeout=60) == 0, (tmp_path / "r1.log").read_text()
        recs = read_records(tmp_path / "r1" / "records.jsonl")
        assert len(recs) == 8 and all(r["ok"] for r in recs)
        # assumed C = 5e9 cycles: 235 J locally at 1 GHz vs a few J offloaded, so the first frame offloads;
        # later frames follow the measured inputs (the stub is cheap, so local may then win).
        # (--deadline-ms 5000: a busy machine's first request may be slow; that is not what we test)
        assert recs[0]["tier"] == "cloud"
        for r in recs:
            assert r["energy_j"] > 0 and r["energy"]["profile"] == "robot1"
            assert r["tier"] == r["energy"]["planned_tier"] or r["energy"]["probe"]
            if r["tier"] == "local":
                assert r["energy_j"] == pytest.approx(47.0 * r["energy"]["cycles"] / 1e9)
        # after the first reply, cycles and the cloud link are measured
        assert "cloud.link" in recs[-1]["energy"]["measured"] and "cycles" in recs[-1]["energy"]["measured"]
        lines = (tmp_path / "r1.log").read_text().splitlines()
        summary = json.loads(next(ln for ln in reversed(lines) if ln.startswith('{"robot"')))
        assert summary["energy"]["requests"] == 8
        assert summary["energy"]["total_j"] == pytest.approx(sum(r["energy_j"] for r in recs))
    finally:
        for p in procs:
            stop_peer(p, timeout=5)


def test_robot_with_profile_and_no_tier_runs_locally_and_costs_eq42(tmp_path):
    robot = _robot(tmp_path, "r2", [], ["--count", "3", "--rate", "20", "--profile", "robot3", "--wait-ms", "0"])
    try:
        assert robot.wait(timeout=60) == 0, (tmp_path / "r2.log").read_text()
        recs = read_records(tmp_path / "r2" / "records.jsonl")
        assert [r["tier"] for r in recs] == ["local"] * 3
        for r in recs:
            assert r["energy"]["cycles_source"] == "measured (this run)"
            assert r["energy_j"] == pytest.approx(93.0 * r["energy"]["cycles"] / 2.5e9)
    finally:
        stop_peer(robot, timeout=5)


def test_robot_rejects_unknown_profile(tmp_path):
    robot = _robot(tmp_path, "r3", [], ["--count", "1", "--profile", "robot9"])
    try:
        assert robot.wait(timeout=60) == 1
        log = (tmp_path / "r3.log").read_text()
        assert "scmr: error:" in log and "robot9" in log and "Traceback" not in log
    finally:
        stop_peer(robot, timeout=5)
