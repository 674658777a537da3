"""Publish ROS 2 messages the way rmw_zenoh does, encoded by rosbags (no ROS install).

rmw_zenoh puts a message of topic /T, type pkg/msg/Name, on the zenoh key
``<domain>/T/pkg::msg::dds_::Name_/<RIHS01 type hash>``, the payload CDR-encoded.
Run: python examples/node/publish_ros2.py tcp/127.0.0.1:7450 [COUNT]
"""

from __future__ import annotations

import json
import sys
import threading
import time

import zenoh
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types


def key(topic: str, rostype: str, domain: int = 0) -> str:
    """The key expression rmw_zenoh publishes ``topic`` of ``rostype`` on."""
    pkg, kind, name = rostype.split("/")
    return f"{domain}/{topic.strip('/')}/{pkg}::{kind}::dds_::{name}_/{STORE.hash_rihs01(rostype)}"


def messages(n: int, stamp: float) -> list[tuple[str, str, object]]:
    """The n-th reading of each topic: (topic, type, message)."""
    sec, nanosec = int(stamp), round((stamp % 1) * 1e9)
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="map"
    )
    point = T["geometry_msgs/msg/Point"](x=10.0 + n, y=20.0, z=1.5)
    orientation = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    pose = T["geometry_msgs/msg/PoseStamped"](
        header=header, pose=T["geometry_msgs/msg/Pose"](position=point, orientation=orientation)
    )
    status = T["sensor_msgs/msg/NavSatStatus"](status=0, service=1)
    import numpy as np

    fix = T["sensor_msgs/msg/NavSatFix"](
        header=header,
        status=status,
        latitude=58.39 + n * 1e-5,
        longitude=15.57,
        altitude=80.0,
        position_covariance=np.zeros(9, dtype=np.float64),
        position_covariance_type=0,
    )
    return [
        ("/station/pose", "geometry_msgs/msg/PoseStamped", pose),
        ("/station/fix", "sensor_msgs/msg/NavSatFix", fix),
        ("/station/temperature", "std_msgs/msg/Float64", T["std_msgs/msg/Float64"](data=21.0 + n)),
        ("/station/status", "std_msgs/msg/String", T["std_msgs/msg/String"](data=f"ok {n}")),
    ]


def main(endpoint: str, count: int, stamp: float | None = None) -> None:
    """Connect (client mode, as an rmw_zenoh node would to its router) and publish."""
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as session:
        publishers = {
            topic: session.declare_publisher(key(topic, rostype))
            for topic, rostype, _ in messages(0, 0.0)
        }
        for topic, publisher in publishers.items():
            _await_subscriber(publisher, f"{topic} at {endpoint}")
        for n in range(count):
            t = stamp + n if stamp is not None else time.time()
            for topic, rostype, msg in messages(n, t):
                publishers[topic].put(bytes(STORE.serialize_cdr(msg, rostype)))
            time.sleep(0.1)
        # not CDR: counted as a bad message by the node, which goes on
        publishers["/station/status"].put(b"\x00\x01")


def _await_subscriber(publisher: zenoh.Publisher, what: str, timeout: float = 30.0) -> None:
    """Return once a subscription matches: zenoh drops a put that none routes."""
    matched = threading.Event()

    def status(change: zenoh.MatchingStatus) -> None:
        if change.matching:  # told at once when one matches already
            matched.set()

    with publisher.declare_matching_listener(status):
        if not matched.wait(timeout):
            sys.exit(f"no subscriber of {what} within {timeout:g} s")


if __name__ == "__main__":
    main(
        sys.argv[1],
        int(sys.argv[2]) if len(sys.argv) > 2 else 5,
        float(sys.argv[3]) if len(sys.argv) > 3 else None,
    )
