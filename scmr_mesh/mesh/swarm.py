"""``scmr swarm`` (its command in :mod:`scmr_mesh.mesh.commands`): several robots played by one process (a load generator for benchmarks).

Each member is a whole robot: its own ``scmr robot`` command line, its own zenoh
session (so its own certificate and key under ``--security``, checked by the
fleet's access rules like any robot), its own frames, records, telemetry queue and
ready file.  What members share is the interpreter: a 2-core machine can offer the
traffic of a hundred robots without a hundred Python processes (issue 23: 64 robot
processes left the cloud no CPU).  Real ``scmr robot`` processes stay the default
for fleets and scenarios; ``scmr up --robots-per-process K`` and ``scmr bench mesh``
group robots into swarms.

A member cannot be leader-capable (a candidate is a process with its own worker
pool; run it as ``scmr robot --leader-capable``).
"""

from __future__ import annotations

import json
from pathlib import Path

from scmr_mesh.errors import InputError

#: Most robots one swarm process plays (each has a zenoh session and a few threads).
MAX_MEMBERS = 256


def read_plan(path: str | Path) -> list[list[str]]:
    """The members' argument lists of a swarm plan file.

    Raises
    ------
    InputError
        The file is not JSON of the form ``{"robots": [[str, ...], ...]}``, is empty or too long.
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"--plan {path}: cannot read a JSON swarm plan ({exc})") from None
    robots = data.get("robots") if isinstance(data, dict) else None
    if (not isinstance(robots, list) or not robots
            or not all(isinstance(m, list) and all(isinstance(a, str) for a in m) for m in robots)):
        raise InputError(f"--plan {path}: expected {{\"robots\": [[arguments of scmr robot], ...]}} "
                         "with at least one robot")
    if len(robots) > MAX_MEMBERS:
        raise InputError(f"--plan {path}: {len(robots)} robots, at most {MAX_MEMBERS} per swarm; "
                         "split them over several swarms")
    return robots
