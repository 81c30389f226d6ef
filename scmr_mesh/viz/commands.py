"""``scmr view FILE.rrd``: open a saved recording in the rerun viewer."""

from __future__ import annotations

import argparse
import subprocess
import sys

from scmr_mesh import cliargs as ca


def register(sub: argparse._SubParsersAction) -> None:
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
    p.add_argument("file", type=ca.PathArg("in-file", what="a rerun recording (.rrd)", example="runs/demo/demo.rrd"), metavar="FILE.rrd", help="recording to open")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--web", action="store_true", help="serve the web viewer instead of opening a window")
    mode.add_argument("--screenshot", type=ca.PathArg("out-file"), metavar="OUT.png", help="render headless and save a PNG, then exit")
    mode.add_argument("--summary", action="store_true", help="print entities with their row counts and exit")
    p.add_argument("--web-port", type=ca.count("a TCP port", lo=1, hi=65535, example="9090"), default=9090, help="port of the web viewer (default: %(default)s)")
    p.add_argument("--settle", type=ca.non_negative("seconds", hi=3600), default=6.0, help="seconds to let the viewer load before --screenshot (default: %(default)s)")
    p.add_argument("--max-size", type=ca.count("pixels", lo=16, hi=16384, example="960"), default=None, help="longest side of the --screenshot PNG in pixels")
    p.set_defaults(func=run)



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
        from scmr_mesh.viz.screenshot import screenshot

        out = screenshot(path, args.screenshot, settle=args.settle, max_size=args.max_size)
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
