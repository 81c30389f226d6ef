"""Radio topology of a scenario: positions in metres, a range, waypoints, bandwidth by distance (pure).

Where robots hear only their neighbours (tunnels, mines, caves), which pairs
of peers can talk follows from where they are.  A scenario may place every
peer at a position (metres), give a radio ``range_m``, move peers along
waypoints (piecewise linear in time, standing still after the last one) and
give a step table of bandwidth by distance.  :class:`Radio` answers, at any
instant, which pairs are in range (:meth:`Radio.links_at`), and lists the
exact instants a pair comes into or goes out of range over a run
(:meth:`Radio.changes`: the roots of ``|p_a(t) - p_b(t)| = range`` on each
linear piece), which the timeline turns into the same block/unblock events
link faults use, so the netns and proxy backends apply them unchanged.

>>> r = Radio(range_m=10, positions={"a": (0, 0), "b": (5, 0), "c": (20, 0)},
...           waypoints={"c": ((10.0, (12.0, 0.0)),)})
>>> sorted(r.links_at(0.0))
[('a', 'b')]
>>> [(round(t, 3), pair, up) for t, pair, up in r.changes(20.0)]
[(6.25, ('b', 'c'), True)]
>>> hops({("a", "b"), ("b", "c")}, "a", "c")
2
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

__all__ = ["Radio", "adjacency", "distances", "hops", "links_timeline", "rate_changes"]

Pos = tuple[float, float]


def _pair(a: str, b: str) -> tuple[str, str]:
    return (a, b) if a <= b else (b, a)


@dataclass(frozen=True)
class Radio:
    """Positions, range, waypoints and bandwidth steps of a scenario's peers (see the module docstring).

    ``positions`` hold every peer's place at time 0; ``waypoints[node]`` is a
    sorted tuple of ``(at_s, (x, y))``: the node moves in a straight line at
    constant speed from its previous place to each waypoint.  ``bandwidth`` is
    ``((max_distance_m, kbit_s), ...)`` in increasing distance: a pair at
    distance d gets the rate of the first step with ``d <= max_distance_m``.
    """

    range_m: float
    positions: Mapping[str, Pos]
    waypoints: Mapping[str, tuple[tuple[float, Pos], ...]] = field(default_factory=dict)
    bandwidth: tuple[tuple[float, int], ...] = ()

    # ------------------------------------------------------------ geometry
    def _track(self, node: str) -> list[tuple[float, Pos]]:
        return [(0.0, tuple(self.positions[node]))] + [(float(t), tuple(p)) for t, p in self.waypoints.get(node, ())]

    def position(self, node: str, t: float) -> Pos:
        """Where ``node`` is at time ``t`` (s)."""
        track = self._track(node)
        if t <= track[0][0]:
            return track[0][1]
        for (t0, p0), (t1, p1) in zip(track, track[1:]):
            if t <= t1:
                f = (t - t0) / (t1 - t0) if t1 > t0 else 1.0
                return (p0[0] + f * (p1[0] - p0[0]), p0[1] + f * (p1[1] - p0[1]))
        return track[-1][1]

    def distance(self, a: str, b: str, t: float) -> float:
        pa, pb = self.position(a, t), self.position(b, t)
        return math.hypot(pa[0] - pb[0], pa[1] - pb[1])

    def in_range(self, a: str, b: str, t: float) -> bool:
        return self.distance(a, b, t) <= self.range_m

    def links_at(self, t: float) -> frozenset[tuple[str, str]]:
        """The pairs in range at ``t`` (sorted name pairs)."""
        return frozenset(_pair(a, b) for a, b in itertools.combinations(sorted(self.positions), 2)
                         if self.in_range(a, b, t))

    def rate_kbit(self, a: str, b: str, t: float) -> int | None:
        """The pair's bandwidth at ``t`` from the step table (None: no table, or beyond its last step)."""
        d = self.distance(a, b, t)
        for max_d, kbit in self.bandwidth:
            if d <= max_d:
                return int(kbit)
        return None

    # ------------------------------------------------------------ changes over a run
    def _breaks(self, a: str, b: str, duration_s: float) -> list[float]:
        ts = {0.0, float(duration_s)}
        ts.update(t for t, _ in self._track(a) + self._track(b) if 0.0 < t < duration_s)
        return sorted(ts)

    def _crossings(self, a: str, b: str, t0: float, t1: float) -> list[float]:
        """Times in (t0, t1) where the pair's distance equals the range (both move linearly there)."""
        pa0, pb0 = self.position(a, t0), self.position(b, t0)
        pa1, pb1 = self.position(a, t1), self.position(b, t1)
        dx, dy = pa0[0] - pb0[0], pa0[1] - pb0[1]
        vx = ((pa1[0] - pb1[0]) - dx) / (t1 - t0)
        vy = ((pa1[1] - pb1[1]) - dy) / (t1 - t0)
        qa = vx * vx + vy * vy
        qb = 2 * (dx * vx + dy * vy)
        qc = dx * dx + dy * dy - self.range_m ** 2
        if qa == 0:
            return []
        disc = qb * qb - 4 * qa * qc
        if disc < 0:
            return []
        r = math.sqrt(disc)
        return [t0 + s for s in ((-qb - r) / (2 * qa), (-qb + r) / (2 * qa)) if 0 < s < t1 - t0]

    def changes(self, duration_s: float, radius: float | None = None) -> list[tuple[float, tuple[str, str], bool]]:
        """Every instant in (0, duration) a pair comes within ``radius`` (default the range: True) or leaves it
        (False), in time order."""
        if radius is not None and radius != self.range_m:
            return dataclasses.replace(self, range_m=radius).changes(duration_s)
        out = []
        for a, b in itertools.combinations(sorted(self.positions), 2):
            cuts = set()
            breaks = self._breaks(a, b, duration_s)
            for t0, t1 in zip(breaks, breaks[1:]):
                cuts.add(t1)
                cuts.update(self._crossings(a, b, t0, t1))
            cuts.discard(float(duration_s))
            state = self.in_range(a, b, 0.0)
            edges = sorted({0.0, float(duration_s), *cuts})
            for t0, t1 in zip(edges, edges[1:]):
                now = self.in_range(a, b, (t0 + t1) / 2)  # the state on (t0, t1)
                if now != state:
                    out.append((round(t0, 6), (a, b), now))
                    state = now
        out.sort(key=lambda c: (c[0], c[1]))
        return out


def rate_changes(radio: Radio, duration_s: float) -> list[tuple[float, tuple[str, str], int | None]]:
    """When a pair's bandwidth step changes (``(t, pair, kbit_s)``; at 0: every pair's first rate).

    Only the pairs in range are shaped; a pair beyond the table's last step keeps no limit (None).
    """
    if not radio.bandwidth:
        return []
    pairs = [_pair(a, b) for a, b in itertools.combinations(sorted(radio.positions), 2)]
    out = [(0.0, p, radio.rate_kbit(*p, 0.0)) for p in pairs]
    last = {p: r for _, p, r in out}
    times = sorted({t for d, _ in radio.bandwidth for t, _, _ in radio.changes(duration_s, radius=d)})
    for t in times:
        for p in pairs:
            r = radio.rate_kbit(*p, t + 1e-9)
            if r != last[p]:
                out.append((t, p, r))
                last[p] = r
    return out


def links_timeline(radio: Radio, duration_s: float) -> list[dict]:
    """The link graph over time: ``[{"t_s", "links": [[a, b], ...]}]``, one entry at 0 and one per change."""
    out = [{"t_s": 0.0, "links": [list(p) for p in sorted(radio.links_at(0.0))]}]
    links = set(radio.links_at(0.0))
    for t, pair, up in radio.changes(duration_s):
        (links.add if up else links.discard)(pair)
        if out[-1]["t_s"] == t:
            out[-1]["links"] = [list(p) for p in sorted(links)]
        else:
            out.append({"t_s": t, "links": [list(p) for p in sorted(links)]})
    return out


def adjacency(links: Iterable[tuple[str, str]]) -> dict[str, set[str]]:
    """Each node's neighbours over undirected ``links``."""
    adj: dict[str, set[str]] = {}
    for x, y in links:
        adj.setdefault(x, set()).add(y)
        adj.setdefault(y, set()).add(x)
    return adj


def distances(adj: Mapping[str, Iterable[str]], src: str) -> dict[str, int]:
    """Hops from ``src`` to every node it reaches (breadth first; ``src`` itself at 0)."""
    dist = {src: 0}
    todo = deque([src])
    while todo:
        n = todo.popleft()
        for m in adj.get(n, ()):
            if m not in dist:
                dist[m] = dist[n] + 1
                todo.append(m)
    return dist


def hops(links: Iterable[tuple[str, str]], a: str, b: str) -> int | None:
    """Radio hops from ``a`` to ``b`` over ``links`` (0 when a == b; None: no path)."""
    return distances(adjacency(links), a).get(b)
