"""Free ports for the processes a run starts (scmr_mesh.ports)."""

from __future__ import annotations

import re
from pathlib import Path

import scmr_mesh.ports as ports

REPO = Path(__file__).resolve().parent.parent


def test_two_picks_in_a_row_never_return_the_same_port(monkeypatch):
    """``free_port(), free_port()``: the first is released before anything binds it, so the second
    pick must not return it again even when the random draw does."""
    draws = iter([23456, 23456, 23456, 23457])
    monkeypatch.setattr(ports.random.SystemRandom, "choice", lambda self, pool: next(draws))
    monkeypatch.setattr(ports, "_ephemeral_range", lambda: (32768, 60999))
    monkeypatch.setattr(ports, "_ISSUED", ports.collections.deque(maxlen=8))
    assert ports.free_port() == 23456
    assert ports.free_port() == 23457


def test_free_port_lies_outside_the_ephemeral_range():
    lo, hi = ports._ephemeral_range()
    assert all(not lo <= ports.free_port() <= hi for _ in range(20))


def test_no_module_picks_a_port_with_bind_zero_and_releases_it():
    """The pick-and-release pattern in the ephemeral range took a robot's port under load
    ("Address already in use"); every pick goes through scmr_mesh.ports."""
    pick = re.compile(r"with socket\.socket\([^)]*\) as (\w+):\s*\n\s*\1\.bind\(\([^)]*, 0\)\)")
    found = [str(p.relative_to(REPO)) for d in ("scmr_mesh", "peers", "tests") for p in (REPO / d).rglob("*.py")
             if p.name != "ports.py" and pick.search(p.read_text())]
    assert found == []
