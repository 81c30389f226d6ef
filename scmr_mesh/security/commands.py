"""Sub-commands of the security area: ``scmr certs``."""

from __future__ import annotations

import argparse
import json
import sys

from scmr_mesh import cliargs as ca

CERTS_HELP = """\
Create a development certificate authority, one certificate per peer (CN = peer name,
signed by the CA, valid for 127.0.0.1, ::1, localhost, the peer name and --hosts), a
usrpwd password per peer, and fleet.json (names, roles, lead grants and priority caps: the
input of the access-control rules).  Roles come from names: cloud* -> cloud, leader* ->
leader, router* -> router, anything else robot; write name=role to choose, and
name=robot+leader-capable for a robot that runs for the lead of the R2R tier and serves
other robots (`scmr robot --leader-capable`).  Services serve a robot's frame requests at
most at its priority cap (--priority-cap; default 0 for every robot).  Private keys and
passwords are mode 0600.  These are development credentials: keep DIR/ca.key off the robots.

Use them with a security profile, e.g. peers/secure/mtls.toml:
  scmr certs --out certs --peers cloud,leader,robot1=robot+leader-capable,robot2
  scmr cloud --node cloud --security peers/secure/mtls.toml --credentials certs ...
`scmr up`, `scmr demo` and `scmr scenario run` make credentials of their own in the run
directory (RUN/certs) unless given --insecure.
"""


def _certs(args: argparse.Namespace) -> int:
    from scmr_mesh.security.acl import build_acl
    from scmr_mesh.security.credentials import create_credentials, parse_priority_caps

    fleet = create_credentials(
        args.out,
        args.peers,
        days=args.days,
        hosts=[h for h in (args.hosts or "").split(",") if h.strip()],
        force=args.force,
        progress=lambda msg: print(msg, file=sys.stderr),
        priority=parse_priority_caps(args.priority_cap or ""),
        default_priority_cap=args.default_priority_cap,
    )
    if args.acl_json:
        with open(args.acl_json, "w") as fh:
            json.dump(build_acl(fleet, kind="tls"), fh, indent=2)
    for p in fleet.peers:
        grants = ",".join([*(["leader-capable"] if p.leads else []),
                           *([f"priority<={p.priority_cap}"] if p.priority_cap is not None else [])])
        print(f"{p.name}\t{p.role}\t{args.out}/{p.name}/\t{grants or '-'}")
    print(f"CA: {args.out}/ca.pem (keep {args.out}/ca.key private)", file=sys.stderr)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``scmr certs``."""
    p = sub.add_parser(
        "certs",
        help="create a development CA, per-peer certificates and passwords",
        description=CERTS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=ca.PathArg("out-dir"), required=True, metavar="DIR", help="directory to write (new or empty)")
    p.add_argument(
        "--peers", required=True, metavar="NAMES",
        help="comma-separated peer names, e.g. cloud,leader,robot1=robot+leader-capable,robot2 (name=role "
             "to set a role: cloud, leader, robot, router; +leader-capable lets a robot run for the lead)",
    )
    p.add_argument("--priority-cap", metavar="NAME=P,...", default="",
                   help="highest priority each robot's frame requests are served at, e.g. r1=10,r2=5 "
                        "(the fleet's policy: a request asking more is served at the cap)")
    p.add_argument("--default-priority-cap", type=ca.count("priority", lo=0, hi=1000000, example="0"), default=0,
                   metavar="P", help="cap of robots not named in --priority-cap (default 0: all equal)")
    p.add_argument("--days", type=ca.count("days", hi=36500), default=365, help="certificate validity in days (default 365)")
    p.add_argument(
        "--hosts", default="", metavar="H1,H2",
        help="extra host names or IPs for every certificate (peers on other hosts or namespaces)",
    )
    p.add_argument("--force", action="store_true", help="overwrite a non-empty --out directory")
    p.add_argument("--acl-json", type=ca.PathArg("out-file"), metavar="FILE", help="also write the fleet's access-control JSON here")
    p.set_defaults(func=_certs)

