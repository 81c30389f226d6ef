"""Running peers as OS processes: signals, ready files, logging, life cycles.

Library functions behind ``scmr cloud | leader | robot | router`` (the CLI
wiring is in :mod:`scmr_mesh.mesh.commands`).  Each ``run_*`` function blocks
until its work is done or SIGTERM/SIGINT arrives, then shuts down cleanly
(undeclare, close the zenoh session, stop the workers, flush files) and
returns.

Ready file: written atomically (temp file + rename) once the peer serves or
is connected, holding JSON ``{"pid", "role", "node", "zid", "keys",
"t_unix_ns"}`` (services add ``"workers"`` and ``"startup"``, the wall and CPU
time of each start-up phase from exec: :mod:`scmr_mesh.mesh.startup`);
removed again at a clean exit.  A stale one is removed at start.
"""

from __future__ import annotations

import json
import logging
import os
import faulthandler
import signal
import threading
import time
from pathlib import Path
from typing import Callable

from scmr_mesh.errors import InputError
from scmr_mesh.mesh.config import MeshConfig, close_session, open_session

log = logging.getLogger(__name__)


class StopFlag:
    """A threading.Event set by SIGTERM/SIGINT (installed on the main thread)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        self._old: dict[int, object] = {}

    def install(self) -> "StopFlag":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                self._old[sig] = signal.signal(sig, self._handle)
            # SIGUSR1 prints every thread's stack to the log (stop_peer sends it before a SIGKILL)
            faulthandler.register(signal.SIGUSR1, all_threads=True)
        return self

    def _handle(self, signum, frame) -> None:
        self.signal = signum
        self.event.set()

    def wait(self) -> None:
        """Block the main thread until stopped.

        In short waits, never one unbounded wait: the kernel may hand a
        process-directed SIGTERM to one of zenoh's threads, and Python runs its
        handler only when the main thread next executes bytecode, which a
        thread blocked in ``Event.wait()`` never does (a cloud sat out a
        SIGTERM until SIGKILLed, py-spy showed it in ``Event.wait``).
        """
        while not self.event.wait(0.2):
            pass

    def restore(self) -> None:
        for sig, old in self._old.items():
            try:
                signal.signal(sig, old)
            except Exception:
                pass
        self._old = {}


def write_ready(path: str | Path | None, info: dict) -> None:
    """Atomically write the ready file ``path`` (no-op when None)."""
    if not path:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(dict(info, pid=os.getpid(), t_unix_ns=time.time_ns())) + "\n")
    os.replace(tmp, path)


def clear_ready(path: str | Path | None) -> None:
    """Remove a ready file if present."""
    if path:
        try:
            Path(path).unlink()
        except FileNotFoundError:
            pass


def run_service(
    node: str,
    mesh: MeshConfig,
    *,
    tier: str,
    workers: int | None = None,
    process: str | None = None,
    max_request_bytes: int | None = None,
    ready_file: str | None = None,
    stop: StopFlag | None = None,
    robot_body: Callable | None = None,
    setup: Callable | None = None,
    verbose: bool = False,
    budget_ms: float | None = None,
) -> int:
    """Run a cloud or leader service until stopped.

    Parameters
    ----------
    node : str
        Node name.
    mesh : MeshConfig
        Zenoh settings.
    tier : {"cloud", "leader"}
    workers, process, max_request_bytes, budget_ms
        Passed to :class:`~scmr_mesh.mesh.server.Service`.
    ready_file : str, optional
        Written once the queryable and token are declared.
    robot_body : callable, optional
        ``fn(session, stop_event) -> int`` run on the main thread after the
        service is up (the leader's own robot); the service stops when it
        returns or on a signal.
    setup : callable, optional
        ``fn(service)`` called before attach (hooks: admission, queryables).
    verbose : bool
        Log the start-up phases (wall and CPU time of each, from exec to
        ready; :mod:`scmr_mesh.mesh.startup`); they are in the ready file
        either way.

    Returns
    -------
    int
        Exit status (0 clean).
    """
    from scmr_mesh import keys, wire
    from scmr_mesh.mesh.server import DEFAULT_BUDGET_MS, Service
    from scmr_mesh.mesh.startup import clock as startup_clock
    from scmr_mesh.mesh.work import DEFAULT_PROCESS

    clock = startup_clock()
    if budget_ms is not None and not budget_ms > 0:
        raise InputError(f"--budget-ms must be > 0, got {budget_ms:g}; e.g. --budget-ms 60")
    # a bad setting (lease 0, unknown key, ...) fails here, before workers are
    # forked or any file is created; building a zenoh.Config starts no thread
    mesh.build()
    clock.mark("zenoh config")
    stop = stop or StopFlag().install()
    clear_ready(ready_file)
    prefork = getattr(setup, "prefork", None)
    if callable(prefork):  # the cloud's data process: forked while this is the only thread
        prefork(node)
        clock.mark("data process forked")
    # workers first: they are forked before zenoh starts any thread
    svc = Service(node, tier=tier, workers=workers, process=process or DEFAULT_PROCESS,
                  max_request_bytes=max_request_bytes or wire.MAX_REQUEST_BYTES,
                  budget_ms=DEFAULT_BUDGET_MS if budget_ms is None else budget_ms, clock=clock)
    session = None
    rc = 0
    try:
        if setup is not None:
            setup(svc)
            clock.mark("setup hooks")
        session = open_session(mesh)
        clock.mark("zenoh session")
        svc.attach(session, clock=clock)
        startup = clock.as_dict()
        write_ready(ready_file, {"role": tier, "node": node, "zid": str(session.info.zid()),
                                 "keys": [svc.key, keys.alive(tier, node)], "workers": svc.worker_pids,
                                 "startup": startup})
        log.info("%s %s ready (zid %s) %.0f ms after exec, %.0f ms of CPU%s", tier, node, session.info.zid(),
                 startup["wall_ms"], startup["cpu_ms"], ":\n" + clock.format() if verbose else "")
        after_ready = getattr(getattr(svc, "data", None), "after_ready", None)
        if callable(after_ready):  # work kept off the start-up (the data tier's CA parse)
            after_ready()
        if robot_body is not None:
            rc = int(robot_body(session, stop.event) or 0)
        else:
            stop.wait()
    finally:
        log.info("%s %s stopping", tier, node)
        svc.detach()
        if session is not None:
            close_session(session)
        svc.shutdown()
        clear_ready(ready_file)
        stop.restore()
    if getattr(getattr(svc, "data", None), "failed", False):
        rc = rc or 1  # the cloud's data process died while it ran (logged at ERROR then)
    return rc


def run_candidate(
    node: str,
    mesh: MeshConfig,
    *,
    capability,
    workers: int | None = None,
    process: str | None = None,
    max_request_bytes: int | None = None,
    ready_file: str | None = None,
    stop: StopFlag | None = None,
    robot_body: Callable | None = None,
    setup: Callable | None = None,
    serve_peers: bool = True,
    data_dir: str | Path | None = None,
    sync_period_s: float = 1.0,
    events_path: str | Path | None = None,
    election: dict | None = None,
    verbose: bool = False,
    budget_ms: float | None = None,
) -> int:
    """Run a leader-capable node of the R2R tier until stopped (``scmr leader``,
    ``scmr robot --leader-capable``).

    The worker pool is forked and warmed before Zenoh starts; the node then
    serves peers (unless ``serve_peers`` is off) and runs for the lead
    (:class:`~scmr_mesh.mesh.r2r.R2RNode`).  The ready file is written once
    the start-up grace has passed and the node has decided once; it says
    whether the node leads.

    Parameters
    ----------
    capability : scmr_mesh.mesh.election.Capability
    robot_body : callable, optional
        ``fn(session, stop_event, r2r) -> int`` run on the main thread (the
        node is also a robot).
    data_dir : path, optional
        The relay queue of the node's data tier (``None``: data tier off).
    events_path : path, optional
        JSON lines of this node's role changes.

    Returns
    -------
    int
        Exit status (0 clean).
    """
    from scmr_mesh import wire
    from scmr_mesh.mesh.r2r import R2RNode
    from scmr_mesh.mesh.server import DEFAULT_BUDGET_MS, Service
    from scmr_mesh.mesh.startup import clock as startup_clock
    from scmr_mesh.mesh.work import DEFAULT_PROCESS

    clock = startup_clock()
    mesh.build()
    clock.mark("zenoh config")
    stop = stop or StopFlag().install()
    clear_ready(ready_file)
    svc = Service(node, tier="peer", workers=workers, process=process or DEFAULT_PROCESS,
                  max_request_bytes=max_request_bytes or wire.MAX_REQUEST_BYTES,
                  budget_ms=DEFAULT_BUDGET_MS if budget_ms is None else budget_ms, clock=clock)
    data = None
    session = None
    r2r = None
    rc = 0
    try:
        if setup is not None:
            setup(svc)
        if data_dir is not None:
            from scmr_mesh.mesh.data_service import LeaderData

            data = LeaderData(node, data_dir, sync_period_s=sync_period_s, leading=False)
        r2r = R2RNode(svc, data, capability=capability, serve_peers=serve_peers, events_path=events_path,
                      election=election)
        session = open_session(mesh)
        clock.mark("zenoh session")
        r2r.attach(session)
        clock.mark("peer service and candidacy")
        r2r.wait_settled()
        clock.mark("election settled")
        startup = clock.as_dict()

        def ready() -> None:
            write_ready(ready_file, {"role": "candidate", "node": node, "zid": str(session.info.zid()),
                                     "leading": r2r.role == "leader", "serves": r2r.role,
                                     "keys": [svc.key], "workers": svc.worker_pids,
                                     "capability": capability.source, "startup": startup})

        log.info("candidate %s up (zid %s), %s, %.0f ms after exec, %.0f ms of CPU%s", node, session.info.zid(),
                 "leading" if r2r.role == "leader" else f"serving as {r2r.role}", startup["wall_ms"],
                 startup["cpu_ms"], ":\n" + clock.format() if verbose else "")
        if robot_body is not None:  # also a robot: ready once its robot part is (it calls ready())
            rc = int(robot_body(session, stop.event, r2r, ready) or 0)
        else:
            ready()
            stop.wait()
    finally:
        log.info("candidate %s stopping", node)
        if r2r is not None:
            r2r.close()
        elif data is not None:
            data.close()
        if session is not None:
            close_session(session)
        svc.shutdown()
        clear_ready(ready_file)
        stop.restore()
    return rc


def run_router(mesh: MeshConfig, *, ready_file: str | None = None, stop: StopFlag | None = None) -> int:
    """Run a zenoh router (a session in router mode) until stopped."""
    stop = stop or StopFlag().install()
    clear_ready(ready_file)
    session = open_session(mesh)
    try:
        write_ready(ready_file, {"role": "router", "node": str(session.info.zid()), "zid": str(session.info.zid()),
                                 "keys": []})
        log.info("router ready (zid %s) listen=%s connect=%s", session.info.zid(), mesh.listen, mesh.connect)
        stop.wait()
    finally:
        close_session(session)
        clear_ready(ready_file)
        stop.restore()
    return 0
