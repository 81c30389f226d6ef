"""Robot routing logic without processes: live view, load spreading, placement (< 1 s)."""

from __future__ import annotations

from dataclasses import dataclass

import zenoh
from hypothesis import given
from hypothesis import strategies as st

from scmr_mesh import keys, wire
from scmr_mesh.mesh.robot import FrameInfo, LiveView, Reachable, default_placement


@dataclass
class _Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class _Sample:
    key_expr: str
    kind: object  # a zenoh.SampleKind, as zenoh hands it
    payload: _Payload | None = None


def _up(view, role, node):
    view.on_liveliness(_Sample(keys.alive(role, node), zenoh.SampleKind.PUT))


def _down(view, role, node):
    view.on_liveliness(_Sample(keys.alive(role, node), zenoh.SampleKind.DELETE))


def _load(view, node, inflight, workers=2):
    msg = wire.make_load(node, "cloud", workers=workers, inflight=inflight, served=0)
    view.on_load(_Sample(keys.load("cloud", node), zenoh.SampleKind.PUT, _Payload(wire.encode(msg))))


FRAME = FrameInfo("r1", 0, 1000, "png")


def test_liveliness_put_and_delete():
    v = LiveView()
    _up(v, "cloud", "c1")
    _up(v, "leader", "L")
    _up(v, "robot", "r9")
    snap = v.snapshot()
    assert snap.cloud == ("c1",) and snap.leader == ("L",)
    _down(v, "cloud", "c1")
    assert v.snapshot().cloud == ()
    assert v.wait_for_tier(0.01)  # the leader is still there
    _down(v, "leader", "L")
    assert not v.wait_for_tier(0.01)


def test_foreign_keys_are_ignored():
    v = LiveView()
    v.on_liveliness(_Sample("scmr/alive/cloud/c1/extra", zenoh.SampleKind.PUT))
    v.on_liveliness(_Sample("other/alive/cloud/c1", zenoh.SampleKind.PUT))
    v.on_load(_Sample("scmr/load/cloud/c1", zenoh.SampleKind.PUT, _Payload(b"\xc1junk")))
    assert v.snapshot().cloud == ()


def test_least_loaded_cloud_first():
    v = LiveView()
    for n in ("c1", "c2", "c3"):
        _up(v, "cloud", n)
    _load(v, "c1", 6)
    _load(v, "c2", 0)
    _load(v, "c3", 2)
    assert v.snapshot().cloud == ("c2", "c3", "c1")
    _down(v, "cloud", "c2")
    assert v.snapshot().cloud == ("c3", "c1")


def test_equal_loads_rotate_so_robots_spread():
    v = LiveView()
    for n in ("c1", "c2", "c3"):
        _up(v, "cloud", n)
    firsts = [v.snapshot().cloud[0] for _ in range(6)]
    assert sorted(set(firsts)) == ["c1", "c2", "c3"]


def test_busy_marks_raise_the_estimate():
    v = LiveView()
    _up(v, "cloud", "c1")
    _up(v, "cloud", "c2")
    v.mark_busy("c1", 5)
    assert all(v.snapshot().cloud[0] == "c2" for _ in range(4))


@given(st.booleans(), st.booleans(), st.booleans())
def test_default_placement_order(cloud, leader, local):
    view = Reachable(("c1",) if cloud else (), ("L",) if leader else (), {}, local)
    plan = default_placement(view, FRAME)
    expected = [t for t, ok in (("cloud", cloud), ("leader", leader), ("local", local)) if ok]
    assert plan == expected


def test_public_names_resolve():
    import scmr_mesh.mesh as mesh

    assert all(getattr(mesh, name) is not None for name in mesh.__all__)


def test_a_leader_beyond_the_term_window_is_not_the_robots_first_choice():
    """Issue #28: a leader-capable liar claiming wire.MAX_TERM (refused by the candidates) came first
    in every robot's leader order (highest term), drawing their frames from the elected leader."""
    v = LiveView()
    for node, term in (("leader0", 3), ("r9", wire.MAX_TERM)):
        _up(v, "leader", node)
        msg = wire.make_candidate(node, term=term, leading=True, clock_hz=1e9, power_w=None, battery=1.0, load=0.0)
        v.on_candidate(_Sample(keys.candidate(node), zenoh.SampleKind.PUT, _Payload(wire.encode(msg))))
    assert v.snapshot().leader == ("leader0", "r9")
    _down(v, "leader", "leader0")
    assert v.snapshot().leader == ("r9",)  # alone, it is a leader like any other


def test_robots_of_one_process_check_a_load_or_candidacy_payload_once(monkeypatch):
    """Issue 23: the robots a swarm plays receive the same load and heartbeat bytes; the first
    checks them against the schema, the others reuse it, and each view still gets the sample.
    A payload that fails the check is not kept: each robot refuses it. Fails on the old code
    (wire.decode ran for every sample of every robot: 8 calls, not 4)."""
    import scmr_mesh.mesh.liveview as liveview

    calls = []
    decode = wire.decode
    monkeypatch.setattr(liveview.wire, "decode", lambda data, kind: calls.append(kind) or decode(data, kind=kind))
    monkeypatch.setattr(liveview, "_decoded", {}, raising=False)
    views = [LiveView(), LiveView()]
    load = wire.encode(wire.make_load("c7", "cloud", workers=2, inflight=3, served=11, clock_hz=2e9))
    cand = wire.encode(wire.make_candidate("L7", term=4, leading=True, clock_hz=1e9, power_w=None, battery=1.0,
                                           load=0.0))
    for v in views:
        _up(v, "cloud", "c7")
        _up(v, "leader", "L7")
        v.on_load(_Sample(keys.load("cloud", "c7"), zenoh.SampleKind.PUT, _Payload(load)))
        v.on_candidate(_Sample(keys.candidate("L7"), zenoh.SampleKind.PUT, _Payload(cand)))
        # the same heartbeat on another candidate's key is still refused by each robot
        v.on_candidate(_Sample(keys.candidate("r9"), zenoh.SampleKind.PUT, _Payload(cand)))
        v.on_load(_Sample(keys.load("cloud", "c7"), zenoh.SampleKind.PUT, _Payload(b"\xc1junk")))
    assert sorted(calls) == ["candidate", "load", "load", "load"]  # junk checked (and refused) by each
    for v in views:
        snap = v.snapshot()
        assert snap.loads == {"c7": 1.5} and snap.clocks == {"c7": 2e9}
        assert v._cands["L7"].term == 4 and "r9" not in v._cands
