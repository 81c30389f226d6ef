"""``scmr swarm``: several robots played by one process (a load generator for benchmarks).

Each member is a whole robot: its own ``scmr robot`` command line, its own zenoh
session (so its own certificate and key under ``--security``, checked by the
fleet's access rules like any robot), its own frames, records, telemetry queue and
ready file.  What members share is the interpreter: a 2-core machine can offer the
traffic of a hundred robots without a hundred Python processes (issue 23: 64 robot
processes left the cloud no CPU).  Real ``scmr robot`` processes stay the default
for fleets and scenarios; ``scmr up --robots-per-process K`` and ``scmr bench mesh``
group robots into swarms.

A member cannot be leader-capable (a candidate is a process with its own worker
pool; run it as ``scmr robot --leader-capable``).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
from pathlib import Path
from typing import Any, Sequence

from scmr_mesh import cliargs as ca
from scmr_mesh.errors import InputError, MeshError, ScmrError

log = logging.getLogger(__name__)

#: Most robots one swarm process plays (each has a zenoh session and a few threads).
MAX_MEMBERS = 256


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``swarm`` to ``scmr``."""
    p = sub.add_parser(
        "swarm", help="play several robots from one process (a load generator for benchmarks)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run the robots of --plan in this one process.  Each member is a whole robot "
                    "(the arguments of one `scmr robot`): its own zenoh session and identity, frames, "
                    "records, telemetry and ready file.  Writes --ready-file once every member is "
                    "ready; exits 1 when a member failed or lost telemetry.  Members cannot be "
                    "leader-capable.",
        epilog="PLAN is JSON: {\"robots\": [[\"--id\", \"r1\", \"--synthetic\", \"road\", \"--out\", "
               "\"run/r1\", ...], ...]}, each entry one robot's `scmr robot` arguments.  "
               "`scmr up --robots-per-process K` writes these plans itself.")
    p.add_argument("--plan", required=True, type=ca.PathArg("in-file"), metavar="PLAN",
                   help="JSON file with each member's `scmr robot` arguments")
    p.add_argument("--ready-file", type=ca.PathArg("out-file"), metavar="PATH",
                   help="written once every member is ready")
    p.set_defaults(func=_cmd_swarm)


def read_plan(path: str | Path) -> list[list[str]]:
    """The members' argument lists of a swarm plan file.

    Raises
    ------
    InputError
        The file is not JSON of the form ``{"robots": [[str, ...], ...]}``, is empty or too long.
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"--plan {path}: cannot read a JSON swarm plan ({exc})") from None
    robots = data.get("robots") if isinstance(data, dict) else None
    if (not isinstance(robots, list) or not robots
            or not all(isinstance(m, list) and all(isinstance(a, str) for a in m) for m in robots)):
        raise InputError(f"--plan {path}: expected {{\"robots\": [[arguments of scmr robot], ...]}} "
                         "with at least one robot")
    if len(robots) > MAX_MEMBERS:
        raise InputError(f"--plan {path}: {len(robots)} robots, at most {MAX_MEMBERS} per swarm; "
                         "split them over several swarms")
    return robots


def parse_members(plans: Sequence[Sequence[str]]) -> list[argparse.Namespace]:
    """Each member's arguments parsed and checked as ``scmr robot`` would, before anything starts."""
    import contextlib
    import io

    from scmr_mesh.cli import build_parser
    from scmr_mesh.mesh.commands import _check_robot_args, check_grant, require_security

    parser = build_parser(["robot"], full=False)
    members, seen = [], set()
    for i, argv in enumerate(plans):
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                args = parser.parse_args(["robot", *argv])
        except SystemExit:
            last = (err.getvalue().strip().splitlines() or ["invalid arguments"])[-1]
            for prefix in ("scmr robot: ", "scmr: ", "error: "):
                last = last.removeprefix(prefix)
            raise InputError(f"swarm member {i + 1}: {last}") from None
        if args.id in seen:
            raise InputError(f"swarm member {i + 1}: robot id {args.id!r} twice; give each member its own --id")
        seen.add(args.id)
        if args.leader_capable:
            raise InputError(f"swarm member {args.id}: --leader-capable robots run as their own process "
                             "(scmr robot --leader-capable), not in a swarm")
        if not args.out:
            raise InputError(f"swarm member {args.id}: --out DIR is required (its records and masks)")
        try:
            require_security(args, "robot")
            check_grant(args, "robot", args.id)
            _check_robot_args(args)
        except ScmrError as exc:
            raise InputError(f"swarm member {args.id}: {exc}") from None
        members.append(args)
    return members


def _cmd_swarm(args) -> int:
    from scmr_mesh.mesh.commands import _mesh, _robot_body
    from scmr_mesh.mesh.config import close_session, open_session
    from scmr_mesh.mesh.peers import StopFlag, clear_ready, write_ready

    members = parse_members(read_plan(args.plan))
    stop = StopFlag().install()
    clear_ready(args.ready_file)
    for m in members:
        clear_ready(m.ready_file)
    sessions: list[Any] = []
    results: dict[str, Any] = {}
    threads: list[threading.Thread] = []
    try:
        for m in members:  # every identity opens its own session: its own certificate and links
            sessions.append(open_session(_mesh(m)))

        def play(m, session) -> None:
            try:
                results[m.id] = _robot_body(m, session, stop.event)
            except Exception as exc:  # one member's failure is reported, the others go on
                log.exception("swarm member %s failed", m.id)
                results[m.id] = exc
                stop_member_problem(m, exc)

        for m, s in zip(members, sessions):
            t = threading.Thread(target=play, args=(m, s), name=f"robot-{m.id}", daemon=True)
            t.start()
            threads.append(t)
        ready_files = [Path(m.ready_file) for m in members if m.ready_file]
        while not stop.event.is_set() and any(t.is_alive() for t in threads):
            if ready_files and all(f.exists() for f in ready_files):
                write_ready(args.ready_file, {"role": "swarm", "robots": [m.id for m in members]})
                ready_files = []
            for t in threads:
                t.join(0.05)
        # stopped: every member's run loop sees the same stop event and ends its frame
        for t in threads:
            while t.is_alive():
                t.join(0.2)
    finally:
        for s in sessions:
            close_session(s)
        clear_ready(args.ready_file)
        for m in members:
            clear_ready(m.ready_file)
        stop.restore()
    problems = [getattr(m, "_problem", None) for m in members]
    problems = [p for p in problems if p]
    if problems:
        raise MeshError(f"{len(problems)} of {len(members)} swarm robots failed: " + "; ".join(problems))
    return 0


def stop_member_problem(m: argparse.Namespace, exc: Exception) -> None:
    """Mark member ``m`` failed with ``exc`` (one line; the swarm exits 1)."""
    m._problem = f"robot {m.id}: {type(exc).__name__}: {exc}"
    print(f"scmr: error: {m._problem}", file=sys.stderr, flush=True)


def plan_swarms(ids: Sequence[str], per_process: int) -> list[list[str]]:
    """Robot ids split into swarms of at most ``per_process``, in order (pure).

    >>> plan_swarms(["r1", "r2", "r3"], 2)
    [['r1', 'r2'], ['r3']]
    """
    if per_process < 1:
        raise InputError(f"robots per process must be >= 1, got {per_process}")
    ids = list(ids)
    return [ids[i:i + per_process] for i in range(0, len(ids), per_process)]
