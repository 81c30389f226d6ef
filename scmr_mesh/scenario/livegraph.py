"""Who could talk to whom during a run, and what that says about rerouting (pure).

The *live graph* at an instant is the scenario's possible links (the radio
pairs in range, the declared ``topology.links``, or every pair) less the pairs
a link fault cuts and less the peers a crash has taken down.  From it and the
robots' records this module derives what the multi-hop tier is judged on
(issue 22, docs/R2R.md "Multi-hop"):

* **reroute** (:func:`reroutes`): for each fault, the robots whose path to the
  node serving them the fault broke (the server crashed, or a relay or a link
  on a shortest path to it), and for each such robot the time from the fault to
  its first answer from another tier or over another path (``reroute_ms``); a
  robot left with no path to any server is listed in ``no_path`` instead (it
  computes alone by design);
* **frames computed alone with a path** (:func:`alone_with_path`): local answers
  of a robot that, when it sent the frame, had a path to a live server;
* **leaders per connected part** (:func:`split_leader_ms`): the longest time one
  connected part of the live graph had more than one leader.

Times are seconds from time 0.  Faults are the run's
:class:`~scmr_mesh.qos.faults.FaultRecord` s (or their JSON).

>>> from scmr_mesh.scenario.spec import parse_scenario
>>> sc = parse_scenario({"name": "t", "seed": 0, "duration_s": 5, "topology": {"range_m": 11,
...     "nodes": {"cloud": [0, 0], "leader": [0, 1], "robot1": [10, 0], "robot2": [20, 0]}},
...     "fleet": {"robots": [{"id": "robot1", "synthetic": "tunnel"}, {"id": "robot2", "synthetic": "tunnel"}]}})
>>> g = LiveGraph(sc, [])
>>> g.path_len("robot2", "cloud", 1.0), sorted(g.parts(1.0)[0])
(2, ['cloud', 'leader', 'robot1', 'robot2'])
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any

from scmr_mesh.scenario.radio import adjacency, distances as _bfs
from scmr_mesh.scenario.spec import Scenario

__all__ = ["LiveGraph", "alone_with_path", "reroutes", "split_leader_ms"]

Pair = tuple[str, str]


def _pair(a: str, b: str) -> Pair:
    return (a, b) if a <= b else (b, a)


class LiveGraph:
    """The live graph of one run over time (see the module docstring).

    Parameters
    ----------
    scenario : Scenario
    faults : sequence of mapping
        The run's faults with ``kind``, ``start_unix_ns``, ``end_unix_ns`` and what they hit
        (``target``/``peer`` for crashes, ``link``, ``groups``).
    t0_unix_ns : int
        Time 0 (fault times are turned into seconds from it).
    """

    def __init__(self, scenario: Scenario, faults: Sequence[Mapping[str, Any]], t0_unix_ns: int = 0) -> None:
        self.scenario = scenario
        self.t0 = t0_unix_ns
        #: (start_s, end_s or inf, crashed peers, cut pairs) per fault
        self.windows: list[tuple[float, float, frozenset[str], frozenset[Pair]]] = []
        #: ``(label, start_unix_ns)`` of each window's fault (how a report finds its fault's reroute)
        self.keys: list[tuple[str, int]] = []
        for f in faults:
            if f.get("start_unix_ns") is None:
                continue
            self.keys.append((str(f.get("label", "")), int(f["start_unix_ns"])))
            a = (int(f["start_unix_ns"]) - t0_unix_ns) / 1e9
            b = float("inf") if f.get("end_unix_ns") is None else (int(f["end_unix_ns"]) - t0_unix_ns) / 1e9
            self.windows.append((a, b, frozenset(self.crashed(f)), frozenset(self.cut(f))))
        #: radio pairs going out of range: ``(t_s, pair)`` (a relay walking away is a silent loss too)
        self.radio_losses: list[tuple[float, Pair]] = []
        if scenario.radio is not None:
            self.radio_losses = [(t, _pair(*p)) for t, p, up in scenario.radio.changes(scenario.duration_s) if not up]

    # ------------------------------------------------------------ what a fault does
    def crashed(self, f: Mapping[str, Any]) -> set[str]:
        """The peers a crash fault took down (none for other faults)."""
        if f.get("kind") != "crash":
            return set()
        if f.get("peer"):
            return {self.scenario.peer_of(str(f["peer"]))}
        return {self.scenario.peer_of(n) for n in str(f.get("target", "")).split(",") if n}

    @staticmethod
    def cut(f: Mapping[str, Any]) -> set[Pair]:
        """The pairs a ``link_down`` or ``partition`` cuts."""
        if f.get("kind") == "link_down" and f.get("link"):
            return {_pair(*f["link"])}
        if f.get("kind") == "partition" and f.get("groups"):
            return {_pair(a, b) for g1, g2 in itertools.combinations(f["groups"], 2) for a in g1 for b in g2}
        return set()

    # ------------------------------------------------------------ the graph at an instant
    def possible(self, t: float) -> set[Pair]:
        """The pairs that could talk at ``t`` with no fault: in radio range, declared, or every pair."""
        sc = self.scenario
        if sc.radio is not None:
            return set(sc.radio.links_at(max(0.0, t)))
        if sc.explicit_links:
            return {_pair(a, b) for a, b in sc.links}
        return {_pair(a, b) for a, b in itertools.combinations(sc.peer_names, 2)}

    def at(self, t: float, *, without: int | None = None) -> tuple[set[str], set[Pair]]:
        """``(nodes, edges)`` live at ``t`` (``without``: leave out the fault of that window index)."""
        down: set[str] = set()
        cut: set[Pair] = set()
        for i, (a, b, crashed, pairs) in enumerate(self.windows):
            if i != without and a <= t < b:
                down |= crashed
                cut |= pairs
        nodes = set(self.scenario.peer_names) - down
        edges = {p for p in self.possible(t) - cut if p[0] in nodes and p[1] in nodes}
        return nodes, edges

    _adj = staticmethod(adjacency)

    def path_len(self, a: str, b: str, t: float) -> int | None:
        """Hops from ``a`` to ``b`` over the live graph at ``t`` (None: no path, or either is down)."""
        nodes, edges = self.at(t)
        if a not in nodes or b not in nodes:
            return None
        return _bfs(self._adj(edges), a).get(b)

    def parts(self, t: float) -> list[set[str]]:
        """The connected parts of the live graph at ``t``."""
        nodes, edges = self.at(t)
        adj = self._adj(edges)
        out, seen = [], set()
        for n in sorted(nodes):
            if n not in seen:
                part = set(_bfs(adj, n))
                seen |= part
                out.append(part)
        return out

    def servers(self, robot: str, *, itself: bool = False) -> set[str]:
        """Nodes that may serve ``robot``: the clouds, the leader, leader-capable robots (``itself``:
        ``robot`` too when it may lead: it then serves itself as its part's leader, if the part
        holds another node)."""
        sc = self.scenario
        out = set(sc.clouds) | ({sc.leader} if sc.leader else set()) | set(sc.candidates)
        return out if itself else out - {robot}

    def reaches_server(self, robot: str, t: float, *, itself: bool = False) -> bool:
        """Whether ``robot`` has a path at ``t`` to any node that may serve it (see :meth:`servers`)."""
        nodes, edges = self.at(t)
        if robot not in nodes:
            return False
        part = set(_bfs(self._adj(edges), robot))
        # a candidate alone claims nothing (election: an isolated node does not claim)
        return bool(part & self.servers(robot, itself=itself and len(part) > 1))

    def breaks(self, i: int, robot: str, server: str) -> bool:
        """Whether fault window ``i`` breaks a shortest path from ``robot`` to ``server`` (or takes it down)."""
        a, _, crashed, pairs = self.windows[i]
        return self._breaks(a, crashed, pairs, robot, server, without=i)

    def _breaks(self, a: float, crashed: frozenset[str], pairs: frozenset[Pair], robot: str, server: str,
                without: int | None = None) -> bool:
        if server in crashed:
            return True
        nodes, edges = self.at(a - 1e-4, without=without)  # just before (radio times are rounded to 1 µs)
        adj = self._adj(edges)
        d_r, d_s = _bfs(adj, robot), _bfs(adj, server)
        if server not in d_r:
            return False
        d = d_r[server]
        if any(x in d_r and x in d_s and d_r[x] + d_s[x] == d for x in crashed):
            return True
        return any(x in d_r and y in d_r and x in d_s and y in d_s
                   and (d_r[x] + 1 + d_s[y] == d or d_r[y] + 1 + d_s[x] == d)
                   for x, y in pairs & edges)


def _remote_ok(r: Mapping[str, Any]) -> bool:
    return bool(r.get("ok")) and r.get("tier") not in (None, "local")


def reroutes(graph: LiveGraph, records: Sequence[Mapping[str, Any]], *, radio: bool = False) -> list[dict[str, Any]]:
    """Per fault window (in :attr:`LiveGraph.windows` order): ``{"reroute_ms": {robot: ms | None},
    "reroute_max_ms", "no_path": [...]}``; with ``radio``, then one per radio pair going out of
    range (:attr:`LiveGraph.radio_losses`, with ``t_s`` and ``link``).

    A robot is affected when the last remote answer it had before the fault came
    from a node the fault took down or over a shortest path the fault broke.
    Its reroute ends with its first remote answer to a frame sent at or after
    the fault (from any tier, over any path): received - fault start.  A robot
    with no path to any server right after the fault is in ``no_path``; one
    with a path that never got a remote answer again has ``None``, and then
    ``reroute_max_ms`` is None too (a reroute that did not happen is not fast).
    """
    by_robot: dict[str, list[Mapping[str, Any]]] = {}
    for r in records:
        if r.get("sent_unix_ns") is not None:
            by_robot.setdefault(str(r.get("robot")), []).append(r)
    for rows in by_robot.values():
        rows.sort(key=lambda r: int(r["sent_unix_ns"]))
    t0 = graph.t0
    out = []
    losses = [(a, crashed, pairs, i) for i, (a, _, crashed, pairs) in enumerate(graph.windows)]
    if radio:
        losses += [(t, frozenset(), frozenset({p}), None) for t, p in graph.radio_losses]
    for a, crashed, pairs, i in losses:
        start_ns = t0 + int(round(a * 1e9))
        per: dict[str, float | None] = {}
        no_path: list[str] = []
        for robot, rows in sorted(by_robot.items()):
            if robot in crashed:
                continue
            before = [r for r in rows if int(r["sent_unix_ns"]) < start_ns and _remote_ok(r)]
            if not before or before[-1].get("served_by") is None:
                continue
            server = graph.scenario.peer_of(str(before[-1]["served_by"]))
            if server == robot or not graph._breaks(a, crashed, pairs, robot, server, without=i):
                continue
            if not graph.reaches_server(robot, a + 1e-4, itself=True):
                no_path.append(robot)
                continue
            first = next((r for r in rows if int(r["sent_unix_ns"]) >= start_ns and _remote_ok(r)
                          and r.get("received_unix_ns") is not None), None)
            per[robot] = None if first is None else round((int(first["received_unix_ns"]) - start_ns) / 1e6, 3)
        vals = list(per.values())
        out.append({**({} if i is not None else {"t_s": round(a, 6), "link": list(next(iter(pairs)))}),
                    "reroute_ms": per, "no_path": no_path,
                    "reroute_max_ms": None if any(v is None for v in vals) else (max(vals) if vals else None)})
    return out


def alone_with_path(graph: LiveGraph, records: Sequence[Mapping[str, Any]]) -> int:
    """Frames a robot computed alone while it had a path to a live server when it sent them."""
    n = 0
    for r in records:
        if r.get("tier") == "local" and r.get("sent_unix_ns") is not None:
            if graph.reaches_server(str(r.get("robot")), (int(r["sent_unix_ns"]) - graph.t0) / 1e9):
                n += 1
    return n


def split_leader_ms(graph: LiveGraph, leaders_over_time: Sequence[Mapping[str, Any]], end_s: float) -> float:
    """The longest time (ms) one connected part of the live graph held two or more leaders.

    ``leaders_over_time`` is the leadership block's ``[{"t_s", "leaders"}]``.  The
    live graph changes at fault starts and ends and radio changes; the leaders at
    the moments in between come from the list.  Leader names are node names.
    """
    sc = graph.scenario
    times = {0.0, float(end_s)} | {float(e["t_s"]) for e in leaders_over_time if 0 <= float(e["t_s"]) <= end_s}
    for a, b, _, _ in graph.windows:
        times |= {t for t in (a, b) if 0 <= t <= end_s}
    if sc.radio is not None:
        times |= {t for t, _, _ in sc.radio.changes(end_s)}
    cuts = sorted(times)
    worst, since = 0.0, None
    for t0, t1 in zip(cuts, cuts[1:]):
        mid = (t0 + t1) / 2
        lead = [e for e in leaders_over_time if float(e["t_s"]) <= mid]
        leaders = {sc.peer_of(n) for n in (lead[-1]["leaders"] if lead else ())}
        split = any(len(leaders & part) > 1 for part in graph.parts(mid))
        if split and since is None:
            since = t0
        if not split and since is not None:
            worst, since = max(worst, (t0 - since) * 1e3), None
    if since is not None:
        worst = max(worst, (cuts[-1] - since) * 1e3)
    return round(worst, 3)
