"""Cloud nodes at two sites sharing one PostgreSQL store, robots at a third; a router per site.

Topology (network namespaces, no default route; each peer reaches other sites only
through its site's router)::

    site a (robots)            site b (cloud0 + database)       site c (cloud1)
    leader0, r1 -> router A ==10.78.1.0/30== router B ==10.78.3.0/30== router C <- cloud1
                           \\================== 10.78.2.0/30 =====================/
    PostgreSQL listens on site b's address 10.78.3.1 (cloud1 reaches it over the b-c link).

cloud0 is SIGKILLed mid-run: the robot goes on with cloud1 at the other site (the
cloud tier, not the leader), and every telemetry record is in the shared store once.
Needs root and ``ip``; the suite runs it with the other netns tests (``-m netns``).  About 30 s.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess

import pytest
from conftest import free_port

from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.mesh.testing import STUB, read_records, spawn_peer, stop_peer, wait_for
from scmr_mesh.scenario.sites import Sites, plan_sites, unavailable_reason

LINKS = [(0, 1), (0, 2), (1, 2)]


def test_plan_sites_addresses_and_cleanup():
    names, up, down, addrs = plan_sites("t1", 3, LINKS)
    assert names == ["scmrm-t1-a", "scmrm-t1-b", "scmrm-t1-c"]
    assert addrs == {(0, 1): ("10.78.1.1", "10.78.1.2"), (0, 2): ("10.78.2.1", "10.78.2.2"),
                     (1, 2): ("10.78.3.1", "10.78.3.2")}
    assert not any("route" in cmd for cmd in up)
    assert down == [["netns", "del", n] for n in names]
    ran = []
    with Sites(3, LINKS, "t1", executor=ran.append) as got:
        assert got == names
    assert ran == up + down


@pytest.mark.netns
@pytest.mark.timeout(240)
def test_clouds_at_two_sites_share_one_postgres_and_survive_a_node_crash(tmp_path):
    from scmr_mesh.fleet.pgserver import PgServer, available

    reason = unavailable_reason() or available()
    if reason:
        pytest.skip(reason)
    sites = Sites(3, LINKS)
    procs, pg = [], None
    lo = lambda p: f"tcp/127.0.0.1:{p}"  # noqa: E731
    try:
        ns_a, ns_b, ns_c = sites.__enter__()
        (a_b, b_a), (a_c, c_a), (b_c, c_b) = sites.addrs[(0, 1)], sites.addrs[(0, 2)], sites.addrs[(1, 2)]
        pg = PgServer(tmp_path / "pg", listen=b_c, port=free_port(), trust=("10.78.3.0/30",),
                      prefix=("ip", "netns", "exec", ns_b))
        pg.start()
        # cloud1 at site c reaches the database over the b-c link; the test reads it over the Unix socket
        dsn_tcp = pg.dsn
        dsn_sock = f"postgresql://scmr@/scmr?host={pg.socket_dir}&port={pg.port}"
        ports = {n: free_port() for n in ("ra", "rb", "rc", "cloud0", "cloud1", "leader0", "r1")}
        common = ["--lease-ms", "300"]

        def start(ns, name, args):
            p = spawn_peer([*args, "--ready-file", str(tmp_path / f"{name}.ready")], log_path=tmp_path / f"{name}.log",
                           prefix=["ip", "netns", "exec", ns])
            procs.append(p)
            return p

        def ready(name, p):
            f = tmp_path / f"{name}.ready"
            wait_for(lambda: f.exists() or p.poll() is not None, timeout=120, what=f"{name} ready")
            assert p.poll() is None, (tmp_path / f"{name}.log").read_text()

        rb = start(ns_b, "rb", ["router", "--insecure", "--listen", f"tcp/0.0.0.0:{ports['rb']}", *common])
        rc = start(ns_c, "rc", ["router", "--insecure", "--listen", f"tcp/0.0.0.0:{ports['rc']}",
                                "--connect", f"tcp/{b_c}:{ports['rb']}", *common])
        ra = start(ns_a, "ra", ["router", "--insecure", "--listen", f"tcp/0.0.0.0:{ports['ra']}",
                                "--connect", f"tcp/{b_a}:{ports['rb']}", "--connect", f"tcp/{c_a}:{ports['rc']}",
                                *common])
        for name, p in (("rb", rb), ("rc", rc), ("ra", ra)):
            ready(name, p)
        svc = ["--workers", "1", "--process", STUB, *common]
        c0 = start(ns_b, "cloud0", ["cloud", "--insecure", "--node", "cloud0", "--listen", lo(ports["cloud0"]),
                                    "--connect", lo(ports["rb"]), "--ods", dsn_tcp, *svc])
        c1 = start(ns_c, "cloud1", ["cloud", "--insecure", "--node", "cloud1", "--listen", lo(ports["cloud1"]),
                                    "--connect", lo(ports["rc"]), "--ods", dsn_tcp, *svc])
        ld = start(ns_a, "leader0", ["leader", "--insecure", "--node", "leader0", "--listen", lo(ports["leader0"]),
                                     "--connect", lo(ports["ra"]), "--relay-dir", str(tmp_path / "relay"), *svc])
        for name, p in (("cloud0", c0), ("cloud1", c1), ("leader0", ld)):
            ready(name, p)
        robot = start(ns_a, "r1", ["robot", "--insecure", "--id", "r1", "--synthetic", "stub", "--out", str(tmp_path / "r1"),
                                   "--listen", lo(ports["r1"]), "--connect", lo(ports["ra"]), "--count", "60",
                                   "--rate", "10", "--no-local-fallback", "--wait-ms", "10000",
                                   "--telemetry-queue", str(tmp_path / "queue"), *common])
        recs = lambda: read_records(tmp_path / "r1" / "records.jsonl")  # noqa: E731
        wait_for(lambda: {r.get("served_by") for r in recs()} >= {"cloud0", "cloud1"} or robot.poll() is not None,
                 timeout=60, what="answers from both sites' cloud nodes")
        os.kill(c0.pid, signal.SIGKILL)
        n_before = len(recs())
        assert robot.wait(timeout=120) == 0, (tmp_path / "r1.log").read_text()[-3000:]
        out = recs()
        assert len(out) == 60 and all(r["ok"] for r in out), [r for r in out if not r["ok"]]
        after = out[n_before + 2:]
        assert after and all(r["served_by"] == "cloud1" for r in after), {r["served_by"] for r in after}
        summary = json.loads((tmp_path / "r1" / "telemetry.json").read_text())
        assert summary["queued"] == 0
        with OperationalDataStore(dsn_sock, readonly=True) as ods:
            assert ods.seqs("r1") == list(range(1, summary["sent"] + 1))  # each record once, whichever site stored it
        assert "(postgresql)" in (tmp_path / "cloud1.log").read_text()
    finally:
        for p in procs:
            stop_peer(p, timeout=5)
        if pg is not None:
            pg.remove()
        sites.close()
        left = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        assert not any(n in left for n in sites.names), left
