"""Benchmarks: every ``scmr bench`` target and the probes behind docs/.

The top layer: it imports whatever it measures (Zenoh itself included, for
the bare-Zenoh probes :mod:`~scmr_mesh.bench.probe` and
:mod:`~scmr_mesh.bench.txstall`), and nothing imports it but the CLI
(:mod:`scmr_mesh.cli`, through :mod:`scmr_mesh.bench.commands`).  Each target
reports medians, p99s and ratios measured in one run.
"""

from scmr_mesh._cpu import usable_cores  # noqa: F401 - the benches' name for it
