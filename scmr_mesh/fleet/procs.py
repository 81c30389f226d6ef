"""A small process supervisor for peers on one host (no middleware).

Every child runs in its own session and process group (so a signal reaches
the peer and any worker processes it forks) and asks the kernel, through
``prctl(PR_SET_PDEATHSIG, SIGKILL)``, to be killed when the supervising
thread dies, so nothing is orphaned even if the supervisor is SIGKILLed.
Each child's stdout and stderr go to its own log file; readiness is a file
the child writes once it serves (``--ready-file``).

The death signal is set in ``preexec_fn`` between ``fork`` and ``exec``; it is
tied to the *thread* that forked, so start children from the main thread (the
fleet runner is single-threaded), and it only covers the direct child: peers
that fork workers should call :func:`die_with_parent` in each worker (the
group kill of :meth:`Supervisor.stop` covers workers in every other case).

Example
-------
>>> from pathlib import Path
>>> import sys, tempfile
>>> d = Path(tempfile.mkdtemp())
>>> code = "import pathlib, sys, time; pathlib.Path(sys.argv[1]).touch(); time.sleep(60)"
>>> spec = PeerSpec("dummy", [sys.executable, "-c", code, str(d / "ready")],
...                 log_path=d / "dummy.log", ready_file=d / "ready")
>>> with Supervisor() as sup:
...     _ = sup.start(spec)
...     sup.wait_ready(["dummy"], timeout=10)
...     sup.stop_all()
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from scmr_mesh import deathsig
from scmr_mesh.errors import MeshError

__all__ = ["PeerSpec", "Proc", "Supervisor", "die_with_parent", "log_tail"]

log = logging.getLogger(__name__)

def die_with_parent(sig: int = signal.SIGKILL) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent dies.

    Call it first thing in a forked worker.  Returns ``False`` where
    ``prctl`` is unavailable (not Linux).  If the parent is already gone
    (reparented to init), the process exits at once.
    """
    ppid = os.getppid()
    if not deathsig.set_in_this_process(sig):
        return False
    if ppid == 1 or os.getppid() != ppid:
        os._exit(1)
    return True


@contextmanager
def signals_to_interrupt(signals: Sequence[int] = (signal.SIGTERM, signal.SIGHUP)) -> Iterator[None]:
    """Turn ``signals`` into :class:`KeyboardInterrupt` inside the block, so ``finally`` cleans up.

    A signal the process inherited as ignored stays ignored (``nohup`` keeps a run alive after
    a logout); outside the main thread nothing changes (Python handles signals there only).
    After the first signal the others are ignored, so a second SIGTERM cannot cut the clean-up
    short (SIGINT stays Ctrl-C; SIGKILL always works).
    """
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    mine = [s for s in signals if signal.getsignal(s) is not signal.SIG_IGN]

    def handler(signum, frame):  # noqa: ARG001
        for s in mine:
            signal.signal(s, signal.SIG_IGN)
        raise KeyboardInterrupt(f"signal {signum}")

    old = {s: signal.signal(s, handler) for s in mine}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def log_tail(path: Path, lines: int = 15) -> str:
    """The last ``lines`` lines of a text log (``"(empty log)"`` if none)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - 64 * 1024))
            data = f.read().decode("utf-8", "replace")
    except OSError:
        return f"(no log at {path})"
    tail = data.splitlines()[-lines:]
    return "\n".join("    " + ln for ln in tail) if tail else "    (empty log)"


@dataclass(frozen=True)
class PeerSpec:
    """How to start one peer.

    Parameters
    ----------
    name : str
        Unique name in the supervisor (``cloud``, ``leader``, ``r0``...).
    argv : sequence of str
        The command line.
    log_path : Path
        stdout and stderr are appended here.
    ready_file : Path, optional
        The child creates it once it is ready; removed before each start.
    env : mapping, optional
        Extra environment variables (added to the supervisor's own).
    cwd : Path, optional
    """

    name: str
    argv: Sequence[str]
    log_path: Path
    ready_file: Path | None = None
    env: Mapping[str, str] | None = None
    cwd: Path | None = None


@dataclass
class Proc:
    """A started child: its spec, ``Popen`` and the times that matter (unix ns)."""

    spec: PeerSpec
    popen: subprocess.Popen
    started_unix_ns: int
    ready_unix_ns: int | None = None
    signalled: list[tuple[int, int]] = field(default_factory=list)  # (signal, unix ns)
    group_killed: bool = False

    @property
    def pid(self) -> int:
        return self.popen.pid

    @property
    def name(self) -> str:
        return self.spec.name

    def alive(self) -> bool:
        return self.popen.poll() is None

    def is_ready(self) -> bool:
        """True once the ready file exists; records when the peer wrote it (its
        ``t_unix_ns``), else when it was first seen (the poll can be 50 ms late)."""
        if self.ready_unix_ns is None:
            rf = self.spec.ready_file
            if rf is None or rf.exists():
                self.ready_unix_ns = _written_at(rf) or time.time_ns()
        return self.ready_unix_ns is not None


def _written_at(ready_file: Path | None) -> int | None:
    """The ``t_unix_ns`` a peer put in its ready file (None if absent or unreadable)."""
    if ready_file is None:
        return None
    try:
        import json

        t = json.loads(Path(ready_file).read_text()).get("t_unix_ns")
        return int(t) if isinstance(t, int) else None
    except (OSError, ValueError, AttributeError):
        return None


class Supervisor:
    """Start, watch, signal and stop a set of named child processes.

    Parameters
    ----------
    term_timeout : float
        Seconds :meth:`stop_all` waits after SIGTERM before it SIGKILLs.

    Use as a context manager: leaving it stops every child (SIGTERM, wait,
    SIGKILL to each process group), also on an exception.
    """

    def __init__(self, *, term_timeout: float = 5.0) -> None:
        self.term_timeout = float(term_timeout)
        self.procs: dict[str, Proc] = {}

    # -- starting ---------------------------------------------------------
    def start(self, spec: PeerSpec) -> Proc:
        """Start ``spec`` (its name must not be running already)."""
        old = self.procs.get(spec.name)
        if old is not None and old.alive():
            raise MeshError(f"peer {spec.name!r} is already running (pid {old.pid}); stop it first")
        if spec.ready_file is not None:
            spec.ready_file.unlink(missing_ok=True)
        spec.log_path.parent.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        if spec.env:
            env.update(spec.env)
        with open(spec.log_path, "ab") as logf:
            logf.write(f"=== {spec.name} starting at {time.strftime('%Y-%m-%dT%H:%M:%S')}: "
                       f"{' '.join(spec.argv)}\n".encode())
            logf.flush()
            t = time.time_ns()
            try:
                popen = subprocess.Popen(
                    list(spec.argv), stdin=subprocess.DEVNULL, stdout=logf, stderr=subprocess.STDOUT,
                    env=env, cwd=spec.cwd, start_new_session=True, preexec_fn=deathsig.preexec(signal.SIGKILL),
                    close_fds=True,
                )
            except OSError as exc:
                raise MeshError(f"cannot start peer {spec.name!r} ({spec.argv[0]}): {exc}") from exc
        proc = Proc(spec, popen, t)
        self.procs[spec.name] = proc
        log.info("started %s (pid %d)", spec.name, popen.pid)
        return proc

    def restart(self, name: str) -> Proc:
        """Start ``name`` again with the same spec (it must have exited)."""
        return self.start(self._get(name).spec)

    def wait_ready(self, names: Iterable[str], *, timeout: float, poll: float = 0.02) -> None:
        """Wait until every named peer has written its ready file.

        Raises
        ------
        MeshError
            A peer exited first or was not ready within ``timeout`` seconds;
            the message names it and ends with the tail of its log.
        """
        pending = [self._get(n) for n in names]
        deadline = time.monotonic() + timeout
        while True:
            still = []
            for p in pending:
                if p.is_ready():
                    continue
                rc = p.popen.poll()
                if rc is not None:
                    raise MeshError(
                        f"peer {p.name!r} exited with status {rc} before it was ready; "
                        f"last lines of {p.spec.log_path}:\n{log_tail(p.spec.log_path)}"
                    )
                still.append(p)
            if not still:
                return
            if time.monotonic() > deadline:
                p = still[0]
                raise MeshError(
                    f"peer {p.name!r} was not ready within {timeout:g} s (no ready file "
                    f"{p.spec.ready_file}); raise the timeout if the machine is busy; "
                    f"last lines of {p.spec.log_path}:\n{log_tail(p.spec.log_path)}"
                )
            pending = still
            time.sleep(poll)

    # -- signals ----------------------------------------------------------
    def signal(self, name: str, sig: int) -> int:
        """Send ``sig`` to the process group of ``name``; return the time (unix ns)."""
        p = self._get(name)
        t = time.time_ns()
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass
        p.signalled.append((int(sig), t))
        return t

    def kill(self, name: str) -> int:
        """SIGKILL ``name`` and its group, reap it, return the kill time (unix ns)."""
        t = self.signal(name, signal.SIGKILL)
        p = self._get(name)
        p.popen.wait()
        p.group_killed = True
        return t

    # -- stopping ---------------------------------------------------------
    def stop(self, names: Iterable[str] | None = None, *, timeout: float | None = None) -> dict[str, int]:
        """SIGTERM the named peers (default: all), wait, then SIGKILL what is left.

        Each group is SIGKILLed after its leader exits too, so workers a peer
        left behind die with it.  Returns ``{name: exit status}``.
        """
        timeout = self.term_timeout if timeout is None else timeout
        procs = [self._get(n) for n in names] if names is not None else list(self.procs.values())
        for p in procs:
            if p.alive():
                self.signal(p.name, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for p in procs:
            try:
                p.popen.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s ignored SIGTERM for %.1f s; sending SIGKILL", p.name, timeout)
                self.signal(p.name, signal.SIGKILL)
                p.popen.wait()
            if not p.group_killed:
                self._kill_group(p)
        return {p.name: p.popen.returncode for p in procs}

    def stop_all(self, *, timeout: float | None = None) -> dict[str, int]:
        """Stop every child (see :meth:`stop`)."""
        return self.stop(None, timeout=timeout)

    @staticmethod
    def _kill_group(p: Proc) -> None:
        p.group_killed = True
        try:
            os.killpg(p.pid, signal.SIGKILL)  # stragglers in the group
        except (ProcessLookupError, PermissionError):
            pass

    def exited(self) -> dict[str, int]:
        """``{name: status}`` of the children that have exited (their groups are killed)."""
        out = {}
        for n, p in self.procs.items():
            if p.popen.poll() is not None and not p.group_killed:
                self._kill_group(p)
            if p.popen.returncode is not None:
                out[n] = p.popen.returncode
        return out

    def _get(self, name: str) -> Proc:
        try:
            return self.procs[name]
        except KeyError:
            raise MeshError(f"no peer named {name!r}; known: {', '.join(self.procs) or 'none'}") from None

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()
