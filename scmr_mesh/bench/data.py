"""``scmr bench data``: the data tier measured in one run (queue, ODS, buffer, store round trip)."""

from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path

from scmr_mesh.data.record import encode_records
from scmr_mesh.errors import InputError, MeshError
from scmr_mesh.mesh.data_service import CloudData, TelemetryAgent, telemetry_key


def _stats(samples: list[float]) -> dict:
    import numpy as np

    a = np.asarray(samples, dtype=float)
    return {"n": int(a.size), "median_ms": round(float(np.median(a)), 4),
            "p99_ms": round(float(np.percentile(a, 99)), 4), "max_ms": round(float(a.max()), 4)}


def run_bench(*, n: int = 200, mesh: bool = True, progress=None) -> dict:
    """Data-tier benchmark: queue appends, ODS inserts, buffer delta/merge, Zenoh store round trip.

    Every figure is a median and p99 over ``n`` samples measured in this run.
    """
    import tempfile
    import time

    from scmr_mesh.data.buffer import DataBuffer
    from scmr_mesh.data.ods import OperationalDataStore
    from scmr_mesh.data.queue import TelemetryQueue
    from scmr_mesh.data.record import make_record

    say = progress or (lambda msg: None)
    out: dict = {"n": n, "results": {}}
    payload = b"x" * 200  # about one telemetry record
    with tempfile.TemporaryDirectory(prefix="scmr-bench-data-") as tmp:
        for policy in ("always", "batch", "never"):
            say(f"queue append, fsync={policy}")
            with TelemetryQueue(Path(tmp) / f"q-{policy}", fsync=policy) as q:
                samples = []
                for _ in range(n):
                    t0 = time.perf_counter()
                    q.append(payload)
                    samples.append((time.perf_counter() - t0) * 1e3)
            out["results"][f"queue_append_fsync_{policy}"] = _stats(samples)
        say("queue reopen (recovery scan) of n records")
        t0 = time.perf_counter()
        with TelemetryQueue(Path(tmp) / "q-always") as q:
            assert len(q) == n
        out["results"]["queue_reopen_ms"] = round((time.perf_counter() - t0) * 1e3, 3)
        with OperationalDataStore(Path(tmp) / "ods.sqlite") as ods:
            seq = 1
            for batch in (1, 64):
                say(f"ODS insert, batch {batch}")
                samples = []
                for _ in range(n):
                    recs = [make_record("b", seq + k, pose=(1, 2, 3), battery=0.5, results={"requests": seq})
                            for k in range(batch)]
                    seq += batch
                    t0 = time.perf_counter()
                    ods.insert(recs, received_from="cloud")
                    samples.append((time.perf_counter() - t0) * 1e3)
                out["results"][f"ods_insert_batch{batch}"] = _stats(samples)
                out["results"][f"ods_insert_batch{batch}"]["records_per_s_median"] = round(
                    batch / (out["results"][f"ods_insert_batch{batch}"]["median_ms"] / 1e3), 1)
            say("ODS duplicate batch of 64 (all ignored)")
            recs = [make_record("dup", k) for k in range(1, 65)]
            ods.insert(recs, received_from="cloud")  # stored once; every later insert is all duplicates
            samples = []
            for _ in range(max(10, n // 10)):
                t0 = time.perf_counter()
                ods.insert(recs, received_from="leader")
                samples.append((time.perf_counter() - t0) * 1e3)
            out["results"]["ods_insert_duplicates64"] = _stats(samples)
        say("buffer delta + merge (1000 entries, 10 changed)")
        src, dst = DataBuffer("cloud"), DataBuffer("leader")
        for i in range(1000):
            src.put(f"state/r{i}", {"seq": i, "pose": [i, i, 0.0], "battery": 0.5})
        dst.merge(src.snapshot())
        samples = []
        for k in range(n):
            rev = src.rev
            for j in range(10):
                src.put(f"state/r{(k * 10 + j) % 1000}", {"seq": k, "pose": [0, 0, 0.0], "battery": 0.4})
            t0 = time.perf_counter()
            dst.merge(src.delta(rev, epoch=src.epoch))
            samples.append((time.perf_counter() - t0) * 1e3)
        out["results"]["buffer_delta10_merge"] = _stats(samples)
        t0 = time.perf_counter()
        snap = src.snapshot()
        DataBuffer("x").merge(snap)
        out["results"]["buffer_snapshot1000_merge_ms"] = round((time.perf_counter() - t0) * 1e3, 3)
        out["results"]["buffer_snapshot1000_bytes"] = len(snap)
        if mesh:
            for batch in (1, 64):
                say(f"Zenoh telemetry round trip (query -> ODS commit -> ack), batch {batch}")
                out["results"][f"zenoh_store_ack_batch{batch}"] = _stats(
                    bench_round_trip(tmp, n=n, batch=batch))
            say(f"backlog replay after an outage: {10 * n} queued records drained to the cloud")
            out["results"]["backlog_drain"] = bench_drain(tmp, backlog=10 * n)
    return out


def cmd_bench_data(args) -> int:
    import os

    if args.n < 10:
        raise InputError(f"--n must be >= 10, got {args.n}")

    def say(msg: str) -> None:
        if not args.quiet:
            print(f"bench data: {msg} ...", file=sys.stderr, flush=True)

    res = run_bench(n=args.n, mesh=not args.no_mesh, progress=say)
    res["load_avg"] = list(os.getloadavg())
    text = json.dumps(res, indent=1)
    if args.json:
        Path(args.json).write_text(text + "\n")
    print(text)
    return 0

@contextlib.contextmanager
def _bench_pair(store: Path, node: str, robot: str):
    """A cloud session serving :class:`CloudData` ``node`` (ODS at ``store``) and a
    robot session linked to it over ``tcp/127.0.0.1``, in this process; yields
    ``(cloud, robot_session)`` once the robot sees ``robot``'s telemetry queryable."""
    from scmr_mesh.ports import free_port

    from scmr_mesh.mesh.config import MeshConfig, close_session, open_session

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    from scmr_mesh.data.quota import Quota

    cloud = CloudData(node, store, quota=Quota(0, 0))  # the store's own throughput: no per-robot quota
    cs = open_session(MeshConfig(listen=[ep]))
    rs = None
    decl = []
    try:
        for key, cb in cloud.queryables():
            decl.append(cs.declare_queryable(key, cb, complete=True))
        rs = open_session(MeshConfig(connect=[ep]))
        q = rs.declare_querier(telemetry_key("cloud", node, robot))
        end = time.monotonic() + 10
        while not q.matching_status.matching:
            if time.monotonic() > end:
                raise MeshError("bench: the robot session never saw the cloud's telemetry queryable")
            time.sleep(0.01)
        q.undeclare()
        yield cloud, rs
    finally:
        for d in decl:
            try:
                d.undeclare()
            except Exception:
                pass
        if rs is not None:
            close_session(rs)
        close_session(cs)
        cloud.close()


def bench_drain(tmp_dir: str | Path, *, backlog: int = 2000) -> dict:
    """Replay a robot backlog to a cloud over Zenoh, as after an outage; return timings.

    A :class:`TelemetryAgent` (real queue, real batching and acks) whose queue
    holds ``backlog`` records drains them into a :class:`CloudData` ODS; two
    sessions in one process over ``tcp/127.0.0.1``.

    Returns
    -------
    dict
        ``backlog``, ``drain_s``, ``records_per_s`` and ``stored`` (checked == backlog).
    """
    from types import SimpleNamespace

    tmp_dir = Path(tmp_dir)
    with _bench_pair(tmp_dir / "drain-ods.sqlite", "drain", "bench") as (cloud, rs):
        view = SimpleNamespace(snapshot=lambda local=False: SimpleNamespace(cloud=("drain",), leader=()))
        robot = SimpleNamespace(id="bench", _session=rs, view=view, publish_telemetry=lambda m: None,
                                add_telemetry_handler=lambda fn: None, remove_telemetry_handler=lambda fn: None)
        agent = TelemetryAgent(robot, tmp_dir / "drain-queue", autostart=False, deadline_ms=5000)
        try:
            for i in range(1, backlog + 1):
                agent.publish({"robot": "bench", "seq": i, "t_unix_ns": time.time_ns(),
                               "pose": {"x": 0.0, "y": 0.0, "theta": 0.0}, "battery": 0.5, "health": "ok",
                               "results": {"requests": i, "succeeded": i, "by_tier": {"cloud": i}}})
            t0 = time.perf_counter()
            while len(agent.queue):
                if not agent.flush_once():
                    raise MeshError("bench: the cloud stopped acknowledging telemetry during the drain")
            dt = time.perf_counter() - t0
            stored = cloud.ods.counts().get("bench", {}).get("stored", 0)
            return {"backlog": backlog, "drain_s": round(dt, 4), "records_per_s": round(backlog / dt, 1),
                    "stored": stored}
        finally:
            agent.close(drain_s=0)


def bench_round_trip(tmp_dir: str | Path, *, n: int = 200, batch: int = 1, warmup: int = 20) -> list[float]:
    """Telemetry store round trips (ms) over Zenoh: robot query -> cloud ODS commit -> ack.

    Two sessions in one process linked over ``tcp/127.0.0.1`` (multicast off):
    a cloud session with :class:`CloudData`'s queryables, and a robot session
    sending ``batch`` records per query.  Each sample is one query, from send
    to the ack (so it includes the ODS commit with ``synchronous=FULL``).
    """
    from scmr_mesh.data.record import make_record

    robot = f"bench{batch}"
    with _bench_pair(Path(tmp_dir) / "bench-ods.sqlite", "bench", robot) as (_cloud, rs):
        q = rs.declare_querier(telemetry_key("cloud", "bench", robot), timeout=5.0)
        out: list[float] = []
        seq = 1
        for i in range(warmup + n):
            recs = [make_record(robot, seq + k, pose=(1.0, 2.0, 0.5), battery=0.9,
                                results={"requests": seq, "succeeded": seq, "by_tier": {"cloud": seq}})
                    for k in range(batch)]
            seq += batch
            payload = encode_records(recs)
            t0 = time.perf_counter()
            ok = False
            for reply in q.get(payload=payload):
                ok = reply.ok is not None
            dt = (time.perf_counter() - t0) * 1e3
            if not ok:
                raise MeshError("bench: the cloud did not acknowledge a telemetry batch")
            if i >= warmup:
                out.append(dt)
        q.undeclare()
        return out
