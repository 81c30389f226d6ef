"""The rmw_zenoh wire contract for camera images and masks (pure: no Zenoh import).

What a ROS 2 node on ``rmw_zenoh_cpp`` (Jazzy, Kilted, Rolling; Humble without type hashes)
puts on Zenoh, checked against rmw_zenoh's ``docs/design.md``, ``liveliness_utils.cpp`` and
``attachment_helpers.cpp`` and, byte for byte, against ``rosbags`` (tests/test_ros_wire.py):

* data key ``<domain>/<topic without leading/trailing '/'>/<pkg>::msg::dds_::<Type>_/<type hash>``,
  the hash ``RIHS01_<64 hex>`` (Humble sends ``TypeHashNotSupported``: subscribe with ``*`` there,
  :func:`subscribe_key`);
* payload: CDR little-endian (XCDR1) behind the 4-byte encapsulation header ``00 01 00 00``;
  alignment counts from the end of that header;
* a 33-byte attachment on every sample (:class:`Attachment`): int64 sequence number, int64 source
  timestamp (ns), the byte 16 (the length of what follows), the 16-byte publisher gid, all
  little-endian (zenoh-cpp's ``ext::Serializer``); rmw_zenoh subscribers drop samples without it;
* graph discovery by liveliness tokens
  ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<kind>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]``
  with ``/`` inside a component written ``%`` (:func:`node_token`, :func:`entity_token`).

Decoding is strict and bounded: anything from the wire that is not an image this project
can segment (an encoding such as ``bgra16``, a 20000x20000 header, a body shorter than its
declared data, a string without its NUL) raises :class:`RosWireError`, whose ``reason``
names what was wrong (the bridge counts by reason), and never allocates what the header
claims before checking the body holds it.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass

from scmr_mesh.errors import InputError, WireError

#: CDR little-endian (XCDR1 plain CDR) encapsulation header.
CDR_LE = b"\x00\x01\x00\x00"

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"

#: RIHS01 type hashes (Jazzy and later): equal to what rosbags 0.11.9 computes for ROS2_JAZZY
#: (tests/test_ros_wire.py).
TYPE_HASHES: dict[str, str] = {
    IMAGE: "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    COMPRESSED_IMAGE: "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
}
#: What rmw_zenoh on Humble writes where later distributions write the hash.
HUMBLE_HASH = "TypeHashNotSupported"

#: Largest image accepted from the wire, in pixels (the pipeline's limit, imaging.codec.MAX_PIXELS).
MAX_PIXELS = 3840 * 2160
#: Largest CDR payload accepted (bytes): a 4K rgb8 frame is 24.9 MB.
MAX_PAYLOAD_BYTES = 32 * 1024 * 1024
#: Longest string field accepted (frame_id, encoding, format), NUL included.
MAX_STRING_BYTES = 4096

#: Image encodings the bridge turns into RGB, with their channels (8 bits each).
ENCODING_CHANNELS: dict[str, int] = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8UC1": 1,
                                     "8UC3": 3}
#: Gid size on the wire (rmw_zenoh keeps 16 bytes of its 24-byte RMW_GID_STORAGE_SIZE).
GID_BYTES = 16
ATTACHMENT_BYTES = 8 + 8 + 1 + GID_BYTES

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
#: Liveliness QoS chunk of a reliable, volatile, keep-last-10 endpoint (rmw_zenoh's qos_to_keyexpr:
#: fields equal to rmw_zenoh's default, reliable/volatile/keep-last, are left empty; depth 10 is not).
QOS_KEEP_LAST_10 = "::,10:,:,:,,"


class RosWireError(WireError):
    """A ROS 2 sample that cannot be used; ``reason`` is one word the bridge counts by.

    Reasons: ``truncated`` (body shorter than its fields), ``encoding`` (not an 8-bit image
    encoding or compressed format we decode), ``size`` (more pixels or bytes than allowed,
    or an empty image), ``layout`` (step and data length disagree), ``header`` (not CDR
    little-endian), ``string`` (a string field without its NUL or too long),
    ``attachment``, ``key``.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


# ------------------------------------------------------------------ messages
@dataclass(frozen=True)
class Header:
    """``std_msgs/msg/Header``: ``builtin_interfaces/Time stamp`` (sec int32, nanosec uint32), frame_id."""

    sec: int = 0
    nanosec: int = 0
    frame_id: str = ""


@dataclass(frozen=True)
class Image:
    """``sensor_msgs/msg/Image``: ``data`` holds ``height`` rows of ``step`` bytes.

    Decoded from the wire, ``data`` is a read-only memoryview of the payload (no copy).
    """

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: bytes | memoryview


@dataclass(frozen=True)
class CompressedImage:
    """``sensor_msgs/msg/CompressedImage``: ``format`` such as ``jpeg``, ``png`` or ``rgb8; jpeg compressed bgr8``."""

    header: Header
    format: str
    data: bytes


class _Writer:
    def __init__(self) -> None:
        self.buf = bytearray(CDR_LE)

    def _align(self, n: int) -> None:
        pad = (-(len(self.buf) - 4)) % n
        self.buf += b"\x00" * pad

    def u8(self, v: int) -> None:
        self.buf += struct.pack("<B", v)

    def u32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", v)

    def i32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<i", v)

    def string(self, s: str) -> None:
        b = s.encode("utf-8") + b"\x00"
        self.u32(len(b))
        self.buf += b

    def header(self, h: Header) -> None:
        self.i32(h.sec)
        self.u32(h.nanosec)
        self.string(h.frame_id)


class _Reader:
    def __init__(self, buf: bytes | bytearray | memoryview) -> None:
        mv = memoryview(buf)
        if len(mv) > MAX_PAYLOAD_BYTES:
            raise RosWireError("size", f"CDR payload of {len(mv)} bytes, more than the {MAX_PAYLOAD_BYTES} allowed")
        if len(mv) < 4:
            raise RosWireError("truncated", f"CDR payload of {len(mv)} bytes has no encapsulation header")
        if bytes(mv[:4]) != CDR_LE:
            raise RosWireError("header", f"encapsulation header {bytes(mv[:4]).hex()}, expected 00010000 "
                                         "(CDR little-endian, what rmw_zenoh sends)")
        self.mv = mv
        self.pos = 4

    def _take(self, n: int, what: str) -> memoryview:
        if n > len(self.mv) - self.pos:
            raise RosWireError("truncated", f"{what}: needs {n} bytes at offset {self.pos}, the body has "
                                            f"{len(self.mv) - self.pos} left")
        out = self.mv[self.pos:self.pos + n]
        self.pos += n
        return out

    def _align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) % n

    def u8(self, what: str) -> int:
        return self._take(1, what)[0]

    def u32(self, what: str) -> int:
        self._align(4)
        return struct.unpack("<I", self._take(4, what))[0]

    def i32(self, what: str) -> int:
        self._align(4)
        return struct.unpack("<i", self._take(4, what))[0]

    def string(self, what: str) -> str:
        n = self.u32(what)
        if n == 0 or n > MAX_STRING_BYTES:
            raise RosWireError("string", f"{what}: string length {n}, expected 1..{MAX_STRING_BYTES} (NUL included)")
        raw = bytes(self._take(n, what))
        if raw[-1] != 0:
            raise RosWireError("string", f"{what}: string does not end with NUL")
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError:
            raise RosWireError("string", f"{what}: not UTF-8") from None

    def octets(self, what: str) -> bytes:
        n = self.u32(what + " length")
        return bytes(self._take(n, what))

    def header(self) -> Header:
        sec = self.i32("header.stamp.sec")
        nanosec = self.u32("header.stamp.nanosec")
        return Header(sec, nanosec, self.string("header.frame_id"))


def encode_image(img: Image) -> bytes:
    """CDR (little-endian, encapsulation header first) of a ``sensor_msgs/msg/Image``."""
    w = _Writer()
    w.header(img.header)
    w.u32(img.height)
    w.u32(img.width)
    w.string(img.encoding)
    w.u8(img.is_bigendian)
    w.u32(img.step)
    w.u32(len(img.data))
    return b"".join((w.buf, img.data))  # the pixels copied once


def encode_compressed(img: CompressedImage) -> bytes:
    """CDR (little-endian, encapsulation header first) of a ``sensor_msgs/msg/CompressedImage``."""
    w = _Writer()
    w.header(img.header)
    w.string(img.format)
    w.u32(len(img.data))
    return b"".join((w.buf, img.data))


def _check_pixels(height: int, width: int) -> None:
    if height <= 0 or width <= 0:
        raise RosWireError("size", f"image header gives an empty size {width}x{height}")
    if height * width > MAX_PIXELS:
        raise RosWireError("size", f"image header claims {width}x{height} = {width * height} pixels, more than "
                                   f"the {MAX_PIXELS} allowed (3840x2160); downscale on the robot")


def decode_image(payload: bytes | bytearray | memoryview) -> Image:
    """Parse a ``sensor_msgs/msg/Image`` sample that the bridge can segment, or raise :class:`RosWireError`.

    Accepted: the 8-bit encodings of :data:`ENCODING_CHANNELS`, at most :data:`MAX_PIXELS`
    pixels, ``step >= width * channels`` and ``step * height`` bytes of data present.
    """
    r = _Reader(payload)
    header = r.header()
    height = r.u32("height")
    width = r.u32("width")
    encoding = r.string("encoding")
    is_bigendian = r.u8("is_bigendian")
    step = r.u32("step")
    channels = ENCODING_CHANNELS.get(encoding)
    if channels is None:
        raise RosWireError("encoding", f"image encoding {encoding!r} is not one the bridge segments; publish "
                                       f"one of {', '.join(ENCODING_CHANNELS)} (8 bits per channel)")
    _check_pixels(height, width)
    n = r.u32("data length")
    if step < width * channels or step * height > n:
        raise RosWireError("layout", f"{encoding} {width}x{height} with step {step} and {n} data bytes: step must be "
                                     f">= {width * channels} and data >= step x height")
    # a view of the payload, not a copy (0.9 MB for a 640x480 rgb8 frame): the pixels are read in place
    data = r._take(n, "data")
    return Image(header, height, width, encoding, is_bigendian, step, data)


def decode_compressed(payload: bytes | bytearray | memoryview) -> CompressedImage:
    """Parse a ``sensor_msgs/msg/CompressedImage`` sample whose format is JPEG or PNG, or raise."""
    r = _Reader(payload)
    header = r.header()
    fmt = r.string("format")
    data = r.octets("data")
    if compressed_kind(fmt, data) is None:
        raise RosWireError("encoding", f"compressed format {fmt!r} (data starts {data[:4].hex()}) is neither JPEG nor "
                                       "PNG; publish image_transport's jpeg or png")
    return CompressedImage(header, fmt, data)


def compressed_kind(fmt: str, data: bytes) -> str | None:
    """``"jpeg"`` or ``"png"`` when both the format string and the data's magic bytes say so, else None."""
    f = fmt.lower()
    if ("jpeg" in f or "jpg" in f) and data[:2] == b"\xff\xd8":
        return "jpeg"
    if "png" in f and data[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    return None


def image_to_rgb(img: Image):
    """The (H, W, 3) uint8 RGB pixels of a decoded :class:`Image`, rows past ``width`` dropped: read-only, a view
    of ``data`` when it already is contiguous ``rgb8``/``8UC3``, else a copy."""
    import numpy as np

    c = ENCODING_CHANNELS[img.encoding]
    rows = np.frombuffer(img.data, np.uint8, count=img.step * img.height).reshape(img.height, img.step)
    px = rows[:, : img.width * c].reshape(img.height, img.width, c)
    if c == 1:
        return np.repeat(px, 3, axis=2)
    if img.encoding.startswith("bgr"):
        return np.ascontiguousarray(px[:, :, 2::-1])
    return np.ascontiguousarray(px[:, :, :3])


def _pixels_view(arr) -> memoryview:
    """The bytes of a uint8 array as a flat memoryview: no copy when it is contiguous (:func:`encode_image`
    then copies the pixels once, into the payload; ``tobytes`` first made a second fresh 0.3-0.9 MB buffer)."""
    import numpy as np

    return memoryview(np.ascontiguousarray(arr, dtype=np.uint8).reshape(-1))


def mono8(header: Header, mask) -> Image:
    """A ``mono8`` Image of a (H, W) uint8 mask (255 = drivable) with ``header`` (``data``: a view of ``mask``)."""
    h, w = mask.shape
    return Image(header, h, w, "mono8", 0, w, _pixels_view(mask))


def rgb8(header: Header, rgb) -> Image:
    """An ``rgb8`` Image of (H, W, 3) uint8 pixels with ``header`` (``data``: a view of ``rgb``)."""
    h, w, _ = rgb.shape
    return Image(header, h, w, "rgb8", 0, 3 * w, _pixels_view(rgb))


# ------------------------------------------------------------------ keys
_ROS_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


def check_topic(name: str, *, flag: str = "--topic") -> str:
    """A fully qualified ROS 2 topic name (``/camera/image_raw``), or :class:`InputError` naming the fix."""
    if not isinstance(name, str) or not _ROS_NAME.match(name) or len(name) > 255:
        raise InputError(f"{flag} {name!r} is not a ROS 2 topic name: give an absolute name such as "
                         "/camera/image_raw (letters, digits and _, each part not starting with a digit)")
    return name


def check_domain(domain: int) -> int:
    """A ROS domain id (0..232, what ROS 2 allows), or :class:`InputError`."""
    if not isinstance(domain, int) or not 0 <= domain <= 232:
        raise InputError(f"--domain must be a ROS domain id 0..232, got {domain!r}")
    return domain


def dds_type(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the type chunk of rmw_zenoh's keys)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def topic_key(domain: int, topic: str, ros_type: str, type_hash: str | None = None) -> str:
    """The data key of ``topic`` (hash from :data:`TYPE_HASHES` unless given)."""
    return f"{domain}/{topic.strip('/')}/{dds_type(ros_type)}/{type_hash or TYPE_HASHES[ros_type]}"


def subscribe_key(domain: int, topic: str, ros_type: str) -> str:
    """The key to subscribe to ``topic`` from any distribution: ``*`` in the hash chunk (Humble sends none)."""
    return f"{domain}/{topic.strip('/')}/{dds_type(ros_type)}/*"


@dataclass(frozen=True)
class TopicKey:
    domain: int
    topic: str       # with its leading '/'
    dds_type: str
    type_hash: str


def parse_topic_key(key: str) -> TopicKey:
    """Split a data key ``<domain>/<topic...>/<type>/<hash>``, or raise :class:`RosWireError` (``key``)."""
    parts = str(key).split("/")
    if len(parts) < 4 or not parts[0].isdigit() or "::" not in parts[-2]:
        raise RosWireError("key", f"{key!r} is not an rmw_zenoh data key <domain>/<topic>/<type>/<hash>")
    return TopicKey(int(parts[0]), "/" + "/".join(parts[1:-2]), parts[-2], parts[-1])


def mangle(name: str) -> str:
    """A name as one liveliness key chunk: ``/`` written ``%`` (an empty name is ``%``)."""
    return name.replace("/", "%") or "%"


def demangle(chunk: str) -> str:
    return chunk.replace("%", "/")


def node_token(domain: int, zid: str, nid: int, node: str, *, namespace: str = "/", enclave: str = "/") -> str:
    """Liveliness key of a node (``NN``)."""
    return "/".join([ADMIN_SPACE, str(domain), zid, str(nid), str(nid), NODE, mangle(enclave), mangle(namespace),
                     mangle(node)])


def entity_token(domain: int, zid: str, nid: int, eid: int, kind: str, node: str, topic: str, ros_type: str, *,
                 type_hash: str | None = None, namespace: str = "/", enclave: str = "/",
                 qos: str = QOS_KEEP_LAST_10) -> str:
    """Liveliness key of a publisher (``MP``) or subscription (``MS``) of ``node``."""
    if kind not in (PUBLISHER, SUBSCRIPTION):
        raise ValueError(f"kind must be {PUBLISHER} or {SUBSCRIPTION}, got {kind!r}")
    return "/".join([ADMIN_SPACE, str(domain), zid, str(nid), str(eid), kind, mangle(enclave), mangle(namespace),
                     mangle(node), mangle(topic), dds_type(ros_type), type_hash or TYPE_HASHES[ros_type], qos])


@dataclass(frozen=True)
class Token:
    domain: int
    zid: str
    nid: str
    eid: str
    kind: str
    enclave: str
    namespace: str
    node: str
    topic: str | None = None
    dds_type: str | None = None
    type_hash: str | None = None
    qos: str | None = None


def parse_token(key: str) -> Token:
    """Split a liveliness key (names demangled), or raise :class:`RosWireError` (``key``)."""
    p = str(key).split("/")
    if p[0] != ADMIN_SPACE or len(p) not in (9, 13) or not p[1].isdigit():
        raise RosWireError("key", f"{key!r} is not an rmw_zenoh liveliness token")
    t = Token(int(p[1]), p[2], p[3], p[4], p[5], demangle(p[6]), demangle(p[7]), demangle(p[8]))
    if len(p) == 13:
        t = Token(*[getattr(t, f) for f in ("domain", "zid", "nid", "eid", "kind", "enclave", "namespace", "node")],
                  topic=demangle(p[9]), dds_type=p[10], type_hash=p[11], qos=p[12])
    return t


# ------------------------------------------------------------------ attachment
@dataclass(frozen=True)
class Attachment:
    """rmw_zenoh's per-sample attachment: sequence number, source timestamp (unix ns), publisher gid."""

    seq: int
    timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_BYTES:
            raise ValueError(f"gid must be {GID_BYTES} bytes, got {len(self.gid)}")
        return struct.pack("<qqB", self.seq, self.timestamp_ns, GID_BYTES) + bytes(self.gid)


def decode_attachment(data: bytes | bytearray | memoryview | None) -> Attachment:
    """Parse the 33-byte attachment, or raise :class:`RosWireError` (``attachment``)."""
    if data is None:
        raise RosWireError("attachment", "sample without the rmw_zenoh attachment")
    b = bytes(data)
    if len(b) != ATTACHMENT_BYTES or b[16] != GID_BYTES:
        raise RosWireError("attachment", f"attachment of {len(b)} bytes, expected {ATTACHMENT_BYTES} "
                                         "(int64 seq, int64 timestamp, 16, 16-byte gid)")
    seq, ts = struct.unpack_from("<qq", b)
    return Attachment(seq, ts, b[17:])


def gid_of(token_key: str) -> bytes:
    """A 16-byte publisher gid derived from its liveliness key (rmw_zenoh hashes the key too, with XXH3-128)."""
    return hashlib.blake2b(token_key.encode(), digest_size=GID_BYTES).digest()
