"""ROS 1 (`ros1` messages, `ros1msg` schemas `pkg/Type`), decoded by `mcap_ros1`.

Differences from ROS 2 handled here: stamps are `secs/nsecs`, CameraInfo uses `D K R P`.
"""

from __future__ import annotations

from functools import partial

from mcap_ros1.decoder import DecoderFactory

from . import ros_common
from .base import stamp_ns

Ros1Deserializer = partial(ros_common.FactoryDeserializer, DecoderFactory, "ros1", "ros1msg")
"""ROS 1 bytes -> message objects with attribute access."""

FLAVOR = ros_common.RosFlavor(
    stamp=lambda header: stamp_ns(header.stamp.secs, header.stamp.nsecs), d="D", k="K", r="R",
    p="P")

DECODE = ros_common.bind(FLAVOR)
