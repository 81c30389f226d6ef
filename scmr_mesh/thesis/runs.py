"""Run the fleet runs of ``scmr thesis`` through the scenario runner and keep their raw data.

Each run of :func:`scmr_mesh.thesis.plan.plan_runs` is played by
:func:`scmr_mesh.scenario.runner.run_scenario` (real ``scmr cloud|leader|robot`` processes,
real faults on the chosen backend; whatever the launchers start by default, such as an
authenticated mesh, reaches these runs too) while a :class:`~scmr_mesh.thesis.cpu.CpuSampler`
records every peer's CPU time.  What the analysis needs is kept in ``OUT/runs/<name>/``:

* ``run.json``: the scenario as run, the backend, time 0, the faults with the times they really
  took effect, the notes and the telemetry count;
* ``cpu.json``: each peer's CPU seconds over time;
* ``robots/<id>/records.jsonl`` and ``robots/<id>/inbox/<seq>.mask.png`` (written by the robots);
* ``images/<id>/`` links to the frames each robot sent (read in place, never copied);
* the scenario's own ``report.md``, ``report.json``, ``tor.png``, ``tiers.png`` and the peer logs.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any, Callable

from scmr_mesh.thesis.cpu import CpuSampler

log = logging.getLogger(__name__)

Say = Callable[[str], None]


def loadavg() -> list[float] | None:
    """``/proc/loadavg``'s 1, 5 and 15 minute averages (None where it cannot be read)."""
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except (OSError, ValueError):
        return None


def run_one(name: str, scenario_dict: dict[str, Any], *, out_dir: Path, backend: str, data_dir: Path | None,
            say: Say, thesis_csv: Path | None = None, ready_timeout: float = 120.0) -> dict[str, Any]:
    """Play one scenario, sample CPU, write ``run.json``, ``cpu.json`` and the scenario report.

    Returns
    -------
    dict
        The content of ``run.json``.

    Raises
    ------
    ScenarioError
        A peer did not start (its log tail is in the message).
    """
    from scmr_mesh.scenario.report import build_report, write_report
    from scmr_mesh.scenario.runner import run_scenario
    from scmr_mesh.scenario.spec import parse_scenario

    sc = parse_scenario(scenario_dict, source=f"scmr thesis run {name}")
    run_dir = Path(out_dir) / "runs" / name
    if (run_dir / "robots").exists():
        from scmr_mesh.errors import InputError

        raise InputError(f"{run_dir} already holds a run; give a new --out or delete {Path(out_dir)}")
    run_dir.mkdir(parents=True, exist_ok=True)
    started = time.time()
    load_before = loadavg()
    with CpuSampler(run_dir / "ready") as sampler:
        res = run_scenario(sc, backend=backend, out_dir=run_dir, data_dir=data_dir,
                           progress=lambda m: say(f"{name}: {m}"), ready_timeout=ready_timeout)
    faults = res.metric_faults()
    info = {
        "name": name,
        "scenario": scenario_dict,
        "backend": backend,
        "t0_unix_ns": res.t0_unix_ns,
        "robots_started_unix_ns": res.robots_started_unix_ns,
        "faults": faults,
        "notes": res.notes,
        "telemetry": res.telemetry,
        "wall_s": round(time.time() - started, 3),
        "loadavg": {"before": load_before, "after": loadavg()},
        "requests": len(res.records),
    }
    (run_dir / "run.json").write_text(json.dumps(info, indent=1, default=str) + "\n")
    (run_dir / "cpu.json").write_text(json.dumps(sampler.to_json()) + "\n")
    try:  # the scenario's own report beside the raw data (tables, ToR and tier plots)
        rep = build_report(sc, res.records, faults, t0_unix_ns=res.t0_unix_ns, backend=backend, notes=res.notes,
                           thesis_csv=thesis_csv, telemetry=res.telemetry, leadership=res.leadership(),
                           topology=res.topology)
        write_report(rep, run_dir)
    except Exception as exc:  # noqa: BLE001 - the thesis report is built from the raw data anyway
        log.warning("scenario report of %s not written: %s", name, exc)
    return info
