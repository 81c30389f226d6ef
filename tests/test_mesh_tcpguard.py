"""The TCP link guard (mesh/tcpguard.py): a workaround for zenoh's 10 s lingering close.

zenoh 1.10.2 sets SO_LINGER 10 s on its TCP links; closing a link whose peer went
silent with unacknowledged data blocks the closing thread until the linger time
or until the route comes back (zenoh issues #1101, #2718).  The guard sets
TCP_USER_TIMEOUT on zenoh's link sockets so the kernel aborts such a connection
and the close returns.  Checked here: which sockets get the option (loopback,
no root), and, in two network namespaces (root), that a lingering close on a
blackholed connection returns while the route is still down with the option and
only after the route comes back without it.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import socket
import subprocess
import sys

import pytest
from conftest import free_port

from scmr_mesh.mesh import tcpguard
from scmr_mesh.mesh.testing import wait_for


def _user_timeout(s: socket.socket) -> int:
    return s.getsockopt(socket.IPPROTO_TCP, tcpguard._TCP_USER_TIMEOUT)


def test_only_the_named_connections_get_the_option():
    srv = socket.create_server(("127.0.0.1", 0))
    a = socket.create_connection(srv.getsockname())
    a_peer, _ = srv.accept()
    b = socket.create_connection(srv.getsockname())
    b_peer, _ = srv.accept()
    try:
        pair = (a.getsockname()[:2], a.getpeername()[:2])
        done: set[int] = set()
        assert tcpguard.set_user_timeout({pair}, 321, done) == 1
        assert _user_timeout(a) == 321
        assert _user_timeout(b) == 0 and _user_timeout(a_peer) == 0 and _user_timeout(srv) == 0
        assert tcpguard.set_user_timeout({pair}, 321, done) == 0  # done once
        a.send(b"still open")  # the duplicate it worked on was closed, not the socket
        assert a_peer.recv(10) == b"still open"
    finally:
        for s in (a, b, a_peer, b_peer, srv):
            s.close()


@pytest.mark.parametrize("text, want", [("tcp/127.0.0.1:7447", ("127.0.0.1", 7447)),
                                        ("tls/[::1]:9000", ("::1", 9000)),
                                        ("tcp/10.0.0.2:7447#iface=eth0", ("10.0.0.2", 7447)),
                                        ("udp/127.0.0.1:7447", None), ("unixsock-stream//tmp/x", None)])
def test_locators(text, want):
    assert tcpguard._addr(text) == want


def test_timeout_follows_the_lease_and_the_environment(monkeypatch):
    monkeypatch.delenv(tcpguard.ENV, raising=False)
    assert tcpguard.timeout_for(500) == 500
    assert tcpguard.timeout_for(20) == tcpguard.MIN_MS
    monkeypatch.setenv(tcpguard.ENV, "0")
    assert tcpguard.timeout_for(500) == 0
    monkeypatch.setenv(tcpguard.ENV, "750")
    assert tcpguard.timeout_for(500) == 750


def test_scmr_sessions_guard_their_links():
    from scmr_mesh.mesh.config import MeshConfig, close_session, open_session

    port = free_port()
    a = open_session(MeshConfig(listen=[f"tcp/127.0.0.1:{port}"], lease_ms=400))
    b = open_session(MeshConfig(connect=[f"tcp/127.0.0.1:{port}"], lease_ms=400))
    try:
        def guarded() -> list[int]:
            out = []
            for name in os.listdir("/proc/self/fd"):
                try:
                    if not os.readlink(f"/proc/self/fd/{name}").startswith("socket:"):
                        continue
                    s = socket.socket(fileno=os.dup(int(name)))
                except OSError:
                    continue
                try:
                    # TCP only: a Unix socket another test left open in this process (a PostgreSQL
                    # client's) has a str name, and peer[1] raised IndexError (fc10)
                    if s.type == socket.SOCK_STREAM and s.family in (socket.AF_INET, socket.AF_INET6):
                        peer = s.getpeername()
                        if port in (s.getsockname()[1], peer[1]):
                            out.append(_user_timeout(s))
                except OSError:
                    pass
                finally:
                    s.close()
            return out

        wait_for(lambda: guarded() == [400, 400], timeout=10, what="both ends of the link guarded")
    finally:
        close_session(b)
        close_session(a)


CLIENT = r"""
import json, socket, subprocess, sys, threading, time
sys.path.insert(0, sys.argv[4])
from scmr_mesh.mesh import tcpguard
server, guard, hold = sys.argv[1], sys.argv[2] == "1", float(sys.argv[3])
c = socket.create_connection((server, 7000))
c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x0a\x00\x00\x00")  # on, 10 s: as zenoh
if guard:
    pair = (c.getsockname()[:2], c.getpeername()[:2])
    assert tcpguard.set_user_timeout({pair}, 300) == 1
c.send(b"w" * 1000)  # the path works
subprocess.run(["ip", "route", "add", "blackhole", server + "/32"], check=True)
c.setblocking(False)
try:
    c.send(b"x" * 200_000)  # unacknowledged now
except BlockingIOError:
    pass
restoring = []
def restore():
    time.sleep(hold)
    # stamped before the route goes: the close may return while `ip` is still exiting,
    # so a stamp taken after it would call a close freed by the route "before route back"
    restoring.append(time.monotonic())
    subprocess.run(["ip", "route", "del", "blackhole", server + "/32"], check=True)
threading.Thread(target=restore).start()
t0 = time.monotonic()
c.close()  # zenoh's drop of a dead link
t1 = time.monotonic()
while not restoring:
    time.sleep(0.01)
print(json.dumps({"close_s": t1 - t0, "returned_before_route_back": t1 < restoring[0]}))
"""

SERVER = r"""
import socket, time
s = socket.create_server(("0.0.0.0", 7000))
print("listening", flush=True)
c, _ = s.accept()
print("ok", flush=True)
time.sleep(60)
"""


@pytest.mark.netns
@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="needs root (network namespaces)")
@pytest.mark.skipif(shutil.which("ip") is None, reason="needs iproute2")
def test_lingering_close_on_a_dead_link_ends_with_the_guard(repo_root):
    tag = secrets.token_hex(2)
    ns = {"a": f"scmrg-{tag}-a", "b": f"scmrg-{tag}-b"}
    addr = {"a": "198.18.2.1", "b": "198.18.2.2"}
    procs: list[subprocess.Popen] = []

    def run(*argv: str) -> None:
        subprocess.run(argv, check=True, capture_output=True, timeout=20)

    try:
        for k in ns:
            run("ip", "netns", "add", ns[k])
            run("ip", "-n", ns[k], "link", "set", "lo", "up")
        run("ip", "-n", ns["a"], "link", "add", "eth0", "type", "veth", "peer", "name", "eth0", "netns", ns["b"])
        for k in ns:
            run("ip", "-n", ns[k], "addr", "add", f"{addr[k]}/24", "dev", "eth0")
            run("ip", "-n", ns[k], "link", "set", "eth0", "up")
        results = {}
        for guard in (False, True):
            srv = subprocess.Popen(["ip", "netns", "exec", ns["b"], sys.executable, "-c", SERVER],
                                   stdout=subprocess.PIPE, text=True, start_new_session=True)
            procs.append(srv)
            assert srv.stdout.readline().strip() == "listening"  # bound: the client can connect
            cl = subprocess.run(["ip", "netns", "exec", ns["a"], sys.executable, "-c", CLIENT, addr["b"],
                                 "1" if guard else "0", "3.0", str(repo_root)],
                                capture_output=True, text=True, timeout=60)
            assert cl.returncode == 0, cl.stderr[-2000:]
            results[guard] = json.loads(cl.stdout.strip().splitlines()[-1])
            srv.kill()
            srv.wait(timeout=10)
        print("lingering close on a blackholed connection:", results)
        # the mechanism (zenoh's 10 s linger on a silent peer): close waits for the route to come back
        assert results[False]["returned_before_route_back"] is False, results
        # with TCP_USER_TIMEOUT the kernel gives up on the connection and close returns while it is down
        assert results[True]["returned_before_route_back"] is True, results
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        for k in ns:
            subprocess.run(["ip", "netns", "del", ns[k]], capture_output=True, timeout=20)
