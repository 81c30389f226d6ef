"""``scmr up``: a whole fleet on loopback (the CLI side of :mod:`scmr_mesh.fleet`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from scmr_mesh import cliargs as ca
from scmr_mesh.data.retention import DEFAULT_KEEP_MASKS
from scmr_mesh.fleet.output import check_fleet, format_summary, run_with_output
from scmr_mesh.fleet.plan import ODS_BACKENDS, TABLE_4_3_ROBOTS, FleetConfig, parse_kill, parse_outage


def _outage(text: str) -> tuple[float, float]:
    return parse_outage(text)


def _add_fleet_args(p: argparse.ArgumentParser, *, robots_default: int = 4) -> None:
    p.add_argument("--duration", type=ca.positive("seconds", hi=604800, example="10"), default=10.0, metavar="S",
                   help="seconds each robot sends frames (default: %(default)s)")
    p.add_argument("--rate", type=ca.positive("frames per second", hi=10000, example="5"), default=5.0, metavar="HZ",
                   help="frames per second per robot (default: %(default)s)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--images", type=ca.PathArg("in-dir", as_path=True, what="a folder of images"), metavar="DIR", help="a folder of images the robots send")
    src.add_argument("--synthetic", metavar="KINDS",
                     help="comma-separated synthetic scene kinds dealt to the robots (default: all kinds)")
    p.add_argument("--workers", type=ca.count("workers", hi=256), metavar="N", help="worker processes of cloud and leader")
    p.add_argument("--lease-ms", type=ca.count("milliseconds", lo=10, hi=3600000, example="500"), metavar="MS", help="zenoh lease of every peer")
    p.add_argument("--deadline-ms", type=ca.count("milliseconds", hi=3600000, example="1000"), metavar="MS", help="robots' per-request deadline")
    p.add_argument("--ready-timeout", type=ca.positive("seconds", hi=86400, example="90"), default=90.0, metavar="S",
                   help="seconds a peer may take to start (default: %(default)s)")
    p.add_argument("--server-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for cloud and leader (repeatable, e.g. --server-arg=--process "
                        "--server-arg=scmr_mesh.mesh.testing:stub_process)")
    p.add_argument("--robot-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for every robot (repeatable)")
    p.add_argument("--keep-all", action="store_true",
                   help="every robot keeps every mask in RUN/robots/<id>/inbox (by default each keeps the newest "
                        f"{DEFAULT_KEEP_MASKS}, so a long run's folders stay bounded; scmr robot --keep-masks N sets another "
                        "bound, e.g. --robot-arg=--keep-masks=100)")
    p.add_argument("--mcap", type=ca.PathArg("out-file"), metavar="FILE", default=None,
                   help="write every robot's frames (CompressedImage) and masks (Image mono8) to FILE.mcap, which "
                        "ROS 2 tools and Foxglove open (topics /ROBOT/camera/compressed, /ROBOT/drivable/mask; "
                        "docs/ROS2.md)")
    p.add_argument("--profiles", nargs="?", const=",".join(TABLE_4_3_ROBOTS), default=None, metavar="NAMES",
                   type=ca.parsed(_profile_list, what="comma-separated Table 4.3 profile names (or the flag alone "
                                  "for robot1..robot4)", example="robot1,robot4"),
                   help="deal energy profiles to the robots round-robin (default list: Table 4.3's "
                        "robot1,robot2,robot3,robot4) and turn on energy placement: each robot's energy model "
                        "(Eq 4.2-4.6) chooses per frame where it runs; the summary shows energy per robot and "
                        "where each task ran.  Without it robots offload every frame (cloud, then leader, "
                        "then peers, then local) and no energy is modelled")
    p.add_argument("--insecure", action="store_true",
                   help="run every peer without authentication (to measure what security costs); by default "
                        "the run makes a development CA and one certificate per peer in RUN/certs and every "
                        "peer runs mutual TLS with the fleet's access rules (docs/SECURITY.md)")
    g = p.add_argument_group("R2R tier (docs/R2R.md)")
    g.add_argument("--leader-capable", type=ca.count("robots", lo=0, hi=10000, example="2"), default=None, metavar="N",
                   help="the first N robots run for the lead besides the dedicated leader, and serve other "
                        "robots while they do not lead (default: 2, or every robot of a smaller fleet)")
    g.add_argument("--bootstrap", default="cloud", metavar="PEER",
                   help="the one peer every robot is handed to connect to (cloud or leader); gossip scouting "
                        "finds the rest (default: %(default)s)")
    g.add_argument("--shape", choices=("auto", "clique", "routers"), default="auto",
                   help="how the peers link: clique, every peer a zenoh peer linked to every other (links "
                        "grow with N^2); routers, one zenoh router for this host and every peer its client "
                        "(links grow with N); auto (default): clique up to 32 robots, routers above, where "
                        "the clique was measured to break (docs/BENCHMARKS.md 'One host, many robots')")
    g.add_argument("--robots-per-process", type=ca.count("robots per process", hi=256, example="16"), default=None,
                   metavar="K",
                   help="play K robots per process with `scmr swarm` (a load generator: each robot keeps its "
                        "own identity, certificate, session and records, they share one interpreter).  Robots "
                        "named by a fault and leader-capable robots keep their own process.  Default: 1 for "
                        "scmr up (a process per robot, as on real robots); scmr bench mesh plays robots 16 "
                        "to a process above 16 robots")


def _profile_list(text: str) -> tuple[str, ...]:
    from scmr_mesh.energy import PROFILES

    names = tuple(n.strip() for n in str(text).split(",") if n.strip())
    bad = [n for n in names if n not in PROFILES] or ([] if names else [text])
    if bad:
        raise ValueError(f"unknown profile {bad[0]!r} (Table 4.3 has {', '.join(PROFILES)})")
    return names


def _config_from_args(args: argparse.Namespace, robots: int, run_dir: Path | None) -> FleetConfig:
    kinds = [k for k in (args.synthetic or "").split(",") if k]
    return FleetConfig(
        robots=robots, clouds=getattr(args, "clouds", 1), ods_backend=getattr(args, "ods_backend", "auto"),
        ods=getattr(args, "ods", None), duration_s=args.duration, rate_hz=args.rate,
        cloud_outage=parse_outage(args.cloud_outage) if getattr(args, "cloud_outage", None) else None,
        kill_cloud=parse_kill(args.kill_cloud) if getattr(args, "kill_cloud", None) else None,
        images=args.images, synthetic=kinds, run_dir=run_dir, workers=args.workers,
        lease_ms=args.lease_ms, deadline_ms=args.deadline_ms, ready_timeout_s=args.ready_timeout,
        server_args=tuple(args.server_arg),
        robot_args=tuple(args.robot_arg) + (("--keep-all",) if getattr(args, "keep_all", False) else ()),
        rerun=_rerun_options(args), leader_capable=args.leader_capable, bootstrap=args.bootstrap,
        leader_crash_s=getattr(args, "leader_crash", None), profiles=getattr(args, "profiles", None) or (),
        insecure=args.insecure, shape=getattr(args, "shape", "auto"), mcap=getattr(args, "mcap", None),
        robots_per_process=getattr(args, "robots_per_process", None) or 1,
    )


def _rerun_options(args: argparse.Namespace):
    """RerunOptions from --save/--spawn/--serve/--connect, or None (scmr_mesh.viz)."""
    from scmr_mesh.viz import RerunOptions

    return RerunOptions.from_args(args)


UP_EPILOG = """\
Exit status: 0 when every request was answered (RoR >= --min-ror, default 1.0)
and nothing else went wrong; 1 when fewer were, when telemetry was lost or
could not be counted, when a restarted peer never became ready or a peer
exited with an error, when the run's PostgreSQL died (it is restarted; the
report's ods.outages has the gap), or when a peer failed to start (the error names each
problem; the report is still written); 130 on Ctrl-C (report written,
"interrupted": true).  The summary always prints the telemetry line (sent,
stored, duplicates, lost, and queued: records still on a robot's disk when it
stopped after its drain phase, sent at its next start, never counted lost).

Example:
  scmr up --robots 4 --duration 20 --cloud-outage 8:14 --json report.json
  scmr up --robots 4 --profiles --duration 20     # Table 4.3 profiles, energy placement
  scmr up --robots 8 --clouds 2 --duration 20
"""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``scmr up``."""
    p = sub.add_parser(
        "up", help="cloud(s), leader and N robots on loopback, with an optional cloud outage",
        description=(
            "Start one or more cloud nodes, a leader and N robots as separate processes on loopback, "
            "show live progress on stderr, optionally SIGKILL the cloud tier at START and restart it at END, stop "
            "everything cleanly at the end or on Ctrl-C, and write a report (ToR percentiles, RoR, "
            "tiers, failover/failback gaps). Logs, records and masks go to the run directory."
        ),
        epilog=UP_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=ca.count("robots", hi=1000, example="4"), default=4, metavar="N", help="robots (default: %(default)s)")
    p.add_argument("--clouds", type=ca.count("cloud nodes", hi=64, example="2"), default=1, metavar="N",
                   help="cloud nodes cloud0..cloud<N-1>; robots spread frames over them by load "
                        "(default: %(default)s)")
    p.add_argument("--ods-backend", choices=ODS_BACKENDS, default="auto",
                   help="the cloud nodes' data store: auto = SQLite (RUN/ods.sqlite) for one cloud node, "
                        "a PostgreSQL server started for the run (RUN/postgres) for several (default: auto)")
    p.add_argument("--ods", type=ca.PathArg("out-file", url=True, what="an ODS file path or a postgresql:// URL"), metavar="FILE|URL",
                   help="use this existing data store instead (a SQLite file or a postgresql:// URL)")
    _add_fleet_args(p)
    p.add_argument("--cloud-outage", type=ca.parsed(_outage, what="START:END seconds with 0 <= START < END", example="8:14", positive=False, keep_text=True), metavar="START:END",
                   help="SIGKILL every cloud node START s after the fleet is ready, restart them at END s")
    p.add_argument("--kill-cloud", type=ca.parsed(parse_kill, what="cloudI@SECONDS", example="cloud0@5", positive=False, keep_text=True), metavar="cloudI@S",
                   help="SIGKILL cloud node cloudI S s after the fleet is ready and leave it down (with "
                        "--clouds N > 1 the other nodes serve on), e.g. cloud0@5")
    p.add_argument("--leader-crash", type=ca.non_negative("seconds", hi=86400, example="8"), metavar="S",
                   help="SIGKILL whichever node leads the R2R tier S s after the fleet is ready (not restarted): "
                        "another candidate takes the lead")
    p.add_argument("--json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the report here")
    p.add_argument("--run-dir", type=ca.PathArg("out-dir", as_path=True, example="runs/my-run"), metavar="DIR", help="run directory (default: runs/<UTC timestamp>)")
    p.add_argument("--min-ror", type=ca.Number(lo=0, hi=1, what="RoR", example="1.0"), default=1.0, metavar="R",
                   help="exit 1 when the RoR is below this (default: %(default)s; 0 never fails)")
    p.add_argument("--quiet", action="store_true", help="no live progress")
    from scmr_mesh.viz import (
        add_rerun_args,  # light: rerun is imported only with a flag
    )

    add_rerun_args(p)
    p.set_defaults(func=_cmd_up)


def _cmd_up(args: argparse.Namespace) -> int:
    config = _config_from_args(args, args.robots, args.run_dir)
    report = run_with_output(config, json_path=args.json, quiet=args.quiet)
    print(format_summary(report))
    print(f"\nreport: {Path(report['run_dir']) / 'report.json'}"
          + (f" and {args.json}" if args.json else "") + f"\nlogs:   {Path(report['run_dir']) / 'logs'}/")
    if getattr(args, "save", None):
        print(f"rerun:  {args.save} (open it with `scmr view {args.save}`)")
    if report.get("interrupted"):
        return 130
    return check_fleet(report, args.min_ror)


