"""ROS 2 (`cdr` messages, `ros2msg` schemas `pkg/msg/Type`), decoded by `mcap_ros2`."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from . import ros_common
from .base import stamp_ns


class Ros2Deserializer:
    """CDR bytes -> message objects with attribute access (one generated decoder per schema)."""

    message_encoding = "cdr"

    def __init__(self) -> None:
        self._factory = DecoderFactory()

    def for_schema(self, schema: Schema | None) -> Callable[[bytes], Any]:
        decoder = self._factory.decoder_for(self.message_encoding, schema)
        if decoder is None:
            raise ValueError("ROS 2 messages need a ros2msg schema")
        return decoder


FLAVOR = ros_common.RosFlavor(
    stamp=lambda header: stamp_ns(header.stamp.sec, header.stamp.nanosec), d="d", k="k")

compressed_image = partial(ros_common.compressed_image, ros=FLAVOR)
raw_image = partial(ros_common.raw_image, ros=FLAVOR)
camera_info = partial(ros_common.camera_info, ros=FLAVOR)
pose_stamped = partial(ros_common.pose_stamped, ros=FLAVOR)
tf_message = partial(ros_common.tf_message, ros=FLAVOR)
joint_state = partial(ros_common.joint_state, ros=FLAVOR)
