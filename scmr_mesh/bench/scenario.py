"""``scmr bench scenario``: failover and failback gaps of a scenario over N runs."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from scmr_mesh.errors import ConfigError


#: A request sent this close to a fault's start or end (s) is not fault-free (``hedged_fault_free``).
FAULT_MARGIN_S = 1.0


def fault_free_rows(report: dict, margin_s: float = FAULT_MARGIN_S) -> list[dict]:
    """The requests of a run report sent at least ``margin_s`` before every fault and after its end.

    >>> rep = {"faults": [{"started_at_s": 4.0, "ended_at_s": 10.0}],
    ...        "request_log": [{"sent_s": t} for t in (0.5, 3.5, 6.0, 10.5, 12.0)]}
    >>> [q["sent_s"] for q in fault_free_rows(rep)]
    [0.5, 12.0]
    """
    from scmr_mesh.scenario.report import request_rows

    spans = [(f["started_at_s"] - margin_s, (f["ended_at_s"] if f.get("ended_at_s") is not None else float("inf"))
              + margin_s) for f in report.get("faults", []) if f.get("started_at_s") is not None]
    return [q for q in request_rows(report) if q.get("sent_s") is not None
            and not any(a <= q["sent_s"] <= b for a, b in spans)]


def _hedged(row: dict) -> bool:
    """Whether a request (a ``request_log`` row) sent a hedge: one of its attempts says ``hedge``."""
    return any(a.get("hedge") for a in row.get("attempts") or [])


def cmd_bench_scenario(args: argparse.Namespace) -> int:
    """Run a scenario N times; report medians and p99 of the failover/failback gaps and RoR."""
    import json as _json

    from scmr_mesh.qos.metrics import percentile
    from scmr_mesh.scenario.commands import _auto_backend, _err, _out, _with_overrides
    from scmr_mesh.scenario.report import request_rows, run_report, write_report
    from scmr_mesh.scenario.runner import check_out_dir, run_scenario
    from scmr_mesh.scenario.spec import load_scenario

    sc = _with_overrides(load_scenario(args.file), args)
    backend = _auto_backend(args.backend)
    if args.runs < 1:
        raise ConfigError(f"--runs must be at least 1, got {args.runs}")
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    base = Path(args.out) if args.out else Path("runs") / f"bench-scenario-{sc.name}-{stamp}"
    for i in range(args.runs):  # all refused up front, not after the first runs took minutes
        check_out_dir(base / f"run{i + 1}", flag=f"--out (not {base})")
    runs = []
    for i in range(args.runs):
        _err(f"bench scenario: run {i + 1}/{args.runs} of {sc.name} ({backend})")
        res = run_scenario(sc, backend=backend, out_dir=base / f"run{i + 1}", data_dir=args.data,
                           progress=lambda m: _err(f"  {m}"), ready_timeout=args.ready_timeout,
                           insecure=args.insecure)
        rep = run_report(res)
        write_report(rep, base / f"run{i + 1}")
        runs.append(rep)
    over = [g for r in runs for f in r["faults"] for g in (f["failover_by_robot"] or {}).values() if g is not None]
    over_max = [f["failover_gap_ms"] for r in runs for f in r["faults"] if f["failover_by_robot"]]
    back = [f["failback_gap_ms"] for r in runs for f in r["faults"] if f["tier"] and f["ended_at_s"] is not None]
    tors = [q["tor_ms"] for r in runs for q in request_rows(r) if q["ok"] and q["tor_ms"] is not None]

    quiet = [q for r in runs for q in fault_free_rows(r)]

    def stats(xs):
        xs = [x for x in xs if x is not None]
        return {"n": len(xs), "median": percentile(xs, 50) if xs else None, "p99": percentile(xs, 99) if xs else None,
                "max": max(xs) if xs else None}

    out = {
        "benchmark": "scenario", "scenario": sc.name, "backend": backend, "runs": args.runs, "seed": sc.seed,
        "lease_ms": sc.lease_ms, "process": sc.process or "drivable pipeline",
        "ror": [r["summary"]["ror"] for r in runs],
        "requests": [r["summary"]["requests"] for r in runs],
        "failover_gap_ms_per_robot": stats(over),
        "failover_gap_ms_per_fault_max": stats(over_max),
        "failover_never_answered": sum(1 for r in runs for f in r["faults"]
                                       if f["failover_by_robot"] and f["failover_gap_ms"] is None),
        "failback_gap_ms": stats(back),
        "tor_ms": stats(tors),
        # hedged requests per run (issue 24): hedged, answered by the hedge
        "hedged": [r["summary"].get("hedged", 0) for r in runs],
        "hedge_won": [r["summary"].get("hedge_won", 0) for r in runs],
        # requests sent at least FAULT_MARGIN_S away from every fault: the budget is < 2 %
        "hedged_fault_free": {"requests": len(quiet), "hedged": sum(map(_hedged, quiet)),
                              "rate": round(sum(map(_hedged, quiet)) / len(quiet), 4) if quiet else None},
        "expectations_held": [all(e["held"] for e in r["expectations"]) for r in runs],
        "expectations_failed": sorted({e["name"] for r in runs for e in r["expectations"] if not e["held"]}),
        "shape": sc.shape,
        "multihop": {k: [(r.get("multihop") or {}).get(k) for r in runs]
                     for k in ("max_hops", "alone_with_path", "max_reroute_ms", "split_leader_ms")},
        "reroute_ms_per_robot": stats([v for r in runs for f in r["faults"] + (r.get("multihop") or {}).get(
            "radio_reroutes", []) for v in (f.get("reroute_ms") or {}).values()]),
        "robot_host": {k: stats([(r.get("hosts") or {}).get("robot_mean", {}).get(k) for r in runs])["median"]
                       for k in ("peak_rss_mb", "cpu_s", "links", "sockets")},
        "local_answers": [r["summary"]["by_tier"].get("local", 0) for r in runs],
        "out": str(base),
        "note": "measured on a shared, busy 2-core machine" if (os.cpu_count() or 0) <= 2 else "",
    }
    text = _json.dumps(out, indent=2)
    if args.json:
        Path(args.json).write_text(text + "\n")
    _out(text)
    return 0
