"""``scmr bench overload``: drive a cloud beyond what it can serve and measure admission.

One run = one cloud process (``scmr cloud``) and N robot processes (``scmr robot``) on
loopback, all sending frames at ``--rate`` Hz for ``--duration`` s.  By default the
service is the mesh's ``slow_process`` stub (a fixed ``--service-ms`` per frame), so the
cloud's capacity is known (``workers * 1000 / service_ms`` frames/s) and the machine's
two cores stay free for the measurement; ``--service-ms 0`` runs the real pipeline.
Robots run with ``--no-local-fallback`` and no leader, so a refused request fails at
once and the robot goes on with its next frame (with a leader or local execution it
would fall back there, which tests/test_security_overload.py checks).

Each policy is run on the same load:

* ``negotiator``: ``scmr cloud --queue Q`` (priority ranking, bounded queue, explicit busy);
* ``fifo``: the service's default admission (FIFO, ``busy`` only beyond 8 x workers in flight).

Reported per run: requests, served, rejected (busy), other failures, ToR of admitted
requests (p50/p99/max; each robot's first request is left out of the ToR figures: it pays
the robot process's warm-up, about 0.3-0.6 s here), time to a busy answer (p50/p99), served share per priority class,
Jain's fairness index of served requests across robots (overall and within each priority
class: robots that pay the same should be served alike), and the peak RSS of the cloud
process and of its workers (``VmHWM``) plus the peak of their summed RSS sampled every
0.2 s.

This module starts processes; it imports no Zenoh.
"""

from __future__ import annotations

import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

from scmr_mesh.errors import InputError, MeshError

log = logging.getLogger(__name__)


def _pct(xs: Sequence[float], q: float) -> float | None:
    if not xs:
        return None
    s = sorted(xs)
    k = min(len(s) - 1, max(0, int(round(q / 100.0 * (len(s) - 1)))))
    return round(float(s[k]), 3)


def _children(pid: int) -> list[int]:
    out: list[int] = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            txt = (task / "children").read_text().split()
            out.extend(int(x) for x in txt)
    except OSError:
        pass
    return out


def _status_kb(pid: int, field: str) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


class _RssSampler:
    """Samples the summed RSS of a process and its children in a thread."""

    def __init__(self, pid: int, period: float = 0.2) -> None:
        import threading

        self.pid = pid
        self.period = period
        self.peak_sum_kb = 0
        self.hwm_kb: dict[int, int] = {}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, name="rss-sampler", daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self.sample()

    def sample(self) -> None:
        pids = [self.pid, *_children(self.pid)]
        self.peak_sum_kb = max(self.peak_sum_kb, sum(_status_kb(p, "VmRSS") for p in pids))
        for p in pids:
            hwm = _status_kb(p, "VmHWM")
            if hwm:
                self.hwm_kb[p] = max(self.hwm_kb.get(p, 0), hwm)

    def stop(self) -> None:
        self.sample()
        self._stop.set()
        self._t.join(timeout=1.0)


def summarize(records_by_robot: dict[str, list[dict]], priorities: dict[str, int]) -> dict[str, Any]:
    """Served/rejected counts, ToR of admitted requests, fairness, per-priority shares.

    Parameters
    ----------
    records_by_robot : dict
        Robot id -> its ``records.jsonl`` records.
    priorities : dict
        Robot id -> the priority it sent.

    Returns
    -------
    dict
        See the module docstring.
    """
    from scmr_mesh.qos.negotiator import jain_index

    served_tor: list[float] = []
    busy_tor: list[float] = []
    per_robot: dict[str, dict[str, int]] = {}
    failures: dict[str, int] = {}
    for robot, recs in sorted(records_by_robot.items()):
        c = per_robot.setdefault(robot, {"requests": 0, "served": 0, "rejected": 0, "failed": 0})
        for i, r in enumerate(recs):
            c["requests"] += 1
            outcomes = [a.get("outcome") for a in r.get("attempts", [])]
            if r.get("ok"):
                c["served"] += 1
                if i > 0:  # a robot's first request pays its process's warm-up
                    served_tor.append(float(r["tor_ms"]))
            elif "error:busy" in outcomes:
                c["rejected"] += 1
                busy_tor.append(float(r["tor_ms"]))
            else:
                c["failed"] += 1
                for o in outcomes or ["no_attempt"]:
                    failures[str(o)] = failures.get(str(o), 0) + 1
    by_prio: dict[int, dict[str, Any]] = {}
    for robot, c in per_robot.items():
        p = priorities.get(robot, 0)
        b = by_prio.setdefault(p, {"robots": 0, "requests": 0, "served": 0, "rejected": 0, "served_per_robot": []})
        b["robots"] += 1
        b["requests"] += c["requests"]
        b["served"] += c["served"]
        b["rejected"] += c["rejected"]
        b["served_per_robot"].append(c["served"])
    total = {k: sum(c[k] for c in per_robot.values()) for k in ("requests", "served", "rejected", "failed")}
    return {
        **total,
        "tor_admitted_ms": {"p50": _pct(served_tor, 50), "p99": _pct(served_tor, 99),
                            "max": round(max(served_tor), 3) if served_tor else None},
        "time_to_busy_ms": {"p50": _pct(busy_tor, 50), "p99": _pct(busy_tor, 99)},
        "jain_all": round(jain_index([c["served"] for c in per_robot.values()]), 4),
        "by_priority": {
            str(p): {
                **{k: v for k, v in b.items() if k != "served_per_robot"},
                "served_share": round(b["served"] / b["requests"], 4) if b["requests"] else None,
                "jain": round(jain_index(b["served_per_robot"]), 4),
            }
            for p, b in sorted(by_prio.items())
        },
        "per_robot": per_robot,
        "failures": failures,
    }


def run_overload(
    *,
    policy: str,
    robots: int = 8,
    rate_hz: float = 10.0,
    duration_s: float = 10.0,
    workers: int = 1,
    service_ms: float = 40.0,
    queue: int = 2,
    per_robot: int | None = None,
    levels: int = 2,
    run_dir: Path,
    progress=None,
    insecure: bool = False,
) -> dict[str, Any]:
    """One overload run (see the module docstring); returns its summary.

    Raises
    ------
    InputError
        Bad parameters.
    MeshError
        A peer failed to start.
    """
    from scmr_mesh.ports import free_port

    from scmr_mesh.mesh.testing import (
        SLOW,
        read_records,
        spawn_peer,
        stop_peer,
        wait_for,
    )

    if policy not in ("negotiator", "fifo"):
        raise InputError(f"policy must be 'negotiator' or 'fifo', got {policy!r}")
    for name, v, lo in (("--robots", robots, 1), ("--workers", workers, 1), ("--levels", levels, 1)):
        if v < lo:
            raise InputError(f"{name} must be >= {lo}, got {v}")
    if rate_hz <= 0 or duration_s <= 0 or service_ms < 0 or queue < 0:
        raise InputError(
            f"--rate, --duration must be > 0 and --service-ms, --queue >= 0; got rate {rate_hz}, "
            f"duration {duration_s}, service-ms {service_ms}, queue {queue}"
        )
    say = progress or (lambda m: None)
    run_dir.mkdir(parents=True, exist_ok=True)
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    ready = run_dir / "cloud.ready"
    priorities = {f"ovl{k}": 10 * (k % levels) for k in range(robots)}
    from scmr_mesh.bench.secure import bench_security

    # the fleet's policy grants each robot the priority it asks (a request asking more is capped)
    sec = bench_security(run_dir, ",".join(["ovl=cloud", *priorities]), insecure=insecure, priority=priorities)
    cloud_args = ["cloud", *sec.args, "--node", "ovl", "--listen", ep, "--workers", str(workers),
                  "--ready-file", str(ready), "--ods", str(run_dir / "ods.sqlite")]
    env = {}
    if service_ms > 0:
        cloud_args += ["--process", SLOW]
        env["SCMR_STUB_DELAY_MS"] = str(service_ms)
    if policy == "negotiator":
        cloud_args += ["--queue", str(queue)]
        if per_robot is not None:
            cloud_args += ["--per-robot", str(per_robot)]
    say(f"[{policy}] starting the cloud ({workers} worker(s), "
        f"{'pipeline' if service_ms == 0 else f'{service_ms:g} ms stub'})")
    cloud = spawn_peer(cloud_args, log_path=run_dir / "cloud.log", env=env)
    procs = []
    sampler = None
    try:
        try:
            wait_for(lambda: ready.exists() or cloud.poll() is not None, timeout=120, what="cloud ready")
        except TimeoutError as exc:
            raise MeshError(f"{exc}; see {run_dir / 'cloud.log'}") from None
        if cloud.poll() is not None:
            tail = (run_dir / "cloud.log").read_text(errors="replace")[-800:]
            raise MeshError(f"the cloud exited with status {cloud.returncode}: {tail}")
        sampler = _RssSampler(cloud.pid)
        say(f"[{policy}] {robots} robots x {rate_hz:g} Hz for {duration_s:g} s "
            f"(offered {robots * rate_hz:g}/s; capacity ~"
            f"{workers * 1000 / service_ms:.0f}/s)" if service_ms > 0 else
            f"[{policy}] {robots} robots x {rate_hz:g} Hz for {duration_s:g} s")
        for rid, prio in priorities.items():
            out = run_dir / rid
            procs.append(spawn_peer(
                ["robot", *sec.args, "--id", rid, "--connect", ep, "--synthetic", "stub", "--rate", str(rate_hz),
                 "--duration", str(duration_s), "--priority", str(prio), "--no-local-fallback",
                 "--deadline-ms", "5000", "--wait-ms", "10000", "--quiet", "--out", str(out)],
                log_path=run_dir / f"{rid}.log"))
        t_end = time.monotonic() + duration_s + 60
        while any(p.poll() is None for p in procs) and time.monotonic() < t_end:
            time.sleep(0.5)
            done = sum(len(read_records(run_dir / r / "records.jsonl")) for r in priorities)
            say(f"[{policy}] {done} requests finished")
        records = {r: read_records(run_dir / r / "records.jsonl") for r in priorities}
        sampler.stop()
    finally:
        for p in procs:
            stop_peer(p, timeout=5)
        if sampler is not None:
            sampler.stop()
        rc = stop_peer(cloud, timeout=10)
    summary = summarize(records, priorities)
    hwm = sampler.hwm_kb if sampler else {}
    summary.update({
        "policy": policy, "robots": robots, "rate_hz": rate_hz, "duration_s": duration_s,
        "workers": workers, "service_ms": service_ms, "queue": queue if policy == "negotiator" else None,
        "per_robot_quota": per_robot if policy == "negotiator" else None,
        "cloud_peak_rss_mb": {
            "main": round(hwm.get(cloud.pid, 0) / 1024, 1),
            "workers_max": round(max([v for p, v in hwm.items() if p != cloud.pid] or [0]) / 1024, 1),
            "sum_sampled": round((sampler.peak_sum_kb if sampler else 0) / 1024, 1),
        },
        "cloud_exit": rc,
    })
    return summary


def run_overload_cli(args) -> int:
    """Handler of ``scmr bench overload``."""
    policies = [p.strip() for p in args.policies.split(",") if p.strip()]
    if not policies:
        raise InputError("--policies is empty; use negotiator,fifo")
    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    root = args.run_dir or Path(tempfile.mkdtemp(prefix="scmr-overload-"))
    runs = []
    for pol in policies:
        runs.append(run_overload(
            policy=pol, robots=args.robots, rate_hz=args.rate, duration_s=args.duration,
            workers=args.workers, service_ms=args.service_ms, queue=args.queue,
            per_robot=args.per_robot, levels=args.levels, run_dir=root / pol, progress=say,
            insecure=args.insecure))
    result = {"bench": "overload", "runs": runs, "run_dir": str(root),
              "note": "measured on a shared, loaded 2-core machine"}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    for r in runs:
        tor = r["tor_admitted_ms"]
        print(f"{r['policy']:>10}: {r['requests']} requests, {r['served']} served, {r['rejected']} busy, "
              f"{r['failed']} failed; ToR admitted p50 {tor['p50']} ms p99 {tor['p99']} ms; busy answer p50 "
              f"{r['time_to_busy_ms']['p50']} ms; Jain {r['jain_all']}; served share by priority "
              + ", ".join(f"{p}: {b['served_share']}" for p, b in r["by_priority"].items())
              + f"; cloud peak RSS {r['cloud_peak_rss_mb']['sum_sampled']} MB (main+workers)")
    if args.json:
        print(f"results: {args.json}")
    return 0
