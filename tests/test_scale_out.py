"""The cloud tier scaled out: several cloud nodes on one shared PostgreSQL store, real processes.

* ``scmr up --clouds 2`` starts a PostgreSQL server for the run, both cloud
  nodes serve and store, nothing is lost, nothing is left running;
* the database stopped mid-run and started again: the cloud says so in one
  line, the robot keeps its records queued, then every record is stored once;
* the leader syncs its data buffer from a cloud node that is not the first by name.

Stub process function, multicast off, loopback endpoints.  About 40 s.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port

from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.data.queue import TelemetryQueue
from scmr_mesh.mesh.testing import STUB, read_records, spawn_peer, stop_peer, wait_for

LEASE = "300"


def _ep(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def _procs_mentioning(text: str) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                state = (d / "stat").read_text().rsplit(")", 1)[1].split()[0]
            except OSError:
                continue
            if text in cmd and state != "Z" and int(d.name) != __import__("os").getpid():
                out.append(int(d.name))
    return out


def _children_named(ppid: int, comm: str) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            name, rest = stat[stat.index("(") + 1:stat.rindex(")")], stat[stat.rindex(")") + 2:].split()
            if name == comm and int(rest[1]) == ppid and rest[0] != "Z":
                out.append(int(d.name))
    return out


@pytest.mark.timeout(180)
def test_up_with_two_clouds_shares_one_postgres_store_and_restarts_it_when_it_dies(tmp_path):
    """Both nodes serve and store on the run's PostgreSQL; SIGKILLed mid-run, it is restarted (issue 25 item 9).

    Before, nobody noticed: the clouds logged errors to the end and the report called the robots' queued
    records lost.  Now the outage is in the report and on the console (a problem: exit 1), and every
    record is stored after the restart, in the run or in the robots' drain phase.
    """
    import os
    import signal

    run_dir = tmp_path / "run"
    up = subprocess.Popen(
        [sys.executable, "-m", "scmr_mesh", "up", "--robots", "3", "--clouds", "2", "--duration", "6",
         "--rate", "5", "--synthetic", "stub", "--server-arg=--process", f"--server-arg={STUB}", "--quiet",
         "--lease-ms", LEASE, "--run-dir", str(run_dir)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        records = run_dir / "robots" / "r1" / "records.jsonl"
        wait_for(lambda: up.poll() is not None or (_children_named(up.pid, "postgres") and records.is_file()
                                                   and len(read_records(records)) >= 5),
                 timeout=120, what="the fleet to serve r1 five frames")
        (pg_pid,) = _children_named(up.pid, "postgres")
        os.kill(pg_pid, signal.SIGKILL)
        out, err = up.communicate(timeout=150)
        assert up.returncode == 1, out + err
        rep = json.loads((run_dir / "report.json").read_text())
        assert rep["clouds"] == 2 and rep["ods"]["backend"] == "postgresql"
        assert rep["ods"]["store"].startswith("postgresql://")
        (outage,) = rep["ods"]["outages"]
        assert outage["exit"] == -9 and outage["gap_ms"] is not None and outage["restarted_unix_ns"] > outage["down_unix_ns"]
        assert rep["problems"] == [f"the run's PostgreSQL data store was killed by signal 9 at {outage['t_s']:.2f} s; "
                                   f"restarted after {outage['gap_ms']:.0f} ms"], rep["problems"]
        assert "PROBLEM: the run's PostgreSQL data store was killed by signal 9" in out
        assert rep["ror"] == 1.0
        served = {rec["served_by"] for rid in ("r1", "r2", "r3")
                  for rec in read_records(run_dir / "robots" / rid / "records.jsonl")}
        assert {"cloud0", "cloud1"} <= served  # robots spread over both nodes
        tel = rep["telemetry"]
        assert tel["ods"] == rep["ods"]["store"]
        assert tel["sent"] > 0 and tel["stored"] + tel["queued"] == tel["sent"] and tel["lost"] == 0, tel
        # both cloud nodes logged the same store, and the server is gone
        for name in ("cloud", "cloud1"):
            assert "(postgresql)" in (run_dir / "logs" / f"{name}.log").read_text()
        sock = rep["ods"]["store"].split("host=", 1)[1].split("&", 1)[0]  # the run's own server
        assert not _procs_mentioning(f"unix_socket_directories={sock}"), "the run's PostgreSQL outlived it"
        assert not _procs_mentioning(str(run_dir))
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
        for pid in _procs_mentioning(str(run_dir)):
            try:
                __import__("os").kill(pid, 9)
            except ProcessLookupError:
                pass


@pytest.mark.timeout(180)
def test_database_down_mid_run_robot_keeps_records_until_it_is_back(tmp_path):
    """No leader: while the database is stopped nothing can store telemetry, so the robot's queue holds it."""
    from scmr_mesh.fleet.pgserver import PgServer

    pg = PgServer(tmp_path / "pg")
    dsn = pg.start()
    procs = []
    cport = free_port()
    qdir = tmp_path / "queue"
    try:
        ready = tmp_path / "cloud.ready"
        cloud = spawn_peer(["cloud", "--insecure", "--node", "cloud0", "--listen", _ep(cport), "--workers", "1", "--process",
                            STUB, "--lease-ms", LEASE, "--ready-file", str(ready), "--ods", dsn],
                           log_path=tmp_path / "cloud.log")
        procs.append(cloud)
        wait_for(lambda: ready.exists() or cloud.poll() is not None, timeout=60, what="cloud ready")
        assert cloud.poll() is None, (tmp_path / "cloud.log").read_text()
        robot = spawn_peer(["robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--rate", "10", "--duration", "60",
                            "--out", str(tmp_path / "r1"), "--process", STUB, "--no-local-fallback",
                            "--lease-ms", LEASE, "--quiet", "--telemetry-queue", str(qdir), "--connect", _ep(cport)],
                           log_path=tmp_path / "r1.log")
        procs.append(robot)

        def stored() -> int:
            with OperationalDataStore(dsn, readonly=True) as ods:
                return ods.counts().get("r1", {}).get("stored", 0)

        wait_for(lambda: pg.alive() and _ods_ready(dsn) and stored() >= 5, timeout=60, what="telemetry stored")
        pg.stop()
        # frames are still served (they need no database); telemetry piles up in the robot's queue
        n_records = len(read_records(tmp_path / "r1" / "records.jsonl"))
        wait_for(lambda: _depth(qdir) >= 15 and len(read_records(tmp_path / "r1" / "records.jsonl")) >= n_records + 15,
                 timeout=60, what="the robot to queue telemetry while the database is down")
        log = (tmp_path / "cloud.log").read_text()
        errors = [ln for ln in log.splitlines() if "ODS:" in ln and "unreachable" in ln]
        assert len(errors) == 1, errors  # one line when it went away, not one per batch
        pg.start()
        wait_for(lambda: _depth(qdir) <= 2, timeout=60, what="the queue to drain once the database is back")
        stop_peer(robot, timeout=15)
        summary = json.loads((tmp_path / "r1" / "telemetry.json").read_text())
        assert summary["queued"] == 0 and summary["acked_by"]["cloud"] == summary["sent"]
        with OperationalDataStore(dsn, readonly=True) as ods:
            assert ods.seqs("r1") == list(range(1, summary["sent"] + 1))  # every record, once
        assert "reachable again" in (tmp_path / "cloud.log").read_text()
    finally:
        for p in procs:
            stop_peer(p, timeout=10)
        pg.remove()


def _ods_ready(dsn: str) -> bool:
    try:
        OperationalDataStore(dsn, readonly=True).close()
        return True
    except Exception:
        return False


def _depth(qdir: Path) -> int:
    try:
        with TelemetryQueue(qdir, readonly=True) as q:
            return q.stats().depth
    except Exception:
        return 0


@pytest.mark.timeout(120)
def test_leader_syncs_from_every_live_cloud_not_only_the_first_by_name(tmp_path):
    """cloud0 and cloud1 hold different shared entries; the leader's copy gets cloud1's too,
    and keeps syncing from cloud1 after cloud0 is gone."""
    import msgpack

    from scmr_mesh.mesh.config import MeshConfig, close_session, open_session

    ports = {n: free_port() for n in ("cloud0", "cloud1", "leader0")}
    procs = []

    def start(role, node, *extra):
        ready = tmp_path / f"{node}.ready"
        p = spawn_peer([role, "--insecure", "--node", node, "--listen", _ep(ports[node]), "--workers", "1", "--process", STUB,
                        "--lease-ms", LEASE, "--ready-file", str(ready), *extra], log_path=tmp_path / f"{node}.log")
        procs.append(p)
        wait_for(lambda: ready.exists() or p.poll() is not None, timeout=60, what=f"{node} ready")
        assert p.poll() is None, (tmp_path / f"{node}.log").read_text()
        return p

    for i, node in enumerate(("cloud0", "cloud1")):
        params = tmp_path / f"{node}.json"
        params.write_text(json.dumps({f"params/{node}": i}))
        start("cloud", node, "--data-params", str(params), "--ods", str(tmp_path / "ods.sqlite"))
    start("leader", "leader0", "--sync-period", "0.2", "--connect", _ep(ports["cloud0"]),
          "--connect", _ep(ports["cloud1"]), "--relay-dir", str(tmp_path / "relay"))
    session = open_session(MeshConfig(connect=[_ep(ports["leader0"])],
                                      cfg=["scouting/gossip/enabled:false"]))

    def leader_items() -> dict:
        for reply in session.get("scmr/data/leader/leader0/buffer", payload=msgpack.packb({"sel": "params/**"}),
                                 timeout=2.0):
            if reply.ok is not None:
                return msgpack.unpackb(reply.ok.payload.to_bytes())["items"]
        return {}

    try:
        wait_for(lambda: leader_items() == {"params/cloud0": 0, "params/cloud1": 1}, timeout=30,
                 what="the leader's copy to hold both nodes' entries")
        stop_peer(procs[0], timeout=10)  # cloud0 (first by name) gone: sync goes on from cloud1
        params = tmp_path / "cloud1-again.json"
        params.write_text(json.dumps({"params/cloud1": 2, "params/late": 3}))
        stop_peer(procs[1], timeout=10)
        start("cloud", "cloud1", "--data-params", str(params), "--ods", str(tmp_path / "ods.sqlite"))
        wait_for(lambda: leader_items().get("params/late") == 3, timeout=30,
                 what="the leader to sync from cloud1 alone")
        assert leader_items()["params/cloud1"] == 2
    finally:
        close_session(session)
        for p in procs:
            stop_peer(p, timeout=10)
