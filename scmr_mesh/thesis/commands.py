"""``scmr thesis``: the dissertation's experiments 1-7 in one command, one report."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from scmr_mesh import cliargs as ca

DESCRIPTION = """\
Run experiments 1-7 of the dissertation (chapter 4) against real peers on this machine and
write one report: report.md, report.json and PNG figures in --out (default runs/thesis/).

For every experiment: the thesis's claim (quoted, with its table or figure number), ours
measured here, and a verdict (holds, does not hold, or not comparable and why).  Fleet runs
(scenarios of `scmr scenario`, built from peers/scenarios/baseline.toml: Table 4.3 profiles,
Table 4.2's five images per robot):

  noloss    experiments 1-3: no fault
  loss      experiments 4-6: robots cut from the cloud one by one, then the cloud from all
  size<N>   Table 4.4: N robots, the cloud cut from everyone from halfway until shortly
            before the end

plus experiment 7 (the energy model's break-even sweep), Eq 3.14 (negotiator ranking),
Eq 3.18-3.19 (transmission schedule) and Table 4.4 (delay against fleet and image size).
The run states its expected duration first; progress goes to stderr.  docs/THESIS.md.
"""

EPILOG = """\
Exit status: 0 when the report was written (whatever the verdicts), 1 on bad input or when a
fleet run could not start (one line naming the problem), 130 on Ctrl-C.

Examples:
  scmr thesis --quick                         # about 2-3 minutes
  scmr thesis                                 # the full run, about 6 minutes
  scmr thesis --reanalyse --out runs/thesis   # rebuild the report from the raw data
"""


def _sizes(text: str) -> tuple[int, ...]:
    vals = []
    for x in str(text).split(","):
        if not x.strip():
            continue
        try:
            v = int(x)
        except ValueError:
            raise ValueError(f"{x.strip()!r} is not a whole number") from None
        if not 1 <= v <= 32:
            raise ValueError(f"fleet size {v} is outside 1..32")
        if v in vals:
            raise ValueError(f"fleet size {v} is given twice")
        vals.append(v)
    if len(vals) < 2:
        raise ValueError(("no fleet size" if not vals else "one fleet size")
                         + ": the growth order of Table 4.4 needs at least two")
    return tuple(vals)


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``scmr thesis``."""
    p = sub.add_parser("thesis", help="experiments 1-7 of the dissertation in one report",
                       description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="short runs (time unit 2 s, fleet sizes 1,2,4): within 5 minutes")
    p.add_argument("--out", type=ca.PathArg("out-dir", as_path=True, example="runs/thesis"), default=Path("runs/thesis"),
                   metavar="DIR", help="report folder (default: %(default)s; replaced when a previous scmr thesis "
                                       "wrote it, refused when it holds other files)")
    p.add_argument("--backend", choices=("auto", "netns", "proxy"), default="auto",
                   help="how faults are made: netns (network namespaces, kernel-level; root), proxy (TCP proxies "
                        "on loopback), auto (default): netns when root, else proxy")
    p.add_argument("--data", type=ca.PathArg("in-dir", as_path=True), metavar="DIR", default=None,
                   help="the road images (default $SCMR_DATA or ../shared/data/roads)")
    p.add_argument("--robots", type=ca.count("robots", hi=4, example="4"), default=4, metavar="N",
                   help="robots of the Table 4.2 runs, robot1..robotN (default: %(default)s)")
    p.add_argument("--images", type=ca.count("images", hi=5, example="5"), default=5, metavar="N",
                   help="images per robot, the first N of its Table 4.2 set (default: %(default)s)")
    p.add_argument("--fleet-sizes", type=ca.parsed(_sizes, what="two or more fleet sizes 1..32", example="1,2,4"),
                   default=None, metavar="LIST", help="fleet sizes of the Table 4.4 runs (default 1,2,4 with --quick, "
                                                      "else 1,2,4,8,16)")
    p.add_argument("--step", type=ca.positive("seconds", hi=600, example="2"), default=None, metavar="S",
                   help="time unit of every run (default 2 with --quick, else 8): noloss lasts 4 units, "
                        "size<N> 3, loss robots + 2.5")
    p.add_argument("--reanalyse", action="store_true",
                   help="run nothing: rebuild report.md, report.json and the figures of --out from its raw data")
    p.set_defaults(func=_cmd_thesis)


def _err(msg: str) -> None:
    print(f"thesis: {msg}", file=sys.stderr, flush=True)


def _cmd_thesis(args: argparse.Namespace) -> int:
    from scmr_mesh.thesis.main import reanalyse, run_thesis
    from scmr_mesh.thesis.plan import ThesisConfig

    if args.reanalyse:
        rep = reanalyse(args.out, say=_err)
    else:
        backend = args.backend
        if backend == "auto":
            backend = "netns" if hasattr(os, "geteuid") and os.geteuid() == 0 else "proxy"
        config = ThesisConfig(quick=args.quick, robots=args.robots, images=args.images,
                              fleet_sizes=args.fleet_sizes or (), step_s=args.step or 0.0, backend=backend,
                              data_dir=args.data, out=args.out)
        rep = run_thesis(config, say=_err)
    from scmr_mesh.thesis.report import verdict

    print(f"report: {Path(args.out) / 'report.md'} (and report.json, figures/)")
    for k in sorted(rep["experiments"], key=int):
        e = rep["experiments"][k]
        print(f"  experiment {k} ({e['claim']['source']}): {verdict(e['holds']).strip('*')}")
    for name, h in rep["model"]["table_4_4"]["holds"].items():
        print(f"  Table 4.4 {name}: {verdict(h).strip('*')}")
    t = rep.get("timing") or {}
    if t.get("total_s") is not None:
        print(f"  took {t['total_s']:.0f} s (estimated {t.get('estimate_s', 0):.0f} s)")
    return 0
