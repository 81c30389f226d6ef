"""Where a peer's start-up time goes: wall and CPU time per phase, from exec to ready.

``scmr -v cloud ...`` logs the breakdown when the service is ready, and the
ready file carries it under ``"startup"``::

    {"since_exec": true, "wall_ms": 231.4, "cpu_ms": 212.0,
     "phases": [{"phase": "interpreter", "wall_ms": 30.0, "cpu_ms": 24.1}, ...]}

The first phase runs from the process's exec (``/proc/self/stat``, 10 ms
resolution) to the first mark; its CPU time is exact (the process's own CPU
clock starts at exec).  CPU time is the process's (all its threads); a phase
that waits on worker processes adds theirs as ``workers_cpu_ms``.  CPU time
is the steadier figure on a busy machine: wall time grows with other load,
CPU time much less.
"""

from __future__ import annotations

import os
import time
from typing import Any

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def exec_age_s() -> float | None:
    """Seconds since this process was exec'd (Linux; None elsewhere), +-10 ms."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / _TICK
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def process_cpu_ms(pid: int) -> float | None:
    """User + system CPU time of process ``pid`` in ms (Linux; None when unknown)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) * 1e3 / _TICK
    except (OSError, ValueError, IndexError):
        return None


class StartupClock:
    """Marks the end of each start-up phase; the first phase starts at exec.

    Example
    -------
    >>> clock = StartupClock()
    >>> clock.mark("interpreter")
    >>> clock.mark("command line")
    >>> [p["phase"] for p in clock.as_dict()["phases"]]
    ['interpreter', 'command line']
    """

    def __init__(self) -> None:
        age = exec_age_s()
        now = time.perf_counter()
        self.since_exec = age is not None
        self._t0 = now - age if age is not None else now
        self._last_wall = self._t0
        self._last_cpu = 0.0 if age is not None else time.process_time()
        self.phases: list[dict[str, Any]] = []

    def mark(self, phase: str, **extra: Any) -> None:
        """End the current phase, named ``phase`` (``extra`` fields are kept with it)."""
        wall, cpu = time.perf_counter(), time.process_time()
        entry = {"phase": phase, "wall_ms": round((wall - self._last_wall) * 1e3, 1),
                 "cpu_ms": round((cpu - self._last_cpu) * 1e3, 1)}
        entry.update(extra)
        self.phases.append(entry)
        self._last_wall, self._last_cpu = wall, cpu

    def as_dict(self) -> dict[str, Any]:
        """Totals and phases (what the ready file holds)."""
        return {
            "since_exec": self.since_exec,
            "wall_ms": round((self._last_wall - self._t0) * 1e3, 1),
            "cpu_ms": round(self._last_cpu * 1e3 if self.since_exec else sum(p["cpu_ms"] for p in self.phases), 1),
            "phases": list(self.phases),
        }

    def format(self) -> str:
        """A small table, one phase per line."""
        d = self.as_dict()
        lines = [f"{'phase':<22}{'wall ms':>9}{'cpu ms':>9}"]
        for p in d["phases"]:
            note = ", ".join(f"{k} {v}" for k, v in p.items() if k not in ("phase", "wall_ms", "cpu_ms"))
            lines.append(f"{p['phase']:<22}{p['wall_ms']:>9.1f}{p['cpu_ms']:>9.1f}" + (f"  ({note})" if note else ""))
        origin = "exec" if d["since_exec"] else "first mark"
        lines.append(f"{'total from ' + origin:<22}{d['wall_ms']:>9.1f}{d['cpu_ms']:>9.1f}")
        return "\n".join(lines)


#: The clock of this process: the CLI marks the interpreter and command-line
#: phases on it, :func:`scmr_mesh.mesh.peers.run_service` the rest.
CLOCK: StartupClock | None = None


def clock() -> StartupClock:
    """This process's clock (created at the first call)."""
    global CLOCK
    if CLOCK is None:
        CLOCK = StartupClock()
    return CLOCK
