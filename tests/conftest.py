"""Shared fixtures: the repo root, the shared data folder, free ports."""

from __future__ import annotations

import itertools
import os
import re
import subprocess
from contextlib import contextmanager
from pathlib import Path

import pytest
from hypothesis import settings

# CI replays the same examples on every run (a failure there is reproducible, not a
# roll of the dice); local runs keep exploring with fresh random examples.
# No per-example deadline anywhere: Hypothesis's default 200 ms is a wall-clock threshold, and a
# loaded 2-core box took longer than that for one example of test_wire (a flake, not a defect).
settings.register_profile("ci", derandomize=True, print_blob=True, deadline=None)
settings.register_profile("local", deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "local")

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("SCMR_SHARED", REPO.parent / "shared")).resolve()
ROADS = SHARED / "data" / "roads"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def roads_dir() -> Path:
    """``../shared/data/roads`` (licence: read in place, never copied into the repo)."""
    if not (ROADS / "manifest.json").is_file():
        pytest.fail(f"shared road data not found at {ROADS}; set SCMR_SHARED to the shared folder")
    return ROADS


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now, outside the ephemeral range (scmr_mesh.ports)."""
    from scmr_mesh.ports import free_port as pick

    return pick()


@pytest.fixture(scope="session")
def pg_server(tmp_path_factory):
    """A real PostgreSQL server for the session (Debian's postgresql package), stopped and removed after.

    ``make test`` / ``.ci/run`` install the package when ``initdb`` is missing.
    """
    from scmr_mesh.fleet.pgserver import PgServer, available

    why = available()
    if why:
        pytest.fail(why)
    pg = PgServer(tmp_path_factory.mktemp("pg"))
    pg.start()
    try:
        yield pg
    finally:
        pg.remove()


_DB_NUMBER = itertools.count(1)


@pytest.fixture
def pg_dsn(pg_server, request) -> str:
    """The URL of a fresh, empty database on the session's PostgreSQL server."""
    name = re.sub(r"[^a-z0-9_]", "_", request.node.name.lower())[:40]
    return pg_server.create_database(f"t{next(_DB_NUMBER)}_{name}")


def _ip(*argv: str) -> None:
    subprocess.run(argv, check=True, capture_output=True, timeout=20)


@contextmanager
def bridged_hosts(prefix: str, addr: dict[str, str]):
    """Network namespaces ``<prefix>-<host>``, one per key of ``addr``, on one bridge (``<prefix>-br``),
    each with ``eth0`` at its address (/24) and no route out; deleted on exit.  Yields host -> namespace
    name.  Kill what runs inside before leaving."""
    from scmr_mesh.scenario.plan import OWN_NS_PREFIXES

    # `scmr scenario cleanup` removes only these families: a killed run's hosts must be among them
    assert f"{prefix}-".startswith(OWN_NS_PREFIXES), f"namespace prefix {prefix!r} is none of {OWN_NS_PREFIXES}"
    names = {h: f"{prefix}-{h}" for h in ("br", *addr)}
    try:
        _ip("ip", "netns", "add", names["br"])
        _ip("ip", "-n", names["br"], "link", "add", "br0", "type", "bridge")
        _ip("ip", "-n", names["br"], "link", "set", "br0", "up")
        for i, h in enumerate(addr):
            ns = names[h]
            _ip("ip", "netns", "add", ns)
            _ip("ip", "-n", ns, "link", "set", "lo", "up")
            _ip("ip", "-n", names["br"], "link", "add", f"v{i}", "type", "veth", "peer", "name", "eth0", "netns", ns)
            _ip("ip", "-n", names["br"], "link", "set", f"v{i}", "master", "br0")
            _ip("ip", "-n", names["br"], "link", "set", f"v{i}", "up")
            _ip("ip", "-n", ns, "addr", "add", f"{addr[h]}/24", "dev", "eth0")
            _ip("ip", "-n", ns, "link", "set", "eth0", "up")
        yield names
    finally:
        for ns in names.values():
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)
