"""A robot's frames and masks as an MCAP file ROS 2 tools and Foxglove open (``--mcap FILE``).

Pure (no Zenoh; the ``mcap`` package writes the file).  Profile ``ros2``, schemas in
``ros2msg`` text (with their dependencies, as ``ros2 bag record`` writes them), messages in
CDR (:mod:`scmr_mesh.ros.wire`).  Per request of robot ``ID``:

* ``/ID/camera/compressed``: ``sensor_msgs/msg/CompressedImage`` ``jpeg``, the frame;
* ``/ID/drivable/mask``: ``sensor_msgs/msg/Image`` ``mono8``, 255 = drivable, the frame's size
  (only for requests that got a mask).

Both carry the header stamp of the request's ``sent_unix_ns`` and frame_id ``ID``; the log
time is the time the answer came back.
"""

from __future__ import annotations

import threading
from pathlib import Path

from scmr_mesh.errors import InputError
from scmr_mesh.ros import wire as rw

_SEP = "=" * 80 + "\n"
_HEADER_DEFS = (_SEP + "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
                + _SEP + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n")
#: ``ros2msg`` schema texts (equal to rosbags' ``generate_msgdef``: tests/test_ros_bag.py).
MSGDEFS: dict[str, str] = {
    rw.IMAGE: ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
               "uint32 step\nuint8[] data\n" + _HEADER_DEFS),
    rw.COMPRESSED_IMAGE: "std_msgs/Header header\nstring format\nuint8[] data\n" + _HEADER_DEFS,
}


class McapRecorder:
    """Write a robot's requests to ``path`` (see the module docstring); :meth:`observe` is a Robot observer."""

    def __init__(self, path: str | Path, robot_id: str, *, jpeg_quality: int = 90) -> None:
        try:
            from mcap.writer import Writer
        except ImportError:
            raise InputError("--mcap needs the mcap package: pip install 'scmr-mesh[ros]'") from None
        self.path = Path(path)
        self.robot = robot_id
        self.jpeg_quality = jpeg_quality or 90
        self.messages = 0
        self._lock = threading.Lock()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")
        except OSError as exc:
            raise InputError(f"--mcap {self.path}: cannot write it ({exc.strerror})") from None
        self._w = Writer(self._file)
        self._w.start(profile="ros2", library="scmr-mesh")
        self._channels: dict[str, int] = {}
        for topic, ros_type in ((f"/{robot_id}/camera/compressed", rw.COMPRESSED_IMAGE),
                                (f"/{robot_id}/drivable/mask", rw.IMAGE)):
            sid = self._w.register_schema(name=ros_type, encoding="ros2msg", data=MSGDEFS[ros_type].encode())
            self._channels[topic] = self._w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
        self._seq = 0

    def _add(self, topic: str, payload: bytes, log_ns: int, pub_ns: int) -> None:
        self._w.add_message(self._channels[topic], log_time=log_ns, data=payload, publish_time=pub_ns,
                            sequence=self._seq)
        self.messages += 1

    def observe(self, record: dict, rgb, mask) -> None:
        """Robot observer ``(record, rgb, mask)``: one frame and, when answered, its mask."""
        import cv2
        import numpy as np

        if rgb is None:
            return
        sent = int(record["sent_unix_ns"])
        header = rw.Header(sent // 1_000_000_000, sent % 1_000_000_000, self.robot)
        ok, jpg = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]),
                               [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        frame = rw.encode_compressed(rw.CompressedImage(header, "jpeg", jpg.tobytes()))
        out = None
        if mask is not None:
            h, w = rgb.shape[:2]
            if mask.shape != (h, w):
                mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_NEAREST)
            out = rw.encode_image(rw.mono8(header, np.where(mask > 0, np.uint8(255), np.uint8(0))))
        got = int(record["received_unix_ns"])
        with self._lock:
            if self._w is None:
                return
            self._seq += 1
            self._add(f"/{self.robot}/camera/compressed", frame, got, sent)
            if out is not None:
                self._add(f"/{self.robot}/drivable/mask", out, got, sent)

    def close(self) -> None:
        """Write the summary and index (an MCAP without them needs `mcap recover`) and close the file."""
        with self._lock:
            if self._w is None:
                return
            try:
                self._w.finish()
            finally:
                self._w = None
                self._file.close()


def readable(parts) -> tuple[list[Path], dict[str, str]]:
    """The MCAP files of ``parts`` that read to their end, and why each other one does not.

    A robot killed mid-run (SIGKILL) leaves a file without its chunks and summary.
    """
    from mcap.reader import make_reader

    good, bad = [], {}
    for p in parts:
        try:
            with open(p, "rb") as f:
                for _ in make_reader(f).iter_messages():
                    pass
            good.append(Path(p))
        except Exception as exc:  # truncated, empty, not MCAP at all
            bad[str(p)] = f"{type(exc).__name__}: {exc}"[:200]
    return good, bad


def merge(parts, out: str | Path) -> int:
    """Merge MCAP files written by :class:`McapRecorder` into ``out`` in log-time order; return the message count.

    Schemas and channels are written once each (by name and topic).  Every part must read to its
    end (:func:`readable` picks those).
    """
    import heapq
    from contextlib import ExitStack

    try:
        from mcap.reader import make_reader
        from mcap.writer import Writer
    except ImportError:
        raise InputError("--mcap needs the mcap package: pip install 'scmr-mesh[ros]'") from None
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    n = 0
    with ExitStack() as stack, open(out, "wb") as f:
        streams = []
        for i, p in enumerate(parts):
            reader = make_reader(stack.enter_context(open(p, "rb")))
            streams.append(((m.log_time, i, m.sequence, s, c, m) for s, c, m in reader.iter_messages(log_time_order=True)))
        w = Writer(f)
        w.start(profile="ros2", library="scmr-mesh")
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        for _t, _i, _q, schema, channel, msg in heapq.merge(*streams, key=lambda x: x[:3]):
            if schema.name not in schemas:
                schemas[schema.name] = w.register_schema(name=schema.name, encoding=schema.encoding, data=schema.data)
            if channel.topic not in channels:
                channels[channel.topic] = w.register_channel(topic=channel.topic, schema_id=schemas[schema.name],
                                                             message_encoding=channel.message_encoding)
            w.add_message(channels[channel.topic], log_time=msg.log_time, data=msg.data,
                          publish_time=msg.publish_time, sequence=msg.sequence)
            n += 1
        w.finish()
    return n
