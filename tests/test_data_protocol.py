"""The telemetry protocol under any sequence of faults, without processes.

The real :class:`TelemetryAgent`, :class:`CloudData` and :class:`LeaderData`
code runs; only the Zenoh transport is replaced by direct calls with fake
query objects.  Faults are chosen by Hypothesis: cloud or leader down, an ack
lost after the store committed, a robot restart, leader forwarding at any
time.  Property: once the cloud is back and everything is flushed, the ODS
holds every seq 1..sent of the robot exactly once, and nothing is lost.
"""

from __future__ import annotations

import shutil
import tempfile
import threading
from pathlib import Path
from types import SimpleNamespace

import msgpack
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.data.ods import OperationalDataStore
from scmr_mesh.data.report import telemetry_report
from scmr_mesh.mesh.data_service import CloudData, LeaderData, TelemetryAgent


class FakeQuery:
    """The parts of a zenoh Query the data services use."""

    def __init__(self, payload: bytes, key_expr: str) -> None:
        self.key_expr = key_expr
        self._p = payload
        self.done = threading.Event()
        self.result = None

    @property
    def payload(self):
        return SimpleNamespace(to_bytes=lambda: self._p)

    def reply(self, key, data: bytes, *, encoding=None) -> None:
        self.result = ("ok", data)
        self.done.set()

    def reply_err(self, data: bytes, *, encoding=None) -> None:
        self.result = ("err", data)
        self.done.set()

    def drop(self) -> None:
        pass


class World:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.cloud_up = True
        self.leader_up = True
        self.lose_next_ack = False
        self.cloud = CloudData("c", tmp / "ods.sqlite")
        self.leader = LeaderData("L", tmp / "relay")
        self.leader._clouds = lambda: ["c"] if self.cloud_up else []
        self.leader._query = self._leader_query
        self.robot = SimpleNamespace(
            id="r1", _session=None, publish_telemetry=lambda m: None, add_telemetry_handler=lambda fn: None,
                           remove_telemetry_handler=lambda fn: None,
            view=SimpleNamespace(snapshot=lambda local=False: SimpleNamespace(
                cloud=("c",) if self.cloud_up else (), leader=("L",) if self.leader_up else ())))
        self.agent = self._new_agent()
        self.produced = 0

    def _new_agent(self) -> TelemetryAgent:
        agent = TelemetryAgent(self.robot, self.tmp / "queue", autostart=False)
        agent._ask = self._ask
        return agent

    def _call(self, tier: str, payload: bytes, key: str):
        q = FakeQuery(payload, key)
        if key.endswith("/relay"):
            self.cloud._on_relay(q)
        elif tier == "cloud":
            self.cloud._on_telemetry(q)
        else:
            self.leader._store_and_ack(q)
        assert q.done.wait(10)
        return q.result

    def _ask(self, key: str, payload: bytes):
        tier = key.split("/")[2]
        if not (self.cloud_up if tier == "cloud" else self.leader_up):
            return None  # no matching queryable
        kind, data = self._call(tier, payload, key)
        if self.lose_next_ack:  # stored, but the reply never arrives
            self.lose_next_ack = False
            return None
        return kind, msgpack.unpackb(data)

    def _leader_query(self, key: str, payload: bytes):
        if not self.cloud_up:
            return None
        kind, data = self._call("cloud", payload, key)
        return data if kind == "ok" else None

    def publish(self) -> None:
        self.produced += 1
        self.agent.publish({"robot": "r1", "seq": self.produced, "t_unix_ns": self.produced,
                            "pose": {"x": 0.0, "y": 1.0, "theta": 0.0}, "battery": 0.5, "health": "ok",
                            "results": {"requests": self.produced}})

    def restart_robot(self) -> None:
        self.agent.close(drain_s=0)
        self.agent = self._new_agent()

    def close(self) -> None:
        self.agent.close(drain_s=0)
        self.leader.close()
        self.cloud.close()


rare = st.integers(0, 4).map(lambda x: x == 0)  # True one time in five
step_st = st.fixed_dictionaries({
    "publish": st.integers(0, 3), "flush": st.booleans(), "forward": st.booleans(),
    "toggle_cloud": st.booleans(), "toggle_leader": rare, "lose_ack": rare, "restart_robot": rare,
})


@settings(max_examples=40, deadline=None)
@given(steps=st.lists(step_st, max_size=12))
def test_nothing_lost_nothing_stored_twice_under_any_faults(steps):
    tmp = Path(tempfile.mkdtemp())
    w = World(tmp)
    try:
        for step in steps:
            for _ in range(step["publish"]):
                w.publish()
            if step["toggle_cloud"]:
                w.cloud_up = not w.cloud_up
            if step["toggle_leader"]:
                w.leader_up = not w.leader_up
            if step["lose_ack"]:
                w.lose_next_ack = True
            if step["flush"]:
                w.agent.flush_once()
            if step["forward"]:
                w.leader.forward_once()
            if step["restart_robot"]:
                w.restart_robot()
        # failback: the cloud is back; robot and leader drain
        w.cloud_up, w.lose_next_ack = True, False
        while w.agent.flush_once():
            pass
        while w.leader.forward_once():
            pass
        sent = w.agent.queue.next_seq - 1
        assert sent == w.produced
        assert len(w.agent.queue) == 0 and len(w.leader.relay) == 0
        rep = telemetry_report(w.cloud.ods, {"r1": sent})["telemetry"]
        assert (rep["sent"], rep["stored"], rep["lost"]) == (sent, sent, 0)
        assert w.cloud.ods.seqs("r1") == list(range(1, sent + 1))
        # the cloud buffer's latest state is the last message
        if sent:
            assert w.cloud.buffer.get("state/r1")["seq"] == sent
    finally:
        w.close()
        shutil.rmtree(tmp)


def test_a_full_leader_relay_refuses_and_the_robot_keeps_its_records(tmp_path):
    w = World(tmp_path)
    try:
        w.leader.relay.max_bytes = 1  # nothing fits
        w.cloud_up = False
        for _ in range(3):
            w.publish()
        assert w.agent.flush_once() == 0  # the leader refused: not acked
        assert len(w.agent.queue) == 3 and len(w.leader.relay) == 0
        w.cloud_up = True
        assert w.agent.flush_once() == 3
        assert w.agent.summary()["replayed"] == 3 and w.agent.summary()["acked_by"]["cloud"] == 3
        with OperationalDataStore(tmp_path / "ods.sqlite", readonly=True) as ods:
            assert ods.seqs("r1") == [1, 2, 3]
    finally:
        w.close()


def test_a_batch_is_stored_only_under_its_robots_key(tmp_path):
    """The service binds records to the key's robot (docs/SECURITY.md): others are refused whole."""
    from scmr_mesh.data.record import encode_records, make_record

    cloud = CloudData("c", tmp_path / "ods.sqlite")
    leader = LeaderData("L", tmp_path / "relay")
    try:
        def send(handler, key, robots):
            q = FakeQuery(encode_records([make_record(r, i + 1) for i, r in enumerate(robots)]), key)
            handler(q)
            assert q.done.wait(10)
            return q.result[0], msgpack.unpackb(q.result[1])

        good = "scmr/data/cloud/c/telemetry/r1"
        kind, body = send(cloud._on_telemetry, "scmr/data/cloud/c/telemetry/r2", ["r2", "r1"])
        assert kind == "err" and "['r1']" in body["error"] and "telemetry/r2" in body["error"]
        for key in ("scmr/data/cloud/c/telemetry/*", "scmr/data/cloud/c/telemetry/**", "scmr/data/cloud/c/telemetry"):
            kind, body = send(cloud._on_telemetry, key, ["r1"])
            assert kind == "err" and "names no robot" in body["error"], key
        kind, body = send(leader._store_and_ack, "scmr/data/leader/L/telemetry/r2", ["r1"])
        assert kind == "err" and len(leader.relay) == 0
        assert cloud.ods.counts() == {}
        # the honest paths: a robot's own key; the leader's relay of several robots
        assert send(cloud._on_telemetry, good, ["r1", "r1"])[0] == "ok"
        assert send(leader._store_and_ack, "scmr/data/leader/L/telemetry/r3", ["r3"])[0] == "ok"
        assert send(cloud._on_relay, "scmr/data/cloud/c/relay", ["r3", "r4"])[0] == "ok"
        assert sorted(cloud.ods.counts()) == ["r1", "r3", "r4"]
        assert {r["robot"]: r["received_from"] for r in cloud.ods.range()} == {"r1": "cloud", "r3": "leader",
                                                                              "r4": "leader"}
    finally:
        leader.close()
        cloud.close()
