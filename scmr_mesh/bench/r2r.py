"""``scmr bench r2r``: how fast the R2R tier finds itself and passes the lead on.

Two measurements, each a median, p99 and max over ``--repeat`` runs on loopback:

* **discovery**: sessions in one process, each handed a single bootstrap in a
  chain (robot k is handed robot k-1, robot 1 the cloud).  From a robot's
  ``zenoh.open`` to the moment it sees the leader's liveliness token (the
  leader was never named to it), and to the moment it has a direct link to
  every other peer (``info.peers_zid()``).  This is gossip scouting plus
  liveliness propagation, the settings of :data:`scmr_mesh.mesh.config.DEFAULTS`.
* **succession after a crash**: real processes (stub processing): a dedicated
  leader, two leader-capable robots and a plain robot at 10 Hz.  The leader
  is SIGKILLed; reported: crash to the new leader's claim (its leadership
  log), and crash to the plain robot's first answer from the new leader.

Silent drops and partitions need network namespaces: measure them with
``scmr bench scenario peers/scenarios/leader-crash.toml --backend netns``
and ``split-fleet.toml`` (docs/R2R.md).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

from scmr_mesh.errors import InputError
from scmr_mesh.ports import free_ports


def _stats(xs: list[float]) -> dict[str, Any]:
    xs = sorted(x for x in xs if x is not None)
    if not xs:
        return {"n": 0, "median": None, "p99": None, "max": None}
    p99 = xs[min(len(xs) - 1, int(round(0.99 * (len(xs) - 1))))]
    return {"n": len(xs), "median": round(statistics.median(xs), 2), "p99": round(p99, 2), "max": round(xs[-1], 2)}


def discovery_once(robots: int = 4, *, lease_ms: int = 500, timeout: float = 10.0,
                   sec=None) -> dict[str, list[float]]:
    """One chained-bootstrap run; per robot: ms to see the leader token, ms to link to every peer,
    and the share of its links that are TLS (under ``sec``: every link, also those gossip found)."""
    from scmr_mesh import keys
    from scmr_mesh.bench.secure import BenchSecurity
    from scmr_mesh.mesh.config import close_session, open_session

    sec = sec or BenchSecurity(None)
    ports = free_ports(["cloud", "leader0", *[f"r{i}" for i in range(1, robots + 1)]])
    ep = {n: f"tcp/127.0.0.1:{p}" for n, p in ports.items()}
    sessions = []
    out: dict[str, list[float]] = {"leader_token_ms": [], "full_mesh_ms": [], "tls_link_share": []}
    try:
        cloud = open_session(sec.mesh("cloud", listen=[ep["cloud"]], lease_ms=lease_ms))
        sessions.append(cloud)
        leader = open_session(sec.mesh("leader0", listen=[ep["leader0"]], connect=[ep["cloud"]], lease_ms=lease_ms))
        sessions.append(leader)
        token = leader.liveliness().declare_token(keys.alive("leader", "leader0"))
        prev = "cloud"
        for i in range(1, robots + 1):
            name = f"r{i}"
            seen = threading.Event()
            t0 = time.perf_counter()
            s = open_session(sec.mesh(name, listen=[ep[name]], connect=[ep[prev]], lease_ms=lease_ms))
            sessions.append(s)
            sub = s.liveliness().declare_subscriber(f"{keys.ALIVE}/leader/*", lambda _s: seen.set(), history=True)
            if seen.wait(timeout):
                out["leader_token_ms"].append((time.perf_counter() - t0) * 1e3)
            want = len(sessions) - 1
            end = time.monotonic() + timeout
            while time.monotonic() < end:
                if len(list(s.info.peers_zid())) >= want:
                    out["full_mesh_ms"].append((time.perf_counter() - t0) * 1e3)
                    links = list(s.info.links())
                    out["tls_link_share"].append(
                        sum(str(lk.dst).startswith("tls/") for lk in links) / max(1, len(links)))
                    break
                time.sleep(0.002)
            sub.undeclare()
            prev = name
        token.undeclare()
    finally:
        for s in reversed(sessions):
            close_session(s)
    return out


def succession_once(tmp: Path, *, lease_ms: int = 500, insecure: bool = False) -> dict[str, float | None]:
    """One crash: ms from SIGKILL of the leader to the new leader's claim, and to a robot's first answer from it."""
    from scmr_mesh.bench.secure import bench_security
    from scmr_mesh.mesh.testing import STUB, read_records, spawn_peer, stop_peer, wait_for

    sec = bench_security(tmp, "leader0=leader,r1=robot+leader-capable,r2=robot+leader-capable,r3=robot",
                         insecure=insecure)
    ports = free_ports(["leader0", "r1", "r2", "r3"])
    procs = {}

    def start(name: str, args: list[str]) -> None:
        ready = tmp / "ready" / f"{name}.ready"
        procs[name] = spawn_peer([*args, *sec.args, "--listen", f"tcp/127.0.0.1:{ports[name]}", "--lease-ms", str(lease_ms),
                                  "--ready-file", str(ready)], log_path=tmp / f"{name}.log")
        wait_for(lambda: ready.exists() or procs[name].poll() is not None, timeout=120, what=f"{name} ready")
        if procs[name].poll() is not None:
            raise InputError(f"bench r2r: {name} did not start; see {tmp / (name + '.log')}")

    boot = ["--connect", f"tcp/127.0.0.1:{ports['leader0']}"]
    robot = ["--synthetic", "stub", "--process", STUB, "--rate", "10"]
    try:
        start("leader0", ["leader", "--node", "leader0", "--workers", "1", "--process", STUB])
        start("r1", ["robot", "--id", "r1", *robot, "--out", str(tmp / "r1"), "--leader-capable",
                     "--capability", "robot4", *boot])
        start("r2", ["robot", "--id", "r2", *robot, "--out", str(tmp / "r2"), "--leader-capable",
                     "--capability", "robot3", *boot])
        start("r3", ["robot", "--id", "r3", *robot, "--out", str(tmp / "r3"), *boot])
        wait_for(lambda: sum(r["served_by"] == "leader0" for r in read_records(tmp / "r3" / "records.jsonl")) >= 5,
                 timeout=60, what="r3 served by leader0")
        t_kill = time.time_ns()
        os.killpg(procs["leader0"].pid, signal.SIGKILL)
        events = tmp / "leadership" / "r1.jsonl"

        def answered():
            return [r for r in read_records(tmp / "r3" / "records.jsonl")
                    if r["served_by"] == "r1" and r["tier"] == "leader" and r["received_unix_ns"] > t_kill]

        wait_for(lambda: events.exists() and answered(), timeout=30, what="r3 served by the new leader")
        from scmr_mesh.qos.leadership import read_events

        lead = [e for e in read_events(events.parent) if e["node"] == "r1" and e["event"] == "lead"]
        local = [r for r in read_records(tmp / "r3" / "records.jsonl")
                 if r["sent_unix_ns"] > t_kill - 1e9 and r["tier"] == "local"]
        return {"claim_ms": (lead[0]["t_unix_ns"] - t_kill) / 1e6 if lead else None,
                "first_answer_ms": (min(r["received_unix_ns"] for r in answered()) - t_kill) / 1e6,
                "local_frames": len(local)}
    finally:
        for p in procs.values():
            stop_peer(p, timeout=10)


def run(*, repeat: int = 5, robots: int = 4, lease_ms: int = 500, crash: bool = True,
        progress: Callable[[str], None] = lambda m: None, insecure: bool = False) -> dict[str, Any]:
    """Both measurements (see the module docstring); secured like ``scmr up`` unless ``insecure``."""
    from scmr_mesh.bench.secure import bench_security

    disc: dict[str, list[float]] = {"leader_token_ms": [], "full_mesh_ms": [], "tls_link_share": []}
    tmpd = Path(tempfile.mkdtemp(prefix="scmr-bench-r2r-certs-"))
    sec = bench_security(tmpd, ",".join(["cloud=cloud", "leader0=leader", *[f"r{i}=robot" for i in range(1, robots + 1)]]),
                         insecure=insecure)
    for i in range(repeat):
        progress(f"discovery run {i + 1}/{repeat} ({robots} robots in a bootstrap chain, {sec.label})")
        d = discovery_once(robots, lease_ms=lease_ms, sec=sec)
        for k in disc:
            disc[k] += d[k]
    out: dict[str, Any] = {"robots": robots, "lease_ms": lease_ms, "repeat": repeat, "security": sec.label,
                           "discovery": {k: _stats(v) for k, v in disc.items()}}
    if crash:
        runs = []
        for i in range(repeat):
            progress(f"succession run {i + 1}/{repeat} (SIGKILL of the leader)")
            with tempfile.TemporaryDirectory(prefix="scmr-bench-r2r-") as tmp:
                runs.append(succession_once(Path(tmp), lease_ms=lease_ms, insecure=insecure))
        out["succession_after_crash"] = {
            "claim_ms": _stats([r["claim_ms"] for r in runs]),
            "first_answer_ms": _stats([r["first_answer_ms"] for r in runs]),
            "local_frames": sum(r["local_frames"] for r in runs),
            "runs": runs,
        }
    out["machine"] = {"cpus": os.cpu_count(), "loadavg": list(os.getloadavg())}
    return out


def cmd_bench_r2r(args: argparse.Namespace) -> int:
    if args.repeat < 1 or args.robots < 1:
        raise InputError(f"--repeat and --robots must be >= 1, got {args.repeat} and {args.robots}")
    res = run(repeat=args.repeat, robots=args.robots, lease_ms=args.lease_ms, crash=not args.no_crash,
              progress=lambda m: print(f"bench r2r: {m} ...", file=sys.stderr, flush=True), insecure=args.insecure)
    text = json.dumps(res, indent=1)
    if args.json:
        Path(args.json).write_text(text + "\n")
    print(text)
    return 0
