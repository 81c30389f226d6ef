"""Fleets of peer processes on one host: plan, run, supervise, show.

Modules, lowest first:

===========  ===============================================================
``procs``    OS processes: start, ready files, stop, no orphans
``plan``     :class:`FleetConfig` and :func:`plan_fleet` (pure: starts nothing)
``run``      :func:`run_fleet`: start, drive, stop, report, in named steps
``output``   the live progress line, the summary table, the exit status
``commands`` ``scmr up``
``demo``     ``scmr demo`` and its pictures
===========  ===============================================================

Public names are imported lazily::

    from scmr_mesh.fleet import FleetConfig, run_fleet
"""

from __future__ import annotations

from scmr_mesh._lazy import lazy_exports

_EXPORTS = {
    "CLOUD": "plan",
    "LEADER": "plan",
    "RUN_MARKER": "plan",
    "FleetConfig": "plan",
    "parse_outage": "plan",
    "plan_fleet": "plan",
    "robot_ids": "plan",
    "Progress": "run",
    "RecordTail": "run",
    "default_run_dir": "run",
    "run_fleet": "run",
    "validate_report": "run",
    "fleet_problems": "run",
    "check_ror": "output",
    "check_fleet": "output",
    "format_telemetry": "output",
    "format_progress": "output",
    "format_summary": "output",
    "run_with_output": "output",
    "PeerSpec": "procs",
    "Supervisor": "procs",
}

__all__ = sorted(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
