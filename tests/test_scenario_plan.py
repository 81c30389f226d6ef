"""Pure fault plans: snapshots per fault kind, and any valid timeline undoes itself."""

from __future__ import annotations

import shlex

from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.scenario.plan import NetnsLayout, compile_timeline, proxy_actions
from scmr_mesh.scenario.spec import parse_scenario

BASE = {"name": "p", "seed": 0, "duration_s": 20,
        "fleet": {"robots": [{"id": "robot1", "synthetic": "stub"}, {"id": "robot2", "synthetic": "stub"}]}}
# peers: cloud .10, leader .11, robot1 .12, robot2 .13


def _scenario(*faults):
    return parse_scenario(dict(BASE, faults=list(faults)))


def _plan(*faults):
    sc = _scenario(*faults)
    lay = NetnsLayout(sc, run_id="t1")
    return [(e.at_s, shlex.join(c)) for e in compile_timeline(sc) for c in lay.commands(e)]


def test_snapshot_link_down():
    assert _plan({"kind": "link_down", "at_s": 1, "for_s": 2, "link": ["robot1", "cloud"]}) == [
        (1.0, "ip -n scmrs-t1-cloud route add blackhole 198.18.0.12/32"),
        (1.0, "ip -n scmrs-t1-robot1 route add blackhole 198.18.0.10/32"),
        (3.0, "ip -n scmrs-t1-cloud route del blackhole 198.18.0.12/32"),
        (3.0, "ip -n scmrs-t1-robot1 route del blackhole 198.18.0.10/32"),
    ]


def test_snapshot_partition_cuts_every_cross_pair_and_is_lifted_at_the_end():
    plan = _plan({"kind": "partition", "at_s": 2, "groups": [["robot2"], ["cloud", "leader"]]})
    assert plan == [
        (2.0, "ip -n scmrs-t1-cloud route add blackhole 198.18.0.13/32"),
        (2.0, "ip -n scmrs-t1-robot2 route add blackhole 198.18.0.10/32"),
        (2.0, "ip -n scmrs-t1-leader route add blackhole 198.18.0.13/32"),
        (2.0, "ip -n scmrs-t1-robot2 route add blackhole 198.18.0.11/32"),
        (20.0, "ip -n scmrs-t1-cloud route del blackhole 198.18.0.13/32"),
        (20.0, "ip -n scmrs-t1-robot2 route del blackhole 198.18.0.10/32"),
        (20.0, "ip -n scmrs-t1-leader route del blackhole 198.18.0.13/32"),
        (20.0, "ip -n scmrs-t1-robot2 route del blackhole 198.18.0.11/32"),
    ]


def test_a_link_fault_held_by_another_ends_when_its_cut_is_restored():
    """The thesis's loss run: robot2's own cut from the cloud ends inside the partition of the cloud
    (no unblock of its own); the partition's unblock at 12 s restores it, and ends it too."""
    sc = _scenario({"kind": "link_down", "at_s": 1, "for_s": 5, "link": ["robot2", "cloud"]},
                   {"kind": "partition", "at_s": 4, "for_s": 8, "groups": [["cloud"], ["leader", "robot1", "robot2"]]})
    unblocks = [(e.at_s, e.target, e.fault, e.ends) for e in compile_timeline(sc) if e.op == "unblock"]
    assert (12.0, ("cloud", "robot2"), 1, (0,)) in unblocks
    assert not [u for u in unblocks if u[0] == 6.0]  # robot2-cloud stays cut at the link_down's own lift
    assert all(u[3] == () for u in unblocks if u[1] != ("cloud", "robot2"))


def test_a_partition_that_restores_some_cuts_at_its_lift_ends_there():
    """robot2 stays cut by its own link_down after the partition lifts: the partition still ends at 8 s."""
    sc = _scenario({"kind": "link_down", "at_s": 1, "for_s": 10, "link": ["robot2", "cloud"]},
                   {"kind": "partition", "at_s": 4, "for_s": 4, "groups": [["cloud"], ["leader", "robot1", "robot2"]]})
    evs = [e for e in compile_timeline(sc) if e.op == "unblock"]
    assert {e.at_s for e in evs if e.fault == 1} == {8.0} and all(e.ends == () for e in evs)
    assert [(e.at_s, e.target) for e in evs if e.fault == 0] == [(11.0, ("cloud", "robot2"))]


def test_snapshot_crash_is_process_only():
    sc = _scenario({"kind": "crash", "at_s": 4, "for_s": 5, "peer": "cloud"})
    evs = compile_timeline(sc)
    assert [(e.at_s, e.op, e.target) for e in evs] == [(4.0, "kill", ("cloud",)), (9.0, "start", ("cloud",))]
    lay = NetnsLayout(sc, run_id="t1")
    assert all(lay.commands(e) == [] for e in evs)
    assert (4.0, "kill cloud (SIGKILL)") in lay.plan()


def test_snapshot_bandwidth_uses_the_link_classes_both_ways():
    assert _plan({"kind": "bandwidth", "at_s": 1, "for_s": 1, "link": ["robot2", "cloud"], "rate_kbit": 8000}) == [
        (1.0, "tc -n scmrs-t1-robot2 class change dev eth0 parent 1: classid 1:10 htb rate 8000kbit ceil 8000kbit"),
        (1.0, "tc -n scmrs-t1-cloud class change dev eth0 parent 1: classid 1:13 htb rate 8000kbit ceil 8000kbit"),
        (2.0, "tc -n scmrs-t1-robot2 class change dev eth0 parent 1: classid 1:10 htb rate 10gbit ceil 10gbit"),
        (2.0, "tc -n scmrs-t1-cloud class change dev eth0 parent 1: classid 1:13 htb rate 10gbit ceil 10gbit"),
    ]


def test_snapshot_latency_and_loss_combine_into_one_netem():
    plan = _plan({"kind": "latency", "at_s": 1, "for_s": 4, "link": ["robot1", "leader"], "delay_ms": 40},
                 {"kind": "loss", "at_s": 2, "for_s": 1, "link": ["robot1", "leader"], "percent": 5})
    assert plan == [
        (1.0, "tc -n scmrs-t1-robot1 qdisc replace dev eth0 parent 1:11 handle 11: netem delay 20ms loss 0%"),
        (1.0, "tc -n scmrs-t1-leader qdisc replace dev eth0 parent 1:12 handle 12: netem delay 20ms loss 0%"),
        (2.0, "tc -n scmrs-t1-robot1 qdisc replace dev eth0 parent 1:11 handle 11: netem delay 20ms loss 5%"),
        (2.0, "tc -n scmrs-t1-leader qdisc replace dev eth0 parent 1:12 handle 12: netem delay 20ms loss 5%"),
        (3.0, "tc -n scmrs-t1-robot1 qdisc replace dev eth0 parent 1:11 handle 11: netem delay 20ms loss 0%"),
        (3.0, "tc -n scmrs-t1-leader qdisc replace dev eth0 parent 1:12 handle 12: netem delay 20ms loss 0%"),
        (5.0, "tc -n scmrs-t1-robot1 qdisc del dev eth0 parent 1:11"),
        (5.0, "tc -n scmrs-t1-leader qdisc del dev eth0 parent 1:12"),
    ]


def test_overlapping_faults_are_reference_counted():
    # a partition over a link that is already down: the route is added once and removed once, at the last lift
    plan = _plan({"kind": "link_down", "at_s": 1, "for_s": 5, "link": ["robot2", "cloud"]},
                 {"kind": "partition", "at_s": 2, "for_s": 1, "groups": [["cloud"], ["robot2"]]})
    assert [t for t, c in plan if "cloud route" in c and ".13/" in c] == [1.0, 6.0]


def test_setup_and_teardown_stay_in_our_namespaces():
    sc = _scenario()
    lay = NetnsLayout(sc, run_id="t1")
    cmds = lay.setup()
    for c in cmds:
        assert c[0] in ("ip", "tc")
        # every command names one of our namespaces (never the host's)
        assert any(a.startswith("scmrs-t1-") for a in c), c
    assert not any("default" in c and "route" in c for c in cmds)  # no default route anywhere
    assert {c[-1] for c in lay.teardown()} == set(lay.namespaces())
    # one htb class + filter per direction of each declared link
    assert sum(1 for c in cmds if "filter" in c) == 2 * len(sc.links)


# -- Hypothesis: any valid timeline yields a plan that undoes itself ------------------------------
PEERS = ["cloud", "leader", "robot1", "robot2"]
LINKS = [("robot1", "cloud"), ("robot1", "leader"), ("robot2", "cloud"), ("robot2", "leader"), ("leader", "cloud")]


@st.composite
def faults(draw):
    kind = draw(st.sampled_from(["link_down", "partition", "crash", "bandwidth", "latency", "loss"]))
    at = draw(st.integers(0, 18)) / 1.0
    f = {"kind": kind, "at_s": at}
    if draw(st.booleans()):
        f["for_s"] = draw(st.integers(1, 30)) / 2.0
    if kind in ("link_down", "bandwidth", "latency", "loss"):
        f["link"] = list(draw(st.sampled_from(LINKS)))
    if kind == "bandwidth":
        f["rate_kbit"] = draw(st.integers(8, 100000))
    if kind == "latency":
        f["delay_ms"] = draw(st.integers(0, 500))
    if kind == "loss":
        f["percent"] = draw(st.integers(0, 100))
    if kind == "partition":
        perm = draw(st.permutations(PEERS))
        cut = draw(st.integers(1, 3))
        f["groups"] = [list(perm[:cut]), list(perm[cut:])]
    if kind == "crash":
        f["peer"] = draw(st.sampled_from(PEERS))
    return f


def _valid(fs):
    try:
        return parse_scenario(dict(BASE, faults=fs))
    except Exception:  # overlapping crashes of one peer are invalid: Hypothesis skips them
        return None


class NetModel:
    """A model of the kernel state our commands touch; it rejects impossible commands like the kernel does."""

    def __init__(self):
        self.routes, self.rates, self.netem, self.down = set(), {}, set(), set()

    def run(self, c):
        if c[3] == "route":
            key = (c[2], c[6])
            if c[4] == "add":
                assert key not in self.routes, f"route added twice: {c}"
                self.routes.add(key)
            else:
                assert key in self.routes, f"route deleted but absent: {c}"
                self.routes.remove(key)
        elif c[3] == "class":
            self.rates[(c[2], c[10])] = c[13]
        elif c[3] == "qdisc":
            key = (c[2], c[8])
            if c[4] == "del":
                assert key in self.netem, f"netem deleted but absent: {c}"
                self.netem.remove(key)
            else:
                self.netem.add(key)


@settings(max_examples=150, deadline=None)
@given(st.lists(faults(), max_size=8))
def test_any_valid_timeline_undoes_itself(fs):
    sc = _valid(fs)
    if sc is None:
        return
    lay = NetnsLayout(sc, run_id="h")
    model = NetModel()
    events = compile_timeline(sc)
    assert [e.at_s for e in events] == sorted(e.at_s for e in events)
    killed = set()
    for e in events:
        for c in lay.commands(e):
            model.run(c)
        if e.op == "kill":
            assert e.target[0] not in killed
            killed.add(e.target[0])
        elif e.op == "start":
            killed.remove(e.target[0])
    # after every fault is lifted the topology is whole again
    assert model.routes == set() and model.netem == set() and killed == set()
    # every link fault is ended by exactly one restoring event at or after its own lift
    for i, f in enumerate(sc.faults):
        if f.kind in ("link_down", "partition"):
            enders = [e for e in events if e.op == "unblock" and i in ((e.fault,) if e.fault == i else e.ends)]
            own_end = f.end_s if f.end_s is not None and f.end_s < sc.duration_s else sc.duration_s
            assert enders and min(e.at_s for e in enders) >= own_end, (i, f, events)
            # a fault that restored some cut at its own lift is named by no later event
            if any(e.fault == i and e.op == "unblock" for e in events):
                assert not [e for e in events if i in e.ends], (i, events)
            assert len({e.at_s for e in events if e.op == "unblock" and i in e.ends}) <= 1
    assert all(r == "10gbit" for r in model.rates.values())
    # the proxy backend ends in the same state: forwarding, unlimited, no delay
    state = {link: {"mode": "forward", "rate": None, "delay": 0.0} for link in sc.links}
    for e in events:
        for link, action, value in proxy_actions(sc.links, e):
            if action in ("blackhole", "forward"):
                state[link]["mode"] = action
            elif action == "rate":
                state[link]["rate"] = value
            else:
                state[link]["delay"] = value
    assert all(s == {"mode": "forward", "rate": None, "delay": 0.0} for s in state.values())


class _NoopBackend:
    def apply_many(self, batch):
        return []


def _ends_after_running(sc) -> dict[int, bool]:
    """Run the runner's event application with a backend that does nothing: which faults got an end."""
    import time

    from scmr_mesh.scenario.runner import AppliedFault, _apply_batch, _batches

    applied = [AppliedFault(i, f) for i, f in enumerate(sc.faults)]
    for batch in _batches(compile_timeline(sc)):
        _apply_batch(batch, _NoopBackend(), None, {}, applied, None, sc, time.monotonic(), lambda m: None)
    return {a.index: a.end_unix_ns is not None for a in applied}


def test_the_runner_ends_held_faults_with_their_holder_but_not_at_the_teardown():
    held = _scenario({"kind": "link_down", "at_s": 1, "for_s": 5, "link": ["robot2", "cloud"]},
                     {"kind": "partition", "at_s": 4, "for_s": 8, "groups": [["cloud"], ["leader", "robot1", "robot2"]]})
    assert _ends_after_running(held) == {0: True, 1: True}
    # the holder lasts to the end of the run: neither gets an end (a teardown is not a heal)
    to_the_end = _scenario({"kind": "link_down", "at_s": 1, "for_s": 5, "link": ["robot2", "cloud"]},
                           {"kind": "partition", "at_s": 4, "groups": [["cloud"], ["leader", "robot1", "robot2"]]})
    assert _ends_after_running(to_the_end) == {0: False, 1: False}


def test_cleanup_by_default_takes_every_prefix_of_the_project_and_nothing_else():
    """`scmr scenario cleanup` (``cleanup_stale()``): the namespaces of scenario runs, sites, the tx-stall
    bench and the tests' hosts go; a namespace of anyone else (or ``scmr-...``, no family letter) stays;
    a prefix outside the project's is refused.  A recording runner, so no root is needed."""
    import pytest

    from scmr_mesh.errors import ScenarioError
    from scmr_mesh.scenario.netns import cleanup_stale

    # tags no real run uses (not hex, not a pid), so the real /proc sweep cannot match a live namespace
    listed = ["scmrs-zzfake-cloud", "scmrm-zzfake-a", "scmrb-zzfake-br", "scmrh-zzfake-r1", "scmrg-zzfake-a",
              "docker-1", "scmr-x", "scmrz-1"]
    deleted = []

    def run(cmd):
        cmd = tuple(cmd)
        if cmd == ("ip", "netns", "list"):
            return "\n".join(f"{n} (id: {i})" for i, n in enumerate(listed))
        if cmd[:3] == ("ip", "netns", "pids"):
            return ""
        if cmd[:3] == ("ip", "netns", "del"):
            deleted.append(cmd[3])
            return ""
        raise AssertionError(cmd)

    assert cleanup_stale(run=run) == listed[:5] and deleted == listed[:5]
    deleted.clear()
    assert cleanup_stale("scmrh-", run=run) == ["scmrh-zzfake-r1"] and deleted == ["scmrh-zzfake-r1"]
    for bad in ("docker", "scmr", "scmrz-", ""):
        with pytest.raises(ScenarioError, match="refusing"):
            cleanup_stale(bad, run=run)


def test_every_namespace_the_code_names_has_one_of_the_projects_prefixes():
    """A scan of the sources and tests for namespace-like names ``scmr<letter>-``: each family is in
    OWN_NS_PREFIXES, so `scmr scenario cleanup` can remove what a killed run of it left.  A name built
    another way escapes the scan; ``tests/conftest.py``'s ``bridged_hosts`` also checks its prefix
    when it runs."""
    import re
    from pathlib import Path

    from scmr_mesh.scenario.plan import OWN_NS_PREFIXES

    root = Path(__file__).resolve().parents[1]
    found = {}
    for path in [*root.joinpath("scmr_mesh").rglob("*.py"), *root.joinpath("tests").rglob("*.py"),
                 *root.joinpath("scripts").rglob("*")]:
        if not path.is_file():
            continue
        if path.name == Path(__file__).name:   # this file names strangers on purpose
            continue
        for m in re.finditer(r"(?<![\w.])scmr([a-z]+)-", path.read_text(errors="replace")):
            found.setdefault(f"scmr{m.group(1)}-", path.name)
    unknown = {p: f for p, f in found.items() if p not in OWN_NS_PREFIXES}
    assert {"scmrs-", "scmrm-", "scmrb-", "scmrh-", "scmrg-"} <= set(found), found
    assert not unknown, unknown
