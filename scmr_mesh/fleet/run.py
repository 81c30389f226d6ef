"""A whole fleet on one host: ``scmr up`` and ``scmr bench mesh``.

:func:`run_fleet` starts one or more cloud nodes, a leader and N robots as
separate OS processes on loopback (each robot listens and connects to every
cloud node and the leader; gossip lets the robots mesh), injects a cloud
outage when asked (every cloud node SIGKILLed at START, restarted at END,
exact times recorded), follows the robots'
``records.jsonl`` for live progress, stops everything (SIGTERM, wait,
SIGKILL, per process group; no orphans even if ``scmr up`` itself is
SIGKILLed, see :mod:`scmr_mesh.fleet.procs`) and returns the report of
:func:`scmr_mesh.qos.metrics.summarize`, validated by
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

import json
import logging
import signal
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scmr_mesh.errors import InputError, MeshError
from scmr_mesh.fleet.plan import (
    CLOUD,
    FLEET_READY,
    LEADER,
    RUN_MARKER,
    FleetConfig,
    cloud_peers,
    ods_backend,
    fleet_topology,
    plan_fleet,
    robot_ids,
    robot_profiles,
)

log = logging.getLogger(__name__)

REPORT_SCHEMA = Path(__file__).resolve().parents[2] / "schemas" / "report.schema.json"


class RecordTail:
    """Read the complete JSON lines appended to a ``records.jsonl`` since last time."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._pos = 0
        self._partial = b""
        self.bad_lines = 0

    def read_new(self) -> list[dict]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self._pos)
                data = f.read()
                self._pos = f.tell()
        except FileNotFoundError:
            return []
        data = self._partial + data
        lines = data.split(b"\n")
        self._partial = lines.pop()  # an incomplete last line waits for its end
        out = []
        for ln in lines:
            if not ln.strip():
                continue
            try:
                out.append(json.loads(ln))
            except json.JSONDecodeError:
                self.bad_lines += 1
                log.warning("%s: skipping a line that is not JSON: %.80r", self.path, ln)
        return out


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


def _free_ports(names: Sequence[str]) -> dict[str, int]:
    import socket

    socks, ports = [], {}
    try:
        for n in names:  # hold them all open so no two peers get the same port
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
            ports[n] = s.getsockname()[1]
    finally:
        for s in socks:
            s.close()
    return ports


def default_run_dir(root: Path = Path("runs")) -> Path:
    """``runs/<UTC timestamp>`` (with a suffix if it already exists)."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    d = root / stamp
    i = 1
    while d.exists():
        i += 1
        d = root / f"{stamp}-{i}"
    return d


def _load_schema() -> dict:
    try:
        return json.loads(REPORT_SCHEMA.read_text())
    except OSError as exc:
        raise MeshError(f"report schema missing at {REPORT_SCHEMA}: {exc}") from None


def validate_report(report: Mapping[str, Any]) -> None:
    """Check ``report`` against ``schemas/report.schema.json``.

    Raises
    ------
    MeshError
        Naming the first field that does not match (a bug in the report code).
    """
    import jsonschema

    v = jsonschema.Draft202012Validator(_load_schema())
    errs = sorted(v.iter_errors(report), key=lambda e: list(e.path))
    if errs:
        e = errs[0]
        where = "/".join(str(x) for x in e.path) or "(top)"
        raise MeshError(f"report does not match schemas/report.schema.json at {where}: {e.message}")


def run_fleet(
    config: FleetConfig,
    *,
    progress: Callable[[Progress], None] | None = None,
    progress_every_s: float = 0.25,
) -> dict[str, Any]:
    """Run a fleet to the end (or Ctrl-C) and return its validated report.

    The report is also written to ``<run_dir>/report.json``.  Ctrl-C or
    SIGTERM (converted to :class:`KeyboardInterrupt` by the caller) stops the
    fleet early: the report then has ``"interrupted": true``.

    Raises
    ------
    MeshError
        A peer failed to start (the message ends with its log tail).
    """
    config.check()
    run = FleetRun(config, progress=progress, progress_every_s=progress_every_s)
    try:
        run.start()   # run directory, rerun sink, servers, then robots, each waited ready
        run.drive()   # until the robots finish: faults on schedule, records, progress
        run.await_restarts()  # a restarted cloud still starting up: ready late, or never
    except KeyboardInterrupt:
        run.interrupted = True
        log.warning("interrupted: stopping the fleet")
    finally:
        run.stop()    # robots first, the data tier's count, everything else, the recording
    if run.t_ready is None:  # interrupted during start-up
        raise KeyboardInterrupt
    return run.report()


class FleetRun:
    """One fleet run, in the steps :func:`run_fleet` calls in order.

    Attributes
    ----------
    run_dir : Path
    specs : dict
        ``{peer: PeerSpec}`` from :func:`~scmr_mesh.fleet.plan.plan_fleet`.
    records : list of dict
        Every robot record read so far.
    faults : list of dict
        The injected faults, with exact times.
    t_ready : float or None
        ``time.monotonic()`` when every peer was ready (None before).
    """

    def __init__(self, config: FleetConfig, *, progress: Callable[[Progress], None] | None = None,
                 progress_every_s: float = 0.25) -> None:
        from scmr_mesh.fleet.procs import Supervisor

        self.config = config
        self.progress = progress
        self.progress_every_s = progress_every_s
        self.run_dir = Path(config.run_dir) if config.run_dir is not None else default_run_dir()
        self.rids = robot_ids(config.robots)
        self.clouds = [name for name, _ in cloud_peers(config.clouds)]
        self.cloud_nodes = dict(cloud_peers(config.clouds))
        self.sup = Supervisor(term_timeout=10.0)
        self.records: list[dict] = []
        self.faults: list[dict] = []
        self.interrupted = False
        self.t_ready: float | None = None
        self.t_end: float | None = None
        self.started_unix_ns: int | None = None
        self.telemetry: dict | None = None
        self.robots_done_unix_ns: int | None = None
        self._killed_once = False  # --kill-cloud done
        self.fviz = None  # scmr_mesh.viz.FleetViz with rerun flags
        self.specs: dict = {}
        self.tails: dict[str, RecordTail] = {}
        self.pg = None  # scmr_mesh.data.pgserver.PgServer when the run starts PostgreSQL
        self.ods: str | None = None  # what the cloud nodes were given as --ods
        self.ods_backend = ods_backend(config)

    # ------------------------------------------------------------ steps
    def start(self) -> None:
        """Prepare the run directory, then start the servers and the robots."""
        config, run_dir = self.config, self.run_dir
        if (run_dir / "robots").is_dir() and any((run_dir / "robots").iterdir()):
            raise InputError(f"run directory {run_dir} already holds a run (robots/ is not empty); "
                             "choose a new --run-dir or delete that one")
        for sub in ("logs", "ready", "robots"):
            (run_dir / sub).mkdir(parents=True, exist_ok=True)
        (run_dir / RUN_MARKER).write_text("written by scmr up; this folder may be replaced by `scmr demo`\n")
        self.ods = self._start_ods()
        self.specs = plan_fleet(config, run_dir, _free_ports([*self.clouds, LEADER, *self.rids]), ods=self.ods,
                                security=self._security())
        self.tails = {rid: RecordTail(run_dir / "robots" / rid / "records.jsonl") for rid in self.rids}
        if config.rerun is not None:
            self.fviz = _start_viz(config.rerun, self.rids, self.specs)
            self._emit(f"rerun: {self.fviz.hint}", 0.0, {CLOUD: False, LEADER: False})
        clouds = "cloud" if config.clouds == 1 else f"{config.clouds} cloud nodes"
        self._emit(f"starting {clouds} and leader", 0.0, {CLOUD: False, LEADER: False})
        t0 = time.monotonic()
        for name in (*self.clouds, LEADER):
            self.sup.start(self.specs[name])
        self.sup.wait_ready([*self.clouds, LEADER], timeout=config.ready_timeout_s)
        log.info("servers ready after %.2f s", time.monotonic() - t0)
        self._emit(f"starting {config.robots} robots", 0.0, self._alive_tiers())
        for rid in self.rids:
            self.sup.start(self.specs[rid])
        self.sup.wait_ready(self.rids, timeout=config.ready_timeout_s)
        self.t_ready = time.monotonic()
        self.started_unix_ns = time.time_ns()
        # for scripts and tests: the whole fleet runs (from now on Ctrl-C/SIGTERM writes a report)
        (run_dir / "ready" / FLEET_READY).write_text(f"{self.started_unix_ns}\n")

    def drive(self) -> None:
        """Until every robot has finished: inject the outage on schedule, follow records, show progress."""
        config = self.config
        grace = 15.0 + (config.deadline_ms or 0) / 1000
        last_emit = 0.0
        warned: set[str] = set()
        while True:
            now = time.monotonic() - self.t_ready
            self._outage_step(now)
            for proc in self.sup.procs.values():  # note every (re)started peer's ready time for the report
                proc.is_ready()
            self._kill_step(now)
            self._leader_crash_step(now)
            n_seen = len(self.records)
            self._read_records()
            if self.fviz is not None:
                alive = {("cloud", node): self._up(name) for name, node in self.cloud_nodes.items()}
                leaders = set(self._leaders())
                for node in self._candidates():  # who leads over time: 1 while a candidate holds the lead
                    alive[("leader", node)] = node in leaders
                self.fviz.update(alive=alive, records=self.records[n_seen:], faults=self.faults)
            exited = self.sup.exited()
            for name, rc in exited.items():
                if not self._expected_exit(name, rc) and name not in warned:
                    warned.add(name)
                    log.warning("peer %s exited with status %s; see %s", name, rc, self.specs[name].log_path)
            if all(r in exited for r in self.rids) and not self._outage_pending():
                self.robots_done_unix_ns = time.time_ns()
                break
            if now > config.duration_s + grace:
                log.warning("robots still running %.0f s after the end; stopping them", grace)
                break
            if self.progress is not None and now - last_emit >= self.progress_every_s:
                last_emit = now
                self._emit("running", min(now, config.duration_s), self._alive_tiers())
            time.sleep(0.05)

    def await_restarts(self) -> None:
        """Wait (up to the ready timeout) for a restarted cloud still starting when the robots finished.

        A cold start can take longer than the rest of the run on a busy box; a
        restart is "never became ready" only when the peer exits or stays
        unready for ``ready_timeout_s`` (docs/FLEET.md).
        """
        fault = self.faults[0] if self.faults else None
        if fault is None or fault["end_unix_ns"] is None or fault["ready_unix_ns"] is not None:
            return
        deadline = time.monotonic() + self.config.ready_timeout_s
        self._emit("waiting for the restarted cloud to become ready", self.config.duration_s, self._alive_tiers())
        while time.monotonic() < deadline and any(self.sup.procs[c].alive() for c in self.clouds):
            self._outage_step(float("inf"))  # notes the ready time once a node is ready
            if fault["ready_unix_ns"] is not None:
                return
            time.sleep(0.05)
        self._outage_step(float("inf"))

    def stop(self) -> None:
        """Stop the robots (they flush their records), count the data tier, stop the rest, close the recording."""
        old = _ignore_interrupts()
        try:
            sup = self.sup
            if sup.procs:
                self._emit("stopping", (time.monotonic() - self.t_ready) if self.t_ready else 0.0,
                           self._alive_tiers() if all(n in sup.procs for n in (*self.clouds, LEADER)) else {})
            try:
                sup.stop([r for r in self.rids if r in sup.procs])
                # data tier (docs/DATA.md): count relayed telemetry while the cloud still runs
                from scmr_mesh.data.report import fleet_telemetry

                self.telemetry = fleet_telemetry(self.run_dir, self.rids,
                                                 wait=any(c in sup.procs and sup.procs[c].alive()
                                                          for c in self.clouds), ods=self.ods)
            except Exception as exc:  # the peers must be stopped whatever happens here
                log.warning("telemetry accounting failed: %s", exc)
            finally:
                sup.stop_all()
                self._stop_ods()
        finally:
            _restore_interrupts(old)
            if self.fviz is not None:  # after the peers: their data is in; --save finalises the file
                try:
                    self.fviz.update(faults=self.faults)
                    self.fviz.close()
                except Exception as exc:  # the run's report matters more than the recording
                    log.warning("rerun: closing the recording failed: %s", exc)
            self.t_end = time.monotonic()

    def report(self) -> dict[str, Any]:
        """The run's report (validated, and written to ``report.json``)."""
        from scmr_mesh.qos import metrics

        config, records = self.config, self.records
        self._read_records()
        report: dict[str, Any] = {"v": 1, "kind": "report"}
        report.update(metrics.summarize(records, self.faults, robots=config.robots))
        report.update({
            "clouds": config.clouds,
            "ods": {"backend": self.ods_backend, "store": self._ods_name()},
            "rate_hz": config.rate_hz,
            "duration_s": config.duration_s,
            "started_unix_ns": self.started_unix_ns,
            "ended_unix_ns": time.time_ns(),
            "wall_s": round(self.t_end - self.t_ready, 3),
            "interrupted": self.interrupted,
            "run_dir": str(self.run_dir),
            "peers": {
                n: {"pid": p.pid, "log": str(p.spec.log_path), "exit": p.popen.returncode,
                    "started_unix_ns": p.started_unix_ns, "ready_unix_ns": p.ready_unix_ns}
                for n, p in self.sup.procs.items()
            },
        })
        for f in report["faults"]:
            if f.get("ready_unix_ns") is not None and f.get("end_unix_ns") is not None:
                # split the failback gap: process start-up, then ready -> first answer
                f["restart_to_ready_ms"] = (f["ready_unix_ns"] - f["end_unix_ns"]) / 1e6
                f["failback_after_ready_ms"] = metrics.failback_gap_ms(
                    records, {**f, "end_unix_ns": f["ready_unix_ns"]})
        if self.telemetry is not None:
            report["telemetry"] = self.telemetry
        report["problems"] = fleet_problems(report)
        report["topology"] = fleet_topology(config)
        profiles = robot_profiles(config)
        if profiles:  # --profiles: the energy model placed each frame (docs/ENERGY.md)
            from scmr_mesh.energy.measure import energy_by_robot

            report["energy"] = {"placement": "energy model (Eq 4.2-4.6), Table 4.3 profiles",
                                "per_robot": energy_by_robot(records, profiles)}
        report["security"] = "insecure" if config.insecure else "mtls+acl"
        report["leadership"] = self._leadership()
        validate_report(report)
        (self.run_dir / "report.json").write_text(json.dumps(report, indent=2) + "\n")
        return report

    # ---------------------------------------------------------- helpers
    def _security(self) -> list[str]:
        """Credentials for every peer in RUN/certs (mutual TLS + access rules), or ``--insecure``."""
        from scmr_mesh.fleet.plan import fleet_identities
        from scmr_mesh.security.runcreds import INSECURE, run_credentials

        if self.config.insecure:
            log.warning("insecure fleet: no authentication, anyone who reaches the ports can join")
            return list(INSECURE)
        return run_credentials(self.run_dir, fleet_identities(self.config)).args()

    def _start_ods(self) -> str | None:
        """Start the run's PostgreSQL server when the fleet needs one; return the cloud nodes' ``--ods``."""
        config = self.config
        if config.ods is not None:
            return config.ods
        if self.ods_backend == "sqlite":
            return None  # the cloud nodes' default: <run dir>/ods.sqlite
        from scmr_mesh.data.pgserver import PgServer, available

        why = available()
        if why:
            raise InputError(f"{config.clouds} cloud nodes share their data store on PostgreSQL, but {why}; "
                             "or run them on one SQLite file with --ods-backend sqlite")
        self._emit("starting the PostgreSQL data store", 0.0, {CLOUD: False, LEADER: False})
        self.pg = PgServer(self.run_dir / "postgres")
        dsn = self.pg.start()
        log.info("data store: PostgreSQL %s (log %s)", dsn, self.pg.log_path)
        return dsn

    def _stop_ods(self) -> None:
        pg, self.pg = self.pg, None
        if pg is None:
            return
        if pg._own_root:  # the server's user could not enter the run dir: the cluster was in /tmp
            log.info("removing the run's PostgreSQL cluster %s (outside the run dir)", pg.root)
            pg.remove()
        else:
            pg.stop()

    def _ods_name(self) -> str:
        if self.ods is None:
            return str(self.run_dir / "ods.sqlite")
        from scmr_mesh.data.ods_pg import redact

        return redact(str(self.ods))

    def _outage_step(self, now: float) -> None:
        """SIGKILL every cloud node at the outage's start, restart them at its end, note when the first is ready."""
        outage = self.config.cloud_outage
        if outage is None:
            return
        fault = next((f for f in self.faults if f.get("tier") == "cloud"), None)
        if fault is None and now >= outage[0]:
            t_kill = min(self.sup.kill(c) for c in self.clouds)
            self.faults.append({"kind": "crash", "target": fault_target(self.cloud_nodes), "tier": "cloud",
                                "start_unix_ns": t_kill, "end_unix_ns": None, "ready_unix_ns": None,
                                "robots": None})
            log.info("cloud tier (%s) SIGKILLed at %.3f s", fault_target(self.cloud_nodes), now)
        elif fault is not None and fault["end_unix_ns"] is None and now >= outage[1]:
            fault["end_unix_ns"] = min(self.sup.restart(c).started_unix_ns for c in self.clouds)
            log.info("cloud tier restarted at %.3f s", now)
        elif fault is not None and fault["end_unix_ns"] is not None and fault["ready_unix_ns"] is None:
            ready = [self.sup.procs[c].ready_unix_ns for c in self.clouds if self.sup.procs[c].is_ready()]
            if ready:  # the tier is back with its first node
                fault["ready_unix_ns"] = min(ready)

    def _kill_step(self, now: float) -> None:
        """SIGKILL one cloud node (``--kill-cloud``) on schedule; it stays down."""
        kill = self.config.kill_cloud
        if kill is None or self._killed_once or now < kill[1]:
            return
        name, node = list(self.cloud_nodes.items())[kill[0]]
        t_kill = self.sup.kill(name)
        self._killed_once = True
        # the cloud tier stays (other nodes serve): a fault that takes away no tier
        self.faults.append({"kind": "crash", "target": node, "tier": "cloud" if self.config.clouds == 1 else None,
                            "start_unix_ns": t_kill, "end_unix_ns": None, "ready_unix_ns": None, "robots": None})
        log.info("cloud node %s SIGKILLed at %.3f s (not restarted)", node, now)

    def _killed(self, name: str) -> bool:
        kill = self.config.kill_cloud
        return kill is not None and name == list(self.cloud_nodes)[kill[0]] and self._killed_once
    def _leader_crash_step(self, now: float) -> None:
        """SIGKILL whichever node leads at ``--leader-crash`` (once)."""
        at = self.config.leader_crash_s
        if at is None or now < at or any(f["kind"] == "crash" and f.get("tier") == "leader" for f in self.faults):
            return
        leaders = self._leaders()
        if not leaders:
            return  # nobody leads yet: try again at the next step
        node = leaders[0]
        peer = LEADER if node == "leader0" else node
        t_kill = self.sup.kill(peer)
        self.faults.append({"kind": "crash", "target": node, "peer": peer, "tier": "leader",
                            "start_unix_ns": t_kill, "end_unix_ns": None, "ready_unix_ns": None, "robots": None,
                            "fallback": ["peer", "leader"]})
        log.info("leader %s SIGKILLed at %.3f s", node, now)

    def _outage_pending(self) -> bool:
        """Whether the cloud is still down, to be restarted."""
        return any(f.get("tier") == "cloud" and f["end_unix_ns"] is None for f in self.faults)

    def _expected_exit(self, name: str, rc: int | None) -> bool:
        crashed = {f["target"] for f in self.faults if f["kind"] == "crash" and f.get("tier") == "leader"}
        return ((name in self.rids and rc == 0) or (name in self.clouds and self._outage_pending())
                or self._killed(name) or self._node(name) in crashed)

    def _read_records(self) -> None:
        for rid in self.rids:
            if rid in self.tails:
                self.records.extend(self.tails[rid].read_new())

    def _up(self, name: str) -> bool:
        p = self.sup.procs.get(name)
        return p is not None and p.alive() and p.is_ready()

    def _node(self, peer: str) -> str:
        return self.cloud_nodes.get(peer) or ("leader0" if peer == LEADER else peer)

    def _candidates(self) -> list[str]:
        topo = fleet_topology(self.config)
        return [self._node(p) for p, t in topo.items() if t["leader_capable"]]

    def _leadership(self) -> dict[str, Any]:
        """The report's ``leadership`` block from the candidates' role changes (scmr_mesh.qos.leadership)."""
        import signal as _signal

        from scmr_mesh.qos.leadership import leadership, read_events

        ended = {}
        for name, p in self.sup.procs.items():  # a killed candidate writes no step_down
            kills = [t for sig, t in p.signalled if sig == _signal.SIGKILL]
            if kills:
                ended[self._node(name)] = kills[0]
        return leadership(read_events(self.run_dir / "leadership"), self.records, self.faults,
                          t0_unix_ns=self.started_unix_ns or 0, ended=ended,
                          end_unix_ns=(self.started_unix_ns or 0) + int(self.config.duration_s * 1e9))

    def _leaders(self) -> list[str]:
        """Who leads now, from the candidates' role changes and the processes alive."""
        from scmr_mesh.qos.leadership import read_events

        leading: set[str] = set()
        for e in read_events(self.run_dir / "leadership"):
            (leading.add if e["event"] == "lead" else leading.discard)(e["node"])
        dead = {self._node(n) for n, p in self.sup.procs.items() if not p.alive()}
        return sorted(leading - dead)

    def _alive_tiers(self) -> dict[str, bool]:
        """``{"cloud": any cloud node up, "leader": leader up}``."""
        return {CLOUD: any(self._up(c) for c in self.clouds), LEADER: bool(self._leaders())}

    def _emit(self, phase: str, elapsed: float, alive: dict[str, bool]) -> None:
        if self.progress is None:
            return
        from scmr_mesh.qos import metrics

        records = self.records
        recent = metrics.tor_values_ms(records[-200:])
        self.progress(Progress(
            elapsed_s=elapsed, duration_s=self.config.duration_s, requests=len(records),
            succeeded=sum(bool(r.get("ok")) for r in records),
            tor_p50_ms=metrics.percentile(recent, 50) if recent else None,
            tor_p99_ms=metrics.percentile(recent, 99) if recent else None,
            by_tier=metrics.tier_counts(records), alive=alive, phase=phase,
            leaders=self._leaders() if self.t_ready is not None else [],
        ))


def fault_target(cloud_nodes: Mapping[str, str]) -> str:
    """The ``target`` of a cloud-tier fault: the node names, comma-separated (``cloud0`` for one)."""
    return ",".join(cloud_nodes.values())


def fleet_problems(report: Mapping[str, Any]) -> list[str]:
    """What went wrong in a fleet run besides failed requests, one sentence each (pure).

    A restarted peer that never became ready, a peer that exited with a
    non-zero status, telemetry that was lost or could not be counted.  An
    interrupted run lists what it saw too.  ``scmr up`` and ``scmr demo``
    print these and exit 1 when there is any (docs/FLEET.md).
    """
    out: list[str] = []
    t0 = report.get("started_unix_ns") or 0
    peers = report.get("peers") or {}
    for f in report.get("faults") or []:
        if f.get("end_unix_ns") is None:
            continue
        # the restarted peers: every cloud node for a cloud-tier crash (scmr up restarts them all)
        names = [n for n in peers if n.startswith(CLOUD)] if f.get("tier") == "cloud" else [str(f.get("target"))]
        never = [n for n in names if n in peers and peers[n].get("ready_unix_ns") is None]
        if f.get("ready_unix_ns") is None and not never:
            never = names or [str(f.get("target"))]
        for name in never:
            p = peers.get(name) or {}
            rc = p.get("exit")
            label = f.get("target") if len(names) <= 1 else name
            out.append(f"{label} was restarted at {(f['end_unix_ns'] - t0) / 1e9:.2f} s but never became "
                       "ready" + (f" (it exited with status {rc})" if rc not in (None, 0) else "")
                       + (f"; see {p['log']}" if p.get("log") else ""))
    # peers a fault killed on purpose (a leader crash, --kill-cloud) and nobody restarted
    killed = {str(f.get(k)) for f in report.get("faults") or [] if f.get("kind") == "crash"
              and f.get("end_unix_ns") is None for k in ("peer", "target") if f.get(k)}
    for name, p in peers.items():
        rc = p.get("exit")
        if rc not in (None, 0) and not (rc == -9 and name in killed):
            what = f"killed by signal {-rc}" if rc < 0 else f"exited with status {rc}"
            out.append(f"peer {name} {what}; see {p.get('log')}")
    tel = report.get("telemetry")
    if tel is None:
        out.append("telemetry was not counted (see the log of scmr up)")
    else:
        if tel.get("error"):
            out.append(f"telemetry: {tel['error']}")
        if tel.get("lost"):
            who = [f"{rid} {r['lost']} (seqs {','.join(r.get('missing') or []) or '?'})"
                   for rid, r in sorted((tel.get("per_robot") or {}).items()) if r.get("lost")]
            out.append(f"{tel['lost']} of {tel.get('sent', 0)} telemetry records lost: " + "; ".join(who))
        if tel.get("conflicts"):
            out.append(f"{tel['conflicts']} telemetry records conflicted with stored ones (a robot reused seqs)")
    return out


def _start_viz(options, rids: Sequence[str], specs: dict) -> Any:
    """Start the rerun sink (scmr_mesh.viz) and hand it to every robot's command line."""
    import dataclasses

    from scmr_mesh.viz import FleetViz

    fviz = FleetViz(options, robots=rids)
    for rid in rids:
        specs[rid] = dataclasses.replace(specs[rid], argv=[*specs[rid].argv, *fviz.child_args()])
    log.info("rerun: %s", fviz.hint)
    return fviz


def _ignore_interrupts():
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    return (signal.signal(signal.SIGINT, signal.SIG_IGN), signal.signal(signal.SIGTERM, signal.SIG_IGN))


def _restore_interrupts(old) -> None:
    if old is not None:
        signal.signal(signal.SIGINT, old[0])
        signal.signal(signal.SIGTERM, old[1])


