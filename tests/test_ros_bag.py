"""``scmr robot --bag``: ROS 2 recordings written by rosbags (SQLite and MCAP storage) replayed as a camera."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from scmr_mesh.errors import InputError
from scmr_mesh.mesh.frames import frames_from_args

rosbags = pytest.importorskip("rosbags.rosbag2")
typesys = pytest.importorskip("rosbags.typesys")
pytest.importorskip("mcap")


def _write(path, storage, *, compressed=False):
    ts = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    T = ts.types
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[3:] = 200
    with rosbags.Writer(path, version=9, storage_plugin=storage) as w:
        if compressed:
            import cv2

            ros_type = "sensor_msgs/msg/CompressedImage"
            conn = w.add_connection("/cam", ros_type, typestore=ts)
            jpg = cv2.imencode(".jpg", rgb)[1].reshape(-1)
            msgs = [T[ros_type](header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=s, nanosec=0),
                                                                 frame_id="c"), format="jpeg", data=jpg)
                    for s in (1, 2)]
        else:
            ros_type = "sensor_msgs/msg/Image"
            conn = w.add_connection("/cam", ros_type, typestore=ts)
            w.add_connection("/odom", "std_msgs/msg/String", typestore=ts)

            def img(sec, enc, px):
                return T[ros_type](header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=5),
                                                                    frame_id="c"),
                                   height=6, width=8, encoding=enc, is_bigendian=0, step=px.nbytes // 6,
                                   data=px.reshape(-1).view(np.uint8))
            msgs = [img(1, "rgb8", rgb), img(2, "bgra16", np.zeros((6, 8, 4), np.uint16)), img(3, "rgb8", rgb)]
        for i, m in enumerate(msgs):
            w.write(conn, 1000 + i, ts.serialize_cdr(m, ros_type))


@pytest.mark.parametrize("storage", ["SQLITE3", "MCAP"])
def test_bag_replays_images_skipping_what_is_not_one(tmp_path, storage, caplog):
    bag = tmp_path / "bag"
    _write(bag, getattr(rosbags.StoragePlugin, storage))
    frames = list(itertools.islice(frames_from_args(None, None, bag=str(bag), topic="/cam"), 4))
    assert [f.name for f in frames] == ["/cam@1.000000005", "/cam@3.000000005"] * 2  # cycled; bgra16 skipped
    assert frames[0].encoding == "jpeg" and frames[0].rgb.shape == (6, 8, 3)
    assert sum("skipped (encoding)" in r.message for r in caplog.records) == 1  # logged once, not per pass


def test_compressed_mcap_sent_as_recorded(tmp_path):
    _write(tmp_path / "c", rosbags.StoragePlugin.MCAP, compressed=True)
    mcap_file = next((tmp_path / "c").glob("*.mcap"))
    f = next(frames_from_args(None, None, bag=str(mcap_file), topic="/cam"))
    assert (f.name, f.encoding, f.data[:2]) == ("/cam@1.000000000", "jpeg", b"\xff\xd8")


def test_bad_bag_flags_are_one_line(tmp_path):
    _write(tmp_path / "b", rosbags.StoragePlugin.SQLITE3)
    with pytest.raises(InputError, match="its image topics: /cam"):
        frames_from_args(None, None, bag=str(tmp_path / "b"), topic="/camera/image_raw")
    with pytest.raises(InputError, match="std_msgs/msg/String, not sensor_msgs/msg/Image"):
        frames_from_args(None, None, bag=str(tmp_path / "b"), topic="/odom")
    with pytest.raises(InputError, match="--bag needs --topic"):
        frames_from_args(None, None, bag=str(tmp_path / "b"))
    with pytest.raises(InputError, match="no .db3 or .mcap"):
        frames_from_args(None, None, bag=str(tmp_path), topic="/cam")


def test_mcap_schemas_equal_rosbags_msgdefs():
    from scmr_mesh.ros.record import MSGDEFS

    ts = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    for ros_type, text in MSGDEFS.items():
        assert ts.generate_msgdef(ros_type, ros_version=2)[0] == text


@pytest.mark.timeout(120)
def test_robot_replays_a_bag_into_an_mcap_that_mcaps_own_reader_decodes(tmp_path):
    """`scmr robot --bag B --mcap F` (a process, local stub pipeline): F read back by mcap + mcap-ros2-support."""
    import subprocess
    import sys

    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    _write(tmp_path / "bag", rosbags.StoragePlugin.SQLITE3)
    out = tmp_path / "run.mcap"
    r = subprocess.run([sys.executable, "-m", "scmr_mesh", "robot", "--id", "r1", "--insecure", "--bag",
                        str(tmp_path / "bag"), "--topic", "/cam", "--count", "3", "--rate", "100", "--wait-ms", "0",
                        "--out", str(tmp_path / "out"), "--process", "scmr_mesh.mesh.testing:stub_process",
                        "--mcap", str(out), "--quiet"], capture_output=True, text=True, timeout=100)
    assert r.returncode == 0, r.stderr[-2000:]
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        got = [(ch.topic, schema.name, msg) for schema, ch, _m, msg in reader.iter_decoded_messages()]
    assert [(t, s) for t, s, _ in got] == [("/r1/camera/compressed", "sensor_msgs/msg/CompressedImage"),
                                           ("/r1/drivable/mask", "sensor_msgs/msg/Image")] * 3
    frame, mask = got[0][2], got[1][2]
    assert frame.format == "jpeg" and bytes(frame.data[:2]) == b"\xff\xd8"
    assert (mask.encoding, mask.height, mask.width, mask.header.frame_id) == ("mono8", 6, 8, "r1")
    stamp = (frame.header.stamp.sec, frame.header.stamp.nanosec)
    assert set(bytes(mask.data)) == {0, 255} and (mask.header.stamp.sec, mask.header.stamp.nanosec) == stamp


def test_fleet_mcap_robots_record_and_the_run_merges_them(tmp_path):
    """`scmr up --mcap F`: each robot gets --mcap RUN/mcap/<robot>.mcap; the files merge in log-time order."""
    from pathlib import Path

    from mcap.reader import make_reader

    from scmr_mesh.ros.record import McapRecorder, merge
    from scmr_mesh.scenario.plan import RunOptions, peer_command
    from scmr_mesh.scenario.spec import parse_scenario

    sc = parse_scenario({"name": "t", "seed": 3, "duration_s": 5, "fleet": {"robots": [{"id": "r1", "synthetic": "road"}]}})
    argv = peer_command(sc, "r1", run_dir=Path("run"), connect=[], options=RunOptions(mcap_dir="run/mcap")).argv
    assert argv[argv.index("--mcap") + 1] == "run/mcap/r1.mcap"
    assert "--mcap" not in peer_command(sc, "r1", run_dir=Path("run"), connect=[]).argv

    rgb = np.zeros((4, 6, 3), np.uint8)
    for rid, times in (("r1", (10, 30)), ("r2", (20, 40))):
        rec = McapRecorder(tmp_path / f"{rid}.mcap", rid)
        for t in times:
            rec.observe({"sent_unix_ns": t - 5, "received_unix_ns": t}, rgb, np.full((2, 3), 255, np.uint8))
        rec.close()
    n = merge(sorted(tmp_path.glob("r*.mcap")), tmp_path / "all.mcap")
    with open(tmp_path / "all.mcap", "rb") as f:
        got = [(c.topic, m.log_time) for _s, c, m in make_reader(f).iter_messages()]
    assert n == 8 and [t for _, t in got] == [10, 10, 20, 20, 30, 30, 40, 40]
    assert {c for c, _ in got} == {"/r1/camera/compressed", "/r1/drivable/mask", "/r2/camera/compressed",
                                   "/r2/drivable/mask"}


def test_a_robot_killed_mid_recording_is_left_out_of_the_merge_and_named(tmp_path):
    """A SIGKILLed robot's MCAP has no chunks or summary: before, the whole merge failed (no FILE, exit 0)."""
    from scmr_mesh.ros.record import McapRecorder, merge, readable
    from scmr_mesh.scenario.report import run_problems

    rec = McapRecorder(tmp_path / "r1.mcap", "r1")
    rec.observe({"sent_unix_ns": 5, "received_unix_ns": 10}, np.zeros((4, 6, 3), np.uint8),
                np.full((2, 3), 255, np.uint8))
    rec.close()
    (tmp_path / "r2.mcap").write_bytes((tmp_path / "r1.mcap").read_bytes()[:30])  # killed before its chunk
    good, bad = readable(sorted(tmp_path.glob("r*.mcap")))
    assert good == [tmp_path / "r1.mcap"] and list(bad) == [str(tmp_path / "r2.mcap")]
    assert merge(good, tmp_path / "all.mcap") == 2
    problems = run_problems({"mcap": {"path": "all.mcap", "parts": 2, "messages": 2, "unreadable": bad,
                                      "error": None}, "telemetry": {"lost": 0}})
    assert len(problems) == 1 and "r2.mcap could not be read" in problems[0]
