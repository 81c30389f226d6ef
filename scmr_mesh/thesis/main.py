"""``scmr thesis``: run the fleet runs, then build and write the report.

:func:`run_thesis` prepares the report folder, states what it will run and for how long,
plays each run of :func:`scmr_mesh.thesis.plan.plan_runs` through
:func:`scmr_mesh.thesis.runs.run_one`, then :func:`scmr_mesh.thesis.analysis.build` and
:func:`scmr_mesh.thesis.report.write`.  :func:`reanalyse` rebuilds the report of an existing
folder from its raw data without running anything.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

from scmr_mesh.errors import InputError
from scmr_mesh.thesis.plan import ThesisConfig, estimate_s, plan_runs

#: A folder holding this file was written by ``scmr thesis`` and may be replaced by it.
MARKER = ".scmr-thesis"

Say = Callable[[str], None]


def _cpu_model() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def host_info() -> dict[str, Any]:
    """This machine: CPUs, model, clock (measured from /proc/cpuinfo), load average."""
    from scmr_mesh.energy import host_clock_hz
    from scmr_mesh.thesis.runs import loadavg

    hz, how = host_clock_hz()
    return {"cpus": os.cpu_count(), "cpu_model": _cpu_model(), "clock_hz": hz, "clock_source": how,
            "loadavg_at_start": loadavg(), "python": platform.python_version()}


def prepare_out(out: Path) -> None:
    """Create ``out``; replace it only when it is empty or was written by ``scmr thesis``."""
    out = Path(out)
    if out.exists():
        if not out.is_dir():
            raise InputError(f"--out {out} is a file; give a folder")
        if any(out.iterdir()):
            if not (out / MARKER).is_file():
                raise InputError(f"--out {out} holds files not written by scmr thesis; give an empty or new folder")
            shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("written by scmr thesis; `scmr thesis --out` may replace this folder\n")


def run_thesis(config: ThesisConfig, *, say: Say, thesis_csv: Path | None = None) -> dict[str, Any]:
    """Run everything and write ``report.md``, ``report.json`` and the figures into ``config.out``.

    Returns the report.
    """
    from scmr_mesh.thesis import analysis, report
    from scmr_mesh.thesis.runs import loadavg, run_one

    config.check()
    runs = plan_runs(config)
    est = estimate_s(config, runs)
    prepare_out(config.out)
    mode = "quick" if config.quick else "full"
    say(f"{mode} run: {len(runs)} fleet runs ({', '.join(runs)}; {sum(r['duration_s'] for r in runs.values()):g} s "
        f"of sending), backend {config.backend}; expect about {est / 60:.1f} min on a quiet 2-core machine "
        f"(more when it is busy; load now {loadavg()}). Report: {config.out}/report.md")
    t_start = time.time()
    meta = {"config": {**{k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(config).items()},
                       "fleet_sizes": list(config.fleet_sizes)},
            "host": host_info(), "runs": list(runs), "data_dir": str(_data_dir(config)),
            "timing": {"estimate_s": round(est, 1), "started_unix": round(t_start, 3)}}
    (config.out / "thesis_run.json").write_text(json.dumps(meta, indent=1) + "\n")
    for i, (name, sc) in enumerate(runs.items(), 1):
        say(f"[{i}/{len(runs)}] {name}: {sc['description']} ({sc['duration_s']:g} s, "
            f"{len(sc['fleet']['robots'])} robots; {time.time() - t_start:.0f} s elapsed)")
        info = run_one(name, sc, out_dir=config.out, backend=config.backend, data_dir=config.data_dir, say=say,
                       thesis_csv=thesis_csv)
        say(f"[{i}/{len(runs)}] {name}: {info['requests']} requests in {info['wall_s']:.0f} s")
    meta["timing"].update({"runs_s": round(time.time() - t_start, 1)})
    meta["host"]["loadavg_after_runs"] = loadavg()
    (config.out / "thesis_run.json").write_text(json.dumps(meta, indent=1) + "\n")
    say("analysis: experiments 1-7, Table 4.4, Eq 3.14, Eq 3.18-3.19")
    rep = analysis.build(config.out, progress=say)
    meta["timing"]["total_s"] = round(time.time() - t_start, 1)
    (config.out / "thesis_run.json").write_text(json.dumps(meta, indent=1) + "\n")
    rep["timing"] = meta["timing"]
    report.write(rep, config.out)
    return rep


def reanalyse(out: Path, *, say: Say, draw: bool = True) -> dict[str, Any]:
    """Rebuild the report of an existing ``scmr thesis`` folder from its raw data."""
    from scmr_mesh.thesis import analysis, report

    out = Path(out)
    if not (out / "thesis_run.json").is_file():
        raise InputError(f"{out} holds no scmr thesis run (no thesis_run.json); run `scmr thesis --out {out}` first")
    rep = analysis.build(out, draw=draw, progress=say)
    if draw:
        report.write(rep, out)
    return rep


def _data_dir(config: ThesisConfig) -> Path:
    from scmr_mesh.scenario.runner import default_data_dir

    return Path(config.data_dir) if config.data_dir is not None else default_data_dir()
