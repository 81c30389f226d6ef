"""The on-disk telemetry queue: round trip, restart, ack, bounds, torn tails, corruption."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scmr_mesh.data.errors import QueueCorruptError, QueueFullError
from scmr_mesh.data.queue import (
    HEADER,
    MAGIC,
    TelemetryQueue,
    encode_frame,
    scan_segment,
)
from scmr_mesh.errors import ScmrError

# payloads that cannot contain the frame magic by accident
payload_st = st.binary(min_size=0, max_size=40).filter(lambda b: MAGIC not in b)


def _segments(path: Path) -> list[Path]:
    return sorted(path.glob("seg-*.log"))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(payloads=st.lists(payload_st, max_size=30), seg=st.integers(20, 300), acked=st.integers(0, 35))
def test_round_trip_survives_reopen(payloads, seg, acked):
    d = Path(tempfile.mkdtemp())
    try:
        with TelemetryQueue(d, segment_bytes=seg) as q:
            seqs = [q.append(p) for p in payloads]
            assert seqs == list(range(1, len(payloads) + 1))
            q.ack(acked)
        with TelemetryQueue(d, segment_bytes=seg) as q:
            st_ = q.stats()
            assert q.pending() == [(s, p) for s, p in zip(seqs, payloads) if s > acked]
            assert st_.corruptions == [] and st_.lost_seqs == [] and st_.torn_bytes == 0
            # seqs are never reused, even when every segment but the active one is deleted
            assert q.next_seq == len(payloads) + 1
            assert q.append(b"next") == len(payloads) + 1
    finally:
        shutil.rmtree(d)


def test_ack_deletes_old_segments_but_keeps_seq_floor(tmp_path):
    with TelemetryQueue(tmp_path, segment_bytes=64) as q:
        for i in range(20):
            q.append(b"x" * 30)
        assert len(_segments(tmp_path)) > 3
        assert q.ack(20) == 20
        assert len(_segments(tmp_path)) == 1  # only the active one
        assert q.pending() == []
    with TelemetryQueue(tmp_path, segment_bytes=64) as q:
        assert q.next_seq == 21
        assert q.stats().acked_seq == 20


def test_pending_limits_and_idempotent_ack(tmp_path):
    with TelemetryQueue(tmp_path) as q:
        for i in range(10):
            q.append(bytes([i]) * 10)
        assert [s for s, _ in q.pending(limit=3)] == [1, 2, 3]
        assert [s for s, _ in q.pending(max_bytes=25)] == [1, 2]
        assert q.ack(4) == 4
        assert q.ack(4) == 0 and q.ack(2) == 0
        assert q.ack(99) == 6  # clipped to the last appended seq
        assert q.stats().acked_seq == 10


def test_full_queue_refuses_clearly_and_keeps_everything(tmp_path):
    with TelemetryQueue(tmp_path, max_bytes=100) as q:
        for _ in range(10):
            q.append(b"y" * 10)
        with pytest.raises(QueueFullError, match=r"full: 10 unacknowledged records, 100 of 100 bytes") as ei:
            q.append(b"z")
        assert isinstance(ei.value, ScmrError)
        st_ = q.stats()
        assert st_.refused == 1 and st_.depth == 10 and q.next_seq == 11
        q.ack(1)
        assert q.append(b"w" * 10) == 11  # room again, and no seq was spent on the refusal
    with TelemetryQueue(tmp_path, max_bytes=100) as q:
        assert [s for s, _ in q.pending()] == list(range(2, 12))
        assert q.stats().lost_seqs == []


def test_refusals_can_keep_their_seqs_so_the_store_sees_the_gap(tmp_path):
    """A robot's queue: a refused record keeps its seq, listed in refused_seqs and lost after a reopen."""
    with TelemetryQueue(tmp_path, max_bytes=20, refusals_use_seqs=True) as q:
        assert q.append(b"a" * 10) == 1 and q.append(b"b" * 10) == 2
        with pytest.raises(QueueFullError, match="record 3 was refused"):
            q.append(b"c" * 10, seq=3)
        q.ack(2)
        assert q.append(b"d" * 10, seq=4) == 4
        with pytest.raises(QueueFullError):
            q.append(b"e" * 20, seq=5)
        st_ = q.stats()
        assert st_.refused == 2 and st_.refused_seqs == [3, 5] and q.next_seq == 6
    with TelemetryQueue(tmp_path, max_bytes=20, refusals_use_seqs=True) as q:
        st_ = q.stats()
        assert [s for s, _ in q.pending()] == [4]
        assert st_.lost_seqs == [3, 5] and q.next_seq == 6


def test_append_with_explicit_seq(tmp_path):
    with TelemetryQueue(tmp_path) as q:
        assert q.append(b"a", seq=1) == 1
        with pytest.raises(ScmrError, match="next seq 2, got 5"):
            q.append(b"b", seq=5)


def _write(d: Path, payloads: list[bytes]) -> tuple[Path, list[int]]:
    with TelemetryQueue(d) as q:
        for p in payloads:
            q.append(p)
    (seg,) = _segments(d)
    ends, pos = [], 0
    for i, p in enumerate(payloads, 1):
        pos += len(encode_frame(i, p))
        ends.append(pos)
    assert seg.stat().st_size == pos
    return seg, ends


@settings(max_examples=60, deadline=None)
@given(payloads=st.lists(payload_st, min_size=1, max_size=8), data=st.data())
def test_appended_records_cut_off_at_any_offset_are_lost_never_reused(payloads, data):
    """Every append returned (fsynced), then the file was cut: not a torn append (issue #12, item 2)."""
    d = Path(tempfile.mkdtemp())
    try:
        seg, ends = _write(d, payloads)
        n = len(payloads)
        cut = data.draw(st.integers(0, ends[-1]), label="cut")
        with seg.open("r+b") as fh:
            fh.truncate(cut)
        whole = [i for i, e in enumerate(ends, 1) if e <= cut]
        boundary = ends[len(whole) - 1] if whole else 0
        with TelemetryQueue(d) as q:
            st_ = q.stats()
            assert [s for s, _ in q.pending()] == whole
            assert st_.torn_bytes == cut - boundary
            assert st_.corruptions == []
            assert st_.lost_seqs == list(range(len(whole) + 1, n + 1))
            assert q.next_seq == n + 1  # the cut records' seqs are never handed out again
            q.append(b"after")
        with TelemetryQueue(d) as q:  # the cut tail was repaired, the file is clean again
            assert q.stats().torn_bytes == 0
            assert [s for s, _ in q.pending()] == whole + [n + 1]
    finally:
        shutil.rmtree(d)


@settings(max_examples=40, deadline=None)
@given(payloads=st.lists(payload_st, min_size=1, max_size=8), torn=payload_st, data=st.data())
def test_a_torn_append_is_truncated_and_its_seq_reused(payloads, torn, data):
    """A crash during an append (its bytes partly written, the head not moved): nothing was handed out."""
    d = Path(tempfile.mkdtemp())
    try:
        seg, ends = _write(d, payloads)
        n = len(payloads)
        frame = encode_frame(n + 1, torn)
        part = data.draw(st.integers(1, len(frame) - 1), label="part")
        with seg.open("ab") as fh:
            fh.write(frame[:part])
        with TelemetryQueue(d) as q:
            st_ = q.stats()
            assert [s for s, _ in q.pending()] == list(range(1, n + 1))
            assert st_.torn_bytes == part and st_.lost_seqs == [] and st_.corruptions == []
            assert q.next_seq == n + 1
    finally:
        shutil.rmtree(d)


@settings(max_examples=60, deadline=None)
@given(payloads=st.lists(payload_st.filter(len), min_size=2, max_size=8), data=st.data())
def test_a_corrupted_byte_is_reported_with_the_seq_it_cost(payloads, data):
    d = Path(tempfile.mkdtemp())
    try:
        seg, ends = _write(d, payloads)
        victim = data.draw(st.integers(1, len(payloads)), label="victim")
        start = ends[victim - 2] if victim > 1 else 0
        # any byte of the record except the magic's (a bad magic is also caught, below)
        off = data.draw(st.integers(start + 4, ends[victim - 1] - 1), label="offset")
        raw = bytearray(seg.read_bytes())
        raw[off] ^= data.draw(st.integers(1, 255), label="xor")
        seg.write_bytes(bytes(raw))
        with pytest.raises(QueueCorruptError, match=str(seg)):
            TelemetryQueue(d, strict=True)
        with TelemetryQueue(d) as q:
            st_ = q.stats()
            assert len(st_.corruptions) >= 1
            assert victim in st_.lost_seqs
            survivors = [s for s, _ in q.pending()]
            assert victim not in survivors
            # every record but the victim survives (a length flip may hide later ones: all reported)
            assert set(survivors) | set(st_.lost_seqs) >= set(range(1, len(payloads) + 1))
            assert q.next_seq > max(survivors + st_.lost_seqs)
            new = q.append(b"after")
        with TelemetryQueue(d) as q:
            assert new in [s for s, _ in q.pending()]
    finally:
        shutil.rmtree(d)


def test_bad_magic_and_lost_segment_are_reported(tmp_path):
    with TelemetryQueue(tmp_path, segment_bytes=30) as q:
        for i in range(6):
            q.append(b"p" * 10)
    segs = _segments(tmp_path)
    assert len(segs) >= 3
    segs[1].unlink()  # a whole segment vanished
    with TelemetryQueue(tmp_path, segment_bytes=30) as q:
        st_ = q.stats()
        assert st_.lost_seqs == [2]
        assert [s for s, _ in q.pending()] == [1, 3, 4, 5, 6]


def test_scan_segment_pure():
    frames = encode_frame(1, b"a") + encode_frame(2, b"bb")
    recs, bad, torn = scan_segment(frames, last=True)
    assert [(s, p) for s, p, _ in recs] == [(1, b"a"), (2, b"bb")] and bad == [] and torn == len(frames)
    recs, bad, torn = scan_segment(frames[:-1], last=True)
    assert [s for s, _, _ in recs] == [1] and torn == HEADER.size + 1
    recs, bad, torn = scan_segment(frames[:-1], last=False)  # not the tail: a corruption
    assert [s for s, _, _ in recs] == [1] and bad and bad[0][0] == HEADER.size + 1


def test_unreadable_ack_file_replays_everything(tmp_path):
    with TelemetryQueue(tmp_path) as q:
        q.append(b"a")
        q.append(b"b")
        q.ack(1)
    (tmp_path / "ack").write_text("garbage")
    with TelemetryQueue(tmp_path) as q:
        assert [s for s, _ in q.pending()] == [1, 2] and q.next_seq == 3


def test_readonly_inspection_never_touches_the_files(tmp_path):
    with TelemetryQueue(tmp_path) as q:
        for _ in range(3):
            q.append(b"abc")
    seg = _segments(tmp_path)[0]
    with seg.open("ab") as fh:  # an append in progress in the robot
        fh.write(encode_frame(4, b"abc")[:10])
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with TelemetryQueue(tmp_path, readonly=True) as q:
        st_ = q.stats()
        assert [s for s, _ in q.pending()] == [1, 2, 3] and st_.torn_bytes == 10 and q.next_seq == 4
        with pytest.raises(ScmrError, match="read-only"):
            q.append(b"x")
        with pytest.raises(ScmrError, match="read-only"):
            q.ack(1)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    with pytest.raises(ScmrError, match="no telemetry queue folder"):
        TelemetryQueue(tmp_path / "absent", readonly=True)


def test_seq_ranges_compresses_runs_and_limits():
    from scmr_mesh.data.queue import seq_ranges

    assert seq_ranges([9, 1, 2, 3, 5, 6]) == ["1-3", "5-6", "9"]
    assert seq_ranges([]) == []
    assert seq_ranges([1, 3, 5, 7], limit=2) == ["1", "3"]


def test_acks_overwrite_the_ack_file_in_place(tmp_path, monkeypatch):
    """Issue 23 (CPU per request): an ack rewrites the fixed-width ``ack`` file in place and syncs it
    (one fdatasync; no ack.tmp, rename or folder fsync per ack), and what it wrote is what a restart reads,
    also after a damaged file of another width was replaced.  Fails on the old code, which renamed a new
    file over ``ack`` on every ack (its inode changed)."""
    import os

    import scmr_mesh.data.queue as qmod

    q = TelemetryQueue(tmp_path)
    for _ in range(4):
        q.append(b"x")
    q.ack(1)
    inode = (tmp_path / "ack").stat().st_ino
    synced = []
    monkeypatch.setattr(qmod.os, "fdatasync", lambda fd: synced.append(fd) or os.fsync(fd))
    for upto in (2, 3):
        q.ack(upto)
        assert (tmp_path / "ack").stat().st_ino == inode and not (tmp_path / "ack.tmp").exists()
        with TelemetryQueue(tmp_path, readonly=True) as ro:
            assert [s for s, _ in ro.pending()] == list(range(upto + 1, 5))
    assert len(synced) == 2  # every in-place ack is synced before ack() returns
    q.close()
    (tmp_path / "ack").write_text("3\n" + "#" * 40)  # damaged and wider than the format
    with TelemetryQueue(tmp_path) as q:
        assert [s for s, _ in q.pending()] == [1, 2, 3, 4]  # unreadable: replay everything
        q.ack(4)
    with TelemetryQueue(tmp_path) as q:
        assert q.pending() == [] and q.next_seq == 5


def test_a_queue_opened_and_never_used_reopens_without_an_error(tmp_path, caplog):
    """Opening creates the head file empty; a robot stopped before its first record (a fleet that
    never started) must not read as a damaged queue: 256 such errors hid a bench's real failure."""
    with TelemetryQueue(tmp_path):
        pass
    assert (tmp_path / "head").read_text() == ""
    with caplog.at_level("ERROR", logger="scmr_mesh.data.queue"):
        with TelemetryQueue(tmp_path) as q:
            assert q.next_seq == 1 and q.pending() == []
        with TelemetryQueue(tmp_path, readonly=True) as q:
            assert q.stats().lost_seqs == []
    assert not [r for r in caplog.records if r.levelname == "ERROR"], caplog.text
    (tmp_path / "head").write_text("x1")  # a damaged one is still reported
    with caplog.at_level("ERROR", logger="scmr_mesh.data.queue"):
        TelemetryQueue(tmp_path).close()
    assert "not a seq" in caplog.text
