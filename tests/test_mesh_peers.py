"""Real cloud / leader / robot processes on loopback (multicast off, free ports).

Services run the stub process function (scmr_mesh.mesh.testing), so these
tests exercise the mesh, not the pipeline.  About 30-40 s on a 2-core box.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
from conftest import free_port

from scmr_mesh.mesh.testing import (
    SLOW,
    STUB,
    read_records,
    spawn_peer,
    stop_peer,
    wait_for,
)

LEASE = "300"


class Fleet:
    """Start peers, remember them, stop them all at the end (also on failure)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: dict[str, object] = {}

    def service(self, role: str, node: str, port: int, *, connect=(), process=STUB, extra=(), env=None, wait=True):
        ready = self.tmp / f"{node}.ready"
        args = [role, "--insecure", "--node", node, "--listen", f"tcp/127.0.0.1:{port}", "--workers", "1",
                "--process", process, "--lease-ms", LEASE, "--ready-file", str(ready), *extra]
        for ep in connect:
            args += ["--connect", ep]
        p = spawn_peer(args, log_path=self.tmp / f"{node}.log", env=env)
        self.procs[node] = p
        if wait:
            wait_for(lambda: ready.exists() or p.poll() is not None, timeout=120, what=f"{node} ready")
            assert p.poll() is None, (self.tmp / f"{node}.log").read_text()
        return p

    def robot(self, rid: str, connect, *, extra=()):
        source = [] if "--images" in extra else ["--synthetic", "stub"]
        args = ["robot", "--insecure", "--id", rid, *source, "--out", str(self.tmp / rid), "--process", STUB,
                "--lease-ms", LEASE, *extra]
        for ep in connect:
            args += ["--connect", ep]
        p = spawn_peer(args, log_path=self.tmp / f"{rid}.log")
        self.procs[rid] = p
        return p

    def records(self, rid: str) -> list[dict]:
        return read_records(self.tmp / rid / "records.jsonl")

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text(errors="replace")

    def stop_all(self) -> None:
        for p in self.procs.values():
            stop_peer(p, timeout=5)


@pytest.fixture
def fleet(tmp_path):
    f = Fleet(tmp_path)
    try:
        yield f
    finally:
        f.stop_all()


def _ep(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is dead for our purposes
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def test_normal_service_and_leader_crash_has_no_effect(fleet):
    cp, lp = free_port(), free_port()
    fleet.service("cloud", "c1", cp)
    leader = fleet.service("leader", "L1", lp, connect=[_ep(cp)])
    robot = fleet.robot("r1", [_ep(cp), _ep(lp)], extra=["--count", "30", "--rate", "25"])
    wait_for(lambda: len(fleet.records("r1")) >= 8, what="8 records")
    stop_peer(leader, sig=signal.SIGKILL)
    assert robot.wait(timeout=90) == 0, fleet.log("r1")
    recs = fleet.records("r1")
    assert [r["seq"] for r in recs] == list(range(30))
    assert all(r["ok"] and r["tier"] == "cloud" and r["served_by"] == "c1" for r in recs)
    for r in recs:
        assert r["sent_unix_ns"] <= r["received_unix_ns"]
        assert r["bytes_up"] > 0 and r["bytes_down"] > 0 and r["tor_ms"] > 0
        # (on a loaded box a slow cloud answer may be hedged to the leader; the cloud's answer still won)
        assert r["attempts"][0]["outcome"] == "ok" and r["attempts"][0]["tier"] == "cloud", r["attempts"]
        assert all(a.get("hedge") and a["outcome"] != "ok" for a in r["attempts"][1:]), r["attempts"]
        assert (fleet.tmp / "r1" / "inbox" / f"{r['seq']}.mask.png").exists()
    assert list((fleet.tmp / "r1" / "outbox").iterdir()) == []
    summary = [json.loads(x) for x in fleet.log("r1").splitlines() if x.startswith('{"robot"')][-1]
    assert summary["succeeded"] == 30 and summary["by_tier"]["cloud"] == 30


def test_cloud_sigkill_and_restart_every_request_answered(fleet):
    cp, lp = free_port(), free_port()
    # a slow cloud keeps requests in flight, so the kill lands mid-request
    env = {"SCMR_STUB_DELAY_MS": "60"}
    cloud = fleet.service("cloud", "c1", cp, process=SLOW, env=env)
    workers = json.loads((fleet.tmp / "c1.ready").read_text())["workers"]
    fleet.service("leader", "L1", lp, connect=[_ep(cp)])
    robot = fleet.robot("r1", [_ep(cp), _ep(lp)], extra=["--rate", "12", "--deadline-ms", "2000"])
    wait_for(lambda: len(fleet.records("r1")) >= 8, what="8 records before the crash")
    os.kill(cloud.pid, signal.SIGKILL)  # the service process only: its workers must die with it
    cloud.wait(timeout=5)
    t_kill = time.time_ns()
    wait_for(lambda: not any(_pid_alive(p) for p in workers), timeout=5, what="cloud workers to exit")
    n_kill = len(fleet.records("r1"))
    wait_for(lambda: len(fleet.records("r1")) >= n_kill + 8, what="records during the outage")
    (fleet.tmp / "c1.ready").unlink(missing_ok=True)
    fleet.service("cloud", "c1", cp, process=SLOW, env=env)
    wait_for(lambda: [r["tier"] for r in fleet.records("r1")][-5:] == ["cloud"] * 5, timeout=90,
             what="5 cloud answers after the restart")
    assert stop_peer(robot) == 0, fleet.log("r1")
    recs = fleet.records("r1")
    assert all(r["ok"] for r in recs), [r for r in recs if not r["ok"]]
    tiers = [r["tier"] for r in recs]
    assert set(tiers) <= {"cloud", "leader"}
    # (a leader answer while the cloud is up is a hedge of a cloud slow to answer on a loaded box)
    assert all(r["tier"] == "cloud" or r["hedge_won"] for r in recs[:5])
    assert "leader" in tiers
    after = [r for r in recs if r["sent_unix_ns"] > t_kill + 50_000_000]
    first_cloud_again = next(i for i, r in enumerate(after) if r["tier"] == "cloud")
    assert all(r["tier"] == "leader" for r in after[:first_cloud_again])
    assert all(r["tier"] == "cloud" or r["hedge_won"] for r in after[first_cloud_again:])  # failback sticks
    # no request after the crash waited for the deadline: failover is driven by liveliness
    assert all(a["outcome"] != "timeout" for r in recs for a in r["attempts"])


def test_both_tiers_down_gives_explicit_failures_without_hanging(fleet):
    port = free_port()  # nobody listens there
    robot = fleet.robot("r1", [_ep(port)], extra=["--count", "3", "--rate", "20", "--wait-ms", "100",
                                                 "--no-local-fallback"])
    assert robot.wait(timeout=90) == 0, fleet.log("r1")
    recs = fleet.records("r1")
    assert len(recs) == 3
    assert all(not r["ok"] and r["tier"] is None and r["served_by"] is None and r["error"] for r in recs)
    assert list((fleet.tmp / "r1" / "inbox").iterdir()) == []


def test_local_fallback_when_no_tier(fleet):
    port = free_port()
    robot = fleet.robot("r1", [_ep(port)], extra=["--count", "2", "--wait-ms", "100"])
    assert robot.wait(timeout=90) == 0, fleet.log("r1")
    recs = fleet.records("r1")
    assert [(r["ok"], r["tier"], r["served_by"]) for r in recs] == [(True, "local", "r1")] * 2


def test_robot_started_before_the_cloud(fleet):
    cp = free_port()
    robot = fleet.robot("r1", [_ep(cp)], extra=["--count", "5", "--rate", "20", "--wait-ms", "20000",
                                               "--no-local-fallback"])
    time.sleep(1.0)
    assert robot.poll() is None
    fleet.service("cloud", "c1", cp)
    assert robot.wait(timeout=90) == 0, fleet.log("r1")
    recs = fleet.records("r1")
    assert [(r["ok"], r["tier"]) for r in recs] == [(True, "cloud")] * 5


def test_robot_waits_for_the_start_file(fleet):
    """--start-file (what `scmr up`, `scmr demo` and scenarios use): no frame before the file appears; a stop while waiting is clean."""
    cp = free_port()
    fleet.service("cloud", "c1", cp)
    go = fleet.tmp / "go"
    r1 = fleet.robot("r1", [_ep(cp)], extra=["--count", "3", "--rate", "20", "--start-file", str(go)])
    r2 = fleet.robot("r2", [_ep(cp)], extra=["--count", "3", "--rate", "20", "--start-file", str(go)])
    for rid, p in (("r1", r1), ("r2", r2)):
        wait_for(lambda: "waiting for" in fleet.log(rid) or p.poll() is not None, timeout=90,
                 what=f"{rid} waiting for the start file")
        assert p.poll() is None, fleet.log(rid)
        assert fleet.records(rid) == []
    r2.send_signal(signal.SIGTERM)  # stopped before the start: a normal exit, nothing sent
    assert r2.wait(timeout=60) == 0, fleet.log("r2")
    assert fleet.records("r2") == [] and '"requests": 0' in fleet.log("r2")
    t_go = time.time_ns()
    go.write_text("go\n")
    assert r1.wait(timeout=90) == 0, fleet.log("r1")
    recs = fleet.records("r1")
    assert [(r["ok"], r["tier"]) for r in recs] == [(True, "cloud")] * 3
    assert min(r["sent_unix_ns"] for r in recs) >= t_go


def test_redundant_mode_and_two_cloud_nodes(fleet):
    c1, c2, lp = free_port(), free_port(), free_port()
    fleet.service("cloud", "c1", c1)
    fleet.service("cloud", "c2", c2, connect=[_ep(c1)])
    fleet.service("leader", "L1", lp, connect=[_ep(c1), _ep(c2)])
    ends = [_ep(c1), _ep(c2), _ep(lp)]
    spread = fleet.robot("r1", ends, extra=["--count", "20", "--rate", "20"])
    red = fleet.robot("r2", ends, extra=["--count", "10", "--rate", "10", "--redundant"])
    assert spread.wait(timeout=90) == 0, fleet.log("r1")
    assert red.wait(timeout=90) == 0, fleet.log("r2")
    served = {r["served_by"] for r in fleet.records("r1")}
    assert served == {"c1", "c2"}
    recs = fleet.records("r2")
    assert all(r["ok"] for r in recs)
    # a robot starts once one tier is alive: its first frames may go out before the leader's
    # token has arrived (one attempt); from the first frame sent to both, every frame is
    both = [i for i, r in enumerate(recs) if sorted(a["tier"] for a in r["attempts"]) == ["cloud", "leader"]]
    assert both and both == list(range(both[0], len(recs))), [r["attempts"] for r in recs]
    for r in recs[both[0]:]:
        winner = [a for a in r["attempts"] if a["outcome"] == "ok"]
        assert len(winner) == 1 and winner[0]["tier"] == r["tier"]
    single = fleet.records("r1")[0]["bytes_up"]
    assert all(r["bytes_up"] > 1.5 * single for r in recs[both[0]:])


def test_sigterm_stops_peers_cleanly_and_drains_the_cloud(fleet):
    cp = free_port()
    marks = fleet.tmp / "marks"
    marks.mkdir()
    cloud = fleet.service("cloud", "c1", cp, process=SLOW,
                          env={"SCMR_STUB_DELAY_MS": "300", "SCMR_STUB_MARK_DIR": str(marks)})
    robot = fleet.robot("r1", [_ep(cp)], extra=["--rate", "10"])
    wait_for(lambda: len(fleet.records("r1")) >= 2, what="2 records")
    seen = {p.name for p in marks.iterdir()}

    def frame_in_the_works():  # the cloud began a 300 ms frame < 100 ms ago (not a record yet)
        new = [p.name for p in marks.iterdir() if p.name not in seen]
        return any(time.time_ns() - int(n.split(".")[0]) < 100e6 for n in new)

    wait_for(frame_in_the_works, interval=0.005, what="the cloud working on a frame")
    t_term = time.time_ns()
    assert stop_peer(cloud) == 0  # SIGTERM (to its process group) while the cloud works on a frame
    n = len(fleet.records("r1"))
    wait_for(lambda: len(fleet.records("r1")) >= n + 2, what="2 records after the cloud stopped")
    assert stop_peer(robot) == 0
    recs = fleet.records("r1")
    assert all(r["ok"] for r in recs)
    # the frame in flight was answered by the draining cloud, not re-sent
    assert all(a["outcome"] != "no_reply" for r in recs for a in r["attempts"])
    assert any(r["tier"] == "cloud" and r["received_unix_ns"] > t_term for r in recs)  # drained
    tiers = [r["tier"] for r in recs]
    k = tiers.index("local")
    assert set(tiers[:k]) == {"cloud"} and set(tiers[k:]) == {"local"}
    assert not (fleet.tmp / "c1.ready").exists()
    assert "Traceback" not in fleet.log("c1") + fleet.log("r1")


def test_dead_worker_costs_at_most_a_resend(fleet):
    """A killed worker breaks the pool; the service replaces it and keeps serving
    (work.WorkerPool._respawn); the request it died on goes to the leader."""
    cp, lp = free_port(), free_port()
    cloud = fleet.service("cloud", "c1", cp)
    worker = json.loads((fleet.tmp / "c1.ready").read_text())["workers"][0]
    fleet.service("leader", "L1", lp, connect=[_ep(cp)])
    robot = fleet.robot("r1", [_ep(cp), _ep(lp)], extra=["--rate", "20", "--no-local-fallback"])
    wait_for(lambda: len(fleet.records("r1")) >= 5, what="5 records")
    os.kill(worker, signal.SIGKILL)
    n = len(fleet.records("r1"))
    wait_for(lambda: [r["tier"] for r in fleet.records("r1")[n:]][-5:] == ["cloud"] * 5, timeout=60,
             what="5 cloud answers after the worker died")
    assert stop_peer(robot) == 0
    assert cloud.poll() is None
    recs = fleet.records("r1")
    assert all(r["ok"] for r in recs)
    # only the frames around the worker's death (the one it died on, any sent while the pool
    # was being replaced) left the cloud, each after an explicit cloud failure or, when the cloud
    # stayed silent past the hedge delay, as a hedge to the leader (issue 24)
    off = [i for i, r in enumerate(recs) if r["tier"] != "cloud"]
    assert off == list(range(off[0], off[0] + len(off))) if off else True
    for i in off:
        assert recs[i]["tier"] == "leader"
        first = recs[i]["attempts"][0]["outcome"]
        assert first in ("error:internal", "timeout", "no_reply") or (first == "superseded" and recs[i]["hedge_won"]), \
            recs[i]["attempts"]


def test_second_cloud_node_is_a_warm_standby(fleet):
    c1, c2 = free_port(), free_port()
    first = fleet.service("cloud", "c1", c1)
    fleet.service("cloud", "c2", c2, connect=[_ep(c1)])
    robot = fleet.robot("r1", [_ep(c1), _ep(c2)], extra=["--rate", "20", "--no-local-fallback"])
    wait_for(lambda: {r["served_by"] for r in fleet.records("r1")} == {"c1", "c2"}, what="both clouds serving")
    stop_peer(first, sig=signal.SIGKILL)
    n = len(fleet.records("r1"))
    wait_for(lambda: len(fleet.records("r1")) >= n + 8, what="8 records after the kill")
    assert stop_peer(robot) == 0
    recs = fleet.records("r1")
    assert all(r["ok"] and r["tier"] == "cloud" for r in recs)
    assert {r["served_by"] for r in recs[n + 1:]} == {"c2"}


def test_real_pipeline_end_to_end(fleet, roads_dir):
    """The drivable pipeline (not the stub) behind the mesh, on real road frames."""
    import cv2

    cp = free_port()
    fleet.service("cloud", "c1", cp, process="scmr_mesh.mesh.work:process_frame")
    robot = fleet.robot("r1", [_ep(cp)], extra=["--images", str(roads_dir / "images"), "--count", "3",
                                               "--rate", "10", "--no-local-fallback"])
    assert robot.wait(timeout=120) == 0, fleet.log("r1")
    recs = fleet.records("r1")
    assert [(r["ok"], r["tier"]) for r in recs] == [(True, "cloud")] * 3
    names = sorted(p.name for p in (roads_dir / "images").iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    assert [r["image"] for r in recs] == names[:3]
    for r in recs:
        # the PNG files go out as JPEG (--jpeg-quality 90 by default): well under the file's size
        assert 0 < r["bytes_up"] < (roads_dir / "images" / r["image"]).stat().st_size / 2
        mask = cv2.imread(str(fleet.tmp / "r1" / "inbox" / f"{r['seq']}.mask.png"), cv2.IMREAD_UNCHANGED)
        assert mask.shape == (225, 300) and set(map(int, set(mask.ravel().tolist()))) <= {0, 255}
