"""The report's leadership block (scmr_mesh/qos/leadership.py), on hand-made timelines."""

from __future__ import annotations

import json

from scmr_mesh.qos.leadership import gap_ms, leadership, wait_ms

S = 1_000_000_000
T0 = 100 * S


def ev(t_s, node, event, term, cause="", *, why="other", by=None):
    """A role change as the election writes it (qos.roles.RoleChange); ``cause`` is prose nobody parses."""
    return {"t_unix_ns": T0 + int(t_s * S), "node": node, "event": event, "term": term, "cause": cause,
            "why": why, "by": by}


def rec(robot, t_s, tier, served_by, tor_ms=10.0):
    sent = T0 + int(t_s * S)
    return {"robot": robot, "ok": True, "tier": tier, "served_by": served_by, "sent_unix_ns": sent,
            "received_unix_ns": sent + int(tor_ms * 1e6), "tor_ms": tor_ms}


def test_a_crash_passes_the_lead_with_its_times():
    events = [ev(0.0, "L", "lead", 1), ev(5.03, "r1", "lead", 2)]
    faults = [{"kind": "crash", "target": "L", "start_unix_ns": T0 + 5 * S, "end_unix_ns": None}]
    records = ([rec("r2", t / 10, "leader", "L") for t in range(10, 50, 5)]
               + [rec("r2", 5.0, "peer", "r3")] + [rec("r2", t / 10, "leader", "r1") for t in range(55, 80, 5)])
    out = leadership(events, records, faults, t0_unix_ns=T0)
    start, move = out["changes"]
    assert start == {"t_s": 0.0, "from": None, "to": "L", "term": 1, "gap_ms": None, "cause": "start",
                     "succession_ms": None, "wait_ms": None}
    assert (move["from"], move["to"], move["cause"], move["term"]) == ("L", "r1", "crash", 2)
    assert move["succession_ms"] == 30.0
    # r2's last answer from L at 4.5 s (+10 ms), first from r1 at 5.5 s (+10 ms): 1000 ms, a request period
    assert move["gap_ms"] == 1000.0
    # it was served by a peer at 5.0 s: it went 10 ms without the tier (its request sent at the crash)
    assert move["wait_ms"] == 10.0
    assert out["leaders_at_end"] == ["r1"]
    assert out["converged_after_heal_ms"] is None


def test_a_partition_elects_on_the_far_side_and_the_heal_leaves_one():
    faults = [{"kind": "partition", "groups": [["L", "r1"], ["r3", "r4"]],
               "start_unix_ns": T0 + 4 * S, "end_unix_ns": T0 + 10 * S}]
    events = [ev(0, "L", "lead", 1), ev(4.3, "r3", "lead", 2),
              ev(10.15, "L", "step_down", 2, "outranked by r3 (term 2 vs 1)", why="outranked", by="r3")]
    out = leadership(events, [], faults, t0_unix_ns=T0)
    link = out["changes"][1]
    assert (link["from"], link["to"], link["cause"]) == ("L", "r3", "link")
    assert link["succession_ms"] == 300.0  # from the start of the cut
    heal = out["changes"][2]
    assert (heal["from"], heal["to"], heal["cause"]) == ("L", "r3", "heal")
    assert out["leaders_at_end"] == ["r3"]
    assert out["converged_after_heal_ms"] == 150.0
    assert [p["leaders"] for p in out["leaders_over_time"]] == [["L"], ["L", "r3"], ["r3"]]


def test_changes_after_the_first_graceful_stop_are_the_end_of_the_run():
    events = [ev(0, "L", "lead", 1), ev(9.0, "L", "step_down", 1, "stopping", why="stopping"), ev(9.01, "r1", "lead", 2)]
    out = leadership(events, [], [], t0_unix_ns=T0)
    assert [c["to"] for c in out["changes"]] == ["L"] and out["leaders_at_end"] == ["L"]


def test_two_leaders_left_are_reported_as_two():
    events = [ev(0, "L", "lead", 1), ev(1, "r1", "lead", 1)]
    out = leadership(events, [], [], t0_unix_ns=T0)
    assert out["leaders_at_end"] == ["L", "r1"]


def test_gap_and_wait_need_answers_from_both():
    assert gap_ms([], "L", "r1", T0) is None
    assert wait_ms([], T0, "r1") is None
    assert gap_ms([rec("a", 1, "leader", "L")], None, "r1", T0) is None


def test_a_newer_term_without_a_fault_replaces_the_old_leader():
    """A blink: r1 claims term 2 while L (term 1) still leads in the log; L yields later."""
    events = [ev(0, "L", "lead", 1), ev(3, "r1", "lead", 2), ev(3.2, "L", "step_down", 2, "outranked by r1 (term 2 vs 1)", why="outranked", by="r1")]
    out = leadership(events, [], [], t0_unix_ns=T0)
    assert [(c["from"], c["to"], c["cause"]) for c in out["changes"]] == [(None, "L", "start"), ("L", "r1", "link")]
    assert out["changes"][1]["succession_ms"] is None  # the loss time is not known: not a pass
    assert out["leaders_at_end"] == ["r1"]


def test_step_down_causes_name_nodes_exactly_and_heals_are_recent():
    faults = [{"kind": "partition", "groups": [["a"], ["r1"], ["r10"]], "start_unix_ns": T0 + S,
               "end_unix_ns": T0 + 2 * S}]
    events = [ev(0, "a", "lead", 1), ev(1.3, "r1", "lead", 2), ev(1.3, "r10", "lead", 2),
              ev(2.1, "r1", "step_down", 2, "outranked by r10 (term 2 vs 2)", why="outranked", by="r10"),
              ev(2.2, "a", "step_down", 2, "outranked by r10 (term 2 vs 1)", why="outranked", by="r10")]
    out = leadership(events, [], faults, t0_unix_ns=T0)
    heals = [(c["from"], c["to"]) for c in out["changes"] if c["cause"] == "heal"]
    assert heals == [("r1", "r10"), ("a", "r10")]
    late = leadership(events + [ev(20, "r10", "step_down", 3, "outranked by zz (term 3 vs 2)", why="outranked", by="zz")], [], faults,
                      t0_unix_ns=T0)
    assert all(c["t_s"] < 20 for c in late["changes"] if c["cause"] == "heal")  # 18 s after the heal: not a heal


def test_no_leader_after_a_heal_is_not_converged_and_a_lost_lead_is_unfilled():
    faults = [{"kind": "partition", "groups": [["a"], ["b"]], "start_unix_ns": T0 + S, "end_unix_ns": T0 + 2 * S},
              {"kind": "crash", "target": "b", "start_unix_ns": T0 + 3 * S, "end_unix_ns": None}]
    events = [ev(0, "a", "lead", 1), ev(1.3, "b", "lead", 2), ev(2.1, "a", "step_down", 2, "outranked by b (term 2 vs 1)", why="outranked", by="b")]
    out = leadership(events, [], faults, t0_unix_ns=T0)
    assert out["converged_after_heal_ms"] == 100.0
    assert out["leaders_at_end"] == [] and out["unfilled"] == [{"t_s": 3.0, "from": "b", "cause": "crash"}]
    # both leaders gone at 2.1 s (one yields, the other crashes): nobody leads until c at 4 s
    gone = [faults[0], {"kind": "crash", "target": "b", "start_unix_ns": T0 + int(2.1 * S), "end_unix_ns": None}]
    both = leadership([ev(0, "a", "lead", 1), ev(1.3, "b", "lead", 2),
                       ev(2.1, "a", "step_down", 2, "outranked by b (term 2 vs 1)", why="outranked", by="b"), ev(4.0, "c", "lead", 3)],
                      [], gone, t0_unix_ns=T0)
    assert both["converged_after_heal_ms"] == 2000.0  # zero leaders is not one leader


def test_the_report_reads_no_prose():
    """Rewording every cause (what the election logs for people) changes nothing in the report."""
    events = [ev(0, "a", "lead", 1, "vacancy; best-ranked live candidate", why="vacancy"),
              ev(1.3, "b", "lead", 2, "vacancy for 300 ms", why="vacancy"),
              ev(2.1, "a", "step_down", 2, "outranked by b (term 2 vs 1)", why="outranked", by="b"),
              ev(9.0, "b", "step_down", 2, "stopping", why="stopping"), ev(9.01, "c", "lead", 3, why="vacancy")]
    faults = [{"kind": "partition", "groups": [["a"], ["b"]], "start_unix_ns": T0, "end_unix_ns": T0 + 2 * S}]
    reworded = [{**e, "cause": "x"} for e in events]
    assert leadership(reworded, [], faults, t0_unix_ns=T0) == leadership(events, [], faults, t0_unix_ns=T0)


def test_role_changes_round_trip_and_skip_other_lines(tmp_path):
    from scmr_mesh.qos.leadership import read_events
    from scmr_mesh.qos.roles import RoleChange, RoleEvent, Why

    c = RoleChange(T0, "r1", RoleEvent.STEP_DOWN, 4, Why.OUTRANKED, "r2", "outranked by r2", ("r2",))
    (tmp_path / "r1.jsonl").write_text("\n".join([json.dumps(c.to_json()), '{"event": "lead"}', "not json",
                                                  json.dumps({**c.to_json(), "why": "bogus"})]) + "\n")
    assert [RoleChange.from_json(e) for e in read_events(tmp_path)] == [c]
