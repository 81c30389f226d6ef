"""``scmr ros``: a robot whose camera is a ROS 2 topic on rmw_zenoh (docs/ROS2.md).

A :class:`RosBridge` holds a second Zenoh session on the ROS side (``rmw_zenohd``,
tcp/localhost:7447 by default), next to the robot's mesh session: a *peer* like an rmw_zenoh
node when the router is on this host (discovery through the router, frames and masks directly
to and from the ROS nodes), a *client* of the router otherwise (:func:`ros_mode_for`).  It
subscribes to the image topic (``sensor_msgs/msg/Image`` or, with ``compressed``,
``CompressedImage``; any type hash, so Humble's ``TypeHashNotSupported`` matches), sends
each frame through :meth:`Robot.request <scmr_mesh.mesh.robot.Robot.request>` (the same
placement, failover, hedging, security, records and telemetry as ``scmr robot``) and
publishes the mask as ``mono8`` (255 = drivable, the input's size, header stamp and
frame_id) on the mask topic and an ``rgb8`` overlay on ``<mask topic>/overlay`` (made
only while that topic has a subscriber), each
sample with rmw_zenoh's attachment.  A ``CompressedImage`` goes to the mesh as it is: only its
JPEG/PNG header is read (size, bounds, end marker); its pixels are decoded only for the overlay
or ``--mcap``.  Liveliness tokens declare its node, its two
publishers and its subscription, so ``ros2 node list`` / ``ros2 topic info`` see it.

Frames that arrive while one is being served wait in a one-frame slot: a newer frame
replaces the waiting one (dropped oldest-first, counted).  The subscriber callback only
checks a sample (its key's type hash, the CDR layout, the declared size: no pixel is read);
a raw ``Image``'s pixels are converted, reduced and JPEG-encoded when the frame is taken to
be served, so a frame replaced in the slot costs its parse and nothing more (a 30 Hz camera
behind ``--rate 5`` used to have all 30 frames a second encoded).  The price: that work (about
1 ms at 640x480) no longer overlaps the request before it, so a served frame's mask comes about
1 ms later after its wait in the slot, and a bridge whose camera outpaces its answers serves up
to prep / (ToR + prep) fewer frames a second (at a 30 Hz camera and ToR >= 33 ms: <= 3 %).  A sample that is not an
image the bridge can segment is counted by reason (:class:`scmr_mesh.ros.wire.RosWireError`)
and logged once per topic and reason; it never reaches the robot.
"""

from __future__ import annotations

import logging
import re
import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from scmr_mesh.mesh.frames import Frame
from scmr_mesh.ros import wire as rw

log = logging.getLogger(__name__)


@dataclass
class BridgeStats:
    """What the bridge saw and did; ``rejected`` counts samples by :class:`RosWireError` reason."""

    received: int = 0
    served: int = 0
    failed: int = 0
    dropped: int = 0
    published: int = 0
    #: overlays published (one per published mask while the overlay topic has a subscriber)
    overlays: int = 0
    publish_errors: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    #: per served frame (the last 10000): ms spent making the frame ready to send (the callback's
    #: parse, then RGB, reduction and JPEG when it is taken; its wait in the slot not counted), and
    #: from the robot's answer to the mask published
    in_ms: deque = field(default_factory=lambda: deque(maxlen=10000))
    out_ms: deque = field(default_factory=lambda: deque(maxlen=10000))
    #: and the wall time of Robot.request (its ToR plus its records, inbox and telemetry)
    request_ms: deque = field(default_factory=lambda: deque(maxlen=10000))
    #: the bridge's own time: from the sample's arrival to the mask published, less the robot's ToR
    bridge_ms: deque = field(default_factory=lambda: deque(maxlen=10000))

    def as_dict(self) -> dict:
        return {"received": self.received, "served": self.served, "failed": self.failed, "dropped": self.dropped,
                "published": self.published, "overlays": self.overlays, "publish_errors": self.publish_errors,
                "rejected": dict(self.rejected), "rejected_total": sum(self.rejected.values()),
                "in_ms_median": _median(self.in_ms), "request_ms_median": _median(self.request_ms),
                "out_ms_median": _median(self.out_ms), "bridge_ms_median": _median(self.bridge_ms)}


def _median(xs) -> float | None:
    return round(statistics.median(xs), 3) if xs else None


@dataclass
class _Pending:
    header: rw.Header
    #: None for a raw Image until :meth:`RosBridge._prepare` makes it from ``img``
    frame: Frame | None
    height: int
    width: int
    in_ms: float = 0.0
    #: perf_counter at the sample's arrival
    t_arrival: float = 0.0
    #: set by the annotator once the mask is published: perf_counter at the answer, ms to publish it
    t_answer: float | None = None
    out_ms: float | None = None
    mask: Any = None
    #: a raw Image's parsed sample (its pixels a view of the payload) and topic, until prepared
    img: Any = None
    topic: str = ""
    key: str = ""


def reduced_for_service(rgb):
    """``rgb`` area-averaged by the JPEG DCT factor a service would decode it at (1, 2, 4 or 8).

    The services work on 300x225 (:func:`scmr_mesh.imaging.codec.decode_frame`): they decode a
    JPEG at the smallest DCT scale 1/r that keeps it at least 300x225, then area-resize.  The
    bridge does that first reduction itself (an integer area average, OpenCV's fast path), so
    the JPEG it encodes and sends is r x r times smaller and the service decodes it at full
    scale to nearly the same 300x225 frame; the mask (300x225 either way) is unchanged in size.
    """
    import cv2

    from scmr_mesh.imaging.codec import reduction_factor

    h, w = rgb.shape[:2]
    r = reduction_factor(w, h)
    if r == 1:
        return rgb
    # rounded up, as the service's own 1/r DCT decode would be: never below its working size
    return cv2.resize(rgb, (-(-w // r), -(-h // r)), interpolation=cv2.INTER_AREA)


def mask_for(mask_png: bytes, height: int, width: int):
    """The ``mono8`` mask of a service's PNG mask at ``height`` x ``width``: 255 = drivable, else 0.

    Thresholded at the service's size (300x225), then resized nearest-neighbour, so the
    full-size array is made once.
    """
    import cv2
    import numpy as np

    small = cv2.imdecode(np.frombuffer(mask_png, np.uint8), cv2.IMREAD_GRAYSCALE)
    if small is None:
        raise ValueError(f"the service's mask ({len(mask_png)} bytes) is not a PNG")
    small = cv2.threshold(small, 0, 255, cv2.THRESH_BINARY)[1]  # > 0 -> 255 (0.002 ms; np.where: 0.04)
    if small.shape != (height, width):
        small = cv2.resize(small, (width, height), interpolation=cv2.INTER_NEAREST)
    return small


def ros_node_name(robot_id: str) -> str:
    """The ROS node name of robot ``robot_id``: ``scmr_ros_<id>`` with characters ROS refuses as ``_``."""
    return "scmr_ros_" + re.sub(r"[^A-Za-z0-9_]", "_", robot_id)


def _frame_name(topic: str, header: rw.Header) -> str:
    """A frame's name in the robot's records (``image``): ``<topic>@<stamp sec>.<nanosec>``."""
    return f"{topic}@{header.sec}.{header.nanosec:09d}"


class _Publisher:
    """A Zenoh publisher on an rmw_zenoh data key that attaches (seq, timestamp, gid) to each sample."""

    def __init__(self, session, key: str, token_key: str) -> None:
        self.pub = session.declare_publisher(key)
        self.gid = rw.gid_of(token_key)
        self.seq = 0

    def put(self, payload: bytes) -> None:
        self.seq += 1
        self.pub.put(payload, attachment=rw.Attachment(self.seq, time.time_ns(), self.gid).encode())

    def matching(self) -> bool:
        """Whether a subscriber (a ROS node, ``ros2 bag record``) matches this publisher now."""
        try:
            return bool(self.pub.matching_status.matching)
        except Exception:  # unknown: publish
            return True

    def undeclare(self) -> None:
        self.pub.undeclare()


#: libjpeg's largest side (JPEG_MAX_DIMENSION): a raw frame that would be sent longer than this is refused
#: when it arrives.
JPEG_MAX_SIDE = 65500


class RosBridge:
    """Serve a ROS 2 image topic through ``robot``; see the module docstring.

    Parameters
    ----------
    robot : Robot
        Attached to the mesh session; its :meth:`request` serves each frame.
    ros_session : zenoh.Session
        A client session of the ROS router.
    domain : int
        ROS domain id.
    image_topic, mask_topic : str
        Absolute ROS topic names.
    compressed : bool
        Subscribe to ``sensor_msgs/msg/CompressedImage`` (JPEG or PNG) instead of ``Image``.
    rate_hz : float or None
        At most this many frames per second go to the mesh (None: as fast as they are served).
    jpeg_quality : int
        Raw ``Image`` frames are sent to the mesh as JPEG at this quality (0: PNG).
    full_frames : bool
        Send raw ``Image`` frames at their full size; by default they are first area-averaged
        by the factor the service would decode them at (:func:`reduced_for_service`).
    """

    def __init__(self, robot, ros_session, *, domain: int, image_topic: str, mask_topic: str,
                 compressed: bool = False, rate_hz: float | None = None, jpeg_quality: int = 90,
                 node_name: str | None = None, full_frames: bool = False) -> None:
        self.robot = robot
        self.session = ros_session
        self.domain = rw.check_domain(domain)
        self.image_topic = rw.check_topic(image_topic, flag="--image-topic")
        self.mask_topic = rw.check_topic(mask_topic, flag="--mask-topic")
        self.overlay_topic = self.mask_topic + "/overlay"
        self.in_type = rw.COMPRESSED_IMAGE if compressed else rw.IMAGE
        self.rate_hz = rate_hz
        self.jpeg_quality = jpeg_quality
        self.full_frames = full_frames
        # imported here, not in Zenoh's receive thread at the first frame (the import loads OpenCV: 0.3 s)
        from scmr_mesh.imaging.codec import reduction_factor

        self._reduction_factor = reduction_factor
        self.node = node_name or ros_node_name(robot.id)
        self.stats = BridgeStats()
        self._cv = threading.Condition()
        self._slot: _Pending | None = None
        self._logged: set[tuple[str, str]] = set()
        self._tokens: list[Any] = []
        self._sub = None
        self._mask_pub: _Publisher | None = None
        self._overlay_pub: _Publisher | None = None
        self._seq = 0
        self._current: _Pending | None = None
        robot.annotators.append(self._on_answer)  # the mask goes out before the robot's records and telemetry

    # ------------------------------------------------------------ life cycle
    def tokens(self, zid: str) -> dict[str, str]:
        """The liveliness keys of the node, its subscription and its two publishers."""
        def ent(eid, kind, topic, ros_type):
            return rw.entity_token(self.domain, zid, 0, eid, kind, self.node, topic, ros_type)

        return {"node": rw.node_token(self.domain, zid, 0, self.node),
                "sub": ent(1, rw.SUBSCRIPTION, self.image_topic, self.in_type),
                "mask": ent(2, rw.PUBLISHER, self.mask_topic, rw.IMAGE),
                "overlay": ent(3, rw.PUBLISHER, self.overlay_topic, rw.IMAGE)}

    def start(self) -> None:
        """Declare the publishers, the subscription and the liveliness tokens."""
        tok = self.tokens(str(self.session.info.zid()))
        self._mask_pub = _Publisher(self.session, rw.topic_key(self.domain, self.mask_topic, rw.IMAGE), tok["mask"])
        self._overlay_pub = _Publisher(self.session, rw.topic_key(self.domain, self.overlay_topic, rw.IMAGE),
                                       tok["overlay"])
        self._sub = self.session.declare_subscriber(rw.subscribe_key(self.domain, self.image_topic, self.in_type),
                                                    self._on_sample)
        lv = self.session.liveliness()
        self._tokens = [lv.declare_token(tok[k]) for k in ("node", "sub", "mask", "overlay")]

    def close(self) -> None:
        from scmr_mesh.mesh.resources import undeclare_all

        undeclare_all([*self._tokens, self._sub, self._mask_pub, self._overlay_pub])
        self._tokens, self._sub, self._mask_pub, self._overlay_pub = [], None, None, None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ input
    def _reject(self, key: str, exc: rw.RosWireError) -> None:
        with self._cv:
            self.stats.rejected[exc.reason] = self.stats.rejected.get(exc.reason, 0) + 1
            first = (key, exc.reason) not in self._logged
            self._logged.add((key, exc.reason))
        if first:  # once per topic and reason; the count is in the summary
            log.error("ros: %s: sample rejected (%s): %s; further ones are counted, not logged", key, exc.reason, exc)

    def _on_sample(self, sample) -> None:
        """Zenoh callback: check the sample (bounded, no pixel read), then put it in the slot, replacing
        one that waits."""
        t0 = time.perf_counter()
        key = str(sample.key_expr)
        with self._cv:
            self.stats.received += 1
        try:
            pending = self._parse(key, sample.payload.to_bytes())
            pending.in_ms = (time.perf_counter() - t0) * 1e3
            pending.t_arrival = t0
        except rw.RosWireError as exc:
            self._reject(key, exc)
            return
        except Exception as exc:  # never let a sample kill the callback thread
            self._reject(key, rw.RosWireError("decode", f"{type(exc).__name__}: {exc}"))
            return
        with self._cv:
            if self._slot is not None:
                self.stats.dropped += 1
            self._slot = pending
            self._cv.notify()

    def _decode(self, key: str, payload: bytes) -> _Pending:
        """:meth:`_parse` and :meth:`_make_frame` at once: the frame ready to serve, or raise :class:`RosWireError`."""
        pending = self._parse(key, payload)
        self._make_frame(pending)
        return pending

    def _parse(self, key: str, payload: bytes) -> _Pending:
        """Check a sample and keep what serving it needs; a raw Image's pixels are not read here."""
        tk = rw.parse_topic_key(key)
        if tk.type_hash not in (rw.TYPE_HASHES[self.in_type], rw.HUMBLE_HASH):
            raise rw.RosWireError("type_hash", f"type hash {tk.type_hash} is not the {self.in_type} this bridge "
                                               f"decodes ({rw.TYPE_HASHES[self.in_type]}, or Humble's)")
        if self.in_type == rw.COMPRESSED_IMAGE:
            msg = rw.decode_compressed(payload)
            kind = rw.compressed_kind(msg.format, msg.data)
            from scmr_mesh.imaging.codec import image_size  # bounded: the declared size, checked
            from scmr_mesh.errors import ImageDecodeError

            try:
                _, width, height = image_size(msg.data)
            except ImageDecodeError as exc:
                raise rw.RosWireError("encoding", str(exc)) from None
            # sent as it is; its pixels are decoded (Frame.pixels) only for the overlay or --mcap
            frame = Frame(name=_frame_name(tk.topic, msg.header), data=msg.data, encoding=kind)
            return _Pending(msg.header, frame, height, width)
        img = rw.decode_image(payload)
        if self.jpeg_quality:  # refused here, not after it has replaced the frame waiting in the slot
            r = 1 if self.full_frames else self._reduction_factor(img.width, img.height)
            side = max(-(-img.width // r), -(-img.height // r))
            if side > JPEG_MAX_SIDE:
                raise rw.RosWireError("size", f"{img.width}x{img.height} would go to the mesh with a side of {side} "
                                              f"pixels, more than JPEG's {JPEG_MAX_SIDE}; publish a frame of "
                                              f"ordinary proportions (or run --jpeg-quality 0 for PNG)")
        return _Pending(img.header, None, img.height, img.width, img=img, topic=tk.topic, key=key)

    def _make_frame(self, pending: _Pending) -> None:
        """A raw Image's frame for the mesh: RGB, reduced (:func:`reduced_for_service`), JPEG or PNG."""
        if pending.frame is not None:
            return
        from scmr_mesh.imaging import encode_jpeg, encode_png

        img = pending.img
        rgb = rw.image_to_rgb(img)
        send = rgb if self.full_frames else reduced_for_service(rgb)
        if self.jpeg_quality:
            data, enc = encode_jpeg(send, quality=self.jpeg_quality), "jpeg"
        else:
            data, enc = encode_png(send), "png"
        # rgb: the full frame (the overlay, --mcap); data: what goes to the mesh
        pending.frame = Frame(name=_frame_name(pending.topic, img.header), data=data, encoding=enc, rgb=rgb)
        pending.img = None

    def _prepare(self, pending: _Pending) -> bool:
        """Make the frame of a pending sample taken from the slot; False (counted, logged once) if that fails."""
        t0 = time.perf_counter()
        key = pending.key
        try:
            self._make_frame(pending)
        except rw.RosWireError as exc:
            self._reject(key, exc)
            return False
        except Exception as exc:  # a frame that cannot be made is counted, never kills the serving loop
            self._reject(key, rw.RosWireError("decode", f"{type(exc).__name__}: {exc}"))
            return False
        pending.in_ms += (time.perf_counter() - t0) * 1e3
        return True

    # ------------------------------------------------------------ serving
    def _take(self, stop: threading.Event, timeout: float) -> _Pending | None:
        with self._cv:
            if self._slot is None:
                self._cv.wait(timeout)
            p, self._slot = self._slot, None
            return p

    def _on_answer(self, record: dict, reply: dict | None) -> None:
        """Robot annotator: publish the mask as soon as the answer is in, before the robot writes its
        record, inbox and telemetry (which ``scmr robot`` also does after its ToR)."""
        p = self._current
        if p is None or reply is None or reply.get("mask_png") is None:
            return
        t0 = time.perf_counter()
        p.t_answer = t0
        try:
            p.mask = mask = mask_for(reply["mask_png"], p.height, p.width)
            self._mask_pub.put(rw.encode_image(rw.mono8(p.header, mask)))
            p.out_ms = (time.perf_counter() - t0) * 1e3
        except Exception as exc:  # counted by serve_one (out_ms stays None)
            p.mask = exc

    def serve_one(self, pending: _Pending) -> dict:
        """Send one frame through the robot, publish its mask and overlay; return the robot's record.

        The mask is published from :meth:`_on_answer`, inside :meth:`Robot.request` right after
        the answer; the overlay after the request returns, and only while something subscribes
        to it (a 640x480 overlay is 0.9 MB through the router and about 1.5 ms of CPU).
        """
        self._make_frame(pending)  # taken by run() prepared already; raises if it cannot be made
        self._current = pending
        t_req = time.perf_counter()
        try:
            record = self.robot.request(self._seq, pending.frame)
        finally:
            self._current = None
        request_ms = (time.perf_counter() - t_req) * 1e3
        self._seq += 1
        if not record["ok"] or pending.mask is None:
            with self._cv:
                self.stats.failed += 1
            log.warning("ros: frame %s got no mask: %s", record["seq"], record.get("error"))
            return record
        with self._cv:
            self.stats.served += 1
        if isinstance(pending.mask, Exception):
            with self._cv:
                self.stats.publish_errors += 1
            log.error("ros: publishing the mask of frame %s failed: %s", record["seq"], pending.mask)
            return record
        with self._cv:  # the mask is out (published from the robot's annotator): counted even if the overlay fails
            self.stats.published += 1
        try:
            mask = pending.mask
            overlay_on = self._overlay_pub.matching()  # made only when subscribed, as image_transport does
            if overlay_on:
                overlay = pending.frame.pixels() // 2  # half brightness, drivable pixels tinted green
                overlay[:, :, 1] += mask // 2
                self._overlay_pub.put(rw.encode_image(rw.rgb8(pending.header, overlay)))
            with self._cv:
                self.stats.overlays += overlay_on
                self.stats.in_ms.append(pending.in_ms)
                self.stats.out_ms.append(pending.out_ms)
                self.stats.request_ms.append(request_ms)
                self.stats.bridge_ms.append((pending.t_answer - pending.t_arrival) * 1e3 - record["tor_ms"]
                                            + pending.out_ms)
        except Exception as exc:
            with self._cv:
                self.stats.publish_errors += 1
            log.error("ros: publishing the overlay of frame %s failed: %s", record["seq"], exc)
        return record

    def run(self, stop: threading.Event, *, count: int | None = None, progress=None) -> BridgeStats:
        """Serve the newest waiting frame until ``stop`` (or ``count`` frames served or failed).

        With a rate cap, frame k goes out no earlier than t0 + k x period (integer ns); frames
        arriving meanwhile replace the waiting one.
        """
        period_ns = int(round(1e9 / self.rate_hz)) if self.rate_hz else 0
        t0 = None
        k = 0
        while not stop.is_set() and (count is None or self.stats.served + self.stats.failed < count):
            if period_ns and t0 is not None:
                due = t0 + k * period_ns
                wait_ns = due - time.monotonic_ns()
                if wait_ns > 0 and stop.wait(wait_ns / 1e9):
                    break
            pending = self._take(stop, 0.1)
            if pending is None or not self._prepare(pending):
                continue
            now = time.monotonic_ns()
            if t0 is None:
                t0 = now
            if period_ns:  # the next slot after this one (late frames do not earn a burst)
                k = max(k + 1, (now - t0) // period_ns + 1)
            rec = self.serve_one(pending)
            if progress is not None:
                progress(rec)
        with self._cv:  # a frame still waiting at exit is dropped too
            if self._slot is not None:
                self._slot = None
                self.stats.dropped += 1
        return self.stats


#: How an rmw_zenoh node joins the graph (rmw_zenoh's DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5, rolling,
#: read 2026-11): a peer that connects to rmw_zenohd, listens on loopback, sends its gossip to the
#: router only and dials the peers the router gossips back (the greater zid of a pair dials).  Data
#: then goes node to node: rmw_zenohd forwards nothing between peers (docs/ROS2.md, docs/ZENOH.md 16).
RMW_NODE_LISTEN = "tcp/localhost:0"
#: The scouting keys rmw_zenoh's session and router configs share.
_RMW_SCOUTING: dict[str, Any] = {
    "scouting/multicast/enabled": False,
    "scouting/gossip/enabled": True,
    "scouting/gossip/multihop": False,
    "scouting/gossip/target": {"router": ["router", "peer"], "peer": ["router"]},
    "scouting/gossip/autoconnect": {"router": [], "peer": ["router", "peer"]},
}
RMW_NODE_KEYS: dict[str, Any] = {
    **_RMW_SCOUTING,
    "scouting/gossip/autoconnect_strategy": {"peer": {"to_router": "always", "to_peer": "greater-zid"}},
}
#: rmw_zenohd's own keys that decide what it does for peers (DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5):
#: gossip to routers and peers, no multicast, and no failover brokering (rmw_zenoh#341: it never
#: forwards data between two peers; zenoh >= 1.9 ignores the key and never does anyway).
RMW_ZENOHD_KEYS: dict[str, Any] = {
    **_RMW_SCOUTING,
    "scouting/gossip/autoconnect_strategy": {"router": {"to_router": "always", "to_peer": "always"}},
    "routing/router/peers_failover_brokering": False,
}

#: The ROS session's shared memory (``scmr ros --ros-shm``; off by default, as in rmw_zenoh's config and
#: scmr's mesh sessions).  It only announces support: a frame goes through /dev/shm (files mode 0600,
#: this user's) only from a ROS node that enabled it as well.  With it on at both ends the frame's and
#: the mask's hops were about 1 ms shorter in all, but the time to mask was not, as the bridge's ToR
#: rose as much in the same runs (docs/BENCHMARKS.md, "ROS 2 bridge", "Shared memory").
ROS_SHM_KEYS: dict[str, Any] = {"transport/shared_memory/enabled": True}


def cfg_items(keys: dict[str, Any]) -> list[str]:
    """``keys`` as ``KEY:JSON`` items for ``--cfg`` / :class:`MeshConfig`'s ``cfg``."""
    import json

    return [f"{k}:{json.dumps(v)}" for k, v in keys.items()]


def _loopback(endpoint: str) -> bool:
    """Whether a zenoh endpoint ``PROTO/HOST:PORT[...]`` names this host's loopback."""
    addr = endpoint.split("/", 1)[1].split("#", 1)[0].split("?", 1)[0]
    host = addr.rsplit(":", 1)[0].strip("[]").lower()
    return host in ("localhost", "::1") or host.startswith("127.")


def ros_mode_for(mode: str, connect: list[str]) -> str:
    """The ROS session's mode: ``auto`` is ``peer`` when every router endpoint is loopback, else ``client``.

    A peer gets data only over direct links to the ROS nodes, which rmw_zenoh nodes accept on
    loopback only (``tcp/localhost:0``); from another host the bridge is a client of the router,
    as rmw_zenoh's README has RViz on another host join.
    """
    if mode == "auto":
        return "peer" if connect and all(_loopback(ep) for ep in connect) else "client"
    return mode


def ros_session_config(connect: list[str], cfg: list[str], mode: str = "peer", *, shm: bool = False):
    """The :class:`MeshConfig` of the ROS side.

    ``peer``: as an rmw_zenoh node (:data:`RMW_NODE_KEYS`, listening on :data:`RMW_NODE_LISTEN`):
    discovery through the router, data directly to and from the ROS nodes.  ``client``: every
    sample through the router (a router forwards to and from its clients, never between two
    peers: rmw_zenoh#929).  ``shm``: offer zenoh shared memory to the ROS nodes (:data:`ROS_SHM_KEYS`;
    used only with nodes that enable it too).  ``cfg`` (``--ros-cfg``) is applied after all that.
    """
    from scmr_mesh.mesh.config import CLIENT_CONNECT_TIMEOUT_MS, MeshConfig

    shm_items = cfg_items(ROS_SHM_KEYS) if shm else []
    if mode == "peer":
        # a router that never answers is an error after 30 s, as for a client (a peer would open
        # without it and wait for ever: zenoh >= 1.9 retries peers' endpoints with no end)
        own = {"listen/endpoints": [RMW_NODE_LISTEN], **RMW_NODE_KEYS,
               "connect/timeout_ms": CLIENT_CONNECT_TIMEOUT_MS, "connect/exit_on_failure": True}
        return MeshConfig(mode="peer", connect=list(connect), cfg=cfg_items(own) + shm_items + list(cfg))
    if mode == "client":
        return MeshConfig(mode="client", connect=list(connect), cfg=shm_items + list(cfg))
    raise ValueError(f"ROS session mode must be peer or client, got {mode!r}")
