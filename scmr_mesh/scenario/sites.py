"""Two (or more) "hosts" on one machine: Linux network namespaces joined by veth pairs.

Used by the cross-host test (tests/test_mesh_netns.py), the several-sites
cloud test (tests/test_scale_out_sites.py, :class:`Sites`) and the router probe
(``python -m scmr_mesh.bench.probe routers``).  The commands are computed by a
pure function (:func:`plan_two_sites`) and run by an executor you can replace,
so the plan is testable without root.  Namespaces are named ``scmrm-<tag>-a``
and ``scmrm-<tag>-b``, have no default route, and are always deleted on exit
(processes still inside are SIGKILLed first).

Topology::

    ns A: lo + veth 10.77.0.1/30  <====>  ns B: lo + veth 10.77.0.2/30
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
from typing import Callable, Sequence

from scmr_mesh.errors import MeshError

log = logging.getLogger(__name__)

ADDR_A = "10.77.0.1"
ADDR_B = "10.77.0.2"

Executor = Callable[[Sequence[str]], None]


def plan_two_sites(tag: str) -> tuple[list[str], list[list[str]], list[list[str]]]:
    """Namespace names, set-up ``ip`` argument lists and tear-down lists (pure).

    Parameters
    ----------
    tag : str
        Makes the names unique (e.g. the pid); at most 9 characters.
    """
    tag = str(tag)[:9]
    a, b = f"scmrm-{tag}-a", f"scmrm-{tag}-b"
    va, vb = f"smA{tag}", f"smB{tag}"
    up = [
        ["netns", "add", a], ["netns", "add", b],
        ["link", "add", va, "netns", a, "type", "veth", "peer", "name", vb, "netns", b],
        ["-n", a, "addr", "add", f"{ADDR_A}/30", "dev", va],
        ["-n", b, "addr", "add", f"{ADDR_B}/30", "dev", vb],
        ["-n", a, "link", "set", "lo", "up"], ["-n", b, "link", "set", "lo", "up"],
        ["-n", a, "link", "set", va, "up"], ["-n", b, "link", "set", vb, "up"],
    ]
    down = [["netns", "del", a], ["netns", "del", b]]
    return [a, b], up, down


def run_ip(args: Sequence[str]) -> None:
    """The default executor: ``ip ARGS`` (raises MeshError with ip's message)."""
    r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    if r.returncode != 0:
        raise MeshError(f"ip {' '.join(args)} failed: {r.stderr.strip()}")


def unavailable_reason() -> str | None:
    """Why namespaces cannot be made here (None when they can)."""
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    if shutil.which("ip") is None:
        return "needs the `ip` command (iproute2)"
    return None


class TwoSites:
    """Context manager creating the two namespaces; yields ``(ns_a, ns_b)``."""

    def __init__(self, tag: str | None = None, *, executor: Executor = run_ip) -> None:
        self.names, self.up, self.down = plan_two_sites(tag or str(os.getpid() % 10**9))
        self.run = executor

    def __enter__(self) -> tuple[str, str]:
        try:
            for cmd in self.up:
                self.run(cmd)
        except Exception:
            self.close()
            raise
        return self.names[0], self.names[1]

    def __exit__(self, *exc) -> None:
        self.close()

    def exec_prefix(self, ns: str) -> list[str]:
        """Command prefix running a program inside ``ns``."""
        return ["ip", "netns", "exec", ns]

    def close(self) -> None:
        """SIGKILL what still runs inside, then delete the namespaces (never raises)."""
        for ns in self.names:
            try:
                pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True,
                                      timeout=10).stdout.split()
            except Exception:
                pids = []
            for pid in pids:
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
        for cmd in self.down:
            try:
                self.run(cmd)
            except Exception as exc:
                log.debug("teardown %s: %s", cmd, exc)


def plan_sites(tag: str, n: int, links: Sequence[tuple[int, int]]) -> tuple[
        list[str], list[list[str]], list[list[str]], dict[tuple[int, int], tuple[str, str]]]:
    """Namespaces for ``n`` sites joined by a veth pair per link (pure).

    Link ``k`` between sites ``i`` and ``j`` gets the /30 ``10.78.<k+1>.0``: site
    ``i`` is ``.1``, site ``j`` is ``.2``.  No default route anywhere; traffic
    crosses only the links given (each site's router forwards between them).

    Returns
    -------
    (names, up, down, addrs)
        ``addrs[(i, j)] = (address of i, address of j)`` on their link.
    """
    tag = str(tag)[:8]
    if not 2 <= n <= 9:
        raise MeshError(f"sites: between 2 and 9 sites, got {n}")
    names = [f"scmrm-{tag}-{chr(ord('a') + i)}" for i in range(n)]
    up = [["netns", "add", ns] for ns in names]
    up += [["-n", ns, "link", "set", "lo", "up"] for ns in names]
    addrs: dict[tuple[int, int], tuple[str, str]] = {}
    for k, (i, j) in enumerate(links):
        if not (0 <= i < n and 0 <= j < n and i != j):
            raise MeshError(f"sites: link {(i, j)} names a site outside 0..{n - 1}")
        vi, vj = f"sm{tag}{k}{i}", f"sm{tag}{k}{j}"
        ai, aj = f"10.78.{k + 1}.1", f"10.78.{k + 1}.2"
        up += [["link", "add", vi, "netns", names[i], "type", "veth", "peer", "name", vj, "netns", names[j]],
               ["-n", names[i], "addr", "add", f"{ai}/30", "dev", vi],
               ["-n", names[j], "addr", "add", f"{aj}/30", "dev", vj],
               ["-n", names[i], "link", "set", vi, "up"], ["-n", names[j], "link", "set", vj, "up"]]
        addrs[(i, j)] = (ai, aj)
    down = [["netns", "del", ns] for ns in names]
    return names, up, down, addrs


class Sites(TwoSites):
    """Context manager creating ``n`` site namespaces joined by ``links``; yields the names.

    ``addrs[(i, j)]`` are the two ends' addresses of the link between sites i and j.
    """

    def __init__(self, n: int, links: Sequence[tuple[int, int]], tag: str | None = None, *,
                 executor: Executor = run_ip) -> None:
        self.names, self.up, self.down, self.addrs = plan_sites(tag or str(os.getpid() % 10**8), n, links)
        self.run = executor

    def __enter__(self) -> list[str]:  # type: ignore[override]
        super().__enter__()
        return list(self.names)
