"""Storage faults under the telemetry queue: a real full tmpfs and an immutable segment file.

Issue #12, item 1: a failed append must leave the segment exactly as it was
before the call (no bytes left in a write buffer that land later under
another seq), the record is refused with its seq, the robot keeps sending
frames, and the loss shows in ``telemetry.json``, the robot's output and its
exit status.  The tests mount their own small tmpfs (root; unmounted in a
``finally``) and use ``chattr +i``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import free_port

from scmr_mesh.data.errors import QueueWriteError
from scmr_mesh.data.queue import TelemetryQueue
from scmr_mesh.mesh.data_service import TelemetryAgent
from scmr_mesh.mesh.testing import STUB

pytestmark = [
    pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0,
                       reason="mounting a tmpfs and chattr +i need root; CI runs as root"),
    pytest.mark.skipif(shutil.which("chattr") is None, reason="needs chattr (e2fsprogs)"),
]

PAGE = 4096


@contextlib.contextmanager
def full_tmpfs(where: Path, *, free_pages: int, size_kb: int = 256):
    """A tmpfs of ``size_kb`` mounted at ``where``, filled up to ``free_pages`` free pages."""
    where.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(where)], check=True)
    try:
        filler = where / "filler"
        fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
        try:
            while True:
                try:
                    os.write(fd, b"\0" * PAGE)
                except OSError:  # ENOSPC: full
                    break
            os.ftruncate(fd, max(0, os.fstat(fd).st_size - free_pages * PAGE))
        finally:
            os.close(fd)
        yield filler
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def _segment(qdir: Path) -> Path:
    return sorted(qdir.glob("seg-*.log"))[-1]


def test_a_full_file_system_leaves_the_segment_unchanged_and_nothing_lands_later(tmp_path):
    with full_tmpfs(tmp_path / "mnt", free_pages=3) as filler:
        qdir = tmp_path / "mnt" / "q"
        q = TelemetryQueue(qdir, refusals_use_seqs=True)
        accepted: dict[int, bytes] = {}
        refused: list[int] = []
        for i in range(60):
            payload = bytes([i]) * 700  # a record now and then spans a page boundary: partial writes
            seg = _segment(qdir)
            before = seg.read_bytes()
            seq = q.next_seq
            try:
                assert q.append(payload, seq=seq) == seq
                accepted[seq] = payload
            except QueueWriteError as exc:
                assert "could not be written" in str(exc) and "No space left" in str(exc)
                assert seg.read_bytes() == before, f"record {seq}: the failed append changed the segment"
                refused.append(seq)
        assert accepted and refused
        st = q.stats()
        assert st.refused == len(refused) and st.refused_seqs == refused and q.next_seq == 61
        filler.unlink()  # space comes back: nothing of the refused records may land now
        accepted[61] = b"after"
        assert q.append(b"after", seq=61) == 61
        q.close()
        with TelemetryQueue(qdir, refusals_use_seqs=True) as q2:
            st2 = q2.stats()
            assert dict(q2.pending()) == accepted  # every acknowledged append reads back as written
            assert st2.corruptions == [] and st2.torn_bytes == 0
            assert st2.lost_seqs == refused and q2.next_seq == 62


def test_an_immutable_segment_refuses_cleanly_and_recovers(tmp_path):
    q = TelemetryQueue(tmp_path / "q")
    assert q.append(b"one") == 1
    seg = _segment(tmp_path / "q")
    before = seg.read_bytes()
    subprocess.run(["chattr", "+i", str(seg)], check=True)
    try:
        for _ in range(3):
            with pytest.raises(QueueWriteError, match="record 2 could not be written"):
                q.append(b"two")
        assert seg.read_bytes() == before
        assert q.stats().refused == 3 and q.next_seq == 2  # the relay's kind of queue: no seq spent
    finally:
        subprocess.run(["chattr", "-i", str(seg)], check=True)
    assert q.append(b"three") == 2
    q.close()
    with TelemetryQueue(tmp_path / "q") as q2:
        assert q2.pending() == [(1, b"one"), (2, b"three")] and q2.stats().corruptions == []


def _robot_stub(rid: str = "r1"):
    return SimpleNamespace(id=rid, _session=None, publish_telemetry=lambda m: None, add_telemetry_handler=lambda fn: None,
                           remove_telemetry_handler=lambda fn: None,
                           view=SimpleNamespace(snapshot=lambda local=False: SimpleNamespace(cloud=(), leader=())))


def _message(i: int) -> dict:
    return {"robot": "r1", "seq": i, "t_unix_ns": i, "pose": {"x": 0.0, "y": 1.0, "theta": 0.0},
            "battery": 0.5, "health": "ok", "results": {"requests": i}}


def test_the_agent_counts_an_unwritable_record_as_refused_with_its_seq(tmp_path):
    agent = TelemetryAgent(_robot_stub(), tmp_path / "q", autostart=False)
    assert agent.publish(_message(1)) == 1
    seg = _segment(tmp_path / "q")
    subprocess.run(["chattr", "+i", str(seg)], check=True)
    try:
        assert agent.publish(_message(2)) == 2  # refused by the disk, never raised: kept in memory
        assert agent.publish(_message(3)) == 3
    finally:
        subprocess.run(["chattr", "-i", str(seg)], check=True)
    assert agent.publish(_message(4)) == 4
    out = agent.close(drain_s=0, summary_path=tmp_path / "telemetry.json")
    # no store took them: the two records die in memory with the agent
    assert out["sent"] == 4 and out["refused"] == 2 and out["refused_seqs"] == ["2-3"] and out["lost"] == 2
    assert out["memory"]["unsent"] == 2 and out["dropped"] == 0
    assert "Operation not permitted" in out["error"]
    assert json.loads((tmp_path / "telemetry.json").read_text())["refused"] == 2


def test_a_robot_on_a_full_disk_keeps_sending_and_reports_the_loss(tmp_path):
    """The issue's reproduction: the queue on a nearly full tmpfs, no tier storing anything."""
    with full_tmpfs(tmp_path / "mnt", free_pages=3):
        qdir = tmp_path / "mnt" / "q"
        out_dir = tmp_path / "r1"
        dead = f"tcp/127.0.0.1:{free_port()}"
        p = subprocess.run([sys.executable, "-m", "scmr_mesh", "robot", "--insecure", "--id", "r1", "--synthetic", "stub",
                            "--process", STUB, "--out", str(out_dir), "--connect", dead, "--count", "60",
                            "--rate", "200", "--wait-ms", "0", "--quiet", "--telemetry-queue", str(qdir)],
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 1, p.stderr
        assert "internal error" not in p.stderr and "Traceback" not in p.stderr
        # one error line (zenoh's threads may still log a line after it while the session closes)
        errors = [ln for ln in p.stderr.splitlines() if ln.startswith("scmr: error: ")]
        assert len(errors) == 1, p.stderr
        assert errors[0].startswith("scmr: error: robot r1: ") and "telemetry records lost" in errors[0]
        assert "No space left on device" in errors[0]
        records = (out_dir / "records.jsonl").read_text().splitlines()
        assert len(records) == 60  # every frame was still sent (and served locally)
        s = json.loads((out_dir / "telemetry.json").read_text())
        assert s["sent"] == 60 and s["refused"] > 0 and s["queued"] > 0
        assert s["queued"] + s["refused"] == 60 and s["lost"] == s["refused"]
        summary = json.loads(p.stdout.strip().splitlines()[-1])
        assert summary["telemetry"]["lost"] == s["refused"]
        with TelemetryQueue(qdir, readonly=True) as q:  # what is on disk is intact
            st = q.stats()
            assert st.corruptions == [] and st.torn_bytes == 0 and st.depth == s["queued"]


def _cloud_stub(rid: str = "r1"):
    """A robot stub that sees cloud node c0 alive, and the seqs that cloud stored (an ack for each batch)."""
    from scmr_mesh.data.record import decode_records

    robot = _robot_stub(rid)
    robot.view = SimpleNamespace(snapshot=lambda local=False: SimpleNamespace(cloud=("c0",), leader=()))
    stored: list[int] = []

    def ask(key, payload):
        recs = decode_records(payload)
        stored.extend(r.seq for r in recs)
        # a cloud's ack names the digest it holds for each record (the robot deletes only its own)
        return "ok", {"acked": len(recs), "digests": [r.digest().hex() for r in recs]}

    return robot, ask, stored


def test_a_full_disk_with_a_live_store_delivers_from_memory_and_drops_only_beyond_its_bound(tmp_path):
    """Issue #25 item 2: the queue on a real, completely full tmpfs while a cloud acknowledges.

    Every record goes to the cloud from the memory buffer (before: refused with its seq, never sent, counted
    lost); once the memory bound is hit too, the rest are dropped and counted, and only those are lost.
    """
    with full_tmpfs(tmp_path / "mnt", free_pages=0):
        robot, ask, stored = _cloud_stub()
        agent = TelemetryAgent(robot, tmp_path / "mnt" / "q", autostart=False, memory_bytes=1500)
        agent._ask = ask
        for i in range(1, 11):
            assert agent.publish(_message(i)) == i  # written nowhere on disk, kept in memory
            assert agent.flush_once() == 1
        assert stored == list(range(1, 11))
        s = agent.summary()
        assert s["refused"] == 10 and s["memory"]["delivered"] == 10 and s["lost"] == 0 and s["dropped"] == 0
        # no store now: the memory buffer fills up to its bound, then records are dropped and counted
        robot.view = SimpleNamespace(snapshot=lambda local=False: SimpleNamespace(cloud=(), leader=()))
        kept = [agent.publish(_message(i)) for i in range(11, 41)]
        held = [k for k in kept if k is not None]
        assert 0 < len(held) < 30 and kept[:len(held)] == held  # the oldest are kept, the rest dropped
        s = agent.summary()
        assert s["dropped"] == 30 - len(held) and s["memory"]["unsent"] == len(held)
        robot.view = SimpleNamespace(snapshot=lambda local=False: SimpleNamespace(cloud=("c0",), leader=()))
        while agent.flush_once():
            pass
        assert stored == list(range(1, 11)) + held
        out = agent.close(drain_s=0, summary_path=None)
        assert out["sent"] == 40 and out["lost"] == out["dropped"] == 30 - len(held) and out["memory"]["unsent"] == 0


def test_records_a_store_took_from_memory_on_a_full_disk_are_not_lost_after_a_restart(tmp_path):
    """A review of issue 25 item 2: the ack file was written as a new file and renamed, which a full disk
    refused; a restart then counted every record delivered from memory as lost (and the robot exited 1)."""
    with full_tmpfs(tmp_path / "mnt", free_pages=8) as filler:
        robot, ask, stored = _cloud_stub()
        agent = TelemetryAgent(robot, tmp_path / "mnt" / "q", autostart=False)
        agent._ask = ask
        fd = os.open(filler, os.O_WRONLY | os.O_APPEND)  # now the disk fills up
        try:
            while True:
                os.write(fd, b"\0" * PAGE)
        except OSError:
            pass
        finally:
            os.close(fd)
        for i in range(1, 31):
            assert agent.publish(_message(i)) == i
            assert agent.flush_once() == 1
        assert stored == list(range(1, 31)) and agent.summary()["refused"] > 0
        agent.close(drain_s=0, summary_path=None)
        with TelemetryQueue(tmp_path / "mnt" / "q", readonly=True) as q:  # the robot restarts
            st = q.stats()
        assert st.lost_seqs == [] and st.acked_seq == 30 and st.depth == 0 and st.next_seq == 31  # no seq reused


def test_the_flusher_sends_a_period_of_records_in_one_batch_and_close_drains_at_once(tmp_path):
    """Issue 23 (CPU per request): after a batch, the records made during the next flush period wait
    (queued on disk) and go in one query and one ack, not one each; close() sends them without waiting for
    the period.  Fails on the old code (no flush_period_s: one query per record)."""
    import threading

    from scmr_mesh.data.record import decode_batch

    robot = _robot_stub()
    robot.view = SimpleNamespace(snapshot=lambda local=False: SimpleNamespace(cloud=("c0",), leader=()))
    batches: list[list[int]] = []
    sent = threading.Event()

    def ask(key, payload):
        recs, _ = decode_batch(payload)
        batches.append([r.seq for r in recs])
        sent.set()
        return "ok", {"digests": [r.digest().hex() for r in recs]}

    agent = TelemetryAgent(robot, tmp_path / "q", autostart=False, flush_period_s=3600)
    agent._ask = ask
    agent._thread.start()
    agent.publish(_message(1))
    assert sent.wait(30)  # the first record goes at once
    for i in (2, 3, 4):
        agent.publish(_message(i))  # queued (on disk) and waiting for the period
    assert batches == [[1]] and [s for s, _ in agent.queue.pending()] == [2, 3, 4]
    out = agent.close(drain_s=30)
    assert batches == [[1], [2, 3, 4]] and out["queued"] == 0 and out["lost"] == 0 and out["acked_by"]["cloud"] == 4
