"""``scmr ros`` end to end with real processes: a router playing rmw_zenohd, a cloud, two bridges.

The outside ROS 2 publisher here is written from the rmw_zenoh contract, not from
scmr_mesh.ros.wire: keys, the 33-byte attachment and ``@ros2_lv`` tokens spelt out by hand,
messages serialized and read back by rosbags.  It is a Zenoh *client* of the router (configured
with rmw_zenohd's keys), as the ``ros2`` CLI or RViz on another host are: every sample through
the router to the bridges, which are peers.  It sends an ``Image`` to one bridge and a ``CompressedImage`` to the
other and gets ``mono8`` masks of the same size and stamp (and an ``rgb8`` overlay) with the
attachment; a ``bgra16`` frame and a truncated one are counted and the bridge keeps serving.
Then zenoh-ros2-sdk (tests/ros_sdk_client.py, offline) sends an Image and gets its mask, when installed.
A camera node configured as rmw_zenoh nodes are (a peer) is linked to the bridge directly.
"""

from __future__ import annotations

import json
import struct
import threading

import cv2
import numpy as np
import pytest

from scmr_mesh.mesh.testing import STUB, spawn_peer, stop_peer, wait_for
from conftest import free_port

rosbags = pytest.importorskip("rosbags.typesys")
zenoh = pytest.importorskip("zenoh")

IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"


# rmw_zenoh's own configs (rolling, read 2026-11), spelt out here rather than taken from scmr_mesh.mesh.ros:
# DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5 (rmw_zenohd) and DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5 (every node)
_RMW_GOSSIP = {"scouting/multicast/enabled": "false", "scouting/gossip/enabled": "true",
               "scouting/gossip/multihop": "false",
               "scouting/gossip/target": '{router: ["router", "peer"], peer: ["router"]}',
               "scouting/gossip/autoconnect": '{router: [], peer: ["router", "peer"]}'}
_RMW_ZENOHD = {"mode": '"router"', **_RMW_GOSSIP, "routing/router/peers_failover_brokering": "false",
               "scouting/gossip/autoconnect_strategy": '{router: {to_router: "always", to_peer: "always"}}'}
_RMW_NODE = {"mode": '"peer"', "listen/endpoints": '["tcp/localhost:0"]', **_RMW_GOSSIP,
             "scouting/gossip/autoconnect_strategy": '{peer: {to_router: "always", to_peer: "greater-zid"}}'}


def _zconf(keys: dict, **endpoints) -> "zenoh.Config":
    conf = zenoh.Config()
    for k, v in {**keys, **{f"{k}/endpoints": json.dumps(v) for k, v in endpoints.items()}}.items():
        conf.insert_json5(k, v)
    return conf


def _key(ts, topic: str, ros_type: str) -> str:
    pkg, _, name = ros_type.split("/")
    return f"0/{topic.strip('/')}/{pkg}::msg::dds_::{name}_/{ts.hash_rihs01(ros_type)}"


def _header(ts, sec: int, frame_id: str):
    T = ts.types
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=123), frame_id=frame_id)


def _image(ts, sec: int, rgb: np.ndarray, encoding: str = "rgb8") -> bytes:
    h, w = rgb.shape[:2]
    step = rgb.nbytes // h
    msg = ts.types[IMAGE](header=_header(ts, sec, "cam"), height=h, width=w, encoding=encoding, is_bigendian=0,
                          step=step, data=rgb.reshape(-1).view(np.uint8))
    return bytes(ts.serialize_cdr(msg, IMAGE))


def _compressed(ts, sec: int, rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", rgb[:, :, ::-1])
    msg = ts.types[COMPRESSED](header=_header(ts, sec, "cam"), format="jpeg", data=buf.reshape(-1))
    return bytes(ts.serialize_cdr(msg, COMPRESSED))


def _attachment(seq: int) -> bytes:
    return struct.pack("<qqB", seq, 1_700_000_000_000_000_000 + seq, 16) + bytes(range(16))


def _sdk_client(tmp_path, port: int, image_topic: str, mask_topic: str) -> dict | None:
    """Run tests/ros_sdk_client.py (zenoh-ros2-sdk as a ROS node); its JSON line, None without the SDK."""
    import importlib.util
    import subprocess
    import sys
    from pathlib import Path

    if importlib.util.find_spec("zenoh_ros2_sdk") is None:
        return None
    script = Path(__file__).with_name("ros_sdk_client.py")
    r = subprocess.run([sys.executable, str(script), str(port), str(tmp_path / "msg"), image_topic, mask_topic],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, (r.stdout + r.stderr)[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def _scene(h: int, w: int) -> np.ndarray:
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[h // 2:] = 200  # bright lower half: the stub marks it drivable
    return rgb


@pytest.mark.timeout(120)
def test_ros_publisher_gets_mono8_masks_through_the_mesh(tmp_path):
    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    cport, rport = free_port(), free_port()
    ros_ep = f"tcp/127.0.0.1:{rport}"
    procs = {}
    bridges = {"img": ("/camera/image_raw", "/drivable/mask", []),
               "cmp": ("/camera/compressed", "/drivable/cmask", ["--compressed"])}
    try:
        rmw_zenohd = [a for k, v in _RMW_ZENOHD.items() if k != "mode" for a in ("--cfg", f"{k}:{v}")]
        procs["router"] = spawn_peer(["router", "--insecure", "--listen", ros_ep, *rmw_zenohd, "--ready-file",
                                      str(tmp_path / "router.ready")], log_path=tmp_path / "router.log")
        procs["cloud"] = spawn_peer(["cloud", "--insecure", "--node", "cloud0", "--listen", f"tcp/127.0.0.1:{cport}",
                                     "--workers", "1", "--process", STUB, "--ready-file", str(tmp_path / "cloud.ready")],
                                    log_path=tmp_path / "cloud.log")
        for name, (topic, mask, extra) in bridges.items():
            procs[name] = spawn_peer(["ros", "--insecure", "--id", f"r{name}", "--connect", f"tcp/127.0.0.1:{cport}",
                                      "--ros-connect", ros_ep, "--image-topic", topic, "--mask-topic", mask, *extra,
                                      "--out", str(tmp_path / name), "--process", STUB, "--no-local-fallback",
                                      "--wait-ms", "20000", "--quiet"],
                                     log_path=tmp_path / f"{name}.log")
        wait_for((tmp_path / "router.ready").exists, timeout=30, what="the router (rmw_zenohd's stand-in)")
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([ros_ep]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        got: dict[str, list] = {m: [] for _, m, _ in bridges.values()}
        got.update({m + "/overlay": [] for _, m, _ in bridges.values()})
        tokens: set[str] = set()
        lock = threading.Condition()

        def on_mask(sample):
            topic = "/" + "/".join(str(sample.key_expr).split("/")[1:-2])
            with lock:
                got[topic].append((str(sample.key_expr), sample.payload.to_bytes(),
                                   None if sample.attachment is None else sample.attachment.to_bytes()))

        def on_token(sample):
            with lock:
                tokens.add(str(sample.key_expr))

        with zenoh.open(conf) as s:
            subs = [s.declare_subscriber(f"0/{m.strip('/')}/*/*", on_mask) for m in got]  # <type>/<hash>
            lv = s.liveliness().declare_subscriber("@ros2_lv/0/**", on_token, history=True)

            def visible(kind, topic):
                return any(t.split("/")[5] == kind and t.split("/")[9] == topic.replace("/", "%") for t in tokens)

            # the graph as `ros2 topic info` reads it: the bridges' subscriptions and publishers
            for topic, mask, _ in bridges.values():
                wait_for(lambda: visible("MS", topic) and visible("MP", mask) and visible("MP", mask + "/overlay"),
                         timeout=60, what=f"liveliness tokens of the bridge on {topic}")
            assert any(t.split("/")[5] == "NN" and t.split("/")[8] == "scmr_ros_rimg" for t in tokens)
            pubs = {n: s.declare_publisher(_key(ts, bridges[n][0], COMPRESSED if n == "cmp" else IMAGE))
                    for n in bridges}
            for p in pubs.values():
                wait_for(lambda: p.matching_status.matching, timeout=10, what="the bridge's subscription")

            def served(mask, n):
                with lock:
                    return len(got[mask]) >= n and len(got[mask + "/overlay"]) >= n

            def check_mask(mask, n, sec, h, w):
                key, payload, att = got[mask][n - 1]
                assert key == _key(ts, mask, IMAGE)
                m = ts.deserialize_cdr(payload, IMAGE)
                assert (m.encoding, m.height, m.width, m.step) == ("mono8", h, w, w)
                assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == (sec, 123, "cam")
                px = np.asarray(m.data).reshape(h, w)
                assert set(np.unique(px)) <= {0, 255} and px[-1].min() == 255 and px[0].max() == 0
                assert len(att) == 33 and att[16] == 16 and struct.unpack_from("<q", att)[0] == n
                o = ts.deserialize_cdr(got[mask + "/overlay"][n - 1][1], IMAGE)
                assert (o.encoding, o.height, o.width, o.header.stamp.sec) == ("rgb8", h, w, sec)

            pubs["img"].put(_image(ts, 41, _scene(48, 64)), attachment=_attachment(1))
            pubs["cmp"].put(_compressed(ts, 42, _scene(60, 80)), attachment=_attachment(1))
            wait_for(lambda: served("/drivable/mask", 1), timeout=30, what="the Image frame's mask")
            wait_for(lambda: served("/drivable/cmask", 1), timeout=30, what="the CompressedImage frame's mask")
            check_mask("/drivable/mask", 1, 41, 48, 64)
            check_mask("/drivable/cmask", 1, 42, 60, 80)

            # bad input: bgra16 and a body shorter than its data; then the bridge still serves
            pubs["img"].put(_image(ts, 43, np.zeros((8, 8, 4), np.uint16), encoding="bgra16"),
                            attachment=_attachment(2))
            pubs["img"].put(_image(ts, 44, _scene(48, 64))[:-100], attachment=_attachment(3))
            pubs["img"].put(_image(ts, 45, _scene(48, 64)), attachment=_attachment(4))
            wait_for(lambda: served("/drivable/mask", 2), timeout=30, what="a mask after the bad frames")
            check_mask("/drivable/mask", 2, 45, 48, 64)
            for x in (*subs, lv, *pubs.values()):
                x.undeclare()
        sdk = _sdk_client(tmp_path, rport, "/camera/image_raw", "/drivable/mask")
        rcs = {n: stop_peer(procs.pop(n)) for n in bridges}
        summaries = {n: json.loads([ln for ln in (tmp_path / f"{n}.log").read_text().splitlines()
                                    if ln.startswith("{")][-1]) for n in bridges}
        assert summaries["img"]["ros"]["rejected"] == {"encoding": 1, "truncated": 1}, summaries
        most = 2 + (sdk["sent"] if sdk else 0)  # the SDK sends again each second until it has a mask
        assert 2 + (sdk is not None) <= summaries["img"]["ros"]["served"] <= most and summaries["img"]["by_tier"]["local"] == 0
        if sdk is not None:  # a second outside client nobody here wrote
            assert sdk["mask"] == {"encoding": "mono8", "height": 30, "width": 40, "sec": 77, "frame_id": "sdk",
                                   "values": [0, 255]}
        assert rcs == {"img": 1, "cmp": 0}, [(tmp_path / f"{n}.log").read_text()[-2000:] for n in bridges]
        assert "2 sample(s) rejected" in (tmp_path / "img.log").read_text()
    finally:
        for p in procs.values():
            stop_peer(p)


def test_frames_arriving_faster_than_served_keep_only_the_newest():
    """The one-frame slot: a newer frame replaces the waiting one, each replaced frame is a drop."""
    from types import SimpleNamespace

    from scmr_mesh.mesh.ros import RosBridge

    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    robot = SimpleNamespace(id="r1", annotators=[])
    b = RosBridge(robot, None, domain=0, image_topic="/cam", mask_topic="/mask")
    key = _key(ts, "/cam", IMAGE)

    def sample(sec):
        return SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: _image(ts, sec, _scene(4, 4))))

    for sec in (1, 2, 3):
        b._on_sample(sample(sec))
    b._on_sample(SimpleNamespace(key_expr=key.rsplit("/", 1)[0] + "/RIHS01_" + "0" * 64,
                                 payload=SimpleNamespace(to_bytes=lambda: b"")))
    assert (b.stats.received, b.stats.dropped, b.stats.rejected) == (4, 2, {"type_hash": 1})
    assert b._take(threading.Event(), 0).header.sec == 3 and b._take(threading.Event(), 0) is None
    humble = key.rsplit("/", 1)[0] + "/TypeHashNotSupported"  # what rmw_zenoh on Humble sends
    b._on_sample(SimpleNamespace(key_expr=humble, payload=SimpleNamespace(to_bytes=lambda: _image(ts, 9, _scene(4, 4)))))
    assert b._take(threading.Event(), 0).header.sec == 9


def test_frames_replaced_in_the_slot_are_never_encoded_and_a_frame_that_cannot_be_made_is_counted(monkeypatch):
    """The callback only parses: of three raw frames arriving while one waits, the two replaced are never
    converted, reduced or JPEG-encoded (old code: every frame encoded in Zenoh's receive thread, so a 30 Hz
    camera behind --rate 5 cost 30 encodes a second); the one taken is encoded once, and a frame whose
    encoding fails is counted as rejected and never reaches the robot, the loop goes on."""
    from types import SimpleNamespace

    import scmr_mesh.imaging as imaging
    from scmr_mesh.mesh.ros import RosBridge

    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    encoded = []
    real = imaging.encode_jpeg
    monkeypatch.setattr(imaging, "encode_jpeg", lambda rgb, **kw: encoded.append(rgb.shape) or real(rgb, **kw))
    served = []
    robot = SimpleNamespace(id="r1", annotators=[])
    b = RosBridge(robot, None, domain=0, image_topic="/cam", mask_topic="/mask")

    def serve_one(p):
        served.append(p.header.sec)
        b.stats.served += 1
        return {"ok": True, "seq": len(served)}

    b.serve_one = serve_one
    key = _key(ts, "/cam", IMAGE)

    def sample(sec, hw=(480, 640)):
        return SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: _image(ts, sec, _scene(*hw))))

    for sec in (1, 2, 3):
        b._on_sample(sample(sec))
    assert encoded == [] and b.stats.dropped == 2  # parsed and checked only
    stop = threading.Event()
    b.run(stop, count=1)
    assert served == [3] and encoded == [(240, 320, 3)] and b.stats.rejected == {}

    def broken(rgb):
        raise MemoryError("no room for the reduced frame")

    monkeypatch.setattr("scmr_mesh.mesh.ros.reduced_for_service", broken)
    b._on_sample(sample(4))
    t = threading.Thread(target=b.run, args=(stop,))
    t.start()
    try:
        wait_for(lambda: b.stats.rejected == {"decode": 1}, timeout=10, what="the broken frame counted")
    finally:
        stop.set()
        t.join(10)
    assert not t.is_alive()
    assert served == [3] and encoded == [(240, 320, 3)] and b.stats.served == 1 and b._slot is None
    # a frame the encoder could not take (a side over JPEG's 65500 pixels) is refused on arrival:
    # the frame waiting in the slot stays (it was replaced first, then lost at encoding)
    b._on_sample(sample(5))
    b._on_sample(sample(6, hw=(1, 70000)))
    assert b.stats.rejected == {"decode": 1, "size": 1} and b._slot.header.sec == 5 and b.stats.dropped == 2
    png = RosBridge(robot, None, domain=0, image_topic="/cam", mask_topic="/mask", jpeg_quality=0)
    png._on_sample(sample(7, hw=(1, 70000)))  # PNG has no such limit: taken
    assert png.stats.rejected == {} and png._slot.header.sec == 7


def test_a_reduced_frame_still_gets_a_mask_of_the_input_size_published_before_the_record(tmp_path):
    """A 640x480 rgb8 frame goes to the mesh as the 320x240 JPEG the service would decode it at;
    the mask comes back mono8 640x480 with the input's header, published before the robot writes
    its record; the overlay is made only while subscribed (old code: a 640x480 JPEG, the mask
    published after records.jsonl was written, an overlay for every frame)."""
    from types import SimpleNamespace

    from scmr_mesh.mesh.robot import Robot, RobotOptions
    from scmr_mesh.mesh.ros import RosBridge

    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    robot = Robot("r1", tmp_path / "r1", options=RobotOptions(process=STUB))  # no session: computed locally
    b = RosBridge(robot, None, domain=0, image_topic="/cam", mask_topic="/mask")
    records = tmp_path / "r1" / "records.jsonl"
    puts = []
    b._mask_pub = SimpleNamespace(put=lambda payload: puts.append((payload, records.read_text())))
    overlays, subscribed = [], [False]
    b._overlay_pub = SimpleNamespace(put=overlays.append, matching=lambda: subscribed[0])
    pending = b._decode(_key(ts, "/cam", IMAGE), _image(ts, 41, _scene(480, 640)))
    sent = cv2.imdecode(np.frombuffer(pending.frame.data, np.uint8), cv2.IMREAD_COLOR)
    assert (pending.frame.encoding, sent.shape) == ("jpeg", (240, 320, 3))
    rec = b.serve_one(pending)
    assert rec["ok"] and rec["tier"] == "local" and b.stats.served == b.stats.published == 1
    assert overlays == [] and b.stats.overlays == 0  # nobody subscribes to the overlay: none made
    subscribed[0] = True
    b.serve_one(b._decode(_key(ts, "/cam", IMAGE), _image(ts, 42, _scene(480, 640))))
    robot.close()
    assert len(overlays) == b.stats.overlays == 1 and ts.deserialize_cdr(overlays[0], IMAGE).header.stamp.sec == 42
    assert len(puts) == 2
    payload, records_then = puts[0]
    assert records_then == "" and json.loads(records.read_text().splitlines()[0])["image"] == "/cam@41.000000123"
    m = ts.deserialize_cdr(payload, IMAGE)
    assert (m.encoding, m.height, m.width, m.step) == ("mono8", 480, 640, 640)
    assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == (41, 123, "cam")
    px = np.asarray(m.data).reshape(480, 640)
    assert set(np.unique(px)) == {0, 255} and px[-1].min() == 255 and px[0].max() == 0


def test_the_ros_mask_is_published_before_the_inbox_file_as_documented(tmp_path):
    """The mask goes out before the robot's inbox file, records and telemetry (Robot._deliver runs
    its annotators first; before, the inbox write and mask pruning came first)."""
    from types import SimpleNamespace

    from scmr_mesh.mesh.robot import Robot, RobotOptions
    from scmr_mesh.mesh.ros import RosBridge
    from scmr_mesh.mesh.testing import STUB

    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    robot = Robot("r1", tmp_path / "r1", options=RobotOptions(process=STUB))
    b = RosBridge(robot, None, domain=0, image_topic="/cam", mask_topic="/mask")
    inbox_then = []
    b._mask_pub = SimpleNamespace(put=lambda payload: inbox_then.append(sorted(p.name for p in robot.inbox.iterdir())))
    b._overlay_pub = SimpleNamespace(put=lambda payload: None, matching=lambda: False)
    try:
        rec = b.serve_one(b._decode(_key(ts, "/cam", IMAGE), _image(ts, 41, _scene(480, 640))))
    finally:
        robot.close()
    assert rec["ok"] and inbox_then == [[]], inbox_then


def test_a_reduced_ros_frame_is_never_smaller_than_the_services_working_frame():
    """Reduced sizes round up as the service's own 1/r DCT decode does (a 599x449 frame went as
    299x224 with floor division, below the service's 300x225 working frame)."""
    from scmr_mesh.mesh.ros import reduced_for_service

    for w, h in ((599, 449), (1199, 899)):
        r = reduced_for_service(np.zeros((h, w, 3), np.uint8))
        assert r.shape[1] >= 300 and r.shape[0] >= 225, (w, h, r.shape)


def _bridge_on_cam(tmp_path, ros_ep: str, rid: str, *extra: str):
    """An `scmr ros` (default --ros-mode, stub computed locally) on /cam/image_raw -> /cam/mask next to the
    router at ``ros_ep``, once ready: (its process, its ready file)."""
    from pathlib import Path

    proc = spawn_peer(["ros", "--insecure", "--id", rid, "--ros-connect", ros_ep, "--image-topic", "/cam/image_raw",
                       "--mask-topic", "/cam/mask", "--out", str(tmp_path / rid), "--process", STUB, *extra,
                       "--wait-ms", "0", "--quiet", "--ready-file", str(tmp_path / f"{rid}.ready")],
                      log_path=tmp_path / f"{rid}.log")
    ready = Path(tmp_path / f"{rid}.ready")
    wait_for(lambda: ready.exists() or proc.poll() is not None, timeout=60, what="the bridge")
    assert proc.poll() is None, (tmp_path / f"{rid}.log").read_text()[-2000:]
    return proc, ready


@pytest.mark.timeout(90)
def test_next_to_rmw_zenohd_frames_and_masks_go_node_to_node_and_survive_the_router(tmp_path):
    """As rmw_zenoh nodes do, the bridge (default --ros-mode) uses rmw_zenohd for discovery only.

    A router configured as rmw_zenohd is and a camera node configured as every rmw_zenoh node is
    (both written from rmw_zenoh's default configs above); the bridge computes locally (stub).
    Its ROS session must be linked to the camera node directly, and a frame sent after the
    router is gone must still get its mask.  Fails on the old code: its bridge was a client of
    the router, so the node had no link to it and the second frame had no path.
    """
    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    ros_ep = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(_zconf(_RMW_ZENOHD, listen=[ros_ep]))
    proc = None
    try:
        proc, ready = _bridge_on_cam(tmp_path, ros_ep, "rp", "--count", "2")
        bridge_zid = json.loads(ready.read_text())["ros_zid"]
        masks: list = []
        with zenoh.open(_zconf(_RMW_NODE, connect=[ros_ep])) as node:
            node.declare_subscriber("0/cam/mask/*/*", lambda s: masks.append(s.payload.to_bytes()))
            pub = node.declare_publisher(_key(ts, "/cam/image_raw", IMAGE))
            wait_for(lambda: pub.matching_status.matching, timeout=30, what="the bridge's subscription")
            assert bridge_zid in {str(z) for z in node.info.peers_zid()}, "the bridge is not linked to the node"
            pub.put(_image(ts, 1, _scene(48, 64)), attachment=_attachment(1))
            wait_for(lambda: len(masks) >= 1, timeout=30, what="the first mask")
            router.close()
            router = None
            wait_for(lambda: not list(node.info.routers_zid()), timeout=10, what="the node to see the router gone")
            pub.put(_image(ts, 2, _scene(48, 64)), attachment=_attachment(2))
            wait_for(lambda: len(masks) >= 2, timeout=30, what="the mask of a frame sent with no router")
        m = ts.deserialize_cdr(masks[1], IMAGE)
        assert (m.encoding, m.height, m.width, m.header.stamp.sec) == ("mono8", 48, 64, 2)
        wait_for(lambda: proc.poll() is not None, timeout=30, what="the bridge to stop after --count 2")
        assert proc.returncode == 0, (tmp_path / "rp.log").read_text()[-2000:]
    finally:
        if proc is not None:
            stop_peer(proc)
        if router is not None:
            router.close()


# rmw_zenoh's session config with shared memory turned on, as its docs tell users to do
_RMW_NODE_SHM = {**_RMW_NODE, "transport/shared_memory/enabled": "true",
                 "transport/shared_memory/transport_optimization/message_size_threshold": "512"}


@pytest.mark.timeout(90)
@pytest.mark.parametrize("flag", ["--ros-shm", "--no-ros-shm"])
def test_a_ros_node_with_shared_memory_gets_its_masks_through_shared_memory(tmp_path, flag):
    """A ROS node whose rmw_zenoh config enables shared memory exchanges frames and masks with the bridge
    through /dev/shm with ``--ros-shm``, and through the socket with ``--no-ros-shm`` (the default): the
    masks' payloads say which (``ZBytes.as_shm``).  Zenoh sends the first large message of a link
    through the socket while it sets the memory up, so frames go until one mask came through shared
    memory (at most 8).  Fails on a bridge whose ROS session always keeps scmr's mesh default (off)."""
    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    ros_ep = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(_zconf(_RMW_ZENOHD, listen=[ros_ep]))
    proc = None
    try:
        proc, _ = _bridge_on_cam(tmp_path, ros_ep, "rs", flag)
        masks: list = []
        with zenoh.open(_zconf(_RMW_NODE_SHM, connect=[ros_ep])) as node:
            node.declare_subscriber("0/cam/mask/*/*", lambda s: masks.append(
                (s.payload.as_shm() is not None, s.payload.to_bytes())))
            pub = node.declare_publisher(_key(ts, "/cam/image_raw", IMAGE))
            wait_for(lambda: pub.matching_status.matching, timeout=30, what="the bridge's subscription")
            for k in range(1, 9):
                pub.put(_image(ts, k, _scene(120, 160)), attachment=_attachment(k))
                wait_for(lambda: len(masks) >= k, timeout=30, what=f"mask {k}")
                if masks[-1][0]:
                    break
        for shm, payload in masks:
            m = ts.deserialize_cdr(payload, IMAGE)
            assert (m.encoding, m.height, m.width) == ("mono8", 120, 160)
            assert np.asarray(m.data).reshape(120, 160)[-1].min() == 255
        through_shm = [shm for shm, _ in masks]
        if flag == "--ros-shm":
            assert through_shm[-1], through_shm  # measured: from the second mask on
        else:
            assert not any(through_shm) and len(masks) == 8, through_shm
        assert stop_peer(proc) == 0, (tmp_path / "rs.log").read_text()[-2000:]
        proc = None
    finally:
        if proc is not None:
            stop_peer(proc)
        router.close()


def test_ros_mode_auto_is_peer_next_to_the_router_and_client_from_another_host():
    from scmr_mesh.mesh.ros import ros_mode_for

    assert ros_mode_for("auto", ["tcp/localhost:7447"]) == "peer"
    assert ros_mode_for("auto", ["tcp/127.0.0.1:7447", "tcp/[::1]:7447#iface=lo"]) == "peer"
    assert ros_mode_for("auto", ["tcp/127.0.0.1:7447", "tcp/192.168.1.5:7447"]) == "client"
    assert ros_mode_for("auto", ["tls/robot.local:7447"]) == "client"
    assert ros_mode_for("client", ["tcp/localhost:7447"]) == "client"
    assert ros_mode_for("peer", ["tcp/10.0.0.1:7447"]) == "peer"


def test_a_compressed_frame_is_sized_from_its_header_not_decoded(tmp_path):
    """A CompressedImage goes to the mesh as it is and its size comes from the JPEG header: its
    pixels are not decoded on the way in (old code: a full decode of every frame, 2-3 ms at
    640x480, rgb set here); a JPEG cut before its end marker is still rejected."""
    from scmr_mesh.mesh.robot import Robot, RobotOptions
    from scmr_mesh.mesh.ros import RosBridge
    from scmr_mesh.ros.wire import RosWireError

    ts = rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)
    robot = Robot("r1", tmp_path / "r1", options=RobotOptions(process=STUB))
    try:
        b = RosBridge(robot, None, domain=0, image_topic="/cam", mask_topic="/mask", compressed=True)
        key = _key(ts, "/cam", COMPRESSED)
        payload = _compressed(ts, 7, _scene(48, 64))
        p = b._decode(key, payload)
        assert (p.height, p.width, p.frame.encoding, p.frame.rgb) == (48, 64, "jpeg", None)
        assert p.frame.pixels().shape == (48, 64, 3)  # decoded when the overlay or --mcap asks
        ok, jpg = cv2.imencode(".jpg", _scene(48, 64))
        cut = ts.types[COMPRESSED](header=_header(ts, 8, "cam"), format="jpeg", data=jpg.reshape(-1)[:-40])
        with pytest.raises(RosWireError) as exc:
            b._decode(key, bytes(ts.serialize_cdr(cut, COMPRESSED)))
        assert exc.value.reason == "encoding", exc.value
    finally:
        robot.close()
