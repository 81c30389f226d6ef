"""Sub-commands of the security area: ``scmr certs`` and ``scmr bench overload``."""

from __future__ import annotations

import argparse
import json
import sys

CERTS_HELP = """\
Create a development certificate authority, one certificate per peer (CN = peer name,
signed by the CA, valid for 127.0.0.1, ::1, localhost, the peer name and --hosts), a
usrpwd password per peer, and fleet.json (names and roles, the input of the access-control
rules).  Roles come from names: cloud* -> cloud, leader* -> leader, anything else robot;
write name=role to choose.  Private keys and passwords are mode 0600.  These are
development credentials: keep DIR/ca.key off the robots.

Use them with a security profile, e.g. peers/secure/mtls.toml:
  scmr certs --out certs --peers cloud,leader,robot1,robot2
  SCMR_CREDENTIALS=certs scmr up ... (peers started with --security peers/secure/mtls.toml)
"""


def _certs(args: argparse.Namespace) -> int:
    from scmr_mesh.security.credentials import create_credentials
    from scmr_mesh.security.acl import build_acl

    fleet = create_credentials(
        args.out,
        args.peers,
        days=args.days,
        hosts=[h for h in (args.hosts or "").split(",") if h.strip()],
        force=args.force,
        progress=lambda msg: print(msg, file=sys.stderr),
    )
    if args.acl_json:
        with open(args.acl_json, "w") as fh:
            json.dump(build_acl(fleet, kind="tls"), fh, indent=2)
    for p in fleet.peers:
        print(f"{p.name}\t{p.role}\t{args.out}/{p.name}/")
    print(f"CA: {args.out}/ca.pem (keep {args.out}/ca.key private)", file=sys.stderr)
    return 0


def _tls(args: argparse.Namespace) -> int:
    from scmr_mesh.mesh.security import bench_link_latency

    if args.queries < 1 or args.payload < 1:
        from scmr_mesh.errors import InputError

        raise InputError(f"--queries and --payload must be >= 1, got {args.queries} and {args.payload}")
    res = bench_link_latency(payload_bytes=args.payload, queries=args.queries,
                             progress=lambda m: print(m, file=sys.stderr, flush=True))
    res["note"] = "two sessions in one process, loopback, shared memory off; shared, loaded 2-core machine"
    for r in res["runs"]:
        print(f"{r['kind']:>8}: p50 {r['p50_ms']:.3f} ms  p99 {r['p99_ms']:.3f} ms  mean {r['mean_ms']:.3f} ms")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2)
    return 0


def _overload(args: argparse.Namespace) -> int:
    from scmr_mesh.security.overload import run_overload_cli

    return run_overload_cli(args)


def register(sub: argparse._SubParsersAction, bench: argparse._SubParsersAction) -> None:
    """Add ``scmr certs`` and ``scmr bench overload``."""
    p = sub.add_parser(
        "certs",
        help="create a development CA, per-peer certificates and passwords",
        description=CERTS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, metavar="DIR", help="directory to write (new or empty)")
    p.add_argument(
        "--peers", required=True, metavar="NAMES",
        help="comma-separated peer names, e.g. cloud,leader,robot1,robot2 (name=role to set a role)",
    )
    p.add_argument("--days", type=int, default=365, help="certificate validity in days (default 365)")
    p.add_argument(
        "--hosts", default="", metavar="H1,H2",
        help="extra host names or IPs for every certificate (peers on other hosts or namespaces)",
    )
    p.add_argument("--force", action="store_true", help="overwrite a non-empty --out directory")
    p.add_argument("--acl-json", metavar="FILE", help="also write the fleet's access-control JSON here")
    p.set_defaults(func=_certs)

    from scmr_mesh.security.overload import add_overload_arguments

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
    add_overload_arguments(b)
    b.set_defaults(func=_overload)

    t = bench.add_parser(
        "tls",
        help="query round trip with no security, usrpwd, mutual TLS and TLS+ACL",
        description=(
            "Measure the cost of authentication: median and p99 round trip of a query carrying "
            "--payload bytes between two zenoh sessions on loopback (shared memory off), with no "
            "security, usrpwd, mutual TLS, and mutual TLS with the fleet ACL."
        ),
    )
    t.add_argument("--payload", type=int, default=200_000, metavar="BYTES", help="query payload (default 200000)")
    t.add_argument("--queries", type=int, default=300, metavar="N", help="timed queries per kind (default 300)")
    t.add_argument("--json", metavar="FILE", help="write the results here")
    t.set_defaults(func=_tls)
