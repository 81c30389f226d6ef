"""A whole fleet on one host: ``scmr up`` and ``scmr demo`` as a scenario on the one engine.

:func:`run_fleet` turns a :class:`~scmr_mesh.fleet.plan.FleetConfig` into a
scenario (:func:`~scmr_mesh.fleet.plan.fleet_scenario`: the cloud outage,
``--kill-cloud`` and ``--leader-crash`` are crash faults) and runs it with
:func:`scmr_mesh.scenario.runner.run_scenario` on the ``loopback`` backend, the
engine ``scmr scenario run`` uses too.  What a fleet adds lives in
:class:`FleetHooks`: the live progress line, the rerun sink and, for several
cloud nodes, the run's PostgreSQL server.  The report is the one every run
writes (:func:`scmr_mesh.scenario.report.run_report`), validated by
``schemas/report.schema.json``.

Run directory layout::

    runs/<UTC timestamp>/
        report.json
        logs/<peer>.log             stdout+stderr of cloud, cloud1.., leader, r1..rN
        robots/<id>/records.jsonl   one JSON record per finished request
        robots/<id>/inbox/*.png     the masks each robot received
        ready/<peer>.ready          readiness files; ready/fleet.ready once the whole fleet runs
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scmr_mesh.errors import InputError, MeshError, ScenarioError
from scmr_mesh.fleet.plan import CLOUD, LEADER, RUN_MARKER, FleetConfig, fleet_options, fleet_scenario, ods_backend
from scmr_mesh.scenario.report import run_problems as fleet_problems
from scmr_mesh.scenario.report import validate_report
from scmr_mesh.scenario.runner import Hooks, RecordTail, ScenarioRun, check_out_dir, metric_faults

__all__ = ["FleetHooks", "Progress", "RecordTail", "default_run_dir", "fleet_problems", "run_fleet",
           "validate_report"]

log = logging.getLogger(__name__)

#: Seconds between attempts to start the run's PostgreSQL again after a start failed.
PG_RETRY_S = 1.0


@dataclass
class Progress:
    """A snapshot of a running fleet for the progress display."""

    elapsed_s: float
    duration_s: float
    requests: int
    succeeded: int
    tor_p50_ms: float | None
    tor_p99_ms: float | None
    by_tier: dict[str, int]
    alive: dict[str, bool]
    phase: str = "running"
    events: list[str] = field(default_factory=list)
    leaders: list[str] = field(default_factory=list)


def default_run_dir(root: Path = Path("runs")) -> Path:
    """``runs/<UTC timestamp>`` (with a suffix if it already exists)."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    d = root / stamp
    i = 1
    while d.exists():
        i += 1
        d = root / f"{stamp}-{i}"
    return d


class FleetHooks(Hooks):
    """What ``scmr up`` hangs on the engine: progress, the rerun sink, the run's PostgreSQL."""

    def __init__(self, config: FleetConfig, *, progress: Callable[[Progress], None] | None = None,
                 progress_every_s: float = 0.25) -> None:
        self.config = config
        self.progress = progress
        self.progress_every_s = progress_every_s
        self.fviz = None  # scmr_mesh.viz.FleetViz with rerun flags
        self.pg = None  # scmr_mesh.fleet.pgserver.PgServer when the run starts PostgreSQL
        #: the run's PostgreSQL deaths: {"t_s", "down_unix_ns", "exit", "restarted_unix_ns", "gap_ms", "error"}
        self.ods_outages: list[dict[str, Any]] = []
        #: ``--mcap``: what the merge wrote and which robots' recordings could not be read
        self.mcap: dict[str, Any] | None = None
        self._pg_retry_at = 0.0
        # restarts run off the run's loop, on one thread that lives as long as the server: the
        # server dies with the thread that started it (PR_SET_PDEATHSIG is per thread), so a thread
        # per restart got every restarted server SIGKILLed at once (measured: 17 "outages" in 6 s)
        self._pg_exec: concurrent.futures.ThreadPoolExecutor | None = None
        self._pg_future: concurrent.futures.Future | None = None
        self.ods: str | None = config.ods
        self._last_emit = -1e9
        self._n_seen = 0

    # ------------------------------------------------------------ engine hooks
    def setup(self, run: ScenarioRun) -> None:
        (run.out_dir / RUN_MARKER).write_text("written by scmr up; this folder may be replaced by `scmr demo`\n")
        self.ods = self._start_ods(run)
        run.options = dataclasses.replace(run.options, ods=self.ods)
        if self.config.mcap:  # each robot writes RUN/mcap/<robot>.mcap; merged into --mcap FILE at the end
            run.options = dataclasses.replace(run.options, mcap_dir=str(run.out_dir / "mcap"))
        if self.config.rerun is not None:
            from scmr_mesh.viz import FleetViz

            self.fviz = FleetViz(self.config.rerun, robots=[r.id for r in run.scenario.robots])
            run.options = dataclasses.replace(run.options, robot_args=(*run.options.robot_args,
                                                                        *self.fviz.child_args()))
            log.info("rerun: %s", self.fviz.hint)
            self._emit(run, f"rerun: {self.fviz.hint}")

    def say(self, run: ScenarioRun, message: str) -> None:
        self._emit(run, message)

    def tick(self, run: ScenarioRun) -> None:
        self._watch_ods(run)
        if self.fviz is not None:
            alive = {("cloud", run.scenario.node_of(c)): run.up(c) for c in run.scenario.clouds}
            leaders = set(run.leaders())
            for peer in run.scenario.candidates:  # who leads over time: 1 while a candidate holds the lead
                alive[("leader", run.scenario.node_of(peer))] = run.scenario.node_of(peer) in leaders
            self.fviz.update(alive=alive, records=run.records[self._n_seen:],
                             faults=metric_faults(run.scenario, run.applied, run.t0_unix_ns or 0))
            self._n_seen = len(run.records)
        if time.monotonic() - self._last_emit >= self.progress_every_s:
            self._emit(run, "running")

    def stopped(self, run: ScenarioRun) -> None:
        try:
            self._stop_ods()
            self._merge_mcap(run)
        finally:
            if self.fviz is not None:  # after the peers: their data is in; --save finalises the file
                try:
                    self.fviz.update(faults=metric_faults(run.scenario, run.applied, run.t0_unix_ns or 0))
                    self.fviz.close()
                except Exception as exc:  # the run's report matters more than the recording
                    log.warning("rerun: closing the recording failed: %s", exc)

    # ------------------------------------------------------------ helpers
    def _merge_mcap(self, run: ScenarioRun) -> None:
        """``--mcap FILE``: the robots' recordings (RUN/mcap/*.mcap) as one file, in log-time order."""
        if not self.config.mcap:
            return
        from scmr_mesh.ros.record import merge, readable

        parts = sorted((run.out_dir / "mcap").glob("*.mcap"))
        good, bad = readable(parts)  # a robot killed mid-write leaves a file without its chunks
        self.mcap = {"path": str(self.config.mcap), "parts": len(parts), "messages": 0, "unreadable": bad,
                     "error": None}
        for p, why in bad.items():
            log.error("--mcap: %s cannot be read (%s); merged without it", p, why)
        try:
            self.mcap["messages"] = merge(good, self.config.mcap)
        except Exception as exc:
            self.mcap["error"] = f"{type(exc).__name__}: {exc}"
            log.error("--mcap %s: merging %d robot recordings failed: %s (they are in %s)", self.config.mcap,
                      len(good), exc, run.out_dir / "mcap")
            self._emit(run, f"mcap: merging failed ({exc}); the robots' files are in {run.out_dir / 'mcap'}")
            return
        self._emit(run, f"mcap: {self.mcap['messages']} messages from {len(good)} robots in {self.config.mcap}"
                   + (f"; {len(bad)} recording(s) unreadable (a robot killed mid-write)" if bad else ""))

    def _emit(self, run: ScenarioRun, phase: str) -> None:
        if self.progress is None:
            return
        from scmr_mesh.qos import metrics

        self._last_emit = time.monotonic()
        records = run.records
        recent = metrics.tor_values_ms(records[-200:])
        started = run.sup is not None and run.t0_mono is not None
        leaders = run.leaders() if run.sup is not None else []  # reads every candidate's events: once
        alive = ({CLOUD: any(run.up(c) for c in run.scenario.clouds), LEADER: bool(leaders)}
                 if run.sup is not None and all(c in run.names for c in run.scenario.clouds)
                 else {CLOUD: False, LEADER: False})
        self.progress(Progress(
            elapsed_s=min(run.elapsed_s(), self.config.duration_s), duration_s=self.config.duration_s,
            requests=len(records), succeeded=sum(bool(r.get("ok")) for r in records),
            tor_p50_ms=metrics.percentile(recent, 50) if recent else None,
            tor_p99_ms=metrics.percentile(recent, 99) if recent else None,
            by_tier=metrics.tier_counts(records), alive=alive, phase=phase,
            leaders=leaders if started else [],
        ))

    def _start_ods(self, run: ScenarioRun) -> str | None:
        """Start the run's PostgreSQL server when the fleet needs one; return the cloud nodes' ``--ods``."""
        config = self.config
        if config.ods is not None:
            return config.ods
        if ods_backend(config) == "sqlite":
            return None  # the cloud nodes' default: <run dir>/ods.sqlite
        from scmr_mesh.fleet.pgserver import PgServer, available

        why = available()
        if why:
            raise InputError(f"{config.clouds} cloud nodes share their data store on PostgreSQL, but {why}; "
                             "or run them on one SQLite file with --ods-backend sqlite")
        self._emit(run, "starting the PostgreSQL data store")
        self.pg = PgServer(run.out_dir / "postgres")
        dsn = self.pg.start()
        log.info("data store: PostgreSQL %s (log %s)", dsn, self.pg.log_path)
        return dsn

    def _watch_ods(self, run: ScenarioRun) -> None:
        """Supervise the run's PostgreSQL like a peer: when it died, say so and start it again.

        The outage (from when the death was seen to when the server accepts connections again) goes
        to the report (``ods.outages``) and the console; a start that fails is tried again every
        :data:`PG_RETRY_S` seconds.  The cloud nodes reconnect by themselves, and the robots keep
        their telemetry queued meanwhile.
        """
        pg = self.pg
        if pg is None or time.monotonic() < self._pg_retry_at:
            return
        if self._pg_future is not None and not self._pg_future.done():
            return  # restarting: the run's loop (faults, records, progress) goes on meanwhile
        if pg.alive():
            return
        out = self.ods_outages[-1] if self.ods_outages and self.ods_outages[-1]["restarted_unix_ns"] is None \
            else None
        if out is None:
            rc = pg.proc.returncode if pg.proc is not None else None
            out = {"t_s": round(run.elapsed_s(), 3), "down_unix_ns": time.time_ns(), "exit": rc,
                   "restarted_unix_ns": None, "gap_ms": None, "error": None}
            self.ods_outages.append(out)
            what = f"killed by signal {-rc}" if rc is not None and rc < 0 else f"exited with status {rc}"
            log.error("the run's PostgreSQL data store %s at %.2f s; restarting it (log %s)", what, out["t_s"],
                      pg.log_path)
            self._emit(run, f"PostgreSQL data store {what}; restarting it")
        # stop + start take up to 35 s: in a thread of their own, or every fault and record of the run
        # would wait for them (a review found the loop stalled while a start kept failing)
        if self._pg_exec is None:
            self._pg_exec = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pg-restart")
        self._pg_future = self._pg_exec.submit(self._restart_pg, run, pg, out)

    def _restart_pg(self, run: ScenarioRun, pg, out: dict) -> None:
        try:
            pg.stop(timeout=5.0)  # reaps it and kills what is left of its group (backends hold its memory)
            pg.start(timeout=30.0)
        except Exception as exc:  # PgServerError, OSError, a timeout: the run goes on; tried again
            out["error"] = str(exc)
            self._pg_retry_at = time.monotonic() + PG_RETRY_S
            log.error("restarting the run's PostgreSQL failed (%s); trying again in %g s", exc, PG_RETRY_S)
            return
        out["restarted_unix_ns"] = time.time_ns()
        out["gap_ms"] = round((out["restarted_unix_ns"] - out["down_unix_ns"]) / 1e6, 1)
        out["error"] = None
        log.warning("the run's PostgreSQL data store is back after %.0f ms", out["gap_ms"])
        self._emit(run, f"PostgreSQL data store restarted after {out['gap_ms']:.0f} ms")

    def _stop_ods(self) -> None:
        pg, self.pg = self.pg, None
        if pg is None:
            return
        if self._pg_future is not None:  # a restart in progress ends first (bounded: 5 s stop + 30 s start)
            concurrent.futures.wait([self._pg_future], timeout=40.0)
        try:
            if pg._own_root:  # the server's user could not enter the run dir: the cluster was in /tmp
                log.info("removing the run's PostgreSQL cluster %s (outside the run dir)", pg.root)
                pg.remove()
            else:
                pg.stop()
        finally:
            if self._pg_exec is not None:  # only once the server it may have started is stopped
                self._pg_exec.shutdown(wait=False)

    def ods_name(self, run_dir: Path) -> str:
        if self.ods is None:
            return str(run_dir / "ods.sqlite")
        from scmr_mesh.data.ods_pg import redact

        return redact(str(self.ods))


def run_fleet(
    config: FleetConfig,
    *,
    progress: Callable[[Progress], None] | None = None,
    progress_every_s: float = 0.25,
    hooks: tuple[Hooks, ...] = (),
) -> dict[str, Any]:
    """Run a fleet to the end (or Ctrl-C) and return its validated report.

    The report is also written to ``<run_dir>/report.json``.  Ctrl-C or
    SIGTERM (converted to :class:`KeyboardInterrupt` by the caller) stops the
    fleet early: the report then has ``"interrupted": true``; before the fleet
    was up it raises :class:`KeyboardInterrupt`.  ``hooks`` are more engine
    hooks (tests use them to act on the run as it goes).

    Raises
    ------
    MeshError
        A peer failed to start (the message ends with its log tail).
    """
    from scmr_mesh.scenario.report import run_report
    from scmr_mesh.scenario.runner import run_scenario

    config.check()
    run_dir = Path(config.run_dir) if config.run_dir is not None else default_run_dir()
    check_out_dir(run_dir, flag="--run-dir")
    if config.insecure:
        log.warning("insecure fleet: no authentication, anyone who reaches the ports can join")
    fleet = FleetHooks(config, progress=progress, progress_every_s=progress_every_s)
    try:
        res = run_scenario(fleet_scenario(config), backend="loopback", out_dir=run_dir,
                           options=fleet_options(config), hooks=(fleet, *hooks), ready_timeout=config.ready_timeout_s,
                           insecure=config.insecure, keep_interrupted=True, progress=lambda m: log.info("%s", m))
    except ScenarioError as exc:  # a peer that did not start: scmr up's own error
        raise MeshError(str(exc).removeprefix("scenario fleet: ")) from None
    ods = {"backend": ods_backend(config), "store": fleet.ods_name(run_dir)}
    if ods["backend"] == "postgresql" and config.ods is None:  # a server of the run's own, supervised
        ods["outages"] = fleet.ods_outages
    extra: dict[str, Any] = {"clouds": config.clouds, "ods": ods}
    if fleet.mcap is not None:
        extra["mcap"] = fleet.mcap
    report = run_report(res, extra=extra)
    import json

    (run_dir / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    for h in hooks:
        h.reported(res, report)
    return report
