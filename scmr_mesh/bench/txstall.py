"""Probe: does a silent cloud link drop stall a robot's path to the leader? (root, netns)

The reproduction behind docs/ZENOH.md section 8.  Six bare zenoh peers (no
pipeline, no data tier), each in its own network namespace ``scmrb-<id>-<peer>``
on a bridge, built with scmr's zenoh config (:mod:`scmr_mesh.mesh.config`):
a cloud and a leader that answer queries after ``--delay`` seconds, and four
robots that send ``--payload``-byte queries every ``--period`` seconds, cloud
first and the leader when the cloud does not answer.  At ``--at`` seconds the
cloud is blackholed from everyone (silent loss) for ``--for`` seconds.  One JSON
line per run: per robot, the time from the blackhole to its first leader answer
and how many of its other links dropped during the fault.

Usage::

    python -m scmr_mesh.bench.txstall --runs 3
    python -m scmr_mesh.bench.txstall --runs 3 \\
        --cfg transport/link/tx/queue/congestion_control/block/wait_before_close:5000000
    ZENOH_RUNTIME='(rx: (worker_threads: 2), tx: (worker_threads: 1))' python -m scmr_mesh.bench.txstall

``--cfg`` overrides go to every peer after scmr's defaults (so the second line
restores zenoh's 5 s default and shows the stall).  Namespaces are deleted and
peers killed on exit, also on failure.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["main", "run_once"]

PEER = r"""
import json, os, sys, threading, time
import zenoh
from scmr_mesh.mesh.config import MeshConfig, open_session
role, name, listen, connect, lease, out, delay, payload, period, cc = sys.argv[1:11]
cfg = sys.argv[11:]
s = open_session(MeshConfig(listen=[listen], connect=[c for c in connect.split(",") if c], lease_ms=int(lease), cfg=cfg))
f = open(out, "a", buffering=1)
def emit(**kw):
    kw["t"] = time.time()
    f.write(json.dumps(kw) + "\n")
emit(ev="open", zid=str(s.info.zid()), name=name)
ll = s.info.declare_link_events_listener(
    lambda e: emit(ev="link", kind=str(e.kind), zid=str(e.link.zid), dst=str(e.link.dst)), history=False)
if role != "robot":
    def answer(q):
        q.reply(q.key_expr, b"r" * 1500)
        q.drop()
    d = float(delay)
    qa = s.declare_queryable(f"scmr/drivable/{role}/{name}",
                             lambda q: threading.Timer(d, answer, (q,)).start(), complete=True)
    tok = s.liveliness().declare_token(f"scmr/alive/{role}/{name}")
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        pass
else:
    cc = zenoh.CongestionControl.BLOCK if cc == "block" else zenoh.CongestionControl.DROP
    qc = s.declare_querier("scmr/drivable/cloud/cloud", timeout=1.0, congestion_control=cc)
    ql = s.declare_querier("scmr/drivable/leader/leader", timeout=1.0, congestion_control=cc)
    data = os.urandom(int(payload))
    seq = 0
    try:
        while True:
            t0 = time.time()
            for tier, q in (("cloud", qc), ("leader", ql)):
                if not q.matching_status.matching:
                    continue
                ok = False
                for r in q.get(payload=data):
                    ok = ok or r.ok is not None
                emit(ev="q", seq=seq, tier=tier, ok=ok)
                if ok:
                    break
            seq += 1
            time.sleep(max(0.0, float(period) - (time.time() - t0)))
    except KeyboardInterrupt:
        pass
s.close()
"""


def _ip(*argv: str) -> None:
    subprocess.run(["ip", *argv], check=True, capture_output=True, timeout=20)


def run_once(*, at_s: float = 3.0, for_s: float = 4.0, lease_ms: int = 150, payload: int = 3_000_000,
             period: float = 0.1, delay: float = 0.03, cfg: list[str] | None = None, block: bool = False) -> dict:
    """One run; returns ``{"robots": {id: {"first_leader_ms", "other_links_dropped"}}, "worst_ms"}``."""
    peers = ["cloud", "leader", "robot1", "robot2", "robot3", "robot4"]
    tag = secrets.token_hex(2)
    ns = {p: f"scmrb-{tag}-{p}" for p in peers}
    br = f"scmrb-{tag}-br"
    addr = {p: f"198.18.0.{10 + i}" for i, p in enumerate(peers)}
    ep = {p: f"tcp/{a}:7447" for p, a in addr.items()}
    procs: list[subprocess.Popen] = []
    made: list[str] = []
    work = Path(tempfile.mkdtemp(prefix="scmr-txstall-"))
    try:
        _ip("netns", "add", br)
        made.append(br)
        _ip("-n", br, "link", "add", "br0", "type", "bridge")
        _ip("-n", br, "link", "set", "br0", "up")
        for i, p in enumerate(peers):
            _ip("netns", "add", ns[p])
            made.append(ns[p])
            _ip("-n", ns[p], "link", "set", "lo", "up")
            _ip("-n", br, "link", "add", f"v{i}", "type", "veth", "peer", "name", "eth0", "netns", ns[p])
            _ip("-n", br, "link", "set", f"v{i}", "master", "br0")
            _ip("-n", br, "link", "set", f"v{i}", "up")
            _ip("-n", ns[p], "addr", "add", f"{addr[p]}/24", "dev", "eth0")
            _ip("-n", ns[p], "link", "set", "eth0", "up")

        def start(p: str, role: str, connect: list[str]) -> None:
            argv = ["ip", "netns", "exec", ns[p], sys.executable, "-c", PEER, role, p, ep[p],
                    ",".join(ep[c] for c in connect), str(lease_ms), str(work / f"{p}.jsonl"), str(delay),
                    str(payload), str(period), "block" if block else "drop", *(cfg or [])]
            procs.append(subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=open(work / f"{p}.err", "w"),
                                          start_new_session=True))

        start("cloud", "cloud", [])
        start("leader", "leader", ["cloud"])
        time.sleep(1.0)
        for r in peers[2:]:
            start(r, "robot", ["cloud", "leader"])
        time.sleep(2.0 + at_s)
        t_block = time.time()
        for p in peers[1:]:
            _ip("-n", ns["cloud"], "route", "add", "blackhole", f"{addr[p]}/32")
            _ip("-n", ns[p], "route", "add", "blackhole", f"{addr['cloud']}/32")
        time.sleep(for_s)
        for p in peers[1:]:
            _ip("-n", ns["cloud"], "route", "del", "blackhole", f"{addr[p]}/32")
            _ip("-n", ns[p], "route", "del", "blackhole", f"{addr['cloud']}/32")
        time.sleep(1.0)
    finally:
        for p in procs:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
        for n in reversed(made):
            subprocess.run(["ip", "netns", "del", n], capture_output=True, timeout=20)
    out: dict = {"robots": {}}
    for r in peers[2:]:
        f = work / f"{r}.jsonl"
        evs = [json.loads(line) for line in f.read_text().splitlines()] if f.exists() else []
        first = next((e["t"] for e in evs if e["ev"] == "q" and e["tier"] == "leader" and e["ok"]
                      and e["t"] > t_block), None)
        dropped = sum(1 for e in evs if e["ev"] == "link" and "DELETE" in e["kind"] and t_block < e["t"] < t_block + for_s
                      and addr["cloud"] not in e["dst"])
        out["robots"][r] = {"first_leader_ms": None if first is None else round((first - t_block) * 1e3, 1),
                            "other_links_dropped": dropped}
    gaps = [v["first_leader_ms"] for v in out["robots"].values()]
    out["worst_ms"] = None if any(g is None for g in gaps) else max(gaps)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m scmr_mesh.bench.txstall", description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=1, help="repetitions (default 1, about 12 s each)")
    p.add_argument("--at", type=float, default=3.0, help="blackhole the cloud after this many seconds (default 3)")
    p.add_argument("--for", dest="for_s", type=float, default=4.0, help="for this many seconds (default 4)")
    p.add_argument("--lease-ms", type=int, default=150, help="zenoh lease of every peer (default 150)")
    p.add_argument("--payload", type=int, default=3_000_000, help="query payload in bytes (default 3000000)")
    p.add_argument("--period", type=float, default=0.1, help="seconds between a robot's requests (default 0.1)")
    p.add_argument("--delay", type=float, default=0.03, help="server answer delay in seconds (default 0.03)")
    p.add_argument("--cfg", action="append", default=[], metavar="KEY:JSON5", help="zenoh override for every peer")
    p.add_argument("--block", action="store_true",
                   help="robots query with congestion control block (as before issue 14) instead of drop (what scmr robots do)")
    a = p.parse_args(argv)
    if os.geteuid() != 0:
        print("txstall: error: needs root (network namespaces)", file=sys.stderr)
        return 1
    for i in range(a.runs):
        res = run_once(at_s=a.at, for_s=a.for_s, lease_ms=a.lease_ms, payload=a.payload, period=a.period,
                       delay=a.delay, cfg=a.cfg, block=a.block)
        print(json.dumps(dict(res, run=i, cfg=a.cfg, block=a.block, zenoh_runtime=os.environ.get("ZENOH_RUNTIME"),
                              tcp_user_timeout_ms=os.environ.get("SCMR_TCP_USER_TIMEOUT_MS"))), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
