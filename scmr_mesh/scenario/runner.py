"""Run a scenario: build the backend, start the peers, play the faults, collect records.

The runner is the only impure part of the scenario package besides the
backends: it starts real ``scmr cloud|leader|robot`` processes through the
shared :class:`scmr_mesh.fleet.procs.Supervisor`, sleeps until each event of
:func:`scmr_mesh.scenario.plan.compile_timeline` is due, applies it (network
events through the backend, crash/restart through the supervisor) and records
when each fault really took effect.  Everything is undone in ``finally`` and
on SIGTERM/SIGINT/SIGHUP (turned into ``KeyboardInterrupt``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from scmr_mesh.errors import ConfigError, ScenarioError
from scmr_mesh.qos.faults import FaultRecord
from scmr_mesh.scenario.faults import AppliedFault, fault_records, fault_tier, metric_faults
from scmr_mesh.scenario.hooks import Hooks, RecordTail, Say
from scmr_mesh.scenario.plan import (RADIO, Event, RunOptions, compile_timeline, peer_command, router_command,
                                     swarm_groups)
from scmr_mesh.scenario.spec import WHOEVER_LEADS, Scenario

__all__ = ["AppliedFault", "Hooks", "RecordTail", "RunResult", "ScenarioRun", "default_data_dir", "fault_records",
           "fault_tier", "metric_faults", "run_scenario"]

log = logging.getLogger(__name__)

Progress = Callable[[str], None]


#: Seconds a robot asked to stop (SIGTERM) may take before SIGKILL: its drain phase (``scmr robot
#: --drain-s``, default 5 s: queued telemetry sent while a tier takes it) plus writing its summary.
ROBOT_STOP_S = 10.0


def default_data_dir() -> Path:
    """``$SCMR_DATA`` or ``<repo>/../shared/data/roads``."""
    env = os.environ.get("SCMR_DATA")
    if env:
        return Path(env)
    shared = Path(os.environ.get("SCMR_SHARED", Path(__file__).resolve().parents[3] / "shared"))
    return shared / "data" / "roads"


@dataclass
class RunResult:
    """What a run produced: records, fault times, backend notes, paths."""

    scenario: Scenario
    backend: str
    out_dir: Path
    t0_unix_ns: int
    records: list[dict[str, Any]]
    faults: list[AppliedFault]
    notes: list[str]
    run_id: str = ""
    peer_logs: dict[str, str] = field(default_factory=dict)
    #: The data tier's count ({"sent", "stored", "duplicates", "lost", "per_robot"}), also in
    #: ``out_dir/telemetry.json``; None when it could not be counted (docs/DATA.md).
    telemetry: dict[str, Any] | None = None
    #: Each peer's role, what it was handed to connect to, and whether it ran for the lead.
    topology: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: When the first robot was started (robots stop ``duration_s`` after their start).
    robots_started_unix_ns: int | None = None
    #: Each process the run started: pid, log, exit status, start and ready times (unix ns).
    peers: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Node -> when a fault SIGKILLed it (a killed candidate writes no step_down).
    killed_unix_ns: dict[str, int] = field(default_factory=dict)
    #: Stopped early by Ctrl-C/SIGTERM (``run_scenario(keep_interrupted=True)``).
    interrupted: bool = False
    #: Seconds from time 0 to the last peer stopped.
    wall_s: float | None = None
    #: The peers ran without authentication (``--insecure``).
    insecure: bool = False
    #: Per host at half time: peak RSS (MB), CPU (s), sockets, TCP links (netns) (``ScenarioRun.sample_costs``).
    costs: dict[str, dict[str, Any]] = field(default_factory=dict)

    def leadership(self) -> dict[str, Any]:
        """The ``leadership`` block from the candidates' role changes (``out_dir/leadership``)."""
        from scmr_mesh.qos.leadership import leadership, read_events

        faults = [dataclasses.replace(f, peer=af.resolved or af.fault.peer, groups=af.fault.groups)
                  for f, af in zip(self.fault_records(), self.faults)]
        return leadership(read_events(self.out_dir / "leadership"), self.records, faults,
                          t0_unix_ns=self.t0_unix_ns, ended=self.killed_unix_ns,
                          # robots send for duration_s from about t0; the first graceful stop of a
                          # candidate (a robot finishing) also ends the window (qos.leadership)
                          end_unix_ns=self.t0_unix_ns + int(self.scenario.duration_s * 1e9))

    def fault_records(self) -> list[FaultRecord]:
        """The faults as they took effect (the one fault type metrics, leadership and reports read)."""
        return fault_records(self.scenario, self.faults, self.t0_unix_ns)

    def metric_faults(self) -> list[dict[str, Any]]:
        """:meth:`fault_records` in their JSON form."""
        return [f.as_dict() for f in self.fault_records()]


def _image_dir(scenario: Scenario, robot_set: str, data_dir: Path, out_dir: Path, robot: str) -> Path:
    d = out_dir / "images" / robot
    d.mkdir(parents=True, exist_ok=True)
    for i, rel in enumerate(scenario.image_sets[robot_set]):
        src = (data_dir / rel).resolve()
        if not src.is_file():
            raise ConfigError(
                f"scenario {scenario.source}: field 'image_sets.{robot_set}': image {rel!r} not found under "
                f"{data_dir}; pass --data with the folder that holds it (the shared data/roads)")
        link = d / f"{i:02d}_{src.name}"
        if not link.exists():
            link.symlink_to(src)  # read in place: never copied
    return d


def check_out_dir(out_dir: Path, *, flag: str = "--out") -> None:
    """Refuse a folder that already holds a scenario run.

    Peers append to ``robots/*/records.jsonl``, ``leadership/*.jsonl`` and their queues: an
    old run's records and leadership events would mix with the new run's (a bench series
    into reused folders reported an old run's leader as a second leader).

    Raises
    ------
    ScenarioError
        One line naming the folder, what is in it, and the fix.
    """
    out_dir = Path(out_dir)
    used = [d for d in ("robots", "leadership", "logs", "queues") if (out_dir / d).is_dir() and any((out_dir / d).iterdir())]
    if used:
        raise ScenarioError(f"output folder {out_dir} already holds a scenario run ({'/, '.join(used)}/ not empty); "
                            f"give a new {flag} or delete that folder")


def router_hosts(scenario: Scenario, be) -> dict[str, str]:
    """Under ``shape = "routers"``: each host's router name -> the peer whose host it is (the first
    peer on it); one per peer on netns, one for the whole host on loopback."""
    out: dict[str, str] = {}
    for p in scenario.peer_names:
        host = be.host_of(p)
        name = scenario.router_of(p) if host == p else f"router-{host}"
        out.setdefault(name, p)
    return out


def scenario_identities(scenario: Scenario, routers: Sequence[str] = ()):
    """The identities of a scenario's peers (pure): names, roles, lead grants; ``routers``: router names."""
    from scmr_mesh.security.credentials import Peer

    capable = set(scenario.candidates)
    out = []
    for p in scenario.peers:
        role, node = scenario.role(p.name), scenario.node_of(p.name)
        if role == "robot":
            out.append(Peer(node, "robot", leader_capable=p.name in capable, priority_cap=0))
        elif role == "leader":
            out.append(Peer(node, "leader", leader_capable=True, priority_cap=0))
        else:
            out.append(Peer(node, role))
    out += [Peer(n, "router") for n in routers]  # the routers of the hosts: trusted infrastructure
    return out


def _security(scenario: Scenario, be, out_dir: Path, insecure: bool) -> list[str]:
    """Credentials for every peer in OUT/certs, valid for every address peers listen on; or --insecure."""
    from scmr_mesh.security.runcreds import INSECURE, run_credentials

    if insecure:
        return list(INSECURE)
    eps = [ep for p in scenario.peers for ep in be.listen(p.name)]
    routers: list[str] = []
    if scenario.shape == "routers":
        eps += [be.router_endpoint(p.name) for p in scenario.peers]
        routers = list(router_hosts(scenario, be))
    hosts = sorted({ep.split("/", 1)[1].rsplit(":", 1)[0].strip("[]") for ep in eps if "/" in ep}
                   - {"127.0.0.1", "::1"})
    return run_credentials(out_dir, scenario_identities(scenario, routers), hosts=hosts).args()


def _make_backend(scenario: Scenario, backend: str):
    if scenario.shape == "routers" and backend == "proxy":
        raise ScenarioError(f"scenario {scenario.name}: topology.shape = \"routers\" runs on --backend netns "
                            "(root: real radio links between hosts) or --backend loopback (no link faults), "
                            "not on proxy")
    if backend == "netns":
        from scmr_mesh.scenario.netns import NetnsBackend, check_root

        check_root()
        return NetnsBackend(scenario)
    if backend == "proxy":
        from scmr_mesh.scenario.proxy import ProxyBackend

        return ProxyBackend(scenario)
    if backend == "loopback":
        from scmr_mesh.scenario.loopback import LoopbackBackend

        return LoopbackBackend(scenario)
    raise ConfigError(f"backend must be netns, proxy or loopback, got {backend!r}")


class ScenarioRun:
    """One run of a scenario on a backend: the steps :func:`run_scenario` calls in order.

    Attributes a hook may read: ``scenario``, ``backend``, ``out_dir``, ``options``,
    ``sup`` (the :class:`~scmr_mesh.fleet.procs.Supervisor`), ``names`` (peer -> the
    name its current process runs under), ``applied`` (the faults as they took effect),
    ``records`` (robot records read so far), ``t0_unix_ns``/``t0_mono`` (time 0, when
    every robot was ready; None before).
    """

    def __init__(self, scenario: Scenario, *, backend: str, out_dir: Path, data_dir: Path | None,
                 options: RunOptions, hooks: list[Hooks], ready_timeout: float, insecure: bool) -> None:
        self.scenario = scenario
        self.backend_name = backend
        self.out_dir = Path(out_dir)
        self.data_dir = Path(data_dir) if data_dir is not None else default_data_dir()
        self.options = options
        self.hooks = hooks
        self.ready_timeout = ready_timeout
        self.insecure = insecure
        self.be = None
        self.sup = None
        self.names: dict[str, str] = {}
        #: peer -> the name of the current process of its host's router (``shape = "routers"``)
        self.routers: dict[str, str] = {}
        self.starts: dict[str, int] = {}
        self.handed: dict[str, list[str]] = {}
        self.security: list[str] = []
        self.images: dict[str, Path] = {}
        self.applied = [AppliedFault(i, f) for i, f in enumerate(scenario.faults)]
        self.notes: list[str] = []
        self.records: list[dict[str, Any]] = []
        self.tails: dict[str, RecordTail] = {}
        self.t0_unix_ns: int | None = None
        self.t0_mono: float | None = None
        self.robots_started: int | None = None
        self.robots_done_unix_ns: int | None = None
        self.ended_mono: float | None = None
        self.telemetry: dict[str, Any] | None = None
        self.interrupted = False
        self.costs: dict[str, dict[str, Any]] = {}
        self._warned: set[str] = set()

    # ------------------------------------------------------------ hooks
    def say(self, message: str) -> None:
        for h in self.hooks:
            h.say(self, message)

    def _hook(self, what: str) -> None:
        for h in self.hooks:
            getattr(h, what)(self)

    # ------------------------------------------------------------ state
    def elapsed_s(self) -> float:
        """Seconds since time 0 (0 before it)."""
        return 0.0 if self.t0_mono is None else time.monotonic() - self.t0_mono

    def proc(self, peer: str):
        """The current process of ``peer`` (None before it started)."""
        return self.sup.procs.get(self.names.get(peer, "")) if self.sup is not None else None

    def up(self, peer: str) -> bool:
        """Whether ``peer``'s current process runs and is ready."""
        p = self.proc(peer)
        return p is not None and p.alive() and p.is_ready()

    def leaders(self) -> list[str]:
        """The nodes that lead now: from the candidates' role changes, less dead processes."""
        from scmr_mesh.qos.leadership import read_events

        leading: set[str] = set()
        for e in read_events(self.out_dir / "leadership"):
            (leading.add if e["event"] == "lead" else leading.discard)(e["node"])
        dead = {self.scenario.node_of(p) for p in self.names if not (self.proc(p) and self.proc(p).alive())}
        return sorted(leading - dead)

    def spec_for(self, peer: str, *, remaining_s: float | None = None):
        """The :class:`~scmr_mesh.fleet.procs.PeerSpec` of the next start of ``peer``."""
        from scmr_mesh.fleet.procs import PeerSpec

        cmd = self._command(peer, remaining_s=remaining_s)
        env = {"SCMR_SCENARIO_SEED": str(self.scenario.seed)}
        return PeerSpec(cmd.name, self.be.wrap(peer, list(cmd.argv)), log_path=cmd.log_path,
                        ready_file=cmd.ready_file, env=env)

    def _command(self, peer: str, *, remaining_s: float | None = None):
        """The :class:`~scmr_mesh.scenario.plan.PeerCommand` of the next start of ``peer``."""
        n = self.starts[peer] = self.starts.get(peer, 0) + 1
        be = self.be
        if self.scenario.shape == "routers":  # a client of its host's router
            where = dict(listen=[], connect=[be.router_endpoint(peer)], zmode="client")
        else:
            where = dict(listen=be.listen(peer), connect=be.connect(peer))
        cmd = peer_command(self.scenario, peer, run_dir=self.out_dir, extra_cfg=be.extra_cfg(peer),
                           security=self.security, options=self.options, images=self.images, start=n,
                           remaining_s=remaining_s, **where)
        cmd.ready_file.parent.mkdir(parents=True, exist_ok=True)
        self.handed[cmd.name if self.options.restart_renames or n == 1 else f"{cmd.name}-{n}"] = \
            list(cmd.argv[3 + self.options.verbose:])  # what each peer was told (peers.json)
        if self.scenario.role(peer) == "robot" and cmd.name not in self.tails:
            self.tails[cmd.name] = RecordTail(self.out_dir / "robots" / cmd.name / "records.jsonl")
        return cmd

    def start_swarm(self, robots: Sequence[str]):
        """Start one ``scmr swarm`` process playing ``robots`` (each its own identity and session)."""
        from scmr_mesh.fleet.procs import PeerSpec

        name = f"swarm-{robots[0]}"
        head = 3 + int(self.options.verbose)  # python -m scmr_mesh [-v] robot ...
        members = []
        for rid in robots:
            argv = list(self._command(rid).argv)
            assert argv[head] == "robot", argv
            members.append(argv[head + 1:])
        plan = self.out_dir / "swarms" / f"{name}.json"
        plan.parent.mkdir(parents=True, exist_ok=True)
        plan.write_text(json.dumps({"robots": members}, indent=1) + "\n")
        ready = self.out_dir / "ready" / f"{name}.ready"
        argv = [self.options.python, "-m", "scmr_mesh"] + (["-v"] if self.options.verbose else [])
        argv += ["swarm", "--plan", str(plan), "--ready-file", str(ready)]
        spec = PeerSpec(name, self.be.wrap(robots[0], argv), log_path=self.out_dir / "logs" / f"{name}.log",
                        ready_file=ready, env={"SCMR_SCENARIO_SEED": str(self.scenario.seed)})
        proc = self.sup.start(spec)
        for rid in robots:
            self.names[rid] = name
        return proc

    def router_spec(self, peer: str):
        """The :class:`~scmr_mesh.fleet.procs.PeerSpec` of the next start of ``peer``'s host router."""
        from scmr_mesh.fleet.procs import PeerSpec

        be, sc = self.be, self.scenario
        name = next(n for n, p in router_hosts(sc, be).items() if p == peer)
        key = f"router:{name}"
        n = self.starts[key] = self.starts.get(key, 0) + 1
        one_host = be.host_of(peer) != peer  # every peer on one host: one router, nobody to dial
        cmd = router_command(sc, peer, run_dir=self.out_dir, listen=[be.router_endpoint(peer)],
                             connect=[] if one_host else [be.router_endpoint(q) for q in sc.router_dials(peer)],
                             security=self.security, options=self.options, start=n, name=name)
        cmd.ready_file.parent.mkdir(parents=True, exist_ok=True)
        self.handed[cmd.name] = list(cmd.argv[3 + self.options.verbose:])
        return PeerSpec(cmd.name, be.wrap(peer, list(cmd.argv)), log_path=cmd.log_path, ready_file=cmd.ready_file)

    def start_router(self, peer: str, *, wait: bool = True):
        """Start the router of ``peer``'s host (``shape = "routers"``); with ``wait``, until it is ready."""
        rep = router_hosts(self.scenario, self.be)
        host = next(p for n, p in rep.items() if self.be.host_of(p) == self.be.host_of(peer))
        spec = self.router_spec(host)
        proc = self.sup.start(spec)
        for p in self.scenario.peer_names:
            if self.be.host_of(p) == self.be.host_of(peer):
                self.routers[p] = spec.name
        if wait:
            self.sup.wait_ready([spec.name], timeout=self.ready_timeout)
        return proc

    def _router_up(self, peer: str) -> bool:
        name = self.routers.get(peer)
        proc = self.sup.procs.get(name) if name else None
        return proc is not None and proc.alive()

    def _host_down(self, peer: str) -> bool:
        """Whether no peer on ``peer``'s host runs any more (a crash of the last one takes the host)."""
        host = self.be.host_of(peer)
        return not any(self.proc(p) is not None and self.proc(p).alive()
                       for p in self.scenario.peer_names if self.be.host_of(p) == host)

    def start_peer(self, peer: str, *, remaining_s: float | None = None):
        spec = self.spec_for(peer, remaining_s=remaining_s)
        proc = self.sup.start(spec)
        self.names[peer] = spec.name
        return proc

    # ------------------------------------------------------------ steps
    def prepare(self) -> None:
        """The run folder, image links, the backend and the hooks' setup."""
        check_out_dir(self.out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        sc = self.scenario
        self.images = {r.id: _image_dir(sc, r.image_set, self.data_dir, self.out_dir, r.id)
                       for r in sc.robots if r.image_set}
        self.be = _make_backend(sc, self.backend_name)
        self._hook("setup")

    def start(self) -> None:
        """Set up the backend, start the servers, then the robots, each waited ready; write time 0."""
        from scmr_mesh.fleet.procs import Supervisor

        sc, be = self.scenario, self.be
        self.sup = Supervisor(term_timeout=5.0)
        rid = getattr(be, "run_id", "")
        self.say(f"[{self.backend_name}] setting up {len(sc.peers)} peers, {len(sc.links)} links"
                 + (f" (namespaces scmrs-{rid}-*)" if rid else ""))
        be.setup()
        initial = [ev for ev in compile_timeline(sc) if ev.fault == RADIO and ev.at_s == 0.0]
        if initial:  # pairs out of radio range (and bandwidth by distance) before any peer starts
            self.say(f"radio topology: {sum(ev.op == 'block' for ev in initial)} pairs out of range at time 0")
            be.apply_many(initial)
        self.security[:] = _security(sc, be, self.out_dir, self.insecure)
        if sc.shape == "routers":
            hosts = router_hosts(sc, be)
            for p in hosts.values():
                self.start_router(p, wait=False)
            self.sup.wait_ready(sorted(set(self.routers.values())), timeout=self.ready_timeout)
            self.say(f"routers ready: one on each of the {len(hosts)} host(s); every peer is its host "
                     "router's client")
        servers = [p.name for p in sc.peers if p.role != "robot"]
        for p in servers:
            self.start_peer(p)
        self.sup.wait_ready([self.names[p] for p in servers], timeout=self.ready_timeout)
        self.say(f"servers ready: {', '.join(servers)}; starting {len(sc.robots)} robots")
        self.robots_started = time.time_ns()
        groups = swarm_groups(sc, self.options.robots_per_process, be.host_of)
        for g in groups:
            self.start_peer(g[0]) if len(g) == 1 else self.start_swarm(g)
        swarms = sum(len(g) > 1 for g in groups)
        if swarms:
            self.say(f"{sum(len(g) for g in groups if len(g) > 1)} robots played by {swarms} swarm process(es) "
                     f"(--robots-per-process {self.options.robots_per_process})")
        self.sup.wait_ready(sorted({self.names[r.id] for r in sc.robots}), timeout=self.ready_timeout)
        self.t0_unix_ns = time.time_ns()
        self.t0_mono = time.monotonic()
        (self.out_dir / "ready" / self.options.start_file).write_text(f"{self.t0_unix_ns}\n")
        self.say(f"robots ready; run of {sc.duration_s:g}s starts (seed {sc.seed})")

    def play(self) -> None:
        """Apply the timeline's events when due, then wait for the robots to finish."""
        sc = self.scenario
        for batch in _batches([ev for ev in compile_timeline(sc) if not (ev.fault == RADIO and ev.at_s == 0.0)]):
            self.wait_until(self.t0_mono + batch[0].at_s)
            if batch[0].op == "kill" and batch[0].target[0] == WHOEVER_LEADS:
                batch = self._resolve_leader(batch)
                if batch is None:
                    continue
            if batch[0].op == "start" and batch[0].target[0] == WHOEVER_LEADS:
                hit = self.applied[batch[0].fault].resolved
                if hit is None:
                    continue  # nobody led, nobody was crashed: nothing to restart
                batch = [dataclasses.replace(ev, target=(hit,)) for ev in batch]
            router = None
            if sc.shape == "routers" and batch[0].op == "start" and not self._router_up(batch[0].target[0]):
                router = self.start_router(batch[0].target[0])  # the host comes back: its router first
            _apply_batch(batch, self.be, self.sup, self.names, self.applied, self._restart_spec, sc,
                         self.t0_mono, lambda m: self.say(m))
            if router is not None and self.applied[batch[0].fault].end_unix_ns is not None:
                # the host was back (its router relaying) when the router started, before the peer
                af = self.applied[batch[0].fault]
                af.end_unix_ns = min(af.end_unix_ns, router.started_unix_ns)
            if sc.shape == "routers" and batch[0].op == "kill" and self._host_down(batch[0].target[0]):
                router = self.routers[batch[0].target[0]]  # the host is down: its router with it
                self.sup.kill(router)
                self.applied[batch[0].fault].killed.append(router)
        # what each host costs, sampled at half time, while every robot still runs (a robot sends for
        # duration_s from its own start, and the first started seconds before time 0)
        self.wait_until(self.t0_mono + sc.duration_s / 2)
        self.costs = self.sample_costs()
        self.wait_until(self.t0_mono + sc.duration_s)
        self.say("duration over; waiting for robots to finish")
        grace = 30.0 + 2.0 * sc.lease_ms / 1000 + max((r.deadline_ms or 0) for r in sc.robots) / 1000
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline and any(self.proc(r.id).alive() for r in sc.robots):
            self.wait_until(time.monotonic() + 0.05)
        late = [self.names[r.id] for r in sc.robots if self.proc(r.id).alive()]
        if late:
            self.notes.append(f"robots still running {grace:.0f} s after the end were stopped: {', '.join(late)}")
        self.robots_done_unix_ns = time.time_ns()
        self.await_restarts()

    def await_restarts(self) -> None:
        """Wait (up to the ready timeout) for a restarted peer still starting when the robots finished.

        A cold start can take longer than the rest of the run on a busy box; a
        restart is "never became ready" only when the peer exits or stays
        unready for the ready timeout (docs/FLEET.md).
        """
        pending = [af for af in self.applied if af.restarted_all and af.ready_unix_ns is None]
        if not pending:
            return
        self.say("waiting for the restarted peers to become ready")
        deadline = time.monotonic() + self.ready_timeout
        while time.monotonic() < deadline and any(
                af.ready_unix_ns is None and any(self.sup.procs[n].alive() for n in af.restarted_all)
                for af in pending):
            self.wait_until(time.monotonic() + 0.05)

    def stop(self) -> None:
        """Stop the robots, count the data tier while the servers run, stop the rest, tear down."""
        sc, sup = self.scenario, self.sup
        try:
            if sup is not None and sup.procs:
                self.say("stopping")
                sup.stop(sorted({self.names[r.id] for r in sc.robots if r.id in self.names}), timeout=ROBOT_STOP_S)
                self.read_records()
                self.telemetry = _count_telemetry(self.out_dir, sc, sup, self.names, ods=self.options.ods)
        finally:
            try:
                if sup is not None:
                    sup.stop_all(timeout=5.0)
            finally:
                try:
                    if self.be is not None:
                        self.be.teardown()
                finally:
                    self.ended_mono = time.monotonic()
                    self._hook("stopped")

    def sample_costs(self) -> dict[str, dict[str, Any]]:
        """What each host costs at half time: its processes' peak RSS (MB), CPU (s) so far and open
        sockets, and on netns its established TCP links to other hosts (read from the kernel).  Per
        peer; under ``shape = "routers"`` a host's figures include its router's, and a router shared
        by every peer of the host (loopback) has its own entry."""
        host_of = getattr(self.be, "host_of", lambda p: p)
        out: dict[str, dict[str, Any]] = {}
        sharing: dict[str, int] = {}  # a swarm process plays several robots: each gets its share
        for p in self.scenario.peer_names:
            sharing[self.names.get(p, "")] = sharing.get(self.names.get(p, ""), 0) + 1
        for p in self.scenario.peer_names:
            own_router = self.routers.get(p) if host_of(p) == p else None  # a shared one: not its own
            names = [n for n in (self.names.get(p), own_router) if n]
            rss = cpu = 0.0
            socks = 0
            seen = False
            for n in names:
                proc = self.sup.procs.get(n)
                got = _proc_cost(proc.pid) if proc is not None and proc.alive() else None
                if got is not None:
                    seen = True
                    k = sharing.get(n, 1) if n == self.names.get(p) else 1
                    rss += got[0] / k
                    cpu += got[1] / k
                    socks += got[2] / k
            if seen:
                out[p] = {"peak_rss_mb": round(rss, 1), "cpu_s": round(cpu, 2), "sockets": round(socks, 1)}
                if sharing.get(self.names.get(p, ""), 1) > 1:
                    out[p]["shared_by"] = sharing[self.names[p]]  # its share of one swarm process
        for name in sorted({n for p, n in self.routers.items() if host_of(p) != p}):  # one for many
            proc = self.sup.procs.get(name)
            got = _proc_cost(proc.pid) if proc is not None and proc.alive() else None
            if got is not None:
                out[name] = {"peak_rss_mb": round(got[0], 1), "cpu_s": round(got[1], 2), "sockets": got[2]}
        layout = getattr(self.be, "layout", None)
        if layout is not None:
            by_addr = {layout.addr(q): q for q in layout.peers}
            for p in out:
                try:
                    got = subprocess.run(["ip", "netns", "exec", layout.ns(p), "ss", "-tnH", "state", "established"],
                                         capture_output=True, text=True, timeout=10).stdout
                except (OSError, subprocess.TimeoutExpired):
                    continue
                remote = {line.split()[-1].rsplit(":", 1)[0] for line in got.splitlines() if line.split()}
                out[p]["links"] = len([a for a in remote if by_addr.get(a) not in (None, p)])
        return out

    # ------------------------------------------------------------ helpers
    def wait_until(self, t_mono: float) -> None:
        """Until ``t_mono``: note restarted peers' ready times, read records, warn of exits, tick hooks."""
        while True:
            for af in self.applied:
                if af.restarted_all and af.ready_unix_ns is None:
                    ready = [self.sup.procs[n].ready_unix_ns for n in af.restarted_all
                             if n in self.sup.procs and self.sup.procs[n].is_ready()]
                    if ready:  # back with its first peer (a cloud tier: its first node)
                        af.ready_unix_ns = min(ready)
            for proc in self.sup.procs.values():
                proc.is_ready()  # every (re)started peer's ready time, for the report
            self.read_records()
            self._warn_exits()
            self._hook("tick")
            left = t_mono - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, 0.05 if self.hooks else 0.02))

    def read_records(self) -> None:
        for tail in list(self.tails.values()):
            self.records.extend(tail.read_new())

    def _warn_exits(self) -> None:
        killed = {n for af in self.applied if af.start_unix_ns is not None for n in af.killed}
        for name, rc in self.sup.exited().items():
            robot = any(name == self.names.get(r.id) for r in self.scenario.robots)
            if name in self._warned or name in killed or (robot and rc == 0):
                continue
            self._warned.add(name)
            log.warning("peer %s exited with status %s; see %s", name, rc, self.sup.procs[name].spec.log_path)

    def _restart_spec(self, peer: str, *, remaining_s: float | None = None):
        return self.spec_for(peer, remaining_s=remaining_s)

    def _resolve_leader(self, batch: list[Event]) -> list[Event] | None:
        """A crash of whoever leads: wait until someone does (to the end of the run), then name it."""
        end = self.t0_mono + self.scenario.duration_s
        while not self.leaders():
            if time.monotonic() >= end:
                self.notes.append(f"{self.scenario.faults[batch[0].fault].label}: nobody led; no crash")
                return None
            self.wait_until(time.monotonic() + 0.05)
        node = self.leaders()[0]
        peer = self.scenario.peer_of(node)
        self.applied[batch[0].fault].resolved = peer
        return [dataclasses.replace(ev, target=(peer,)) for ev in batch]

    def result(self) -> RunResult:
        notes = list(self.notes)
        notes.extend(n for n in getattr(self.be, "notes", []) if n not in notes)
        for af in self.applied:
            notes.extend(n for n in af.notes if n not in notes)
        records = read_run_records(self.out_dir / "robots")
        (self.out_dir / "peers.json").write_text(json.dumps(self.handed, indent=1) + "\n")
        sc, be = self.scenario, self.be
        capable = set(sc.candidates)
        topology = {p.name: {"role": p.role, "connect": be.connect_names(p.name), "leader_capable": p.name in capable,
                             "capability": (sc.leader_capability if p.role == "leader" else
                                            next((r.capability or r.profile for r in sc.robots if r.id == p.name
                                                  and r.leader_capable), None))}
                    for p in sc.peers}
        sup = self.sup
        peers = {} if sup is None else {
            n: {"pid": p.pid, "log": str(p.spec.log_path), "exit": p.popen.returncode,
                "started_unix_ns": p.started_unix_ns, "ready_unix_ns": p.ready_unix_ns}
            for n, p in sup.procs.items()}
        ended = {}
        for name, p in ({} if sup is None else sup.procs).items():  # a killed candidate writes no step_down
            kills = [t for sig, t in p.signalled if sig == signal.SIGKILL]
            if kills:
                ended[sc.node_of(name)] = kills[0]
        return RunResult(scenario=sc, backend=self.backend_name, out_dir=self.out_dir,
                         t0_unix_ns=self.t0_unix_ns or time.time_ns(), records=records,
                         faults=self.applied, notes=notes, run_id=getattr(be, "run_id", ""),
                         robots_started_unix_ns=self.robots_started,
                         peer_logs={n: str(self.out_dir / "logs" / f"{n}.log") for n in self.names.values()},
                         telemetry=self.telemetry, topology=topology, peers=peers, killed_unix_ns=ended,
                         interrupted=self.interrupted, insecure=self.insecure, costs=self.costs,
                         wall_s=None if self.ended_mono is None or self.t0_mono is None
                         else round(self.ended_mono - self.t0_mono, 3))


def run_scenario(
    scenario: Scenario,
    *,
    backend: str = "netns",
    out_dir: Path,
    data_dir: Path | None = None,
    progress: Progress | None = None,
    ready_timeout: float = 120.0,
    python: str = sys.executable,
    insecure: bool = False,
    options: RunOptions | None = None,
    hooks: Sequence[Hooks] = (),
    keep_interrupted: bool = False,
) -> RunResult:
    """Run ``scenario`` once and return its records and fault times.

    Parameters
    ----------
    scenario : Scenario
    backend : {"netns", "proxy", "loopback"}, keyword-only
    out_dir : Path, keyword-only
        Peer logs, robot records and image links go here.
    data_dir : Path, keyword-only
        Root of the image sets (default :func:`default_data_dir`).
    progress : callable, keyword-only
        Receives one-line progress messages.
    ready_timeout : float, keyword-only
        Seconds each peer may take to become ready (first numba compile is slow).
    insecure : bool, keyword-only
        Run the peers without authentication.  By default a development CA and one
        certificate per peer (valid for every address a peer listens on, so links that
        gossip finds pass name verification) are made in ``OUT/certs`` and every peer
        runs mutual TLS with the fleet's access rules.
    options : RunOptions, keyword-only
        How peers are started (``scmr up`` passes its own; default the scenario runner's).
    hooks : sequence of Hooks, keyword-only
        Progress, rerun, data store... (see :class:`Hooks`).
    keep_interrupted : bool, keyword-only
        Ctrl-C/SIGTERM after time 0 stops the run and returns what it has
        (``interrupted`` True) instead of raising ``KeyboardInterrupt``.

    Raises
    ------
    ScenarioError
        Setup failed or a peer did not start (message names it, with its log tail).
    """
    from scmr_mesh.errors import MeshError
    from scmr_mesh.fleet.procs import signals_to_interrupt

    options = options or RunOptions(python=python)
    run = ScenarioRun(scenario, backend=backend, out_dir=out_dir, data_dir=data_dir, options=options,
                      hooks=([Say(progress)] if progress else [Say(lambda m: log.info("%s", m))]) + list(hooks),
                      ready_timeout=ready_timeout, insecure=insecure)
    with signals_to_interrupt():
        try:
            run.prepare()
            run.start()
            run.play()
        except KeyboardInterrupt:
            if not keep_interrupted or run.t0_unix_ns is None:
                _stop_quietly(run)
                raise
            run.interrupted = True
            log.warning("interrupted: stopping the run")
        except MeshError as exc:
            _stop_quietly(run)
            raise ScenarioError(f"scenario {scenario.name}: {exc}") from None
        except BaseException:
            _stop_quietly(run)
            raise
        _stop_quietly(run)
    res = run.result()
    run.say(f"done: {len(res.records)} requests recorded")
    return res


def _stop_quietly(run: ScenarioRun) -> None:
    """``run.stop()`` once, with Ctrl-C/SIGTERM ignored while the peers are stopped."""
    if getattr(run, "_stopped", False):
        return
    run._stopped = True
    old = _ignore_interrupts()
    try:
        run.stop()
    finally:
        _restore_interrupts(old)


def _ignore_interrupts():
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    return (signal.signal(signal.SIGINT, signal.SIG_IGN), signal.signal(signal.SIGTERM, signal.SIG_IGN))


def _restore_interrupts(old) -> None:
    if old is not None:
        signal.signal(signal.SIGINT, old[0])
        signal.signal(signal.SIGTERM, old[1])


def _count_telemetry(out_dir: Path, scenario: Scenario, sup, names: dict[str, str], *,
                     ods: str | None = None) -> dict[str, Any] | None:
    """The data tier's telemetry count, taken while the servers still run; saved as ``telemetry.json``.

    The peers' run dir is ``out_dir`` (their ready files are in ``out_dir/ready``), so the
    cloud's store is ``out_dir/ods.sqlite`` and the robots' queues ``out_dir/queues/<id>``.
    Waits up to 5 s for the leader's relayed records when a cloud node is still alive: only a cloud stores records, so with none running nothing more can arrive (a run
    without a cloud, or whose clouds are down at the end, was counted 5 s late).
    """
    from scmr_mesh.data.report import fleet_telemetry

    clouds = [p.name for p in scenario.peers if p.role == "cloud"]
    alive = any(names.get(p) in sup.procs and sup.procs[names[p]].alive() for p in clouds)
    tel = fleet_telemetry(out_dir, [r.id for r in scenario.robots], wait=alive, ods=ods)
    if tel is not None:
        (out_dir / "telemetry.json").write_text(json.dumps(tel, indent=2) + "\n")
    return tel


def _sleep_watching(seconds: float, sup, applied: list[AppliedFault], names: dict[str, str]) -> None:
    """Sleep, noting when restarted peers become ready (their ready file appears)."""
    end = time.monotonic() + seconds
    while True:
        for af in applied:
            if af.restarted and af.ready_unix_ns is None:
                proc = sup.procs.get(af.restarted)
                if proc is not None and proc.is_ready():
                    af.ready_unix_ns = proc.ready_unix_ns
        left = end - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(left, 0.02))


def _batches(events: list[Event]) -> list[list[Event]]:
    """Group events due at the same time and of the same kind (network, or each process op)."""
    out: list[list[Event]] = []
    for ev in events:
        net = ev.op not in ("kill", "start")
        if out and out[-1][0].at_s == ev.at_s and net and out[-1][0].op not in ("kill", "start"):
            out[-1].append(ev)
        else:
            out.append([ev])
    return out


def _apply_batch(batch: list[Event], be, sup, names: dict[str, str], applied: list[AppliedFault], spec_for,
                 scenario: Scenario, t0_mono: float, say: Progress) -> None:
    """Apply events due together.

    A fault's start is the time *before* its commands are issued and its end
    the time *after* the lifting commands completed, so the failover and
    failback gaps are never flattered by the time the commands take.
    """
    ev0 = batch[0]
    t_before = time.time_ns()
    if ev0.op == "kill":
        t_before = sup.kill(names[ev0.target[0]])
        applied[ev0.fault].killed.append(names[ev0.target[0]])
        t_after = t_before
        say(f"t={time.monotonic() - t0_mono:5.2f}s  SIGKILL {ev0.target[0]}")
    elif ev0.op == "start":
        peer = ev0.target[0]
        remaining = scenario.duration_s - (time.monotonic() - t0_mono) if scenario.role(peer) == "robot" else None
        spec = spec_for(peer, remaining_s=remaining)
        proc = sup.start(spec)
        names[peer] = spec.name
        af0 = applied[ev0.fault]
        af0.restarted = af0.restarted or spec.name
        af0.restarted_all.append(spec.name)
        t_after = proc.started_unix_ns
        say(f"t={time.monotonic() - t0_mono:5.2f}s  restart {peer}")
    else:
        notes = be.apply_many(batch)
        t_after = time.time_ns()
        for ev in batch:
            if ev.fault != RADIO:
                applied[ev.fault].notes.extend(n for n in notes if n not in applied[ev.fault].notes
                                               and scenario.faults[ev.fault].label in n)
        say(f"t={time.monotonic() - t0_mono:5.2f}s  " + ", ".join(
            f"{ev.op} {'-'.join(ev.target)}" + (f" -> {ev.value}" if ev.value is not None else "")
            + (" (radio)" if ev.fault == RADIO else "") for ev in batch))
    for ev in batch:
        if ev.fault == RADIO:
            continue  # the radio topology's own change: no fault to note
        af = applied[ev.fault]
        if ev.lift:
            # the fault's end, unless it is the teardown of one lasting to the end of the run; faults
            # it held past their own lift (plan.Event.ends) end with it, or not at all
            if ev.at_s < scenario.duration_s or (af.fault.end_s is not None and af.fault.end_s <= scenario.duration_s):
                for k in (ev.fault, *ev.ends):
                    if applied[k].end_unix_ns is None:  # a tier of several peers is back with the first
                        applied[k].end_unix_ns = t_after
        elif af.start_unix_ns is None:
            af.start_unix_ns = t_before


def _proc_cost(pid: int) -> tuple[float, float, int] | None:
    """``(peak RSS MB, CPU s, open sockets)`` of a live process from /proc (None when unreadable)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    hwm = next((int(line.split()[1]) for line in status.splitlines() if line.startswith("VmHWM:")), 0)
    ticks = os.sysconf("SC_CLK_TCK")
    socks = 0
    try:
        for fd in os.listdir(f"/proc/{pid}/fd"):
            try:
                socks += os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:")
            except OSError:
                pass
    except OSError:
        pass
    return hwm / 1024.0, (int(stat[11]) + int(stat[12])) / ticks, socks


def read_run_records(robots_dir: Path) -> list[dict[str, Any]]:
    """Every robot's request records under ``robots_dir/*/records.jsonl``, in sending order.

    A line that is not JSON (a robot killed mid-write) is skipped with a warning.
    """
    recs: list[dict[str, Any]] = []
    for f in sorted(robots_dir.glob("*/records.jsonl")):
        for line in f.read_text(encoding="utf-8", errors="replace").splitlines():
            line = line.strip()
            if not line:
                continue
            try:
                recs.append(json.loads(line))
            except json.JSONDecodeError:
                log.warning("%s: skipping a line that is not JSON", f)
    recs.sort(key=lambda r: (r.get("sent_unix_ns") or 0, str(r.get("robot"))))
    return recs
