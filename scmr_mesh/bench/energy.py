"""``scmr bench energy``: measured energy-model inputs on real frames and decision latency."""

from __future__ import annotations

import argparse
import sys

from scmr_mesh.errors import InputError


def cmd_bench_energy(args: argparse.Namespace) -> int:
    import time

    from scmr_mesh.energy.commands import (
        _frame_files,
        _profiles,
        _write_json,
        parse_rate,
    )
    from scmr_mesh.energy.experiments import _pct, measured_inputs_report
    from scmr_mesh.energy.measure import host_clock_hz
    from scmr_mesh.energy.placement import LinkEstimate, Task, choose_placement
    from scmr_mesh.imaging import decode_frame, encode_mask_png, segment_drivable, warm_up

    files = _frame_files(args.data)
    if args.count is not None:
        if args.count <= 0:
            raise InputError(f"--count must be > 0, got {args.count}")
        files = (files * (args.count // len(files) + 1))[: args.count]
    profs = _profiles(args, args.profile)
    up = parse_rate(args.bandwidth_up)
    down = parse_rate(args.bandwidth_down) if args.bandwidth_down else up
    hz, hz_source = host_clock_hz()
    print("warming up the pipeline (JIT) ...", file=sys.stderr)
    warm_up()
    samples = []
    for i, f in enumerate(files):
        data = f.read_bytes()
        c0 = time.thread_time()
        rgb = decode_frame(data)
        res = segment_drivable(rgb, mode=args.mode)
        mask_png = encode_mask_png(res.mask)
        cpu = time.thread_time() - c0
        samples.append({"cpu_s": cpu, "bytes_up": len(data), "bytes_down": len(mask_png)})
        print(f"\r{i + 1}/{len(files)} frames", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    report = measured_inputs_report(samples, profs, host_hz=hz, host_hz_source=hz_source, up_Bps=up, down_Bps=down)
    # decision latency: the policy runs once per frame on the robot
    task = Task(report["inputs"]["cycles"]["value"], report["inputs"]["bytes_up"]["value"],
                report["inputs"]["bytes_down"]["value"], 1.0)
    links = {"cloud": LinkEstimate(up, down), "leader": LinkEstimate(up, down)}
    lat = []
    for k in range(args.decisions):
        t0 = time.perf_counter()
        choose_placement(task, profs[k % len(profs)], reachable=("cloud", "leader"), links=links, dvs=bool(k % 2))
        lat.append((time.perf_counter() - t0) * 1e6)
    report["decision_us"] = {"median": _pct(lat, 50), "p99": _pct(lat, 99), "n": len(lat)}
    report["host"] = {"hz": hz, "source": hz_source, "note": "measured on a shared, busy machine"}
    report["mode"] = args.mode
    c, bu, bd = report["cpu_s"], report["bytes_up"], report["bytes_down"]
    print(f"{report['frames']} frames: pipeline CPU median {c['median'] * 1e3:.1f} ms (p99 {c['p99'] * 1e3:.1f}) "
          f"= {report['cycles']['median']:.3g} cycles at {hz / 1e9:.3g} GHz ({hz_source})")
    print(f"frame bytes median {bu['median']:.0f} (p99 {bu['p99']:.0f}); mask PNG median {bd['median']:.0f} B")
    print(f"links (assumed) up {up:.0f} B/s, down {down:.0f} B/s; placement decision median "
          f"{report['decision_us']['median']:.1f} us, p99 {report['decision_us']['p99']:.1f} us")
    print(f"{'profile':<10} {'E_proc J':>10} {'E_cloud J':>10} {'E_saved J':>10} {'local s':>8} {'remote s':>9}"
          f" {'break-even Mb/s':>16}  decision")
    for r in report["rows"]:
        be = f"{r['break_even_mbps']:.3f}" if r["break_even_mbps"] is not None else "never"
        print(f"{r['profile']:<10} {r['e_proc_j']:>10.4f} {r['e_cloud_j']:>10.4f} {r['e_saved_j']:>10.4f} "
              f"{r['local_s']:>8.4f} {r['remote_s']:>9.4f} {be:>16}  {r['decision']}")
    _write_json(args.json, report)
    return 0
