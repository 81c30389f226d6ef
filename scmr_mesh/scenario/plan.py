"""Pure planning: topology and faults -> the exact actions a backend performs.

Nothing here runs a command.  :func:`compile_timeline` turns a scenario's
faults into backend-neutral :class:`Event` s (block / unblock a pair of peers,
kill / start a peer, shape a link, netem a link) with reference counting, so
overlapping faults (a partition over a link that is already down) neither add a
route twice nor lift it early.  :class:`NetnsLayout` names the namespaces,
interfaces and addresses of one run and turns setup, teardown and each event
into ``ip`` / ``tc`` argv lists.  The proxy backend interprets the same events
with :func:`proxy_actions`.  Tests check these plans without root.

Example
-------
>>> from scmr_mesh.scenario.spec import parse_scenario
>>> sc = parse_scenario({"name": "t", "seed": 0, "duration_s": 5,
...     "fleet": {"robots": [{"id": "robot1", "synthetic": "road"}]},
...     "faults": [{"kind": "link_down", "at_s": 1, "for_s": 2, "link": ["robot1", "cloud"]}]})
>>> [(e.at_s, e.op, e.target) for e in compile_timeline(sc)]
[(1.0, 'block', ('cloud', 'robot1')), (3.0, 'unblock', ('cloud', 'robot1'))]
>>> NetnsLayout(sc, run_id="ab12").commands(compile_timeline(sc)[0])[0]
('ip', '-n', 'scmrs-ab12-cloud', 'route', 'add', 'blackhole', '198.18.0.12/32')
"""

from __future__ import annotations

import itertools
from pathlib import Path
from dataclasses import dataclass, field
from typing import Iterable

from scmr_mesh.scenario.spec import Fault, Scenario

__all__ = [
    "Event",
    "PeerCommand",
    "RunOptions",
    "peer_command",
    "router_command",
    "NetnsLayout",
    "NS_PREFIX",
    "OWN_NS_PREFIXES",
    "SUBNET",
    "UNLIMITED",
    "compile_timeline",
    "proxy_actions",
    "affected_pairs",
]

#: Every namespace a scenario run creates starts with this prefix.
NS_PREFIX = "scmrs-"
#: The prefixes of every network namespace the project creates, and only of those: scenario runs
#: (``scmrs-``, also the blackhole test's hosts), the sites of the several-sites tests and the
#: router probe (``scmrm-``, :mod:`scmr_mesh.scenario.sites`), the tx-stall bench (``scmrb-``,
#: :mod:`scmr_mesh.bench.txstall`), the tests' bridged hosts (``scmrh-``, ``tests/conftest.py``)
#: and the TCP guard's test hosts (``scmrg-``, ``tests/test_mesh_tcpguard.py``).  ``scmr scenario
#: cleanup`` removes what a killed run of any of them left; a test checks that no other prefix is used.
OWN_NS_PREFIXES = (NS_PREFIX, "scmrm-", "scmrb-", "scmrh-", "scmrg-")
#: The private test subnet (RFC 2544 benchmarking range); it exists only inside our namespaces.
SUBNET = "198.18.0"
#: The htb rate used for "no limit".
UNLIMITED = "10gbit"


@dataclass(frozen=True)
class Event:
    """A backend-neutral change at ``at_s`` seconds.

    ``op`` is one of ``block`` / ``unblock`` (``target`` = sorted peer pair),
    ``kill`` / ``start`` (``target`` = ``(peer,)``), ``shape`` (``target`` =
    link, ``value`` = kbit/s or ``None`` for unlimited) and ``netem``
    (``target`` = link, ``value`` = ``(delay_ms, loss_percent)``, ``None`` to
    remove).  ``fault`` is the index of the causing fault, ``lift`` whether it
    is the end of that fault.  ``ends`` names other faults this event ends:
    link faults none of whose cuts was restored at their own lift because
    another fault still cut the same peers.
    """

    at_s: float
    op: str
    target: tuple[str, ...]
    value: object = None
    fault: int = -1
    lift: bool = False
    ends: tuple[int, ...] = ()


def _pair(a: str, b: str) -> tuple[str, str]:
    return (a, b) if a <= b else (b, a)


def affected_pairs(fault: Fault) -> list[tuple[str, str]]:
    """The sorted peer pairs a ``link_down`` or ``partition`` cuts."""
    if fault.kind == "link_down" and fault.link:
        return [_pair(*fault.link)]
    if fault.kind == "partition" and fault.groups:
        pairs = set()
        for g1, g2 in itertools.combinations(fault.groups, 2):
            for a in g1:
                for b in g2:
                    pairs.add(_pair(a, b))
        return sorted(pairs)
    return []


def compile_timeline(scenario: Scenario) -> list[Event]:
    """Turn the scenario's faults into ordered events (reference-counted).

    Faults without ``for_s`` are lifted at ``duration_s`` so that, once every
    event has run, the topology is whole again.  A link fault none of whose cuts
    is restored at its own lift (another fault still cuts the same peers) ends
    when they are: the ``unblock`` that restores the last of them names it in
    ``ends``.  A fault that restores some of its cuts at its lift ends there.

    Parameters
    ----------
    scenario : Scenario

    Returns
    -------
    list of Event
        Sorted by time; at equal times lifts come before new faults.
    """
    marks: list[tuple[float, int, int, bool]] = []
    for i, f in enumerate(scenario.faults):
        marks.append((f.at_s, 1, i, False))
        end = f.end_s if f.end_s is not None and f.end_s < scenario.duration_s else scenario.duration_s
        marks.append((end, 0, i, True))
    radio = _radio_marks(scenario)
    marks.extend((t, 2, RADIO, k) for k, (t, _, _) in enumerate(radio))  # (lift slot holds the change's index)
    marks.sort()
    blocks: dict[tuple[str, str], int] = {}
    shapes: dict[tuple[str, str], list[tuple[int, int]]] = {}
    netem: dict[tuple[str, str], dict[int, tuple[str, float]]] = {}
    events: list[Event] = []
    held: dict[int, set[tuple[str, str]]] = {}  # lifted faults' cuts still held by another fault
    for at, _, i, lift in marks:
        if i == RADIO:  # a pair goes out of / comes into radio range, or its bandwidth step changes
            _, p, change = radio[lift]
            if change in ("out", "in"):
                n = blocks.get(p, 0)
                blocks[p] = n + 1 if change == "out" else n - 1
                if (change == "out" and n == 0) or (change == "in" and n == 1):
                    events.append(Event(at, "block" if change == "out" else "unblock", p, fault=RADIO))
            else:
                active = shapes.setdefault(p, [])
                before = min((r for _, r in active), default=None)
                active[:] = [x for x in active if x[0] != RADIO] + ([(RADIO, change[1])] if change[1] else [])
                after = min((r for _, r in active), default=None)
                if after != before:
                    events.append(Event(at, "shape", p, after, fault=RADIO))
            continue
        f = scenario.faults[i]
        if f.kind in ("link_down", "partition"):
            still_cut: set[tuple[str, str]] = set()
            restored_any = False
            for p in affected_pairs(f):
                n = blocks.get(p, 0)
                if lift:
                    blocks[p] = n - 1
                    if n == 1:
                        restored_any = True
                        ends = []
                        for k, pairs in held.items():
                            if p in pairs:
                                pairs.discard(p)
                                if not pairs:
                                    ends.append(k)
                        for k in ends:
                            del held[k]
                        events.append(Event(at, "unblock", p, fault=i, lift=True, ends=tuple(sorted(ends))))
                    else:
                        still_cut.add(p)
                else:
                    blocks[p] = n + 1
                    if n == 0:
                        events.append(Event(at, "block", p, fault=i))
            if lift and still_cut and not restored_any:  # wholly held by another fault: it ends with that cut
                held[i] = still_cut
        elif f.kind == "crash":
            if lift and not f.restart and f.end_s is None:
                continue  # stays down (scmr up's --kill-cloud, --leader-crash)
            for peer in f.crashed:
                events.append(Event(at, "start" if lift else "kill", (peer,), fault=i, lift=lift))
        elif f.kind == "bandwidth":
            link = tuple(f.link)
            active = shapes.setdefault(link, [])
            before = min((r for _, r in active), default=None)
            if lift:
                active.remove((i, f.rate_kbit))
            else:
                active.append((i, f.rate_kbit))
            after = min((r for _, r in active), default=None)
            if after != before:
                events.append(Event(at, "shape", link, after, fault=i, lift=lift))
        elif f.kind in ("latency", "loss"):
            link = tuple(f.link)
            active_n = netem.setdefault(link, {})
            before_n = _netem_value(active_n)
            if lift:
                active_n.pop(i, None)
            else:
                active_n[i] = (f.kind, float(f.delay_ms if f.kind == "latency" else f.percent))
            after_n = _netem_value(active_n)
            if after_n != before_n:
                events.append(Event(at, "netem", link, after_n, fault=i, lift=lift))
    return events


#: ``Event.fault`` of the events a radio topology causes (not a fault of the timeline).
RADIO = -1


def _radio_marks(scenario: Scenario) -> list[tuple[float, tuple[str, str], object]]:
    """A radio topology's changes: ``(t, pair, "out"|"in"|("rate", kbit))``; pairs out of range at 0 first."""
    radio = getattr(scenario, "radio", None)
    if radio is None:
        return []
    from scmr_mesh.scenario.radio import rate_changes

    at0 = radio.links_at(0.0)
    out: list[tuple[float, tuple[str, str], object]] = [
        (0.0, (a, b) if a <= b else (b, a), "out")
        for a, b in itertools.combinations(sorted(radio.positions), 2) if _pair(a, b) not in at0]
    out += [(t, p, "in" if up else "out") for t, p, up in radio.changes(scenario.duration_s)]
    out += [(t, p, ("rate", r)) for t, p, r in rate_changes(radio, scenario.duration_s)]
    return out


def _netem_value(active: dict[int, tuple[str, float]]) -> tuple[float, float] | None:
    if not active:
        return None
    delay = sum(v for k, v in active.values() if k == "latency")
    loss = max((v for k, v in active.values() if k == "loss"), default=0.0)
    return (delay, loss)


@dataclass
class NetnsLayout:
    """Names and addresses of one netns run, and the ``ip``/``tc`` commands for it.

    Every peer gets namespace ``scmrs-<run_id>-<peer>`` with ``eth0`` at
    ``198.18.0.<10+i>/24``; the bridge ``br0`` lives in its own namespace
    ``scmrs-<run_id>-br`` with one veth end ``v<i>`` per peer.  Nothing is
    created in the host's namespace and there is no default route.  Each
    declared link gets an htb class per direction (rate :data:`UNLIMITED`
    until a bandwidth fault changes it).
    """

    scenario: Scenario
    run_id: str
    port: int = 7447
    peers: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        self.peers = self.scenario.peer_names

    # names ---------------------------------------------------------------
    @property
    def bridge_ns(self) -> str:
        return f"{NS_PREFIX}{self.run_id}-br"

    def ns(self, peer: str) -> str:
        """The namespace of ``peer``."""
        return f"{NS_PREFIX}{self.run_id}-{peer}"

    def addr(self, peer: str) -> str:
        """The IPv4 address of ``peer`` (inside its namespace only)."""
        return f"{SUBNET}.{10 + self.peers.index(peer)}"

    def endpoint(self, peer: str) -> str:
        """The Zenoh endpoint ``peer`` listens on."""
        return f"tcp/{self.addr(peer)}:{self.port}"

    def classid(self, src: str, dst: str) -> str:
        """The htb class in ``src``'s namespace that carries traffic to ``dst``."""
        return f"1:{10 + self.peers.index(dst)}"

    def namespaces(self) -> list[str]:
        return [self.bridge_ns] + [self.ns(p) for p in self.peers]

    # plans ---------------------------------------------------------------
    def setup(self) -> list[tuple[str, ...]]:
        """Commands that build the bridge, the namespaces, veths, addresses and htb classes."""
        br = self.bridge_ns
        cmds: list[tuple[str, ...]] = [
            ("ip", "netns", "add", br),
            ("ip", "-n", br, "link", "set", "lo", "up"),
            ("ip", "-n", br, "link", "add", "br0", "type", "bridge"),
            ("ip", "-n", br, "link", "set", "br0", "up"),
        ]
        for i, p in enumerate(self.peers):
            ns = self.ns(p)
            cmds += [
                ("ip", "netns", "add", ns),
                ("ip", "-n", ns, "link", "set", "lo", "up"),
                ("ip", "-n", br, "link", "add", f"v{i}", "type", "veth", "peer", "name", "eth0", "netns", ns),
                ("ip", "-n", br, "link", "set", f"v{i}", "master", "br0"),
                ("ip", "-n", br, "link", "set", f"v{i}", "up"),
                ("ip", "-n", ns, "addr", "add", f"{self.addr(p)}/24", "dev", "eth0"),
                ("ip", "-n", ns, "link", "set", "eth0", "up"),
                ("tc", "-n", ns, "qdisc", "add", "dev", "eth0", "root", "handle", "1:", "htb", "default", "1"),
                ("tc", "-n", ns, "class", "add", "dev", "eth0", "parent", "1:", "classid", "1:1",
                 "htb", "rate", UNLIMITED),
            ]
        for a, b in self.scenario.links:
            for src, dst in ((a, b), (b, a)):
                ns, cid = self.ns(src), self.classid(src, dst)
                cmds += [
                    ("tc", "-n", ns, "class", "add", "dev", "eth0", "parent", "1:", "classid", cid,
                     "htb", "rate", UNLIMITED),
                    ("tc", "-n", ns, "filter", "add", "dev", "eth0", "parent", "1:", "protocol", "ip",
                     "prio", "1", "u32", "match", "ip", "dst", f"{self.addr(dst)}/32", "flowid", cid),
                ]
        return cmds

    def teardown(self) -> list[tuple[str, ...]]:
        """Commands that remove everything :meth:`setup` made (peers first, bridge last)."""
        return [("ip", "netns", "del", self.ns(p)) for p in self.peers] + [("ip", "netns", "del", self.bridge_ns)]

    def commands(self, event: Event) -> list[tuple[str, ...]]:
        """The ``ip``/``tc`` commands for one network event (``[]`` for kill/start).

        Blocks are blackhole routes on both sides: the kernel drops the packets
        silently (no FIN, no RST), as when a radio link is lost.
        """
        if event.op in ("block", "unblock"):
            a, b = event.target
            verb = "add" if event.op == "block" else "del"
            return [
                ("ip", "-n", self.ns(a), "route", verb, "blackhole", f"{self.addr(b)}/32"),
                ("ip", "-n", self.ns(b), "route", verb, "blackhole", f"{self.addr(a)}/32"),
            ]
        if event.op == "shape":
            a, b = event.target
            rate = UNLIMITED if event.value is None else f"{int(event.value)}kbit"
            out = []
            for src, dst in ((a, b), (b, a)):
                out.append(("tc", "-n", self.ns(src), "class", "change", "dev", "eth0", "parent", "1:",
                            "classid", self.classid(src, dst), "htb", "rate", rate, "ceil", rate))
            return out
        if event.op == "netem":
            a, b = event.target
            out = []
            for src, dst in ((a, b), (b, a)):
                cid = self.classid(src, dst)
                handle = f"{cid.split(':')[1]}:"
                if event.value is None:
                    out.append(("tc", "-n", self.ns(src), "qdisc", "del", "dev", "eth0", "parent", cid))
                else:
                    delay, loss = event.value  # type: ignore[misc]
                    # delay is one-way per direction: half the round trip each side
                    out.append(("tc", "-n", self.ns(src), "qdisc", "replace", "dev", "eth0", "parent", cid,
                                "handle", handle, "netem", "delay", f"{delay / 2:g}ms", "loss", f"{loss:g}%"))
            return out
        return []

    def plan(self, events: Iterable[Event] | None = None) -> list[tuple[float | str, tuple[str, ...] | str]]:
        """The whole run as ``(when, action)`` rows: setup, timed events, teardown.

        ``when`` is ``"setup"``, a time in seconds, or ``"teardown"``; ``action``
        is an argv tuple or a text like ``kill cloud``.
        """
        evs = compile_timeline(self.scenario) if events is None else list(events)
        rows: list[tuple[float | str, tuple[str, ...] | str]] = [("setup", c) for c in self.setup()]
        for e in evs:
            if e.op in ("kill", "start"):
                rows.append((e.at_s, f"{e.op} {e.target[0]}" + (" (SIGKILL)" if e.op == "kill" else "")))
            for c in self.commands(e):
                rows.append((e.at_s, c))
        rows += [("teardown", c) for c in self.teardown()]
        return rows


def proxy_actions(links: Iterable[tuple[str, str]], event: Event) -> list[tuple[tuple[str, str], str, object]]:
    """What the proxy backend does for one event: ``(link, action, value)`` rows.

    ``action`` is ``blackhole`` (stop forwarding, keep the sockets), ``forward``,
    ``rate`` (bytes/s or ``None``) or ``delay`` (seconds).  Only declared links
    have proxies, so a block between two peers without a link does nothing
    (there is no proxied path between them).
    """
    out: list[tuple[tuple[str, str], str, object]] = []
    for link in links:
        key = _pair(*link)
        if event.op in ("block", "unblock") and key == event.target:
            out.append((tuple(link), "blackhole" if event.op == "block" else "forward", None))
        elif event.op == "shape" and key == _pair(*event.target):
            out.append((tuple(link), "rate", None if event.value is None else int(event.value) * 1000 // 8))
        elif event.op == "netem" and key == _pair(*event.target):
            delay = 0.0 if event.value is None else float(event.value[0]) / 1000.0  # type: ignore[index]
            out.append((tuple(link), "delay", delay))
    return out


@dataclass(frozen=True)
class RunOptions:
    """How a scenario's peers are started (what ``scmr up`` and ``scmr scenario run`` differ in).

    The scenario says *what* runs (peers, links, faults); these say *how*: the
    interpreter, extra arguments, the data store, the file robots start on.
    """

    python: str = "python3"
    #: ``-v`` to every peer (``scmr up`` logs each peer's INFO lines).
    verbose: bool = False
    #: Robots get ``--quiet`` (no line per request in their log) and ``--seed`` (the scenario's).
    robot_quiet: bool = True
    robot_seed: bool = True
    workers: int | None = None
    server_args: tuple[str, ...] = ()
    robot_args: tuple[str, ...] = ()
    #: The store every cloud node gets as ``--ods`` (None: theirs, ``<run dir>/ods.sqlite``).
    ods: str | None = None
    #: Written in ``<run dir>/ready/`` at time 0; robots send from then on (``--start-file``).
    start_file: str = "run.start"
    #: A restarted peer runs under a new name (``cloud-2``: its own log, ready file and, for a
    #: robot, records folder) or under its own (``scmr up``: one log per peer).
    restart_renames: bool = True
    #: Robots played by one ``scmr swarm`` process (1: a process per robot).  Only robots that
    #: no fault names, that are not leader-capable and share a host are grouped (:func:`swarm_groups`).
    robots_per_process: int = 1
    #: Robots also write their frames and masks to ``<mcap_dir>/<name>.mcap`` (``scmr up --mcap``).
    mcap_dir: str | None = None


@dataclass(frozen=True)
class PeerCommand:
    """One start of one peer: its name, command line, log and ready file (pure data)."""

    name: str
    peer: str
    argv: tuple[str, ...]
    log_path: Path
    ready_file: Path


def peer_command(scenario: Scenario, peer: str, *, run_dir: Path, listen: Iterable[str] = (),
                 connect: Iterable[str] = (), extra_cfg: Iterable[str] = (), security: Iterable[str] = (),
                 options: RunOptions = RunOptions(), images: dict[str, Path] | None = None,
                 start: int = 1, remaining_s: float | None = None, zmode: str | None = None) -> PeerCommand:
    """The command line of ``peer`` (the one builder ``scmr up`` and ``scmr scenario run`` share; pure).

    Parameters
    ----------
    listen, connect, extra_cfg : iterables of str
        From the backend: the endpoints ``peer`` listens on and is handed, and ``--cfg`` overrides.
    security : iterable of str
        ``--security PROFILE --credentials DIR`` or ``--insecure``.
    images : dict, optional
        Robot id -> folder of its image set's links (robots with an ``image_set``).
    start : int
        1 for the first start, n for the n-th (a restart); see :attr:`RunOptions.restart_renames`.
    remaining_s : float, optional
        A robot restarted mid-run sends for this long instead of the scenario's duration.
    zmode : str, optional
        ``client`` under ``shape = "routers"``: the peer is a client of its host's router.

    Examples
    --------
    >>> from scmr_mesh.scenario.spec import parse_scenario
    >>> sc = parse_scenario({"name": "t", "seed": 3, "duration_s": 5,
    ...     "fleet": {"robots": [{"id": "robot1", "synthetic": "road"}]}})
    >>> c = peer_command(sc, "robot1", run_dir=Path("run"), connect=["tcp/127.0.0.1:7001"])
    >>> c.argv[3:8], c.ready_file.as_posix()
    (('robot', '--id', 'robot1', '--synthetic', 'road'), 'run/ready/robot1.ready')
    """
    name = peer if start == 1 or not options.restart_renames else f"{peer}-{start}"
    ready = run_dir / "ready" / f"{name}.ready"
    role = scenario.role(peer)
    argv: list[str] = [options.python, "-m", "scmr_mesh"] + (["-v"] if options.verbose else [])
    if role in ("cloud", "leader"):
        argv += [role, "--node", scenario.node_of(peer)]
        if role == "leader":
            argv += ["--capability", scenario.leader_capability]
        if options.workers is not None:
            argv += ["--workers", str(options.workers)]
        if role == "cloud" and options.ods is not None:
            argv += ["--ods", str(options.ods)]
        if scenario.process:
            argv += ["--process", scenario.process]
    else:
        r = next(x for x in scenario.robots if x.id == peer)
        argv += ["robot", "--id", peer]
        if r.image_set:
            argv += ["--images", str((images or {})[peer])]
        elif r.images:
            argv += ["--images", str(r.images)]
        else:
            argv += ["--synthetic", r.synthetic or "road"]
        dur = scenario.duration_s if remaining_s is None else max(0.5, remaining_s)
        argv += ["--rate", f"{r.rate_hz:g}", "--duration", f"{dur:g}", "--out", str(run_dir / "robots" / name)]
        if r.energy_placement:
            if not r.profile:
                from scmr_mesh.errors import ConfigError

                raise ConfigError(f"scenario {scenario.source}: field 'fleet.robots' ({peer}): energy_placement "
                                  "needs a profile; add profile = \"robot1\" (Table 4.3) or similar")
            argv += ["--profile", r.profile]
        if r.deadline_ms is not None:
            argv += ["--deadline-ms", str(r.deadline_ms)]
        if not r.local_fallback:
            argv += ["--no-local-fallback"]
        if r.leader_capable:
            argv += ["--leader-capable"]
            if r.capability or r.profile:
                argv += ["--capability", str(r.capability or r.profile)]
        if scenario.process:
            argv += ["--process", scenario.process]
        if options.robot_seed:
            argv += ["--seed", str(scenario.seed)]
        if options.robot_quiet:
            argv += ["--quiet"]
        if options.mcap_dir is not None:
            argv += ["--mcap", str(Path(options.mcap_dir) / f"{name}.mcap")]
        argv += ["--start-file", str(run_dir / "ready" / options.start_file)]
    if zmode is not None:
        argv += ["--zmode", zmode]
    if zmode is None and scenario.dials_every_pair:
        extra_cfg = [*extra_cfg, PEER_DIALS_CFG]
    argv += _link_args(scenario, listen, connect, extra_cfg, security, ready)
    argv += list(options.robot_args if role == "robot" else options.server_args)
    return PeerCommand(name, peer, tuple(argv), run_dir / "logs" / f"{name}.log", ready)


def swarm_groups(scenario: Scenario, per_process: int, host_of=lambda p: p) -> list[list[str]]:
    """The scenario's robots as the processes that play them (pure): lists of ids, one per process.

    With ``per_process`` > 1, robots that no fault names (a crash, a link, a partition), that are
    not leader-capable and that share a host (``host_of``) are played ``per_process`` to a
    ``scmr swarm`` process; every other robot, and every robot of a scenario with a radio
    topology, keeps its own process.

    >>> from scmr_mesh.scenario.spec import parse_scenario
    >>> sc = parse_scenario({"name": "t", "seed": 1, "duration_s": 5, "fleet": {"robots": [
    ...     {"id": f"r{i}", "synthetic": "road"} for i in range(1, 6)]},
    ...     "faults": [{"kind": "crash", "at_s": 1, "peer": "r5"}]})
    >>> swarm_groups(sc, 2, host_of=lambda p: "h")
    [['r1', 'r2'], ['r3', 'r4'], ['r5']]
    >>> swarm_groups(sc, 1)
    [['r1'], ['r2'], ['r3'], ['r4'], ['r5']]
    """
    ids = [r.id for r in scenario.robots]
    if per_process <= 1 or scenario.radio is not None:
        return [[r] for r in ids]
    named: set[str] = set()
    for f in scenario.faults:
        named.update(f.link or ())
        named.update(p for g in (f.groups or ()) for p in g)
        named.update(f.peers or ())
        if f.peer:
            named.add(f.peer)
    capable = {r.id for r in scenario.robots if r.leader_capable}
    by_host: dict[str, list[str]] = {}
    out: list[list[str]] = []
    for rid in ids:
        if rid in named or rid in capable:
            out.append([rid])
        else:
            by_host.setdefault(host_of(rid), []).append(rid)
    for members in by_host.values():
        out.extend(members[i:i + per_process] for i in range(0, len(members), per_process))
    return out


def _link_args(scenario: Scenario, listen: Iterable[str], connect: Iterable[str], cfg: Iterable[str],
               security: Iterable[str], ready: Path) -> list[str]:
    """The flags every process of a run ends with: endpoints, lease, ``--cfg``, security, ready file."""
    argv = [a for ep in listen for a in ("--listen", ep)] + [a for ep in connect for a in ("--connect", ep)]
    argv += ["--lease-ms", str(scenario.lease_ms)] + [a for c in cfg for a in ("--cfg", c)]
    return argv + [*security, "--ready-file", str(ready)]


#: A peer handed every earlier peer (``Scenario.dials_every_pair``) does not dial the peers gossip
#: tells it of: the later one of each pair dials it, and both dialling at once left 21 links for
#: 15 pairs (6 peers, loopback; 15 with this), each extra link one more to tear down when a
#: link dies silently (docs/ZENOH.md sections 8 and 14).  Routers are still dialled.
PEER_DIALS_CFG = 'scouting/gossip/autoconnect:{router:[],peer:["router"]}'

#: Routers dial their neighbours only (``Scenario.router_dials``): gossip would link them to
#: routers the scenario does not link (an explicit topology) or retry the unreachable ones.
ROUTER_CFG: tuple[str, ...] = ("scouting/gossip/enabled:false",)


def router_command(scenario: Scenario, peer: str, *, run_dir: Path, listen: Iterable[str],
                   connect: Iterable[str], security: Iterable[str] = (), options: RunOptions = RunOptions(),
                   start: int = 1, name: str | None = None) -> PeerCommand:
    """The command line of the router on ``peer``'s host (``shape = "routers"``; pure).

    ``name``: the router's identity when it is not ``Scenario.router_of(peer)`` (the loopback
    backend's one router for the whole host).

    >>> from scmr_mesh.scenario.spec import parse_scenario
    >>> sc = parse_scenario({"name": "t", "seed": 3, "duration_s": 5, "topology": {"shape": "routers"},
    ...     "fleet": {"robots": [{"id": "robot1", "synthetic": "road"}]}})
    >>> c = router_command(sc, "robot1", run_dir=Path("run"), listen=["tcp/10.0.0.3:7448"],
    ...                    connect=["tcp/10.0.0.1:7448"])
    >>> c.name, c.argv[3:7]
    ('router-robot1', ('router', '--node', 'router-robot1', '--listen'))
    """
    base = name or scenario.router_of(peer)
    name = base if start == 1 or not options.restart_renames else f"{base}-{start}"
    argv: list[str] = [options.python, "-m", "scmr_mesh"] + (["-v"] if options.verbose else [])
    argv += ["router", "--node", base]
    ready = run_dir / "ready" / f"{name}.ready"
    argv += _link_args(scenario, listen, connect, ROUTER_CFG, security, ready)
    return PeerCommand(name, peer, tuple(argv), run_dir / "logs" / f"{name}.log", ready)
