"""``scmr bench scale``: how the cloud tier's capacity grows with cloud nodes.

32 robots (``--robots``) against N = 1, 2, 4 (and 8 without ``--quick``)
cloud nodes sharing one PostgreSQL data store, each run a real fleet of
``scmr up`` (separate processes on loopback), then a crash run: 4 nodes, one
SIGKILLed in the middle and left down.

What is measured, and why it is the cloud tier's capacity
---------------------------------------------------------
The cloud nodes run :func:`scmr_mesh.mesh.testing.fixed_process`: a fixed
service time S (``--service-ms``, default 200 ms) spent sleeping, with no CPU
work, on W worker processes per node (``--workers``, default 2).  A node then
serves at most W/S requests per second whatever the host's cores do, so the
tier's capacity is N x W / S, and the question is how much of it the mesh
delivers as N grows: load spreading over nodes (robots pick the least loaded
node by its published load), the shared store, zenoh's routing.

The other limits are lifted on purpose:

* the robots' pacing: they send as fast as answers come (``--rate`` 1000 Hz,
  one request in flight per robot, the robot's design), so the offered
  concurrency is the robot count, 32, above the tier's N x W worker slots up
  to N = 16 with W = 2; each node always has work queued;
* admission: each node queues up to 64 requests (``--queue 64``, the
  priority negotiator) instead of answering ``busy`` past 8 x W in flight,
  so at N = 1 all 32 robots wait at the one node instead of being turned away
  to the leader;
* deadlines: 10 s per request (``--deadline-ms``), far above the worst queue
  wait (32 / W x S = 3.2 s at N = 1), so nothing expires;
* no local fallback, so a robot never answers itself.

served/s counts requests answered by the cloud tier and received in the
window from 2 s after the fleet is ready to 1 s before the robots stop.
efficiency(N) = served/s(N) / (N x served/s(1)).

What it does not show: the host has 2 cores, so the 32 robots, N nodes, the
leader and PostgreSQL share them; per-request CPU (zenoh, msgpack, the
telemetry queue's fsync, the store's commits) grows with served/s, and at
N = 8 (80 requests/s ideal) the cores, not the tier, can become the limit.
Nor does it show a real pipeline's CPU cost per frame, unless ``--pipeline``
is given: the nodes then run the real pipeline on the synthetic scenes (every
kind, dealt round-robin), and the ideal at N nodes is N x the one-node rate
measured in the same run (a host with fewer free cores than N x W workers plus
the robots' share cannot show the tier's efficiency: measure it on a large
host, docs/DEPLOY.md).  Nor a network between hosts (docs/DEPLOY.md,
docs/SCENARIOS.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from scmr_mesh.bench import usable_cores
from scmr_mesh.errors import InputError

#: Targets of issue 18.
SCALE_TARGETS = {"efficiency_at": 4, "efficiency_min": 0.85, "crash_ror": 1.0, "crash_telemetry_lost": 0}
FIXED = "scmr_mesh.mesh.testing:fixed_process"
WARMUP_S = 2.0
TAIL_S = 1.0


def _records(run_dir: Path) -> list[dict]:
    out = []
    for f in sorted((run_dir / "robots").glob("*/records.jsonl")):
        for line in f.read_text().splitlines():
            if line.strip():
                try:
                    out.append(json.loads(line))
                except ValueError:
                    pass
    return out


def served_in_window(report: dict, *, duration_s: float) -> dict[str, Any]:
    """Cloud-tier answers per second in the steady window of one fleet run, and how they spread."""
    t0 = report["started_unix_ns"] + int(WARMUP_S * 1e9)
    t1 = report["started_unix_ns"] + int((duration_s - TAIL_S) * 1e9)
    recs = [r for r in _records(Path(report["run_dir"]))
            if r.get("received_unix_ns") is not None and t0 <= r["received_unix_ns"] < t1]
    cloud = [r for r in recs if r.get("ok") and r.get("tier") == "cloud"]
    by_node: dict[str, int] = {}
    for r in cloud:
        by_node[r["served_by"]] = by_node.get(r["served_by"], 0) + 1
    window = (t1 - t0) / 1e9
    return {"served_per_s": round(len(cloud) / window, 2), "window_s": window, "served": len(cloud),
            "other": len(recs) - len(cloud), "by_node": dict(sorted(by_node.items()))}


def _loadavg() -> list[float]:
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return list(os.getloadavg())


def _config(args, clouds: int, run_dir: Path, duration_s: float):
    from scmr_mesh.fleet.plan import FleetConfig

    pipeline = getattr(args, "pipeline", False)
    return FleetConfig(
        robots=args.robots, clouds=clouds, ods_backend="postgresql", duration_s=duration_s, rate_hz=1000.0,
        # --pipeline: every synthetic scene kind through the real pipeline; else the sleeping stub
        synthetic=() if pipeline else ["stub"], run_dir=run_dir, workers=args.workers, lease_ms=None,
        server_args=("--queue", "64") if pipeline else ("--process", FIXED, "--queue", "64"),
        robot_args=("--no-local-fallback", "--deadline-ms", "10000", "--quiet"),
        ready_timeout_s=120.0, insecure=getattr(args, "insecure", False),
    )


def run_scale(args: argparse.Namespace) -> dict[str, Any]:
    """Run every fleet of the benchmark; return the result (see module docstring)."""
    from scmr_mesh.fleet.pgserver import available
    from scmr_mesh.fleet.output import run_with_output
    from scmr_mesh.fleet.run import default_run_dir

    why = available()
    if why:
        raise InputError(f"scmr bench scale runs the cloud nodes on a shared PostgreSQL store, but {why}")
    nodes = [1, 2, 4] if args.quick else [1, 2, 4, 8]
    duration = args.duration or (14.0 if args.quick else 30.0)
    if duration < WARMUP_S + TAIL_S + 2:
        raise InputError(f"--duration must be at least {WARMUP_S + TAIL_S + 2:g} s, got {duration:g}")
    root = args.run_dir or default_run_dir(Path("runs")).with_name(
        "bench-scale-" + time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()))
    pipeline = bool(getattr(args, "pipeline", False))
    service = "the real pipeline" if pipeline else f"service {args.service_ms:g} ms"
    old_delay = os.environ.get("SCMR_STUB_DELAY_MS")
    os.environ["SCMR_STUB_DELAY_MS"] = f"{args.service_ms:g}"  # the cloud nodes inherit it
    t_start = time.monotonic()
    runs: dict[str, dict] = {}
    try:
        for n in nodes:
            print(f"bench scale: {args.robots} robots, {n} cloud node(s) x {args.workers} workers, "
                  f"{service}, {duration:g} s ...", file=sys.stderr, flush=True)
            rep = run_with_output(_config(args, n, root / f"clouds-{n}", duration), quiet=True)
            w = served_in_window(rep, duration_s=duration)
            w.update({"ror": rep["ror"], "requests": rep["requests"], "loadavg": _loadavg(),
                      # with the real pipeline the ideal is n x the 1-node rate measured here
                      "ideal_per_s": (round(n * runs["1"]["served_per_s"], 2) if pipeline and "1" in runs
                                      else None if pipeline else round(n * args.workers * 1000.0 / args.service_ms, 2)),
                      "run_dir": rep["run_dir"]})
            runs[str(n)] = w
            ideal = "-" if w["ideal_per_s"] is None else f"{w['ideal_per_s']:g}"
            print(f"  {n} node(s): {w['served_per_s']:.1f} served/s (ideal {ideal}), by node "
                  f"{w['by_node']}, load {w['loadavg'][0]:.1f}", file=sys.stderr, flush=True)
        print(f"bench scale: crash run, 4 cloud nodes, cloud0 SIGKILLed at {duration / 2:g} s ...",
              file=sys.stderr, flush=True)
        cfg = _config(args, 4, root / "crash", duration)
        cfg.kill_cloud = (0, duration / 2)
        rep = run_with_output(cfg, quiet=True)
    finally:
        if old_delay is None:
            os.environ.pop("SCMR_STUB_DELAY_MS", None)
        else:
            os.environ["SCMR_STUB_DELAY_MS"] = old_delay
    tel = rep.get("telemetry") or {}
    crash = {
        "ror": rep["ror"], "requests": rep["requests"], "succeeded": rep["succeeded"], "by_tier": rep["by_tier"],
        "killed": rep["faults"][0]["target"] if rep["faults"] else None,
        "telemetry": {"sent": tel.get("sent"), "stored": tel.get("stored"), "lost": tel.get("lost"),
                      "duplicates": tel.get("duplicates")},
        "loadavg": _loadavg(), "run_dir": rep["run_dir"],
    }
    base = runs["1"]["served_per_s"]
    efficiency = {k: (round(v["served_per_s"] / (int(k) * base), 3) if base else None)
                  for k, v in runs.items() if k != "1"}
    at = str(SCALE_TARGETS["efficiency_at"])
    targets = {
        f"efficiency_{at}_ok": efficiency.get(at) is not None and efficiency[at] >= SCALE_TARGETS["efficiency_min"],
        "crash_ror_ok": crash["ror"] == SCALE_TARGETS["crash_ror"],
        "crash_telemetry_ok": crash["telemetry"]["lost"] == 0 and (crash["telemetry"]["sent"] or 0) > 0,
    }
    return {
        "ods_backend": "postgresql",
        "robots": args.robots, "workers_per_node": args.workers,
        "service": "pipeline" if pipeline else "fixed", "service_ms": None if pipeline else args.service_ms,
        "duration_s": duration, "window_s": [WARMUP_S, duration - TAIL_S], "quick": bool(args.quick),
        "served_per_s": {k: v["served_per_s"] for k, v in runs.items()},
        "efficiency": efficiency,
        "crash": crash,
        "runs": runs,
        "targets": targets,
        "machine": {"cpus": os.cpu_count(), "usable_cpus": usable_cores(), "loadavg_at_end": _loadavg()},
        "wall_s": round(time.monotonic() - t_start, 1),
        "measured_unix_ns": time.time_ns(),
    }


def cmd_bench_scale(args: argparse.Namespace) -> int:
    if args.robots < 1:
        raise InputError(f"--robots must be at least 1, got {args.robots}")
    if args.workers < 1:
        raise InputError(f"--workers must be at least 1, got {args.workers}")
    if not args.service_ms > 0:
        raise InputError(f"--service-ms must be positive, got {args.service_ms:g}")
    result = run_scale(args)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"{'nodes':>6}{'served/s':>10}{'ideal':>8}{'efficiency':>12}{'load 1m':>9}  by node")
    for k, r in result["runs"].items():
        eff = result["efficiency"].get(k)
        ideal = "-" if r["ideal_per_s"] is None else f"{r['ideal_per_s']:g}"
        print(f"{k:>6}{r['served_per_s']:>10.1f}{ideal:>8}{'-' if eff is None else f'{eff:.3f}':>12}"
              f"{r['loadavg'][0]:>9.1f}  {r['by_node']}")
    c = result["crash"]
    t = c["telemetry"]
    print(f"crash: {c['killed']} SIGKILLed mid-run; RoR {c['ror']} ({c['succeeded']}/{c['requests']}), "
          f"telemetry sent {t['sent']} stored {t['stored']} lost {t['lost']}")
    missed = [k for k, ok in result["targets"].items() if not ok]
    print(f"targets: {json.dumps(result['targets'])} ({result['wall_s']:g} s)")
    print(f"wrote {args.json}")
    if missed:
        print(f"scmr bench scale: target(s) missed: {', '.join(missed)}", file=sys.stderr)
        return 1
    return 0


__all__ = ["SCALE_TARGETS", "cmd_bench_scale", "run_scale", "served_in_window"]
