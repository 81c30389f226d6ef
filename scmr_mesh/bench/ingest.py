"""``scmr bench ingest``: a cloud's memory under a telemetry flood, at any rate (issue #12, item 4).

A real ``scmr cloud`` (stub pipeline, its own ODS) is flooded by a stranger's
zenoh session with telemetry batches on ``scmr/data/cloud/<node>/telemetry/flood``
at several rates (batches per second; 0 = as fast as the sender can), for a few
seconds per rate.  Each case starts a fresh cloud, samples its RSS (``/proc``,
20 Hz) and reads its peak (``VmHWM``), and counts the answers: stored (ok),
busy, refused (error), zenoh's timeout and none.  A query ends with none when
zenoh finalises it without a reply: its link closed (a cloud stalled past the
lease, docs/ZENOH.md section 20) or it was sent while no link to the cloud was
up.  The flooder watches its transports and reports the link drops it saw
beside the count; any query left unanswered makes the command exit 1 (and keeps
the case folders, with the cloud's log, for a look).  With ``--unbounded`` each case also runs
against a cloud whose bounds are lifted (``--ingest-queue 10000000
--ingest-batch 100000``), the behaviour before the bounds, so the ratio is
measured in the same run.
"""

from __future__ import annotations

import functools
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

from scmr_mesh.errors import InputError
from scmr_mesh.qos.schedule import due_ns

UNBOUNDED = ["--ingest-queue", "10000000", "--ingest-batch", "100000", "--telemetry-quota", "0",
             "--telemetry-quota-bytes", "0"]


def _rss_mb(pid: int) -> dict[str, float]:
    out = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(("VmRSS:", "VmHWM:")):
                    out[line.split(":")[0]] = int(line.split()[1]) / 1024
    except OSError:
        pass
    return out


def _payloads(records: int, k: int = 8, *, key: Path | None = None) -> list[bytes]:
    """``k`` junk batches of ``records`` valid records each (distinct seqs; cycled by the sender), signed
    with ``key`` (the flood robot's own, as a real robot signs) when given."""
    import dataclasses

    from scmr_mesh.data.record import encode_records, make_record
    from scmr_mesh.data.signing import RecordSigner

    signer = RecordSigner(key) if key is not None else None
    out = []
    for i in range(k):
        recs = [make_record("flood", i * records + s + 1, battery=0.5, results={"junk": "x" * 64})
                for s in range(records)]
        if signer is not None:
            recs = [dataclasses.replace(r, sig=signer.sign(r.digest())) for r in recs]
        out.append(encode_records(recs))
    return out


def flood_case(*, rate_hz: float, records: int, duration_s: float, extra: list[str], workdir: Path,
               say=lambda m: None, insecure: bool = False, lease_ms: int | None = None, fault=None,
               query_timeout_s: float = 10.0) -> dict:
    """One case: a fresh cloud flooded at ``rate_hz`` batches/s of ``records`` records for ``duration_s``.

    ``lease_ms``: the cloud's and the flooder's lease (default: scmr's).  ``fault``: called with the
    cloud's pid, on a thread of its own, once the first query is sent (tests stall the cloud with it;
    a blocked ``get`` holds this process's other threads, so time a fault from another process).
    ``query_timeout_s``: each query's zenoh timeout (its ``Timeout`` answer).
    """
    import zenoh

    from scmr_mesh.mesh.config import open_session
    from scmr_mesh.mesh.data_service import telemetry_key
    from scmr_mesh.mesh.testing import STUB, spawn_peer, stop_peer, wait_for

    from scmr_mesh.ports import free_port

    port = free_port()
    tag = f"{int(rate_hz)}hz-{records}r{'-unbounded' if extra else ''}"
    ready = workdir / f"{tag}.ready"
    from scmr_mesh.bench.secure import bench_security

    sec = bench_security(workdir / tag, "c1=cloud,flood=robot", insecure=insecure)
    lease = [] if lease_ms is None else ["--lease-ms", str(int(lease_ms))]
    cloud = spawn_peer(["cloud", *sec.args, *lease, "--node", "c1", "--workers", "1", "--process", STUB, "--listen",
                        f"tcp/127.0.0.1:{port}", "--ready-file", str(ready), "--ods", str(workdir / f"{tag}.sqlite"),
                        *extra], log_path=workdir / f"{tag}.log")
    payloads = _payloads(records, key=None if sec.creds is None else sec.creds.directory / "flood" / "key.pem")
    counts = {"sent": 0, "ok": 0, "busy": 0, "refused": 0, "timeout": 0}
    lock = threading.Lock()
    link_drops: list[float] = []  # when this process saw a transport to the cloud close (s since the flood's start;
    # the callback can run late while a blocked get holds the interpreter)
    samples: list[float] = []
    try:
        wait_for(lambda: ready.exists() or cloud.poll() is not None, timeout=120, what="cloud ready")
        if cloud.poll() is not None:
            raise InputError(f"the cloud did not start; see {workdir / f'{tag}.log'}")
        session = open_session(sec.mesh("flood", connect=[f"tcp/127.0.0.1:{port}"], lease_ms=lease_ms))
        try:
            key = telemetry_key("cloud", "c1", "flood")
            q = session.declare_querier(key, timeout=query_timeout_s)
            wait_for(lambda: q.matching_status.matching, timeout=10, what="the cloud's telemetry queryable")
            base = _rss_mb(cloud.pid)
            t0 = time.monotonic()

            def on_transport(ev) -> None:  # a link to the cloud closed: zenoh ends its queries with no reply
                if ev.kind == zenoh.SampleKind.DELETE:
                    with lock:
                        link_drops.append(round(time.monotonic() - t0, 3))

            listener = session.info.declare_transport_events_listener(on_transport)
            seen: set[int] = set()

            def on_reply(i: int, reply) -> None:  # the first answer of query i counts
                with lock:
                    if i in seen:
                        return
                    seen.add(i)
                    if reply.ok is not None:
                        counts["ok"] += 1
                        return
                    raw = reply.err.payload.to_bytes()
                    if raw == b"Timeout":  # zenoh's own: the cloud did not answer in time
                        counts["timeout"] += 1
                        return
                    try:
                        import msgpack

                        body = msgpack.unpackb(raw, raw=False)
                    except Exception:
                        body = {}
                    counts["busy" if isinstance(body, dict) and body.get("busy") else "refused"] += 1

            stop = threading.Event()

            def sample() -> None:
                while not stop.wait(0.05):
                    samples.append(_rss_mb(cloud.pid).get("VmRSS", 0.0))

            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()
            t0_ns = time.monotonic_ns()
            i = 0
            while time.monotonic() - t0 < duration_s:
                if rate_hz > 0:  # query i+1 due at t0 + (i+1) x period, from integers (no float drift)
                    delay_ns = due_ns(t0_ns, i + 1, rate_hz) - time.monotonic_ns()
                    if delay_ns > 0:
                        time.sleep(delay_ns / 1e9)
                session.get(key, handler=functools.partial(on_reply, i), payload=payloads[i % len(payloads)],
                            timeout=query_timeout_s)
                i += 1
                if i == 1 and fault is not None:
                    threading.Thread(target=fault, args=(cloud.pid,), daemon=True).start()
            sent_s = time.monotonic() - t0
            counts["sent"] = i
            end = time.monotonic() + query_timeout_s + 2.0  # the last queries' answers, or their Timeout
            while time.monotonic() < end:
                with lock:
                    answered = counts["ok"] + counts["busy"] + counts["refused"] + counts["timeout"]
                if answered >= i:
                    break
                time.sleep(0.05)
            stop.set()
            sampler.join()
            peak = _rss_mb(cloud.pid)
            alive = cloud.poll() is None
            listener.undeclare()
        finally:
            from scmr_mesh.mesh.config import close_session

            close_session(session)
    finally:
        stop_peer(cloud, timeout=20)
    with lock:
        c = dict(counts)
        drops = list(link_drops)
    c["none"] = c["sent"] - c["ok"] - c["busy"] - c["refused"] - c["timeout"]
    c["link_drops"] = len(drops)
    res = {"case": tag, "rate_hz": rate_hz, "records_per_batch": records, "bounded": not extra,
           "duration_s": round(sent_s, 2), "sent_per_s": round(c["sent"] / max(sent_s, 1e-9), 1),
           "batch_bytes": len(payloads[0]), "answers": c,
           "rss_start_mb": round(base.get("VmRSS", 0.0), 1), "rss_peak_mb": round(peak.get("VmHWM", 0.0), 1),
           "rss_sampled_max_mb": round(max(samples, default=0.0), 1), "cloud_alive": alive,
           "link_drops_at_s": drops, "lease_ms": lease_ms}
    res["rss_rise_mb"] = round(res["rss_peak_mb"] - res["rss_start_mb"], 1)
    say(f"{tag}: {c['sent']} batches ({res['sent_per_s']}/s) -> ok {c['ok']}, busy {c['busy']}, refused "
        f"{c['refused']}, timeout {c['timeout']}, none {c['none']}"
        + (f" (the link to the cloud dropped {len(drops)} time(s), seen at {drops} s)" if drops else "")
        + f"; cloud RSS {res['rss_start_mb']} -> peak "
        f"{res['rss_peak_mb']} MB")
    return res


def cmd_bench_ingest(args) -> int:
    """``scmr bench ingest``."""
    rates = [float(x) for x in str(args.rates).split(",") if x.strip()]
    sizes = [int(x) for x in str(args.records).split(",") if x.strip()]
    say = (lambda m: None) if args.quiet else (lambda m: print(f"bench ingest: {m}", file=sys.stderr, flush=True))
    with open("/proc/loadavg") as f:
        load_before = f.read().split()[:3]
    cases = []
    tmp = Path(tempfile.mkdtemp(prefix="scmr-bench-ingest-"))  # kept when a case fails: its logs are there
    for records in sizes:
        for rate in rates:
            for extra in ([[], UNBOUNDED] if args.unbounded else [[]]):
                cases.append(flood_case(rate_hz=rate, records=records, duration_s=args.duration, extra=extra,
                                        workdir=tmp, say=say, insecure=args.insecure, lease_ms=args.lease_ms))
    with open("/proc/loadavg") as f:
        load_after = f.read().split()[:3]
    bounded = [c for c in cases if c["bounded"]]
    unbounded = [c for c in cases if not c["bounded"]]
    out = {"benchmark": "ingest", "duration_s": args.duration, "rates_hz": rates, "records_per_batch": sizes,
           "loadavg_before": load_before, "loadavg_after": load_after, "cases": cases,
           "bounded_rss_peak_mb_max": max((c["rss_peak_mb"] for c in bounded), default=None),
           "bounded_rss_rise_mb_max": max((c["rss_rise_mb"] for c in bounded), default=None),
           "unbounded_rss_rise_mb_max": max((c["rss_rise_mb"] for c in unbounded), default=None)}
    print(f"{'case':<24}{'sent/s':>9}{'ok':>8}{'busy':>8}{'refused':>9}{'timeout':>9}{'none':>7}{'drops':>7}"
          f"{'RSS start':>11}{'peak':>8}{'rise':>8}")
    for c in cases:
        a = c["answers"]
        print(f"{c['case']:<24}{c['sent_per_s']:>9}{a['ok']:>8}{a['busy']:>8}{a['refused']:>9}{a['timeout']:>9}"
              f"{a['none']:>7}{a['link_drops']:>7}{c['rss_start_mb']:>11}{c['rss_peak_mb']:>8}{c['rss_rise_mb']:>8}")
    print(f"bounded: peak RSS at most {out['bounded_rss_peak_mb_max']} MB (rise {out['bounded_rss_rise_mb_max']} MB)"
          + (f"; unbounded: rise up to {out['unbounded_rss_rise_mb_max']} MB" if unbounded else "")
          + f"; load {' '.join(load_before)} -> {' '.join(load_after)}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    dead = [c["case"] for c in cases if not c["cloud_alive"]]
    if dead:
        raise InputError(f"the cloud died under the flood in {', '.join(dead)}; see its log in {tmp}/<case>.log")
    problems = []
    for c in cases:
        a = c["answers"]
        if a["none"] and a["link_drops"]:
            problems.append(f"{c['case']}: {a['none']} queries had no answer and the link to the cloud dropped "
                            f"{a['link_drops']} time(s) (a cloud stalled past its lease: rerun on a quieter machine "
                            "or with a longer --lease-ms)")
        elif a["none"]:
            problems.append(f"{c['case']}: the cloud left {a['none']} queries unanswered with no link drop (a defect)")
    if problems:
        raise InputError(f"{'; '.join(problems)}; logs in {tmp}")
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    return 0
