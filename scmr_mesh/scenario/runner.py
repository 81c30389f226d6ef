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

import json
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from scmr_mesh.errors import ConfigError, ScenarioError
from scmr_mesh.scenario.plan import Event, affected_pairs, compile_timeline
from scmr_mesh.scenario.spec import Fault, Scenario

__all__ = ["RunResult", "default_data_dir", "fault_tier", "run_scenario"]

log = logging.getLogger(__name__)

Progress = Callable[[str], None]


def default_data_dir() -> Path:
    """``$SCMR_DATA`` or ``<repo>/../shared/data/roads``."""
    env = os.environ.get("SCMR_DATA")
    if env:
        return Path(env)
    shared = Path(os.environ.get("SCMR_SHARED", Path(__file__).resolve().parents[3] / "shared"))
    return shared / "data" / "roads"


def fault_tier(scenario: Scenario, fault: Fault) -> tuple[str | None, list[str] | None]:
    """Which serving tier ``fault`` takes away, and from which robots (pure).

    Returns ``(tier, robots)`` in the form :mod:`scmr_mesh.qos.metrics` expects:
    ``tier`` is ``"cloud"``, ``"leader"`` or ``None``; ``robots`` ``None``
    means every robot.
    """
    robots = [r.id for r in scenario.robots]
    if fault.kind == "crash":
        role = scenario.role(fault.peer or "")
        return (role, None) if role in ("cloud", "leader") else (None, None)
    if fault.kind in ("link_down", "partition"):
        pairs = set(affected_pairs(fault))
        for tier, servers in (("cloud", scenario.clouds), ("leader", (scenario.leader,) if scenario.leader else ())):
            if not servers:
                continue
            cut = [r for r in robots if all(tuple(sorted((r, s))) in pairs for s in servers)]
            if cut:
                return tier, (None if len(cut) == len(robots) else cut)
    return None, None


@dataclass
class AppliedFault:
    """When one fault really took effect (unix ns) and what was skipped."""

    index: int
    fault: Fault
    start_unix_ns: int | None = None
    end_unix_ns: int | None = None
    restarted: str | None = None  # supervisor name of the restarted process (crash faults)
    ready_unix_ns: int | None = None  # when the restarted peer wrote its ready file
    notes: list[str] = field(default_factory=list)


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

    def leadership(self) -> dict[str, Any]:
        """The ``leadership`` block from the candidates' role changes (``out_dir/leadership``)."""
        from scmr_mesh.qos.leadership import leadership, read_events

        faults = [{**f, "peer": af.fault.peer, "groups": af.fault.groups}
                  for f, af in zip(self.metric_faults(), self.faults)]
        return leadership(read_events(self.out_dir / "leadership"), self.records, faults,
                          t0_unix_ns=self.t0_unix_ns,
                          # robots send for duration_s from about t0; the first graceful stop of a
                          # candidate (a robot finishing) also ends the window (qos.leadership)
                          end_unix_ns=self.t0_unix_ns + int(self.scenario.duration_s * 1e9))

    def metric_faults(self) -> list[dict[str, Any]]:
        """Faults as :func:`scmr_mesh.qos.metrics.summarize` takes them."""
        out = []
        for af in self.faults:
            tier, robots = fault_tier(self.scenario, af.fault)
            target = (af.fault.peer or ("-".join(af.fault.link) if af.fault.link else
                      " | ".join(",".join(g) for g in af.fault.groups or ())))
            out.append({
                "kind": af.fault.kind, "target": target, "label": af.fault.label, "tier": tier,
                "link": list(af.fault.link) if af.fault.link else None,
                "robots": robots, "at_s": af.fault.at_s, "for_s": af.fault.for_s,
                **({"fallback": ["peer", "leader"]} if tier == "leader" else {}),
                "start_unix_ns": af.start_unix_ns if af.start_unix_ns is not None
                else self.t0_unix_ns + int(af.fault.at_s * 1e9),
                "end_unix_ns": af.end_unix_ns, "notes": af.notes, "ready_unix_ns": af.ready_unix_ns,
            })
        return out


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


def scenario_identities(scenario: Scenario):
    """The identities of a scenario's peers (pure): names, roles, lead grants."""
    from scmr_mesh.security.credentials import Peer

    capable = set(scenario.candidates)
    out = []
    for p in scenario.peers:
        role = scenario.role(p.name)
        if role == "robot":
            out.append(Peer(p.name, "robot", leader_capable=p.name in capable, priority_cap=0))
        elif role == "leader":
            out.append(Peer(p.name, "leader", leader_capable=True, priority_cap=0))
        else:
            out.append(Peer(p.name, role))
    return out


def _security(scenario: Scenario, be, out_dir: Path, insecure: bool) -> list[str]:
    """Credentials for every peer in OUT/certs, valid for every address peers listen on; or --insecure."""
    from scmr_mesh.security.runcreds import INSECURE, run_credentials

    if insecure:
        return list(INSECURE)
    hosts = sorted({ep.split("/", 1)[1].rsplit(":", 1)[0].strip("[]")
                    for p in scenario.peers for ep in be.listen(p.name) if "/" in ep} - {"127.0.0.1", "::1"})
    return run_credentials(out_dir, scenario_identities(scenario), hosts=hosts).args()


def _make_backend(scenario: Scenario, backend: str):
    if backend == "netns":
        from scmr_mesh.scenario.netns import NetnsBackend, check_root

        check_root()
        return NetnsBackend(scenario)
    if backend == "proxy":
        from scmr_mesh.scenario.proxy import ProxyBackend

        return ProxyBackend(scenario)
    raise ConfigError(f"backend must be netns or proxy, got {backend!r}")


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
) -> RunResult:
    """Run ``scenario`` once and return its records and fault times.

    Parameters
    ----------
    scenario : Scenario
    backend : {"netns", "proxy"}, keyword-only
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

    Raises
    ------
    ScenarioError
        Setup failed or a peer did not start (message names it, with its log tail).
    """
    from scmr_mesh.errors import MeshError
    from scmr_mesh.fleet.procs import PeerSpec, Supervisor, signals_to_interrupt

    say = progress or (lambda m: log.info("%s", m))
    out_dir = Path(out_dir)
    check_out_dir(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data_dir = Path(data_dir) if data_dir is not None else default_data_dir()
    images = {r.id: _image_dir(scenario, r.image_set, data_dir, out_dir, r.id)
              for r in scenario.robots if r.image_set}
    events = compile_timeline(scenario)
    applied = [AppliedFault(i, f) for i, f in enumerate(scenario.faults)]
    be = _make_backend(scenario, backend)
    notes: list[str] = []
    base = [python, "-m", "scmr_mesh"]
    starts: dict[str, int] = {}
    handed: dict[str, list[str]] = {}
    security: list[str] = []

    def common(peer: str) -> list[str]:
        a: list[str] = list(security)
        for ep in be.listen(peer):
            a += ["--listen", ep]
        for ep in be.connect(peer):
            a += ["--connect", ep]
        a += ["--lease-ms", str(scenario.lease_ms)]
        for c in be.extra_cfg(peer):
            a += ["--cfg", c]
        return a

    # written at t0 (every robot ready); robots send from then on, each at a phase of its own
    start_file = out_dir / "ready" / "run.start"

    def spec_for(peer: str, *, remaining_s: float | None = None) -> PeerSpec:
        role = scenario.role(peer)
        n = starts[peer] = starts.get(peer, 0) + 1
        suffix = "" if n == 1 else f"-{n}"
        ready = out_dir / "ready" / f"{peer}{suffix}"
        ready.parent.mkdir(parents=True, exist_ok=True)
        if role in ("cloud", "leader"):
            argv = base + [role, "--node", peer] + common(peer)
            if role == "leader":
                argv += ["--capability", scenario.leader_capability]
            if scenario.process:
                argv += ["--process", scenario.process]
        else:
            r = next(x for x in scenario.robots if x.id == peer)
            argv = base + ["robot", "--id", peer]
            argv += ["--images", str(images[peer])] if r.image_set else ["--synthetic", r.synthetic or "road"]
            dur = scenario.duration_s if remaining_s is None else max(0.5, remaining_s)
            argv += ["--rate", f"{r.rate_hz:g}", "--duration", f"{dur:g}",
                     "--out", str(out_dir / "robots" / f"{peer}{suffix}")]
            if r.energy_placement:
                if not r.profile:
                    raise ConfigError(f"scenario {scenario.source}: field 'fleet.robots' ({peer}): energy_placement "
                                      "needs a profile; add profile = \"robot1\" (Table 4.3) or similar")
                argv += ["--profile", r.profile]
            if r.deadline_ms is not None:
                argv += ["--deadline-ms", str(r.deadline_ms)]
            if not r.local_fallback:
                argv += ["--no-local-fallback"]
            if r.leader_capable:
                argv += ["--leader-capable"]
                if r.capability:
                    argv += ["--capability", r.capability]
                elif r.profile:
                    argv += ["--capability", r.profile]
            if scenario.process:
                argv += ["--process", scenario.process]
            argv += ["--seed", str(scenario.seed), "--quiet", "--start-file", str(start_file)]
            argv += common(peer)
        argv += ["--ready-file", str(ready)]
        handed[peer + suffix] = argv[len(base):]  # what each peer was told (checked by tests; peers.json)
        env = {"SCMR_SCENARIO_SEED": str(scenario.seed)}
        return PeerSpec(peer + suffix, be.wrap(peer, argv), log_path=out_dir / "logs" / f"{peer}{suffix}.log",
                        ready_file=ready, env=env)

    t0 = time.time_ns()
    sup = Supervisor(term_timeout=5.0)
    names: dict[str, str] = {}
    telemetry = None
    robots_started: int | None = None
    with signals_to_interrupt():
        try:
            rid = getattr(be, "run_id", "")
            say(f"[{backend}] setting up {len(scenario.peers)} peers, {len(scenario.links)} links"
                + (f" (namespaces scmrs-{rid}-*)" if rid else ""))
            be.setup()
            security[:] = _security(scenario, be, out_dir, insecure)
            servers = [p.name for p in scenario.peers if p.role != "robot"]
            for p in servers:
                spec = spec_for(p)
                sup.start(spec)
                names[p] = spec.name
            sup.wait_ready([names[p] for p in servers], timeout=ready_timeout)
            say(f"servers ready: {', '.join(servers)}; starting {len(scenario.robots)} robots")
            robots_started = time.time_ns()
            for r in scenario.robots:
                spec = spec_for(r.id)
                sup.start(spec)
                names[r.id] = spec.name
            sup.wait_ready([names[r.id] for r in scenario.robots], timeout=ready_timeout)
            t0 = time.time_ns()
            t0_mono = time.monotonic()
            start_file.write_text(f"{t0}\n")
            say(f"robots ready; run of {scenario.duration_s:g}s starts (seed {scenario.seed})")
            for batch in _batches(events):
                delay = t0_mono + batch[0].at_s - time.monotonic()
                if delay > 0:
                    _sleep_watching(delay, sup, applied, names)
                _apply_batch(batch, be, sup, names, applied, spec_for, scenario, t0_mono, say)
            left = t0_mono + scenario.duration_s - time.monotonic()
            if left > 0:
                _sleep_watching(left, sup, applied, names)
            say("duration over; waiting for robots to finish")
            deadline = time.monotonic() + 30.0 + 2.0 * scenario.lease_ms / 1000
            robot_procs = [sup.procs[names[r.id]] for r in scenario.robots]
            while time.monotonic() < deadline and any(p.alive() for p in robot_procs):
                _sleep_watching(0.1, sup, applied, names)
            late = [p.name for p in robot_procs if p.alive()]
            if late:
                notes.append(f"robots still running 30 s after the end were stopped: {', '.join(late)}")
            telemetry = _count_telemetry(out_dir, scenario, sup, names, servers)
        except MeshError as exc:
            raise ScenarioError(f"scenario {scenario.name}: {exc}") from None
        finally:
            try:
                sup.stop_all(timeout=5.0)
            finally:
                be.teardown()
    notes.extend(be.notes)
    for af in applied:
        notes.extend(n for n in af.notes if n not in notes)
    records = read_run_records(out_dir / "robots")
    (out_dir / "peers.json").write_text(json.dumps(handed, indent=1) + "\n")
    say(f"done: {len(records)} requests recorded")
    capable = set(scenario.candidates)
    topology = {p.name: {"role": p.role, "connect": be.connect_names(p.name), "leader_capable": p.name in capable,
                         "capability": (scenario.leader_capability if p.role == "leader" else
                                        next((r.capability or r.profile for r in scenario.robots if r.id == p.name
                                              and r.leader_capable), None))}
                for p in scenario.peers}
    return RunResult(scenario=scenario, backend=backend, out_dir=out_dir, t0_unix_ns=t0, records=records,
                     faults=applied, notes=notes, run_id=getattr(be, "run_id", ""),
                     robots_started_unix_ns=robots_started,
                     peer_logs={n: str(out_dir / "logs" / f"{n}.log") for n in names.values()},
                     telemetry=telemetry, topology=topology)


def _count_telemetry(out_dir: Path, scenario: Scenario, sup, names: dict[str, str],
                     servers: list[str]) -> dict[str, Any] | None:
    """The data tier's telemetry count, taken while the servers still run; saved as ``telemetry.json``.

    The peers' run dir is ``out_dir`` (their ready files are in ``out_dir/ready``), so the
    cloud's store is ``out_dir/ods.sqlite`` and the robots' queues ``out_dir/queues/<id>``.
    Waits up to 5 s for the leader's relayed records when a server is still alive.
    """
    from scmr_mesh.data.report import fleet_telemetry

    alive = any(names.get(p) in sup.procs and sup.procs[names[p]].alive() for p in servers)
    tel = fleet_telemetry(out_dir, [r.id for r in scenario.robots], wait=alive)
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
        t_after = t_before
        say(f"t={time.monotonic() - t0_mono:5.2f}s  SIGKILL {ev0.target[0]}")
    elif ev0.op == "start":
        peer = ev0.target[0]
        remaining = scenario.duration_s - (time.monotonic() - t0_mono) if scenario.role(peer) == "robot" else None
        spec = spec_for(peer, remaining_s=remaining)
        proc = sup.start(spec)
        names[peer] = spec.name
        applied[ev0.fault].restarted = spec.name
        t_after = proc.started_unix_ns
        say(f"t={time.monotonic() - t0_mono:5.2f}s  restart {peer}")
    else:
        notes = be.apply_many(batch)
        t_after = time.time_ns()
        for ev in batch:
            applied[ev.fault].notes.extend(n for n in notes if n not in applied[ev.fault].notes
                                           and scenario.faults[ev.fault].label in n)
        say(f"t={time.monotonic() - t0_mono:5.2f}s  " + ", ".join(
            f"{ev.op} {'-'.join(ev.target)}" + (f" -> {ev.value}" if ev.value is not None else "") for ev in batch))
    for ev in batch:
        af = applied[ev.fault]
        if ev.lift:
            # the fault's end, unless it is the teardown of one lasting to the end of the run; faults
            # it held past their own lift (plan.Event.ends) end with it, or not at all
            if ev.at_s < scenario.duration_s or (af.fault.end_s is not None and af.fault.end_s <= scenario.duration_s):
                for k in (ev.fault, *ev.ends):
                    applied[k].end_unix_ns = t_after
        elif af.start_unix_ns is None:
            af.start_unix_ns = t_before


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
