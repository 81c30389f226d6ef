"""CPU time of the peers of a running fleet, sampled from ``/proc`` (Linux).

The scenario runner starts every peer in its own process group (``start_new_session``)
and each peer writes a ready file holding its pid.  :class:`CpuSampler` watches a run's
``ready/`` folder, and every ``period_s`` sums ``utime + stime + cutime + cstime`` over
every live process of each peer's group: the peer and its worker processes (a worker that
exits is counted through its reaped parent's ``cutime``).  The series is what
``scmr thesis`` turns into the servers' energy (thesis Figure 4.17 D, Figure 4.21 B and C).

Pure helpers (:func:`cpu_between`) read the series back.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

log = logging.getLogger(__name__)

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _stat(pid: str) -> tuple[int, float] | None:
    """``(pgrp, cpu seconds incl. reaped children)`` of one process, or None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read().decode("ascii", "replace")
    except OSError:
        return None
    rest = data.rsplit(")", 1)[-1].split()
    # fields after "pid (comm)": state ppid pgrp session tty tpgid flags minflt cminflt majflt cmajflt
    # utime stime cutime cstime
    try:
        pgrp = int(rest[2])
        ticks = int(rest[11]) + int(rest[12]) + int(rest[13]) + int(rest[14])
    except (IndexError, ValueError):
        return None
    return pgrp, ticks / _TICK


def group_cpu_s(pgids: Sequence[int]) -> dict[int, float]:
    """CPU seconds per process group (live members, with what they reaped)."""
    want = set(pgids)
    out = {g: 0.0 for g in want}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        st = _stat(name)
        if st is not None and st[0] in want:
            out[st[0]] += st[1]
    return out


class CpuSampler:
    """Samples the CPU time of every peer of a run, in a thread, until :meth:`stop`.

    Parameters
    ----------
    ready_dir : Path
        The run's ``ready/`` folder (each peer writes ``<peer>.ready`` with ``{"pid": ...}``).
    period_s : float
        Seconds between samples.

    Attributes
    ----------
    series : dict
        ``{peer: [[t_unix_ns, cpu_s], ...]}``.
    """

    def __init__(self, ready_dir: Path, *, period_s: float = 0.2) -> None:
        self.ready_dir = Path(ready_dir)
        self.period_s = float(period_s)
        self.series: dict[str, list[list[float]]] = {}
        self.pgids: dict[str, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="scmr-cpu-sampler", daemon=True)

    def __enter__(self) -> "CpuSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        """One last sample, then stop."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def _discover(self) -> None:
        if not self.ready_dir.is_dir():
            return
        for f in self.ready_dir.iterdir():
            peer = f.name.removesuffix(".ready")  # the engine's ready files: <peer>.ready, <peer>-2.ready
            if peer in self.pgids:
                continue
            try:
                pid = int(json.loads(f.read_text())["pid"])
                self.pgids[peer] = os.getpgid(pid)
            except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError, ProcessLookupError):
                continue  # not written completely yet, or already gone: next round

    def sample(self) -> None:
        """Take one sample of every known peer."""
        self._discover()
        if not self.pgids:
            return
        now = time.time_ns()
        cpu = group_cpu_s(list(self.pgids.values()))
        for peer, g in self.pgids.items():
            s = self.series.setdefault(peer, [])
            v = cpu.get(g, 0.0)
            if s and v < s[-1][1]:  # the group is gone (peer stopped): keep the last value
                v = s[-1][1]
            s.append([now, v])

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.sample()
            except Exception as exc:  # noqa: BLE001 - a sampler must never take the run down
                log.warning("cpu sampler: %s", exc)
        try:
            self.sample()
        except Exception as exc:  # noqa: BLE001
            log.warning("cpu sampler: %s", exc)

    def to_json(self) -> dict[str, Any]:
        return {"period_s": self.period_s, "clock_ticks_per_s": _TICK, "pgids": self.pgids, "series": self.series}


def cpu_between(series: Sequence[Sequence[float]], t0_ns: float, t1_ns: float) -> float | None:
    """CPU seconds a peer used between two times, linearly interpolated between samples (pure).

    None when the window is not covered by the samples.

    Examples
    --------
    >>> cpu_between([[0, 1.0], [10, 2.0], [20, 4.0]], 5, 15)
    1.5
    """
    if not series or t0_ns < series[0][0] or t1_ns > series[-1][0] or t1_ns < t0_ns:
        return None

    def at(t: float) -> float:
        for (ta, va), (tb, vb) in zip(series, series[1:]):
            if ta <= t <= tb:
                return va if tb == ta else va + (vb - va) * (t - ta) / (tb - ta)
        return float(series[-1][1])

    return at(t1_ns) - at(t0_ns)


def peer_series(cpu: Mapping[str, Any], peer: str) -> list[list[float]]:
    """The series of ``peer`` (a restarted peer's ready file is ``peer-2``: its samples follow)."""
    series = cpu.get("series", {})
    out = list(series.get(peer, []))
    for k in sorted(series):
        if k.startswith(f"{peer}-"):
            base = out[-1][1] if out else 0.0
            out += [[t, base + v] for t, v in series[k]]
    return out
