"""A whole fleet on one host: ``scmr up`` and ``scmr bench mesh``.

:func:`run_fleet` starts a cloud, a leader and N robots as separate OS
processes on loopback (each robot listens and connects to the cloud and the
leader; gossip lets the robots mesh), injects a cloud outage when asked
(SIGKILL at START, restart at END, exact times recorded), follows the robots'
``records.jsonl`` for live progress, stops everything (SIGTERM, wait,
SIGKILL, per process group; no orphans even if ``scmr up`` itself is
SIGKILLed, see :mod:`scmr_mesh.procs`) and returns the report of
:func:`scmr_mesh.metrics.summarize`, validated by
``schemas/report.schema.json``.

Run directory layout::

    runs/<UTC timestamp>/
        report.json
        logs/<peer>.log             stdout+stderr of cloud, leader, r1..rN
        robots/<id>/records.jsonl   one JSON record per finished request
        robots/<id>/inbox/*.png     the masks each robot received
        ready/<peer>.ready          readiness files
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scmr_mesh.errors import InputError, MeshError

__all__ = [
    "FleetConfig",
    "Progress",
    "RecordTail",
    "format_progress",
    "format_summary",
    "parse_outage",
    "plan_fleet",
    "run_fleet",
    "validate_report",
]

log = logging.getLogger(__name__)

REPORT_SCHEMA = Path(__file__).resolve().parents[1] / "schemas" / "report.schema.json"
CLOUD, LEADER = "cloud", "leader"
#: File that marks a folder as an scmr run directory (``scmr demo`` only replaces such folders).
RUN_MARKER = ".scmr-run"


# --------------------------------------------------------------------------
# configuration and plan (pure)
# --------------------------------------------------------------------------
@dataclass
class FleetConfig:
    """What to run.

    Attributes
    ----------
    robots : int
        Number of robot peers (besides the leader).
    duration_s : float
        How long each robot sends frames.
    rate_hz : float
        Frames per second per robot.
    cloud_outage : (float, float) or None
        Seconds after the fleet is ready at which the cloud is SIGKILLed and
        restarted.
    images : Path or None
        A folder of images every robot sends (else synthetic scenes).
    synthetic : sequence of str
        Synthetic scene kinds, dealt to the robots round-robin (empty: all
        kinds the imaging package offers).
    run_dir : Path or None
        Where logs, records and the report go (default ``runs/<timestamp>``).
    workers : int or None
        Worker processes of the cloud and the leader (default: theirs).
    lease_ms, deadline_ms : int or None
        Passed to the peers when set.
    server_args, robot_args : sequence of str
        Extra arguments for cloud+leader and for robots.
    ready_timeout_s : float
        How long a peer may take to write its ready file.
    rerun : scmr_mesh.viz.RerunOptions or None
        Show or record the run in rerun (``--save/--spawn/--serve/--connect``);
        ``None``: nothing rerun-related happens.
    """

    robots: int = 4
    duration_s: float = 10.0
    rate_hz: float = 5.0
    cloud_outage: tuple[float, float] | None = None
    images: Path | None = None
    synthetic: Sequence[str] = ()
    run_dir: Path | None = None
    workers: int | None = None
    lease_ms: int | None = None
    deadline_ms: int | None = None
    server_args: Sequence[str] = ()
    robot_args: Sequence[str] = ()
    ready_timeout_s: float = 90.0
    python: str = sys.executable
    rerun: Any = None

    def check(self) -> None:
        """Raise :class:`InputError` naming the bad value and the fix."""
        if self.robots < 1:
            raise InputError(f"--robots must be at least 1, got {self.robots}")
        if not self.duration_s > 0:
            raise InputError(f"--duration must be positive (seconds), got {self.duration_s}")
        if not self.rate_hz > 0:
            raise InputError(f"--rate must be positive (Hz), got {self.rate_hz}")
        if self.cloud_outage is not None:
            start, end = self.cloud_outage
            if not 0 <= start < end <= self.duration_s:
                raise InputError(
                    f"--cloud-outage must satisfy 0 <= START < END <= --duration ({self.duration_s:g}), "
                    f"got {start:g}:{end:g}"
                )
        if self.images is not None and not Path(self.images).is_dir():
            raise InputError(f"--images must be a folder of images, got {self.images} (not a folder)")


def parse_outage(text: str) -> tuple[float, float]:
    """``"8:14"`` -> ``(8.0, 14.0)`` (seconds after the fleet is ready)."""
    try:
        a, b = str(text).split(":")
        start, end = float(a), float(b)
    except ValueError:
        raise InputError(f"--cloud-outage must be START:END in seconds such as 8:14, got {text!r}") from None
    if not 0 <= start < end:
        raise InputError(f"--cloud-outage needs 0 <= START < END, got {text!r}")
    return start, end


def _default_kinds() -> list[str]:
    try:
        from scmr_mesh.imaging.synthetic import SCENE_KINDS
    except ImportError:  # pragma: no cover - imaging not built yet
        return ["road"]
    return list(SCENE_KINDS)


def robot_ids(n: int) -> list[str]:
    """Robot ids of a fleet of ``n``: ``r1`` ... ``rn``."""
    return [f"r{i}" for i in range(1, n + 1)]


def plan_fleet(config: FleetConfig, run_dir: Path, ports: Mapping[str, int]):
    """The peers of a fleet as :class:`~scmr_mesh.procs.PeerSpec` (pure: starts nothing).

    Parameters
    ----------
    config : FleetConfig
    run_dir : Path
    ports : mapping
        Loopback port per peer name (``cloud``, ``leader``, ``r1``...).

    Returns
    -------
    dict
        ``{name: PeerSpec}``, servers first.
    """
    from scmr_mesh.procs import PeerSpec

    def ep(name: str) -> str:
        return f"tcp/127.0.0.1:{ports[name]}"

    common: list[str] = []
    if config.lease_ms is not None:
        common += ["--lease-ms", str(config.lease_ms)]
    base = [config.python, "-m", "scmr_mesh", "-v"]
    specs = {}
    for name, cmd, node, connect in ((CLOUD, "cloud", "cloud0", []), (LEADER, "leader", "leader0", [CLOUD])):
        argv = [*base, cmd, "--node", node, "--listen", ep(name)]
        for c in connect:
            argv += ["--connect", ep(c)]
        if config.workers is not None:
            argv += ["--workers", str(config.workers)]
        argv += [*common, "--ready-file", str(run_dir / "ready" / f"{name}.ready"), *config.server_args]
        specs[name] = PeerSpec(name, argv, log_path=run_dir / "logs" / f"{name}.log",
                               ready_file=run_dir / "ready" / f"{name}.ready")
    kinds = list(config.synthetic) or _default_kinds()
    for i, rid in enumerate(robot_ids(config.robots)):
        argv = [*base, "robot", "--id", rid]
        if config.images is not None:
            argv += ["--images", str(config.images)]
        else:
            argv += ["--synthetic", kinds[i % len(kinds)]]
        argv += ["--rate", f"{config.rate_hz:g}", "--duration", f"{config.duration_s:g}",
                 "--out", str(run_dir / "robots" / rid),
                 "--listen", ep(rid), "--connect", ep(CLOUD), "--connect", ep(LEADER)]
        if config.deadline_ms is not None:
            argv += ["--deadline-ms", str(config.deadline_ms)]
        argv += [*common, "--ready-file", str(run_dir / "ready" / f"{rid}.ready"), *config.robot_args]
        specs[rid] = PeerSpec(rid, argv, log_path=run_dir / "logs" / f"{rid}.log",
                              ready_file=run_dir / "ready" / f"{rid}.ready")
    return specs


# --------------------------------------------------------------------------
# following records
# --------------------------------------------------------------------------
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


def format_progress(p: Progress) -> str:
    """One line: time, phase, alive tiers, requests, RoR, ToR (last 200), answers per tier."""
    ror = f"{p.succeeded / p.requests:.3f}" if p.requests else "-"
    tor = "-" if p.tor_p50_ms is None else f"{p.tor_p50_ms:.1f}/{p.tor_p99_ms:.1f}"
    tiers = " ".join(f"{k} {p.by_tier.get(k, 0)}" for k in ("cloud", "leader", "local", "failed"))
    alive = ", ".join(f"{k} {'up' if v else 'DOWN'}" for k, v in p.alive.items())
    phase = "" if p.phase == "running" else f"{p.phase} | "
    return (f"[{p.elapsed_s:5.1f}/{p.duration_s:g} s] {phase}{alive} | {p.requests} req, RoR {ror}, "
            f"ToR p50/p99 {tor} ms | {tiers}")


# --------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------
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
    from scmr_mesh import metrics
    from scmr_mesh.procs import Supervisor

    config.check()
    run_dir = Path(config.run_dir) if config.run_dir is not None else default_run_dir()
    if (run_dir / "robots").is_dir() and any((run_dir / "robots").iterdir()):
        raise InputError(f"run directory {run_dir} already holds a run (robots/ is not empty); "
                         "choose a new --run-dir or delete that one")
    for sub in ("logs", "ready", "robots"):
        (run_dir / sub).mkdir(parents=True, exist_ok=True)
    (run_dir / RUN_MARKER).write_text("written by scmr up; this folder may be replaced by `scmr demo`\n")
    rids = robot_ids(config.robots)
    ports = _free_ports([CLOUD, LEADER, *rids])
    specs = plan_fleet(config, run_dir, ports)
    tails = {rid: RecordTail(run_dir / "robots" / rid / "records.jsonl") for rid in rids}
    records: list[dict] = []
    faults: list[dict] = []
    interrupted = False
    sup = Supervisor(term_timeout=10.0)
    t_ready = t_end = None
    telemetry = None
    fviz = None  # scmr_mesh.viz.FleetViz with rerun flags

    def emit(phase: str, elapsed: float, alive: dict[str, bool]) -> None:
        if progress is None:
            return
        recent = metrics.tor_values_ms(records[-200:])
        progress(Progress(
            elapsed_s=elapsed, duration_s=config.duration_s, requests=len(records),
            succeeded=sum(bool(r.get("ok")) for r in records),
            tor_p50_ms=metrics.percentile(recent, 50) if recent else None,
            tor_p99_ms=metrics.percentile(recent, 99) if recent else None,
            by_tier=metrics.tier_counts(records), alive=alive, phase=phase,
        ))

    def alive_tiers() -> dict[str, bool]:
        return {n: sup.procs[n].alive() and sup.procs[n].is_ready() for n in (CLOUD, LEADER)}

    try:
        if config.rerun is not None:
            fviz = _start_viz(config.rerun, rids, specs)
            emit(f"rerun: {fviz.hint}", 0.0, {CLOUD: False, LEADER: False})
        emit("starting cloud and leader", 0.0, {CLOUD: False, LEADER: False})
        t0 = time.monotonic()
        sup.start(specs[CLOUD])
        sup.start(specs[LEADER])
        sup.wait_ready([CLOUD, LEADER], timeout=config.ready_timeout_s)
        log.info("servers ready after %.2f s", time.monotonic() - t0)
        emit(f"starting {config.robots} robots", 0.0, alive_tiers())
        for rid in rids:
            sup.start(specs[rid])
        sup.wait_ready(rids, timeout=config.ready_timeout_s)
        t_ready = time.monotonic()
        started_unix_ns = time.time_ns()
        outage = config.cloud_outage
        fault: dict | None = None
        grace = 15.0 + (config.deadline_ms or 0) / 1000
        last_emit = 0.0
        warned: set[str] = set()
        while True:
            now = time.monotonic() - t_ready
            if outage is not None and fault is None and now >= outage[0]:
                t_kill = sup.kill(CLOUD)
                fault = {"kind": "crash", "target": "cloud0", "tier": "cloud",
                         "start_unix_ns": t_kill, "end_unix_ns": None, "ready_unix_ns": None, "robots": None}
                faults.append(fault)
                log.info("cloud SIGKILLed at %.3f s", now)
            if fault is not None and fault["end_unix_ns"] is None and now >= outage[1]:
                p = sup.restart(CLOUD)
                fault["end_unix_ns"] = p.started_unix_ns
                log.info("cloud restarted at %.3f s", now)
            if fault is not None and fault["end_unix_ns"] is not None and fault["ready_unix_ns"] is None:
                if sup.procs[CLOUD].is_ready():
                    fault["ready_unix_ns"] = sup.procs[CLOUD].ready_unix_ns
            n_seen = len(records)
            for rid in rids:
                records.extend(tails[rid].read_new())
            if fviz is not None:
                a = alive_tiers()
                fviz.update(alive={("cloud", "cloud0"): a[CLOUD], ("leader", "leader0"): a[LEADER]},
                            records=records[n_seen:], faults=faults)
            exited = sup.exited()
            for name, rc in exited.items():
                expected = name in rids and rc == 0 or (name == CLOUD and fault is not None
                                                        and fault["end_unix_ns"] is None)
                if not expected and name not in warned:
                    warned.add(name)
                    log.warning("peer %s exited with status %s; see %s", name, rc, specs[name].log_path)
            robots_done = all(r in exited for r in rids)
            if robots_done and (fault is None or fault["end_unix_ns"] is not None or outage is None):
                break
            if now > config.duration_s + grace:
                log.warning("robots still running %.0f s after the end; stopping them", grace)
                break
            if progress is not None and now - last_emit >= progress_every_s:
                last_emit = now
                emit("running", min(now, config.duration_s), alive_tiers())
            time.sleep(0.05)
    except KeyboardInterrupt:
        interrupted = True
        log.warning("interrupted: stopping the fleet")
    finally:
        old = _ignore_interrupts()
        try:
            if sup.procs:
                emit("stopping", (time.monotonic() - t_ready) if t_ready else 0.0,
                     alive_tiers() if CLOUD in sup.procs and LEADER in sup.procs else {})
            robots_running = [r for r in rids if r in sup.procs]
            try:
                sup.stop(robots_running)  # robots first: they finish and flush their records
                # data tier (docs/DATA.md): count relayed telemetry while the cloud still runs
                from scmr_mesh.data.report import fleet_telemetry

                telemetry = fleet_telemetry(run_dir, rids, wait=CLOUD in sup.procs and sup.procs[CLOUD].alive())
            except Exception as exc:  # the peers must be stopped whatever happens here
                log.warning("telemetry accounting failed: %s", exc)
            finally:
                sup.stop_all()
        finally:
            _restore_interrupts(old)
            if fviz is not None:  # after the peers: their data is in; --save finalises the file
                try:
                    fviz.update(faults=faults)
                    fviz.close()
                except Exception as exc:  # the run's report matters more than the recording
                    log.warning("rerun: closing the recording failed: %s", exc)
        t_end = time.monotonic()
    if t_ready is None:  # interrupted during start-up
        raise KeyboardInterrupt
    for rid in rids:
        records.extend(tails[rid].read_new())
    report: dict[str, Any] = {"v": 1, "kind": "report"}
    report.update(metrics.summarize(records, faults, robots=config.robots))
    report.update({
        "rate_hz": config.rate_hz,
        "duration_s": config.duration_s,
        "started_unix_ns": started_unix_ns,
        "ended_unix_ns": time.time_ns(),
        "wall_s": round(t_end - t_ready, 3),
        "interrupted": interrupted,
        "run_dir": str(run_dir),
        "peers": {
            n: {"pid": p.pid, "log": str(p.spec.log_path), "exit": p.popen.returncode,
                "started_unix_ns": p.started_unix_ns, "ready_unix_ns": p.ready_unix_ns}
            for n, p in sup.procs.items()
        },
    })
    for f in report["faults"]:
        if f.get("ready_unix_ns") is not None and f.get("end_unix_ns") is not None:
            # split the failback gap: process start-up, then ready -> first answer
            f["restart_to_ready_ms"] = (f["ready_unix_ns"] - f["end_unix_ns"]) / 1e6
            f["failback_after_ready_ms"] = metrics.failback_gap_ms(
                records, {**f, "end_unix_ns": f["ready_unix_ns"]})
    if telemetry is not None:
        report["telemetry"] = telemetry
    validate_report(report)
    (run_dir / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


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


# --------------------------------------------------------------------------
# output (used by the CLI handlers)
# --------------------------------------------------------------------------
def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def format_summary(report: Mapping[str, Any]) -> str:
    """A readable table of a report."""
    t = report["tor_ms"]
    bt = report["by_tier"]
    ror = "-" if report["ror"] is None else f"{report['ror']:.3f}"
    lines = [
        f"fleet: {report['robots']} robots, {report.get('duration_s', 0):g} s at {report.get('rate_hz', 0):g} Hz"
        + (" (interrupted)" if report.get("interrupted") else ""),
        "",
        f"  {'robot':<8}{'requests':>9}{'ok':>7}{'RoR':>7}{'p50':>8}{'p90':>8}{'p99':>8}{'max':>8}"
        f"{'cloud':>7}{'leader':>7}{'local':>7}{'failed':>7}",
    ]

    def row(name: str, s: Mapping[str, Any]) -> str:
        r = "-" if s["ror"] is None else f"{s['ror']:.3f}"
        tt, b = s["tor_ms"], s["by_tier"]
        return (f"  {name:<8}{s['requests']:>9}{s['succeeded']:>7}{r:>7}{_ms(tt['p50']):>8}{_ms(tt['p90']):>8}"
                f"{_ms(tt['p99']):>8}{_ms(tt['max']):>8}{b['cloud']:>7}{b['leader']:>7}{b['local']:>7}"
                f"{b.get('failed', 0):>7}")

    for rid, s in report.get("per_robot", {}).items():
        lines.append(row(rid, s))
    lines.append(row("all", report))
    lines.append(f"  (ToR in ms over succeeded requests; RoR {ror})")
    for f in report.get("faults", []):
        start = (f["start_unix_ns"] - report.get("started_unix_ns", f["start_unix_ns"])) / 1e9
        end = "never" if f.get("end_unix_ns") is None else \
            f"{(f['end_unix_ns'] - report.get('started_unix_ns', 0)) / 1e9:.2f} s"
        lines.append(f"  fault: {f['kind']} {f['target']} at {start:.2f} s, restored {end}; "
                     f"failover gap {_ms(f.get('failover_gap_ms'))} ms (largest robot), "
                     f"failback gap {_ms(f.get('failback_gap_ms'))} ms"
                     + (f" = restart to ready {f['restart_to_ready_ms']:.0f} ms"
                        f" + ready to first answer {_ms(f.get('failback_after_ready_ms'))} ms"
                        if f.get("restart_to_ready_ms") is not None else ""))
    if not report.get("faults"):
        lines.append("  no faults injected")
    return "\n".join(lines)


class _ProgressPrinter:
    """A single updating line on a TTY, a line every few seconds otherwise."""

    def __init__(self, stream=sys.stderr, every_s: float = 2.0) -> None:
        self.stream = stream
        self.tty = hasattr(stream, "isatty") and stream.isatty()
        self.every_s = every_s
        self._last = -1e9
        self._phase = None

    def __call__(self, p: Progress) -> None:
        line = format_progress(p)
        if self.tty:
            import shutil

            width = max(20, shutil.get_terminal_size((120, 24)).columns - 1)  # no wrap: \r redraws one row
            self.stream.write("\r" + line[:width] + "\x1b[K")
            self.stream.flush()
            return
        now = time.monotonic()
        if p.phase != self._phase or now - self._last >= self.every_s:
            self._last, self._phase = now, p.phase
            print(line, file=self.stream, flush=True)

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


class _TermAsInterrupt:
    """While active, SIGTERM raises KeyboardInterrupt in the main thread."""

    def __enter__(self):
        def handler(signum, frame):
            raise KeyboardInterrupt

        self._old = signal.signal(signal.SIGTERM, handler)
        return self

    def __exit__(self, *exc):
        signal.signal(signal.SIGTERM, self._old)


def run_with_output(config: FleetConfig, *, json_path: str | None = None, quiet: bool = False) -> dict:
    """:func:`run_fleet` with progress on stderr; writes ``json_path`` if given."""
    printer = _ProgressPrinter() if not quiet else None
    try:
        with _TermAsInterrupt():
            report = run_fleet(config, progress=printer)
    finally:
        if printer is not None:
            printer.close()
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(report, indent=2) + "\n")
    return report


# --------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------
def _add_fleet_args(p: argparse.ArgumentParser, *, robots_default: int = 4) -> None:
    p.add_argument("--duration", type=float, default=10.0, metavar="S",
                   help="seconds each robot sends frames (default: %(default)s)")
    p.add_argument("--rate", type=float, default=5.0, metavar="HZ",
                   help="frames per second per robot (default: %(default)s)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--images", type=Path, metavar="DIR", help="a folder of images the robots send")
    src.add_argument("--synthetic", metavar="KINDS",
                     help="comma-separated synthetic scene kinds dealt to the robots (default: all kinds)")
    p.add_argument("--workers", type=int, metavar="N", help="worker processes of cloud and leader")
    p.add_argument("--lease-ms", type=int, metavar="MS", help="zenoh lease of every peer")
    p.add_argument("--deadline-ms", type=int, metavar="MS", help="robots' per-request deadline")
    p.add_argument("--ready-timeout", type=float, default=90.0, metavar="S",
                   help="seconds a peer may take to start (default: %(default)s)")
    p.add_argument("--server-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for cloud and leader (repeatable, e.g. --server-arg=--process "
                        "--server-arg=scmr_mesh.mesh.testing:stub_process)")
    p.add_argument("--robot-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for every robot (repeatable)")


def _config_from_args(args: argparse.Namespace, robots: int, run_dir: Path | None) -> FleetConfig:
    kinds = [k for k in (args.synthetic or "").split(",") if k]
    return FleetConfig(
        robots=robots, duration_s=args.duration, rate_hz=args.rate,
        cloud_outage=parse_outage(args.cloud_outage) if getattr(args, "cloud_outage", None) else None,
        images=args.images, synthetic=kinds, run_dir=run_dir, workers=args.workers,
        lease_ms=args.lease_ms, deadline_ms=args.deadline_ms, ready_timeout_s=args.ready_timeout,
        server_args=tuple(args.server_arg), robot_args=tuple(args.robot_arg),
        rerun=_rerun_options(args),
    )


def _rerun_options(args: argparse.Namespace):
    """RerunOptions from --save/--spawn/--serve/--connect, or None (scmr_mesh.viz)."""
    from scmr_mesh.viz import RerunOptions

    return RerunOptions.from_args(args)


UP_EPILOG = """\
Exit status: 0 when every request was answered (RoR >= --min-ror, default 1.0),
1 when fewer were (the report is still written) or a peer failed to start
(the error ends with the tail of its log), 130 on Ctrl-C (report written,
"interrupted": true).

Example:
  scmr up --robots 4 --duration 20 --cloud-outage 8:14 --json report.json
"""


def register(sub: argparse._SubParsersAction, bench: argparse._SubParsersAction) -> None:
    """Add ``scmr up`` and ``scmr bench mesh``."""
    p = sub.add_parser(
        "up", help="cloud, leader and N robots on loopback, with an optional cloud outage",
        description=(
            "Start a cloud, a leader and N robots as separate processes on loopback, show live "
            "progress on stderr, optionally SIGKILL the cloud at START and restart it at END, stop "
            "everything cleanly at the end or on Ctrl-C, and write a report (ToR percentiles, RoR, "
            "tiers, failover/failback gaps). Logs, records and masks go to the run directory."
        ),
        epilog=UP_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robots", type=int, default=4, metavar="N", help="robots (default: %(default)s)")
    _add_fleet_args(p)
    p.add_argument("--cloud-outage", metavar="START:END",
                   help="SIGKILL the cloud START s after the fleet is ready, restart it at END s")
    p.add_argument("--json", metavar="FILE", help="also write the report here")
    p.add_argument("--run-dir", type=Path, metavar="DIR", help="run directory (default: runs/<UTC timestamp>)")
    p.add_argument("--min-ror", type=float, default=1.0, metavar="R",
                   help="exit 1 when the RoR is below this (default: %(default)s; 0 never fails)")
    p.add_argument("--quiet", action="store_true", help="no live progress")
    from scmr_mesh.viz import add_rerun_args  # light: rerun is imported only with a flag

    add_rerun_args(p)
    p.set_defaults(func=_cmd_up)

    b = bench.add_parser(
        "mesh", help="ToR/RoR of fleets of 1, 4, 16 robots and a cloud-crash run",
        description=(
            "Run fleets of each size in --robots (no faults), then a crash run (4 robots for 16 s, "
            "cloud SIGKILLed at 4 s and restarted at 7 s), and write "
            '{"runs": [{"robots", "rate_hz", "requests", "ror", "tor_ms"}], "crash": {...}, '
            '"targets": {...}}. Targets: ToR p50 <= 15 ms and p99 <= 50 ms with 4 robots at 5 Hz; '
            "RoR 1.0 through a cloud crash; failover gap <= 50 ms; failback gap <= 1 s."
        ),
    )
    b.add_argument("--robots", default="1,4,16", metavar="LIST",
                   help="comma-separated fleet sizes (default: %(default)s)")
    _add_fleet_args(b)
    b.add_argument("--crash-robots", type=int, default=4, metavar="N",
                   help="robots in the crash run (0 skips it; default: %(default)s)")
    b.add_argument("--crash-duration", type=float, default=16.0, metavar="S",
                   help="length of the crash run (default: %(default)s)")
    b.add_argument("--crash-outage", default="4:7", metavar="START:END",
                   help="cloud SIGKILL and restart in the crash run, s (default: %(default)s; the run "
                        "goes on after END so the restarted cloud's first answer is seen)")
    b.add_argument("--overload-robots", type=int, default=8, metavar="N",
                   help="robots in the overload run (0 skips it; default: %(default)s): a cloud with a "
                        "40 ms service and 1 worker (~25 requests/s) against N robots at --overload-rate, "
                        "once with the priority negotiator (--queue 2) and once FIFO; see `scmr bench overload`")
    b.add_argument("--overload-rate", type=float, default=10.0, metavar="HZ",
                   help="frames/s per robot in the overload run (default: %(default)s)")
    b.add_argument("--json", metavar="FILE", required=True, help="where to write the results")
    b.add_argument("--run-dir", type=Path, metavar="DIR", help="parent of the runs' directories")
    b.set_defaults(func=_cmd_bench_mesh)


def _cmd_up(args: argparse.Namespace) -> int:
    config = _config_from_args(args, args.robots, args.run_dir)
    report = run_with_output(config, json_path=args.json, quiet=args.quiet)
    print(format_summary(report))
    print(f"\nreport: {Path(report['run_dir']) / 'report.json'}"
          + (f" and {args.json}" if args.json else "") + f"\nlogs:   {Path(report['run_dir']) / 'logs'}/")
    if getattr(args, "save", None):
        print(f"rerun:  {args.save} (open it with `scmr view {args.save}`)")
    if report.get("interrupted"):
        return 130
    return check_ror(report, args.min_ror)


def check_ror(report: Mapping[str, Any], min_ror: float) -> int:
    """0 if the run met ``min_ror``; raise :class:`MeshError` otherwise."""
    n, ok = report["requests"], report["succeeded"]
    if n == 0 and min_ror > 0:
        raise MeshError(f"no request finished (see the robots' logs in {report['run_dir']}/logs)")
    if n and ok / n < min_ror:
        raise MeshError(f"{n - ok} of {n} requests failed (RoR {ok / n:.3f} < --min-ror {min_ror:g}); "
                        f"report in {report['run_dir']}/report.json")
    return 0


MESH_TARGETS = {"tor_p50_ms": 15.0, "tor_p99_ms": 50.0, "crash_ror": 1.0,
                "failover_gap_ms": 50.0, "failback_gap_ms": 1000.0}


def bench_targets(runs: Sequence[Mapping[str, Any]], crash: Mapping[str, Any] | None) -> dict[str, Any]:
    """Compare bench results with the issue's targets (``None`` where not measured)."""
    out: dict[str, Any] = {"limits": dict(MESH_TARGETS)}
    four = next((r for r in runs if r["robots"] == 4 and abs(r["rate_hz"] - 5) < 1e-9), None)
    if four is not None:
        p50, p99 = four["tor_ms"]["p50"], four["tor_ms"]["p99"]
        out["tor_p50_4x5hz_ok"] = p50 is not None and p50 <= MESH_TARGETS["tor_p50_ms"]
        out["tor_p99_4x5hz_ok"] = p99 is not None and p99 <= MESH_TARGETS["tor_p99_ms"]
    else:
        out["tor_p50_4x5hz_ok"] = out["tor_p99_4x5hz_ok"] = None
    if crash is not None:
        fo = crash["failover_gaps_ms"]
        fb = crash["failback_gaps_ms"]
        out["crash_ror_ok"] = crash["ror"] == 1.0
        out["failover_ok"] = bool(fo) and all(g is not None and g <= MESH_TARGETS["failover_gap_ms"] for g in fo)
        out["failback_ok"] = bool(fb) and all(g is not None and g <= MESH_TARGETS["failback_gap_ms"] for g in fb)
    return out


def _run_entry(report: Mapping[str, Any]) -> dict[str, Any]:
    return {"robots": report["robots"], "rate_hz": report["rate_hz"], "duration_s": report["duration_s"],
            "requests": report["requests"], "succeeded": report["succeeded"], "ror": report["ror"],
            "tor_ms": report["tor_ms"], "by_tier": report["by_tier"], "run_dir": report["run_dir"]}


def _cmd_bench_mesh(args: argparse.Namespace) -> int:
    try:
        sizes = [int(x) for x in args.robots.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--robots must be a comma-separated list of integers such as 1,4,16, "
                         f"got {args.robots!r}") from None
    if not sizes or min(sizes) < 1:
        raise InputError(f"--robots needs fleet sizes >= 1, got {args.robots!r}")
    root = args.run_dir or default_run_dir(Path("runs")).with_name(
        "bench-mesh-" + time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()))
    runs = []
    for n in sizes:
        print(f"bench mesh: {n} robots at {args.rate:g} Hz for {args.duration:g} s ...", file=sys.stderr)
        rep = run_with_output(_config_from_args(args, n, root / f"robots-{n}"))
        runs.append(_run_entry(rep))
        t = rep["tor_ms"]
        print(f"  {n} robots: {rep['requests']} requests, RoR {rep['ror']}, "
              f"ToR p50 {_ms(t['p50'])} p99 {_ms(t['p99'])} max {_ms(t['max'])} ms", file=sys.stderr)
    crash = None
    if args.crash_robots > 0:
        outage = parse_outage(args.crash_outage)
        print(f"bench mesh: crash run, {args.crash_robots} robots, cloud down {outage[0]:g}-{outage[1]:g} s ...",
              file=sys.stderr)
        cfg = _config_from_args(args, args.crash_robots, root / "crash")
        cfg.duration_s = args.crash_duration
        cfg.cloud_outage = outage
        rep = run_with_output(cfg)
        crash = {**_run_entry(rep), "failover_gaps_ms": rep["failover_gaps_ms"],
                 "failback_gaps_ms": rep["failback_gaps_ms"], "faults": rep["faults"]}
        print(format_summary(rep), file=sys.stderr)
    overload = None
    if args.overload_robots > 0:  # served/busy, ToR of admitted, fairness, peak RSS (security area)
        from scmr_mesh.security.overload import run_overload

        overload = {"runs": [
            run_overload(policy=pol, robots=args.overload_robots, rate_hz=args.overload_rate, duration_s=10.0,
                         run_dir=root / f"overload-{pol}", progress=lambda m: print(m, file=sys.stderr))
            for pol in ("negotiator", "fifo")
        ]}
    result = {
        "runs": runs,
        "crash": crash,
        "overload": overload,
        "targets": bench_targets(runs, crash),
        "machine": {"cpus": os.cpu_count(), "loadavg_at_end": list(os.getloadavg())},
        "measured_unix_ns": time.time_ns(),
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"{'robots':>7}{'rate':>6}{'requests':>10}{'RoR':>7}{'p50':>8}{'p90':>8}{'p99':>8}{'max':>8}  (ms)")
    for r in runs:
        t = r["tor_ms"]
        ror = "-" if r["ror"] is None else f"{r['ror']:.3f}"
        print(f"{r['robots']:>7}{r['rate_hz']:>6g}{r['requests']:>10}{ror:>7}{_ms(t['p50']):>8}"
              f"{_ms(t['p90']):>8}{_ms(t['p99']):>8}{_ms(t['max']):>8}")
    if crash is not None:
        print(f"crash run: RoR {crash['ror']}, failover gaps {crash['failover_gaps_ms']} ms, "
              f"failback gaps {crash['failback_gaps_ms']} ms")
    for r in (overload or {}).get("runs", []):
        print(f"overload {r['policy']}: {r['requests']} requests, {r['served']} served, {r['rejected']} busy; "
              f"ToR admitted p50 {r['tor_admitted_ms']['p50']} p99 {r['tor_admitted_ms']['p99']} ms; "
              f"Jain {r['jain_all']}; cloud peak RSS {r['cloud_peak_rss_mb']['sum_sampled']} MB")
    print(f"targets: {json.dumps({k: v for k, v in result['targets'].items() if k != 'limits'})}")
    print(f"wrote {args.json}")
    return 0


