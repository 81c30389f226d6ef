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
(``links``).  A scenario that lists ``topology.links`` gets exactly those
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


@dataclass(frozen=True)
class Fault:
    """One fault of the timeline (a verb on a named link, peer or set of peers).

    ``at_s`` is when it starts (seconds after the robots start), ``for_s`` how
    long it lasts (``None``: until the end of the run).
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
            what = self.peer or ""
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
        return any(f.kind in ("link_down", "partition", "bandwidth", "latency", "loss") for f in self.faults)

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
        leader_capability=fleet.get("leader_capability", "leader"), explicit_links=explicit,
    )


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
