"""The cloud node's ingress against its workers (issue 23 item 2): ``scmr bench mesh --ingress-seconds S``.

One ``scmr cloud`` whose workers run a fixed-time stub
(:func:`scmr_mesh.mesh.testing.fixed_process`: a sleep, no CPU), so the
workers' capacity is known and does not compete for the host's cores: what
limits the node is then its ingress (zenoh's threads, decoding, admission,
dispatch to the pool, replies: one interpreter) or its admission rule.

1. **closed loop**: ``2 x workers`` senders, each sending the next frame when the
   last is answered: the workers' closed-loop capacity (frames/s);
2. **open-loop ramp**: requests at fixed times (``t0 + k / rate``) at rising
   fractions of that capacity, each step for ``step_s`` seconds; per step the
   frames served per second and the busy answers;
3. per step, the cloud's CPU per thread (``/proc/PID/task``) and its workers'.

``served_at_first_busy_ratio``: the highest served frames/s of a step without a
busy answer, over the closed-loop capacity (target >= 0.85).
"""

from __future__ import annotations

import os
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Sequence

from scmr_mesh.bench import usable_cores


#: Offered load of the ramp's steps, as fractions of the closed-loop capacity.
RAMP = (0.5, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0, 1.1)
#: The issue's target for :func:`knee` ``["served_at_first_busy_ratio"]``.
TARGET_RATIO = 0.85

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds of process ``pid``'s threads by name (``comm``), plus ``"workers"``: its children's.

    zenoh's threads carry their pool's name (``rx-0``, ``tx-0``, ``net-0``, ``acc-0``: grouped
    without the number); Python's threads are all named after the interpreter (``python``):
    the service's callback, pool, reply and load threads together.
    """
    out: dict[str, float] = defaultdict(float)
    children: list[int] = []
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return {}
    for task in tasks:
        try:
            stat = (task / "stat").read_text()
            children += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        f = stat.rsplit(")", 1)[1].split()
        out[_group(name)] += (int(f[11]) + int(f[12])) / _TICK
    for c in children:
        try:
            f = Path(f"/proc/{c}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out["workers"] += (int(f[11]) + int(f[12])) / _TICK
    return dict(out)


def _group(comm: str) -> str:
    """Thread names grouped: zenoh's pools (``rx-3`` -> ``rx``), the service's threads by role."""
    base = comm.rstrip("0123456789").rstrip("-_")
    return base or comm


def cpu_delta(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    """``b - a`` per thread group (groups only in ``b`` count from 0).

    >>> cpu_delta({"rx": 1.0}, {"rx": 1.5, "workers": 0.2})
    {'rx': 0.5, 'workers': 0.2}
    """
    return {k: round(b[k] - a.get(k, 0.0), 3) for k in sorted(b)}


def _fields(result) -> dict:
    """The fields of a reply or error payload, unchecked (the bench reads two; the client's CPU is the schedule's)."""
    import msgpack

    try:
        out = msgpack.unpackb(result.payload.to_bytes(), raw=False)
    except Exception:
        return {}
    return out if isinstance(out, dict) else {}


def _pcts(values: Sequence[float]) -> dict[str, float | None]:
    from scmr_mesh.qos import metrics

    return {p: (round(metrics.percentile(values, q), 1) if values else None)
            for p, q in (("p50", 50), ("p99", 99))}


def knee(capacity_fps: float, steps: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Where the first busy answer appears on a ramp (pure).

    ``steps``: ``{"offered_fps", "served_fps", "busy"}`` (and
    ``sender_late_max_ms``) in ramp order.  The
    ratio is the highest served frames/s of the steps before the first one
    with a busy answer, over ``capacity_fps``.

    >>> k = knee(100.0, [{"offered_fps": 50, "served_fps": 50, "busy": 0},
    ...                  {"offered_fps": 90, "served_fps": 88, "busy": 0},
    ...                  {"offered_fps": 100, "served_fps": 91, "busy": 4}])
    >>> k["served_at_first_busy_ratio"], k["first_busy_offered_fps"], k["ok"]
    (0.88, 100, True)
    """
    clean = []
    first = None
    for s in steps:
        if s["busy"]:
            first = s
            break
        clean.append(s["served_fps"])
    best = max(clean, default=0.0)
    ratio = round(best / capacity_fps, 3) if capacity_fps > 0 else None
    return {"capacity_fps": round(capacity_fps, 1), "served_before_busy_fps": round(best, 1),
            "served_at_first_busy_ratio": ratio,
            "first_busy_offered_fps": None if first is None else first["offered_fps"],
            "first_busy_served_fps": None if first is None else first["served_fps"],
            # a client that fell behind its schedule sent a burst in that step: read the ratio with it
            "first_busy_sender_late_ms": None if first is None else first.get("sender_late_max_ms"),
            "target": TARGET_RATIO, "ok": ratio is not None and ratio >= TARGET_RATIO}


def measure_ingress(*, workers: int = 8, delay_ms: float = 20.0, step_s: float = 3.0,
                    ramp: Sequence[float] = RAMP, run_dir: Path, insecure: bool = False,
                    extra_args: Sequence[str] = (), process: str | None = None, progress=None) -> dict[str, Any]:
    """Closed-loop capacity, then the open-loop ramp, of one ``scmr cloud`` on the fixed-time stub
    (``process``: another process function, e.g. the pipeline, ``delay_ms`` then unused)."""
    import zenoh

    from scmr_mesh import keys, wire
    from scmr_mesh.bench.secure import bench_cloud
    from scmr_mesh.imaging.synthetic import SCENE_KINDS
    from scmr_mesh.mesh.robot import frames_from_args
    from scmr_mesh.mesh.testing import FIXED, wait_for
    from scmr_mesh.qos.schedule import due_ns
    from scmr_mesh.ports import free_ports

    say = progress or (lambda m: None)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    port = free_ports(["ing"])["ing"]
    frames = []
    for i, kind in enumerate(SCENE_KINDS):
        it = frames_from_args(None, kind, seed=i)
        frames += [next(it) for _ in range(2)]
    seq = iter(range(1, 1 << 62))
    lock = threading.Lock()
    with bench_cloud(run_dir, "ing0", "ing", port=port, insecure=insecure, what="ingress",
                     args=["--workers", str(workers), "--process", process or FIXED, *extra_args],
                     env={"SCMR_STUB_DELAY_MS": str(delay_ms)}) as (proc, session, q):

        def payload() -> bytes:
            with lock:
                n = next(seq)
            f = frames[n % len(frames)]
            return wire.encode(wire.make_request("ing", n, f.data, encoding=f.encoding, shape=f.shape))

        def outcome(r) -> str:
            if r.ok is not None:
                return "ok"
            code = _fields(r.err).get("code")
            return "busy" if code == "busy" else str(code)

        # 1. closed loop
        conc = 2 * workers
        state = {"stop": False, "measure": False}
        closed = defaultdict(int)

        def sender() -> None:
            while not state["stop"]:
                out, retry_ms = "none", None
                for r in q.get(payload=payload()):
                    out = outcome(r)
                    if out == "busy":
                        retry_ms = _fields(r.err).get("retry_after_ms")
                if state["measure"]:
                    with lock:
                        closed[out] += 1
                if retry_ms:  # as a robot would: elsewhere now, back here when the queue has drained
                    time.sleep(min(1.0, float(retry_ms) / 1e3))

        threads = [threading.Thread(target=sender, daemon=True) for _ in range(conc)]
        for t in threads:
            t.start()
        time.sleep(1.0)
        c0, t0 = thread_cpu(proc.pid), time.monotonic()
        state["measure"] = True
        time.sleep(step_s * 2)
        state["measure"] = False
        c1, t1 = thread_cpu(proc.pid), time.monotonic()
        state["stop"] = True
        for t in threads:
            t.join(timeout=15)
        capacity = closed["ok"] / (t1 - t0)
        closed_cpu = cpu_delta(c0, c1)
        ideal = f"{workers} workers x {delay_ms:g} ms, ideal {workers * 1e3 / delay_ms:.0f}" if not process else \
            f"{workers} workers running {process}"
        say(f"ingress: closed loop {capacity:.1f} frames/s ({ideal}, {conc} senders); {dict(closed)}")

        # 2. open-loop ramp
        steps = []
        for frac in ramp:
            rate = frac * capacity
            counts: dict[str, int] = defaultdict(int)
            pending = [0]

            times: dict[str, list[float]] = {"server_ms": [], "queue_ms": []}

            def done(r, counts=counts, times=times) -> None:
                o = outcome(r)
                if o == "ok":  # the cloud's own time: arrival to reply, and of it the wait before a worker
                    rep = _fields(r.ok)
                with lock:
                    counts[o] += 1
                    if o == "ok":
                        times["server_ms"].append(float(rep["server_ms"]))
                        times["queue_ms"].append(float(rep.get("queue_ms") or 0.0))

            def finished(counts=counts) -> None:
                with lock:
                    pending[0] -= 1

            n = max(1, int(rate * step_s))
            # made before the step: the client's one interpreter then only sends on time (a late
            # client sends a burst, which the node rightly answers busy)
            payloads = [payload() for _ in range(n)]
            c0, s0 = thread_cpu(proc.pid), time.monotonic_ns()
            late_ns = 0
            for k in range(n):  # request k due at s0 + k / rate, from integers (no float drift)
                wait_ns = due_ns(s0, k, rate) - time.monotonic_ns()
                if wait_ns > 0:
                    time.sleep(wait_ns / 1e9)
                else:
                    late_ns = max(late_ns, -wait_ns)
                with lock:
                    pending[0] += 1
                session.get(keys.drivable_request("cloud", "ing0", "ing"), payload=payloads[k], timeout=10.0,
                            handler=zenoh.handlers.Callback(done, finished))
            sent_s = (time.monotonic_ns() - s0) / 1e9
            wait_for(lambda: pending[0] <= 0, timeout=30, what="the ramp step's replies")
            c1 = thread_cpu(proc.pid)
            cpu = cpu_delta(c0, c1)
            ok, busy = counts.get("ok", 0), counts.get("busy", 0)
            step = {"fraction": frac, "offered_fps": round(n / sent_s, 1), "requests": n,
                    "served_fps": round(ok / sent_s, 1), "ok": ok, "busy": busy,
                    "other": {k: v for k, v in counts.items() if k not in ("ok", "busy")},
                    "sender_late_max_ms": round(late_ns / 1e6, 1), "cpu_s": cpu,
                    **{k: _pcts(v) for k, v in times.items()},
                    "cpu_ms_per_request": {k: round(v * 1e3 / n, 3) for k, v in cpu.items()},
                    "loadavg_1min": round(os.getloadavg()[0], 2)}
            steps.append(step)
            say(f"  offered {step['offered_fps']} frames/s ({frac:g}): served {step['served_fps']}, busy {busy}, "
                f"server ms p50 {step['server_ms']['p50']} (queue {step['queue_ms']['p50']}); "
                f"cloud CPU ms/request {step['cpu_ms_per_request']}")
    return {"workers": workers, "delay_ms": delay_ms if not process else None, "process": process or FIXED, "step_s": step_s, "senders": conc,
            "closed_loop": {"frames_per_s": round(capacity, 1), "outcomes": dict(closed), "cpu_s": closed_cpu,
                            "cpu_ms_per_request": {k: round(v * 1e3 / max(1, closed["ok"]), 3)
                                                   for k, v in closed_cpu.items()}},
            "steps": steps, **knee(capacity, steps), "cores": usable_cores(),
            "loadavg_at_end": list(os.getloadavg())}


__all__ = ["RAMP", "TARGET_RATIO", "cpu_delta", "knee", "measure_ingress", "thread_cpu"]
