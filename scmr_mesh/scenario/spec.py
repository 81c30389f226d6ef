"""Scenario files: TOML loading and validation (pure: no Zenoh, no rerun, no processes).

A scenario file declares the fleet (cloud nodes, the leader, robots with an
energy profile and an image set), the link topology, a timeline of faults, the
seed and the expectations checked at the end.  :func:`load_scenario` reads one
and validates it against ``schemas/scenario.schema.json`` and then against the
rules a schema cannot express (names known, partitions disjoint, ...).  Every
problem raises :class:`~scmr_mesh.errors.ConfigError` naming the file, the
field and the fix.

Example
-------
>>> from scmr_mesh.scenario.spec import parse_scenario
>>> sc = parse_scenario({"name": "tiny", "seed": 1, "duration_s": 2,
...     "fleet": {"robots": [{"id": "robot1", "synthetic": "road"}]}})
>>> [p.name for p in sc.peers]
['cloud', 'leader', 'robot1']
>>> sc.bootstraps
{'cloud': (), 'leader': ('cloud',), 'robot1': ('cloud',)}
>>> sc.links
(('leader', 'cloud'), ('robot1', 'cloud'), ('robot1', 'leader'))

Every peer is handed one bootstrap (``bootstraps``) and finds the others by
gossip scouting, so every pair of peers is a link a fault can name
(``links``); it also dials the peers started before it (``Scenario.dials``), the
only links Zenoh re-dials after a cut.  A scenario that lists ``topology.links`` gets exactly those
links and connections instead.
"""

from __future__ import annotations

import json
import math
import operator
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Mapping

import tomllib

from scmr_mesh.errors import ConfigError

__all__ = [
    "WHOEVER_LEADS",
    "Expectation",
    "Fault",
    "PeerSpec",
    "RobotSpec",
    "Scenario",
    "SCHEMA_PATH",
    "FAULT_KINDS",
    "load_scenario",
    "parse_scenario",
]

#: The JSON schema every scenario file is validated against.
SCHEMA_PATH = Path(__file__).resolve().parents[2] / "schemas" / "scenario.schema.json"

#: The target of a crash of whichever node leads when the crash is due.
WHOEVER_LEADS = "@leader"

#: Fault verbs, and the verb that lifts each one (used in plans and reports).
FAULT_KINDS: dict[str, str] = {
    "link_down": "link_up",
    "partition": "heal",
    "crash": "restart",
    "bandwidth": "unlimit",
    "latency": "no_latency",
    "loss": "no_loss",
}

_OPS: dict[str, Callable[[float, float], bool]] = {
    ">=": operator.ge, "<=": operator.le, "==": operator.eq, ">": operator.gt, "<": operator.lt,
}


@dataclass(frozen=True)
class PeerSpec:
    """A peer of the fleet: ``role`` is ``"cloud"``, ``"leader"`` or ``"robot"``."""

    name: str
    role: str


@dataclass(frozen=True)
class RobotSpec:
    """A robot: its energy profile, where its images come from and its request rate."""

    id: str
    profile: str | None = None
    image_set: str | None = None
    synthetic: str | None = None
    rate_hz: float = 2.0
    deadline_ms: int | None = None
    local_fallback: bool = True
    energy_placement: bool = False
    leader_capable: bool = False
    capability: str | None = None
    bootstrap: str | None = None
    #: A folder of images the robot sends in turn (``scmr up --images DIR``), instead of an image set.
    images: str | None = None


@dataclass(frozen=True)
class Fault:
    """One fault of the timeline (a verb on a named link, peer or set of peers).

    ``at_s`` is when it starts (seconds after the robots start), ``for_s`` how
    long it lasts (``None``: until the end of the run).

    A crash names one ``peer``, or several in ``peers`` crashed together (a
    whole cloud tier: ``scmr up --cloud-outage``), or :data:`WHOEVER_LEADS`:
    the node that leads when the crash is due (``scmr up --leader-crash``).
    ``restart`` False: a crashed peer without ``for_s`` stays down after the
    run too (by default the end of the run restarts it, so the data tier can
    drain).
    """

    kind: str
    at_s: float
    for_s: float | None = None
    link: tuple[str, str] | None = None
    groups: tuple[tuple[str, ...], ...] | None = None
    peer: str | None = None
    rate_kbit: int | None = None
    delay_ms: float | None = None
    percent: float | None = None
    peers: tuple[str, ...] | None = None
    restart: bool = True

    @property
    def crashed(self) -> tuple[str, ...]:
        """The peers a crash fault kills (``()`` for other kinds)."""
        if self.kind != "crash":
            return ()
        return tuple(self.peers) if self.peers else ((self.peer,) if self.peer else ())

    @property
    def end_s(self) -> float | None:
        """When the fault is lifted, or ``None`` when it lasts to the end."""
        return None if self.for_s is None else self.at_s + self.for_s

    @property
    def label(self) -> str:
        """A short human-readable label, e.g. ``link_down robot1-cloud @4s``."""
        if self.link:
            what = "-".join(self.link)
        elif self.groups:
            what = " | ".join(",".join(g) for g in self.groups)
        else:
            what = ",".join(self.crashed) or self.peer or ""
        extra = ""
        if self.rate_kbit is not None:
            extra = f" {self.rate_kbit} kbit/s"
        elif self.delay_ms is not None:
            extra = f" {self.delay_ms:g} ms"
        elif self.percent is not None:
            extra = f" {self.percent:g} %"
        dur = f" for {self.for_s:g}s" if self.for_s is not None else ""
        return f"{self.kind} {what}{extra} @{self.at_s:g}s{dur}"


@dataclass(frozen=True)
class Expectation:
    """``metric op value``, checked against the run's summary."""

    metric: str
    op: str
    value: float

    @property
    def name(self) -> str:
        return f"{self.metric} {self.op} {self.value:g}"

    def holds(self, observed: float | None) -> bool:
        """Whether the expectation holds for ``observed`` (``None`` never holds)."""
        if observed is None:
            return False
        return bool(_OPS[self.op](float(observed), float(self.value)))


#: Checked in every scenario unless it states its own expectation on the same metric:
#: nothing the robots sent as telemetry may be lost (docs/DATA.md).
DEFAULT_EXPECTATIONS: tuple[Expectation, ...] = (Expectation("telemetry_lost", "<=", 0.0),)


@dataclass(frozen=True)
class Scenario:
    """A validated scenario (see the module docstring)."""

    name: str
    seed: int
    duration_s: float
    robots: tuple[RobotSpec, ...]
    clouds: tuple[str, ...] = ("cloud",)
    leader: str | None = "leader"
    lease_ms: int = 500
    description: str = ""
    image_sets: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    links: tuple[tuple[str, str], ...] = ()
    faults: tuple[Fault, ...] = ()
    expectations: tuple[Expectation, ...] = ()
    process: str | None = None
    source: str = "<dict>"
    bootstraps: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    leader_capability: str = "leader"
    explicit_links: bool = False
    #: Radio topology (positions, range, waypoints): which pairs can talk follows from where they are.
    radio: Any = None
    #: The ``--node`` name of a peer when it differs from the peer's name (``scmr up``'s
    #: ``cloud`` runs node ``cloud0``, its ``leader`` node ``leader0``); reports name nodes.
    node_names: Mapping[str, str] = field(default_factory=dict)
    #: How peers link (``topology.shape``): ``clique``, every peer a Zenoh peer linked to the
    #: others it can reach (one hop); ``routers``, a Zenoh router on every peer's host, linked to
    #: the routers it can reach, the peer its client, so traffic crosses several radio hops
    #: (docs/R2R.md "Multi-hop").
    shape: str = "clique"

    def router_of(self, peer: str) -> str:
        """The name of the router on ``peer``'s host (``shape = "routers"``; its certificate's name)."""
        return f"router-{self.node_of(peer)}"

    def router_dials(self, peer: str) -> tuple[str, ...]:
        """The peers whose routers ``peer``'s router dials (``shape = "routers"``).

        With ``topology.links``, the peers it is linked to; otherwise every peer started
        before it (each pair is dialled from one side; a pair out of radio range fails to
        connect, kernel-side, until it comes into range, and the dial is retried).
        """
        if self.explicit_links:
            return tuple(b for a, b in self.links if a == peer)
        names = self.peer_names
        return names[:names.index(peer)]

    def dials(self, peer: str) -> tuple[str, ...]:
        """The peers ``peer`` is handed to connect to (``shape = "clique"``): its bootstrap first,
        then every peer started before it that does not dial ``peer`` itself.

        Zenoh re-dials after a link loss only the configured endpoint that link was opened
        through, never a peer gossip linked (docs/ZENOH.md section 14): with only its bootstrap,
        a robot cut off for 2 s after the cloud died never linked to the leader again.  Each pair
        is dialled from one side (the later peer, or the one whose bootstrap names the other), so
        a pair keeps one link.  With ``topology.links``, exactly the links (the bootstraps); a robot
        whose scenario names its own ``bootstrap`` is handed only that one (the scenario shows
        gossip discovery).

        >>> sc = parse_scenario({"name": "d", "seed": 1, "duration_s": 2, "fleet": {"robots": [
        ...     {"id": "r1", "synthetic": "road"}, {"id": "r2", "synthetic": "road"}]}})
        >>> sc.dials("cloud"), sc.dials("leader"), sc.dials("r2")
        ((), ('cloud',), ('cloud', 'leader', 'r1'))
        """
        boots = tuple(self.bootstraps.get(peer, ()))
        if self.explicit_links or any(r.id == peer and r.bootstrap for r in self.robots):
            return boots
        names = self.peer_names
        earlier = names[:names.index(peer)] if peer in names else ()
        more = tuple(q for q in earlier if q not in boots and peer not in self.bootstraps.get(q, ()))
        return boots + more

    @property
    def dials_every_pair(self) -> bool:
        """Whether :meth:`dials` links every pair of peers (no explicit links, no robot that names its
        own bootstrap, the clique shape): then gossip need not dial peers, and must not, or a pair
        dialled by both sides at once keeps two links (docs/ZENOH.md section 14)."""
        return self.shape == "clique" and not self.explicit_links and not any(r.bootstrap for r in self.robots)

    def node_of(self, peer: str) -> str:
        """The node name peer ``peer`` runs as (its ``--node``/``--id``)."""
        return self.node_names.get(peer, peer)

    def peer_of(self, node: str) -> str:
        """The peer that runs node ``node`` (inverse of :meth:`node_of`)."""
        for p, n in self.node_names.items():
            if n == node:
                return p
        return node

    @property
    def checked_expectations(self) -> tuple[Expectation, ...]:
        """The declared expectations plus :data:`DEFAULT_EXPECTATIONS` on metrics not declared.

        A fleet with no cloud has no store: its telemetry stays queued on the
        robots, so the default ``telemetry_lost <= 0`` does not apply to it.
        """
        mine = {e.metric for e in self.expectations}
        return self.expectations + tuple(e for e in DEFAULT_EXPECTATIONS if e.metric not in mine
                                         and (self.clouds or e.metric != "telemetry_lost"))

    @property
    def peers(self) -> tuple[PeerSpec, ...]:
        """Every peer in start order: clouds, the leader (if any), then the robots."""
        return (
            tuple(PeerSpec(c, "cloud") for c in self.clouds)
            + ((PeerSpec(self.leader, "leader"),) if self.leader else ())
            + tuple(PeerSpec(r.id, "robot") for r in self.robots)
        )

    @property
    def candidates(self) -> tuple[str, ...]:
        """The leader-capable peers: the dedicated leader and robots with ``leader_capable``."""
        return ((self.leader,) if self.leader else ()) + tuple(r.id for r in self.robots if r.leader_capable)

    @property
    def link_faults(self) -> bool:
        """Whether any fault acts on links (then the proxy backend needs a proxy per link)."""
        return self.radio is not None or any(
            f.kind in ("link_down", "partition", "bandwidth", "latency", "loss") for f in self.faults)

    @property
    def peer_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.peers)

    def role(self, name: str) -> str:
        """The role of peer ``name``."""
        for p in self.peers:
            if p.name == name:
                return p.role
        raise KeyError(name)


@lru_cache(maxsize=1)
def _schema() -> dict[str, Any]:
    try:
        return json.loads(SCHEMA_PATH.read_text())
    except OSError as exc:  # pragma: no cover - packaging problem
        raise ConfigError(
            f"scenario schema not found at {SCHEMA_PATH} ({exc}); run from a source checkout "
            "(pip install -e .)"
        ) from None


def _path_str(path: Any) -> str:
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def _fix_for(err: Any) -> str:
    v = err.validator
    if v == "required":
        return "add the missing field"
    if v == "additionalProperties":
        allowed = sorted((err.schema.get("properties") or {}).keys())
        return f"remove it or fix its spelling; allowed here: {', '.join(allowed)}"
    if v == "enum":
        return "use one of " + ", ".join(map(str, err.validator_value))
    if v == "type":
        return f"give a value of type {err.validator_value}"
    if v == "pattern":
        return err.schema.get("description") or f"match {err.validator_value}"
    if v in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
        return f"use a value within the allowed range ({v} {err.validator_value})"
    if v in ("minItems", "maxItems"):
        return f"give a list with {v} {err.validator_value}"
    return "see schemas/scenario.schema.json"


def _leaf_errors(err: Any) -> Any:
    """The most specific error (descend into allOf/if-then contexts)."""
    while err.context:
        err = sorted(err.context, key=lambda e: -len(e.absolute_path))[0]
    return err


def _non_finite(value: Any, path: str = "") -> str | None:
    """Path of the first NaN or inf in ``value`` (TOML has both; the schema's "number" takes them)."""
    if isinstance(value, float) and not math.isfinite(value):
        return path
    items = value.items() if isinstance(value, Mapping) else enumerate(value) if isinstance(value, list) else ()
    for k, v in items:
        found = _non_finite(v, f"{path}[{k}]" if isinstance(k, int) else f"{path}.{k}" if path else str(k))
        if found is not None:
            return found
    return None


def _validate_schema(data: Mapping[str, Any], source: str) -> None:
    import jsonschema

    bad = _non_finite(data)
    if bad is not None:
        raise _err(source, bad, "not a finite number (nan/inf)", "write a finite number")

    validator = jsonschema.Draft202012Validator(_schema())
    errors = sorted(validator.iter_errors(dict(data)), key=lambda e: (list(map(str, e.absolute_path)), e.validator))
    if not errors:
        return
    err = _leaf_errors(errors[0])
    more = f" (and {len(errors) - 1} more problem(s))" if len(errors) > 1 else ""
    raise ConfigError(
        f"scenario {source}: field '{_path_str(err.absolute_path)}': {err.message}; "
        f"fix: {_fix_for(err)}{more}"
    )


def _err(source: str, fld: str, problem: str, fix: str) -> ConfigError:
    return ConfigError(f"scenario {source}: field '{fld}': {problem}; fix: {fix}")


def parse_scenario(data: Mapping[str, Any], *, source: str = "<dict>") -> Scenario:
    """Validate a scenario given as a mapping (the parsed TOML) and build it.

    Parameters
    ----------
    data : mapping
        The scenario, as ``tomllib`` parses it.
    source : str, keyword-only
        Where it came from (used in error messages).

    Returns
    -------
    Scenario

    Raises
    ------
    ConfigError
        With the file, the field and the fix.
    """
    _validate_schema(data, source)
    fleet = data["fleet"]
    clouds = tuple(fleet.get("clouds", ["cloud"]))
    leader = fleet.get("leader", "leader") or None
    image_sets = {k: tuple(v) for k, v in (data.get("image_sets") or {}).items()}
    robots = []
    for i, r in enumerate(fleet["robots"]):
        where = f"fleet.robots[{i}]"
        if ("image_set" in r) == ("synthetic" in r):
            raise _err(source, where, f"robot '{r['id']}' needs exactly one of image_set or synthetic",
                       "give image_set = \"<a key of [image_sets]>\" or synthetic = \"road\"")
        if "image_set" in r and r["image_set"] not in image_sets:
            raise _err(source, f"{where}.image_set", f"unknown image set {r['image_set']!r}",
                       f"use one of {sorted(image_sets) or '(none defined)'} or add it under [image_sets]")
        robots.append(RobotSpec(id=r["id"], profile=r.get("profile"), image_set=r.get("image_set"),
                                synthetic=r.get("synthetic"), rate_hz=float(r.get("rate_hz", 2.0)),
                                deadline_ms=r.get("deadline_ms"), local_fallback=bool(r.get("local_fallback", True)),
                                energy_placement=bool(r.get("energy_placement", False)),
                                leader_capable=bool(r.get("leader_capable", False)),
                                capability=r.get("capability"), bootstrap=r.get("bootstrap")))
    names = list(clouds) + ([leader] if leader else []) + [r.id for r in robots]
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise _err(source, "fleet", f"peer name {n!r} is used twice", "give every cloud, leader and robot its own name")
        seen.add(n)
    known = set(names)

    def check_peer(fld: str, name: str) -> None:
        if name not in known:
            raise _err(source, fld, f"unknown peer {name!r}", f"use one of {', '.join(names)}")

    for i, r in enumerate(robots):
        if r.bootstrap is not None:
            check_peer(f"fleet.robots[{i}].bootstrap", r.bootstrap)
            if r.bootstrap == r.id:
                raise _err(source, f"fleet.robots[{i}].bootstrap", f"robot {r.id!r} cannot bootstrap to itself",
                           "name another peer (a cloud, the leader or another robot)")
    if fleet.get("leader_bootstrap") is not None:
        check_peer("fleet.leader_bootstrap", fleet["leader_bootstrap"])
    boot_of = {r.id: r.bootstrap for r in robots if r.bootstrap}
    for i, r in enumerate(robots):  # robots handed each other in a ring would never reach the fleet
        seen, n = [r.id], boot_of.get(r.id)
        while n in boot_of and n not in seen:
            seen.append(n)
            n = boot_of[n]
        if n in seen:
            raise _err(source, f"fleet.robots[{i}].bootstrap", "bootstraps form a ring: " + " -> ".join(seen + [n]),
                       "hand one robot of the ring a cloud or the leader")
    topo = data.get("topology") or {}
    explicit = "links" in topo
    radio = _parse_radio(topo, names, float(data["duration_s"]), source, check_peer)
    if radio is not None and explicit:
        raise _err(source, "topology", "both links and a radio topology (range_m, nodes) are given",
                   "give topology.links (fixed links) or range_m with nodes (links follow the positions), not both")
    if "links" in topo:
        links = []
        for i, (a, b) in enumerate(topo["links"]):
            check_peer(f"topology.links[{i}]", a)
            check_peer(f"topology.links[{i}]", b)
            if a == b:
                raise _err(source, f"topology.links[{i}]", f"link from {a!r} to itself", "link two different peers")
            if frozenset((a, b)) in {frozenset(x) for x in links}:
                raise _err(source, f"topology.links[{i}]", f"link {a}-{b} declared twice", "declare each link once")
            links.append((a, b))
        links_t = tuple(links)
        bootstraps = {n: tuple(b for a, b in links_t if a == n) for n in names}
    elif radio is not None:
        bootstraps = _radio_bootstraps(radio, names, robots, source)
        links_t = tuple((names[i], names[j]) for i in range(len(names)) for j in range(i))
    else:
        bootstraps = _default_bootstraps(clouds, leader, robots, fleet.get("leader_bootstrap"))
        # every pair is a potential (gossip) link; the later-started peer connects to the earlier one
        links_t = tuple((names[i], names[j]) for i in range(len(names)) for j in range(i))
    link_set = {frozenset(x) for x in links_t}

    duration = float(data["duration_s"])
    faults = []
    crashed: dict[str, dict[int, tuple[float, float]]] = {}
    for i, f in enumerate(data.get("faults") or []):
        where = f"faults[{i}]"
        if f["at_s"] >= duration:
            raise _err(source, f"{where}.at_s", f"fault at {f['at_s']}s is not before the end of the run ({duration:g}s)",
                       "use an at_s below duration_s")
        link = tuple(f["link"]) if "link" in f else None
        if link:
            for n in link:
                check_peer(f"{where}.link", n)
            if frozenset(link) not in link_set:
                raise _err(source, f"{where}.link", f"{link[0]}-{link[1]} is not a link of the topology",
                           "name a pair listed in topology.links (without topology.links every pair is a link)")
        groups = tuple(tuple(g) for g in f["groups"]) if "groups" in f else None
        if groups:
            flat: list[str] = []
            for g in groups:
                for n in g:
                    check_peer(f"{where}.groups", n)
                    if n in flat:
                        raise _err(source, f"{where}.groups", f"peer {n!r} is in two groups", "make the groups disjoint")
                    flat.append(n)
        if "peer" in f:
            check_peer(f"{where}.peer", f["peer"])
            end = f["at_s"] + f["for_s"] if "for_s" in f else float("inf")
            for other, (a, b) in crashed.get(f["peer"], {}).items():
                if a < end and f["at_s"] < b or a == f["at_s"]:
                    raise _err(source, where, f"peer {f['peer']!r} is crashed twice at once (see faults[{other}])",
                               "let the first crash end (for_s) before the next one starts")
            crashed.setdefault(f["peer"], {})[i] = (f["at_s"], end)
        faults.append(Fault(kind=f["kind"], at_s=float(f["at_s"]),
                            for_s=float(f["for_s"]) if "for_s" in f else None,
                            link=link, groups=groups, peer=f.get("peer"), rate_kbit=f.get("rate_kbit"),
                            delay_ms=f.get("delay_ms"), percent=f.get("percent")))
    expectations = tuple(Expectation(e["metric"], e["op"], float(e["value"])) for e in data.get("expectations") or [])
    return Scenario(
        name=data["name"], seed=int(data["seed"]), duration_s=duration, robots=tuple(robots),
        clouds=clouds, leader=leader, lease_ms=int(data.get("lease_ms", 500)),
        description=data.get("description", ""), image_sets=image_sets, links=links_t,
        faults=tuple(sorted(faults, key=lambda x: x.at_s)), expectations=expectations,
        process=data.get("process"), source=source, bootstraps=bootstraps,
        leader_capability=fleet.get("leader_capability", "leader"), explicit_links=explicit, radio=radio,
        shape=topo.get("shape", "clique"),
    )


def _parse_radio(topo: Mapping[str, Any], names: list[str], duration: float, source: str,
                 check_peer: Callable[[str, str], None]):
    """The scenario's :class:`~scmr_mesh.scenario.radio.Radio`, or None without ``range_m``/``nodes``."""
    keys = [k for k in ("range_m", "nodes", "waypoints", "bandwidth") if k in topo]
    if not keys:
        return None
    from scmr_mesh.scenario.radio import Radio

    if "range_m" not in topo or "nodes" not in topo:
        missing = "range_m" if "range_m" not in topo else "nodes"
        raise _err(source, f"topology.{missing}", f"a radio topology ({', '.join(keys)}) needs {missing}",
                   "give range_m = <metres> and a [topology.nodes] table with every peer's [x, y]")
    nodes = topo["nodes"]
    for n in nodes:
        check_peer("topology.nodes", n)
    missing = [n for n in names if n not in nodes]
    if missing:
        raise _err(source, "topology.nodes", f"no position for {', '.join(missing)}",
                   "give every cloud, leader and robot a position [x, y] in metres")
    way: dict[str, list[tuple[float, tuple[float, float]]]] = {}
    for i, w in enumerate(topo.get("waypoints") or []):
        where = f"topology.waypoints[{i}]"
        check_peer(f"{where}.node", w["node"])
        prev = way.get(w["node"], [])
        if prev and w["at_s"] <= prev[-1][0]:
            raise _err(source, f"{where}.at_s", f"waypoint at {w['at_s']:g}s of {w['node']!r} is not after its "
                       f"previous one ({prev[-1][0]:g}s)", "list each node's waypoints in time order")
        if w["at_s"] > duration:
            raise _err(source, f"{where}.at_s", f"waypoint at {w['at_s']:g}s is after the end of the run "
                       f"({duration:g}s)", "use an at_s within duration_s")
        way.setdefault(w["node"], []).append((float(w["at_s"]), (float(w["pos"][0]), float(w["pos"][1]))))
    steps = [(float(d), int(k)) for d, k in topo.get("bandwidth") or []]
    if any(b[0] <= a[0] for a, b in zip(steps, steps[1:])):
        raise _err(source, "topology.bandwidth", "distances are not increasing",
                   "list [max_distance_m, kbit_s] steps from the nearest to the farthest")
    radio = Radio(range_m=float(topo["range_m"]),
                  positions={n: (float(nodes[n][0]), float(nodes[n][1])) for n in names},
                  waypoints={n: tuple(v) for n, v in way.items()}, bandwidth=tuple(steps))
    linked = {n for pair in radio.links_at(0.0) for n in pair}
    alone = [n for n in names if n not in linked]
    if alone and len(names) > 1:
        raise _err(source, "topology.nodes", f"{', '.join(alone)} out of every other peer's range "
                   f"({radio.range_m:g} m) at time 0", "move it within range_m of a neighbour (it must join the "
                   "fleet at start), or raise range_m")
    return radio


def _radio_bootstraps(radio, names: list[str], robots: list[RobotSpec], source: str) -> dict[str, tuple[str, ...]]:
    """Whom each peer is handed under a radio topology: the nearest peer started before it that is in
    range at time 0 (a robot's own ``bootstrap`` must be in range)."""
    out: dict[str, tuple[str, ...]] = {}
    own = {r.id: r.bootstrap for r in robots if r.bootstrap}
    for i, n in enumerate(names):
        if n in own:
            if not radio.in_range(n, own[n], 0.0):
                raise _err(source, "fleet.robots", f"robot {n!r} bootstraps to {own[n]!r}, out of its radio range "
                           f"at time 0", "name a peer within range_m of it, or leave bootstrap out")
            out[n] = (own[n],)
            continue
        near = sorted((radio.distance(n, m, 0.0), j, m) for j, m in enumerate(names[:i]) if radio.in_range(n, m, 0.0))
        out[n] = (near[0][2],) if near else ()
    return out


def _default_bootstraps(clouds: tuple[str, ...], leader: str | None, robots: list[RobotSpec],
                        leader_bootstrap: str | None) -> dict[str, tuple[str, ...]]:
    """Whom each peer is handed: one bootstrap, gossip finds the rest.

    Clouds after the first join through the first; the leader is handed
    ``leader_bootstrap`` or the first cloud; a robot its ``bootstrap``, else the
    first cloud, else the leader, else the first robot (which listens only).
    """
    out: dict[str, tuple[str, ...]] = {}
    for i, c in enumerate(clouds):
        out[c] = () if i == 0 else (clouds[0],)
    if leader:
        boot = leader_bootstrap or (clouds[0] if clouds else None)
        out[leader] = (boot,) if boot else ()
    default = clouds[0] if clouds else leader if leader else (robots[0].id if robots else None)
    for r in robots:
        boot = r.bootstrap or (default if default != r.id else None)
        out[r.id] = (boot,) if boot else ()
    return out


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file.

    Parameters
    ----------
    path : str or Path
        The ``.toml`` file.

    Returns
    -------
    Scenario

    Raises
    ------
    ConfigError
        The file is missing, is not TOML, or breaks a rule (message: file, field, fix).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"scenario file {p} not found; give the path of a .toml file "
                          "(examples in peers/scenarios/)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"scenario file {p} cannot be read ({exc}); give a UTF-8 TOML file") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"scenario {p}: not valid TOML ({exc}); fix the syntax at that line") from None
    return parse_scenario(data, source=str(p))
