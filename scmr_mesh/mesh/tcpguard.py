"""Bound how long a silently dead TCP link can hold zenoh's threads (a workaround).

zenoh 1.10.2 sets ``SO_LINGER`` to 10 s on every TCP (and TLS) link and gives
no option to change it (``io/zenoh-links/zenoh-link-tcp``: ``TCP_LINGER_TIMEOUT``).
On Linux a lingering ``close()`` blocks the calling thread, even on a
non-blocking socket, until the unsent data is acknowledged or the linger time
runs out.  When a peer goes silent (WiFi out of range, cable pulled: no FIN, no
RST), data sent just before stays unacknowledged, so when zenoh drops the dead
link at lease expiry the thread that closes it, one of zenoh's runtime workers,
is stuck for up to 10 s, or until the route comes back and the peer answers
with a reset.  Upstream: eclipse-zenoh/zenoh#1101 ("Drop of LinkUnicastTcp can
stall Runtime") and #2718 (all forwarding stalls ~10 s when a silently dead
link is closed at lease expiry), both open; docs/ZENOH.md section 8.

The workaround, from outside zenoh: give each of the session's TCP sockets
``TCP_USER_TIMEOUT``.  The kernel then aborts a connection whose data stays
unacknowledged that long, which ends a lingering close (and a write stuck on
the dead socket) at once.  :class:`LinkGuard` listens to the session's link
events and sets the option on the socket of every new link (found in
``/proc/self/fd`` by its local and remote address; only zenoh's links are
touched, never a database or viewer connection).

The timeout defaults to the lease (a link that acknowledges nothing for a lease
is dead, as zenoh's lease already says), at least 100 ms;
``$SCMR_TCP_USER_TIMEOUT_MS`` overrides it, ``0`` turns the guard off.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from typing import Any

log = logging.getLogger(__name__)

#: Environment override of the timeout in ms (``0``: no guard).
ENV = "SCMR_TCP_USER_TIMEOUT_MS"
#: Smallest timeout the guard sets (below the kernel's 200 ms minimum RTO a single
#: lost segment would already abort the connection).
MIN_MS = 100

_TCP_USER_TIMEOUT = getattr(socket, "TCP_USER_TIMEOUT", 18)


def _addr(locator: str) -> tuple[str, int] | None:
    """``"tcp/127.0.0.1:7447"`` -> ``("127.0.0.1", 7447)`` (tcp and tls only)."""
    proto, sep, rest = str(locator).partition("/")
    if not sep or proto not in ("tcp", "tls"):
        return None
    rest = rest.split("#", 1)[0].split("?", 1)[0]
    host, sep, port = rest.rpartition(":")
    if not sep:
        return None
    try:
        return host.strip("[]"), int(port)
    except ValueError:
        return None


def _norm(addr: Any) -> tuple[str, int]:
    host = str(addr[0])
    if host.startswith("::ffff:"):  # an IPv4 peer on a dual-stack socket
        host = host[7:]
    return host, int(addr[1])


def set_user_timeout(pairs: set[tuple[tuple[str, int], tuple[str, int]]], timeout_ms: int,
                     done: set[int] | None = None) -> int:
    """Set ``TCP_USER_TIMEOUT`` on this process's TCP sockets whose (local, remote) address is in ``pairs``.

    ``done`` holds the socket inodes already handled (updated).  Returns how
    many sockets were changed.  Works on duplicates of the descriptors: the
    option belongs to the socket, and closing the duplicate leaves it open.
    """
    done = set() if done is None else done
    changed = 0
    try:
        names = os.listdir("/proc/self/fd")
    except OSError:
        return 0
    for name in names:
        try:
            target = os.readlink(f"/proc/self/fd/{name}")
        except OSError:
            continue
        if not target.startswith("socket:["):
            continue
        inode = int(target[8:-1])
        if inode in done:
            continue
        try:
            dup = os.dup(int(name))
        except OSError:
            continue
        try:
            s = socket.socket(fileno=dup)
        except OSError:
            os.close(dup)
            continue
        try:
            if s.type != socket.SOCK_STREAM or s.family not in (socket.AF_INET, socket.AF_INET6):
                done.add(inode)
                continue
            try:
                key = (_norm(s.getsockname()), _norm(s.getpeername()))
            except OSError:  # a listening socket
                done.add(inode)
                continue
            if key in pairs:
                s.setsockopt(socket.IPPROTO_TCP, _TCP_USER_TIMEOUT, int(timeout_ms))
                done.add(inode)
                changed += 1
        except OSError as exc:
            log.debug("TCP_USER_TIMEOUT on fd %s: %s", name, exc)
        finally:
            s.close()
    return changed


class LinkGuard:
    """Sets ``TCP_USER_TIMEOUT`` on every TCP link of ``session`` (see the module docstring).

    Link events only queue work; a daemon thread does the ``/proc`` scan, so
    zenoh's callback threads never wait for it.  :meth:`close` undeclares the
    listener.
    """

    def __init__(self, session, timeout_ms: int) -> None:
        self.timeout_ms = int(timeout_ms)
        self.applied = 0
        self._done: set[int] = set()
        self._pending: set[tuple[tuple[str, int], tuple[str, int]]] = set()
        self._all: set[tuple[tuple[str, int], tuple[str, int]]] = set()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="scmr-tcpguard", daemon=True)
        self._thread.start()
        self._listener = session.info.declare_link_events_listener(self._on_event, history=True)

    def _on_event(self, event) -> None:
        if "PUT" not in str(event.kind):
            return
        src, dst = _addr(event.link.src), _addr(event.link.dst)
        if src is None or dst is None:
            return
        with self._lock:
            self._pending.add((src, dst))
        self._wake.set()

    def _run(self) -> None:
        while not self._closed:
            self._wake.wait()
            self._wake.clear()
            with self._lock:
                pairs, self._pending = self._pending, set()
            if not pairs or self._closed:
                continue
            self._all |= pairs
            # a link's socket is already open when zenoh reports the link
            n = set_user_timeout(self._all, self.timeout_ms, self._done)
            self.applied += n
            log.debug("TCP_USER_TIMEOUT %d ms on %d new link socket(s)", self.timeout_ms, n)

    def close(self) -> None:
        self._closed = True
        self._wake.set()
        try:
            self._listener.undeclare()
        except Exception:  # the session may be gone already
            pass


def timeout_for(lease_ms: int | None) -> int:
    """The guard's timeout for a lease (``$SCMR_TCP_USER_TIMEOUT_MS`` wins; 0 = off)."""
    raw = os.environ.get(ENV, "").strip()
    if raw:
        try:
            return max(0, int(float(raw)))
        except ValueError:
            log.warning("%s=%r is not a number of ms; using the lease", ENV, raw)
    return max(MIN_MS, int(lease_ms or 0))


def guard(session, lease_ms: int | None) -> LinkGuard | None:
    """Start a :class:`LinkGuard` on ``session`` (None when turned off or not on Linux)."""
    ms = timeout_for(lease_ms)
    if ms <= 0 or not os.path.isdir("/proc/self/fd"):
        return None
    try:
        return LinkGuard(session, ms)
    except Exception as exc:  # an older zenoh without link events: no guard
        log.warning("TCP link guard not started (%s); a silently dead link may stall zenoh up to 10 s", exc)
        return None
