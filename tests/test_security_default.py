"""Secure by default (issue #13), with real processes.  Run with ``pytest -m security``.

1. The issue's stranger against the default ``scmr up``: with Zenoh's default config and
   no credentials it dials every port of the fleet, declares the token
   ``scmr/alive/cloud/aaa``, a queryable answering every frame with an all-drivable map,
   a data queryable acknowledging every telemetry batch, and publishes a heavy load for
   ``cloud0``.  Against the default fleet it gets no link, no frame and no telemetry, and
   no robot record is served by it.  The same stranger against ``scmr up --insecure`` (the
   control) is sent frames, so the assertions can fail.
2. A credentialed robot (robot2's certificate) names another robot: a request naming
   robot1 on its own key is refused ``forbidden``; on robot1's key, or on a wildcard
   selector, it gets no reply (access rules); its own request is served at the fleet's
   priority cap.  Control with ``mtls-noacl``: robot1's key answers.
3. The decompression bombs sent to a real cloud: refused from their headers (7000x7000
   JPEG, 4K PNG) or decoded at 1/8 scale (4K JPEG); the cloud's workers stay small and the
   cloud keeps serving.
4. The R2R tier under mutual TLS and the access rules: a plain robot's forged candidacy
   (a huge term, published as itself and as the leader) takes no lead, its leader queryable
   gets no frame; control with ``mtls-noacl``: the forgery makes the leader step down.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from conftest import free_port

from scmr_mesh import keys, wire
from scmr_mesh.mesh.testing import STUB, read_records, spawn_peer, stop_peer, synthetic_png, wait_for
from scmr_mesh.security.credentials import create_credentials

pytestmark = pytest.mark.security


# ------------------------------------------------------------------ 1. the stranger
class Stranger:
    """The issue's attacker: Zenoh defaults, no credentials, a fake cloud ``aaa``."""

    def __init__(self) -> None:
        import cv2
        import numpy as np

        self.frames = 0
        self.batches = 0
        self.telemetry = 0
        self.max_peers = 0
        self.green = cv2.imencode(".png", np.full((225, 300), 255, np.uint8))[1].tobytes()
        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{free_port()}"]))
        self.conf = conf
        self.session = None
        self._stop = threading.Event()
        self._decl: list = []

    def _on_frame(self, q) -> None:
        self.frames += 1
        try:
            req = wire.decode(q.payload.to_bytes(), kind="request")
            rep = wire.make_reply(req, mask_png=self.green, shape=[225, 300], threshold=0.0, timings_ms={},
                                  served_by="aaa", tier="cloud", server_ms=0.1, queue_ms=0.0)
            q.reply(str(q.key_expr), wire.encode(rep))
        except Exception:
            pass

    def _on_batch(self, q) -> None:
        self.batches += 1
        import msgpack

        q.reply(str(q.key_expr), msgpack.packb({"acked": 64, "stored": 64, "duplicates": 0, "contiguous": 0}))

    def start(self, endpoints: list[str]) -> None:
        self.conf.insert_json5("connect/endpoints", json.dumps(endpoints))
        s = self.session = zenoh.open(self.conf)
        self._decl += [
            s.liveliness().declare_token("scmr/alive/cloud/aaa"),
            s.declare_queryable("scmr/drivable/**", self._on_frame),
            s.declare_queryable("scmr/data/**", self._on_batch),
            s.declare_subscriber("scmr/telemetry/*", lambda _s: setattr(self, "telemetry", self.telemetry + 1)),
        ]
        pub = s.declare_publisher("scmr/load/cloud/cloud0")
        mine = s.declare_publisher("scmr/load/cloud/aaa")
        self._decl += [pub, mine]

        def loop():
            heavy = wire.encode(wire.make_load("cloud0", "cloud", workers=1, inflight=500, served=0))
            light = wire.encode(wire.make_load("aaa", "cloud", workers=64, inflight=0, served=0))
            while not self._stop.wait(0.05):
                try:
                    pub.put(heavy)
                    mine.put(light)
                    self.max_peers = max(self.max_peers, len(list(s.info.peers_zid())))
                except Exception:
                    return

        threading.Thread(target=loop, daemon=True).start()

    def close(self) -> None:
        self._stop.set()
        if self.session is not None:
            self.session.close()


def _listen_ports(run_dir: Path) -> list[str]:
    """Every ``--listen`` endpoint in the fleet's peer logs (what a port scan would find)."""
    out = []
    for log in sorted((run_dir / "logs").glob("*.log")):
        head = log.read_text(errors="replace").split("\n", 1)[0]
        out += re.findall(r"--listen (tcp/127\.0\.0\.1:\d+)", head)
    return sorted(set(out))


def _stranger_against_up(tmp_path: Path, *extra: str) -> tuple[Stranger, dict, list[dict]]:
    run_dir = tmp_path / "run"
    up = subprocess.Popen([sys.executable, "-m", "scmr_mesh", "up", "--robots", "2", "--duration", "6",
                           "--synthetic", "stub", "--server-arg=--process", f"--server-arg={STUB}",
                           "--leader-capable", "0", "--run-dir", str(run_dir), "--quiet", "--min-ror", "0",
                           "--json", str(tmp_path / "report.json"), *extra],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    stranger = Stranger()
    try:
        # the servers' ports, as soon as their logs name them (before the robots start)
        wait_for(lambda: len(_listen_ports(run_dir)) >= 2 or up.poll() is not None, timeout=60, what="server ports")
        stranger.start(_listen_ports(run_dir))
        out, err = up.communicate(timeout=180)
    finally:
        if up.poll() is None:
            import os

            os.killpg(up.pid, signal.SIGTERM)
            up.wait(timeout=30)
        stranger.close()
    report = json.loads((tmp_path / "report.json").read_text())
    records = [r for rid in ("r1", "r2") for r in read_records(run_dir / "robots" / rid / "records.jsonl")]
    return stranger, report, records


def test_a_stranger_cannot_serve_or_take_telemetry_from_the_default_fleet(tmp_path):
    stranger, report, records = _stranger_against_up(tmp_path)
    assert report["security"] == "mtls+acl"
    assert records and all(r["ok"] for r in records)
    assert stranger.max_peers == 0, "the stranger got a Zenoh session with the fleet"
    assert stranger.frames == 0 and stranger.batches == 0 and stranger.telemetry == 0
    assert not [r for r in records if r["served_by"] == "aaa"]
    tel = report["telemetry"]
    assert tel["lost"] == 0 and tel["stored"] == tel["sent"] == len(records), tel


def test_control_the_same_stranger_is_sent_frames_by_an_insecure_fleet(tmp_path):
    stranger, report, records = _stranger_against_up(tmp_path, "--insecure")
    assert report["security"] == "insecure"
    assert stranger.max_peers > 0
    assert stranger.frames > 0 or [r for r in records if r["served_by"] == "aaa"], (stranger.frames, records[:2])


# ----------------------------------------------- 2. a robot naming another robot
def _cloud(tmp_path: Path, creds: Path, profile: str, *, process: str = STUB) -> tuple[subprocess.Popen, str]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    ready = tmp_path / "cloud.ready"
    p = spawn_peer(["cloud", "--node", "cloud", "--listen", ep, "--workers", "1", "--process", process,
                    "--security", profile, "--credentials", str(creds), "--ready-file", str(ready),
                    "--ods", str(tmp_path / "ods.sqlite")], log_path=tmp_path / "cloud.log")
    wait_for(lambda: ready.exists() or p.poll() is not None, timeout=90, what="cloud ready")
    assert p.poll() is None, (tmp_path / "cloud.log").read_text()[-2000:]
    return p, ep


def _session(creds: Path, profile: str, who: str, ep: str):
    from scmr_mesh.mesh.config import MeshConfig, open_session

    return open_session(MeshConfig(connect=[ep], security=profile, credentials=str(creds), identity=who))


def _ask(session, key: str, req: dict, timeout: float = 2.0) -> str:
    """``ok``, ``error:<code>`` or ``none`` (no reply: dropped by the access rules)."""
    got = "none"
    for r in session.get(key, payload=wire.encode(req), timeout=timeout):
        if r.ok is not None:
            return "ok"
        try:
            got = "error:" + wire.decode(r.err.payload.to_bytes(), kind="error")["code"]
        except wire.WireProblem:
            got = "error:" + r.err.payload.to_bytes().decode(errors="replace")
    return got


@pytest.mark.parametrize("profile_name", ["mtls.toml", "mtls-noacl.toml"])
def test_a_credentialed_robot_cannot_send_requests_as_another_robot(tmp_path, repo_root, profile_name):
    creds = tmp_path / "certs"
    create_credentials(creds, "cloud,robot1,robot2", priority={"robot2": 3})
    profile = str(repo_root / "peers" / "secure" / profile_name)
    cloud, ep = _cloud(tmp_path, creds, profile)
    s = _session(creds, profile, "robot2", ep)
    try:
        own = keys.drivable_request("cloud", "cloud", "robot2")
        wait_for(lambda: _ask(s, own, wire.make_request("robot2", 0, synthetic_png(0))) == "ok", timeout=20,
                 what="robot2 served on its own key")
        as_robot1 = wire.make_request("robot1", 1, synthetic_png(1))
        outcome = {
            "robot1 named on own key": _ask(s, own, as_robot1),
            "robot1's key": _ask(s, keys.drivable_request("cloud", "cloud", "robot1"), as_robot1),
            "wildcard": _ask(s, "scmr/drivable/**", wire.make_request("robot2", 2, synthetic_png(2))),
            "high priority": _ask(s, own, wire.make_request("robot2", 3, synthetic_png(3), priority=900)),
        }
    finally:
        s.close()
        assert stop_peer(cloud) == 0
    log = (tmp_path / "cloud.log").read_text()
    assert outcome["robot1 named on own key"] == "error:forbidden"  # the service's own check, ACL or not
    assert outcome["high priority"] == "ok"
    assert "robot robot2 asks priority 900, the fleet grants at most 3" in log
    if profile_name == "mtls.toml":
        assert outcome["robot1's key"] == "none"  # access rules: robot2 may query only keys ending in /robot2
        assert outcome["wildcard"] == "none"
    else:  # control: without access rules the key names no verified identity
        assert outcome["robot1's key"] == "ok"
        assert outcome["wildcard"] == "error:malformed"  # refused by the service, no pipeline run


# --------------------------------------------------------------------- 3. bombs
def _vm_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def _cpu_s(pid: int) -> float:
    import os

    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def test_decompression_bombs_sent_to_a_real_cloud_cost_little(tmp_path, repo_root):
    import cv2
    import numpy as np

    from scmr_mesh.imaging.testing import jpeg_bomb

    creds = tmp_path / "certs"
    create_credentials(creds, "cloud,robot1")
    profile = str(repo_root / "peers" / "secure" / "mtls.toml")
    cloud, ep = _cloud(tmp_path, creds, profile, process="scmr_mesh.mesh.work:process_frame")  # real decoding
    worker = json.loads((tmp_path / "cloud.ready").read_text())["workers"][0]
    s = _session(creds, profile, "robot1", ep)
    key = keys.drivable_request("cloud", "cloud", "robot1")
    png4k = cv2.imencode(".png", np.zeros((2160, 3840, 3), np.uint8))[1].tobytes()  # 28 KB, ~1000:1
    bombs = {"jpeg 7000x7000": (jpeg_bomb(7000, 7000), "jpeg"), "jpeg 3840x2160": (jpeg_bomb(3840, 2160), "jpeg"),
             "png 3840x2160": (png4k, "png")}
    try:
        wait_for(lambda: _ask(s, key, wire.make_request("robot1", 0, synthetic_png(0))) == "ok", timeout=20,
                 what="robot1 served")
        hwm0 = _vm_kb(worker, "VmHWM")
        got, cpu = {}, {}
        for i, (name, (data, enc)) in enumerate(bombs.items(), 1):
            c0 = _cpu_s(worker)
            got[name] = _ask(s, key, wire.make_request("robot1", i, data, encoding=enc), timeout=10)
            cpu[name] = _cpu_s(worker) - c0
        growth_mb = (_vm_kb(worker, "VmHWM") - hwm0) / 1024
        after = _ask(s, key, wire.make_request("robot1", 9, synthetic_png(9)))
    finally:
        s.close()
        assert stop_peer(cloud) == 0
    assert got == {"jpeg 7000x7000": "error:malformed", "jpeg 3840x2160": "ok", "png 3840x2160": "error:malformed"}
    assert after == "ok"  # the cloud keeps serving
    assert growth_mb < 20, growth_mb  # peak resident set of the worker that decoded them
    print(f"\nbombs at a real cloud: worker CPU s {cpu}, worker peak RSS growth {growth_mb:.1f} MB")


# --------------------------------------------------------- 4. R2R forgeries
def _r2r_fleet(tmp_path: Path, creds: Path, profile: str) -> tuple[dict, dict]:
    procs = {}
    ports = {n: free_port() for n in ("leader0", "r1", "r3")}

    def start(name, args):
        ready = tmp_path / "ready" / f"{name}.ready"
        procs[name] = p = spawn_peer([*args, "--security", profile, "--credentials", str(creds), "--listen",
                                      f"tcp/127.0.0.1:{ports[name]}", "--lease-ms", "300", "--ready-file", str(ready)],
                                     log_path=tmp_path / f"{name}.log")
        wait_for(lambda: ready.exists() or p.poll() is not None, timeout=90, what=f"{name} ready")
        assert p.poll() is None, (tmp_path / f"{name}.log").read_text()[-2000:]

    boot = ["--connect", f"tcp/127.0.0.1:{ports['leader0']}"]
    robot = ["--synthetic", "stub", "--process", STUB, "--rate", "10", "--quiet"]
    start("leader0", ["leader", "--node", "leader0", "--workers", "1", "--process", STUB,
                      "--leadership-log", str(tmp_path / "leadership" / "leader0.jsonl")])
    start("r1", ["robot", "--id", "r1", *robot, "--out", str(tmp_path / "r1"), "--leader-capable",
                 "--capability", "robot4", "--leadership-log", str(tmp_path / "leadership" / "r1.jsonl"), *boot])
    start("r3", ["robot", "--id", "r3", *robot, "--out", str(tmp_path / "r3"), *boot])
    return procs, ports


@pytest.mark.parametrize("profile_name", ["mtls.toml", "mtls-noacl.toml"])
def test_a_plain_robot_cannot_take_the_lead(tmp_path, repo_root, profile_name):
    creds = tmp_path / "certs"
    create_credentials(creds, "leader0=leader,r1=robot+leader-capable,r3,r9")
    profile = str(repo_root / "peers" / "secure" / profile_name)
    procs, ports = _r2r_fleet(tmp_path, creds, profile)
    forged = {"frames": 0}
    s = None
    try:
        wait_for(lambda: sum(r["served_by"] == "leader0" for r in read_records(tmp_path / "r3" / "records.jsonl")) >= 3,
                 timeout=60, what="r3 served by leader0")
        s = _session(creds, profile, "r9", f"tcp/127.0.0.1:{ports['leader0']}")
        from scmr_mesh.mesh.election import Candidacy

        def frame(q):
            forged["frames"] += 1
            q.reply(str(q.key_expr), b"")

        decl = [s.liveliness().declare_token(keys.alive("candidate", "r9")),
                s.liveliness().declare_token(keys.alive("leader", "r9")),
                s.declare_queryable(keys.drivable_serve("leader", "r9"), frame)]
        pubs = {n: s.declare_publisher(keys.candidate(n)) for n in ("r9", "leader0")}
        t_forge = time.time_ns()
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            for n, pub in pubs.items():  # as itself, and a candidacy of leader0 that steps it down
                c = Candidacy(n, term=10**6, leading=n == "r9", clock_hz=9e9, power_w=1.0)
                pub.put(wire.encode(c.to_message()))
            time.sleep(0.05)
        records = [r for r in read_records(tmp_path / "r3" / "records.jsonl") if r["sent_unix_ns"] > t_forge]
        for d in decl:
            d.undeclare()
    finally:
        if s is not None:
            s.close()
        for p in procs.values():
            stop_peer(p, timeout=10)
    events = [json.loads(x) for x in (tmp_path / "leadership" / "leader0.jsonl").read_text().splitlines()]
    stepped = [e for e in events if e["event"] == "step_down" and e["cause"] != "stopping"]
    if profile_name == "mtls.toml":
        assert not stepped, events  # the forged term was never seen
        assert forged["frames"] == 0
        assert records and all(r["ok"] for r in records) and "r9" not in {r["served_by"] for r in records}
    else:  # control: without access rules the forged candidacy reaches leader0 (who steps down)
        # or robots route frames to the forged leader
        assert stepped or forged["frames"] > 0 or "r9" in {r["served_by"] for r in records}, events
