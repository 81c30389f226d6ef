"""``scmr bench tls``: the query round trip with no security, usrpwd, mutual TLS and TLS+ACL."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import zenoh

from scmr_mesh.errors import MeshError
from scmr_mesh.mesh.security import secure_config
from scmr_mesh.security.profile import SecurityProfile


def bench_link_latency(
    *,
    payload_bytes: int = 200_000,
    queries: int = 300,
    warmup: int = 30,
    kinds: tuple[str, ...] = ("none", "usrpwd", "tls", "tls+acl"),
    progress=None,
) -> dict:
    """Query round trip over loopback with each security kind (``scmr bench tls``).

    Two sessions in one process (a queryable replying 100 B, a querier sending
    ``payload_bytes``), shared memory off so every byte crosses the link (and TLS).

    Returns
    -------
    dict
        ``{"payload_bytes", "queries", "runs": [{"kind", "p50_ms", "p99_ms", "mean_ms"}]}``.
    """
    import socket
    import statistics
    import tempfile
    import time

    from scmr_mesh.security.credentials import create_credentials

    say = progress or (lambda m: None)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        creds = create_credentials(Path(tmp) / "certs", "cloud,robot1").directory
        for kind in kinds:
            base = kind.split("+")[0]
            prof = None if base == "none" else SecurityProfile(kind=base, credentials=creds, acl=kind.endswith("+acl"))
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = s.getsockname()[1]
            ep = f"tcp/127.0.0.1:{port}"
            confs = []
            for ident, listen, connect in (("cloud", [ep], []), ("robot1", [], [ep])):
                c = secure_config(prof, identity=ident, listen=listen, connect=connect)
                c.insert_json5("transport/shared_memory/enabled", "false")
                if not listen:
                    c.insert_json5("listen/endpoints", "[]")
                confs.append(c)
            key = "scmr/drivable/cloud/cloud"
            with zenoh.open(confs[0]) as a, zenoh.open(confs[1]) as b:
                qa = a.declare_queryable(key, lambda q: q.reply(q.key_expr, b"x" * 100), complete=True)
                q = b.declare_querier(key, timeout=5.0)
                t_end = time.monotonic() + 10
                while not q.matching_status.matching and time.monotonic() < t_end:
                    time.sleep(0.01)
                payload = b"\x00" * payload_bytes
                times = []
                for i in range(warmup + queries):
                    t0 = time.perf_counter()
                    ok = any(r.ok is not None for r in q.get(payload=payload))
                    dt = (time.perf_counter() - t0) * 1e3
                    if not ok:
                        raise MeshError(f"bench_link_latency: query over {kind} got no reply")
                    if i >= warmup:
                        times.append(dt)
                qa.undeclare()
            times.sort()
            run = {"kind": kind, "p50_ms": round(statistics.median(times), 3),
                   "p99_ms": round(times[min(len(times) - 1, int(0.99 * (len(times) - 1)))], 3),
                   "mean_ms": round(statistics.fmean(times), 3)}
            say(f"{kind}: p50 {run['p50_ms']} ms, p99 {run['p99_ms']} ms")
            runs.append(run)
    return {"payload_bytes": payload_bytes, "queries": queries, "shared_memory": False, "runs": runs}


def cmd_bench_tls(args: argparse.Namespace) -> int:
    if args.queries < 1 or args.payload < 1:
        from scmr_mesh.errors import InputError

        raise InputError(f"--queries and --payload must be >= 1, got {args.queries} and {args.payload}")
    res = bench_link_latency(payload_bytes=args.payload, queries=args.queries,
                             progress=lambda m: print(m, file=sys.stderr, flush=True))
    res["note"] = "two sessions in one process, loopback, shared memory off; shared, loaded 2-core machine"
    for r in res["runs"]:
        print(f"{r['kind']:>8}: p50 {r['p50_ms']:.3f} ms  p99 {r['p99_ms']:.3f} ms  mean {r['mean_ms']:.3f} ms")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2)
    return 0
