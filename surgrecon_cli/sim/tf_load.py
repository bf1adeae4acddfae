"""A TF-heavy ROS 2 log, for the TF memory benchmark and its test.

`/tf` messages (`tf2_msgs/msg/TFMessage`, cdr, zstd chunks) at `rate_hz`, each holding the
transforms of a robot's `links` frames at one stamp: a chain world -> link_0 -> link_1 -> ...
(joints turning about z, 1 cm apart), as a robot's state publisher sends them. Only TF: the
log is read with `io.logs.transforms.read_transforms`, not ingested.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as Ros2Writer

from ..io.logs.records import PoseRecord
from ..io.run.atomic import atomic_open
from .ros_encoding import MSGS_ROS2, full_text, ros_message

T0_NS = 1_700_000_000_000_000_000


def link_frames(links: int) -> list[str]:
    """Frame names of the chain, world first."""
    return ["world", *(f"link_{k}" for k in range(links))]


def write_tf_log(path: Path, samples: int, links: int = 20, rate_hz: float = 1000.0) -> int:
    """Write about `samples` transforms (whole messages of `links` each) to `path`;
    returns the number written."""
    frames = link_frames(links)
    messages = math.ceil(samples / links)
    period_ns = round(1e9 / rate_hz)
    with atomic_open(Path(path), "wb") as stream:
        writer = Ros2Writer(stream, chunk_size=1 << 20, compression=CompressionType.ZSTD)
        schema = writer.register_msgdef("tf2_msgs/msg/TFMessage",
                                        full_text("tf2_msgs/TFMessage", MSGS_ROS2))
        for m in range(messages):
            stamp = T0_NS + m * period_ns
            angles = 0.3 * np.sin(1e-3 * m + np.arange(links))
            transforms = [ros_message(PoseRecord(
                stamp, frames[k], frames[k + 1], np.array([0.01, 0.0, 0.0]),
                np.array([0.0, 0.0, math.sin(a / 2), math.cos(a / 2)])), ros1=False)[1][
                    "transforms"][0] for k, a in enumerate(angles)]
            writer.write_message("/tf", schema, {"transforms": transforms}, log_time=stamp,
                                 publish_time=stamp, sequence=m)
        writer.finish()
    return messages * links
