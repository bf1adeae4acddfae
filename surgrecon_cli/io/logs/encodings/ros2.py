"""ROS 2 (`cdr` messages, `ros2msg` schemas `pkg/msg/Type`), decoded by `mcap_ros2`."""

from __future__ import annotations

from functools import partial

from mcap_ros2.decoder import DecoderFactory

from . import ros_common
from .base import stamp_ns

Ros2Deserializer = partial(ros_common.FactoryDeserializer, DecoderFactory, "cdr", "ros2msg")
"""CDR bytes -> message objects with attribute access."""

FLAVOR = ros_common.RosFlavor(
    stamp=lambda header: stamp_ns(header.stamp.sec, header.stamp.nanosec), d="d", k="k", r="r",
    p="p")

DECODE = ros_common.bind(FLAVOR)
