"""The realistic backend: one Linux network namespace per peer (needs root).

Peers sit in namespaces ``scmrs-<run id>-<peer>`` joined by veth pairs to a
bridge that lives in its own namespace (``scmrs-<run id>-br``); addresses are
in the private 198.18.0.0/24 test subnet, which exists only inside those
namespaces; there is no default route, so nothing can leave.  Faults are
kernel-level (see :mod:`scmr_mesh.scenario.plan`): blackhole routes for silent
loss, htb class rates for bandwidth, netem for latency/loss where the kernel has
it (:func:`netem_available` detects it; without it those faults are skipped and
reported, not failed).

The executor is passed in (``run=``), so tests can record the commands.
:func:`cleanup_stale` removes the namespaces (and kills the processes inside them)
that a crashed run left behind: ``scmrs-*`` of scenario runs and, by default, those of
the project's other namespace users too (:data:`~scmr_mesh.scenario.plan.OWN_NS_PREFIXES`).
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
import signal
import subprocess
from pathlib import Path
from typing import Callable, Sequence

from scmr_mesh.errors import ScenarioError
from scmr_mesh.scenario.plan import NS_PREFIX, OWN_NS_PREFIXES, Event, NetnsLayout
from scmr_mesh.scenario.spec import Scenario

__all__ = [
    "NetnsBackend",
    "check_root",
    "cleanup_stale",
    "list_namespaces",
    "netem_available",
    "run_cmd",
    "run_parallel",
]

log = logging.getLogger(__name__)

Runner = Callable[[Sequence[str]], str]


def run_cmd(argv: Sequence[str]) -> str:
    """Run one ``ip``/``tc`` command; return its stdout.

    Raises
    ------
    ScenarioError
        The command failed (message: the command and its stderr).
    """
    try:
        p = subprocess.run(list(argv), capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ScenarioError(f"command failed: {' '.join(argv)}: {exc}") from None
    if p.returncode != 0:
        raise ScenarioError(f"command failed (status {p.returncode}): {' '.join(argv)}: {p.stderr.strip()}")
    return p.stdout


def run_parallel(cmds: Sequence[Sequence[str]], *, run: Runner = run_cmd) -> None:
    """Run independent commands at once (one fault touching many namespaces lands together).

    With the default runner they run as concurrent processes; any other runner
    is called in order.  Raises :class:`ScenarioError` naming the first failure.
    """
    if run is not run_cmd or len(cmds) <= 1:
        for c in cmds:
            run(c)
        return
    procs = []
    for c in cmds:
        try:
            procs.append((c, subprocess.Popen(list(c), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)))
        except OSError as exc:
            raise ScenarioError(f"command failed: {' '.join(c)}: {exc}") from None
    errors = []
    for c, p in procs:
        try:
            _, err = p.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            _, err = p.communicate()
        if p.returncode != 0:
            errors.append(f"{' '.join(c)}: {err.strip()}")
    if errors:
        raise ScenarioError(f"{len(errors)} command(s) failed: " + "; ".join(errors))


def check_root() -> None:
    """Raise :class:`ScenarioError` unless we are root on Linux with ``ip`` and ``tc``."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        raise ScenarioError("the netns backend needs root (network namespaces); "
                            "run as root or use --backend proxy")
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            raise ScenarioError(f"the netns backend needs '{tool}' (iproute2); install it or use --backend proxy")


def list_namespaces(prefix: str = NS_PREFIX, *, run: Runner = run_cmd) -> list[str]:
    """Names of the network namespaces starting with ``prefix``."""
    out = run(("ip", "netns", "list"))
    names = [line.split()[0] for line in out.splitlines() if line.strip()]
    return [n for n in names if n.startswith(prefix)]


def _ns_inode(ns: str) -> tuple[int, int] | None:
    """``(st_dev, st_ino)`` of a named namespace (what ``/proc/<pid>/ns/net`` of its processes shows)."""
    try:
        st = os.stat(f"/run/netns/{ns}")
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _sweep(ns: str, ino: tuple[int, int] | None) -> set[int]:
    """Pids inside namespace ``ns`` (by its inode, so also after its name is gone) or entering it
    (``ip netns exec NS ...`` between opening the namespace and ``setns``)."""
    found: set[int] = set()
    me = os.getpid()
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == me:
            continue
        try:
            if ino is not None:
                st = os.stat(d / "ns" / "net")
                if (st.st_dev, st.st_ino) == ino:
                    found.add(int(d.name))
                    continue
            argv = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if argv[:4] == [b"ip", b"netns", b"exec", ns.encode()] or (
                len(argv) > 4 and argv[0].endswith(b"/ip") and argv[1:4] == [b"netns", b"exec", ns.encode()]):
            found.add(int(d.name))
    return found


def _kill_pids_in(ns: str, run: Runner, ino: tuple[int, int] | None = None) -> int:
    pids: set[int] = set()
    try:
        pids |= {int(t) for t in run(("ip", "netns", "pids", ns)).split() if t.isdigit()}
    except ScenarioError:
        pass
    pids |= _sweep(ns, ino)
    n = 0
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
            n += 1
        except (ProcessLookupError, PermissionError):
            pass
    return n


def cleanup_stale(prefix: str | None = None, *, run: Runner = run_cmd) -> list[str]:
    """Kill processes in, and delete, every namespace starting with ``prefix``.

    ``prefix`` None: every prefix the project uses (:data:`OWN_NS_PREFIXES`: scenario runs,
    sites, the tx-stall bench, the tests' hosts); only namespaces this package and its tests
    create carry them.  A ``prefix`` must start with one of them.  Returns the names removed.
    A process still entering a namespace (``ip netns exec`` between opening it and
    ``setns``) is killed too, and after the name is deleted the namespace is swept again by
    its inode until nothing is left in it, so nothing keeps running in a namespace nobody can
    name any more.
    """
    if prefix is not None and not prefix.startswith(OWN_NS_PREFIXES):
        raise ScenarioError(f"refusing to clean namespaces with prefix {prefix!r}; it must start with one of "
                            f"{', '.join(OWN_NS_PREFIXES)}")
    prefixes = OWN_NS_PREFIXES if prefix is None else (prefix,)
    removed = []
    names = [ns for ns in list_namespaces("", run=run) if ns.startswith(prefixes)]
    for ns in names:
        ino = _ns_inode(ns)
        killed = _kill_pids_in(ns, run, ino)
        try:
            run(("ip", "netns", "del", ns))
            removed.append(ns)
        except ScenarioError as exc:
            log.warning("could not delete %s: %s", ns, exc)
        for _ in range(50):  # a process that entered while we were killing: sweep until none is left
            late = _sweep(ns, ino)
            if not late:
                break
            for pid in late:
                try:
                    os.kill(pid, signal.SIGKILL)
                    killed += 1
                except (ProcessLookupError, PermissionError):
                    pass
            for pid in late:  # wait for them to be gone (reaped by their parent or zombies)
                _wait_gone(pid)
        if killed:
            log.info("killed %d process(es) in %s", killed, ns)
    return removed


def _wait_gone(pid: int, timeout: float = 5.0) -> None:
    """Wait until ``pid`` has exited (a zombie counts as exited)."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return
        except OSError:
            return
        time.sleep(0.01)


_NETEM: bool | None = None


def netem_available(*, run: Runner = run_cmd) -> bool:
    """Whether this kernel has the netem qdisc (probed in a throw-away namespace)."""
    global _NETEM
    if _NETEM is not None:
        return _NETEM
    ns = f"{NS_PREFIX}probe{secrets.token_hex(3)}"
    run(("ip", "netns", "add", ns))
    try:
        run(("ip", "-n", ns, "link", "set", "lo", "up"))
        try:
            run(("tc", "-n", ns, "qdisc", "add", "dev", "lo", "root", "netem", "delay", "1ms"))
            _NETEM = True
        except ScenarioError as exc:
            log.info("netem not available: %s", exc)
            _NETEM = False
    finally:
        try:
            run(("ip", "netns", "del", ns))
        except ScenarioError:  # pragma: no cover
            pass
    return _NETEM


class NetnsBackend:
    """Build a scenario's namespaces, apply its network events, tear it down.

    Parameters
    ----------
    scenario : Scenario
    run_id : str, keyword-only
        Short id in every namespace name (default: 6 random hex digits).
    run : callable, keyword-only
        Executes one argv (default :func:`run_cmd`); pass a recorder in tests.
    """

    name = "netns"

    def __init__(self, scenario: Scenario, *, run_id: str | None = None, run: Runner = run_cmd) -> None:
        self.scenario = scenario
        self.run_id = run_id or secrets.token_hex(3)
        self.layout = NetnsLayout(scenario, self.run_id)
        self._run = run
        self.netem: bool | None = None
        self.notes: list[str] = []
        self._up = False

    def setup(self) -> None:
        """Create namespaces, bridge, veths, addresses and htb classes (undone on failure)."""
        if self._run is run_cmd:
            check_root()
        self._up = True
        try:
            for cmd in self.layout.setup():
                self._run(cmd)
        except BaseException:
            self.teardown()
            raise
        try:
            self.netem = netem_available(run=self._run)
        except ScenarioError as exc:
            self.netem = False
            log.info("netem probe failed: %s", exc)

    def wrap(self, peer: str, argv: Sequence[str]) -> list[str]:
        """The command line that runs ``argv`` inside ``peer``'s namespace."""
        return ["ip", "netns", "exec", self.layout.ns(peer), *argv]

    def listen(self, peer: str) -> list[str]:
        """Endpoints ``peer`` listens on."""
        return [self.layout.endpoint(peer)]

    def host_of(self, peer: str) -> str:
        """The host ``peer`` runs on: its own namespace."""
        return peer

    def router_endpoint(self, peer: str) -> str:
        """Where the router on ``peer``'s host listens (``shape = "routers"``)."""
        return f"tcp/{self.layout.addr(peer)}:{self.layout.port + 1}"

    def connect(self, peer: str) -> list[str]:
        """Endpoints ``peer`` is handed: its bootstrap, then the peers started before it
        (:meth:`~scmr_mesh.scenario.spec.Scenario.dials`: zenoh re-dials only those after a cut)."""
        return [self.layout.endpoint(b) for b in self.connect_names(peer)]

    def connect_names(self, peer: str) -> list[str]:
        """The peers ``peer`` is handed (the report's ``topology``)."""
        return list(self.scenario.dials(peer))

    def extra_cfg(self, peer: str) -> list[str]:
        """Extra ``--cfg`` overrides for ``peer`` (none: gossip may run, paths are real)."""
        return []

    def apply(self, event: Event) -> list[str]:
        """Run the commands of one network event; return notes (e.g. netem skipped)."""
        return self.apply_many([event])

    def apply_many(self, events: Sequence[Event]) -> list[str]:
        """Run the commands of simultaneous network events concurrently; return notes."""
        notes, cmds = [], []
        for event in events:
            if event.op == "netem" and not self.netem:
                note = (f"{self.scenario.faults[event.fault].label}: skipped, this kernel has no netem qdisc "
                        "('tc qdisc ... netem' -> 'Specified qdisc kind is unknown')")
                if note not in self.notes:
                    self.notes.append(note)
                notes.append(note)
                continue
            cmds += self.layout.commands(event)
        run_parallel(cmds, run=self._run)
        return notes

    def teardown(self) -> None:
        """Kill what runs in our namespaces and delete them (never raises)."""
        if not self._up:
            return
        for ns in self.layout.namespaces():
            _kill_pids_in(ns, self._run)
        for cmd in self.layout.teardown():
            try:
                self._run(cmd)
            except ScenarioError as exc:
                log.debug("teardown: %s", exc)
        self._up = False
