"""``scmr view FILE.rrd``: open a saved recording in the rerun viewer."""

from __future__ import annotations

import argparse
import subprocess
import sys


def register(sub: argparse._SubParsersAction, bench: argparse._SubParsersAction) -> None:
    """Add ``scmr view`` to ``scmr``."""
    p = sub.add_parser(
        "view",
        help="open a saved recording (FILE.rrd) in the rerun viewer",
        description=(
            "Open a recording written with --save (by `scmr up`, `scmr scenario run` or "
            "`scmr demo`) in the rerun viewer: red/green overlays per robot, ToR and "
            "serving-tier plots, cloud/leader liveliness and faults.  A thin wrapper over "
            "`rerun FILE` with rerun's usage analytics turned off."
        ),
        epilog=(
            "examples:\n"
            "  scmr view runs/demo/demo.rrd                 native viewer (needs a display)\n"
            "  scmr view runs/demo/demo.rrd --web           web viewer on http://127.0.0.1:9090\n"
            "  scmr view runs/demo/demo.rrd --screenshot shot.png   headless PNG (needs mesa-vulkan-drivers)\n"
            "  scmr view runs/demo/demo.rrd --summary       entities and row counts, no viewer"
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", metavar="FILE.rrd", help="recording to open")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--web", action="store_true", help="serve the web viewer instead of opening a window")
    mode.add_argument("--screenshot", metavar="OUT.png", help="render headless and save a PNG, then exit")
    mode.add_argument("--summary", action="store_true", help="print entities with their row counts and exit")
    p.add_argument("--web-port", type=int, default=9090, help="port of the web viewer (default: %(default)s)")
    p.add_argument("--settle", type=float, default=6.0, help="seconds to let the viewer load before --screenshot (default: %(default)s)")
    p.add_argument("--max-size", type=int, default=None, help="longest side of the --screenshot PNG in pixels")
    p.set_defaults(func=run)

    b = bench.add_parser(
        "viz",
        help="cost of rerun logging per robot request (median/p99 ms, bytes per frame)",
        description=(
            "Time RobotViz.observe() (camera JPEG + drivability map + scalars) into a "
            "--save sink started as in a fleet run, and the sink's start and finalise "
            "times.  Synthetic frames; reports medians and p99s measured in one run."
        ),
    )
    b.add_argument("--frames", type=int, default=200, help="requests to log (default: %(default)s)")
    b.add_argument("--size", default="640x480", help="camera frame WxH (default: %(default)s)")
    b.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    b.set_defaults(func=run_bench)


def run_bench(args: argparse.Namespace) -> int:
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
        for i in range(args.frames):
            rec = {"seq": i, "ok": True, "tier": "cloud", "tor_ms": 5.0, "received_unix_ns": time.time_ns()}
            t = time.perf_counter()
            rv.observe(rec, rgb, mask)
            times.append((time.perf_counter() - t) * 1e3)
            if i % 50 == 0:
                print(f"logged {i}/{args.frames}", file=sys.stderr)
        t = time.perf_counter()
        rv.close()
        fv.close()
        close_ms = (time.perf_counter() - t) * 1e3
        size = out.stat().st_size
    arr = np.array(times)
    result = {
        "frames": args.frames,
        "frame_size": [w, h],
        "observe_ms_median": round(float(np.median(arr)), 3),
        "observe_ms_p99": round(float(np.percentile(arr, 99)), 3),
        "sink_start_ms": round(start_ms, 1),
        "flush_and_finalise_ms": round(close_ms, 1),
        "rrd_bytes_per_frame": round(size / args.frames),
    }
    print(json.dumps(result, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0


def run(args: argparse.Namespace) -> int:
    from scmr_mesh import viz

    path = viz.check_rrd(args.file)
    if args.summary:
        rows = viz.rrd_rows(path)
        for entity in sorted(rows):
            comps = ", ".join(f"{c}={n}" for c, n in sorted(rows[entity].items()))
            print(f"{entity}  {comps}")
        return 0
    if args.screenshot:
        print(f"rendering {path} headless ...", file=sys.stderr)
        out = viz.screenshot(path, args.screenshot, settle=args.settle, max_size=args.max_size)
        print(f"wrote {out}", file=sys.stderr)
        return 0
    exe = viz.rerun_executable()
    if args.web:
        cmd = [exe, "--web-viewer", "--web-viewer-port", str(args.web_port), "--bind", "127.0.0.1", str(path)]
        print(f"serving the web viewer on http://127.0.0.1:{args.web_port} (Ctrl-C to stop)", file=sys.stderr)
    else:
        if not viz.has_display():
            raise viz.ViewerError(
                "no display (DISPLAY/WAYLAND_DISPLAY unset) for the native viewer; "
                f"use `scmr view {args.file} --web` or --screenshot OUT.png"
            )
        cmd = [exe, str(path)]
    try:
        return subprocess.call(cmd, env=viz.rerun_env())
    except KeyboardInterrupt:
        return 130
    except OSError as exc:
        raise viz.ViewerError(f"could not run {cmd[0]}: {exc}") from exc
