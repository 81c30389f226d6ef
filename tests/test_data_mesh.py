"""The data tier with real processes: cloud outage, robot restart, full and corrupt queues.

Cloud and leader run the stub process function; robots send stub frames.
Multicast off, explicit tcp/127.0.0.1 endpoints, lease 300 ms, every process
group killed at the end.  About 40-60 s on a loaded 2-core box.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port

from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.data.queue import TelemetryQueue
from scmr_mesh.data.report import telemetry_report
from scmr_mesh.mesh.testing import STUB, spawn_peer, stop_peer, wait_for

LEASE = "300"


def _ep(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


class Peers:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: list = []

    def service(self, role: str, node: str, port: int, *, connect=(), extra=()):
        ready = self.tmp / f"{node}.ready"
        args = [role, "--insecure", "--node", node, "--listen", _ep(port), "--workers", "1", "--process", STUB,
                "--lease-ms", LEASE, "--ready-file", str(ready), *extra]
        for ep in connect:
            args += ["--connect", ep]
        p = spawn_peer(args, log_path=self.tmp / f"{node}.log")
        self.procs.append(p)
        wait_for(lambda: ready.exists() or p.poll() is not None, timeout=40, what=f"{node} ready")
        assert p.poll() is None, self.log(node)
        return p

    def robot(self, rid: str, connect, *extra, name: str | None = None):
        name = name or rid  # a restarted robot may get a new output folder (the scenario runner does)
        args = ["robot", "--insecure", "--id", rid, "--synthetic", "stub", "--out", str(self.tmp / name), "--process", STUB,
                "--lease-ms", LEASE, "--quiet", *extra]
        for ep in connect:
            args += ["--connect", ep]
        p = spawn_peer(args, log_path=self.tmp / f"{name}.log")
        self.procs.append(p)
        return p

    def log(self, name: str) -> str:
        path = self.tmp / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def stop_all(self) -> None:
        for p in self.procs:
            stop_peer(p, timeout=5)


@pytest.fixture
def peers(tmp_path):
    p = Peers(tmp_path)
    try:
        yield p
    finally:
        p.stop_all()


def _leader_items(agent, selector: str) -> dict:
    """The leader L's own buffer (asked directly, whichever tier is alive)."""
    import msgpack

    from scmr_mesh.mesh.data_service import buffer_key

    ans = agent._ask(buffer_key("leader", "L"), msgpack.packb({"sel": selector}))
    return ans[1]["items"] if ans is not None and ans[0] == "ok" else {}


def _stored(ods_path: Path, robot: str) -> list[int]:
    if not ods_path.exists():
        return []
    with OperationalDataStore(ods_path, readonly=True) as ods:
        return ods.seqs(robot)


def _summary(tmp: Path, rid: str) -> dict:
    return json.loads((tmp / rid / "telemetry.json").read_text())


@pytest.mark.parametrize("data_process", ["on", "off"])  # the cloud's data tier in its own process, or not
def test_cloud_outage_loses_nothing_and_data_requests_fail_over(peers, tmp_path, data_process):
    from scmr_mesh.mesh.config import MeshConfig, close_session, open_session
    from scmr_mesh.mesh.data_service import TelemetryAgent
    from scmr_mesh.mesh.robot import Robot, RobotOptions

    pc, pl = free_port(), free_port()
    ods_path = tmp_path / "ods.sqlite"
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"params/speed_mps": 1.5, "maps/site": {"lanes": 2}}))
    cloud_args = dict(extra=["--ods", str(ods_path), "--data-params", str(params), "--data-process", data_process])
    cloud = peers.service("cloud", "c1", pc, **cloud_args)
    peers.service("leader", "L", pl, connect=[_ep(pc)], extra=["--sync-period", "0.3"])
    r1 = peers.robot("r1", [_ep(pc), _ep(pl)], "--rate", "20", "--duration", "7", "--deadline-ms", "400",
                     "--listen", _ep(free_port()))
    session = open_session(MeshConfig(connect=[_ep(pc), _ep(pl)], lease_ms=int(LEASE)))
    probe = Robot("probe", tmp_path / "probe", options=RobotOptions(local_fallback=False, deadline_ms=400))
    agent = None
    try:
        probe.attach(session)
        agent = TelemetryAgent(probe, tmp_path / "probe" / "q", deadline_ms=400)
        wait_for(lambda: len(_stored(ods_path, "r1")) >= 10, timeout=30, what="r1 telemetry in the ODS")
        # the cloud's buffer serves the latest state; the leader pulls it in batches
        tier, node, items = agent.fetch("state/r1")
        assert (tier, node) == ("cloud", "c1") and items["state/r1"]["robot"] == "r1"
        # the leader has pulled the cloud's buffer (a condition, not "> 2 sync periods" of sleep)
        wait_for(lambda: {"maps/site", "state/r1"} <= set(_leader_items(agent, "**")), timeout=30,
                 what="the leader's synced copy of the cloud's buffer")
        stop_peer(cloud, sig=signal.SIGKILL)
        wait_for(lambda: not probe.view.snapshot().cloud, timeout=10, what="the probe to see the cloud go")
        tier, node, items = agent.fetch("state/r1")
        assert (tier, node) == ("leader", "L")  # same query, answered by the leader's copy
        assert agent.fetch("maps/*")[2] == {"maps/site": {"lanes": 2}}  # shared data pulled in the sync
        seq_at_leader = items["state/r1"]["seq"]
        # r1 keeps sending telemetry to the leader during the outage: the leader stores what it receives
        wait_for(lambda: _leader_items(agent, "state/r1").get("state/r1", {}).get("seq", 0) > seq_at_leader,
                 timeout=30, what="the leader's state/r1 to advance")
        _, _, items = agent.fetch("state/r1")
        assert items["state/r1"]["seq"] > seq_at_leader
        cloud = peers.service("cloud", "c1", pc, **cloud_args)  # failback, same ODS file
        assert r1.wait(timeout=30) == 0, peers.log("r1")
        sent = _summary(tmp_path, "r1")["sent"]
        wait_for(lambda: len(_stored(ods_path, "r1")) >= sent, timeout=30, what="every r1 record in the ODS")
    finally:
        if agent is not None:
            agent.close(drain_s=0)
        probe.close()
        close_session(session)
    rep = telemetry_report(ods_path, {"r1": sent})["telemetry"]
    assert rep["lost"] == 0 and rep["stored"] == sent and rep["per_robot"]["r1"]["unexpected"] == 0
    assert _stored(ods_path, "r1") == list(range(1, sent + 1))  # each seq exactly once
    with OperationalDataStore(ods_path, readonly=True) as ods:
        via = {r["received_from"] for r in ods.range(robot="r1")}
    # end to end: what the leader relayed during the outage is stored once, whichever copy
    # (the leader's relay or the robot's own resend after failback) reached the cloud first
    assert via <= {"cloud", "leader"}
    assert _summary(tmp_path, "r1")["acked_by"]["leader"] > 0  # the leader took records during the outage


def test_robot_restarted_mid_outage_keeps_its_queue(peers, tmp_path):
    """The scenario layout: ready files in RUN/ready/, a new --out per restart, the queue in RUN/queues/ID."""
    from scmr_mesh.data.report import run_telemetry

    pc = free_port()
    ods_path = tmp_path / "ods.sqlite"

    def robot(name: str, *extra):
        return peers.robot("r2", [_ep(pc)], "--rate", "50", "--ready-file", str(tmp_path / "ready" / name),
                           *extra, name=name)

    cloud = peers.service("cloud", "c1", pc, extra=["--ods", str(ods_path)])
    r = robot("r2", "--count", "10")
    assert r.wait(timeout=30) == 0, peers.log("r2")
    qdir = tmp_path / "queues" / "r2"
    assert _summary(tmp_path, "r2")["queued"] == 0 and qdir.is_dir()
    stop_peer(cloud, sig=signal.SIGKILL)
    # mid-outage: the robot queues telemetry on disk, then crashes (SIGKILL, no clean exit)
    r = robot("r2-2", "--count", "100000", "--wait-ms", "0")

    def depth() -> int:
        q = TelemetryQueue(qdir, readonly=True)  # the robot is appending: look only
        try:
            return q.stats().depth
        finally:
            q.close()

    wait_for(lambda: r.poll() is None and depth() >= 15, timeout=30, what="telemetry queued during the outage")
    stop_peer(r, sig=signal.SIGKILL)
    queued = depth()
    assert queued >= 15
    peers.service("cloud", "c1", pc, extra=["--ods", str(ods_path)])
    r = robot("r2-3", "--count", "5")  # restarted again, with yet another --out
    assert r.wait(timeout=30) == 0, peers.log("r2-3")
    summary = _summary(tmp_path, "r2-3")
    sent = summary["sent"]
    assert sent >= 10 + queued + 5 and summary["queued"] == 0 and summary["replayed"] >= queued
    wait_for(lambda: len(_stored(ods_path, "r2")) >= sent, timeout=20, what="replayed telemetry in the ODS")
    rep = run_telemetry(tmp_path, ["r2"])["telemetry"]
    assert (rep["sent"], rep["stored"], rep["lost"], rep["conflicts"]) == (sent, sent, 0, 0)
    # the restarted cloud's buffer (re-seeded from the ODS, then fed) serves the latest state
    out = subprocess.run([sys.executable, "-m", "scmr_mesh", "ods", "fetch", "state/**", "--connect", _ep(pc),
                          "--lease-ms", LEASE], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "answered by cloud/c1" in out.stderr
    assert json.loads(out.stdout)["state/r2"]["seq"] == sent


def test_bad_data_params_stop_the_cloud_with_one_line(tmp_path):
    bad = tmp_path / "params.json"
    bad.write_text("[1, 2]")
    out = subprocess.run([sys.executable, "-m", "scmr_mesh", "cloud", "--insecure", "--node", "c9", "--workers", "1",
                          "--process", STUB, "--listen", _ep(free_port()), "--ods", str(tmp_path / "o.sqlite"),
                          "--data-params", str(bad)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1, out.stderr
    assert "scmr: error: --data-params" in out.stderr and "must hold a JSON object, got list" in out.stderr


def test_full_and_corrupt_queues_are_reported(peers, tmp_path):
    dead = _ep(free_port())  # nothing listens: no tier stores anything
    out = subprocess.run([sys.executable, "-m", "scmr_mesh", "ods", "fetch", "state/**", "--connect", dead,
                          "--wait-ms", "300"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and out.stderr.startswith("scmr: error: no cloud or leader alive after 0.3 s")
    r = peers.robot("r3", [dead], "--rate", "200", "--count", "40", "--wait-ms", "0",
                    "--telemetry-max-bytes", "3000")
    assert r.wait(timeout=60) == 1, peers.log("r3")  # telemetry was lost: the exit status says so
    s = _summary(tmp_path, "r3")
    # a refused record keeps its seq: the store sees the gap, every report counts it as lost
    assert s["refused"] > 0 and s["sent"] == 40 and s["queued"] + s["refused"] == 40 and s["lost"] == s["refused"]
    assert "is full" in peers.log("r3") and "refused" in peers.log("r3")
    assert "scmr: error: robot r3: " in peers.log("r3") and "telemetry records lost" in peers.log("r3")
    qdir = tmp_path / "r3" / "telemetry-queue"
    seg = sorted(qdir.glob("seg-*.log"))[0]
    raw = bytearray(seg.read_bytes())
    raw[len(raw) // 2] ^= 0x5A  # somewhere in the middle of the segment
    seg.write_bytes(bytes(raw))
    out = subprocess.run([sys.executable, "-m", "scmr_mesh", "ods", "queue", str(qdir)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and "lost" in out.stderr and "Traceback" not in out.stderr
    lost = json.loads(out.stdout)["lost_seqs"]
    assert len(lost) >= 1
    r = peers.robot("r3", [dead], "--rate", "50", "--count", "1", "--wait-ms", "0")
    assert r.wait(timeout=60) == 1, peers.log("r3")  # it starts with lost records: reported, exit 1
    assert "corrupt bytes" in peers.log("r3")
    s = _summary(tmp_path, "r3")
    assert s["corruptions"] >= 1 and s["lost_seqs"] == lost
