"""Camera frames out of ROS 2 recordings: rosbag2 (SQLite ``.db3`` or MCAP storage) and ``.mcap`` files.

Pure (no Zenoh).  SQLite bags are read with the standard library; MCAP with the ``mcap``
package (``pip install 'scmr-mesh[ros]'``).  Only ``sensor_msgs/msg/Image`` and
``sensor_msgs/msg/CompressedImage`` topics in CDR are read; each message's payload is
returned as recorded (CDR with its encapsulation header) for :mod:`scmr_mesh.ros.wire`
to decode.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from scmr_mesh.errors import InputError
from scmr_mesh.ros import wire as rw

IMAGE_TYPES = (rw.IMAGE, rw.COMPRESSED_IMAGE)


@dataclass(frozen=True)
class BagTopic:
    """One image topic of a recording: where it is and what it holds."""

    path: Path          # the .db3 or .mcap file
    storage: str        # "sqlite3" or "mcap"
    topic: str
    ros_type: str
    count: int


def _files(path: Path) -> list[Path]:
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix in (".db3", ".mcap") and p.is_file())
        if not files:
            raise InputError(f"--bag {path}: the folder holds no .db3 or .mcap file; give a rosbag2 folder "
                             "or an .mcap file")
        return files
    if not path.is_file():
        raise InputError(f"--bag {path}: no such file or folder")
    if path.suffix not in (".db3", ".mcap"):
        raise InputError(f"--bag {path}: not a .db3 or .mcap file; give a rosbag2 folder or an .mcap file")
    return [path]


def _mcap_reader(f):
    try:
        from mcap.reader import make_reader
    except ImportError:
        raise InputError("--bag: reading MCAP needs the mcap package: pip install 'scmr-mesh[ros]'") from None
    return make_reader(f)


def _sqlite(path: Path) -> sqlite3.Connection:
    return sqlite3.connect(f"file:{path}?mode=ro", uri=True)


def _topics(path: Path) -> dict[str, tuple[str, int]]:
    """``{topic: (type, message count)}`` of one file."""
    try:
        if path.suffix == ".db3":
            with _sqlite(path) as db:
                rows = db.execute("SELECT t.name, t.type, COUNT(m.id) FROM topics t LEFT JOIN messages m "
                                  "ON m.topic_id = t.id GROUP BY t.id").fetchall()
            return {name: (typ, n) for name, typ, n in rows}
        with open(path, "rb") as f:
            summary = _mcap_reader(f).get_summary()
        if summary is None:
            raise InputError(f"--bag {path}: the MCAP file has no summary (was it closed?); reindex it with "
                             "`mcap recover`")
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        return {ch.topic: (summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas else "",
                           counts.get(cid, 0)) for cid, ch in summary.channels.items()}
    except (sqlite3.Error, OSError, ValueError) as exc:
        raise InputError(f"--bag {path}: cannot read it ({exc})") from None


def find_topic(path: str | Path, topic: str) -> BagTopic:
    """Where ``topic`` is in the recording ``path``, checked (exists, an image type, has messages); else one line."""
    path = Path(path)
    rw.check_topic(topic, flag="--topic")
    seen: dict[str, str] = {}
    for f in _files(path):
        topics = _topics(f)
        seen.update({t: typ for t, (typ, _) in topics.items()})
        if topic in topics:
            typ, n = topics[topic]
            if typ not in IMAGE_TYPES:
                raise InputError(f"--topic {topic} in {f} is {typ or 'of unknown type'}, not {rw.IMAGE} or "
                                 f"{rw.COMPRESSED_IMAGE}")
            if n == 0:
                raise InputError(f"--topic {topic} in {f} holds no messages")
            return BagTopic(f, "sqlite3" if f.suffix == ".db3" else "mcap", topic, typ, n)
    images = sorted(t for t, typ in seen.items() if typ in IMAGE_TYPES)
    raise InputError(f"--topic {topic} is not in --bag {path}; its image topics: {', '.join(images) or 'none'}")


def messages(bt: BagTopic) -> Iterator[tuple[int, bytes]]:
    """``(timestamp ns, CDR payload)`` of each message of ``bt``, in recorded order."""
    if bt.storage == "sqlite3":
        with _sqlite(bt.path) as db:
            cur = db.execute("SELECT m.timestamp, m.data FROM messages m JOIN topics t ON m.topic_id = t.id "
                             "WHERE t.name = ? ORDER BY m.timestamp", (bt.topic,))
            for ts, data in cur:
                yield int(ts), bytes(data)
        return
    with open(bt.path, "rb") as f:
        for _schema, _channel, msg in _mcap_reader(f).iter_messages(topics=[bt.topic], log_time_order=True):
            yield int(msg.log_time), bytes(msg.data)
