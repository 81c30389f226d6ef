"""``scmr bench mesh``: ToR and RoR of fleets, the service's capacity, repeated
cloud crashes (quiet and under CPU hogs) and an overload run."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from scmr_mesh.bench import usable_cores
from scmr_mesh.bench.overload import run_overload
from scmr_mesh.errors import InputError
from scmr_mesh.fleet.commands import _config_from_args
from scmr_mesh.fleet.output import _ms, run_with_output
from scmr_mesh.fleet.plan import parse_outage
from scmr_mesh.fleet.run import default_run_dir
from scmr_mesh.thesis.cpu import CpuSampler

#: Issue 14's targets: failover median and failback max over the crash runs, and
#: both (max) under two CPU hogs; the ToR targets of the 4-robot fleet.
MESH_TARGETS = {"tor_p50_ms": 15.0, "tor_p99_ms": 50.0, "crash_ror": 1.0,
                "failover_gap_median_ms": 20.0, "failback_gap_max_ms": 500.0,
                "hogs_failover_gap_max_ms": 1000.0, "hogs_failback_gap_max_ms": 1000.0,
                "tor_admitted_p99_ms": 100.0, "hedge_rate_fault_free": 0.02,
                # issue 23 item 2: served frames/s before the first busy answer, over the workers' capacity
                "served_at_first_busy_ratio": 0.85}


#: ``scmr bench mesh`` plays fleets above this many robots this many to a ``scmr swarm`` process
#: (``--robots-per-process`` overrides): 64 robot interpreters on a 2-core box left the cloud no CPU.
SWARM_ABOVE = 16


def _stat(values: Sequence[float | None]) -> dict[str, Any]:
    """Median and max of the measured values (``missing`` counts the None ones)."""
    vals = [float(v) for v in values if v is not None]
    return {"median": round(statistics.median(vals), 1) if vals else None,
            "max": round(max(vals), 1) if vals else None, "n": len(vals), "missing": len(values) - len(vals)}


def bench_targets(runs: Sequence[Mapping[str, Any]], crash: Mapping[str, Any] | None,
                  hogs: Mapping[str, Any] | None = None, ingress: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Compare bench results with the targets (``None`` where not measured)."""
    out: dict[str, Any] = {"limits": dict(MESH_TARGETS)}
    ratio = (ingress or {}).get("served_at_first_busy_ratio")
    out["served_at_first_busy_ok"] = None if ratio is None else ratio >= MESH_TARGETS["served_at_first_busy_ratio"]
    four = next((r for r in runs if r["robots"] == 4 and abs(r["rate_hz"] - 5) < 1e-9), None)
    if four is not None:
        p50, p99 = four["tor_ms"]["p50"], four["tor_ms"]["p99"]
        out["tor_p50_4x5hz_ok"] = p50 is not None and p50 <= MESH_TARGETS["tor_p50_ms"]
        out["tor_p99_4x5hz_ok"] = p99 is not None and p99 <= MESH_TARGETS["tor_p99_ms"]
    else:
        out["tor_p50_4x5hz_ok"] = out["tor_p99_4x5hz_ok"] = None
    admitted = [r["tor_admitted_ms"]["p99"] for r in runs if r.get("tor_admitted_ms", {}).get("p99") is not None]
    out["tor_admitted_p99_ok"] = (all(v <= MESH_TARGETS["tor_admitted_p99_ms"] for v in admitted)
                                  if admitted else None)
    rates = [r["hedge_rate"] for r in runs if r.get("hedge_rate") is not None]
    out["hedge_rate_ok"] = all(v <= MESH_TARGETS["hedge_rate_fault_free"] for v in rates) if rates else None
    if crash is not None:
        fo, fb = crash["failover_gap_ms"], crash["failback_gap_ms"]
        out["crash_ror_ok"] = crash["ror_min"] == 1.0
        out["failover_ok"] = (not fo["missing"] and fo["median"] is not None
                              and fo["median"] <= MESH_TARGETS["failover_gap_median_ms"])
        out["failback_ok"] = (not fb["missing"] and fb["max"] is not None
                              and fb["max"] <= MESH_TARGETS["failback_gap_max_ms"])
    if hogs is not None:
        fo, fb = hogs["failover_gap_ms"], hogs["failback_gap_ms"]
        out["hogs_ror_ok"] = hogs["ror_min"] == 1.0
        out["hogs_failover_ok"] = (not fo["missing"] and fo["max"] is not None
                                   and fo["max"] <= MESH_TARGETS["hogs_failover_gap_max_ms"])
        out["hogs_failback_ok"] = (not fb["missing"] and fb["max"] is not None
                                   and fb["max"] <= MESH_TARGETS["hogs_failback_gap_max_ms"])
    return out


def _records(run_dir: Path) -> list[dict]:
    out = []
    for f in sorted(Path(run_dir).glob("robots/*/records.jsonl")):
        for line in f.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                continue
    return out


def admitted_tor(run_dir: Path) -> dict[str, Any]:
    """ToR of the requests a service admitted (answered by cloud or leader), and the busy answers seen."""
    from scmr_mesh.qos import metrics

    recs = _records(run_dir)
    served = [r for r in recs if r.get("ok") and r.get("tier") in ("cloud", "leader")]
    busy = sum(1 for r in recs for a in r.get("attempts", []) if a.get("outcome") == "error:busy")
    tor = [float(r["tor_ms"]) for r in served if r.get("tor_ms") is not None]
    return {"n": len(tor), "p50": round(metrics.percentile(tor, 50), 1) if tor else None,
            "p99": round(metrics.percentile(tor, 99), 1) if tor else None, "busy_answers": busy}


def hedges(run_dir: Path) -> dict[str, Any]:
    """Requests hedged to a second tier and their share of the run's requests (issue 24)."""
    recs = _records(run_dir)
    hedged = sum(1 for r in recs if r.get("hedged"))
    return {"hedged": hedged, "hedge_won": sum(1 for r in recs if r.get("hedge_won")),
            "hedge_rate": round(hedged / len(recs), 4) if recs else None}


def _run_entry(report: Mapping[str, Any]) -> dict[str, Any]:
    return {"robots": report["robots"], "rate_hz": report["rate_hz"], "duration_s": report["duration_s"],
            "requests": report["requests"], "succeeded": report["succeeded"], "ror": report["ror"],
            "tor_ms": report["tor_ms"], "by_tier": report["by_tier"], "run_dir": report["run_dir"],
            "tor_admitted_ms": admitted_tor(Path(report["run_dir"])),
            # fault-free runs: hedges stay under MESH_TARGETS["hedge_rate_fault_free"]
            **hedges(Path(report["run_dir"])),
            # the network's shape and what it costs per robot (peak RSS, CPU, open sockets)
            "shape": (report.get("hosts") or {}).get("shape"), "hosts": report.get("hosts"),
            "telemetry_lost": (report.get("telemetry") or {}).get("lost")}


# ------------------------------------------------------------------ CPU per request
#: Roles of a fleet's peers, by the name of their ready file (``RUN/ready/<peer>.ready``).
CPU_ROLES = ("cloud", "leader", "router", "robots")


def _role(peer: str) -> str:
    for role in CPU_ROLES[:-1]:
        if peer.startswith(role):
            return role
    return "robots"  # robot processes and swarms (a swarm's members share its process group)


def cpu_per_request(cpu: Mapping[str, Any], t0_ns: int, t1_ns: int, requests: int,
                    cores: int | None = None) -> dict[str, Any]:
    """Where a fleet's CPU went, by role, per request sent in ``[t0_ns, t1_ns]`` (pure; issue 23 item 2).

    ``cpu`` is :meth:`scmr_mesh.thesis.cpu.CpuSampler.to_json`: one CPU series per
    peer, each the CPU seconds of the peer's process group (the peer and its
    worker processes).  Peers that share a process group (the members of a
    ``scmr swarm``) are counted once.  A series that does not cover the whole
    window is counted over the part it covers (a peer started late or stopped
    early).

    Examples
    --------
    >>> cpu = {"pgids": {"cloud0": 10, "r1": 20, "r2": 20},
    ...        "series": {"cloud0": [[0, 0.0], [10, 2.0]], "r1": [[0, 0.0], [10, 4.0]],
    ...                   "r2": [[0, 0.0], [10, 4.0]]}}
    >>> out = cpu_per_request(cpu, 0, 10, 1000, cores=2)
    >>> out["cpu_s"], out["ms_per_request"]
    ({'cloud': 2.0, 'leader': 0.0, 'router': 0.0, 'robots': 4.0, 'total': 6.0}, {'cloud': 2.0, 'leader': 0.0, 'router': 0.0, 'robots': 4.0, 'total': 6.0})
    """
    from scmr_mesh.thesis.cpu import cpu_between

    seen: set = set()
    cpu_s = dict.fromkeys(CPU_ROLES, 0.0)
    series = cpu.get("series", {})
    pgids = cpu.get("pgids", {})
    for peer in sorted(series):
        g = pgids.get(peer, peer)
        if g in seen:
            continue
        seen.add(g)
        s = series[peer]
        if not s:
            continue
        a, b = max(t0_ns, s[0][0]), min(t1_ns, s[-1][0])
        used = cpu_between(s, a, b) if b > a else None
        cpu_s[_role(peer)] += used or 0.0
    cpu_s["total"] = sum(cpu_s.values())
    window_s = max(0.0, (t1_ns - t0_ns) / 1e9)
    return {
        "window_s": round(window_s, 3), "requests": requests,
        "cpu_s": {k: round(v, 3) for k, v in cpu_s.items()},
        "ms_per_request": {k: (round(v * 1e3 / requests, 3) if requests else None) for k, v in cpu_s.items()},
        # the share of the host's cores the fleet used: near 1.0 the cores, not the mesh, are the limit
        "host_share": (round(cpu_s["total"] / (window_s * cores), 3) if cores and window_s > 0 else None),
    }


# ------------------------------------------------------------------ capacity
def _tree_cpu_s(pid: int) -> float:
    """CPU seconds of ``pid`` and its children (a service and its workers)."""
    from scmr_mesh.mesh.startup import process_cpu_ms

    pids = [pid]
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            pids += [int(x) for x in (task / "children").read_text().split()]
    except OSError:
        pass
    return sum((process_cpu_ms(p) or 0.0) for p in pids) / 1e3


def measure_capacity(*, workers: int | None, seconds: float, run_dir: Path, concurrency: int | None = None,
                     progress=None, insecure: bool = False) -> dict[str, Any]:
    """Saturate one ``scmr cloud`` (real pipeline) with a closed loop of requests.

    ``concurrency`` senders (default 2 x workers) each send the next frame (the
    robots' synthetic scenes, as robots encode them) as soon as the last one is
    answered, for ``seconds``.  The service's CPU time (main process and
    workers, from ``/proc``) over the same interval gives its capacity per
    core: frames served per CPU-second, i.e. what one fully used core serves.
    """
    import zenoh  # noqa: F401  (bench layer: the client side)

    from scmr_mesh import wire
    from scmr_mesh.ports import free_ports as _free_ports
    from scmr_mesh.imaging.synthetic import SCENE_KINDS
    from scmr_mesh.mesh.robot import frames_from_args
    from scmr_mesh.qos import metrics

    workers = int(workers or usable_cores())
    concurrency = int(concurrency or 2 * workers)
    run_dir.mkdir(parents=True, exist_ok=True)
    port = _free_ports(["cap"])["cap"]
    frames = []
    for i, kind in enumerate(SCENE_KINDS):
        it = frames_from_args(None, kind, seed=i)
        frames += [next(it) for _ in range(4)]
    from scmr_mesh.bench.secure import bench_cloud

    counts = {"ok": 0, "busy": 0, "other": 0}
    server_ms: list[float] = []
    lock = threading.Lock()
    with bench_cloud(run_dir, "cap0", "cap", port=port, insecure=insecure, what="capacity",
                     args=["--workers", str(workers)]) as (proc, _session, q):
        state = {"measure": False, "stop": False}

        def sender(k: int) -> None:
            n = k
            while not state["stop"]:
                f = frames[n % len(frames)]
                n += concurrency
                req = wire.make_request("cap", n, f.data, encoding=f.encoding, shape=f.shape)
                outcome, sms = "other", None
                for r in q.get(payload=wire.encode(req)):
                    if r.ok is not None:
                        outcome = "ok"
                        sms = wire.decode(r.ok.payload.to_bytes(), kind="reply")["server_ms"]
                    else:
                        err = wire.decode(r.err.payload.to_bytes(), kind="error")
                        outcome = "busy" if err["code"] == "busy" else "other"
                if state["measure"]:
                    with lock:
                        counts[outcome] += 1
                        if sms is not None:
                            server_ms.append(sms)

        threads = [threading.Thread(target=sender, args=(k,), daemon=True) for k in range(concurrency)]
        for t in threads:
            t.start()
        time.sleep(min(2.0, seconds / 4))  # warm: every worker busy, averages settled
        cpu0, t0 = _tree_cpu_s(proc.pid), time.monotonic()
        state["measure"] = True
        if progress:
            progress(f"capacity: {concurrency} senders, {workers} workers, {seconds:g} s ...")
        time.sleep(seconds)
        state["measure"] = False
        cpu1, t1 = _tree_cpu_s(proc.pid), time.monotonic()
        state["stop"] = True
        for t in threads:
            t.join(timeout=15)
    wall, cpu = t1 - t0, cpu1 - cpu0
    return {
        "workers": workers, "cores": usable_cores(), "concurrency": concurrency, "seconds": round(wall, 2),
        "served": counts["ok"], "busy": counts["busy"], "other_errors": counts["other"],
        "frames_per_s": round(counts["ok"] / wall, 1),
        "service_cpu_s": round(cpu, 2),
        "frames_per_s_per_core": round(counts["ok"] / cpu, 1) if cpu > 0 else None,
        "server_ms": {"p50": round(metrics.percentile(server_ms, 50), 1) if server_ms else None,
                      "p99": round(metrics.percentile(server_ms, 99), 1) if server_ms else None},
        "loadavg_at_end": list(os.getloadavg()),
    }


# ------------------------------------------------------------ crash series
class CpuHogs:
    """``n`` busy CPU processes (``stress-ng --cpu n``, else Python spin loops) while in use."""

    def __init__(self, n: int) -> None:
        self.n = int(n)
        self.procs: list[subprocess.Popen] = []
        self.tool = "stress-ng" if shutil.which("stress-ng") else "python spin loop"

    def __enter__(self) -> "CpuHogs":
        if self.n <= 0:
            return self
        if self.tool == "stress-ng":
            cmds = [["stress-ng", "--cpu", str(self.n), "--quiet"]]
        else:
            cmds = [[sys.executable, "-c", "while True: pass"] for _ in range(self.n)]
        for c in cmds:
            self.procs.append(subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                               start_new_session=True))
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(timeout=10)
        self.procs = []


def crash_series(args: argparse.Namespace, root: Path, *, runs: int, label: str) -> dict[str, Any]:
    """``runs`` fleet runs of ``--crash-robots`` with the cloud SIGKILLed and restarted in each."""
    outage = parse_outage(args.crash_outage)
    per_run = []
    for i in range(runs):
        cfg = _config_from_args(args, args.crash_robots, root / f"{label}-{i + 1:02d}")
        cfg.duration_s = args.crash_duration
        cfg.cloud_outage = outage
        load = os.getloadavg()[0]
        rep = run_with_output(cfg, quiet=True)
        f = (rep.get("faults") or [{}])[0]
        entry = {"run": i + 1, "ror": rep["ror"], "requests": rep["requests"],
                 "failover_gap_ms": f.get("failover_gap_ms"), "failback_gap_ms": f.get("failback_gap_ms"),
                 "restart_to_ready_ms": f.get("restart_to_ready_ms"),
                 "failback_after_ready_ms": f.get("failback_after_ready_ms"),
                 "loadavg_1min_at_start": round(load, 2), "loadavg_1min_at_end": round(os.getloadavg()[0], 2),
                 "run_dir": rep["run_dir"]}
        per_run.append(entry)
        print(f"  {label} {i + 1}/{runs}: RoR {rep['ror']}, failover {_ms(entry['failover_gap_ms'])} ms, "
              f"failback {_ms(entry['failback_gap_ms'])} ms (restart->ready {_ms(entry['restart_to_ready_ms'])} "
              f"+ ready->answer {_ms(entry['failback_after_ready_ms'])}), load {load:.2f}", file=sys.stderr)
    return {
        "runs": per_run,
        "robots": args.crash_robots, "outage_s": list(outage), "duration_s": args.crash_duration,
        "ror_min": min((r["ror"] for r in per_run if r["ror"] is not None), default=None),
        "failover_gap_ms": _stat([r["failover_gap_ms"] for r in per_run]),
        "failback_gap_ms": _stat([r["failback_gap_ms"] for r in per_run]),
        "restart_to_ready_ms": _stat([r["restart_to_ready_ms"] for r in per_run]),
        "failback_after_ready_ms": _stat([r["failback_after_ready_ms"] for r in per_run]),
    }


def cmd_bench_mesh(args: argparse.Namespace) -> int:
    try:
        sizes = [int(x) for x in args.robots.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--robots must be a comma-separated list of integers such as 1,4,16, "
                         f"got {args.robots!r}") from None
    if min(sizes, default=1) < 1:
        raise InputError(f"--robots needs fleet sizes >= 1, got {args.robots!r}")
    for flag in ("crash_runs", "hogs"):
        if getattr(args, flag) < 0:
            raise InputError(f"--{flag.replace('_', '-')} must be >= 0, got {getattr(args, flag)}")
    if args.capacity_seconds < 0:
        raise InputError(f"--capacity-seconds must be >= 0, got {args.capacity_seconds}")
    parse_outage(args.crash_outage)
    root = args.run_dir or default_run_dir(Path("runs")).with_name(
        "bench-mesh-" + time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()))
    say = lambda m: print(m, file=sys.stderr)  # noqa: E731
    capacity = None
    if args.capacity_seconds > 0:
        say(f"bench mesh: service capacity ({args.capacity_seconds:g} s, real pipeline) ...")
        capacity = measure_capacity(workers=args.workers, seconds=args.capacity_seconds, run_dir=root / "capacity",
                                    progress=say, insecure=args.insecure)
        say(f"  capacity: {capacity['frames_per_s_per_core']} frames/s per core ({capacity['frames_per_s']} frames/s "
            f"with {capacity['workers']} workers, {capacity['service_cpu_s']} CPU-s in {capacity['seconds']} s)")
    ingress = None
    if args.ingress_seconds > 0:
        from scmr_mesh.bench.ingress import measure_ingress

        say(f"bench mesh: the cloud's ingress ({args.ingress_workers} workers on a {args.ingress_service_ms:g} ms "
            f"fixed-time stub: closed loop, then a ramp of {args.ingress_seconds:g} s steps) ...")
        ingress = measure_ingress(workers=args.ingress_workers, delay_ms=args.ingress_service_ms,
                                  step_s=args.ingress_seconds, run_dir=root / "ingress", insecure=args.insecure,
                                  progress=say)
    runs = []
    for n in sizes:
        say(f"bench mesh: {n} robots at {args.rate:g} Hz for {args.duration:g} s ...")
        cfg = _config_from_args(args, n, root / f"robots-{n}")
        if getattr(args, "robots_per_process", None) is None and n > SWARM_ABOVE:
            # the load generator: a process per robot left a 2-core box's cloud no CPU (issue 23)
            cfg = dataclasses.replace(cfg, robots_per_process=SWARM_ABOVE)
        with CpuSampler(cfg.run_dir / "ready") as sampler:
            rep = run_with_output(cfg)
        t0 = int(rep["t0_unix_ns"])
        cores = usable_cores()
        cpu = cpu_per_request(sampler.to_json(), t0, t0 + int(rep["duration_s"] * 1e9), rep["requests"], cores)
        runs.append(dict(_run_entry(rep), robots_per_process=cfg.robots_per_process, cpu=cpu))
        t, a = rep["tor_ms"], runs[-1]["tor_admitted_ms"]
        say(f"  {n} robots: {rep['requests']} requests, RoR {rep['ror']}, ToR p50 {_ms(t['p50'])} "
            f"p99 {_ms(t['p99'])} max {_ms(t['max'])} ms; admitted by cloud/leader p99 {_ms(a['p99'])} ms, "
            f"{a['busy_answers']} busy answers; hedged {runs[-1]['hedged']} ({runs[-1]['hedge_rate']})")
        m = cpu["ms_per_request"]
        say("  CPU ms per request: " + ", ".join(f"{k} {m[k]}" for k in (*CPU_ROLES, "total"))
            + f"; the fleet used {cpu['host_share']} of the {cores} cores it may run on")
    crash = hogs = None
    if args.crash_robots > 0 and args.crash_runs > 0:
        say(f"bench mesh: {args.crash_runs} crash runs, {args.crash_robots} robots, cloud down "
            f"{args.crash_outage} s ...")
        crash = crash_series(args, root, runs=args.crash_runs, label="crash")
        if args.hogs > 0:
            with CpuHogs(args.hogs) as h:
                say(f"bench mesh: {args.crash_runs} crash runs under {args.hogs} CPU hogs ({h.tool}) ...")
                hogs = crash_series(args, root, runs=args.crash_runs, label=f"crash-hogs{args.hogs}")
                hogs["hogs"] = {"n": args.hogs, "tool": h.tool}
    overload = None
    if args.overload_robots > 0:  # served/busy, ToR of admitted, fairness, peak RSS (security area)
        overload = {"runs": [
            run_overload(policy=pol, robots=args.overload_robots, rate_hz=args.overload_rate, duration_s=10.0,
                         run_dir=root / f"overload-{pol}", progress=say, insecure=args.insecure)
            for pol in ("negotiator", "fifo")
        ]}
    result = {
        "capacity": capacity,
        "ingress": ingress,
        "runs": runs,
        "crash": crash,
        "crash_hogs": hogs,
        "overload": overload,
        "targets": bench_targets(runs, crash, hogs, ingress),
        "machine": {"cpus": os.cpu_count(), "usable_cpus": usable_cores(), "loadavg_at_end": list(os.getloadavg())},
        "measured_unix_ns": time.time_ns(),
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    if capacity is not None:
        print(f"service capacity: {capacity['frames_per_s_per_core']} frames/s per core "
              f"({capacity['frames_per_s']} frames/s, {capacity['workers']} workers on {capacity['cores']} cores; "
              f"server time p50 {capacity['server_ms']['p50']} p99 {capacity['server_ms']['p99']} ms)")
    if ingress is not None:
        first = (f"first busy at {ingress['first_busy_offered_fps']} frames/s offered (the client up to "
                 f"{ingress['first_busy_sender_late_ms']} ms late in that step)"
                 if ingress["first_busy_offered_fps"] is not None else "no busy answer on the ramp")
        print(f"cloud ingress: workers' closed-loop capacity {ingress['capacity_fps']} frames/s "
              f"({ingress['workers']} workers x {ingress['delay_ms'] or '-'} ms stub); served "
              f"{ingress['served_before_busy_fps']} frames/s before any busy answer: "
              f"served_at_first_busy_ratio {ingress['served_at_first_busy_ratio']} (target >= "
              f"{MESH_TARGETS['served_at_first_busy_ratio']}); {first}")
    print(f"{'robots':>7}{'rate':>6}{'requests':>10}{'RoR':>7}{'p50':>8}{'p90':>8}{'p99':>8}{'max':>8}"
          f"{'adm p99':>9}{'busy':>6}  (ms)")
    for r in runs:
        t, a = r["tor_ms"], r["tor_admitted_ms"]
        ror = "-" if r["ror"] is None else f"{r['ror']:.3f}"
        print(f"{r['robots']:>7}{r['rate_hz']:>6g}{r['requests']:>10}{ror:>7}{_ms(t['p50']):>8}"
              f"{_ms(t['p90']):>8}{_ms(t['p99']):>8}{_ms(t['max']):>8}{_ms(a['p99']):>9}{a['busy_answers']:>6}")
    for name, c in (("crash runs", crash), ("crash runs under CPU hogs", hogs)):
        if c is not None:
            fo, fb, rr, ar = (c["failover_gap_ms"], c["failback_gap_ms"], c["restart_to_ready_ms"],
                              c["failback_after_ready_ms"])
            print(f"{name} ({len(c['runs'])}): RoR min {c['ror_min']}; failover median {fo['median']} max {fo['max']} "
                  f"ms; failback median {fb['median']} max {fb['max']} ms (restart->ready median {rr['median']} "
                  f"max {rr['max']}, ready->first answer median {ar['median']} max {ar['max']})"
                  + (f"; missing {fo['missing']} failover / {fb['missing']} failback" if fo["missing"] or fb["missing"]
                     else ""))
    for r in (overload or {}).get("runs", []):
        print(f"overload {r['policy']}: {r['requests']} requests, {r['served']} served, {r['rejected']} busy; "
              f"ToR admitted p50 {r['tor_admitted_ms']['p50']} p99 {r['tor_admitted_ms']['p99']} ms; "
              f"Jain {r['jain_all']}; cloud peak RSS {r['cloud_peak_rss_mb']['sum_sampled']} MB")
    print(f"targets: {json.dumps({k: v for k, v in result['targets'].items() if k != 'limits'})}")
    print(f"wrote {args.json}")
    return 0


__all__ = ["CpuHogs", "MESH_TARGETS", "cpu_per_request", "admitted_tor", "bench_targets", "cmd_bench_mesh", "crash_series",
           "measure_capacity"]

