"""``scmr bench viz``: the cost of rerun logging per robot request."""

from __future__ import annotations

import argparse
import sys


def cmd_bench_viz(args: argparse.Namespace) -> int:
    import json
    import tempfile
    import time
    from pathlib import Path

    import numpy as np

    from scmr_mesh import viz
    from scmr_mesh.errors import InputError

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 640x480, got {args.size!r}") from None
    if args.frames < 1:
        raise InputError(f"--frames must be >= 1, got {args.frames}")
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    rgb[h // 2 :] = (90, 90, 90)
    mask = np.zeros((225, 300), np.uint8)
    mask[120:, 60:240] = 255
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.rrd"
        t = time.perf_counter()
        fv = viz.FleetViz(viz.RerunOptions("save", str(out)), robots=["r0"])
        start_ms = (time.perf_counter() - t) * 1e3
        rv = viz.RobotViz(viz.RerunOptions("connect", fv.url, fv.recording_id), "r0")
        times = []
        cpu0 = time.process_time()
        for i in range(args.frames):
            rec = {"seq": i, "ok": True, "tier": "cloud", "tor_ms": 5.0, "received_unix_ns": time.time_ns()}
            t = time.perf_counter()
            rv.observe(rec, rgb, mask)
            times.append((time.perf_counter() - t) * 1e3)
            if i % 50 == 0:
                print(f"logged {i}/{args.frames}", file=sys.stderr)
            time.sleep(args.interval)
        t = time.perf_counter()
        rv.close()
        cpu_ms = (time.process_time() - cpu0) * 1e3
        fv.close()
        close_ms = (time.perf_counter() - t) * 1e3
        size = out.stat().st_size
    arr = np.array(times)
    result = {
        "frames": args.frames,
        "frame_size": [w, h],
        "observe_ms_median": round(float(np.median(arr)), 3),
        "observe_ms_p99": round(float(np.percentile(arr, 99)), 3),
        "process_cpu_ms_per_frame": round(cpu_ms / args.frames, 3),
        "sink_start_ms": round(start_ms, 1),
        "flush_and_finalise_ms": round(close_ms, 1),
        "rrd_bytes_per_frame": round(size / args.frames),
    }
    print(json.dumps(result, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0
