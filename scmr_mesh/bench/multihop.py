"""``scmr bench multihop``: Zenoh routers as multi-hop relays (issue 22): cost per hop, reroute after a relay crash.

Real ``scmr router`` processes on loopback, each handed only its neighbours
(gossip off, so no router links to one it was not handed), and two client
sessions in this process: a queryable attached to the first router (the
portal's server) and a querier attached to the last (a robot deep in the
tunnel).

* **chain**: routers R0 - R1 - ... - Rn in a line; the query crosses n
  router-to-router links (the radio hops of a router-per-robot tunnel).  ToR
  median per n, and the cost per hop (least-squares slope of the medians).
* **diamond**: portal P, relays A and B, far router F (P-A-F and P-B-F);
  queries every ``--period-ms``; one relay is SIGKILLed; ``reroute_ms`` is
  the time from the kill to the first answer to a query sent after it (the
  route moved to the other relay), or 0 when no query failed (it did not
  carry the traffic).  Silent relay loss (a radio walking out of range) needs
  network namespaces: ``scmr scenario run`` with a radio topology.

Medians and maxima measured in one run; nothing here is a pass/fail threshold.
"""

from __future__ import annotations

import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

from scmr_mesh.errors import InputError

KEY = "scmr/bench/multihop"


def _client(endpoint: str):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


class Routers:
    """Router processes on loopback; ``links`` says whom each connects to."""

    def __init__(self, names: list[str], links: dict[str, list[str]], tmp: Path, *, lease_ms: int) -> None:
        from scmr_mesh.ports import free_ports

        self.ports = free_ports(names)
        self.tmp = tmp
        self.procs = {}
        self.names, self.links, self.lease_ms = names, links, lease_ms

    def endpoint(self, name: str) -> str:
        return f"tcp/127.0.0.1:{self.ports[name]}"

    def start(self) -> None:
        from scmr_mesh.mesh.testing import spawn_peer, wait_for

        for n in self.names:
            argv = ["router", "--insecure", "--listen", self.endpoint(n), "--lease-ms", str(self.lease_ms),
                    "--cfg", "scouting/gossip/enabled:false", "--ready-file", str(self.tmp / f"{n}.ready")]
            for m in self.links.get(n, []):
                argv += ["--connect", self.endpoint(m)]
            self.procs[n] = spawn_peer(argv, log_path=self.tmp / f"{n}.log")
        wait_for(lambda: all((self.tmp / f"{n}.ready").exists() for n in self.names), timeout=60,
                 what="routers ready")

    def kill(self, name: str) -> int:
        import os
        import signal

        t = time.time_ns()
        os.killpg(self.procs[name].pid, signal.SIGKILL)
        self.procs[name].wait()
        return t

    def stop(self) -> None:
        from scmr_mesh.mesh.testing import stop_peer

        for p in self.procs.values():
            stop_peer(p, timeout=5)


def _serve(session):
    def on_query(q):
        q.reply(q.key_expr, b"ok")

    return session.declare_queryable(KEY, on_query)


def _ask(session, timeout_s: float) -> float | None:
    """One query; ms to its answer, or None."""
    t0 = time.perf_counter()
    for reply in session.get(KEY, timeout=timeout_s):
        if reply.ok is not None:
            return (time.perf_counter() - t0) * 1e3
    return None


def chain(max_hops: int, queries: int, *, lease_ms: int, tmp: Path) -> list[dict]:
    """ToR per number of router-to-router hops (0 .. max_hops)."""
    out = []
    for hops in range(max_hops + 1):
        names = [f"r{i}" for i in range(hops + 1)]
        links = {names[i]: [names[i - 1]] for i in range(1, len(names))}
        d = tmp / f"chain{hops}"
        d.mkdir()
        routers = Routers(names, links, d, lease_ms=lease_ms)
        try:
            routers.start()
            with _client(routers.endpoint(names[0])) as srv, _client(routers.endpoint(names[-1])) as cli:
                q = _serve(srv)
                deadline = time.monotonic() + 30
                while _ask(cli, 1.0) is None:  # routes settle: the queryable is known at the far end
                    if time.monotonic() > deadline:
                        raise InputError(f"no answer over {hops} router hops within 30 s (see {d}/*.log)")
                for _ in range(20):
                    _ask(cli, 1.0)
                tors = [t for t in (_ask(cli, 1.0) for _ in range(queries)) if t is not None]
                q.undeclare()
        finally:
            routers.stop()
        row = {"hops": hops, "queries": queries, "answered": len(tors),
               "tor_ms_p50": statistics.median(tors) if tors else None,
               "tor_ms_p90": statistics.quantiles(tors, n=10)[-1] if len(tors) >= 10 else None}
        print(f"multihop chain: {hops} router hops: {len(tors)}/{queries} answered, p50 "
              f"{row['tor_ms_p50']:.3f} ms", file=sys.stderr)
        out.append(row)
    return out


def slope(rows: list[dict]) -> float | None:
    """Least-squares ms per hop over the chain's medians."""
    pts = [(r["hops"], r["tor_ms_p50"]) for r in rows if r["tor_ms_p50"] is not None]
    if len(pts) < 2:
        return None
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    den = sum((x - mx) ** 2 for x, _ in pts)
    return sum((x - mx) * (y - my) for x, y in pts) / den if den else None


def diamond(runs: int, *, period_ms: float, lease_ms: int, tmp: Path) -> list[dict]:
    """Reroute time after SIGKILL of relay A or B (alternately) in P-A-F / P-B-F."""
    out = []
    for i in range(runs):
        victim = "a" if i % 2 == 0 else "b"
        d = tmp / f"diamond{i}"
        d.mkdir()
        routers = Routers(["p", "a", "b", "f"], {"a": ["p"], "b": ["p"], "f": ["a", "b"]}, d, lease_ms=lease_ms)
        try:
            routers.start()
            with _client(routers.endpoint("p")) as srv, _client(routers.endpoint("f")) as cli:
                q = _serve(srv)
                deadline = time.monotonic() + 30
                while _ask(cli, 1.0) is None:
                    if time.monotonic() > deadline:
                        raise InputError(f"no answer across the diamond within 30 s (see {d}/*.log)")
                results: list[tuple[int, int | None]] = []  # (sent ns, answered ns or None)
                stop = threading.Event()

                def loop() -> None:
                    k, t0 = 0, time.monotonic_ns()
                    while not stop.is_set():
                        due = t0 + round(k * period_ms * 1e6)  # query k at t0 + k x period
                        wait = (due - time.monotonic_ns()) / 1e9
                        if wait > 0:
                            time.sleep(wait)
                        sent = time.time_ns()
                        ms = _ask(cli, max(2.0, 4 * lease_ms / 1000))
                        results.append((sent, None if ms is None else sent + int(ms * 1e6)))
                        k += 1

                th = threading.Thread(target=loop, daemon=True)
                th.start()
                time.sleep(1.0)  # steady traffic before the crash
                t_kill = routers.kill(victim)
                end = time.monotonic() + 5.0 + 4 * lease_ms / 1000
                while time.monotonic() < end and not any(s >= t_kill and a is not None for s, a in results):
                    time.sleep(0.01)
                time.sleep(0.5)
                stop.set()
                th.join(timeout=10)
                q.undeclare()
        finally:
            routers.stop()
        failed = [s for s, a in results if a is None and s >= t_kill - 4 * lease_ms * 10**6]
        after = [a for s, a in results if s >= t_kill and a is not None]
        reroute = (min(after) - t_kill) / 1e6 if after else None
        row = {"run": i + 1, "killed": victim, "queries": len(results), "failed": len(failed),
               "reroute_ms": (0.0 if not failed else reroute) if after else None}
        print(f"multihop diamond run {i + 1}: relay {victim} SIGKILLed: {len(failed)} queries failed, reroute "
              f"{row['reroute_ms'] if row['reroute_ms'] is not None else 'NEVER'} ms", file=sys.stderr)
        out.append(row)
    return out


_QUERIER = r"""
import json, sys, threading, time, zenoh
ep, key, period_ms, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
tail_s = float(sys.argv[5]) if len(sys.argv) > 5 else 2.0
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([ep]))
conf.insert_json5("scouting/multicast/enabled", "false")
lock = threading.Lock()
with zenoh.open(conf) as s:
    print(json.dumps({"ready": time.time_ns()}), flush=True)
    t0, k = time.monotonic_ns(), 0
    while time.monotonic_ns() - t0 < seconds * 1e9:
        due = t0 + round(k * period_ms * 1e6)
        wait = (due - time.monotonic_ns()) / 1e9
        if wait > 0:
            time.sleep(wait)
        sent = time.time_ns()
        def cb(reply, sent=sent, k=k):
            if reply.ok is not None:
                with lock:
                    print(json.dumps({"k": k, "sent": sent, "ok": time.time_ns()}), flush=True)
        s.get(key, handler=cb, timeout=30.0)
        with lock:
            print(json.dumps({"k": k, "sent": sent}), flush=True)
        k += 1
    time.sleep(tail_s)
"""

_QUERYABLE = r"""
import json, sys, time, zenoh
ep, key = sys.argv[1], sys.argv[2]
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([ep]))
conf.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(conf) as s:
    q = s.declare_queryable(key, lambda query: query.reply(query.key_expr, b"ok"))
    print("ready", flush=True)
    sys.stdin.readline()
"""


def silent_diamond(runs: int, *, period_ms: float, lease_ms: int, tmp: Path, hold_s: float = 12.0,
                   tail_s: float = 2.0) -> list[dict]:
    """(root) The diamond in network namespaces; relay A or B goes *silent* (blackhole routes, no FIN/RST).

    Each router and client runs in its own namespace (``scmr_mesh.scenario.netns``); the relay's
    links to the portal and the far router are blackholed at once, as a robot walking out of range
    would lose them.  Returns per run: queries sent in the ``hold_s`` after the cut, how many were
    never answered (an answer may come up to ``tail_s`` after the last query), and ``reroute_ms``:
    the cut to the first answer to a query sent after it.
    """
    import subprocess

    from scmr_mesh.scenario.netns import NetnsBackend, check_root
    from scmr_mesh.scenario.plan import Event
    from scmr_mesh.scenario.spec import parse_scenario

    check_root()
    sc = parse_scenario({"name": "diamond", "seed": 1, "duration_s": 600,
                         "fleet": {"clouds": ["p"], "leader": False,
                                   "robots": [{"id": n, "synthetic": "road"} for n in ("a", "b", "f")]}})
    links = {"a": ["p"], "b": ["p"], "f": ["a", "b"]}
    out = []
    for i in range(runs):
        victim = "a" if i % 2 == 0 else "b"
        be = NetnsBackend(sc)
        d = tmp / f"silent{i}"
        d.mkdir()
        procs = []
        try:
            be.setup()
            ep = {n: f"tcp/{be.layout.addr(n)}:7449" for n in ("p", "a", "b", "f")}
            from scmr_mesh.mesh.testing import spawn_peer, wait_for

            for n in ("p", "a", "b", "f"):
                argv = ["router", "--insecure", "--listen", ep[n], "--lease-ms", str(lease_ms),
                        "--cfg", "scouting/gossip/enabled:false", "--ready-file", str(d / f"{n}.ready")]
                for m in links.get(n, []):
                    argv += ["--connect", ep[m]]
                procs.append(spawn_peer(argv, log_path=d / f"{n}.log", prefix=["ip", "netns", "exec", be.layout.ns(n)]))
            wait_for(lambda: all((d / f"{n}.ready").exists() for n in ("p", "a", "b", "f")), timeout=60,
                     what="routers ready")
            srv = subprocess.Popen(["ip", "netns", "exec", be.layout.ns("p"), sys.executable, "-c", _QUERYABLE,
                                    ep["p"], KEY], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            procs.append(srv)
            assert srv.stdout.readline().strip() == "ready"
            cli = subprocess.Popen(["ip", "netns", "exec", be.layout.ns("f"), sys.executable, "-c", _QUERIER,
                                    ep["f"], KEY, str(period_ms), str(2.0 + hold_s), str(tail_s)],
                                   stdout=subprocess.PIPE, text=True)
            procs.append(cli)
            lines: list[dict] = []
            reader = threading.Thread(target=lambda: lines.extend(json.loads(x) for x in cli.stdout), daemon=True)
            reader.start()
            wait_for(lambda: sum(1 for x in lines if "ok" in x) >= 20, timeout=30, what="answers before the cut")
            time.sleep(1.0)
            t_cut = time.time_ns()
            be.apply_many([Event(0.0, "block", tuple(sorted((victim, "p")))),
                           Event(0.0, "block", tuple(sorted((victim, "f"))))])
            cli.wait(timeout=hold_s + tail_s + 30)
            reader.join(timeout=10)
            srv.stdin.close()
        finally:
            from scmr_mesh.mesh.testing import stop_peer

            for p in procs:
                stop_peer(p, timeout=5)
            be.teardown()
        sent = {x["k"]: x["sent"] for x in lines if "ok" not in x and "k" in x}
        ok = {x["k"]: x["ok"] for x in lines if "ok" in x}
        after = [k for k, t in sent.items() if t >= t_cut]
        lost = [k for k in sent if sent[k] >= t_cut - 2 * lease_ms * 10**6 and k not in ok]
        first = min((ok[k] for k in after if k in ok), default=None)
        row = {"run": i + 1, "silent": victim, "queries_after_cut": len(after), "never_answered": len(lost),
               "reroute_ms": None if first is None else (first - t_cut) / 1e6}
        print(f"multihop silent diamond run {i + 1}: relay {victim} silent: {len(lost)} queries never answered, "
              f"reroute {row['reroute_ms'] if first is not None else 'NEVER'} ms", file=sys.stderr)
        out.append(row)
    return out


def cmd_bench_multihop(args) -> int:
    with tempfile.TemporaryDirectory(prefix="scmr-multihop-") as t:
        tmp = Path(t)
        rows = chain(args.max_hops, args.queries, lease_ms=args.lease_ms, tmp=tmp)
        dia = diamond(args.runs, period_ms=args.period_ms, lease_ms=args.lease_ms, tmp=tmp) if args.runs else []
        silent = (silent_diamond(args.silent_runs, period_ms=args.period_ms, lease_ms=args.lease_ms, tmp=tmp)
                  if args.silent_runs else [])
    per_hop = slope(rows)
    rr = [r["reroute_ms"] for r in dia if r["reroute_ms"] is not None]
    out = {"benchmark": "multihop", "lease_ms": args.lease_ms, "chain": rows, "cost_per_hop_ms": per_hop,
           "diamond": dia, "reroute_ms_median": statistics.median(rr) if rr else None,
           "reroute_ms_max": max(rr) if rr else None,
           "reroute_never": sum(1 for r in dia if r["reroute_ms"] is None), "silent": silent}
    print(f"multihop: cost per router hop {per_hop:.3f} ms (least squares over {len(rows)} chain lengths); "
          + (f"reroute after a relay crash: median {out['reroute_ms_median']} ms, max {out['reroute_ms_max']} ms, "
             f"never {out['reroute_never']} of {len(dia)}" if dia else "no diamond runs"))
    if args.json:
        try:
            Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
        except OSError as exc:
            raise InputError(f"--json {args.json}: cannot write ({exc})") from None
    if silent:
        sr = [r["reroute_ms"] for r in silent if r["reroute_ms"] is not None]
        print(f"multihop: a relay gone silent: reroute median {statistics.median(sr) if sr else None} ms, "
              f"max {max(sr) if sr else None} ms, never {sum(r['reroute_ms'] is None for r in silent)} of "
              f"{len(silent)}; queries never answered {sum(r['never_answered'] for r in silent)}")
    return 1 if out["reroute_never"] or any(r["reroute_ms"] is None for r in silent) else 0
