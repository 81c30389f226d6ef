"""``scmr view FILE.rrd``: open a saved recording in the rerun viewer."""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import threading
import time
from urllib.parse import quote

from scmr_mesh import cliargs as ca
from scmr_mesh.errors import InputError
from scmr_mesh.ports import free_port


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
            "  scmr view runs/demo/demo.rrd --web           web viewer on free ports; prints its URL\n"
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
    p.add_argument("--web-port", type=ca.count("a TCP port", lo=1, hi=65535, example="9090"), default=None, metavar="PORT",
                   help="HTTP port of the web viewer (default: a free port; an error when the given one is taken)")
    p.add_argument("--port", type=ca.count("a TCP port", lo=1, hi=65535, example="9876"), default=None, metavar="PORT",
                   help="gRPC port the web viewer streams the recording from (default: a free port, so two "
                        "viewers do not clash on rerun's 9876; an error when the given one is taken)")
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
        web, grpc = viewer_ports(args.web_port, args.port)
        cmd = [exe, "--web-viewer", "--web-viewer-port", str(web), "--port", str(grpc), "--bind", "127.0.0.1",
               str(path)]
        try:
            return serve(cmd, env=viz.rerun_env(), ready_ports=(web, grpc),
                         ready=f"serving the web viewer on {viewer_url(web, grpc)} (Ctrl-C to stop)")
        except OSError as exc:
            raise viz.ViewerError(f"could not run {cmd[0]}: {exc}") from exc
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


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def viewer_ports(web_port: int | None, grpc_port: int | None, *, free=_port_free, pick=free_port) -> tuple[int, int]:
    """``(web, grpc)`` ports of ``scmr view --web``: the given ones if free, else free ones.

    rerun's gRPC server takes 9876 unless told otherwise, so a second viewer exited with
    "Address already in use" after printing a URL that showed the first one's recording.

    >>> viewer_ports(None, None, pick=iter([4001, 4002]).__next__)
    (4001, 4002)
    >>> viewer_ports(9090, None, free=lambda p: False)
    Traceback (most recent call last):
    ...
    scmr_mesh.errors.InputError: --web-port 9090 is taken (another viewer?); give another port or leave --web-port out for a free one
    """
    out = []
    for flag, port in (("--web-port", web_port), ("--port", grpc_port)):
        if port is None:
            port = pick()
            while port in out:
                port = pick()
        elif port in out or not free(port):
            raise InputError(f"{flag} {port} is taken (another viewer?); give another port or leave {flag} out "
                             "for a free one")
        out.append(port)
    return out[0], out[1]


def viewer_url(web_port: int, grpc_port: int) -> str:
    """The URL that opens the web viewer on its own recording (rerun's ``?url=`` form).

    >>> viewer_url(9090, 9876)
    'http://127.0.0.1:9090?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9876%2Fproxy'
    """
    return f"http://127.0.0.1:{web_port}?url=" + quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")


#: After Ctrl-C, how long rerun may take to stop before SIGTERM, then SIGKILL.
STOP_GRACE_S = 1.0
#: How long ``serve`` waits for the viewer's ports before it prints the URL with a warning.
READY_WAIT_S = 15.0


def serve(cmd, *, env=None, ready_ports=(), ready: str | None = None) -> int:
    """Run the rerun web viewer until it exits or SIGINT/SIGTERM; return an exit status.

    ``ready`` is printed once every port of ``ready_ports`` answers (the URL must open when shown),
    or after :data:`READY_WAIT_S` with the ports that do not answer yet named.

    A Python started with SIGINT ignored (a script or CI job that ran it in the background)
    keeps ignoring it, and so did the rerun child: Ctrl-C/SIGINT did nothing.  Here the
    handlers are installed explicitly, rerun runs in its own session with SIGINT at its
    default, and a signal stops it (SIGINT, then SIGTERM and SIGKILL after a grace).
    """
    from scmr_mesh.viz.sink import _dies_with_us, _port_open, _stop

    got: list[int] = []
    stop = threading.Event()

    def handle(signum, _frame) -> None:
        got.append(signum)
        stop.set()

    old = {}
    main = threading.current_thread() is threading.main_thread()
    if main:
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, handle)

    # rerun dies with this command, even a SIGKILLed one (None off the main thread)
    die = _dies_with_us()

    def child_setup() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        if die is not None:
            die()

    proc = subprocess.Popen(cmd, env=env, start_new_session=True, preexec_fn=child_setup)
    waiting = list(ready_ports)
    if ready and not waiting:
        print(ready, file=sys.stderr)
        ready = None
    deadline = time.monotonic() + READY_WAIT_S
    try:
        while proc.poll() is None and not stop.wait(0.05 if ready else 0.1):
            if ready:
                waiting = [p for p in waiting if not _port_open(p)]
                if not waiting:
                    print(ready, file=sys.stderr)
                    ready = None
                elif time.monotonic() > deadline:
                    print(f"{ready} [port {', '.join(map(str, waiting))} not answering after "
                          f"{READY_WAIT_S:.0f} s]", file=sys.stderr)
                    ready = None
    finally:
        if proc.poll() is None:
            _stop(proc, grace=STOP_GRACE_S)
        for sig, h in old.items():
            signal.signal(sig, h)
    if got:
        return 128 + got[0]
    return proc.returncode

