"""``scmr demo``: the main job, run by ``make demo``."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction, bench: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the fleet demo on one host (what `make demo` runs)",
        description="Run the scmr-mesh demo on embedded defaults.",
    )
    p.add_argument("--out", default="runs/demo", help="where to write results (default: %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from scmr_mesh.errors import ScmrError

    raise ScmrError("the demo is not built yet")
