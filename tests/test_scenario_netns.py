"""netns backend: kernel primitives in our own namespaces, and one real short cloud-link-drop run.

Needs root and iproute2 (CI has both); skipped with the reason otherwise.  ~15 s.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import subprocess
import sys
import textwrap

import pytest

from scmr_mesh.mesh.testing import wait_for
from scmr_mesh.scenario.netns import (
    NetnsBackend,
    cleanup_stale,
    list_namespaces,
    netem_available,
    run_cmd,
)
from scmr_mesh.scenario.plan import Event
from scmr_mesh.scenario.spec import parse_scenario

pytestmark = [
    pytest.mark.netns,
    pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0,
                       reason="netns tests need root (network namespaces); CI runs them as root"),
    pytest.mark.skipif(shutil.which("ip") is None or shutil.which("tc") is None, reason="needs iproute2 (ip, tc)"),
]

TINY = {"name": "tiny", "seed": 3, "duration_s": 5,
        "fleet": {"robots": [{"id": "robot1", "synthetic": "stub"}]}}

SERVER = textwrap.dedent("""
    import socket, sys
    s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind((sys.argv[1], 7000)); s.listen(4); print("listening", flush=True)
    c, _ = s.accept()
    while True:
        d = c.recv(100)
        if not d: break
        c.sendall(d)
""")

CLIENT = textwrap.dedent("""
    import socket, sys
    c = socket.create_connection((sys.argv[1], 7000), timeout=5)
    c.sendall(b"a"); print("echo", c.recv(10).decode(), flush=True)
    sys.stdin.readline()                     # the test blocks the link here
    c.sendall(b"b"); c.settimeout(1.0)
    try:
        print("during", c.recv(10).decode() or "closed", flush=True)
    except socket.timeout:
        print("during timeout", flush=True)
    try:
        socket.create_connection((sys.argv[1], 7000), timeout=1.0); print("new ok", flush=True)
    except OSError as e:
        print("new failed", type(e).__name__, flush=True)
    sys.stdin.readline()                     # the test lifts the block here
    c.settimeout(10)
    print("after", c.recv(10).decode(), flush=True)
""")


def test_blackhole_is_silent_and_reversible_between_two_namespaces():
    sc = parse_scenario(TINY)
    be = NetnsBackend(sc)
    srv = cli = None
    try:
        be.setup()
        assert set(be.layout.namespaces()) <= set(list_namespaces())
        # nothing routes out: the peer namespaces have no default route
        routes = run_cmd(("ip", "-n", be.layout.ns("robot1"), "route", "show"))
        assert "default" not in routes
        cloud_ip = be.layout.addr("cloud")
        srv = subprocess.Popen(be.wrap("cloud", [sys.executable, "-c", SERVER, cloud_ip]),
                               stdout=subprocess.PIPE, text=True)
        assert srv.stdout.readline().strip() == "listening"
        cli = subprocess.Popen(be.wrap("robot1", [sys.executable, "-c", CLIENT, cloud_ip]),
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert cli.stdout.readline().strip() == "echo a"
        be.apply(Event(0.0, "block", ("cloud", "robot1")))
        cli.stdin.write("\n")
        cli.stdin.flush()
        assert cli.stdout.readline().strip() == "during timeout"  # silent: no reply, no reset
        assert cli.stdout.readline().startswith("new failed")  # and no new connection
        be.apply(Event(1.0, "unblock", ("cloud", "robot1"), lift=True))
        cli.stdin.write("\n")
        cli.stdin.flush()
        assert cli.stdout.readline().strip() == "after b"  # TCP retransmitted once the link came back
    finally:
        for p in (cli, srv):
            if p is not None:
                p.kill()
                p.wait()
        be.teardown()
    assert not set(be.layout.namespaces()) & set(list_namespaces())


def test_netem_detection_skips_latency_with_a_note():
    have = netem_available()
    assert isinstance(have, bool)
    sc = parse_scenario(dict(TINY, faults=[{"kind": "latency", "at_s": 1, "link": ["robot1", "cloud"],
                                            "delay_ms": 10}]))
    be = NetnsBackend(sc)
    try:
        be.setup()
        notes = be.apply(Event(1.0, "netem", ("robot1", "cloud"), (10.0, 0.0), fault=0))
        qd = run_cmd(("tc", "-n", be.layout.ns("robot1"), "qdisc", "show", "dev", "eth0"))
        if have:
            assert notes == [] and "netem" in qd
        else:
            assert notes and "no netem" in notes[0] and "netem" not in qd
    finally:
        be.teardown()


@pytest.mark.parametrize("entered", [True, False], ids=["inside", "racing-ip-netns-exec"])
def test_cleanup_removes_stale_namespaces_and_their_processes(entered):
    """Also when the cleanup runs before `ip netns exec` has entered the namespace (issue #12, item 8):
    the process is killed while entering, or cannot enter a namespace whose name is gone."""
    prefix = f"scmrs-stale{secrets.token_hex(2)}"
    ns = f"{prefix}-x"
    run_cmd(("ip", "netns", "add", ns))
    p = subprocess.Popen(["ip", "netns", "exec", ns, "sleep", "60"])
    try:
        if entered:  # the condition, not a sleep: its pid is listed inside the namespace
            wait_for(lambda: str(p.pid) in run_cmd(("ip", "netns", "pids", ns)).split(), timeout=30,
                     what="sleep inside the namespace")
        assert cleanup_stale(prefix) == [ns]
        assert p.wait(timeout=10) != 0  # killed, or refused to enter
        assert ns not in list_namespaces()
    finally:
        if p.poll() is None:
            p.kill()
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


@pytest.mark.parametrize("family", ["scmrm", "scmrb", "scmrh", "scmrg"])
def test_cleanup_removes_the_other_namespace_users_leftovers(family):
    """A killed test run or bench leaves its sites (scmrm-), tx-stall hosts (scmrb-) or bridged hosts
    (scmrh-) behind, as one SIGKILLed suite did on 2026-11-29; `scmr scenario cleanup` removes those too."""
    prefix = f"{family}-stale{secrets.token_hex(2)}"
    ns = f"{prefix}-x"
    run_cmd(("ip", "netns", "add", ns))
    p = subprocess.Popen(["ip", "netns", "exec", ns, "sleep", "60"])
    try:
        wait_for(lambda: str(p.pid) in run_cmd(("ip", "netns", "pids", ns)).split(), timeout=30,
                 what="sleep inside the namespace")
        assert cleanup_stale(prefix) == [ns]
        assert p.wait(timeout=10) != 0
        assert ns not in list_namespaces("")
    finally:
        if p.poll() is None:
            p.kill()
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_cleanup_kills_a_process_that_enters_while_it_runs():
    """The race made deterministic: a process enters right after the cleanup listed the namespace's pids
    (as `ip netns exec` may): the sweep by the namespace's inode after the delete still kills it."""
    prefix = f"scmrs-late{secrets.token_hex(2)}"
    ns = f"{prefix}-x"
    run_cmd(("ip", "netns", "add", ns))
    late = []

    def run(cmd):
        out = run_cmd(cmd)
        if tuple(cmd[:3]) == ("ip", "netns", "pids") and not late:
            late.append(subprocess.Popen(["ip", "netns", "exec", ns, "sleep", "60"]))
            wait_for(lambda: str(late[0].pid) in run_cmd(("ip", "netns", "pids", ns)).split(), timeout=30,
                     what="sleep inside the namespace")
        return out

    try:
        assert cleanup_stale(prefix, run=run) == [ns]
        assert late and late[0].wait(timeout=10) != 0  # killed, although the name is gone
    finally:
        for p in late:
            if p.poll() is None:
                p.kill()
        subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_real_cloud_link_drop_with_netns(tmp_path):
    """Real peers (stub pipeline) in namespaces; the cloud is silently cut and comes back."""
    from scmr_mesh.scenario.report import build_report, write_report
    from scmr_mesh.scenario.runner import run_scenario

    sc = parse_scenario({
        "name": "short-drop", "seed": 11, "duration_s": 7, "lease_ms": 200,
        "process": "scmr_mesh.mesh.testing:stub_process",
        "fleet": {"robots": [{"id": "robot1", "synthetic": "stub", "rate_hz": 8, "local_fallback": False},
                             {"id": "robot2", "synthetic": "stub", "rate_hz": 8, "local_fallback": False}]},
        "faults": [{"kind": "partition", "at_s": 2.5, "for_s": 2.0,
                    "groups": [["cloud"], ["leader", "robot1", "robot2"]]}],
        "expectations": [{"metric": "ror", "op": ">=", "value": 0.9}],
    })
    res = run_scenario(sc, backend="netns", out_dir=tmp_path, ready_timeout=90)
    assert not set(NetnsBackend(sc, run_id=res.run_id).layout.namespaces()) & set(list_namespaces())
    rep = build_report(sc, res.records, res.metric_faults(), t0_unix_ns=res.t0_unix_ns, backend="netns")
    paths = write_report(rep, tmp_path)
    s = rep["summary"]
    assert s["requests"] > 0
    assert s["by_tier"]["leader"] > 0 and s["by_tier"]["cloud"] > 0
    f = rep["faults"][0]
    assert f["tier"] == "cloud"
    assert f["failover_gap_ms"] is not None and f["failover_gap_ms"] > 0
    assert f["failback_gap_ms"] is not None  # the cloud answered again after the link returned
    # the cloud is preferred: before the cut the leader answered only hedges (a cloud answer later
    # than the hedge delay, e.g. on a loaded box), each sent to the cloud first
    t_cut = rep["t0_unix_ns"] + f["started_at_s"] * 1e9
    early = [r for r in rep["requests"] if r["tier"] == "leader" and r["received_unix_ns"] < t_cut]
    assert all(r["attempts"][0]["tier"] == "cloud" and [a for a in r["attempts"] if a["outcome"] == "ok"][0].get("hedge")
               for r in early), early
    data = json.loads(paths["json"].read_text())
    assert data["seed"] == 11 and {"summary", "faults", "expectations", "requests"} <= set(data)


def test_a_robot_cut_off_after_the_cloud_died_rejoins_the_leader(tmp_path):
    """Issue 28 item 5: the cloud is killed for good, then robot1 is cut off for 2 s.

    Zenoh re-dials only a configured endpoint whose link closed: a robot handed only its
    bootstrap (the dead cloud) never linked to the leader again and computed every later frame
    alone.  Each robot is now handed the peers started before it, so it re-dials the leader.
    """
    from scmr_mesh.scenario.runner import run_scenario

    sc = parse_scenario({
        "name": "blink", "seed": 5, "duration_s": 8, "lease_ms": 200,
        "process": "scmr_mesh.mesh.testing:stub_process",
        "fleet": {"robots": [{"id": "robot1", "synthetic": "stub", "rate_hz": 8}]},
        "faults": [{"kind": "crash", "at_s": 1.5, "peer": "cloud"},
                   {"kind": "partition", "at_s": 3.0, "for_s": 2.0, "groups": [["robot1"], ["cloud", "leader"]]}],
        "expectations": [{"metric": "telemetry_lost", "op": ">=", "value": 0}],
    })
    res = run_scenario(sc, backend="netns", out_dir=tmp_path, ready_timeout=90)
    cut = [f for f in res.faults if f.fault.kind == "partition"][0]
    assert cut.end_unix_ns is not None, "the cut was never lifted"
    after = [r for r in res.records if r["robot"] == "robot1" and r["sent_unix_ns"] > cut.end_unix_ns + 1e9]
    assert after, "robot1 sent nothing after the cut"
    # served by the leader again, not computed alone, within a second of the link coming back
    assert {r["tier"] for r in after} == {"leader"}, sorted({str(r["tier"]) for r in after})


def _run_cli(tmp_path):
    """Start `scmr scenario run` (netns, stub pipeline) and wait until the robots run; return (proc, run id)."""
    import re
    import time

    sc = tmp_path / "long.toml"
    sc.write_text("""
name = "interrupted"
seed = 1
duration_s = 60
lease_ms = 200
process = "scmr_mesh.mesh.testing:stub_process"
[fleet]
robots = [ { id = "robot1", synthetic = "stub", rate_hz = 4 } ]
""")
    import signal

    # Ctrl-C at a terminal: SIGINT at its default disposition.  A suite started in the background
    # by a shell without job control (`make test &`, some CI runners) inherits SIGINT *ignored*, and
    # Python then keeps it ignored: the runner ran its whole 60 s and the test timed out.
    p = subprocess.Popen([sys.executable, "-m", "scmr_mesh", "scenario", "run", str(sc), "--backend", "netns",
                          "--out", str(tmp_path / "out")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    rid = None
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        line = p.stderr.readline()
        if not line:
            break
        m = re.search(r"namespaces scmrs-([0-9a-f]+)-\*", line)
        if m:
            rid = m.group(1)
        if "robots ready" in line:
            return p, rid
    p.kill()
    pytest.fail(f"scenario run did not get going (run id {rid})")


def _gone(prefix, timeout=15.0):
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if not list_namespaces(prefix):
            return True
        time.sleep(0.2)
    return False


def test_ctrl_c_cleans_up_namespaces_and_peers(tmp_path):
    import signal

    p, rid = _run_cli(tmp_path)
    try:
        assert rid and list_namespaces(f"scmrs-{rid}-")
        pids = run_cmd(("ip", "netns", "pids", f"scmrs-{rid}-cloud")).split()
        assert pids  # the cloud runs inside its namespace
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=60) == 130
        assert _gone(f"scmrs-{rid}-")
        for pid in pids:
            assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"
    finally:
        if p.poll() is None:
            p.kill()
        cleanup_stale(f"scmrs-{rid}-") if rid else None


def test_sigkilled_runner_leaves_nothing_running_and_cleanup_removes_its_namespaces(tmp_path):
    import signal
    import time

    p, rid = _run_cli(tmp_path)
    try:
        pids = run_cmd(("ip", "netns", "pids", f"scmrs-{rid}-cloud")).split()
        os.killpg(p.pid, signal.SIGKILL)  # no finally, no handler: only PDEATHSIG and cleanup remain
        p.wait(timeout=10)
        end = time.monotonic() + 15
        while time.monotonic() < end and any(os.path.exists(f"/proc/{x}") for x in pids):
            time.sleep(0.2)
        assert not any(os.path.exists(f"/proc/{x}") for x in pids)  # peers died with the runner
        assert list_namespaces(f"scmrs-{rid}-")  # namespaces are left behind ...
        assert len(cleanup_stale(f"scmrs-{rid}-")) == 4  # ... until `scmr scenario cleanup` (br, cloud, leader, robot1)
    finally:
        if p.poll() is None:
            p.kill()
        cleanup_stale(f"scmrs-{rid}-") if rid else None
    assert not list_namespaces(f"scmrs-{rid}-")


@pytest.mark.timeout(240)
def test_a_radio_chain_blocks_every_pair_out_of_range_and_peers_do_not_forward(tmp_path):
    """Three robots down a tunnel, 10 m apart, range 12 m (issue 22): only neighbours are linked.

    robot1 at the portal is answered by the cloud over 1 hop; robot2 and robot3 have no direct
    link to any server (their pairs are blackholed before any peer starts) and Zenoh 1.10 peers do
    not forward for other peers, so neither gets a single answer from the cloud or the leader:
    they compute alone.  This is the clique's limit the multi-hop tier (routers) removes.
    """
    from scmr_mesh.scenario.report import run_report
    from scmr_mesh.scenario.runner import run_scenario

    sc = parse_scenario({
        "name": "chain", "seed": 3, "duration_s": 4, "lease_ms": 250,
        "process": "scmr_mesh.mesh.testing:stub_process",
        "fleet": {"robots": [{"id": f"robot{i}", "synthetic": "stub", "rate_hz": 5} for i in (1, 2, 3)]},
        "topology": {"range_m": 12, "nodes": {"cloud": [0, 0], "leader": [0, 1], "robot1": [10, 0],
                                              "robot2": [20, 0], "robot3": [30, 0]}}})
    res = run_scenario(sc, backend="netns", out_dir=tmp_path / "run", progress=lambda m: None)
    rep = run_report(res)
    rows = rep["request_log"]
    by = {rid: [r for r in rows if r["robot"] == rid] for rid in ("robot1", "robot2", "robot3")}
    assert all(by.values()), {k: len(v) for k, v in by.items()}
    assert any(r["tier"] == "cloud" and r["hops"] == 1 for r in by["robot1"])
    for rid in ("robot2", "robot3"):  # out of every server's range: no direct link, no forwarding peer
        assert not [r for r in by[rid] if r["tier"] in ("cloud", "leader")], by[rid][:3]
        assert all(r["tier"] == "local" and r["hops"] == 0 for r in by[rid] if r["ok"])
    assert rep["links_over_time"] == [{"t_s": 0.0, "links": [["cloud", "leader"], ["cloud", "robot1"],
                                                             ["leader", "robot1"], ["robot1", "robot2"],
                                                             ["robot2", "robot3"]]}]
    assert not list_namespaces(prefix=f"scmrs-{res.run_id}-")


class _LinkProbe:
    """A run hook that lists, once the run has gone 1.5 s, every established TCP link of every host.

    Read from the kernel (``ss`` in each namespace), not from zenoh: what is really connected.
    """

    def __init__(self) -> None:
        self.links: dict[str, set[str]] | None = None

    def setup(self, run) -> None: ...
    def say(self, run, message) -> None: ...
    def stopped(self, run) -> None: ...
    def reported(self, result, report) -> None: ...

    def tick(self, run) -> None:
        if self.links is not None or run.t0_mono is None or run.elapsed_s() < 1.5:
            return
        lay = run.be.layout
        by_addr = {lay.addr(p): p for p in lay.peers}
        self.links = {}
        for p in lay.peers:
            out = subprocess.run(["ip", "netns", "exec", lay.ns(p), "ss", "-tnH", "state", "established"],
                                 capture_output=True, text=True, check=True).stdout
            far = set()
            for line in out.splitlines():
                remote = line.split()[-1].rsplit(":", 1)[0]
                if remote in by_addr and by_addr[remote] != p:
                    far.add(by_addr[remote])
            self.links[p] = far


@pytest.mark.timeout(300)
def test_routers_relay_down_a_radio_chain_and_a_cut_off_part_elects_its_own_leader(tmp_path):
    """The same tunnel with ``topology.shape = "routers"`` (issue 22): robots relay for each other.

    robot4, three radio hops from the portal, is served by the cloud over 4 hops through the routers
    on robot1's, robot2's and robot3's hosts; no host holds a TCP link to a host out of its radio
    range (read from the kernel).  When robot2's host crashes, robot3 (leader-capable) and robot4
    have no path to the portal: robot3 leads their part and serves both; when robot2 is back, one
    leader remains.
    """
    from scmr_mesh.scenario.radio import Radio
    from scmr_mesh.scenario.report import run_report
    from scmr_mesh.scenario.runner import run_scenario

    sc = parse_scenario({
        "name": "chain", "seed": 3, "duration_s": 9, "lease_ms": 250,
        "process": "scmr_mesh.mesh.testing:stub_process",
        "fleet": {"robots": [{"id": "robot1", "synthetic": "stub", "rate_hz": 5},
                             {"id": "robot2", "synthetic": "stub", "rate_hz": 5},
                             {"id": "robot3", "synthetic": "stub", "rate_hz": 5, "leader_capable": True},
                             {"id": "robot4", "synthetic": "stub", "rate_hz": 5}]},
        "topology": {"shape": "routers", "range_m": 12,
                     "nodes": {"cloud": [0, 0], "leader": [0, 1], "robot1": [10, 0], "robot2": [20, 0],
                               "robot3": [30, 0], "robot4": [40, 0]}},
        "faults": [{"kind": "crash", "peer": "robot2", "at_s": 3.0, "for_s": 3.0}]})
    probe = _LinkProbe()
    res = run_scenario(sc, backend="netns", out_dir=tmp_path / "run", progress=lambda m: None, hooks=[probe])
    rep = run_report(res)
    rows = rep["request_log"]
    # 1. real relaying: robot4 served by the cloud over four radio hops before the crash
    assert any(r["robot"] == "robot4" and r["tier"] == "cloud" and r["hops"] == 4 for r in rows)
    # 2. no host is linked to a host out of its range (the routers dial everyone; the kernel refuses)
    radio: Radio = sc.radio
    assert probe.links is not None
    for host, far in probe.links.items():
        for other in far:
            assert radio.in_range(host, other, 1.5), f"{host} holds a TCP link to {other}, out of its range"
    assert "robot2" in probe.links["robot3"] and "robot1" in probe.links["robot2"]
    # 3. cut off, robot3 leads its own part and serves itself; after the heal one leader remains
    assert any(r["robot"] == "robot4" and r["tier"] == "leader" and r["served_by"] == "robot3" for r in rows)
    lead = rep["leadership"]
    assert any(set(e["leaders"]) == {"leader", "robot3"} for e in lead["leaders_over_time"]), lead
    assert len(lead["leaders_at_end"]) == 1, lead
    crash = next(f for f in rep["faults"] if f["kind"] == "crash")
    assert set(crash["reroute_ms"]) == {"robot3", "robot4"} and None not in crash["reroute_ms"].values(), crash
    assert rep["multihop"]["alone_with_path"] == 0, [r for r in rows if r["tier"] == "local"]
    assert rep["ror"] == 1.0
    assert not list_namespaces(prefix=f"scmrs-{res.run_id}-")
