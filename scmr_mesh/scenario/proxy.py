"""The no-root backend: one controllable TCP proxy per link, on loopback.

Peer ``a`` of link ``(a, b)`` connects to the link's proxy, which forwards to
``b``'s listen endpoint.  Each :class:`LinkProxy` can

* ``forward`` (normal),
* ``blackhole``: stop forwarding *without closing sockets*; bytes already in
  flight are held, not dropped, and nothing is read, so TCP flow control
  stalls the sender exactly as on a silently dead link (no FIN, no RST); new
  connections are accepted but not connected onwards until the link returns
  (those whose dialer gave up meanwhile are dropped, as a dead link drops a SYN),
* ``down``: close every proxied connection at once and refuse new ones (the
  loud failure, like a crashed router),
* limit the rate (bytes/s, per direction) and add a one-way delay.

What it cannot do (see docs/SCENARIOS.md): packet loss (TCP hides it: loss
faults are skipped), kernel-level behaviour (retransmission timers), or stop
traffic that does not go through a proxy: Zenoh gossip tells peers each
other's real locators, so :class:`ProxyBackend` turns gossip off and only the
links of the topology exist.  Timing is Python-thread timing: under load the
proxy adds its own sub-millisecond to millisecond delays.  Its threads block
on their sockets and on events instead of polling: an idle or blackholed link
costs no wake-ups (with polling, the threads of a blackholed cloud's links
held this process's GIL so long under `stress-ng --cpu 2` that every other
link's keep-alives missed a 1 s lease at once, and the R2R tier flapped).
"""

from __future__ import annotations

import collections
import logging
import socket
import threading
import time
from typing import Sequence

from scmr_mesh.errors import ScenarioError
from scmr_mesh.ports import free_ports
from scmr_mesh.scenario.plan import Event, proxy_actions
from scmr_mesh.scenario.spec import Scenario

__all__ = ["LinkProxy", "ProxyBackend"]

log = logging.getLogger(__name__)

_CHUNK = 65536


class _Pipe:
    """One direction of one proxied connection: a reader and a sender thread."""

    def __init__(self, proxy: "LinkProxy", src: socket.socket, dst: socket.socket, name: str) -> None:
        self.proxy, self.src, self.dst = proxy, src, dst
        self.queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self.cv = threading.Condition()
        self.queued = 0  # bytes read but not yet sent (bounded, so flow control reaches the sender)
        self.reader = threading.Thread(target=self._read, name=f"{name}-rd", daemon=True)
        self.sender = threading.Thread(target=self._send, name=f"{name}-tx", daemon=True)

    def start(self) -> None:
        self.reader.start()
        self.sender.start()

    def _read(self) -> None:
        p = self.proxy
        self.src.settimeout(None)  # blocking: no polling while idle (shutdown wakes it on close)
        while not p.closed_event.is_set():
            # blackhole or backlog: do not read, the sender's TCP stalls.  Waits are on events,
            # never sleep-polls: 20 polling threads of a blackholed cloud held the GIL of this
            # process so long that every other link's keep-alives missed a 1 s lease.
            if p.mode != "forward":
                p.flowing.wait(0.5)
                continue
            if self.queued > 4 * _CHUNK:
                with self.cv:
                    self.cv.wait_for(lambda: self.queued <= 4 * _CHUNK or p.closed_event.is_set(), 0.5)
                continue
            try:
                data = self.src.recv(_CHUNK)
            except OSError:
                data = b""
            with self.cv:
                self.queue.append((time.monotonic(), data))
                self.queued += len(data)
                self.cv.notify()
            if not data:
                return

    def _send(self) -> None:
        p = self.proxy
        while True:
            with self.cv:
                while not self.queue and not p.closed_event.is_set():
                    self.cv.wait(1.0)  # the reader notifies (data, or b"" at EOF/close)
                if p.closed_event.is_set():
                    return
                t_in, data = self.queue[0]
            # hold while blackholed; honour the delay
            while p.mode != "forward" and not p.closed_event.is_set():
                p.flowing.wait(0.5)
            wait = t_in + p.delay_s - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            with self.cv:
                self.queue.popleft()
                self.queued -= len(data)
                self.cv.notify_all()  # a reader held by the backlog
            if not data:
                try:
                    self.dst.shutdown(socket.SHUT_WR)
                except OSError:
                    pass
                return
            try:
                view = memoryview(data)
                while view:
                    rate = p.rate_bps
                    n = len(view) if rate is None else max(1, min(len(view), int(rate * 0.01) or 1))
                    sent = self.dst.send(view[:n])
                    view = view[sent:]
                    p.bytes_forwarded += sent
                    if rate is not None:
                        time.sleep(sent / rate)
            except OSError:
                return


class LinkProxy:
    """A TCP proxy from ``127.0.0.1:<listen_port>`` to ``target`` with fault controls.

    Parameters
    ----------
    target : (str, int)
        Where connections are forwarded.
    listen_port : int, keyword-only
        0 picks a free port (see :attr:`port`).
    name : str, keyword-only
        For thread names and logs.

    Example
    -------
    >>> p = LinkProxy(("127.0.0.1", 9), name="demo")
    >>> p.start(); p.set_mode("blackhole"); p.mode
    'blackhole'
    >>> p.close()
    """

    def __init__(self, target: tuple[str, int], *, listen_port: int = 0, name: str = "proxy") -> None:
        self.target = target
        self.name = name
        self.mode = "forward"
        self.delay_s = 0.0
        self.rate_bps: float | None = None
        self.bytes_forwarded = 0
        self.closed_event = threading.Event()
        self.flowing = threading.Event()  # set while the mode is forward (and at close, to wake waiters)
        self.flowing.set()
        self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._lsock.bind(("127.0.0.1", listen_port))
        except OSError as exc:
            self._lsock.close()
            raise ScenarioError(f"proxy {name}: cannot listen on 127.0.0.1:{listen_port} ({exc}); "
                                "pick another port or pass 0") from None
        self._lsock.listen(64)
        self.port = self._lsock.getsockname()[1]
        self._conns: list[tuple[socket.socket, socket.socket | None]] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._accept_loop, name=f"{name}-accept", daemon=True)

    @property
    def endpoint(self) -> str:
        """The Zenoh endpoint peers connect to: ``tcp/127.0.0.1:<port>``."""
        return f"tcp/127.0.0.1:{self.port}"

    def start(self) -> None:
        self._thread.start()

    def set_mode(self, mode: str) -> None:
        """``forward``, ``blackhole`` or ``down`` (closes every connection now)."""
        if mode not in ("forward", "blackhole", "down"):
            raise ScenarioError(f"proxy mode must be forward, blackhole or down, got {mode!r}")
        self.mode = mode
        if mode == "forward":
            self.flowing.set()
        else:
            self.flowing.clear()
        if mode == "down":
            self._close_conns()
        log.info("proxy %s: %s", self.name, mode)

    def set_rate(self, bytes_per_s: float | None) -> None:
        """Limit each direction to ``bytes_per_s`` (``None``: unlimited)."""
        self.rate_bps = None if bytes_per_s is None else float(bytes_per_s)

    def set_delay(self, seconds: float) -> None:
        """Add ``seconds`` of one-way delay to each direction."""
        self.delay_s = max(0.0, float(seconds))

    @property
    def connections(self) -> int:
        with self._lock:
            return len(self._conns)

    def _accept_loop(self) -> None:
        while not self.closed_event.is_set():
            try:
                client, _ = self._lsock.accept()  # blocking: close() shuts the socket down to wake it
            except OSError:
                return
            if self.mode == "down":
                client.close()
                continue
            threading.Thread(target=self._connect, args=(client,), name=f"{self.name}-conn", daemon=True).start()

    def _connect(self, client: socket.socket) -> None:
        held = False
        while self.mode == "blackhole" and not self.closed_event.is_set():
            held = True
            self.flowing.wait(0.5)  # hold the half-open connection, like a SYN lost in a dead link
        if self.mode == "down" or self.closed_event.is_set() or (held and _closed_by_peer(client)):
            # a dialer that gave up while the link was dead never reaches the far end (its SYN
            # was lost): passing its stale connection on would make the far end's TLS acceptor
            # wait on a handshake nobody finishes (docs/ZENOH.md, TLS accept)
            client.close()
            return
        try:
            upstream = socket.create_connection(self.target, timeout=2.0)
        except OSError:
            client.close()
            return
        upstream.settimeout(None)
        for s in (client, upstream):
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            self._conns.append((client, upstream))
        _Pipe(self, client, upstream, f"{self.name}-up").start()
        _Pipe(self, upstream, client, f"{self.name}-down").start()

    def _close_conns(self) -> None:
        with self._lock:
            conns, self._conns = self._conns, []
        for a, b in conns:
            for s in (a, b):
                if s is None:
                    continue
                try:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
                    s.shutdown(socket.SHUT_RD)  # wakes a reader blocked in recv (sends nothing)
                except OSError:
                    pass
                try:
                    s.close()
                except OSError:
                    pass

    def close(self) -> None:
        """Stop accepting and close every connection."""
        self.closed_event.set()
        self.flowing.set()
        try:
            self._lsock.shutdown(socket.SHUT_RDWR)  # wakes the blocked accept()
        except OSError:
            pass
        try:
            self._lsock.close()
        except OSError:
            pass
        self._close_conns()


def _closed_by_peer(sock: socket.socket) -> bool:
    """Whether the other end of ``sock`` has closed it (FIN or reset), even with unread data waiting."""
    import select

    p = select.poll()
    p.register(sock, select.POLLRDHUP | select.POLLHUP | select.POLLERR)
    return any(ev & (select.POLLRDHUP | select.POLLHUP | select.POLLERR) for _fd, ev in p.poll(0))


class ProxyBackend:
    """Run a scenario on loopback with a :class:`LinkProxy` per link.

    Every peer listens on its own ``127.0.0.1`` port.  When the scenario has
    link faults (or lists ``topology.links``), every link ``(a, b)`` gets a
    proxy that ``a`` connects to in front of ``b``, and gossip is turned off
    (``--cfg scouting/gossip/enabled:false``) so peers cannot find paths around
    the proxies: without ``topology.links`` every pair of peers is linked
    through its own proxy, the paths gossip would have found.  A scenario with
    only process faults (crashes) needs no proxy: each peer is handed its one
    bootstrap and gossip scouting runs as on real hosts.  Loss faults are
    skipped (TCP hides loss); latency and bandwidth are emulated in the proxy.
    """

    name = "proxy"

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.ports = free_ports(scenario.peer_names)  # all distinct (held open together while picked)
        self.proxies: dict[tuple[str, str], LinkProxy] = {}
        self.notes: list[str] = []

    def host_of(self, peer: str) -> str:
        """Each peer is its own host (the proxies stand for the links between them)."""
        return peer

    @property
    def gossip(self) -> bool:
        """Whether peers find each other by gossip (no link faults to route through proxies)."""
        return not (self.scenario.link_faults or self.scenario.explicit_links)

    def setup(self) -> None:
        if self.gossip:
            self.notes.append("proxy backend: no link faults, so no proxies: each peer was handed its bootstrap "
                              "and gossip scouting linked the rest")
            return
        if not self.scenario.explicit_links:
            self.notes.append("proxy backend: gossip off; every pair of peers linked through its own proxy "
                              "(the links gossip would find), so link faults act on every path")
        for a, b in self.scenario.links:
            px = LinkProxy(("127.0.0.1", self.ports[b]), name=f"{a}-{b}")
            px.start()
            self.proxies[(a, b)] = px

    def wrap(self, peer: str, argv: Sequence[str]) -> list[str]:
        return list(argv)

    def listen(self, peer: str) -> list[str]:
        return [f"tcp/127.0.0.1:{self.ports[peer]}"]

    def connect(self, peer: str) -> list[str]:
        if self.gossip:
            return [f"tcp/127.0.0.1:{self.ports[b]}" for b in self.scenario.dials(peer)]
        return [px.endpoint for (a, _b), px in self.proxies.items() if a == peer]

    def connect_names(self, peer: str) -> list[str]:
        """The peers ``peer`` is handed (the report's ``topology``)."""
        if self.gossip:
            return list(self.scenario.dials(peer))
        return [b for (a, b) in self.proxies if a == peer]

    def extra_cfg(self, peer: str) -> list[str]:
        return [] if self.gossip else ["scouting/gossip/enabled:false"]

    def apply(self, event: Event) -> list[str]:
        notes = []
        if event.op == "netem" and event.value is not None and float(event.value[1]) > 0:  # type: ignore[index]
            note = (f"{self.scenario.faults[event.fault].label}: loss skipped, the proxy backend "
                    "forwards TCP streams and cannot drop packets")
            if note not in self.notes:
                self.notes.append(note)
            notes.append(note)
        for link, action, value in proxy_actions(self.proxies, event):
            px = self.proxies[link]
            if action in ("blackhole", "forward"):
                px.set_mode(action)
            elif action == "rate":
                px.set_rate(value)  # type: ignore[arg-type]
            elif action == "delay":
                px.set_delay(value)  # type: ignore[arg-type]
        return notes

    def apply_many(self, events: Sequence[Event]) -> list[str]:
        notes: list[str] = []
        for e in events:
            notes += self.apply(e)
        return notes

    def teardown(self) -> None:
        for px in self.proxies.values():
            px.close()
        self.proxies.clear()
