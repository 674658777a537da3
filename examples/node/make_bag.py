"""Write the recordings station-rosbag.toml replays: a rosbag2 bag (rosbags) and an MCAP
file (mcap), each of ten messages 0.1 s apart from 1764000000 s.

Run from examples/node: python make_bag.py
"""

from __future__ import annotations

import shutil
from pathlib import Path

from mcap.writer import Writer as McapWriter
from publish_ros2 import STORE, messages
from rosbags.rosbag2 import StoragePlugin, Writer

T0 = 1764000000.0
HERE = Path(__file__).resolve().parent


def main(out: Path = HERE / "recorded") -> None:
    """Write ``out/station_bag`` (rosbag2, MCAP storage) and ``out/station.mcap``."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    pose = "geometry_msgs/msg/PoseStamped"
    with Writer(out / "station_bag", version=9, storage_plugin=StoragePlugin.MCAP) as bag:
        conn = bag.add_connection("/station/pose", pose, typestore=STORE)
        for n in range(10):
            t = T0 + 0.1 * n
            _, _, msg = messages(n, t)[0]
            bag.write(conn, int(t * 1e9), bytes(STORE.serialize_cdr(msg, pose)))
    float64 = "std_msgs/msg/Float64"
    with (out / "station.mcap").open("wb") as f:
        mcap = McapWriter(f)
        mcap.start(profile="ros2", library="make_bag.py")
        msgdef, _ = STORE.generate_msgdef(float64)
        schema = mcap.register_schema(float64, "ros2msg", msgdef.encode())
        channel = mcap.register_channel("/station/temperature", "cdr", schema)
        for n in range(10):
            t = int((T0 + 0.1 * n) * 1e9)
            _, _, msg = messages(n, T0)[2]
            mcap.add_message(channel, t, bytes(STORE.serialize_cdr(msg, float64)), t, n)
        mcap.finish()


if __name__ == "__main__":
    main()
