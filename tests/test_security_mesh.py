"""Break-in attempts against an authenticated mesh, with real peer processes.

Each peer is this file run as a script (``python test_security_mesh.py agent ...``): a
Zenoh peer that joins with a security profile, serves / subscribes / publishes / queries
as told and prints JSON lines.  One scenario runs a cloud, an honest robot, a rogue robot
(valid robot certificate, declares drivable queryables and a fake cloud liveliness token)
and two strangers (plain TCP; TLS with a certificate from another CA that claims to be
``robot1``), all at once; the tests check what each saw.  The same scenario without ACL
is the control: there the rogue's attacks work, so these tests can fail.

About 8 s in total.  Run alone with ``pytest -m security``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import free_port  # noqa: E402

pytestmark = pytest.mark.security

HERE = Path(__file__).resolve()


# ----------------------------------------------------------------------------- agent
def agent(argv: list[str]) -> int:
    """A scripted peer (runs in its own process)."""
    import argparse
    import threading

    import zenoh

    from scmr_mesh.mesh.security import secure_config
    from scmr_mesh.security.profile import SecurityProfile

    ap = argparse.ArgumentParser()
    ap.add_argument("--kind", default="tls")
    ap.add_argument("--creds")
    ap.add_argument("--acl", action="store_true")
    ap.add_argument("--id", required=True)
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--serve", action="append", default=[])
    ap.add_argument("--sub", action="append", default=[])
    ap.add_argument("--pub", action="append", default=[])
    ap.add_argument("--query", action="append", default=[])
    ap.add_argument("--token", action="append", default=[])
    ap.add_argument("--alive", default=None, help="liveliness key expr to list")
    ap.add_argument("--delay", type=float, default=0.0,
                    help="seconds to wait before acting (peers that are expected never to connect)")
    ap.add_argument("--peers", type=int, default=None,
                    help="before acting, wait until this many peers are connected (at most 60 s)")
    ap.add_argument("--mode", default="peer", help="zenoh mode: peer, client (of a router) or router")
    ap.add_argument("--await-alive", default=None,
                    help="before acting, wait until this liveliness key is seen (at most 60 s)")
    ap.add_argument("--duration", type=float, default=2.0)
    ap.add_argument("--hold", action="store_true",
                    help="after the duration, keep serving until stdin is closed (the harness decides when)")
    a = ap.parse_args(argv)
    lock = threading.Lock()

    def out(**kw):
        with lock:
            print(json.dumps(kw), flush=True)

    prof = None if a.kind == "none" else SecurityProfile(kind=a.kind, credentials=Path(a.creds), acl=a.acl)
    conf = secure_config(prof, identity=a.id, listen=a.listen, connect=a.connect, lease_ms=1000, mode=a.mode)
    with zenoh.open(conf) as s:
        keep = []
        for k in a.serve:
            keep.append(s.declare_queryable(
                k, lambda q: q.reply(q.key_expr, f"served-by-{a.id}".encode()), complete=True))
        for k in a.sub:
            keep.append(s.declare_subscriber(
                k, lambda smp: out(ev="sample", key=str(smp.key_expr),
                                   payload=smp.payload.to_bytes().decode())))
        for k in a.token:
            keep.append(s.liveliness().declare_token(k))
        out(ev="ready")
        if a.peers is not None:  # a condition: the links this peer is expected to have
            end = time.time() + 60
            while len(list(s.info.peers_zid())) < a.peers and time.time() < end:
                time.sleep(0.02)
        if a.await_alive:
            end = time.time() + 60
            while time.time() < end and a.await_alive not in {
                    str(r.ok.key_expr) for r in s.liveliness().get(a.await_alive, timeout=0.5) if r.ok}:
                time.sleep(0.05)
        time.sleep(a.delay)
        out(ev="peers", n=len(list(s.info.peers_zid())))
        if a.alive:
            out(ev="alive", keys=sorted(str(r.ok.key_expr) for r in s.liveliness().get(a.alive, timeout=1.0) if r.ok))
        t_end = time.time() + a.duration
        while time.time() < t_end:
            for k in a.pub:
                s.put(k, f"from-{a.id}")
            for k in a.query:
                res = [r.ok.payload.to_bytes().decode() if r.ok else "ERR" for r in s.get(k, timeout=0.5)]
                out(ev="reply", key=k, replies=res)
            time.sleep(0.15)
        if a.hold:
            sys.stdin.read()  # until the harness closes stdin: everyone else has finished
        out(ev="done")
    return 0


# ----------------------------------------------------------------------------- harness
class Agent:
    """A running agent process whose JSON lines are collected as they come."""

    def __init__(self, args: list[str]) -> None:
        import threading

        env = dict(os.environ)
        env.pop("RUST_LOG", None)
        self.proc = subprocess.Popen(
            [sys.executable, str(HERE), "agent", *args],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
            start_new_session=True, env=env,
        )
        self.events: list[dict] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            try:
                self.events.append(json.loads(line))
            except ValueError:
                pass

    def wait_event(self, ev: str, timeout: float = 60.0) -> None:
        """Wait for a line ``{"ev": ev}`` (the condition), e.g. "ready"."""
        end = time.monotonic() + timeout
        while not any(e.get("ev") == ev for e in self.events):
            if self.proc.poll() is not None and not self._reader.is_alive():
                raise AssertionError(f"agent exited before {ev!r}: {self.events}")
            if time.monotonic() > end:
                raise AssertionError(f"agent did not say {ev!r} within {timeout:g} s: {self.events}")
            time.sleep(0.02)

    def finish(self, timeout: float = 60.0) -> list[dict]:
        """Close stdin (ends --hold), wait for the process, return its events."""
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self._reader.join(timeout=10)
        return self.events

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()


def _run_scenario(creds: Path, other_ca: Path, *, acl: bool) -> dict[str, list[dict]]:
    """Cloud + robot1 + rogue + two strangers, concurrently; returns each one's events.

    Ordered by conditions, not by timing: the cloud and the rogue serve until every
    other agent is done (``--hold``), robot1 acts once it has its 2 links (``--peers``);
    only the strangers, who must never connect, act after a fixed delay.
    """
    pc, pr, prg = free_port(), free_port(), free_port()
    cloud_ep, robot_ep, rogue_ep = (f"tcp/127.0.0.1:{p}" for p in (pc, pr, prg))
    base = ["--creds", str(creds)] + (["--acl"] if acl else [])
    agents: dict[str, Agent] = {}
    try:
        agents["cloud"] = Agent(base + [
            "--id", "cloud", "--listen", cloud_ep, "--serve", "scmr/drivable/cloud/cloud/*",
            "--sub", "scmr/telemetry/*", "--token", "scmr/alive/cloud/cloud", "--duration", "0", "--hold"])
        agents["cloud"].wait_event("ready")
        agents["rogue"] = Agent(base + [
            "--id", "rogue", "--listen", rogue_ep, "--connect", cloud_ep, "--connect", robot_ep,
            "--serve", "scmr/drivable/leader/leader/*", "--serve", "scmr/drivable/cloud/cloud/*",
            "--token", "scmr/alive/cloud/fake", "--sub", "scmr/telemetry/*",
            "--pub", "scmr/telemetry/robot1", "--peers", "1", "--duration", "1.5", "--hold"])
        agents["rogue"].wait_event("ready")
        agents["robot1"] = Agent(base + [
            "--id", "robot1", "--listen", robot_ep, "--connect", cloud_ep, "--connect", rogue_ep,
            "--pub", "scmr/telemetry/robot1", "--pub", "scmr/telemetry/robot2",
            "--query", "scmr/drivable/cloud/cloud/robot1", "--query", "scmr/drivable/leader/leader/robot1",
            "--alive", "scmr/alive/**", "--peers", "2", "--duration", "1.5"])
        # strangers: no TLS at all; TLS with a certificate from another CA (CN robot1)
        agents["plain"] = Agent([
            "--kind", "none", "--id", "plain", "--connect", cloud_ep, "--connect", robot_ep,
            "--pub", "scmr/telemetry/robot1", "--query", "scmr/drivable/cloud/cloud/robot1",
            "--delay", "1.0", "--duration", "1.0"])
        agents["forged"] = Agent([
            "--creds", str(other_ca), "--id", "robot1", "--connect", cloud_ep, "--connect", robot_ep,
            "--pub", "scmr/telemetry/robot2", "--query", "scmr/drivable/cloud/cloud/robot1",
            "--delay", "1.0", "--duration", "1.0"])
        out = {name: agents[name].finish() for name in ("robot1", "plain", "forged")}
        out["rogue"] = agents["rogue"].finish()
        out["cloud"] = agents["cloud"].finish()
        return out
    finally:
        for a in agents.values():
            a.kill()


@pytest.fixture(scope="module")
def credentials(tmp_path_factory):
    from scmr_mesh.security.credentials import create_credentials

    d = tmp_path_factory.mktemp("creds")
    create_credentials(d / "fleet", "cloud,leader,robot1,robot2,rogue,router0")
    create_credentials(d / "other", "cloud,robot1,robot2")  # a different CA
    return d / "fleet", d / "other"


@pytest.fixture(scope="module")
def secured(credentials):
    return _run_scenario(*credentials, acl=True)


@pytest.fixture(scope="module")
def control(credentials):
    return _run_scenario(*credentials, acl=False)


def _replies(evs, key):
    return [r for e in evs if e["ev"] == "reply" and e["key"] == key for r in e["replies"]]


def _samples(evs):
    return [(e["key"], e["payload"]) for e in evs if e["ev"] == "sample"]


def _peers(evs):
    return [e["n"] for e in evs if e["ev"] == "peers"]


# ----------------------------------------------------------------------------- tests
def test_credentialed_robot_is_served(secured):
    got = _replies(secured["robot1"], "scmr/drivable/cloud/cloud/robot1")
    assert got and set(got) == {"served-by-cloud"}
    assert ("scmr/telemetry/robot1", "from-robot1") in _samples(secured["cloud"])


@pytest.mark.parametrize("stranger", ["plain", "forged"])
def test_peer_without_credentials_cannot_join(secured, stranger):
    evs = secured[stranger]
    assert _peers(evs) == [0], f"{stranger} joined the mesh: {evs}"
    assert _replies(evs, "scmr/drivable/cloud/cloud/robot1") == []
    assert f"from-{stranger}" not in [p for _, p in _samples(secured["cloud"])]
    # the forged peer claims to be robot1 and publishes robot2's telemetry: never seen
    assert ("scmr/telemetry/robot2", "from-robot1") not in _samples(secured["cloud"])


def test_robot_cannot_publish_another_robots_telemetry(secured, control):
    keys = {k for k, p in _samples(secured["cloud"]) if p == "from-robot1"}
    assert keys == {"scmr/telemetry/robot1"}
    # the rogue (a valid robot identity) publishing robot1's telemetry is dropped too
    assert ("scmr/telemetry/robot1", "from-rogue") not in _samples(secured["cloud"])
    # control: without ACL the spoofed telemetry arrives, so the check above can fail
    assert ("scmr/telemetry/robot2", "from-robot1") in _samples(control["cloud"])


def test_robot_cannot_read_other_robots_telemetry(secured, control):
    assert [s for s in _samples(secured["rogue"]) if s[1] == "from-robot1"] == []
    assert [s for s in _samples(control["rogue"]) if s[1] == "from-robot1"] != []


def test_rogue_drivable_queryable_never_answers(secured, control):
    robot = secured["robot1"]
    assert _peers(robot) == [2]  # the rogue holds a valid certificate and is connected
    assert _replies(robot, "scmr/drivable/leader/leader/robot1") == []
    assert "served-by-rogue" not in _replies(robot, "scmr/drivable/cloud/cloud/robot1")
    # control: without ACL the rogue answers the robot
    assert "served-by-rogue" in _replies(control["robot1"], "scmr/drivable/leader/leader/robot1")


def test_rogue_cannot_fake_a_cloud_liveliness_token(secured, control):
    alive = [e["keys"] for e in secured["robot1"] if e["ev"] == "alive"]
    assert alive == [["scmr/alive/cloud/cloud"]]
    alive_ctl = [e["keys"] for e in control["robot1"] if e["ev"] == "alive"]
    assert "scmr/alive/cloud/fake" in alive_ctl[0]


def test_usrpwd_keeps_out_peers_without_password(credentials, tmp_path):
    creds, _ = credentials
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    agents: dict[str, Agent] = {}
    try:
        agents["cloud"] = Agent(["--kind", "usrpwd", "--creds", str(creds), "--id", "cloud",
                                 "--listen", ep, "--serve", "scmr/drivable/cloud/cloud/*", "--duration", "0", "--hold"])
        agents["cloud"].wait_event("ready")
        agents["robot1"] = Agent(["--kind", "usrpwd", "--creds", str(creds), "--id", "robot1",
                                  "--connect", ep, "--query", "scmr/drivable/cloud/cloud/robot1",
                                  "--peers", "1", "--duration", "0.6"])
        agents["none"] = Agent(["--kind", "none", "--id", "x", "--connect", ep,
                                "--query", "scmr/drivable/cloud/cloud/robot1", "--delay", "0.5", "--duration", "0.6"])
        # robot2's name with robot1's password
        wrong = tmp_path / "wrong"
        import shutil
        shutil.copytree(creds, wrong)
        (wrong / "robot2" / "password").write_text((creds / "robot1" / "password").read_text())
        agents["wrong"] = Agent(["--kind", "usrpwd", "--creds", str(wrong), "--id", "robot2",
                                 "--connect", ep, "--query", "scmr/drivable/cloud/cloud/robot1",
                                 "--delay", "0.5", "--duration", "0.6"])
        evs = {k: agents[k].finish() for k in ("robot1", "none", "wrong", "cloud")}
    finally:
        for a in agents.values():
            a.kill()
    assert _peers(evs["robot1"]) == [1]
    assert "served-by-cloud" in _replies(evs["robot1"], "scmr/drivable/cloud/cloud/robot1")
    for k in ("none", "wrong"):
        assert _peers(evs[k]) == [0], k
        assert _replies(evs[k], "scmr/drivable/cloud/cloud/robot1") == [], k


def _behind_router(creds: Path, *, acl: bool) -> dict[str, list[dict]]:
    """A router (the multi-hop tier's shape) with the cloud, a rogue and robot1 as its clients.

    The rogue holds a valid robot certificate and, as in issue 25 item 4, declares a
    cloud token and answers on the cloud's keys.  Ordered by conditions: the rogue
    first, then the cloud, and robot1 acts once the cloud's token reaches it.
    """
    ep = f"tcp/127.0.0.1:{free_port()}"
    base = ["--creds", str(creds)] + (["--acl"] if acl else [])
    agents: dict[str, Agent] = {}
    try:
        agents["router0"] = Agent(base + ["--id", "router0", "--mode", "router", "--listen", ep,
                                          "--duration", "0", "--hold"])
        agents["router0"].wait_event("ready")
        agents["rogue"] = Agent(base + [
            "--id", "rogue", "--mode", "client", "--connect", ep, "--serve", "scmr/drivable/cloud/cloud/*",
            "--serve", "scmr/drivable/cloud/fake/*", "--token", "scmr/alive/cloud/fake",
            "--duration", "0", "--hold"])
        agents["rogue"].wait_event("ready")
        agents["cloud"] = Agent(base + [
            "--id", "cloud", "--mode", "client", "--connect", ep, "--serve", "scmr/drivable/cloud/cloud/*",
            "--token", "scmr/alive/cloud/cloud", "--duration", "0", "--hold"])
        agents["cloud"].wait_event("ready")
        agents["robot1"] = Agent(base + [
            "--id", "robot1", "--mode", "client", "--connect", ep, "--await-alive", "scmr/alive/cloud/cloud",
            "--query", "scmr/drivable/cloud/cloud/robot1", "--query", "scmr/drivable/cloud/fake/robot1",
            "--alive", "scmr/alive/**", "--duration", "1.5"])
        out = {"robot1": agents["robot1"].finish()}
        for k in ("rogue", "cloud", "router0"):
            out[k] = agents[k].finish()
        return out
    finally:
        for a in agents.values():
            a.kill()


def test_a_router_enforces_the_fleets_rules_for_its_clients(credentials):
    """Issue 25 item 4, closed in the design: a client attached to a router that enforces the
    fleet's rules (every router of the multi-hop tier does) cannot be fooled by a robot certificate
    playing the cloud, whatever the client checks itself.  Control: the same without the rules."""
    creds, _ = credentials
    secured = _behind_router(creds, acl=True)
    alive = [e["keys"] for e in secured["robot1"] if e["ev"] == "alive"]
    assert alive and "scmr/alive/cloud/fake" not in alive[0] and "scmr/alive/cloud/cloud" in alive[0]
    real = _replies(secured["robot1"], "scmr/drivable/cloud/cloud/robot1")
    assert real and set(real) == {"served-by-cloud"}  # the rogue's answers on the cloud's key never arrive
    assert _replies(secured["robot1"], "scmr/drivable/cloud/fake/robot1") == []
    control = _behind_router(creds, acl=False)
    alive_ctl = [e["keys"] for e in control["robot1"] if e["ev"] == "alive"]
    assert "scmr/alive/cloud/fake" in alive_ctl[0]
    assert "served-by-rogue" in _replies(control["robot1"], "scmr/drivable/cloud/cloud/robot1")


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "agent":
    sys.exit(agent(sys.argv[2:]))


def test_real_peers_with_security_profile(credentials, tmp_path, repo_root):
    """`scmr cloud` / `scmr robot --security peers/secure/mtls.toml`: served; without it: not."""
    from scmr_mesh.mesh.testing import (
        STUB,
        read_records,
        spawn_peer,
        stop_peer,
        wait_for,
    )

    creds, _ = credentials
    profile = str(repo_root / "peers" / "secure" / "mtls.toml")
    ep = f"tcp/127.0.0.1:{free_port()}"
    env = {"SCMR_CREDENTIALS": str(creds)}
    peers = []
    try:
        cloud = spawn_peer(["cloud", "--node", "cloud", "--listen", ep, "--workers", "1", "--process", STUB,
                            "--security", profile, "--ready-file", str(tmp_path / "c.ready"),
                            "--ods", str(tmp_path / "ods.sqlite")], log_path=tmp_path / "c.log", env=env)
        peers.append(cloud)
        wait_for(lambda: (tmp_path / "c.ready").exists() or cloud.poll() is not None, timeout=60, what="cloud")
        assert cloud.poll() is None, (tmp_path / "c.log").read_text()[-1500:]
        common = ["--connect", ep, "--synthetic", "stub", "--count", "3", "--rate", "10",
                  "--no-local-fallback", "--quiet"]
        # the good robot waits for the cloud's token (a condition; returns when seen), the bad one
        # never sees it: it waits 1.5 s and then fails every request
        good = spawn_peer(["robot", "--id", "robot1", "--security", profile, "--out", str(tmp_path / "r1"),
                           *common, "--wait-ms", "60000"], log_path=tmp_path / "r1.log", env=env)
        bad = spawn_peer(["robot", "--insecure", "--id", "robot2", "--out", str(tmp_path / "r2"), *common, "--wait-ms", "1500"],
                         log_path=tmp_path / "r2.log", env=env)
        peers += [good, bad]
        wait_for(lambda: good.poll() is not None and bad.poll() is not None, timeout=40, what="robots")
    finally:
        for p in reversed(peers):
            stop_peer(p, timeout=5)
    ok1 = [r["ok"] for r in read_records(tmp_path / "r1" / "records.jsonl")]
    ok2 = [r["ok"] for r in read_records(tmp_path / "r2" / "records.jsonl")]
    assert ok1 == [True, True, True], (tmp_path / "r1.log").read_text()[-1500:]
    assert ok2 and not any(ok2)
