"""The kernel's parent-death signal (Linux ``PR_SET_PDEATHSIG``) for the children the project starts.

A child started in its own session (peers, the PostgreSQL server, rerun) gets no signal of the
terminal's and none from a parent killed with SIGKILL, which runs no handler; the kernel's
death signal is what stops it then.  The signal follows the *thread* that forked the child:
when that thread ends, the child gets it, even if the process lives on, so start such children
from a thread that lasts as long as they should (the main thread).  No Zenoh, no rerun.
"""

from __future__ import annotations

import os
import signal
from typing import Callable

__all__ = ["preexec", "set_in_this_process"]

PR_SET_PDEATHSIG = 1
try:   # looked up before any fork: the child between fork and exec only calls it
    import ctypes

    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):   # pragma: no cover - not Linux
    _PRCTL = None


def preexec(sig: int = signal.SIGKILL, *, reset: bool = False) -> Callable[[], None]:
    """A ``preexec_fn`` for :class:`subprocess.Popen`: the child gets ``sig`` when the calling thread dies.

    If the parent died before the signal was set, the child exits at once (status 1).  With
    ``reset``, ``sig`` is set back to its default disposition in the child first: an ignored
    signal stays ignored across exec, so a parent started with SIGTERM ignored (``trap '' TERM``,
    some supervisors) gave its child a death signal the child then ignored.  Where ``prctl`` is
    missing (not Linux) only the parent check is done.
    """
    parent, prctl, signum = os.getpid(), _PRCTL, int(sig)

    def setup() -> None:   # between fork and exec: keep it tiny
        if reset:
            signal.signal(signum, signal.SIG_DFL)
        if prctl is not None:
            prctl(PR_SET_PDEATHSIG, signum, 0, 0, 0)
        if os.getppid() != parent:
            os._exit(1)

    return setup


def set_in_this_process(sig: int = signal.SIGKILL) -> bool:
    """Ask the kernel to send ``sig`` to the calling process when its parent (thread) dies.

    For a forked worker, first thing.  False where ``prctl`` is missing (not Linux) or refuses.
    """
    if _PRCTL is None:
        return False
    return _PRCTL(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
