"""Benchmarks: every ``scmr bench`` target and the probes behind docs/.

The top layer: it imports whatever it measures (Zenoh itself included, for
the bare-Zenoh probes :mod:`~scmr_mesh.bench.probe` and
:mod:`~scmr_mesh.bench.txstall`), and nothing imports it but the CLI
(:mod:`scmr_mesh.cli`, through :mod:`scmr_mesh.bench.commands`).  Each target
reports medians, p99s and ratios measured in one run.
"""

import os as _os


def usable_cores() -> int:
    """The cores this process may run on (``taskset``/cgroup affinity), not the host's count."""
    try:
        return len(_os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return _os.cpu_count() or 1
