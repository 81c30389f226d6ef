"""Free TCP ports on loopback for the processes a run starts (no Zenoh, no rerun).

A port picked here is released before the process it is meant for binds it, so
something else can take it in between.  The ports are drawn outside the kernel's
ephemeral range, where only another process picking at random can collide.
"""

from __future__ import annotations

import collections
import os
import random
import socket
import threading
from typing import Sequence

__all__ = ["free_port", "free_ports"]

# The ports this process handed out lately: two picks in a row (``free_port(), free_port()``)
# must not return the same port before either is bound.
_ISSUED: collections.deque[int] = collections.deque(maxlen=4096)
_LOCK = threading.Lock()


def _new_lock_in_child() -> None:
    # a child forked while another thread held the lock would wait on it for ever
    global _LOCK
    _LOCK = threading.Lock()


os.register_at_fork(after_in_child=_new_lock_in_child)


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range for ephemeral ports (``bind(0)`` and outgoing connections)."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            lo, hi = (int(v) for v in f.read().split())
        return lo, hi
    except (OSError, ValueError):
        return 32768, 60999   # Linux's default


def free_ports(names: Sequence[str], host: str = "127.0.0.1") -> dict[str, int]:
    """One free TCP port per name, all distinct (every socket is held open until all are bound).

    The ports are drawn outside the kernel's ephemeral range: a port picked there and released is
    back in the pool that outgoing connections and ``bind(0)`` listeners (the proxy backend's link
    proxies) draw from, and one of them took a robot's port before the robot bound it ("Address
    already in use", once in a run of the suite under load).  Outside the range only another
    process picking the same port at random can take it.
    """
    lo, hi = _ephemeral_range()
    pool = range(10000, lo) if lo - 10000 >= 1000 else range(hi + 1, 65536)
    rng = random.SystemRandom()
    socks, ports = [], {}
    with _LOCK:   # held throughout: two threads picking at once never draw the same port
        try:
            for n in names:
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                socks.append(s)
                for _ in range(1000 if len(pool) >= 1000 else 0):
                    port = rng.choice(pool)
                    if port in ports.values() or port in _ISSUED:
                        continue
                    try:
                        s.bind((host, port))
                        break
                    except OSError:
                        continue
                else:
                    # no room outside the ephemeral range (ip_local_port_range 1024 65535), or
                    # nothing free there: any free port, as bind(0) gives
                    s.bind((host, 0))
                ports[n] = s.getsockname()[1]
        finally:
            for s in socks:
                s.close()
        _ISSUED.extend(ports.values())
    return ports


def free_port(host: str = "127.0.0.1") -> int:
    """One free TCP port on ``host``, outside the ephemeral range; see :func:`free_ports`."""
    return free_ports(["port"], host)["port"]
