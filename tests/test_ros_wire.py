"""The rmw_zenoh wire contract (scmr_mesh.ros.wire) checked against code nobody here wrote: rosbags.

CDR bytes must equal rosbags' serializer byte for byte (padding after odd-length strings and
after ``is_bigendian`` included), rosbags' bytes must decode, the RIHS01 hashes must equal what
rosbags computes, and untrusted input must fail with a typed, counted reason.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from scmr_mesh.errors import InputError
from scmr_mesh.ros import wire as rw

rosbags = pytest.importorskip("rosbags.typesys")


@pytest.fixture(scope="module")
def ts():
    return rosbags.get_typestore(rosbags.Stores.ROS2_JAZZY)


def _rb_header(ts, h: rw.Header):
    T = ts.types
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=h.sec, nanosec=h.nanosec),
                                    frame_id=h.frame_id)


def _rb_image(ts, img: rw.Image):
    return ts.types[rw.IMAGE](header=_rb_header(ts, img.header), height=img.height, width=img.width,
                              encoding=img.encoding, is_bigendian=img.is_bigendian, step=img.step,
                              data=np.frombuffer(img.data, np.uint8))


# frame_id and encoding lengths chosen so every alignment case occurs (0..3 bytes of padding)
@pytest.mark.parametrize("frame_id,encoding,h,w", [("", "rgb8", 2, 3), ("cam", "mono8", 3, 5),
                                                    ("camera_optical", "bgr8", 1, 1), ("ab", "rgba8", 4, 2)])
def test_image_cdr_equals_rosbags_both_ways(ts, frame_id, encoding, h, w):
    c = rw.ENCODING_CHANNELS[encoding]
    data = bytes(range(256)) * (h * w * c // 256 + 1)
    img = rw.Image(rw.Header(-5, 999_999_999, frame_id), h, w, encoding, 0, w * c, data[: h * w * c])
    ours = rw.encode_image(img)
    theirs = bytes(ts.serialize_cdr(_rb_image(ts, img), rw.IMAGE))
    assert ours == theirs
    assert rw.decode_image(theirs) == img


def test_compressed_cdr_equals_rosbags_both_ways(ts):
    jpeg = b"\xff\xd8\xff\xe0" + bytes(37)
    img = rw.CompressedImage(rw.Header(1700000000, 5, "c"), "jpeg", jpeg)
    msg = ts.types[rw.COMPRESSED_IMAGE](header=_rb_header(ts, img.header), format="jpeg",
                                       data=np.frombuffer(jpeg, np.uint8))
    theirs = bytes(ts.serialize_cdr(msg, rw.COMPRESSED_IMAGE))
    assert rw.encode_compressed(img) == theirs
    assert rw.decode_compressed(theirs) == img
    back = ts.deserialize_cdr(rw.encode_compressed(img), rw.COMPRESSED_IMAGE)
    assert back.format == "jpeg" and bytes(back.data) == jpeg


def test_type_hashes_equal_rosbags(ts):
    for ros_type, h in rw.TYPE_HASHES.items():
        assert ts.hash_rihs01(ros_type) == h


def test_data_keys():
    key = rw.topic_key(0, "/camera/image_raw", rw.IMAGE)
    assert key == "0/camera/image_raw/sensor_msgs::msg::dds_::Image_/" + rw.TYPE_HASHES[rw.IMAGE]
    assert rw.subscribe_key(3, "/cam/", rw.COMPRESSED_IMAGE) == "3/cam/sensor_msgs::msg::dds_::CompressedImage_/*"
    k = rw.parse_topic_key("7/a/b/c/sensor_msgs::msg::dds_::Image_/" + rw.HUMBLE_HASH)
    assert (k.domain, k.topic, k.dds_type, k.type_hash) == (7, "/a/b/c", "sensor_msgs::msg::dds_::Image_",
                                                            rw.HUMBLE_HASH)
    with pytest.raises(rw.RosWireError) as e:
        rw.parse_topic_key("scmr/alive/robot/r1")
    assert e.value.reason == "key"
    for bad in ("camera", "/9cam", "/a//b", "/a/", "/a b"):
        with pytest.raises(InputError, match="/camera/image_raw"):
            rw.check_topic(bad)


def test_liveliness_tokens_round_trip():
    zid = "1f2e3d"
    node = rw.node_token(0, zid, 4, "scmr_ros_r1")
    assert node == "@ros2_lv/0/1f2e3d/4/4/NN/%/%/scmr_ros_r1"
    pub = rw.entity_token(0, zid, 4, 6, rw.PUBLISHER, "scmr_ros_r1", "/drivable/mask", rw.IMAGE)
    assert pub == ("@ros2_lv/0/1f2e3d/4/6/MP/%/%/scmr_ros_r1/%drivable%mask/sensor_msgs::msg::dds_::Image_/"
                   + rw.TYPE_HASHES[rw.IMAGE] + "/::,10:,:,:,,")
    t = rw.parse_token(pub)
    assert (t.kind, t.node, t.topic, t.namespace, t.type_hash) == ("MP", "scmr_ros_r1", "/drivable/mask", "/",
                                                                   rw.TYPE_HASHES[rw.IMAGE])
    assert rw.parse_token(node).topic is None
    assert len(rw.gid_of(pub)) == 16 and rw.gid_of(pub) != rw.gid_of(node)


def test_attachment_33_bytes():
    gid = bytes(range(16))
    a = rw.Attachment(7, 1_700_000_000_123_456_789, gid)
    b = a.encode()
    assert len(b) == 33 and b[:8] == struct.pack("<q", 7) and b[16] == 16 and b[17:] == gid
    assert rw.decode_attachment(b) == a
    for bad in (None, b[:32], b[:16] + b"\x18" + b[17:]):
        with pytest.raises(rw.RosWireError) as e:
            rw.decode_attachment(bad)
        assert e.value.reason == "attachment"


def _image_bytes(h=2, w=2, encoding="rgb8", step=None, data=None, n=None):
    """An Image CDR body written by hand so it can lie (declared sizes, data length)."""
    c = rw.ENCODING_CHANNELS.get(encoding, 8)
    step = w * c if step is None else step
    data = bytes(step * h) if data is None else data
    body = rw.encode_image(rw.Image(rw.Header(1, 2, "f"), h, w, encoding, 0, step, data))
    if n is not None:  # declare n data bytes, keep what is there
        at = len(body) - len(data) - 4
        body = body[:at] + struct.pack("<I", n) + body[at + 4:]
    return body


@pytest.mark.parametrize("payload,reason", [
    (_image_bytes(encoding="bgra16"), "encoding"),
    (_image_bytes(encoding="bayer_rggb8"), "encoding"),
    (_image_bytes(h=20000, w=20000, data=b""), "size"),
    (_image_bytes(h=0, w=5, data=b""), "size"),
    (_image_bytes(h=480, w=640, data=bytes(100), n=640 * 480 * 3), "truncated"),  # body shorter than declared
    (_image_bytes(h=4, w=4, step=8, data=bytes(32)), "layout"),                   # step < width x 3
    (_image_bytes(h=4, w=4, data=bytes(10)), "layout"),                           # data < step x height
    (_image_bytes()[:9], "truncated"),
    (b"\x00\x00\x00\x00" + _image_bytes()[4:], "header"),                         # big-endian CDR
    (b"", "truncated"),
])
def test_untrusted_images_fail_with_a_reason(payload, reason):
    with pytest.raises(rw.RosWireError) as e:
        rw.decode_image(payload)
    assert e.value.reason == reason, str(e.value)


def test_string_without_nul_and_compressed_not_an_image():
    good = rw.encode_compressed(rw.CompressedImage(rw.Header(), "png", b"\x89PNG\r\n\x1a\n" + bytes(4)))
    assert rw.decode_compressed(good).format == "png"
    with pytest.raises(rw.RosWireError) as e:
        rw.decode_compressed(good[:16] + b"x" + good[17:])  # frame_id's NUL (offset 4+8+4) replaced
    assert e.value.reason == "string"
    fake = rw.encode_compressed(rw.CompressedImage(rw.Header(), "jpeg", b"GIF89a"))
    with pytest.raises(rw.RosWireError) as e:
        rw.decode_compressed(fake)
    assert e.value.reason == "encoding"


def test_image_to_rgb_and_masks():
    bgr = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    padded = np.zeros((2, 12), np.uint8)  # step 12 > 9: the row padding is dropped
    padded[:, :9] = bgr.reshape(2, 9)
    img = rw.decode_image(rw.encode_image(rw.Image(rw.Header(), 2, 3, "bgr8", 0, 12, padded.tobytes())))
    assert np.array_equal(rw.image_to_rgb(img), bgr[:, :, ::-1])
    mono = rw.image_to_rgb(rw.Image(rw.Header(), 1, 2, "mono8", 0, 2, b"\x05\x09"))
    assert mono.tolist() == [[[5, 5, 5], [9, 9, 9]]]
    m = rw.mono8(rw.Header(3, 4, "x"), np.full((2, 5), 255, np.uint8))
    assert (m.encoding, m.step, m.width, m.height, len(m.data)) == ("mono8", 5, 5, 2, 10)
    assert rw.decode_image(rw.encode_image(m)) == m
