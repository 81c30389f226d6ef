"""The local data buffer: snapshot/delta, idempotent merge, scheduled sync."""

from __future__ import annotations

import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scmr_mesh.data.buffer import (
    BufferSync,
    DataBuffer,
    decode_batch,
    results_key,
    state_key,
)
from scmr_mesh.errors import WireError

ops_st = st.lists(
    st.tuples(st.sampled_from(["put", "delete"]), st.sampled_from(["maps/a", "params/b", "state/r1", "x"]),
              st.integers(0, 50), st.integers(-5, 5)),
    max_size=30,
)


def _apply(buf: DataBuffer, ops) -> None:
    for op, key, order, value in ops:
        if op == "put":
            buf.put(key, value, order=order)
        else:
            buf.delete(key, order=order)


def _view(buf: DataBuffer) -> dict:
    return {k: (e.value, e.stamp, e.deleted) for k in ("maps/a", "params/b", "state/r1", "x")
            if (e := buf.entry(k)) is not None}


@settings(max_examples=60, deadline=None)
@given(a=ops_st, b=ops_st, order=st.permutations(range(4)))
def test_merge_is_idempotent_and_order_free(a, b, order):
    src_a, src_b = DataBuffer("cloud"), DataBuffer("leader")
    _apply(src_a, a)
    _apply(src_b, b)
    batches = [src_a.snapshot(), src_b.snapshot(), src_a.snapshot(), src_b.delta(0)]
    one, two = DataBuffer("x"), DataBuffer("y")
    for i in order:
        one.merge(batches[i])
    for blob in batches[:2]:
        two.merge(blob)
    assert _view(one) == _view(two)
    # a second pass changes nothing
    assert all(one.merge(blob).applied == 0 for blob in batches)
    # the winner of each key is the greatest stamp among both sources
    for key, (value, stamp, deleted) in _view(one).items():
        cands = [e for s in (src_a, src_b) if (e := s.entry(key)) is not None]
        best = max(cands, key=lambda e: e.stamp)
        assert (value, stamp, deleted) == (best.value, best.stamp, best.deleted)


@settings(max_examples=40, deadline=None)
@given(first=ops_st, second=ops_st)
def test_delta_plus_earlier_snapshot_equals_full_snapshot(first, second):
    src = DataBuffer("cloud")
    _apply(src, first)
    replica = DataBuffer("leader")
    r = replica.merge(src.snapshot())
    _apply(src, second)
    d = decode_batch(src.delta(r.source_rev, epoch=r.source_epoch))
    assert not d["full"] or r.source_rev == 0
    replica.merge(src.delta(r.source_rev, epoch=r.source_epoch))
    full = DataBuffer("other")
    full.merge(src.snapshot())
    assert _view(replica) == _view(full)


def test_delta_is_small_and_epoch_change_gives_snapshot():
    src = DataBuffer("cloud")
    for i in range(10):
        src.put(f"maps/m{i}", i)
    rev = src.rev
    src.put("maps/m3", 33)
    d = decode_batch(src.delta(rev, epoch=src.epoch))
    assert not d["full"] and [e[0] for e in d["entries"]] == ["maps/m3"]
    d = decode_batch(src.delta(rev, epoch="another-epoch"))
    assert d["full"] and len(d["entries"]) == 10


def test_telemetry_updates_state_by_seq_and_recent_results():
    buf = DataBuffer("cloud")
    for seq in (2, 1, 3, 3):
        buf.record_telemetry({"robot": "r1", "seq": seq, "t_unix_ns": seq, "results": {"frames": seq}}, keep=2)
    assert buf.get(state_key("r1"))["seq"] == 3  # an older seq arriving late does not win
    assert [r["seq"] for r in buf.get(results_key("r1"))] == [2, 3]
    assert set(buf.query("state/**")) == {"state/r1"}
    assert buf.query("nothing/here") == {}


def test_scheduled_sync_pulls_deltas_and_survives_failures():
    cloud, leader = DataBuffer("cloud"), DataBuffer("leader")
    cloud.put("params/speed", 1.0)
    up = {"ok": True}
    calls = []

    def fetch(epoch, since):
        calls.append((epoch, since))
        return cloud.delta(since, epoch=epoch) if up["ok"] else None

    sync = BufferSync(leader, fetch, period_s=0.01)
    assert sync.pull_once().full
    cloud.put("params/speed", 2.0)
    up["ok"] = False
    assert sync.pull_once() is None and sync.stats.failures == 1
    assert leader.get("params/speed") == 1.0  # the leader keeps serving its last copy
    up["ok"] = True
    res = sync.pull_once()
    assert not res.full and res.applied == 1 and leader.get("params/speed") == 2.0
    assert calls[-1] == (cloud.epoch, 1)
    # background: pulls keep coming at the configured period
    done = threading.Event()
    cloud.put("maps/m", [1, 2])

    def fetch_bg(epoch, since):
        blob = fetch(epoch, since)
        if leader.get("maps/m") is not None:
            done.set()
        return blob

    sync.fetch = fetch_bg
    sync.start()
    try:
        assert done.wait(10)
    finally:
        sync.stop()
    assert leader.get("maps/m") == [1, 2]


def test_bad_batches_and_keys_are_rejected():
    buf = DataBuffer("x")
    with pytest.raises(WireError, match="format 'scmr-buffer/1'"):
        buf.merge(b"\x80")
    with pytest.raises(WireError, match="not msgpack"):
        buf.merge(b"\xc1")
    with pytest.raises(WireError, match="relative path"):
        buf.put("/abs", 1)
    with pytest.raises(WireError, match="period"):
        BufferSync(buf, lambda e, s: None, period_s=0)
