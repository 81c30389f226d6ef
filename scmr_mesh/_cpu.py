"""The cores this process may use: what ``taskset``, cpusets and a cgroup CPU quota allow, not the host's count.

One definition for the services (a cloud's default workers, ``--data-process auto``) and the
benchmarks, which report it beside their figures.

A container limited with ``docker run --cpus 2`` (or a Kubernetes CPU limit) still sees every
core of the host in its affinity: the limit is a cgroup quota, ``cpu.max`` in cgroup v2
(``"200000 100000"``: 2 CPUs' time per period) or ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``
in cgroup v1.  The quota is rounded down to whole cores, at least 1 (as Go's automaxprocs
does): 1.5 CPUs count as 1, so a node's workers never outnumber the CPU time it is given and
are not throttled in bursts; the fraction left over goes to its ingress and zenoh's threads.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

#: Where the cgroup file systems are mounted.
CGROUP_ROOT = Path("/sys/fs/cgroup")


def _cgroup_paths(proc_cgroup: str) -> tuple[str | None, str | None]:
    """This process's cgroup v2 path and its v1 ``cpu`` controller's path, from ``/proc/self/cgroup``."""
    v2 = v1 = None
    for line in proc_cgroup.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        hid, controllers, path = parts
        if hid == "0" and controllers == "":
            v2 = path
        elif "cpu" in controllers.split(","):
            v1 = path
    return v2, v1


def _ancestors(base: Path, path: str | None) -> list[Path]:
    """``base`` joined with ``path`` and each of its parents up to ``base`` (a quota anywhere above applies)."""
    out = [base]
    if path:
        cur = base
        for part in [p for p in path.split("/") if p]:
            cur = cur / part
            out.append(cur)
    return out


def _read(p: Path) -> str | None:
    try:
        return p.read_text().strip()
    except OSError:
        return None


def quota_cores(root: Path = CGROUP_ROOT, proc_cgroup: str | None = None) -> float | None:
    """The CPU quota over this process's cgroups in CPUs (the tightest of them), or None when there is none."""
    if proc_cgroup is None:
        proc_cgroup = _read(Path("/proc/self/cgroup")) or ""
    v2, v1 = _cgroup_paths(proc_cgroup)
    limits: list[float] = []
    for d in _ancestors(root, v2):  # cgroup v2: "max 100000" or "<quota> <period>"
        text = _read(d / "cpu.max")
        if text:
            quota, _, period = text.partition(" ")
            if quota != "max" and quota.isdigit() and period.isdigit() and int(period) > 0:
                limits.append(int(quota) / int(period))
    try:  # cgroup v1: the hierarchy the cpu controller is mounted in (cpu, cpu,cpuacct, cpuset,cpu,...)
        v1_mounts = sorted(d for d in root.iterdir() if "cpu" in d.name.split(",") and d.is_dir())
    except OSError:
        v1_mounts = []
    for base in v1_mounts:  # the first hierarchy that has the files; -1 means no quota
        if not (base / "cpu.cfs_period_us").is_file():
            continue
        for d in _ancestors(base, v1):
            quota, period = _read(d / "cpu.cfs_quota_us"), _read(d / "cpu.cfs_period_us")
            if quota and period and quota.lstrip("-").isdigit() and period.isdigit():
                if int(quota) > 0 and int(period) > 0:
                    limits.append(int(quota) / int(period))
        break
    return min(limits) if limits else None


def usable_cores() -> int:
    """The cores this process may run on (``sched_getaffinity``, else ``os.cpu_count()``), capped by a
    cgroup CPU quota rounded down; at least 1.  Unreadable cgroup files count as no quota."""
    try:
        n = len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    try:
        q = quota_cores()
    except (OSError, ValueError):  # a locked-down sandbox: EACCES on /sys/fs/cgroup
        q = None
    if q is not None:
        n = min(n, max(1, math.floor(q + 1e-9)))
    return n
