"""What a fleet run shows: the live progress line, the summary table, the exit status."""

from __future__ import annotations

import json
import signal
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from scmr_mesh.errors import MeshError
from scmr_mesh.fleet.plan import FleetConfig
from scmr_mesh.fleet.run import Progress, run_fleet


def _failover_text(fault: dict) -> str:
    """``failover gap 8.6 ms (largest robot)``, or why there is none."""
    by_robot = fault.get("failover_by_robot")
    if fault.get("failover_gap_ms") is not None:
        return f"failover gap {_ms(fault['failover_gap_ms'])} ms (largest robot)"
    if by_robot == {}:
        return "no request failed on it (no failover gap)"
    if by_robot:
        stuck = sorted(r for r, g in by_robot.items() if g is None)
        return f"NO FALLBACK ANSWER for {', '.join(stuck)} (failover gap missing)"
    return "failover gap - ms"


def format_progress(p: Progress) -> str:
    """One line: time, phase, alive tiers, requests, RoR, ToR (last 200), answers per tier."""
    ror = f"{p.succeeded / p.requests:.3f}" if p.requests else "-"
    tor = "-" if p.tor_p50_ms is None else f"{p.tor_p50_ms:.1f}/{p.tor_p99_ms:.1f}"
    tiers = " ".join(f"{k} {p.by_tier.get(k, 0)}" for k in ("cloud", "leader", "peer", "local", "failed"))
    alive = ", ".join(f"{k} {'up' if v else 'DOWN'}" for k, v in p.alive.items() if k != "leader")
    if p.leaders:
        alive += f", leader {'+'.join(p.leaders)}" + (" (SPLIT)" if len(p.leaders) > 1 else "")
    elif "leader" in p.alive:
        alive += ", leader NONE"
    phase = "" if p.phase == "running" else f"{p.phase} | "
    return (f"[{p.elapsed_s:5.1f}/{p.duration_s:g} s] {phase}{alive} | {p.requests} req, RoR {ror}, "
            f"ToR p50/p99 {tor} ms | {tiers}")


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def format_summary(report: Mapping[str, Any]) -> str:
    """A readable table of a report."""
    ror = "-" if report["ror"] is None else f"{report['ror']:.3f}"
    lines = [
        f"fleet: {report['robots']} robots, {report.get('duration_s', 0):g} s at {report.get('rate_hz', 0):g} Hz"
        + (" (interrupted)" if report.get("interrupted") else ""),
        "",
        f"  {'robot':<8}{'requests':>9}{'ok':>7}{'RoR':>7}{'p50':>8}{'p90':>8}{'p99':>8}{'max':>8}"
        f"{'cloud':>7}{'leader':>7}{'peer':>7}{'local':>7}{'failed':>7}",
    ]

    def row(name: str, s: Mapping[str, Any]) -> str:
        r = "-" if s["ror"] is None else f"{s['ror']:.3f}"
        tt, b = s["tor_ms"], s["by_tier"]
        return (f"  {name:<8}{s['requests']:>9}{s['succeeded']:>7}{r:>7}{_ms(tt['p50']):>8}{_ms(tt['p90']):>8}"
                f"{_ms(tt['p99']):>8}{_ms(tt['max']):>8}{b['cloud']:>7}{b['leader']:>7}{b.get('peer', 0):>7}{b['local']:>7}"
                f"{b.get('failed', 0):>7}")

    for rid, s in report.get("per_robot", {}).items():
        lines.append(row(rid, s))
    lines.append(row("all", report))
    lines.append(f"  (ToR in ms over succeeded requests; RoR {ror})")
    if report.get("security"):
        lines.append("  security: " + ("mutual TLS + access rules (certificates in RUN/certs)"
                                       if report["security"] == "mtls+acl"
                                       else "NONE (--insecure): anyone who reached the ports could join"))
    hosts = report.get("hosts") or {}
    if hosts.get("shape"):
        mean = hosts.get("robot_mean") or {}
        lines.append("  network: " + ("every peer a client of one zenoh router for this host"
                                      if hosts["shape"] == "routers" else "a clique: every peer linked to every other")
                     + (f"; per robot {mean['peak_rss_mb']:.0f} MB, {mean['sockets']:.0f} socket(s) at half time"
                        if mean.get("peak_rss_mb") is not None and mean.get("sockets") is not None else ""))
    for f in report.get("faults", []):
        start = (f["start_unix_ns"] - report.get("started_unix_ns", f["start_unix_ns"])) / 1e9
        if f.get("end_unix_ns") is None:
            end = "never restarted"
        else:
            at = f"{(f['end_unix_ns'] - report.get('started_unix_ns', 0)) / 1e9:.2f} s"
            end = f"restored {at}" if f.get("ready_unix_ns") is not None else \
                f"restarted {at} but NEVER BECAME READY"
        lines.append(f"  fault: {f['kind']} {f['target']} at {start:.2f} s, {end}; " + _failover_text(f)
                     + ("" if f.get("end_unix_ns") is None else f", failback gap {_ms(f.get('failback_gap_ms'))} ms")
                     + (f" = restart to ready {f['restart_to_ready_ms']:.0f} ms"
                        f" + ready to first answer {_ms(f.get('failback_after_ready_ms'))} ms"
                        if f.get("restart_to_ready_ms") is not None else ""))
    if not report.get("faults"):
        lines.append("  no faults injected")
    lines.extend(format_energy(report.get("energy")))
    lines.append("  " + format_telemetry(report.get("telemetry")))
    lines.extend(format_leadership(report.get("leadership")))
    for p in report.get("problems") or []:
        lines.append(f"  PROBLEM: {p}")
    return "\n".join(lines)


def format_energy(energy: Mapping[str, Any] | None) -> list[str]:
    """Energy per robot and where its tasks ran (``scmr up --profiles``); nothing without it."""
    if not energy:
        return ["  energy: not modelled (no --profiles: robots offloaded every frame, cloud first)"]
    lines = [f"  energy ({energy.get('placement', 'energy model')}); robot energy in J, tasks per tier where they ran:"]
    for rid, e in (energy.get("per_robot") or {}).items():
        ran = ", ".join(f"{t} {v['tasks']} ({v['energy_j']:.2f} J)" for t, v in sorted(e["ran"].items()))
        extra = []
        if e.get("planned_elsewhere"):
            extra.append(f"{e['planned_elsewhere']} ran elsewhere than planned (failover)")
        if e.get("deadline_missed"):
            extra.append(f"{e['deadline_missed']} planned past the deadline")
        if e.get("costed", 0) < e.get("tasks", 0):
            extra.append(f"{e['tasks'] - e['costed']} not costed")
        lines.append(f"    {rid:<6} {e['profile']:<8} {e['total_j']:>10.2f} J  {ran or 'no task'}"
                     + (f"; {'; '.join(extra)}" if extra else ""))
    return lines


def format_telemetry(tel: Mapping[str, Any] | None) -> str:
    """The summary's telemetry line: sent, stored, duplicates, lost, and queued when any (always printed)."""
    if tel is None:
        return "telemetry: NOT COUNTED (see the log)"
    line = (f"telemetry: {tel.get('sent', 0)} sent, {tel.get('stored', 0)} stored, "
            f"{tel.get('duplicates', 0)} duplicates, {tel.get('lost', 0)} lost")
    if tel.get("queued"):
        line += f", {tel['queued']} queued (still on the robots' disks, sent at their next start)"
    extra = []
    if tel.get("refused"):
        extra.append(f"{tel['refused']} refused by the robots' disks")
    if tel.get("dropped"):
        extra.append(f"{tel['dropped']} dropped: disk and memory buffer both full")
    if tel.get("conflicts"):
        extra.append(f"{tel['conflicts']} conflicts")
    if tel.get("error"):
        extra.append(tel["error"])
    return line + (f" ({'; '.join(extra)})" if extra else "")


def format_leadership(lead: Mapping[str, Any] | None) -> list[str]:
    """Lines naming who led the R2R tier and each change of the lead (docs/R2R.md)."""
    if not lead:
        return []
    parts = []
    for c in lead.get("changes", []):
        if c["from"] is None and c["cause"] == "start":
            parts.append(f"{c['to']} at {c['t_s']:.2f} s")
        else:
            gap = "" if c.get("succession_ms") is None else f", took {c['succession_ms']:.0f} ms"
            gap += "" if c.get("wait_ms") is None else f", robots waited <= {c['wait_ms']:.0f} ms"
            parts.append(f"{c['from'] or '-'} -> {c['to']} at {c['t_s']:.2f} s ({c['cause']}{gap})")
    for u in lead.get("unfilled") or []:
        parts.append(f"{u['from']} lost at {u['t_s']:.2f} s ({u['cause']}) and NOBODY took the lead")
    end = lead.get("leaders_at_end") or []
    out = [f"  leadership: {'; '.join(parts) or 'no leader was elected'}",
           f"  leader at the end: {', '.join(end) if end else 'none'}"
           + (f" (TWO LEADERS: {len(end)})" if len(end) > 1 else "")]
    if lead.get("converged_after_heal_ms") is not None:
        out[-1] += f"; one leader {lead['converged_after_heal_ms']:.0f} ms after the heal"
    return out


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


def run_with_output(config: FleetConfig, *, json_path: str | None = None, quiet: bool = False,
                    hooks: tuple = ()) -> dict:
    """:func:`run_fleet` with progress on stderr; writes ``json_path`` if given; ``hooks`` go to the engine."""
    printer = _ProgressPrinter() if not quiet else None
    try:
        with _TermAsInterrupt():
            report = run_fleet(config, progress=printer, hooks=tuple(hooks))
    finally:
        if printer is not None:
            printer.close()
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(report, indent=2) + "\n")
    return report


def check_fleet(report: Mapping[str, Any], min_ror: float) -> int:
    """0 if the run met ``min_ror`` and had no problem; raise :class:`MeshError` otherwise.

    Problems (``report["problems"]``, see :func:`scmr_mesh.fleet.run.fleet_problems`):
    telemetry lost or not counted, a restart that never became ready, a peer
    that exited with a non-zero status.
    """
    problems = list(report.get("problems") or [])
    try:
        check_ror(report, min_ror)
    except MeshError as exc:
        problems.insert(0, str(exc))
    if problems:
        raise MeshError("; ".join(problems) + f" (report in {report['run_dir']}/report.json)")
    return 0


def check_ror(report: Mapping[str, Any], min_ror: float) -> int:
    """0 if the run met ``min_ror``; raise :class:`MeshError` otherwise."""
    n, ok = report["requests"], report["succeeded"]
    if n == 0 and min_ror > 0:
        raise MeshError(f"no request finished (see the robots' logs in {report['run_dir']}/logs)")
    if n and ok / n < min_ror:
        raise MeshError(f"{n - ok} of {n} requests failed (RoR {ok / n:.3f} < --min-ror {min_ror:g}); "
                        f"report in {report['run_dir']}/report.json")
    return 0


