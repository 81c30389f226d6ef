"""Shared fixtures: the repo root, the shared data folder, free ports."""

from __future__ import annotations

import itertools
import os
import re
import socket
from pathlib import Path

import pytest
from hypothesis import settings

# CI replays the same examples on every run (a failure there is reproducible, not a
# roll of the dice); local runs keep exploring with fresh random examples.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

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
    """A TCP port on 127.0.0.1 that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
