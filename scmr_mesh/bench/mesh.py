"""``scmr bench mesh``: ToR and RoR of fleets, a cloud-crash run and an overload run."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from scmr_mesh.bench.overload import run_overload
from scmr_mesh.errors import InputError
from scmr_mesh.fleet.commands import _config_from_args
from scmr_mesh.fleet.output import _ms, format_summary, run_with_output
from scmr_mesh.fleet.plan import parse_outage
from scmr_mesh.fleet.run import default_run_dir

MESH_TARGETS = {"tor_p50_ms": 15.0, "tor_p99_ms": 50.0, "crash_ror": 1.0,
                "failover_gap_ms": 50.0, "failback_gap_ms": 1000.0}


def bench_targets(runs: Sequence[Mapping[str, Any]], crash: Mapping[str, Any] | None) -> dict[str, Any]:
    """Compare bench results with the issue's targets (``None`` where not measured)."""
    out: dict[str, Any] = {"limits": dict(MESH_TARGETS)}
    four = next((r for r in runs if r["robots"] == 4 and abs(r["rate_hz"] - 5) < 1e-9), None)
    if four is not None:
        p50, p99 = four["tor_ms"]["p50"], four["tor_ms"]["p99"]
        out["tor_p50_4x5hz_ok"] = p50 is not None and p50 <= MESH_TARGETS["tor_p50_ms"]
        out["tor_p99_4x5hz_ok"] = p99 is not None and p99 <= MESH_TARGETS["tor_p99_ms"]
    else:
        out["tor_p50_4x5hz_ok"] = out["tor_p99_4x5hz_ok"] = None
    if crash is not None:
        fo = crash["failover_gaps_ms"]
        fb = crash["failback_gaps_ms"]
        out["crash_ror_ok"] = crash["ror"] == 1.0
        out["failover_ok"] = bool(fo) and all(g is not None and g <= MESH_TARGETS["failover_gap_ms"] for g in fo)
        out["failback_ok"] = bool(fb) and all(g is not None and g <= MESH_TARGETS["failback_gap_ms"] for g in fb)
    return out


def _run_entry(report: Mapping[str, Any]) -> dict[str, Any]:
    return {"robots": report["robots"], "rate_hz": report["rate_hz"], "duration_s": report["duration_s"],
            "requests": report["requests"], "succeeded": report["succeeded"], "ror": report["ror"],
            "tor_ms": report["tor_ms"], "by_tier": report["by_tier"], "run_dir": report["run_dir"]}


def cmd_bench_mesh(args: argparse.Namespace) -> int:
    try:
        sizes = [int(x) for x in args.robots.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--robots must be a comma-separated list of integers such as 1,4,16, "
                         f"got {args.robots!r}") from None
    if not sizes or min(sizes) < 1:
        raise InputError(f"--robots needs fleet sizes >= 1, got {args.robots!r}")
    root = args.run_dir or default_run_dir(Path("runs")).with_name(
        "bench-mesh-" + time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()))
    runs = []
    for n in sizes:
        print(f"bench mesh: {n} robots at {args.rate:g} Hz for {args.duration:g} s ...", file=sys.stderr)
        rep = run_with_output(_config_from_args(args, n, root / f"robots-{n}"))
        runs.append(_run_entry(rep))
        t = rep["tor_ms"]
        print(f"  {n} robots: {rep['requests']} requests, RoR {rep['ror']}, "
              f"ToR p50 {_ms(t['p50'])} p99 {_ms(t['p99'])} max {_ms(t['max'])} ms", file=sys.stderr)
    crash = None
    if args.crash_robots > 0:
        outage = parse_outage(args.crash_outage)
        print(f"bench mesh: crash run, {args.crash_robots} robots, cloud down {outage[0]:g}-{outage[1]:g} s ...",
              file=sys.stderr)
        cfg = _config_from_args(args, args.crash_robots, root / "crash")
        cfg.duration_s = args.crash_duration
        cfg.cloud_outage = outage
        rep = run_with_output(cfg)
        crash = {**_run_entry(rep), "failover_gaps_ms": rep["failover_gaps_ms"],
                 "failback_gaps_ms": rep["failback_gaps_ms"], "faults": rep["faults"]}
        print(format_summary(rep), file=sys.stderr)
    overload = None
    if args.overload_robots > 0:  # served/busy, ToR of admitted, fairness, peak RSS (security area)
        overload = {"runs": [
            run_overload(policy=pol, robots=args.overload_robots, rate_hz=args.overload_rate, duration_s=10.0,
                         run_dir=root / f"overload-{pol}", progress=lambda m: print(m, file=sys.stderr))
            for pol in ("negotiator", "fifo")
        ]}
    result = {
        "runs": runs,
        "crash": crash,
        "overload": overload,
        "targets": bench_targets(runs, crash),
        "machine": {"cpus": os.cpu_count(), "loadavg_at_end": list(os.getloadavg())},
        "measured_unix_ns": time.time_ns(),
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"{'robots':>7}{'rate':>6}{'requests':>10}{'RoR':>7}{'p50':>8}{'p90':>8}{'p99':>8}{'max':>8}  (ms)")
    for r in runs:
        t = r["tor_ms"]
        ror = "-" if r["ror"] is None else f"{r['ror']:.3f}"
        print(f"{r['robots']:>7}{r['rate_hz']:>6g}{r['requests']:>10}{ror:>7}{_ms(t['p50']):>8}"
              f"{_ms(t['p90']):>8}{_ms(t['p99']):>8}{_ms(t['max']):>8}")
    if crash is not None:
        print(f"crash run: RoR {crash['ror']}, failover gaps {crash['failover_gaps_ms']} ms, "
              f"failback gaps {crash['failback_gaps_ms']} ms")
    for r in (overload or {}).get("runs", []):
        print(f"overload {r['policy']}: {r['requests']} requests, {r['served']} served, {r['rejected']} busy; "
              f"ToR admitted p50 {r['tor_admitted_ms']['p50']} p99 {r['tor_admitted_ms']['p99']} ms; "
              f"Jain {r['jain_all']}; cloud peak RSS {r['cloud_peak_rss_mb']['sum_sampled']} MB")
    print(f"targets: {json.dumps({k: v for k, v in result['targets'].items() if k != 'limits'})}")
    print(f"wrote {args.json}")
    return 0


