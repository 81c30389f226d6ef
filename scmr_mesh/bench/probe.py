"""Measure the zenoh facts the mesh relies on (numbers for docs/ZENOH.md).

Run ``python -m scmr_mesh.bench.probe <probe> [options]``; each probe starts
real processes on loopback (multicast off), prints one JSON object per
measurement on stdout and a summary line on stderr.

Probes
------
``detect``     time until a liveliness DELETE (and querier matching=False) is
               seen after the serving process is SIGKILLed, closes its session,
               or its link is blackholed (a TCP proxy stops forwarding, sockets
               stay open), for each ``--lease`` value.
``stress``     false expiries: a client queries a server back to back for
               ``--seconds`` while ``--busy`` Python threads hog the GIL in
               both processes; counts liveliness DELETEs (should be 0).
``reconnect``  time from a restarted server's ready (same port) until the client
               sees its token again, and the client's CPU while the server is
               down, per ``--retry INIT,MAX,FACTOR`` (ms); ``--token-delay``
               lets the server listen that long before it declares the token
               (a service's queryables and warm-up query).
``routers``    (root) robot and cloud in two network namespaces, joined only
               through zenoh routers: one router or one per site, ends in peer
               or client mode; counts answered requests per set-up.
``failover``   cloud + leader + robot processes; the cloud is SIGKILLed and
               restarted ``--repeat`` times; reports the failover gap (kill ->
               first leader answer, or from the first request the cloud failed
               if later), failback (restart command -> first cloud answer, and
               cloud ready -> first cloud answer) and whether every request
               was answered.
``redundant``  the same robots with and without ``--redundant`` against one
               cloud and one leader: ToR p50/p90/p99/max, bytes sent per frame
               and pipeline runs per frame (what redundancy costs and gains).
``latency``    request/reply round trip for payload sizes, first query and
               median/p99, SHM on and off, FIFO channel vs Python callback.

The probes are scripts for humans; tests do not call them.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time

from scmr_mesh.ports import free_port, free_ports

KEY_TOKEN = "probe/alive/server"
KEY_ECHO = "probe/echo"


def _conf(*, listen=(), connect=(), lease=500, keep_alive=4, shm=True, retry=True):
    from scmr_mesh.mesh.config import MeshConfig

    cfg = [f"transport/shared_memory/enabled:{'true' if shm else 'false'}"]
    if not retry:  # zenoh's own connect retry (1 s -> 4 s backoff)
        cfg.append('connect/retry:{"period_init_ms":1000,"period_max_ms":4000,"period_increase_factor":2}')
    return MeshConfig(listen=list(listen), connect=list(connect), lease_ms=lease, keep_alive=keep_alive, cfg=cfg)


def _busy(stop: threading.Event) -> None:
    x = 0
    while not stop.is_set():
        x += 1


# ------------------------------------------------------------------ server
def serve(args) -> int:
    """Child process: token + echo queryable; prints 'ready'; runs until stdin closes."""
    import zenoh

    stop = threading.Event()
    for _ in range(args.busy):
        threading.Thread(target=_busy, args=(stop,), daemon=True).start()
    conf = _conf(listen=[args.listen], lease=args.lease, shm=not args.no_shm).build()
    with zenoh.open(conf) as s:
        def echo(q):
            q.reply(q.key_expr, b"r" * args.reply_bytes)
            q.drop()

        qa = s.declare_queryable(KEY_ECHO, echo, complete=True)
        time.sleep(args.token_delay)
        tok = s.liveliness().declare_token(KEY_TOKEN)
        print("ready", flush=True)
        if args.close_after is not None:
            time.sleep(args.close_after)
            print(f"closing {time.time_ns()}", flush=True)
            tok.undeclare()
            qa.undeclare()
            return 0
        sys.stdin.read()  # until the parent closes our stdin
        stop.set()
    return 0


def _spawn_server(port: int, *, lease: int, busy: int = 0, no_shm: bool = False, close_after=None,
                  reply_bytes: int = 100, token_delay: float = 0.0) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "scmr_mesh.bench.probe", "_serve", "--listen", f"tcp/127.0.0.1:{port}",
           "--lease", str(lease), "--busy", str(busy), "--reply-bytes", str(reply_bytes),
           "--token-delay", str(token_delay)]
    if no_shm:
        cmd.append("--no-shm")
    if close_after is not None:
        cmd += ["--close-after", str(close_after)]
    env = dict(os.environ)
    env.pop("RUST_LOG", None)
    p = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
                         start_new_session=True)
    line = p.stdout.readline()
    if line.strip() != "ready":
        p.kill()
        raise RuntimeError(f"probe server failed to start: {line!r}")
    return p


class Proxy:
    """A TCP proxy 127.0.0.1:port -> 127.0.0.1:target that can stop forwarding."""

    def __init__(self, target: int) -> None:
        self.target = target
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = self.sock.getsockname()[1]
        self.holed = threading.Event()
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            u = socket.create_connection(("127.0.0.1", self.target))
            self.conns += [c, u]
            for a, b in ((c, u), (u, c)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        while True:
            try:
                data = a.recv(65536)
            except OSError:
                return
            if not data:
                return
            if self.holed.is_set():
                continue  # swallow: the link is silent, the sockets stay open
            try:
                b.sendall(data)
            except OSError:
                return

    def close(self) -> None:
        for s in [self.sock, *self.conns]:
            try:
                s.close()
            except OSError:
                pass


# ------------------------------------------------------------------ probes
def _watch(session, key: str):
    """Liveliness subscriber recording (kind, t_ns) events."""
    events: list[tuple[str, int]] = []
    cond = threading.Condition()

    def cb(sample):
        with cond:
            events.append(("PUT" if "PUT" in str(sample.kind) else "DELETE", time.time_ns()))
            cond.notify_all()

    sub = session.liveliness().declare_subscriber(key, cb, history=True)
    return sub, events, cond


def _wait_event(events, cond, kind: str, *, after: int = 0, timeout: float = 30.0) -> int | None:
    end = time.monotonic() + timeout
    with cond:
        while True:
            for k, t in events:
                if k == kind and t >= after:
                    return t
            left = end - time.monotonic()
            if left <= 0:
                return None
            cond.wait(left)


def probe_detect(args) -> int:
    import zenoh

    out = []
    for lease in args.lease:
        for case in args.cases:
            for rep in range(args.repeat):
                port = free_port()
                srv = _spawn_server(port, lease=lease, close_after=1.0 if case == "close" else None)
                proxy = Proxy(port) if case == "blackhole" else None
                ep = f"tcp/127.0.0.1:{proxy.port if proxy else port}"
                with zenoh.open(_conf(connect=[ep], lease=lease).build()) as s:
                    sub, events, cond = _watch(s, KEY_TOKEN)
                    querier = s.declare_querier(KEY_ECHO)
                    unmatched: list[int] = []
                    ml = querier.declare_matching_listener(
                        lambda st: unmatched.append(time.time_ns()) if not st.matching else None)
                    if _wait_event(events, cond, "PUT", timeout=10) is None:
                        raise RuntimeError("server token never seen")
                    time.sleep(0.3)
                    if case == "sigkill":
                        t0 = time.time_ns()
                        os.killpg(srv.pid, signal.SIGKILL)
                    elif case == "close":
                        line = srv.stdout.readline()
                        t0 = int(line.split()[1])
                    else:
                        t0 = time.time_ns()
                        proxy.holed.set()
                    t1 = _wait_event(events, cond, "DELETE", after=t0, timeout=max(30.0, 3 * lease / 1e3))
                    time.sleep(0.05)
                    rec = {"probe": "detect", "case": case, "lease_ms": lease, "keep_alive": 4, "rep": rep,
                           "delete_ms": None if t1 is None else round((t1 - t0) / 1e6, 2),
                           "matching_false_ms": round((unmatched[0] - t0) / 1e6, 2) if unmatched else None}
                    print(json.dumps(rec), flush=True)
                    out.append(rec)
                    ml.undeclare()
                    querier.undeclare()
                    sub.undeclare()
                if proxy:
                    proxy.close()
                srv.kill()
                srv.wait()
    for lease in args.lease:
        for case in args.cases:
            vals = [r["delete_ms"] for r in out if r["lease_ms"] == lease and r["case"] == case and r["delete_ms"]]
            if vals:
                print(f"detect {case:9s} lease {lease:5d} ms: median {statistics.median(vals):8.1f} ms "
                      f"(min {min(vals):.1f}, max {max(vals):.1f}, n={len(vals)})", file=sys.stderr)
    return 0


def probe_stress(args) -> int:
    import zenoh

    for lease in args.lease:
        port = free_port()
        srv = _spawn_server(port, lease=lease, busy=args.busy, reply_bytes=args.bytes)
        stop = threading.Event()
        for _ in range(args.busy):
            threading.Thread(target=_busy, args=(stop,), daemon=True).start()
        n = fails = 0
        lat = []
        with zenoh.open(_conf(connect=[f"tcp/127.0.0.1:{port}"], lease=lease).build()) as s:
            sub, events, cond = _watch(s, KEY_TOKEN)
            _wait_event(events, cond, "PUT", timeout=10)
            q = s.declare_querier(KEY_ECHO, timeout=5.0)
            payload = b"x" * args.bytes
            end = time.monotonic() + args.seconds
            while time.monotonic() < end:
                t = time.perf_counter()
                ok = any(r.ok is not None for r in q.get(payload=payload))
                lat.append((time.perf_counter() - t) * 1e3)
                n += 1
                fails += not ok
            deletes = sum(1 for k, _ in events if k == "DELETE")
            q.undeclare()
            sub.undeclare()
        stop.set()
        srv.stdin.close()
        srv.wait(timeout=10)
        lat.sort()
        rec = {"probe": "stress", "lease_ms": lease, "keep_alive": 4, "busy_threads_per_process": args.busy,
               "seconds": args.seconds, "bytes": args.bytes, "queries": n, "failed": fails,
               "false_expiries": deletes, "p50_ms": round(lat[len(lat) // 2], 3),
               "p99_ms": round(lat[int(len(lat) * 0.99)], 3)}
        print(json.dumps(rec), flush=True)
        print(f"stress lease {lease} ms, {args.busy} busy threads: {n} queries, {fails} failed, "
              f"{deletes} false expiries, p50 {rec['p50_ms']} ms p99 {rec['p99_ms']} ms", file=sys.stderr)
    return 0


def _retry_spec(text: str) -> tuple[float, float, float]:
    """``"INIT_MS,MAX_MS,FACTOR"`` -> floats (each > 0)."""
    parts = [float(x) for x in text.split(",")]
    if len(parts) != 3 or not all(x > 0 for x in parts):
        raise ValueError("three numbers > 0")
    return tuple(parts)


def probe_reconnect(args) -> int:
    import random

    import zenoh

    rng = random.Random(args.seed)
    for spec in args.retry:
        init, top, factor = (float(x) for x in spec.split(","))
        retry = {"period_init_ms": int(init), "period_max_ms": int(top), "period_increase_factor": factor}
        vals, cpus = [], []
        for rep in range(args.repeat):
            port = free_port()
            srv = _spawn_server(port, lease=500)
            conf = _conf(connect=[f"tcp/127.0.0.1:{port}"])
            conf.cfg.append(f"connect/retry:{json.dumps(retry)}")
            with zenoh.open(conf.build()) as s:
                sub, events, cond = _watch(s, KEY_TOKEN)
                _wait_event(events, cond, "PUT", timeout=10)
                os.killpg(srv.pid, signal.SIGKILL)
                srv.wait()
                _wait_event(events, cond, "DELETE", timeout=10)
                c0 = time.process_time()
                down = args.down + rng.uniform(0, 0.5)  # no phase lock with the retry period
                time.sleep(down)
                cpu_ms = (time.process_time() - c0) * 1e3
                t0 = time.time_ns()
                srv = _spawn_server(port, lease=500, token_delay=args.token_delay)
                t_ready = time.time_ns()
                t1 = _wait_event(events, cond, "PUT", after=t0, timeout=30)
                sub.undeclare()
            srv.kill()
            srv.wait()
            rec = {"probe": "reconnect", "retry": retry, "down_s": round(down, 3), "rep": rep,
                   "token_delay_ms": args.token_delay * 1e3,
                   "seen_after_restart_ms": None if t1 is None else round((t1 - t0) / 1e6, 1),
                   "server_start_ms": round((t_ready - t0) / 1e6, 1),
                   "seen_after_ready_ms": None if t1 is None else round((t1 - t_ready) / 1e6, 1),
                   "client_cpu_ms_per_s_down": round(cpu_ms / down, 2)}
            print(json.dumps(rec), flush=True)
            cpus.append(rec["client_cpu_ms_per_s_down"])
            if t1:
                vals.append(rec["seen_after_ready_ms"])
        if vals:
            print(f"reconnect retry {spec}: token seen {statistics.median(vals):.1f} ms (median, max {max(vals):.1f}) "
                  f"after the restarted server was ready; client CPU while down {statistics.median(cpus):.2f} ms/s",
                  file=sys.stderr)
    return 0


def probe_latency(args) -> int:
    import queue

    import zenoh

    for shm in (True, False):
        for size in args.sizes:
            port = free_port()
            srv = _spawn_server(port, lease=500, no_shm=not shm, reply_bytes=args.reply_bytes)
            with zenoh.open(_conf(connect=[f"tcp/127.0.0.1:{port}"], shm=shm).build()) as s:
                q = s.declare_querier(KEY_ECHO, timeout=5.0)
                deadline = time.monotonic() + 10
                while not q.matching_status.matching and time.monotonic() < deadline:
                    time.sleep(0.01)
                payload = b"x" * size

                def chan():
                    for r in q.get(payload=payload):
                        assert r.ok is not None

                def cb():
                    box: queue.Queue = queue.Queue()
                    q.get(zenoh.handlers.Callback(box.put, lambda: box.put(None)), payload=payload)
                    while box.get() is not None:
                        pass

                for name, fn in (("channel", chan), ("callback", cb)):
                    ts = []
                    for _ in range(args.n + 1):
                        t = time.perf_counter()
                        fn()
                        ts.append((time.perf_counter() - t) * 1e3)
                    first, rest = ts[0], sorted(ts[1:])
                    rec = {"probe": "latency", "shm": shm, "bytes": size, "handler": name, "first_ms": round(first, 3),
                           "p50_ms": round(rest[len(rest) // 2], 3), "p99_ms": round(rest[int(len(rest) * 0.99)], 3),
                           "n": args.n}
                    print(json.dumps(rec), flush=True)
                    print(f"latency shm={shm!s:5s} {size:8d} B {name:8s}: first {first:7.2f} ms, "
                          f"p50 {rec['p50_ms']:6.3f} ms, p99 {rec['p99_ms']:6.3f} ms", file=sys.stderr)
                q.undeclare()
            srv.stdin.close()
            srv.wait(timeout=10)
    return 0


def probe_routers(args) -> int:
    import tempfile
    from pathlib import Path

    from scmr_mesh.mesh import netns
    from scmr_mesh.mesh.testing import (
        STUB,
        read_records,
        spawn_peer,
        stop_peer,
        wait_for,
    )

    reason = netns.unavailable_reason()
    if reason:
        print(f"routers probe: {reason}", file=sys.stderr)
        return 1
    for layout in ("one-router", "router-per-site"):
        for mode in ("peer", "client"):
            tmp = Path(tempfile.mkdtemp(prefix="scmr-probe-"))
            procs = []
            sites = netns.TwoSites()
            try:
                with sites as (ns_a, ns_b):
                    def start(ns, name, argv):
                        p = spawn_peer([*argv, "--ready-file", str(tmp / f"{name}.ready")], log_path=tmp / f"{name}.log",
                                       prefix=sites.exec_prefix(ns))
                        procs.append(p)
                        wait_for(lambda: (tmp / f"{name}.ready").exists() or p.poll() is not None, timeout=60,
                                 what=f"{name} ready")
                        return p

                    lo = "tcp/127.0.0.1:{}".format
                    start(ns_b, "rb", ["router", "--insecure", "--listen", f"tcp/{netns.ADDR_B}:7449", "--listen", lo(7450)])
                    if layout == "router-per-site":
                        start(ns_a, "ra", ["router", "--insecure", "--listen", lo(7451), "--connect", f"tcp/{netns.ADDR_B}:7449"])
                        robot_ep = lo(7451)
                    else:
                        robot_ep = f"tcp/{netns.ADDR_B}:7449"
                    listen = lambda port: ["--listen", lo(port)] if mode == "peer" else []  # noqa: E731
                    start(ns_b, "c1", ["cloud", "--insecure", "--node", "c1", "--zmode", mode, *listen(7460), "--connect", lo(7450),
                                       "--workers", "1", "--process", STUB])
                    t0 = time.monotonic()
                    r = spawn_peer(["robot", "--insecure", "--id", "r1", "--zmode", mode, *listen(7461), "--connect", robot_ep,
                                    "--synthetic", "stub", "--count", str(args.count), "--rate", "20",
                                    "--no-local-fallback", "--wait-ms", "3000", "--out", str(tmp / "r1")],
                                   log_path=tmp / "r1.log", prefix=sites.exec_prefix(ns_a))
                    procs.append(r)
                    r.wait(timeout=60)
                    recs = read_records(tmp / "r1" / "records.jsonl")
                    ok = sum(1 for x in recs if x["ok"])
                    tor = sorted(x["tor_ms"] for x in recs if x["ok"])
                    rec = {"probe": "routers", "layout": layout, "mode": mode, "requests": len(recs), "answered": ok,
                           "tor_p50_ms": tor[len(tor) // 2] if tor else None,
                           "run_s": round(time.monotonic() - t0, 1)}
                    print(json.dumps(rec), flush=True)
                    print(f"routers {layout:15s} {mode:6s}: {ok}/{len(recs)} answered", file=sys.stderr)
            finally:
                for p in procs:
                    stop_peer(p, timeout=5)
    return 0


def probe_failover(args) -> int:
    import tempfile
    from pathlib import Path

    from scmr_mesh.mesh.testing import read_records, spawn_peer, stop_peer, wait_for

    tmp = Path(tempfile.mkdtemp(prefix="scmr-failover-"))
    cp, lp = free_ports(["c", "l"]).values()
    ep = "tcp/127.0.0.1:{}".format
    svc = ["--workers", str(args.workers), "--lease-ms", "500"] + (["--process", args.process] if args.process else [])
    procs = {}

    def start_cloud():
        ready = tmp / "c1.ready"
        ready.unlink(missing_ok=True)
        t = time.time_ns()
        procs["c1"] = spawn_peer(["cloud", "--insecure", "--node", "c1", "--listen", ep(cp), "--ready-file", str(ready), *svc],
                                 log_path=tmp / "c1.log")
        wait_for(ready.exists, timeout=300, what="cloud ready")
        return t, time.time_ns()

    try:
        start_cloud()
        procs["L1"] = spawn_peer(["leader", "--insecure", "--node", "L1", "--listen", ep(lp), "--connect", ep(cp),
                                  "--ready-file", str(tmp / "L1.ready"), *svc], log_path=tmp / "L1.log")
        wait_for((tmp / "L1.ready").exists, timeout=300, what="leader ready")
        src = ["--images", args.images] if args.images else ["--synthetic", "stub"]
        procs["r1"] = spawn_peer(["robot", "--insecure", "--id", "r1", *src, "--rate", str(args.rate), "--out", str(tmp / "r1"),
                                  "--connect", ep(cp), "--connect", ep(lp), "--no-local-fallback"] +
                                 (["--process", args.process] if args.process else []), log_path=tmp / "r1.log")
        recs = lambda: read_records(tmp / "r1" / "records.jsonl")  # noqa: E731
        wait_for(lambda: len(recs()) >= 10, timeout=120, what="10 records")
        events = []
        for rep in range(args.repeat):
            time.sleep(args.up)
            t_kill = time.time_ns()
            os.kill(procs["c1"].pid, signal.SIGKILL)
            procs["c1"].wait()
            time.sleep(args.down)
            t_restart, t_ready = start_cloud()
            n = len(recs())
            wait_for(lambda: any(r["tier"] == "cloud" for r in recs()[n:]), timeout=60, what="cloud answers again")
            events.append((t_kill, t_restart, t_ready))
        stop_peer(procs.pop("r1"))
        rs = recs()
        for rep, (t_kill, t_restart, t_ready) in enumerate(events):
            # the first request the fault touched: in flight at the kill (its cloud
            # attempt failed) or the first one sent after it; the gap does not
            # count the idle time before that request (the rate's share)
            touched = [r for r in rs if r["received_unix_ns"] >= t_kill and (r["sent_unix_ns"] >= t_kill or any(
                a["tier"] == "cloud" and a["outcome"] != "ok" for a in r["attempts"]))]
            start = max(t_kill, touched[0]["sent_unix_ns"]) if touched else t_kill
            leader = [r for r in rs if r["tier"] == "leader" and r["received_unix_ns"] >= t_kill]
            cloud_again = [r for r in rs if r["tier"] == "cloud" and r["received_unix_ns"] >= t_restart]
            rec = {"probe": "failover", "rep": rep, "rate_hz": args.rate, "images": bool(args.images),
                   "failover_gap_ms": round((leader[0]["received_unix_ns"] - start) / 1e6, 1) if leader else None,
                   "failback_from_restart_ms": round((cloud_again[0]["received_unix_ns"] - t_restart) / 1e6, 1)
                   if cloud_again else None,
                   "failback_from_ready_ms": round((cloud_again[0]["received_unix_ns"] - t_ready) / 1e6, 1)
                   if cloud_again else None,
                   "cloud_start_ms": round((t_ready - t_restart) / 1e6, 1)}
            print(json.dumps(rec), flush=True)
        ok = sum(1 for r in rs if r["ok"])
        tor = sorted(r["tor_ms"] for r in rs if r["ok"])
        summary = {"probe": "failover", "requests": len(rs), "answered": ok, "ror": round(ok / max(1, len(rs)), 4),
                   "tor_p50_ms": tor[len(tor) // 2] if tor else None,
                   "tor_p99_ms": tor[int(len(tor) * 0.99)] if tor else None,
                   "tor_max_ms": tor[-1] if tor else None,
                   "by_tier": {t: sum(1 for r in rs if r["tier"] == t) for t in ("cloud", "leader", "local")}}
        print(json.dumps(summary), flush=True)
        print(f"failover: {ok}/{len(rs)} answered; see JSON lines; logs in {tmp}", file=sys.stderr)
    finally:
        for p in procs.values():
            stop_peer(p, timeout=10)
    return 0


def probe_redundant(args) -> int:
    import tempfile
    from pathlib import Path

    from scmr_mesh.mesh.testing import read_records, spawn_peer, stop_peer, wait_for

    tmp = Path(tempfile.mkdtemp(prefix="scmr-redundant-"))
    cp, lp = free_ports(["c", "l"]).values()
    ep = "tcp/127.0.0.1:{}".format
    proc = ["--process", args.process] if args.process else []
    svc = ["--workers", str(args.workers), *proc]
    procs = {}
    try:
        procs["c1"] = spawn_peer(["cloud", "--insecure", "--node", "c1", "--listen", ep(cp), "--ready-file", str(tmp / "c1.ready"),
                                  *svc], log_path=tmp / "c1.log")
        procs["L1"] = spawn_peer(["leader", "--insecure", "--node", "L1", "--listen", ep(lp), "--connect", ep(cp),
                                  "--ready-file", str(tmp / "L1.ready"), *svc], log_path=tmp / "L1.log")
        for n in ("c1", "L1"):
            wait_for((tmp / f"{n}.ready").exists, timeout=300, what=f"{n} ready")
        src = ["--images", args.images] if args.images else ["--synthetic", "stub"]
        for mode in ("default", "redundant"):
            robots = []
            for i in range(args.robots):
                rid = f"{mode[:3]}{i}"
                robots.append((rid, spawn_peer(
                    ["robot", "--insecure", "--id", rid, *src, "--rate", str(args.rate), "--count", str(args.count),
                     "--out", str(tmp / rid), "--connect", ep(cp), "--connect", ep(lp), "--no-local-fallback", *proc,
                     *(["--redundant"] if mode == "redundant" else [])], log_path=tmp / f"{rid}.log")))
            for _, p in robots:
                p.wait(timeout=600)
            rs = [r for rid, _ in robots for r in read_records(tmp / rid / "records.jsonl")]
            ok = [r for r in rs if r["ok"]]
            tor = sorted(r["tor_ms"] for r in ok)
            q = lambda f: tor[min(len(tor) - 1, int(len(tor) * f))] if tor else None  # noqa: E731
            sends = sum(1 for r in rs for a in r["attempts"] if a["outcome"] not in ("unreachable",))
            rec = {"probe": "redundant", "mode": mode, "robots": args.robots, "rate_hz": args.rate,
                   "requests": len(rs), "answered": len(ok),
                   "tor_ms": {"p50": q(0.5), "p90": q(0.9), "p99": q(0.99), "max": tor[-1] if tor else None},
                   "bytes_up_per_frame": round(sum(r["bytes_up"] for r in rs) / max(1, len(rs))),
                   "pipeline_runs_per_frame": round(sends / max(1, len(rs)), 2),
                   "by_tier": {t: sum(1 for r in ok if r["tier"] == t) for t in ("cloud", "leader")}}
            print(json.dumps(rec), flush=True)
            print(f"redundant probe {mode:9s}: ToR p50 {rec['tor_ms']['p50']} p99 {rec['tor_ms']['p99']} ms, "
                  f"{rec['bytes_up_per_frame']} B up/frame, {rec['pipeline_runs_per_frame']} runs/frame",
                  file=sys.stderr)
    finally:
        for p in procs.values():
            stop_peer(p, timeout=10)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The probes' parser (``scmr bench zenoh PROBE ...`` hands it the options after PROBE)."""
    from scmr_mesh import cliargs as ca

    p = ca.ScmrArgumentParser(prog="scmr bench zenoh", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="probe", required=True)
    s = sub.add_parser("_serve")
    s.add_argument("--listen", required=True)
    s.add_argument("--lease", type=ca.count("milliseconds", lo=10, hi=3600000, example="500"), default=500)
    s.add_argument("--busy", type=ca.count("busy threads", lo=0, hi=64), default=0)
    s.add_argument("--no-shm", action="store_true")
    s.add_argument("--close-after", type=ca.positive("seconds", hi=86400), default=None)
    s.add_argument("--reply-bytes", type=ca.count("bytes", lo=0, hi=1 << 30), default=100)
    s.add_argument("--token-delay", type=ca.non_negative("seconds", hi=60), default=0.0)
    s.set_defaults(func=serve)
    d = sub.add_parser("detect", help="liveliness loss detection per lease")
    d.add_argument("--lease", type=ca.count("milliseconds", lo=10, hi=3600000, example="500"), nargs="+", default=[500])
    d.add_argument("--cases", nargs="+", default=["sigkill", "close", "blackhole"],
                   choices=["sigkill", "close", "blackhole"])
    d.add_argument("--repeat", type=ca.count("repeats", hi=1000), default=3)
    d.set_defaults(func=probe_detect)
    st = sub.add_parser("stress", help="false expiries under GIL load")
    st.add_argument("--lease", type=ca.count("milliseconds", lo=10, hi=3600000, example="500"), nargs="+", default=[500])
    st.add_argument("--busy", type=ca.count("busy threads", lo=0, hi=64), default=2)
    st.add_argument("--seconds", type=ca.positive("seconds", hi=86400), default=10.0)
    st.add_argument("--bytes", type=ca.count("bytes", hi=1 << 30), default=200_000)
    st.set_defaults(func=probe_stress)
    r = sub.add_parser("reconnect", help="token seen again after a restart")
    r.add_argument("--repeat", type=ca.count("repeats", hi=1000), default=3)
    r.add_argument("--down", type=ca.positive("seconds", hi=3600), default=1.0, help="seconds the server stays down")
    r.add_argument("--retry", type=ca.parsed(_retry_spec, what="INIT_MS,MAX_MS,FACTOR", example="50,50,1",
                                              keep_text=True),
                   nargs="+", default=["1000,4000,2", "50,250,2", "50,50,1"],
                   metavar="INIT,MAX,FACTOR", help="connect/retry settings to compare (ms, ms, factor)")
    r.add_argument("--seed", type=ca.count("seed", lo=0, hi=2**32), default=1,
                   help="seed of the random extra down time (0-0.5 s)")
    r.add_argument("--token-delay", type=ca.non_negative("seconds", hi=60), default=0.03,
                   help="seconds between the server's listen and its token (default 0.03)")
    r.set_defaults(func=probe_reconnect)
    ro = sub.add_parser("routers", help="(root) cross-namespace routing set-ups")
    ro.add_argument("--count", type=ca.count("repeats", hi=1000), default=5)
    ro.set_defaults(func=probe_routers)
    fo = sub.add_parser("failover", help="cloud SIGKILL/restart with a running robot")
    fo.add_argument("--repeat", type=ca.count("repeats", hi=1000), default=3)
    fo.add_argument("--rate", type=ca.positive("frames per second", hi=10000), default=10.0)
    fo.add_argument("--up", type=ca.positive("seconds", hi=3600), default=2.0, help="seconds between recoveries and the next kill")
    fo.add_argument("--down", type=ca.positive("seconds", hi=3600), default=2.0, help="seconds the cloud stays down")
    fo.add_argument("--workers", type=ca.count("workers", hi=256), default=1)
    fo.add_argument("--images", type=ca.PathArg("in-dir"), default=None, help="folder of frames (default: stub frames)")
    fo.add_argument("--process", default="scmr_mesh.mesh.testing:stub_process",
                    help="process function ('' for the real pipeline)")
    fo.set_defaults(func=probe_failover)
    rd = sub.add_parser("redundant", help="--redundant vs default")
    rd.add_argument("--robots", type=ca.count("robots", hi=1000), default=2)
    rd.add_argument("--rate", type=ca.positive("frames per second", hi=10000), default=5.0)
    rd.add_argument("--count", type=ca.count("frames", hi=10**6), default=40)
    rd.add_argument("--workers", type=ca.count("workers", hi=256), default=1)
    rd.add_argument("--images", type=ca.PathArg("in-dir"), default=None, help="folder of frames (default: stub frames)")
    rd.add_argument("--process", default="scmr_mesh.mesh.testing:stub_process",
                    help="process function ('' for the real pipeline)")
    rd.set_defaults(func=probe_redundant)
    la = sub.add_parser("latency", help="query round trip")
    la.add_argument("--sizes", type=ca.count("bytes", hi=1 << 30), nargs="+", default=[1000, 40_000, 260_000])
    la.add_argument("--reply-bytes", type=ca.count("bytes", lo=0, hi=1 << 30), default=1500)
    la.add_argument("-n", type=ca.count("round trips", hi=10**6), default=200)
    la.set_defaults(func=probe_latency)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
