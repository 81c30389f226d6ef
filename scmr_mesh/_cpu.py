"""The cores this process may use: what ``taskset`` and cpusets allow, not the host's count.

One definition for the services (a cloud's default workers, ``--data-process auto``) and the
benchmarks, which report it beside their figures.  A cgroup CPU *quota* (``cpu.max``) is not
an affinity and is not counted.
"""

from __future__ import annotations

import os


def usable_cores() -> int:
    """The cores this process may run on (``sched_getaffinity``), else ``os.cpu_count()``, at least 1."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        return os.cpu_count() or 1
