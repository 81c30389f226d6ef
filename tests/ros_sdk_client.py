"""zenoh-ros2-sdk (a pure-Python rmw_zenoh client nobody here wrote) as an outside ROS 2 node.

Run as a process by tests/test_ros_bridge.py:
``python tests/ros_sdk_client.py ROUTER_PORT MSG_DIR IMAGE_TOPIC MASK_TOPIC``.  The SDK fetches
``.msg`` definitions from GitHub unless they are in its messages folder, so the three it needs
are written to MSG_DIR first (offline).  It publishes one 30x40 rgb8 Image (again every second
until answered, at most 20 s) and prints the first mask it receives as one JSON line.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

DEFS = {
    "sensor_msgs/msg/Image": "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
                             "uint8 is_bigendian\nuint32 step\nuint8[] data\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
}


def main(port: int, msg_dir: Path, image_topic: str, mask_topic: str) -> int:
    for t, d in DEFS.items():
        p = msg_dir / f"{t}.msg"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(d)
    import zenoh_ros2_sdk as sdk

    sdk.get_registry(str(msg_dir))
    got: list = []
    answered = threading.Event()

    def on_mask(msg) -> None:
        got.append(msg)
        answered.set()

    sdk.ROS2Subscriber(topic=mask_topic, msg_type="sensor_msgs/msg/Image", callback=on_mask,
                       router_ip="127.0.0.1", router_port=port)
    pub = sdk.ROS2Publisher(topic=image_topic, msg_type="sensor_msgs/msg/Image", router_ip="127.0.0.1",
                            router_port=port)
    Header, Time = sdk.get_message_class("std_msgs/msg/Header"), sdk.get_message_class("builtin_interfaces/msg/Time")
    rgb = np.zeros((30, 40, 3), np.uint8)
    rgb[15:] = 200
    sent = 0
    end = time.monotonic() + 20
    while not answered.is_set() and time.monotonic() < end:
        pub.publish(header=Header(stamp=Time(sec=77, nanosec=1), frame_id="sdk"), height=30, width=40,
                    encoding="rgb8", is_bigendian=0, step=120, data=rgb.reshape(-1))
        sent += 1
        answered.wait(1.0)
    m = got[0] if got else None
    print(json.dumps({"sent": sent, "mask": None if m is None else {
        "encoding": m.encoding, "height": int(m.height), "width": int(m.width), "sec": int(m.header.stamp.sec),
        "frame_id": m.header.frame_id, "values": sorted(set(bytes(m.data)))}}), flush=True)
    return 0 if m is not None else 1


if __name__ == "__main__":
    rc = main(int(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], sys.argv[4])
    os._exit(rc)  # the SDK's session threads would keep the process alive past main()
