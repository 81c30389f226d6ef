"""The rerun executable: analytics off, running the CLI, reading recordings back (no rerun import)."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path

from scmr_mesh.errors import InputError
from scmr_mesh.viz.common import (
    ViewerError,
)

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------
# analytics off, rerun executable


def state_dir() -> Path:
    """Folder that holds the rerun config/data dirs of project processes.

    ``$SCMR_RERUN_HOME`` if set (tests point it to a temporary folder), else
    ``$XDG_CACHE_HOME/scmr-mesh/rerun`` (``~/.cache/scmr-mesh/rerun``).
    """
    env = os.environ.get("SCMR_RERUN_HOME")
    if env:
        return Path(env)
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "scmr-mesh" / "rerun"


def rerun_env(base: Mapping[str, str] | None = None) -> dict[str, str]:
    """Environment for a rerun child process with usage analytics off.

    rerun reads ``<config dir>/rerun/analytics.json`` (``analytics_enabled``)
    from the XDG config dir; this points ``XDG_CONFIG_HOME`` and
    ``XDG_DATA_HOME`` into :func:`state_dir`, where that file says ``false``
    (what ``rerun analytics disable`` would write), so no analytics are
    collected and the user's own rerun dirs are neither read nor written.

    Parameters
    ----------
    base : mapping, optional
        Environment to start from (default ``os.environ``).

    Returns
    -------
    dict
        A new environment.
    """
    env = dict(os.environ if base is None else base)
    root = state_dir()
    config_home, data_home = root / "config", root / "data"
    cfg = config_home / "rerun" / "analytics.json"
    want = {
        "analytics_enabled": False,
        "analytics_id": "scmr-mesh-analytics-disabled",
        "metadata": {},
        "config_file_path": str(cfg),
        "data_dir_path": str(data_home / "rerun" / "analytics"),
    }
    try:
        current = json.loads(cfg.read_text()) if cfg.is_file() else None
    except (OSError, ValueError):
        current = None
    if current != want:
        cfg.parent.mkdir(parents=True, exist_ok=True)
        tmp = cfg.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(want))
        os.replace(tmp, cfg)
    data_home.mkdir(parents=True, exist_ok=True)
    env["XDG_CONFIG_HOME"] = str(config_home)
    env["XDG_DATA_HOME"] = str(data_home)
    return env


def rerun_executable() -> str:
    """Path of the ``rerun`` CLI that comes with rerun-sdk.

    ``$RERUN_CLI_PATH`` if set, else the binary inside the ``rerun_cli``
    package, else ``rerun`` on ``PATH``.

    Raises
    ------
    ViewerError
        When no rerun executable is found.
    """
    env = os.environ.get("RERUN_CLI_PATH")
    if env:
        return env
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin:
        exe = Path(spec.origin).parent / "rerun"
        if exe.is_file():
            return str(exe)
    found = shutil.which("rerun")
    if found:
        return found
    raise ViewerError(
        "the rerun executable was not found (looked in the rerun_cli package and on PATH); "
        "reinstall with `pip install rerun-sdk==0.41.0` or set RERUN_CLI_PATH"
    )


def run_rerun_cli(args: Sequence[str], *, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """Run ``rerun ARGS`` with analytics off and return the finished process.

    Parameters
    ----------
    args : sequence of str
        Arguments after ``rerun`` (e.g. ``["rrd", "verify", "f.rrd"]``).
    timeout : float
        Seconds before giving up.

    Raises
    ------
    ViewerError
        When the CLI cannot be run or times out (a non-zero exit is returned,
        not raised).
    """
    cmd = [rerun_executable(), *map(str, args)]
    try:
        return subprocess.run(
            cmd, env=rerun_env(), capture_output=True, text=True, timeout=timeout, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ViewerError(f"`{' '.join(cmd)}` failed: {exc}") from exc


# --------------------------------------------------------------------------
# reading recordings back


_CHUNK_RE = re.compile(r"^Chunk\(\S+\) with (\d+) rows .*? - (/\S*) - data columns: \[(.*)\]$")


def check_rrd(path: str | os.PathLike) -> Path:
    """Return ``path`` if it looks like a rerun recording, else raise.

    Raises
    ------
    InputError
        When the file is missing, empty or does not start with rerun's magic.
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise InputError(f"recording {str(path)!r} not found; pass a .rrd file written with --save")
    with p.open("rb") as f:
        head = f.read(4)
    if head[:3] != b"RRF":
        raise InputError(f"{str(path)!r} is not a rerun recording (starts with {head!r}, expected b'RRF2')")
    return p


def rrd_rows(path: str | os.PathLike) -> dict[str, dict[str, int]]:
    """Rows per entity and component of a ``.rrd``, read with ``rerun rrd print``.

    Returns
    -------
    dict
        ``{entity_path: {component: rows}}`` of the recording (not the
        blueprint), e.g. ``{"/scmr/results/r0/tor_ms": {"Scalars:scalars": 20}}``.

    Raises
    ------
    InputError, ViewerError
        For a missing/invalid file, or when the CLI fails.
    """
    p = check_rrd(path)
    res = run_rerun_cli(["rrd", "print", str(p)])
    if res.returncode != 0:
        raise ViewerError(f"`rerun rrd print {p}` failed: {res.stderr.strip()[-300:]}")
    out: dict[str, dict[str, int]] = {}
    in_recording = False
    for line in res.stdout.splitlines():
        if "StoreId(" in line or line.strip().startswith("Recording,") or line.strip().startswith("Blueprint,"):
            if line.strip().startswith("Recording,"):
                in_recording = True
            elif line.strip().startswith("Blueprint,"):
                in_recording = False
            continue
        m = _CHUNK_RE.match(line.strip())
        if not m or not in_recording:
            continue
        rows, entity, cols = int(m.group(1)), m.group(2), m.group(3)
        comps = out.setdefault(entity, {})
        for col in cols.split():
            comp = col.split("@", 1)[-1]
            comps[comp] = comps.get(comp, 0) + rows
    return out


