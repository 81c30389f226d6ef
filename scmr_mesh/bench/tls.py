"""``scmr bench tls``: the query round trip with no security, usrpwd, mutual TLS and TLS+ACL."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import zenoh

from scmr_mesh import keys
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
    from scmr_mesh.ports import free_port
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
            port = free_port()
            ep = f"tcp/127.0.0.1:{port}"
            confs = []
            for ident, listen, connect in (("cloud", [ep], []), ("robot1", [], [ep])):
                c = secure_config(prof, identity=ident, listen=listen, connect=connect)
                c.insert_json5("transport/shared_memory/enabled", "false")
                if not listen:
                    c.insert_json5("listen/endpoints", "[]")
                confs.append(c)
            with zenoh.open(confs[0]) as a, zenoh.open(confs[1]) as b:
                qa = a.declare_queryable(keys.drivable_serve("cloud", "cloud"),
                                         lambda q: q.reply(str(q.key_expr), b"x" * 100), complete=True)
                q = b.declare_querier(keys.drivable_request("cloud", "cloud", "robot1"), timeout=5.0)
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


def bench_fleets(*, runs: int = 2, robots: int = 4, duration_s: float = 10.0, root: Path | None = None,
                 progress=None) -> dict:
    """Whole fleets as ``scmr up`` runs them, secured and ``--insecure`` alternately.

    Each run: a cloud, the leader and ``robots`` robots on loopback sending synthetic JPEG
    frames at 5 Hz to the stub service (so the mesh's transport, not the pipeline, is
    timed).  Returns per mode the pooled ToR median and p99 over every request, the RoR,
    and the median time from the first peer's start to the fleet being ready.
    """
    import os
    import statistics
    import tempfile
    import time

    from scmr_mesh.fleet.plan import FleetConfig
    from scmr_mesh.fleet.run import run_fleet
    from scmr_mesh.mesh.testing import STUB

    say = progress or (lambda m: None)
    base = Path(root) if root is not None else Path(tempfile.mkdtemp(prefix="scmr-bench-tls-"))
    tor: dict[str, list[float]] = {"mtls+acl": [], "insecure": []}
    out: dict[str, dict] = {m: {"runs": 0, "requests": 0, "ok": 0, "ready_s": [], "load": []} for m in tor}
    for i in range(runs):
        for mode in ("mtls+acl", "insecure") if i % 2 == 0 else ("insecure", "mtls+acl"):
            cfg = FleetConfig(robots=robots, duration_s=duration_s, rate_hz=5.0, synthetic=("structured_road",),
                              run_dir=base / f"{mode}-{i + 1}", server_args=("--process", STUB),
                              insecure=mode == "insecure", workers=1)
            t0 = time.monotonic()
            rep = run_fleet(cfg)
            peers = rep["peers"].values()
            ready = max(p["ready_unix_ns"] or 0 for p in peers) - min(p["started_unix_ns"] or 0 for p in peers)
            recs = [r for rid in rep["per_robot"] for r in _records(cfg.run_dir / "robots" / rid)]
            o = out[mode]
            o["runs"] += 1
            o["requests"] += len(recs)
            o["ok"] += sum(1 for r in recs if r["ok"])
            o["ready_s"].append(ready / 1e9)
            o["load"].append(os.getloadavg()[0])
            tor[mode] += [r["tor_ms"] for r in recs if r["ok"] and r["tier"] != "local"]
            say(f"fleet {mode} run {i + 1}: {len(recs)} requests, ToR p50 {rep['tor_ms']['p50']:.2f} ms, "
                f"p99 {rep['tor_ms']['p99']:.2f} ms ({time.monotonic() - t0:.0f} s, load {o['load'][-1]:.1f})")
    res = {}
    for mode, o in out.items():
        t = sorted(tor[mode])
        res[mode] = {
            "runs": o["runs"], "requests": o["requests"], "ror": round(o["ok"] / o["requests"], 4) if o["requests"] else None,
            "tor_p50_ms": round(statistics.median(t), 2) if t else None,
            "tor_p99_ms": round(t[min(len(t) - 1, int(0.99 * (len(t) - 1)))], 2) if t else None,
            "ready_s": round(statistics.median(o["ready_s"]), 2) if o["ready_s"] else None,
            "load_1min": [round(x, 2) for x in o["load"]],
        }
    a, b = res["mtls+acl"], res["insecure"]
    if a["tor_p50_ms"] and b["tor_p50_ms"]:
        res["p50_ratio"] = round(a["tor_p50_ms"] / b["tor_p50_ms"], 3)
        res["p99_ratio"] = round(a["tor_p99_ms"] / b["tor_p99_ms"], 3)
    return {"robots": robots, "duration_s": duration_s, "run_dir": str(base), "modes": res}


def _records(out_dir: Path) -> list[dict]:
    from scmr_mesh.mesh.testing import read_records

    return read_records(Path(out_dir) / "records.jsonl")


def cmd_bench_tls(args: argparse.Namespace) -> int:
    if args.queries < 1 or args.payload < 1:
        from scmr_mesh.errors import InputError

        raise InputError(f"--queries and --payload must be >= 1, got {args.queries} and {args.payload}")
    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    res = bench_link_latency(payload_bytes=args.payload, queries=args.queries, progress=say)
    res["note"] = "two sessions in one process, loopback, shared memory off; shared, loaded 2-core machine"
    for r in res["runs"]:
        print(f"{r['kind']:>8}: p50 {r['p50_ms']:.3f} ms  p99 {r['p99_ms']:.3f} ms  mean {r['mean_ms']:.3f} ms")
    if getattr(args, "fleet_runs", 0):
        fl = bench_fleets(runs=args.fleet_runs, robots=args.fleet_robots, duration_s=args.fleet_duration, progress=say)
        res["fleets"] = fl
        for mode, m in fl["modes"].items():
            if not isinstance(m, dict):
                continue
            print(f"fleet {mode:>8}: {m['requests']} requests in {m['runs']} runs, RoR {m['ror']}, ToR p50 "
                  f"{m['tor_p50_ms']} ms  p99 {m['tor_p99_ms']} ms, ready in {m['ready_s']} s, load {m['load_1min']}")
        if "p50_ratio" in fl["modes"]:
            print(f"fleet secured / insecure: ToR p50 x{fl['modes']['p50_ratio']}, p99 x{fl['modes']['p99_ratio']}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2)
    return 0
