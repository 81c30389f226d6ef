"""The ``scmr`` command line.

Each area of the project contributes its sub-commands through a ``register``
function in its own ``commands`` module (listed in :data:`COMMAND_MODULES`), so
this file never needs to know the details.  A ``register(sub)`` call receives
the top-level sub-parser action; each sub-command sets ``func`` to a handler
``handler(args) -> int``.  Every ``scmr bench`` target comes from
:mod:`scmr_mesh.bench.commands` (the only import of the bench layer).

Exit status: 0 success, 1 expected failure (bad input, failed expectation,
unreachable tier: an :class:`~scmr_mesh.errors.ScmrError`), 2 usage error or
bug, 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
import traceback
from typing import NoReturn, Sequence

from scmr_mesh import __version__
from scmr_mesh.cliargs import ScmrArgumentParser
from scmr_mesh.errors import ScmrError

#: Modules that contribute sub-commands, in the order ``--help`` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "scmr_mesh.fleet.demo",
    "scmr_mesh.imaging.commands",
    "scmr_mesh.mesh.commands",
    "scmr_mesh.fleet.commands",
    "scmr_mesh.scenario.commands",
    "scmr_mesh.thesis.commands",
    "scmr_mesh.energy.commands",
    "scmr_mesh.data.commands",
    "scmr_mesh.security.commands",
    "scmr_mesh.viz.commands",
)

#: Command -> the module that registers it, so that ``scmr cloud ...`` imports
#: only its own module (about 100 ms less of a peer's start-up); a command not
#: listed here makes the parser load every module (tests/test_cli.py keeps
#: this table in step with :data:`COMMAND_MODULES`).
COMMAND_HOME: dict[str, str] = {
    "demo": "scmr_mesh.fleet.demo",
    "segment": "scmr_mesh.imaging.commands",
    "eval": "scmr_mesh.imaging.commands",
    "cloud": "scmr_mesh.mesh.commands",
    "leader": "scmr_mesh.mesh.commands",
    "robot": "scmr_mesh.mesh.commands",
    "router": "scmr_mesh.mesh.commands",
    "ros": "scmr_mesh.mesh.commands",
    "tap": "scmr_mesh.mesh.commands",
    "up": "scmr_mesh.fleet.commands",
    "scenario": "scmr_mesh.scenario.commands",
    "thesis": "scmr_mesh.thesis.commands",
    "energy": "scmr_mesh.energy.commands",
    "ods": "scmr_mesh.data.commands",
    "certs": "scmr_mesh.security.commands",
    "view": "scmr_mesh.viz.commands",
    "swarm": "scmr_mesh.mesh.commands",
}

EPILOG = """\
Start here:
  scmr demo                      the fleet demo on one host (what `make demo` runs)
  scmr segment IMG --out DIR     drivable-region masks for images
  scmr up --robots 4             cloud, leader and 4 robots on loopback
Each command has its own --help.  Set SCMR_DEBUG=1 to see tracebacks.
"""


def _command_of(argv: Sequence[str] | None) -> str | None:
    """The sub-command named in ``argv`` (the top-level options take no value)."""
    for a in sys.argv[1:] if argv is None else argv:
        if not a.startswith("-"):
            return a
        if a in ("-h", "--help", "--version"):
            return None
    return None


def build_parser(argv: Sequence[str] | None = None, *, full: bool = True) -> argparse.ArgumentParser:
    """The ``scmr`` parser; with ``full=False`` only the module of the command in ``argv``."""
    command = None if full else _command_of(argv)
    parser = ScmrArgumentParser(
        prog="scmr",
        description=(
            "scmr-mesh: robots offload drivable-region segmentation to a cloud "
            "over Eclipse Zenoh, and fail over to a robot leader when the cloud "
            "is lost."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"scmr-mesh {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench_parser = sub.add_parser(
        "bench",
        help="benchmarks (medians and ratios measured in one run)",
        description="Benchmarks. Each writes JSON with medians and p99s measured in one run.",
    )
    bench = bench_parser.add_subparsers(dest="bench_command", metavar="BENCH")
    bench_parser.set_defaults(func=lambda args: _missing_sub(bench_parser))
    if command == "bench":
        modules: Sequence[str] = ()
    elif command in COMMAND_HOME:
        modules = (COMMAND_HOME[command],)
    else:
        modules = COMMAND_MODULES
    for name in modules:
        importlib.import_module(name).register(sub)
    if command is None or command == "bench" or command not in COMMAND_HOME:
        from scmr_mesh.bench.commands import register as register_bench

        register_bench(bench)
    return parser


def _missing_sub(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


def _configure_logging(verbosity: int) -> None:
    level = logging.WARNING if verbosity == 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``scmr`` command line; return the exit status."""
    from scmr_mesh.mesh.startup import clock

    clock().mark("interpreter")  # a peer's start-up phases (scmr -v cloud prints them)
    # no BLAS in the pipeline: one OpenBLAS thread halves numpy's import (70 ms of CPU)
    # and keeps workers from oversubscribing the cores
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = build_parser(argv, full=False)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2)
        return int(exc.code or 0) if isinstance(exc.code, int) else 2
    clock().mark("command line")
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    _configure_logging(args.verbose)
    try:
        return int(args.func(args) or 0)
    except ScmrError as exc:
        print(f"scmr: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("scmr: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1
    except Exception as exc:  # a bug: one line, traceback on request
        if os.environ.get("SCMR_DEBUG"):
            traceback.print_exc()
        print(
            f"scmr: internal error: {type(exc).__name__}: {exc} "
            "(this is a bug; rerun with SCMR_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return 2


def _exit_now(status: int) -> NoReturn:
    """Leave the process as the interpreter would, minus its finalization.

    Before 3.14, CPython ends a thread that takes the GIL once finalization has begun with
    ``pthread_exit``; unwinding through zenoh's Rust frames (a callback thread, or a daemon thread
    coming back from a blocking zenoh call) then aborts the process after its work is done:
    "FATAL: exception not rethrown", exit status -6 (cpython gh-87135).  A robot that had served
    and written everything died so in one run of the suite; a daemon thread in ``recv()`` on a
    subscriber that still gets samples aborts 3 exits in 30 (docs/ZENOH.md section 21).  So this
    does what finalization does first (join the non-daemon threads, run the ``atexit`` functions:
    logging, executors and pools, the data tier's close), flushes the standard streams, and
    leaves with ``os._exit``.
    """
    import atexit
    import threading

    try:
        threading._shutdown()  # what Py_FinalizeEx runs first: join non-daemon threads, executors' hooks
    except Exception:  # pragma: no cover - a thread that failed to join; the exit still happens
        pass
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:
            pass
    os._exit(status)


def run() -> NoReturn:
    """The ``scmr`` program (console script and ``python -m scmr_mesh``): :func:`main`, then
    :func:`_exit_now` with its status."""
    try:
        status = main()
    except SystemExit as exc:  # (main returns its status; a stray exit keeps its code)
        status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    _exit_now(status)


if __name__ == "__main__":  # pragma: no cover
    run()
