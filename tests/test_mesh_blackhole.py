"""Regression test: a send on a silently dead link must not stall the robot's other links.

Issue 3/4 (cloud-link-drop with netns): when the cloud's link is blackholed while
a robot pushes a large frame to it, zenoh's reliable ("block") send waits for
queue space while holding the link's pipeline lock, by default for 5 s
(``wait_before_close``).  Meanwhile the dead link cannot be torn down and
zenoh's single TX thread stalls, so the robot stops sending keep-alives on
*every* link: the leader expires it, every query to the leader times out, and
the robot runs locally for ~5 s although the leader is up.  scmr now ties
``wait_before_close`` to the lease (``scmr_mesh.mesh.config``); docs/ZENOH.md
section 8 has the measurements.

Three namespaces (cloud, leader, robot), real zenoh peers opened as every scmr
process opens them (``open_session``: scmr's config, its zenoh runtime and the
TCP link guard), lease 150 ms.  The robot blackholes its route to the cloud
itself (so the push is sure to happen before the lease notices) and pushes an
8 MB query to the cloud (more than the socket and zenoh queue can hold) while a
second thread queries the leader until it answers.  Before the fix the 8 MB push
blocked for 5 s and no leader answer came inside the 4 s window.  About 2 s,
root only.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import bridged_hosts  # noqa: E402

pytestmark = [
    pytest.mark.netns,
    pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="needs root (network namespaces)"),
    pytest.mark.skipif(shutil.which("ip") is None or shutil.which("tc") is None, reason="needs iproute2 (ip, tc)"),
]

LEASE_MS = 150
WINDOW_S = 4.0  # below zenoh's default 5 s wait_before_close

PEER = r"""
import json, subprocess, sys, threading, time
import zenoh
from scmr_mesh.mesh.config import _GUARDS, MeshConfig, open_session
from scmr_mesh.mesh.testing import wait_for
role, listen, connect, lease, cloud_addr, window = sys.argv[1:7]
mc = MeshConfig(listen=[listen], connect=[c for c in connect.split(",") if c], lease_ms=int(lease))
# the session a robot really opens: scmr's zenoh runtime (4 RX / 2 TX workers) and the TCP link guard
with open_session(mc) as s:
    if role != "robot":
        qa = s.declare_queryable(f"scmr/drivable/{role}/{role}", lambda q: q.reply(q.key_expr, b"ok"), complete=True)
        tok = s.liveliness().declare_token(f"scmr/alive/{role}/{role}")
        print("ready", flush=True)
        sys.stdin.read()
        sys.exit(0)
    events = []
    listener = s.info.declare_link_events_listener(
        lambda e: events.append((time.monotonic(), str(e.kind), str(e.link.dst))), history=False)
    qc = s.declare_querier("scmr/drivable/cloud/cloud", timeout=1.0)
    ql = s.declare_querier("scmr/drivable/leader/leader", timeout=1.0)
    wait_for(lambda: qc.matching_status.matching and ql.matching_status.matching, timeout=20,
             what="the cloud's and the leader's queryables")
    for _ in range(5):  # warm both paths
        for q in (qc, ql):
            list(q.get(payload=b"x" * 200_000))
    guard = _GUARDS.get(id(s))
    try:  # both links' sockets carry TCP_USER_TIMEOUT before the cut
        wait_for(lambda: guard is not None and guard.applied >= 2, timeout=5, interval=0.01, what="the link guard")
    except TimeoutError:
        pass  # reported below
    guarded = guard.applied if guard else 0
    if guarded < 2:
        print(json.dumps({"guarded": guarded}), flush=True)
        sys.exit(0)
    # the robot's leader traffic goes on while its push to the cloud is blocked (a robot's
    # frames and telemetry run on their own threads): ask the leader from a second thread
    leader = {"first_ok_s": None, "attempts": 0}
    go = threading.Event()

    def ask_leader():
        go.wait()
        while time.monotonic() - t_block < float(window):
            leader["attempts"] += 1
            # each get waits for the leader's answer or its final (1 s timeout at most); no pause between
            if any(r.ok is not None for r in ql.get(payload=b"z" * 100_000)):
                leader["first_ok_s"] = time.monotonic() - t_block
                return

    asker = threading.Thread(target=ask_leader, daemon=True)
    asker.start()
    subprocess.run(["ip", "route", "add", "blackhole", f"{cloud_addr}/32"], check=True)
    t_block = time.monotonic()
    go.set()
    list(qc.get(payload=b"y" * 8_000_000))  # fills the socket and zenoh's queue
    push_s = time.monotonic() - t_block
    asker.join(float(window) + 2)
    dropped = [dst for t, kind, dst in events if t >= t_block and "DELETE" in kind and cloud_addr not in dst]
    print(json.dumps({"push_s": push_s, "first_leader_ok_s": leader["first_ok_s"], "attempts": leader["attempts"],
                      "other_links_dropped": dropped, "guarded": guarded}), flush=True)
"""


def test_blackholed_cloud_send_does_not_stall_the_leader_path(repo_root):
    tag = secrets.token_hex(2)
    addr = {"cloud": "198.18.0.10", "leader": "198.18.0.11", "robot": "198.18.0.12"}
    procs: list[subprocess.Popen] = []
    with bridged_hosts(f"scmrs-{tag}", addr) as names:
        try:
            ep = {p: f"tcp/{a}:7447" for p, a in addr.items()}
            env = dict(os.environ, PYTHONPATH=str(repo_root))
            env.pop("RUST_LOG", None)
            env.pop("SCMR_ZENOH_LOG", None)
            env.pop("SCMR_TCP_USER_TIMEOUT_MS", None)  # the default guard, as a robot runs it
            env.pop("ZENOH_RUNTIME", None)  # and scmr's default zenoh runtime (open_session sets it)

            def start(role: str, connect: list[str]) -> subprocess.Popen:
                argv = ["ip", "netns", "exec", names[role], sys.executable, "-c", PEER, role, ep[role],
                        ",".join(connect), str(LEASE_MS), addr["cloud"], str(WINDOW_S)]
                p = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=env, start_new_session=True)
                procs.append(p)
                return p

            servers = [start("cloud", []), start("leader", [ep["cloud"]])]
            for s in servers:
                assert s.stdout.readline().strip() == "ready", s.stderr.read()
            robot = start("robot", [ep["cloud"], ep["leader"]])
            out, err = robot.communicate(timeout=60)
            assert robot.returncode == 0, err[-2000:]
            res = json.loads(out.strip().splitlines()[-1])
            # the robot ran with scmr's link guard on both links (without it a lingering close of a
            # dead link can hold zenoh's threads for 10 s; docs/ZENOH.md sections 8 and 22)
            assert res["guarded"] >= 2, f"the TCP link guard covered {res['guarded']} of the robot's 2 links in 5 s"
            # the send to the dead cloud gave up within a few leases, not zenoh's default 5 s
            assert res["push_s"] < WINDOW_S, (
                f"the 8 MB push to the blackholed cloud blocked {res['push_s']:.2f} s (wait_before_close "
                f"should end it after half the {LEASE_MS} ms lease): {res}")
            # the leader answered the robot while the cloud was silently gone ...
            assert res["first_leader_ok_s"] is not None, (
                f"no leader answer within {WINDOW_S} s of the cloud's blackhole ({res['attempts']} asked): {res}")
            # ... and the robot never went quiet on its other links (the leader did not expire it)
            assert res["other_links_dropped"] == [], res
        finally:
            for p in procs:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(timeout=10)
