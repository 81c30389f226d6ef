"""Radio topology in scenarios (issue 22, item 1): positions, range, waypoints, bandwidth by distance.

Pure: which pairs can talk at each instant, the exact instants that changes,
the timeline's block/unblock/shape events, hops, and one-line errors for bad
files.  <2 s.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings, strategies as st

from scmr_mesh.errors import ConfigError
from scmr_mesh.scenario.plan import RADIO, compile_timeline
from scmr_mesh.scenario.radio import Radio, hops, links_timeline, rate_changes
from scmr_mesh.scenario.report import build_report, request_hops
from scmr_mesh.scenario.spec import parse_scenario

T0 = 1_700_000_000_000_000_000


def tunnel(**topology) -> dict:
    """The portal (cloud, leader) at 0 m and five robots 10 m apart down a tunnel; range 12 m."""
    topo = {"range_m": 12, "nodes": {"cloud": [0, 0], "leader": [0, 1], "robot1": [10, 0], "robot2": [20, 0],
                                     "robot3": [30, 0], "robot4": [40, 0], "robot5": [50, 0]}}
    topo.update(topology)
    return {"name": "tunnel", "seed": 1, "duration_s": 20, "topology": topo,
            "fleet": {"robots": [{"id": f"robot{i}", "synthetic": "tunnel"} for i in range(1, 6)]}}


def test_a_tunnel_chain_links_only_neighbours_and_chains_bootstraps():
    sc = parse_scenario(tunnel())
    assert sorted(sc.radio.links_at(0.0)) == [("cloud", "leader"), ("cloud", "robot1"), ("leader", "robot1"),
                                              ("robot1", "robot2"), ("robot2", "robot3"), ("robot3", "robot4"),
                                              ("robot4", "robot5")]
    # each peer is handed the nearest earlier-started peer in range: robot5 -> robot4 -> ... -> the portal
    assert sc.bootstraps["robot5"] == ("robot4",) and sc.bootstraps["robot1"] == ("cloud",)
    assert sc.bootstraps["leader"] == ("cloud",) and sc.bootstraps["cloud"] == ()
    # every pair out of range is blocked before any peer starts (RADIO events at 0), none lifted later
    ev = compile_timeline(sc)
    blocked = {e.target for e in ev if e.op == "block" and e.fault == RADIO and e.at_s == 0.0}
    assert ("cloud", "robot5") in blocked and ("robot1", "robot2") not in blocked and len(blocked) == 21 - 7
    assert not [e for e in ev if e.op == "unblock"]
    # robot5 is 5 radio hops from the cloud, 1 from robot4
    links = sc.radio.links_at(0.0)
    assert hops(links, "robot5", "cloud") == 5 and hops(links, "robot5", "robot4") == 1
    assert hops(links, "robot5", "robot5") == 0 and hops({("a", "b")}, "a", "c") is None


def test_a_robot_walking_out_of_range_is_cut_and_back_in_range_is_healed():
    sc = parse_scenario(tunnel(waypoints=[{"node": "robot5", "at_s": 5, "pos": [70, 0]},
                                          {"node": "robot5", "at_s": 10, "pos": [50, 0]}]))
    ev = [(round(e.at_s, 3), e.op, e.target) for e in compile_timeline(sc) if e.at_s > 0]
    # robot5 moves from 50 to 70 m over 5 s (4 m/s): leaves robot4's 12 m at 52 m = 0.5 s; back at 9.5 s
    assert ev == [(0.5, "block", ("robot4", "robot5")), (9.5, "unblock", ("robot4", "robot5"))]
    tl = links_timeline(sc.radio, sc.duration_s)
    assert [e["t_s"] for e in tl] == [0.0, 0.5, 9.5]
    assert ["robot4", "robot5"] not in tl[1]["links"] and ["robot4", "robot5"] in tl[2]["links"]


def test_a_link_fault_and_the_radio_share_the_cut():
    """A link fault on a pair that walks out of range is not lifted while the pair is still out of range."""
    d = tunnel(waypoints=[{"node": "robot5", "at_s": 4, "pos": [70, 0]}])
    d["faults"] = [{"kind": "link_down", "at_s": 0.1, "for_s": 2, "link": ["robot4", "robot5"]}]
    ev = [(round(e.at_s, 3), e.op, e.fault) for e in compile_timeline(parse_scenario(d)) if e.at_s > 0]
    assert ev == [(0.1, "block", 0)]  # out of range from 0.4 s: the fault's lift at 2.1 s restores nothing


def test_bandwidth_falls_with_distance():
    sc = parse_scenario(tunnel(bandwidth=[[5, 54000], [11, 11000], [12, 1000]],
                               waypoints=[{"node": "robot1", "at_s": 10, "pos": [2, 0]}]))
    r = sc.radio
    assert r.rate_kbit("robot1", "cloud", 0.0) == 11000 and r.rate_kbit("robot1", "cloud", 10.0) == 54000
    ch = [(round(t, 3), p, k) for t, p, k in rate_changes(r, sc.duration_s) if t > 0 and p == ("cloud", "robot1")]
    assert ch == [(6.25, ("cloud", "robot1"), 54000)]  # 10 m -> 2 m over 10 s: within 5 m at 6.25 s
    shapes = [e for e in compile_timeline(sc) if e.op == "shape" and e.target == ("cloud", "robot1")]
    assert [(round(e.at_s, 3), e.value) for e in shapes] == [(0.0, 11000), (6.25, 54000)]


@pytest.mark.parametrize("change, field, says", [
    ({"nodes": {"cloud": [0, 0]}}, "topology.nodes", "no position for leader, robot1"),
    ({"nodes": {**tunnel()["topology"]["nodes"], "robot5": [90, 0]}}, "topology.nodes",
     "robot5 out of every other peer's range (12 m) at time 0"),
    ({"waypoints": [{"node": "robot2", "at_s": 5, "pos": [0, 0]}, {"node": "robot2", "at_s": 3, "pos": [1, 0]}]},
     "topology.waypoints[1].at_s", "is not after its previous one"),
    ({"waypoints": [{"node": "robot9", "at_s": 5, "pos": [0, 0]}]}, "topology.waypoints[0].node", "unknown peer 'robot9'"),
    ({"waypoints": [{"node": "robot2", "at_s": 25, "pos": [0, 0]}]}, "topology.waypoints[0].at_s", "after the end"),
    ({"links": [["robot1", "cloud"]]}, "topology", "both links and a radio topology"),
    ({"bandwidth": [[10, 100], [5, 1000]]}, "topology.bandwidth", "distances are not increasing"),
])
def test_bad_radio_topologies_get_one_line(change, field, says):
    d = tunnel()
    d["topology"].update(change)
    with pytest.raises(ConfigError) as err:
        parse_scenario(d)
    msg = str(err.value)
    assert f"field '{field}'" in msg and says in msg and "fix:" in msg and "\n" not in msg


def test_range_without_nodes_is_refused():
    d = tunnel()
    del d["topology"]["nodes"]
    with pytest.raises(ConfigError, match=r"field 'topology.nodes': a radio topology \(range_m\) needs nodes"):
        parse_scenario(d)


def test_requests_carry_their_hops():
    sc = parse_scenario(tunnel())
    recs = [{"robot": "robot5", "seq": 0, "sent_unix_ns": T0 + 10**9, "ok": True, "tier": "cloud",
             "served_by": "cloud", "tor_ms": 5.0},
            {"robot": "robot5", "seq": 1, "sent_unix_ns": T0 + 2 * 10**9, "ok": True, "tier": "local",
             "served_by": "robot5", "tor_ms": 50.0},
            {"robot": "robot2", "seq": 0, "sent_unix_ns": T0 + 10**9, "ok": False, "tier": None}]
    rep = build_report(sc, recs, [], t0_unix_ns=T0, backend="test")
    assert [r["hops"] for r in rep["requests"]] == [5, 0, None]
    assert rep["links_over_time"][0]["t_s"] == 0.0
    flat = parse_scenario({"name": "f", "seed": 1, "duration_s": 5,
                           "fleet": {"robots": [{"id": "robot1", "synthetic": "road"}]}})
    assert request_hops(flat, None, {"ok": True, "tier": "cloud", "served_by": "cloud"}) == 1


steps = st.floats(-60, 60, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0.5, 19.5), steps, steps), min_size=1, max_size=4),
       st.floats(0.01, 19.99))
def test_the_changes_replay_the_link_state_at_any_instant(waypoints, t):
    """Link state at t = state at 0 toggled by every change before t (the changes are exact and complete)."""
    way = sorted({round(w[0], 3): w for w in waypoints}.values())
    r = Radio(range_m=12, positions={"a": (0.0, 0.0), "b": (10.0, 0.0), "c": (20.0, 5.0)},
              waypoints={"c": tuple((w[0], (w[1], w[2])) for w in way)})
    changes = r.changes(20.0)
    for a, b in (("a", "c"), ("b", "c"), ("a", "b")):
        state = r.in_range(a, b, 0.0)
        for tc, pair, up in changes:
            if pair == (a, b) and tc < t:
                assert up != state  # changes alternate
                state = up
        near = [tc for tc, pair, _ in changes if pair == (a, b) and abs(tc - t) < 1e-4]
        if not near and abs(r.distance(a, b, t) - 12) > 1e-6:
            assert state == r.in_range(a, b, t)
    assert all(changes[i][0] <= changes[i + 1][0] for i in range(len(changes) - 1))
    assert all(0 < tc < 20 and not math.isnan(tc) for tc, _, _ in changes)
