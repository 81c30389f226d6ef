"""``scmr ods``: query the operational data store and inspect telemetry queues."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from datetime import datetime, timezone
from pathlib import Path

from scmr_mesh import cliargs as ca
from scmr_mesh.errors import InputError

DESCRIPTION = """\
Query the operational data store (ODS): the SQLite file (or the PostgreSQL
database several cloud nodes share) in which the cloud keeps every robot's
telemetry (pose, battery, health, results summary), stored once per (robot, incarnation of its queue, seq).

  scmr ods --db runs/ods.sqlite counts
  scmr ods --db runs/ods.sqlite latest
  scmr ods --db runs/ods.sqlite range --since 2026-11-21T17:00:00Z --until 1795281200
  scmr ods --db runs/ods.sqlite export --format csv --out telemetry.csv
  scmr ods --db 'postgresql://scmr@db.site:5432/scmr' counts   (a shared PostgreSQL store)
  scmr ods queue runs/<run>/robots/r1/telemetry-queue   (a robot's on-disk queue)
  scmr ods fetch 'state/**' --connect tcp/127.0.0.1:7447  (the mesh's data buffer)

--db (a file, a run folder or a postgresql:// URL) defaults to $SCMR_ODS, else
$SCMR_RUN_DIR/ods.sqlite, else runs/ods.sqlite.  A run folder of several cloud
nodes (`scmr up --clouds 3`) holds a PostgreSQL cluster in RUN/postgres that
was stopped with the run: `scmr ods --db RUN counts` starts it for the query
and stops it again.
"""

TIME_HELP = ("a time: ISO 8601 (2026-11-21T17:00:00Z; naive means UTC), unix seconds "
             "(1795281200.5) or unix nanoseconds (an integer >= 1e15)")


def parse_time_ns(text: str) -> int:
    """Parse an ISO 8601 time, unix seconds or unix ns into unix ns.

    Raises
    ------
    InputError
        ``text`` is none of these.
    """
    t = text.strip()
    try:
        if t.lstrip("-").isdigit() and abs(int(t)) >= 10**15:
            return int(t)
        return int(round(float(t) * 1e9))
    except ValueError:
        pass
    try:
        dt = datetime.fromisoformat(t.replace("Z", "+00:00"))
    except ValueError:
        raise InputError(f"cannot read {text!r} as a time; give {TIME_HELP}") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return int(dt.timestamp() * 1e9)


@contextlib.contextmanager
def _open(args):
    """The store ``--db`` names, read-only; a run folder's stopped PostgreSQL server runs meanwhile."""
    from scmr_mesh.data.ods import OperationalDataStore, default_db_path, is_dsn

    target = args.db or default_db_path()
    if is_dsn(target) or not Path(target).is_dir():
        with OperationalDataStore(target, readonly=True) as ods:
            yield ods
        return
    from scmr_mesh.fleet.pgserver import run_store

    with run_store(target) as (store, server):
        if server is not None:
            print(f"started the run's PostgreSQL server ({server.data_dir}) to read it; it is stopped after",
                  file=sys.stderr)
        with OperationalDataStore(store, readonly=True) as ods:
            yield ods


def _iso(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, tz=timezone.utc).isoformat(timespec="milliseconds")


def _print_json(obj, **kw) -> None:
    json.dump(obj, sys.stdout, indent=1, **kw)
    print()


def _ask_store(args, query):
    """What ``query(ods)`` answers from the store ``args`` names, or None when ``--json``
    asked for it and it was printed as JSON instead."""
    with _open(args) as ods:
        answer = query(ods)
    if args.json:
        _print_json(answer)
        return None
    return answer


def _cmd_counts(args) -> int:
    counts = _ask_store(args, lambda ods: ods.counts())
    if counts is None:
        return 0
    if not counts:
        print("no telemetry stored yet", file=sys.stderr)
        return 0
    print(f"{'robot':<16}{'stored':>8}{'dups':>7}{'min_seq':>9}{'max_seq':>9}{'contig':>8}{'conflicts':>10}")
    for robot, c in counts.items():
        print(f"{robot:<16}{c['stored']:>8}{c['duplicates']:>7}{c['min_seq']:>9}{c['max_seq']:>9}"
              f"{c['contiguous']:>8}{c['conflicts']:>10}")
    tot = sum(c["stored"] for c in counts.values())
    dup = sum(c["duplicates"] for c in counts.values())
    print(f"{'total':<16}{tot:>8}{dup:>7}")
    return 0


def _cmd_latest(args) -> int:
    latest = _ask_store(args, lambda ods: ods.latest())
    if latest is None:
        return 0
    for robot, r in latest.items():
        pose = "-" if r["pose"] is None else "(" + ", ".join(f"{v:.2f}" for v in r["pose"]) + ")"
        batt = "-" if r["battery"] is None else f"{r['battery']:.2f}"
        print(f"{robot}: seq {r['seq']} at {_iso(r['t_unix_ns'])} pose {pose} battery {batt} "
              f"health {r['health']} via {r['received_from']} results {json.dumps(r['results'])}")
    return 0


def _range_bounds(args) -> tuple[int | None, int | None]:
    since = parse_time_ns(args.since) if args.since else None
    until = parse_time_ns(args.until) if args.until else None
    if since is not None and until is not None and until < since:
        raise InputError(f"--until ({args.until}) is before --since ({args.since}); swap them")
    return since, until


def _cmd_range(args) -> int:
    since, until = _range_bounds(args)
    with _open(args) as ods:
        rows = ods.range(since_ns=since, until_ns=until, robot=args.robot)
    for r in rows:
        print(json.dumps(r))
    print(f"{len(rows)} record(s)", file=sys.stderr)
    return 0


def _cmd_export(args) -> int:
    since, until = _range_bounds(args)
    with _open(args) as ods:
        n = ods.export(args.out, fmt=args.format, since_ns=since, until_ns=until)
    print(f"wrote {n} record(s) to {args.out}", file=sys.stderr)
    return 0


def _cmd_queue(args) -> int:
    from scmr_mesh.data.queue import TelemetryQueue

    path = Path(args.dir)
    if not path.is_dir():
        raise InputError(f"no telemetry queue folder at {str(path)!r}; pass a robot's queue folder")
    with TelemetryQueue(path, readonly=True) as q:  # the robot may be running: look only
        st = q.stats().to_dict()
    _print_json(st)
    if st["corruptions"] or st["lost_seqs"]:
        print(f"queue {path}: {len(st['corruptions'])} corrupt stretch(es), "
              f"{len(st['lost_seqs'])} seq(s) lost", file=sys.stderr)
        return 1
    return 0


def _cmd_fetch(args) -> int:
    from scmr_mesh.mesh.config import from_args
    from scmr_mesh.mesh.data_service import fetch_once

    if not args.connect:
        raise InputError("scmr ods fetch needs --connect ENDPOINT (a cloud or leader, e.g. tcp/127.0.0.1:7447)")
    tier, node, items = fetch_once(args.selector, from_args(args, mode="peer"), wait_s=args.wait_ms / 1e3,
                                   deadline_ms=args.deadline_ms)
    print(f"answered by {tier}/{node}: {len(items)} item(s)", file=sys.stderr)
    _print_json(items, default=str)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``scmr ods`` to the command line."""
    p = sub.add_parser("ods", help="query the operational data store (telemetry) and robot queues",
                       description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--db", type=ca.PathArg("in-path", url=True, what="an ODS file written by a cloud peer, a run folder, or a postgresql:// URL", example="runs/demo"), metavar="FILE|DIR|URL", help="the ODS file, a run folder (its ods.sqlite, or its PostgreSQL cluster: started for the query when stopped) or a postgresql:// URL (see above for the default)")
    p.set_defaults(func=lambda args: (p.print_help(sys.stderr), 2)[1])
    ods_sub = p.add_subparsers(dest="ods_command", metavar="QUERY")

    c = ods_sub.add_parser("counts", help="per-robot stored / duplicate counts and seq span",
                           description="Per robot: records stored, duplicates ignored, lowest and "
                           "highest seq, highest contiguous seq (1..n all stored), and conflicts (a seq "
                           "sent again with other content: the robot started over with a fresh queue).")
    c.add_argument("--json", action="store_true", help="print JSON instead of a table")
    c.set_defaults(func=_cmd_counts)

    lt = ods_sub.add_parser("latest", help="latest state (highest seq) of each robot",
                            description="The record with the highest seq of each robot.")
    lt.add_argument("--json", action="store_true", help="print JSON instead of one line per robot")
    lt.set_defaults(func=_cmd_latest)

    r = ods_sub.add_parser("range", help="records in a time range, as JSON lines",
                           description="Records with SINCE <= t < UNTIL (robot time), one JSON "
                           "object per line, by time.")
    r.add_argument("--since", type=ca.parsed(parse_time_ns, what=TIME_HELP, example="2026-11-21T17:00:00Z", keep_text=True), metavar="TIME", help=TIME_HELP)
    r.add_argument("--until", type=ca.parsed(parse_time_ns, what=TIME_HELP, example="2026-11-21T18:00:00Z", keep_text=True), metavar="TIME", help=TIME_HELP + " (exclusive)")
    r.add_argument("--robot", help="only this robot")
    r.set_defaults(func=_cmd_range)

    e = ods_sub.add_parser("export", help="export records to CSV or JSON",
                           description="Write every record (or a time range) to a CSV or JSON file.")
    e.add_argument("--format", choices=("csv", "json"), default="csv", help="output format (default csv)")
    e.add_argument("--out", type=ca.PathArg("out-file"), required=True, metavar="FILE", help="file to write")
    e.add_argument("--since", type=ca.parsed(parse_time_ns, what=TIME_HELP, example="2026-11-21T17:00:00Z", keep_text=True), metavar="TIME", help=TIME_HELP)
    e.add_argument("--until", type=ca.parsed(parse_time_ns, what=TIME_HELP, example="2026-11-21T18:00:00Z", keep_text=True), metavar="TIME", help=TIME_HELP + " (exclusive)")
    e.set_defaults(func=_cmd_export)

    q = ods_sub.add_parser("queue", help="inspect a robot's on-disk telemetry queue",
                           description="Print a telemetry queue's counters (depth, acked seq, "
                           "refused, torn bytes, corruptions, lost seqs) as JSON; exit 1 when "
                           "it found a corrupt stretch or records lost to one (lost_seqs: seqs the "
                           "queue can no longer deliver), 0 otherwise.  Read-only: safe while the robot runs (the robot "
                           "itself repairs a torn tail when it opens its queue).")
    q.add_argument("dir", type=ca.PathArg("in-dir", what="a robot's telemetry queue folder", example="runs/demo/queues/r1"), metavar="DIR", help="the robot's queue folder")
    q.set_defaults(func=_cmd_queue)

    f = ods_sub.add_parser("fetch", help="ask the mesh's data buffer (cloud, else leader) for entries",
                           description="Query the local data buffer over Zenoh, routed like a robot's data "
                           "request: an alive cloud node first, else the leader's synced copy.  SELECTOR is "
                           "a key (state/r1) or a pattern (state/**, maps/*, **).  Prints the items as JSON; "
                           "stderr says which tier answered.")
    f.add_argument("selector", metavar="SELECTOR", help="buffer key or pattern, e.g. state/**")
    f.add_argument("--wait-ms", type=ca.non_negative("milliseconds", hi=3600000), default=3000.0, metavar="MS",
                   help="wait up to MS for a cloud or leader to be seen (default 3000)")
    f.add_argument("--deadline-ms", type=ca.positive("milliseconds", hi=3600000), default=1000.0, metavar="MS",
                   help="per-tier deadline (default 1000)")
    f.add_argument("--id", default=None, metavar="NAME",
                   help="identity in the credentials to join a secured mesh with (a robot's name from scmr certs; "
                        "needed with --security: every launcher's mesh is secured by default, RUN/certs)")
    from scmr_mesh.mesh import config as _zconfig

    _zconfig.add_arguments(f)
    f.set_defaults(func=_cmd_fetch)



