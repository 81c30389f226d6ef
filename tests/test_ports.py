"""Free ports for the processes a run starts (scmr_mesh.ports)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import scmr_mesh.ports as ports

REPO = Path(__file__).resolve().parent.parent
#: ``NAME.bind((host, 0))``: a pick by the kernel (the check below and its control share it)
BIND0 = re.compile(r"([\w.]+)\.bind\(\([^()]*,\s*0\)\)")


def test_two_picks_in_a_row_never_return_the_same_port(monkeypatch):
    """``free_port(), free_port()``: the first is released before anything binds it, so the second
    pick must not return it again even when the random draw does."""
    a, b = ports.free_ports(["a", "b"]).values()   # two ports free on this host right now
    draws = iter([a, a, a, b])
    monkeypatch.setattr(ports.random.SystemRandom, "choice", lambda self, pool: next(draws))
    monkeypatch.setattr(ports, "_ISSUED", ports.collections.deque(maxlen=8))
    assert ports.free_port() == a
    assert ports.free_port() == b


def test_free_port_lies_outside_the_ephemeral_range():
    lo, hi = ports._ephemeral_range()
    if lo - 10000 < 1000 and hi > 64535:
        pytest.skip(f"this host's ephemeral range {lo}-{hi} leaves no room outside it (bind(0) is used)")
    assert all(not lo <= ports.free_port() <= hi for _ in range(20))


def test_no_module_picks_a_port_with_bind_zero_and_releases_it():
    """The pick-and-release pattern in the ephemeral range took a robot's port under load
    ("Address already in use"); every pick goes through scmr_mesh.ports.  A ``bind(0)`` elsewhere
    must be a listener that keeps its socket: ``listen`` on the same socket within 3 lines."""
    found = []
    for d in ("scmr_mesh", "peers", "tests"):
        for p in (REPO / d).rglob("*.py"):
            if p.name in ("ports.py", "test_ports.py"):   # the picker, and this check's control
                continue
            lines = p.read_text().splitlines()
            for i, line in enumerate(lines):
                m = BIND0.search(line)
                if m and not any(f"{m.group(1)}.listen(" in nxt for nxt in lines[i + 1:i + 4]):
                    found.append(f"{p.relative_to(REPO)}:{i + 1}")
    assert found == []


def test_the_pick_and_release_check_finds_one():
    """Control for the check above: the pattern the review slipped past the first regex."""
    src = 's = socket.socket(); s.bind(("127.0.0.1", 0)); port = s.getsockname()[1]; s.close()'
    m = BIND0.search(src)
    assert m and m.group(1) == "s"


def test_a_host_whose_ephemeral_range_covers_every_port_still_gets_ports(monkeypatch):
    """ip_local_port_range 1024 65535 (a common tuning) leaves no room outside it: bind(0)."""
    monkeypatch.setattr(ports, "_ephemeral_range", lambda: (1024, 65535))
    got = ports.free_ports(["a", "b"])
    assert len(set(got.values())) == 2 and all(p > 0 for p in got.values())


def test_picks_hold_the_lock_while_drawing(monkeypatch):
    """The review's race: thread B copied the recent picks, thread A picked and returned, B drew
    A's port.  Every draw now happens under the lock that guards the recent picks, so B waits."""
    held = []

    def choice(self, pool):
        held.append(ports._LOCK.locked())
        return 23456 + len(held)

    monkeypatch.setattr(ports.random.SystemRandom, "choice", choice)
    monkeypatch.setattr(ports, "_ephemeral_range", lambda: (32768, 60999))
    ports.free_ports(["a", "b"])
    assert held and all(held)
