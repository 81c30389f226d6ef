"""A robot's folder stays bounded over a long run: masks and acknowledged telemetry (issue 25 item 11). < 1 s.

Before, every mask was kept (1.7 MB and 1,200 files a minute for 4 robots at 5 Hz); now a robot keeps
the newest ``--keep-masks`` (default 1000) unless ``--keep-all``, and its telemetry queue deletes
acknowledged segments.
"""

from __future__ import annotations

from concurrent.futures import Future
from types import SimpleNamespace

from scmr_mesh.data.queue import TelemetryQueue
from scmr_mesh.data.retention import DEFAULT_KEEP_MASKS, Retention
from scmr_mesh.mesh.robot import Robot, RobotOptions


def _mask_names(folder):
    return sorted((p.name for p in folder.iterdir() if p.name.endswith(".mask.png")),
                  key=lambda n: int(n.split(".")[0]))


def test_a_robot_keeps_only_its_newest_masks_over_many_frames(tmp_path):
    robot = Robot("r1", tmp_path / "r1", options=RobotOptions(keep_masks=20))
    robot.emit_telemetry = lambda message: None  # no session: the rest of a delivery is what we look at
    winner = SimpleNamespace(body={"mask_png": b"\x89PNG-mask"})
    gone = Future()  # the outbox write's future, done: its file was never written
    gone.set_result(tmp_path / "gone")
    for seq in range(1, 501):
        robot._deliver(seq, None, {"robot": "r1", "seq": seq, "ok": True, "tier": "cloud", "tor_ms": 1.0,
                                   "mismatched": 0},
                       winner, gone)
        assert len(_mask_names(robot.inbox)) == min(seq, 20)
    robot.close()
    assert _mask_names(robot.inbox) == [f"{s}.mask.png" for s in range(481, 501)]
    assert robot.masks.deleted == 480
    # restarted with the same --out: the masks already there count (oldest seq first)
    again = Retention(robot.inbox, keep=5)
    assert _mask_names(robot.inbox) == [f"{s}.mask.png" for s in range(496, 501)] and again.deleted == 15


def test_keep_all_keeps_every_mask_and_the_default_is_bounded(tmp_path):
    assert RobotOptions().keep_masks == DEFAULT_KEEP_MASKS
    r = Retention(tmp_path, keep=None)
    for seq in range(1, 201):
        p = tmp_path / f"{seq}.mask.png"
        p.write_bytes(b"x")
        r.add(p)
    (tmp_path / "notes.txt").write_text("never touched")
    assert len(_mask_names(tmp_path)) == 200 and r.deleted == 0
    Retention(tmp_path, keep=150)
    assert len(_mask_names(tmp_path)) == 150 and (tmp_path / "notes.txt").is_file()


def test_acknowledged_telemetry_leaves_the_disk(tmp_path):
    with TelemetryQueue(tmp_path / "q", segment_bytes=4096, fsync="never") as q:
        for i in range(1, 3001):
            q.append(b"r" * 200)
            if i % 10 == 0:
                q.ack(i)
            files = list((tmp_path / "q").iterdir())
            assert sum(f.stat().st_size for f in files) < 3 * 4096 + 1024, (i, len(files))
