"""``scmr bench ...``: every benchmark target's parser (light: no heavy import).

Each target's code is in its own module of this package and is imported only
when that target runs (``scmr --help`` stays fast):

===========  ====================================  =================================
target       module                                measures
===========  ====================================  =================================
pipeline     :mod:`scmr_mesh.bench.pipeline`       per-stage ms of the vision pipeline
mesh         :mod:`scmr_mesh.bench.mesh`           capacity, ToR/RoR of fleets, cloud crashes, overload
scale        :mod:`scmr_mesh.bench.scale`          served/s against 1..8 cloud nodes, a node crash
scenario     :mod:`scmr_mesh.bench.scenario`       failover/failback of a scenario over N runs
energy       :mod:`scmr_mesh.bench.energy`         measured energy-model inputs
data         :mod:`scmr_mesh.bench.data`           queue, ODS, buffer, store round trip
overload     :mod:`scmr_mesh.bench.overload`       the negotiator against FIFO under overload
tls          :mod:`scmr_mesh.bench.tls`            the cost of authentication per query
viz          :mod:`scmr_mesh.bench.viz`            rerun logging per request
zenoh        :mod:`scmr_mesh.bench.zenoh`          the probes behind docs/ZENOH.md
r2r          :mod:`scmr_mesh.bench.r2r`            gossip discovery, succession after a crash
ros          :mod:`scmr_mesh.bench.ros`            what the ROS 2 bridge adds to the time to result
===========  ====================================  =================================
"""

from __future__ import annotations

import argparse
import importlib
from typing import Callable

from scmr_mesh import cliargs as ca


def _fleet_sizes(text: str) -> list[int]:
    """``"1,4,16"`` -> ``[1, 4, 16]`` (each >= 1)."""
    sizes = [int(x) for x in text.split(",") if x.strip()]
    if not sizes or min(sizes) < 1:
        raise ValueError("fleet sizes must be whole numbers >= 1")
    return sizes


def _outage(text: str) -> tuple[float, float]:
    from scmr_mesh.fleet.plan import parse_outage

    return parse_outage(text)


def _rate(text: str) -> float:
    from scmr_mesh.energy.commands import parse_rate

    return parse_rate(text)


def _frame_size(text: str) -> tuple[int, int]:
    """``"640x480"`` -> ``(640, 480)`` (each 1..16384)."""
    w, h = (int(v) for v in text.lower().split("x"))
    if not (0 < w <= 16384 and 0 < h <= 16384):
        raise ValueError("width and height must be 1..16384")
    return w, h


def _insecure_arg(p: argparse.ArgumentParser) -> None:
    """``--insecure`` for a bench that starts peers (secured by default, as ``scmr up``)."""
    p.add_argument("--insecure", action="store_true",
                   help="start the peers without authentication (default: a development CA and one certificate "
                        "per peer in the run folder, mutual TLS and the fleet's access rules, as scmr up does)")


#: Targets that run the real pipeline in the peers they start (the AOT warning applies to them).
PIPELINE_TARGETS = ("pipeline", "mesh", "scenario")


def _warn_if_jit() -> None:
    """Say so when the pipeline kernels were not compiled ahead of time (figures would be worse).

    Without the AOT module every peer pays numba's JIT: a cloud's start-up took 560-760 ms
    instead of 200-360 ms, and failover median 66 ms instead of 10 (a bench run from a checkout
    whose kernels had changed since its last ``make``).  Never stops a bench.
    """
    import sys

    try:
        from scmr_mesh.imaging import _aot

        st = _aot.status()
    except Exception as exc:  # a broken AOT module is a warning here too, not a failed bench
        st = f"jit (AOT status unreadable: {exc})"
    if st.startswith("jit"):
        print(f"scmr bench: WARNING: pipeline kernels are not compiled ahead of time here ({st}); peers start "
              "slower and each worker's first frame pays numba's JIT, so start-up and failover figures are worse "
              "than an installed copy's; run `make` (or python -m scmr_mesh.imaging._aot) first",
              file=sys.stderr, flush=True)


def _handler(module: str, func: str) -> Callable[[argparse.Namespace], int]:
    """A handler that imports ``scmr_mesh.bench.<module>`` only when the target runs."""

    def run(args: argparse.Namespace) -> int:
        from scmr_mesh.fleet.procs import signals_to_interrupt

        if module in PIPELINE_TARGETS:
            _warn_if_jit()
        target = getattr(importlib.import_module(f"scmr_mesh.bench.{module}"), func)
        # SIGTERM/SIGHUP as Ctrl-C: the benches' `finally` blocks stop the peers they started (a
        # SIGTERMed `bench r2r` left its leader and robots running, reparented to init)
        with signals_to_interrupt():
            return target(args)

    run.__name__ = f"{module}.{func}"
    return run


def register(bench: argparse._SubParsersAction) -> None:
    """Add every ``scmr bench`` target."""
    add_pipeline(bench)
    add_mesh(bench)
    add_scale(bench)
    add_scenario(bench)
    add_energy(bench)
    add_data(bench)
    add_ingest(bench)
    add_overload(bench)
    add_tls(bench)
    add_viz(bench)
    add_zenoh(bench)
    add_r2r(bench)
    add_multihop(bench)
    add_ros(bench)


def add_pipeline(bench: argparse._SubParsersAction) -> None:
    """``scmr bench pipeline``."""
    from scmr_mesh.imaging.commands import MODES

    p = bench.add_parser(
        "pipeline",
        help="per-stage median/p99 ms of the drivable-region pipeline",
        description=(
            "Time the pipeline on one core (sched_setaffinity, numba and OpenCV at 1 thread) after "
            "JIT warm-up.  'total' = 300x225 RGB array to mask.  A separate pass times decode_frame "
            "(bytes to the 300x225 frame) per encoding: each frame as PNG and as JPEG (quality 90), "
            "and decompression bombs as a service decodes them (a ~700-byte JPEG claiming 3840x2160, decoded at "
            "1/8 scale; one claiming 7000x7000, refused; a 28 KB PNG of zeros claiming 3840x2160, refused, and "
            "the largest PNG a service accepts, 1280x960, decoded in full).  Frames come from --images (PNG/JPEG folder) or "
            "built-in synthetic scenes."
        ),
    )
    p.add_argument("--frames", type=ca.count("frames", hi=10**6), default=300, help="frames to time (default: %(default)s)")
    p.add_argument("--images", type=ca.PathArg("in-dir", as_path=True, what="a folder of PNG/JPEG frames"), metavar="DIR", help="folder of PNG/JPEG frames (default: synthetic)")
    p.add_argument("--mode", choices=MODES, default="best", help="pipeline mode (default: %(default)s)")
    p.add_argument("--reference", action="store_true",
                   help="also time the C++ SRM of the dpm-srm package (grey input, same frames, same Q) and "
                        "report our total and SRM as ratios of it; installs nothing: needs "
                        "pip install 'scmr-mesh[bench]'")
    p.add_argument("--json", type=ca.PathArg("out-file", as_path=True), metavar="FILE", help="write the result as JSON here")
    p.set_defaults(func=_handler("pipeline", "cmd_bench_pipeline"))


def add_mesh(bench: argparse._SubParsersAction) -> None:
    """``scmr bench mesh``."""
    from scmr_mesh.fleet.commands import _add_fleet_args

    b = bench.add_parser(
        "mesh", help="service capacity, ToR/RoR of fleets, repeated cloud crashes (also under CPU hogs), overload",
        description=(
            "Measure the cloud service's capacity (a closed loop of requests against one `scmr cloud` "
            "running the real pipeline: frames/s, and frames per CPU-second of the service = frames/s per "
            "core), the cloud's ingress (--ingress-seconds: served frames/s before the first busy answer over "
            "the workers' closed-loop capacity, on a fixed-time stub), run fleets of each size in --robots (no faults; ToR of all requests and of those a "
            "cloud or leader admitted, the busy answers, the hedge rate, and where the fleet's CPU went: CPU ms "
            "per request of the cloud nodes, the leader, the routers and the robots, each peer's process group "
            "sampled from /proc over the run, and the share of the host's cores the fleet used), then "
            "--crash-runs fleet runs of "
            "--crash-robots with the cloud SIGKILLed and restarted (median and max of the failover and "
            "failback gaps, with restart->ready and ready->first answer), then the same under --hogs busy "
            "CPU processes (stress-ng --cpu N when installed), and write JSON.  Targets: ToR p50 <= 15 ms "
            "and p99 <= 50 ms with 4 robots at 5 Hz; admitted ToR p99 <= 100 ms in every fleet; RoR 1.0 "
            "through the crashes; failover median <= 20 ms; failback max <= 500 ms; under the hogs both "
            "<= 1 s.  Run one benchmark at a time and note the machine's load."
        ),
    )
    b.add_argument("--robots", type=ca.parsed(_fleet_sizes, what="comma-separated fleet sizes >= 1", example="1,4", keep_text=True), default="1,4,16", metavar="LIST",
                   help="comma-separated fleet sizes (default: %(default)s)")
    _add_fleet_args(b)
    b.add_argument("--capacity-seconds", type=ca.non_negative("seconds", hi=3600), default=10.0, metavar="S",
                   help="length of the capacity measurement (0 skips it; default: %(default)s)")
    b.add_argument("--ingress-seconds", type=ca.non_negative("seconds", hi=600), default=3.0, metavar="S",
                   help="length of each step of the ingress ramp (0 skips it; default: %(default)s): one cloud "
                        "whose workers run a fixed-time stub (no CPU), its workers' closed-loop capacity, then "
                        "requests at 0.5-1.1 of it; reports served_at_first_busy_ratio (served frames/s before "
                        "the first busy answer over that capacity, target >= 0.85) and the cloud's CPU per "
                        "request by thread (issue 23 item 2)")
    b.add_argument("--ingress-workers", type=ca.count("worker processes", hi=256, example="8"), default=8, metavar="N",
                   help="workers of the ingress run's cloud (default: %(default)s)")
    b.add_argument("--ingress-service-ms", type=ca.positive("milliseconds", hi=10000, example="20"), default=20.0,
                   metavar="MS", help="the ingress run's stub time per frame (default: %(default)s; capacity "
                                      "about N x 1000 / MS frames/s)")
    b.add_argument("--crash-robots", type=ca.count("robots", lo=0, hi=1000), default=4, metavar="N",
                   help="robots in each crash run (0 skips them; default: %(default)s)")
    b.add_argument("--crash-runs", type=ca.count("runs", lo=0, hi=1000), default=10, metavar="N",
                   help="crash runs, each one fleet run with one cloud crash (default: %(default)s)")
    b.add_argument("--crash-duration", type=ca.positive("seconds", hi=604800), default=8.0, metavar="S",
                   help="length of each crash run (default: %(default)s)")
    b.add_argument("--crash-outage", type=ca.parsed(_outage, what="START:END seconds with 0 <= START < END", example="3:5", positive=False, keep_text=True), default="3:5", metavar="START:END",
                   help="cloud SIGKILL and restart in each crash run, s (default: %(default)s; the run "
                        "goes on after END so the restarted cloud's first answer is seen)")
    b.add_argument("--hogs", type=ca.count("CPU hogs", lo=0, hi=64), default=2, metavar="N",
                   help="repeat the crash runs under N busy CPU processes (0 skips; default: %(default)s)")
    b.add_argument("--overload-robots", type=ca.count("robots", lo=0, hi=1000), default=8, metavar="N",
                   help="robots in the overload run (0 skips it; default: %(default)s): a cloud with a "
                        "40 ms service and 1 worker (~25 requests/s) against N robots at --overload-rate, "
                        "once with the priority negotiator (--queue 2) and once FIFO; see `scmr bench overload`")
    b.add_argument("--overload-rate", type=ca.positive("frames per second", hi=10000), default=10.0, metavar="HZ",
                   help="frames/s per robot in the overload run (default: %(default)s)")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", required=True, help="where to write the results")
    b.add_argument("--run-dir", type=ca.PathArg("out-dir", as_path=True), metavar="DIR", help="parent of the runs' directories")
    b.set_defaults(func=_handler("mesh", "cmd_bench_mesh"))


def add_scale(bench: argparse._SubParsersAction) -> None:
    """``scmr bench scale``."""
    b = bench.add_parser(
        "scale", help="served/s of 32 robots against 1, 2, 4 (8) cloud nodes on a shared PostgreSQL store",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Run a fleet of --robots robots against N = 1, 2, 4 (and 8 without --quick) cloud nodes that "
            "share a PostgreSQL data store, then a crash run (4 nodes, cloud0 SIGKILLed halfway and left "
            "down), and write {\"ods_backend\", \"served_per_s\": {\"1\": ...}, \"efficiency\": "
            "{\"2\": ...}, \"crash\": {\"ror\", \"telemetry\": {\"sent\", \"stored\", \"lost\"}}, ...}.\n\n"
            "The nodes run a fixed service time (--service-ms, sleeping, no CPU work) on --workers worker "
            "processes, so a node serves at most workers/service requests/s and the tier N times that; "
            "robots send as fast as answers come (one request in flight each), nodes queue up to 64 "
            "requests instead of answering busy, deadlines are 10 s and local fallback is off, so the "
            "cloud tier, not the robots' pacing or admission, limits served/s. efficiency(N) = "
            "served/s(N) / (N x served/s(1)). Targets: efficiency >= 0.85 at 4 nodes, RoR 1.0 and no "
            "telemetry lost in the crash run; exit 1 when one is missed. On one 2-core host the robots, "
            "nodes and database share the cores: see docs/DEPLOY.md for what the figures do and do not show."
        ),
    )
    b.add_argument("--quick", action="store_true",
                   help="N = 1, 2, 4 and 14 s per run (about 2 minutes) instead of N = 1, 2, 4, 8 and 30 s")
    b.add_argument("--robots", type=ca.count("robots", hi=1000), default=32, metavar="N", help="robots (default: %(default)s)")
    b.add_argument("--workers", type=ca.count("workers", hi=256), default=2, metavar="W",
                   help="worker processes per cloud node (default: %(default)s)")
    b.add_argument("--service-ms", type=ca.positive("milliseconds", hi=3600000), default=200.0, metavar="MS",
                   help="fixed service time per request (default: %(default)s; ignored with --pipeline)")
    b.add_argument("--pipeline", action="store_true",
                   help="the nodes run the real pipeline on synthetic scenes instead of the sleeping stub; "
                        "the ideal at N nodes is N x the 1-node rate of the same run (needs N x W free cores "
                        "beside the robots')")
    b.add_argument("--duration", type=ca.positive("seconds", hi=604800), default=None, metavar="S",
                   help="seconds each fleet runs (default: 14 with --quick, else 30)")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", required=True, help="where to write the results")
    b.add_argument("--run-dir", type=ca.PathArg("out-dir", as_path=True), metavar="DIR", help="parent of the runs' directories")
    _insecure_arg(b)
    b.set_defaults(func=_handler("scale", "cmd_bench_scale"))


def add_scenario(bench: argparse._SubParsersAction) -> None:
    """``scmr bench scenario``."""
    from scmr_mesh.scenario.commands import _override_args

    bs = bench.add_parser("scenario", help="failover/failback gaps of a scenario over N runs (median, p99)",
                          description="Run a scenario N times (default peers/scenarios/cloud-link-drop.toml) and "
                          "print JSON with the median, p99 and max of the per-robot failover gaps, the failback "
                          "gaps and ToR, and the RoR of each run.")
    bs.add_argument("file", type=ca.PathArg("in-file", what="a scenario TOML file", example="peers/scenarios/cloud-crash.toml"), nargs="?", default="peers/scenarios/cloud-link-drop.toml", help="scenario TOML file")
    bs.add_argument("--runs", type=ca.count("runs", hi=1000), default=3, help="number of runs (default 3)")
    bs.add_argument("--backend", choices=["auto", "netns", "proxy", "loopback"], default="auto", help="as for scenario run")
    bs.add_argument("--out", type=ca.PathArg("out-dir"), metavar="DIR", help="run folders go here (default runs/bench-scenario-...)")
    bs.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the JSON here")
    bs.add_argument("--data", metavar="DIR", type=ca.PathArg("in-dir", as_path=True), default=None, help="image folder (as for scenario run)")
    bs.add_argument("--ready-timeout", type=ca.positive("seconds", hi=86400), default=120.0, metavar="S", help="peer start timeout (s)")
    _override_args(bs)
    bs.set_defaults(func=_handler("scenario", "cmd_bench_scenario"))


def add_energy(bench: argparse._SubParsersAction) -> None:
    """``scmr bench energy``."""
    from scmr_mesh.energy import commands as energy_commands
    from scmr_mesh.energy.commands import _common

    fmt = argparse.RawDescriptionHelpFormatter
    b = bench.add_parser(
        "energy",
        help="measured energy-model inputs on real frames (C, D) and placement decision latency",
        description=(
            "Run the drivable-region pipeline on the frames of --data and measure, per frame, its "
            "thread CPU time (C = CPU time x host clock), the encoded frame size (D_up) and the mask "
            "PNG size (D_down); report medians/p99 and, per profile, E_proc, E_cloud, E_saved and the "
            "break-even bandwidth at the median frame, plus the median/p99 time of one placement "
            "decision.  Link rates and powers are assumed and marked so."
        ),
        epilog=energy_commands.__doc__.split("\n\n", 1)[1],
        formatter_class=fmt,
    )
    b.add_argument("--data", type=ca.PathArg("in-dir"), required=True, metavar="DIR",
                   help="roads folder with manifest.json (read in place) or a folder of PNG/JPEG frames")
    b.add_argument("--count", type=ca.count("frames", hi=10**6), default=None, help="frames to run (default: each file once)")
    b.add_argument("--mode", choices=("best", "thesis"), default="best", help="pipeline mode (default best)")
    b.add_argument("--profile", metavar="NAMES", help="comma-separated profile names (default: all)")
    b.add_argument("--bandwidth-up", type=ca.parsed(_rate, what="a rate such as 23Mb/s", example="23Mb/s", keep_text=True), default="23Mb/s", help="assumed upload rate (default 23Mb/s, Eq 4.9)")
    b.add_argument("--bandwidth-down", type=ca.parsed(_rate, what="a rate such as 28Mb/s", example="28Mb/s", keep_text=True), default="28Mb/s", help="assumed download rate (default 28Mb/s, Eq 4.9)")
    b.add_argument("--decisions", type=ca.count("decisions", hi=10**7), default=5000, help="placement decisions to time (default 5000)")
    _common(b, json_help="write the report to FILE")
    b.set_defaults(func=_handler("energy", "cmd_bench_energy"))


def add_data(bench: argparse._SubParsersAction) -> None:
    """``scmr bench data``."""
    b = bench.add_parser("data", help="data tier: queue appends, ODS inserts, buffer sync, store round trip",
                         description="Measure the data tier in one run: on-disk queue append latency per "
                         "fsync policy, ODS insert latency (batch 1 and 64, and a batch of duplicates), "
                         "buffer delta+merge, the telemetry store round trip over Zenoh (query -> "
                         "ODS commit -> ack, two sessions on loopback), and how fast a robot's backlog "
                         "of 10*N queued records drains to the cloud after an outage.  Prints JSON "
                         "with medians and p99s.")
    b.add_argument("--n", type=ca.count("samples", hi=10**6), default=200, help="samples per figure (default 200)")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the JSON here")
    b.add_argument("--no-mesh", action="store_true", help="skip the Zenoh round trip")
    b.add_argument("--quiet", action="store_true", help="no progress on stderr")
    b.set_defaults(func=_handler("data", "cmd_bench_data"))


def _rates(text: str) -> list[float]:
    """``"10,100,0"`` -> batches per second (0 = as fast as the sender can)."""
    import math

    out = [float(x) for x in text.split(",") if x.strip()]
    if not out or any(not math.isfinite(x) or x < 0 or x > 100000 for x in out):
        raise ValueError("rates must be batches per second in 0..100000 (0: unpaced)")
    return out


def add_ingest(bench: argparse._SubParsersAction) -> None:
    """``scmr bench ingest``."""
    b = bench.add_parser(
        "ingest", help="a cloud's peak RSS under a telemetry flood at any rate (bounded ingest)",
        description="Flood a real cloud (stub pipeline, its own ODS) with telemetry batches from a stranger's "
                    "session at each rate for --duration s, a fresh cloud per case; report the answers (ok, "
                    "busy, refused, zenoh's timeout, none, and the link drops seen) and the cloud's RSS at the start "
                    "and its peak (VmHWM); it exits 1 when the cloud died or a query had no answer at all (the "
                    "case folders are then kept).  With "
                    "--unbounded every case also runs with the bounds lifted (the behaviour before them), "
                    "for the ratio.  docs/DATA.md has the figures.")
    b.add_argument("--rates", default="10,100,1000,0", metavar="LIST",
                   type=ca.parsed(_rates, what="batches per second, comma-separated (0: unpaced)", example="10,100,0",
                                  positive=False, keep_text=True),
                   help="batches per second, comma-separated; 0 = as fast as possible (default %(default)s)")
    b.add_argument("--records", default="200,1000", metavar="LIST",
                   type=ca.parsed(_fleet_sizes, what="records per batch, comma-separated", example="200,1000",
                                  keep_text=True),
                   help="records per batch, comma-separated (default %(default)s; the cloud takes at most 256)")
    b.add_argument("--duration", type=ca.positive("seconds", hi=3600, example="5"), default=5.0, metavar="S",
                   help="seconds of flood per case (default %(default)s)")
    b.add_argument("--unbounded", action="store_true", help="also run each case with the bounds lifted")
    b.add_argument("--lease-ms", type=ca.count("milliseconds", lo=10, hi=3600000, example="5000"), default=None,
                   metavar="MS", help="the cloud's and the flooder's zenoh lease (default: scmr's, 500); a cloud "
                                      "stalled past it loses its link and the queries in flight on it")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the results here")
    b.add_argument("--quiet", action="store_true", help="no progress on stderr")
    _insecure_arg(b)
    b.set_defaults(func=_handler("ingest", "cmd_bench_ingest"))


def add_overload(bench: argparse._SubParsersAction) -> None:
    """``scmr bench overload``."""

    b = bench.add_parser(
        "overload",
        help="overload a cloud: served/busy counts, ToR of admitted requests, fairness, peak RSS",
        description=(
            "Start a cloud and more robots at a higher rate than it can serve, once with the "
            "priority negotiator (--queue) and once with the default FIFO admission.  Reports "
            "served and rejected ('busy') counts, ToR of admitted requests (p50/p99), time to a busy "
            "answer, served share per priority class, Jain's fairness index across robots, and the "
            "cloud's peak RSS.  Progress on stderr; JSON with --json."
        ),
    )
    _add_overload_arguments(b)
    _insecure_arg(b)
    b.set_defaults(func=_handler("overload", "run_overload_cli"))


def _add_overload_arguments(p) -> None:
    """Flags of ``scmr bench overload``."""
    p.add_argument("--robots", type=ca.count("robots", hi=1000), default=8, metavar="N", help="robot processes (default 8)")
    p.add_argument("--rate", type=ca.positive("frames per second", hi=10000), default=10.0, metavar="HZ", help="frames/s per robot (default 10)")
    p.add_argument("--duration", type=ca.positive("seconds", hi=604800), default=10.0, metavar="S", help="seconds per run (default 10)")
    p.add_argument("--workers", type=ca.count("workers", hi=256), default=1, metavar="N", help="cloud worker processes (default 1)")
    p.add_argument("--service-ms", type=ca.non_negative("milliseconds", hi=3600000, example="40"), default=40.0, metavar="MS",
                   help="fixed service time per frame (slow_process stub); 0 = the real pipeline (default 40)")
    p.add_argument("--queue", type=ca.count("waiting requests", lo=0, hi=100000), default=2, metavar="Q", help="negotiator queue size (default 2)")
    p.add_argument("--per-robot", type=ca.count("requests", hi=100000), default=None, metavar="N", help="negotiator per-robot quota")
    p.add_argument("--levels", type=ca.count("priority levels", hi=1000), default=2, metavar="L",
                   help="priority classes: robot k pays 10 * (k mod L) (default 2)")
    p.add_argument("--policies", default="negotiator,fifo", metavar="LIST",
                   help="runs to make, in order (default negotiator,fifo)")
    p.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="write the results here")
    p.add_argument("--run-dir", type=ca.PathArg("out-dir", as_path=True), metavar="DIR", help="keep logs and records here (default: a temp dir)")


def add_tls(bench: argparse._SubParsersAction) -> None:
    """``scmr bench tls``."""
    t = bench.add_parser(
        "tls",
        help="query round trip with no security, usrpwd, mutual TLS and TLS+ACL",
        description=(
            "Measure the cost of authentication: median and p99 round trip of a query carrying "
            "--payload bytes between two zenoh sessions on loopback (shared memory off), with no "
            "security, usrpwd, mutual TLS, and mutual TLS with the fleet ACL; then whole fleets as "
            "`scmr up` runs them (cloud, leader, --fleet-robots robots sending synthetic JPEG frames at "
            "5 Hz to the stub service, so the transport is what is measured), secured (the default) and "
            "--insecure, alternately, --fleet-runs times each: ToR median/p99, RoR and start-up time."
        ),
    )
    t.add_argument("--fleet-runs", type=ca.count("runs", lo=0, hi=100, example="2"), default=2, metavar="N",
                   help="fleet runs per mode (default 2; 0 skips the fleets)")
    t.add_argument("--fleet-robots", type=ca.count("robots", hi=64, example="4"), default=4, metavar="N",
                   help="robots per fleet run (default 4)")
    t.add_argument("--fleet-duration", type=ca.positive("seconds", hi=3600, example="10"), default=10.0, metavar="S",
                   help="seconds each fleet run sends frames (default 10)")
    t.add_argument("--payload", type=ca.count("bytes", hi=1 << 30), default=200_000, metavar="BYTES", help="query payload (default 200000)")
    t.add_argument("--queries", type=ca.count("queries", hi=10**6), default=300, metavar="N", help="timed queries per kind (default 300)")
    t.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="write the results here")
    t.set_defaults(func=_handler("tls", "cmd_bench_tls"))


def add_viz(bench: argparse._SubParsersAction) -> None:
    """``scmr bench viz``."""
    b = bench.add_parser(
        "viz",
        help="cost of rerun logging per robot request (median/p99 ms, bytes per frame)",
        description=(
            "Time RobotViz.observe() on the caller's thread (it only queues; a background "
            "thread encodes the camera JPEG and logs map and scalars in batches) into a "
            "--save sink started as in a fleet run, the process's CPU per frame (caller, "
            "logger thread and rerun's own threads), and the sink's start and finalise "
            "times.  Synthetic frames; reports medians and p99s measured in one run."
        ),
    )
    b.add_argument("--frames", type=ca.count("requests", hi=10**6), default=200, help="requests to log (default: %(default)s)")
    b.add_argument("--size", type=ca.parsed(_frame_size, what="WIDTHxHEIGHT in pixels", example="640x480", keep_text=True), default="640x480", help="camera frame WxH (default: %(default)s)")
    b.add_argument("--interval", type=ca.non_negative("seconds", hi=60), default=0.0, metavar="S",
                   help="seconds between requests (default 0: back to back; 0.2 is a robot at 5 Hz)")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the results as JSON")
    b.set_defaults(func=_handler("viz", "cmd_bench_viz"))


def add_zenoh(bench: argparse._SubParsersAction) -> None:
    """``scmr bench zenoh``."""
    b = bench.add_parser(
        "zenoh", help="zenoh/mesh probes: loss detection, false expiries, reconnect, failover, redundancy",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run one probe of scmr_mesh/bench/probe.py (real processes on loopback; the "
                    "figures in docs/ZENOH.md come from these).  PROBE is one of: detect, stress, "
                    "reconnect, failover, redundant, latency, routers (root).  Options after PROBE "
                    "go to the probe; `scmr bench zenoh PROBE -h` lists them.",
        epilog="example: scmr bench zenoh failover --repeat 3 --json failover.json")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the measurements as a JSON list")
    b.add_argument("probe", choices=("detect", "stress", "reconnect", "failover", "redundant", "latency", "routers"))
    b.add_argument("probe_args", nargs=argparse.REMAINDER, help="options of the probe")
    b.set_defaults(func=_handler("zenoh", "cmd_bench_zenoh"))


def add_multihop(bench: argparse._SubParsersAction) -> None:
    """``scmr bench multihop``."""
    b = bench.add_parser(
        "multihop", help="zenoh routers as multi-hop relays: ToR per hop, reroute after a relay crash",
        description="Real `scmr router` processes on loopback, each handed only its neighbours: (1) a chain "
                    "of 0..--max-hops router-to-router links between a queryable and a querier: ToR median per "
                    "hop count and the cost per hop; (2) a diamond (portal - A - far, portal - B - far): one "
                    "relay SIGKILLed per run, ms from the kill to the first answer over the other relay.  One "
                    "benchmark at a time (docs/R2R.md, Multi-hop).")
    b.add_argument("--max-hops", type=ca.count("hops", lo=1, hi=16, example="5"), default=5, metavar="N",
                   help="longest chain in router-to-router hops (default 5)")
    b.add_argument("--queries", type=ca.count("queries", hi=100000, example="200"), default=200, metavar="N",
                   help="queries per chain length (default 200)")
    b.add_argument("--runs", type=ca.count("runs", lo=0, hi=1000, example="6"), default=6, metavar="N",
                   help="diamond runs, killing relay A and B alternately (default 6; 0: chain only)")
    b.add_argument("--silent-runs", type=ca.count("runs", lo=0, hi=1000, example="4"), default=0, metavar="N",
                   help="(root) diamond runs in network namespaces where a relay goes silent (blackhole routes, "
                        "no FIN/RST) instead of crashing (default 0)")
    b.add_argument("--period-ms", type=ca.positive("milliseconds", hi=10000, example="10"), default=10.0,
                   metavar="MS", help="query period during the diamond runs (default 10)")
    b.add_argument("--lease-ms", type=ca.count("milliseconds", lo=10, hi=600000, example="500"), default=500,
                   metavar="MS", help="zenoh lease of the routers (default 500)")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the JSON here")
    b.set_defaults(func=_handler("multihop", "cmd_bench_multihop"))


def add_r2r(bench: argparse._SubParsersAction) -> None:
    """``scmr bench r2r``."""
    b = bench.add_parser(
        "r2r", help="R2R tier: gossip discovery from one bootstrap, succession after a leader crash",
        description="Measure, over --repeat runs on loopback: (1) discovery: robots handed a single bootstrap "
                    "in a chain; ms from zenoh.open to seeing the leader's token and to a direct link to every "
                    "peer; (2) succession: a dedicated leader, two leader-capable robots and a robot (real "
                    "processes, stub processing); the leader is SIGKILLed; ms to the new leader's claim and to "
                    "the robot's first answer from it.  Medians, p99 and max measured in one run (docs/R2R.md).")
    b.add_argument("--repeat", type=ca.count("runs", hi=1000, example="5"), default=5, metavar="N",
                   help="runs of each measurement (default 5)")
    b.add_argument("--robots", type=ca.count("robots", hi=64, example="4"), default=4, metavar="N",
                   help="robots in the discovery chain (default 4)")
    b.add_argument("--lease-ms", type=ca.count("milliseconds", lo=10, hi=600000, example="500"), default=500,
                   metavar="MS", help="zenoh lease (default 500)")
    b.add_argument("--no-crash", action="store_true", help="only the discovery measurement")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the JSON here")
    _insecure_arg(b)
    b.set_defaults(func=_handler("r2r", "cmd_bench_r2r"))


def add_ros(bench: argparse._SubParsersAction) -> None:
    """``scmr bench ros``."""
    b = bench.add_parser(
        "ros", help="ROS 2 bridge: ms `scmr ros` adds to a frame's time to result (paired per frame)",
        description="Real processes on loopback: `scmr router` playing rmw_zenohd (its gossip and routing keys), a "
                    "cloud, N `scmr ros` bridges; this process, a peer configured as an rmw_zenoh node is, "
                    "publishes sensor_msgs/Image rgb8 frames as a ROS node would and times each "
                    "frame from put to its mask (e2e), against the bridge's own record of the same frame (the "
                    "`scmr robot` request path: tor).  overhead = e2e - tor, median/p95/p99; ros_out (the mask's "
                    "hop back, which any rmw_zenoh node pays) and the bridges' own time outside their ToR "
                    "(bridge_ms); floor: the same frames to an echo node (a peer like the publisher) that "
                    "answers at once (the ROS-side transport alone); floor_router: the same with both ends "
                    "clients, through the router.  Alternating with the bridges' frames (--rounds blocks each), "
                    "N `scmr robot` processes send the same frames (JPEG 90, full size) to "
                    "the same cloud: robot_tor, and added_vs_robot = the median over rounds of (a round's median "
                    "e2e - the median ToR of its robot block), the issue's target (docs/BENCHMARKS.md).  Exit 1 when a mask or a floor echo never arrived "
                    "(counted in the JSON and on the console).")
    b.add_argument("--robots", type=ca.count("robots", hi=64, example="4"), default=4, metavar="N",
                   help="bridges, each with its own camera topic (default 4)")
    b.add_argument("--rate", type=ca.positive("frames per second", hi=1000, example="5"), default=5.0, metavar="HZ",
                   help="frames per second per robot (default 5)")
    b.add_argument("--duration", type=ca.positive("seconds", hi=3600, example="10"), default=10.0, metavar="S",
                   help="seconds of frames per round (default 10)")
    b.add_argument("--rounds", type=ca.count("rounds", hi=100, example="3"), default=3, metavar="R",
                   help="rounds of a bridge block and an `scmr robot` block, alternating B R, R B, ... (default 3); "
                        "added_vs_robot is the median of the rounds' paired differences; from 6 rounds the "
                        "median gets a 95 %% distribution-free interval and the <= 2 ms target a verdict "
                        "(met, not met or undecided), printed last")
    b.add_argument("--size", type=ca.parsed(_frame_size, what="WIDTHxHEIGHT in pixels", example="640x480"),
                   default="640x480", help="camera frame WxH (default: %(default)s)")
    b.add_argument("--process", default=None, metavar="MODULE:FUNC",
                   help="the cloud's process function (default: the stub, scmr_mesh.mesh.testing:stub_process; "
                        "the overhead is paired per frame, so the pipeline's own time cancels out)")
    b.add_argument("--robot-baseline", action=argparse.BooleanOptionalAction, default=True,
                   help="in each round, time the same frames from `scmr robot` processes (default on)")
    b.add_argument("--ros-mode", choices=("auto", "peer", "client"), default="auto",
                   help="the bridges' --ros-mode (default auto: peer, as the router is on loopback; client: "
                        "every frame and mask through the router, as `scmr ros` was before --ros-mode)")
    b.add_argument("--compressed", action="store_true",
                   help="the cameras publish sensor_msgs/CompressedImage (JPEG 90 of the same scenes, the bytes "
                        "`scmr robot` sends) and the bridges run --compressed")
    b.add_argument("--ros-cfg", action="append", default=[], metavar="KEY:JSON5",
                   help="zenoh setting of the whole ROS side (the cameras, the echo node and the bridges' "
                        "--ros-cfg), e.g. transport/shared_memory/enabled:true for ROS nodes with shared memory on")
    b.add_argument("--floor-router", action=argparse.BooleanOptionalAction, default=True,
                   help="also time the floor with both ends clients of the router (floor_router; default on)")
    b.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the JSON here")
    b.set_defaults(func=_handler("ros", "cmd_bench_ros"))
