"""The explicit table of supported schemas: (message encoding, schema name) -> decoder.

Decoding is chosen by the channel's encoding and schema name only, never by its topic.
A `geometry_msgs/TransformStamped` is read as a pose (kind "pose", like a PoseStamped: the
topic says whose pose it is), its header and child frame ids kept in the record.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

from . import foxglove, ros1, ros2, ros_common
from .base import Deserializer, SchemaDecoder

DECODERS: dict[tuple[str, str], SchemaDecoder] = {
    # ROS 2
    ("cdr", "sensor_msgs/msg/CompressedImage"): SchemaDecoder(
        "image", ros2.DECODE.compressed_image
    ),
    ("cdr", "sensor_msgs/msg/Image"): SchemaDecoder("image", ros2.DECODE.raw_image),
    ("cdr", "sensor_msgs/msg/CameraInfo"): SchemaDecoder("camera_info", ros2.DECODE.camera_info),
    ("cdr", "geometry_msgs/msg/PoseStamped"): SchemaDecoder("pose", ros2.DECODE.pose_stamped),
    ("cdr", "geometry_msgs/msg/TransformStamped"): SchemaDecoder(
        "pose", partial(ros_common.transform_stamped, ros=ros2.FLAVOR)),
    ("cdr", "tf2_msgs/msg/TFMessage"): SchemaDecoder("transforms", ros2.DECODE.tf_message),
    ("cdr", "sensor_msgs/msg/JointState"): SchemaDecoder("joint_states", ros2.DECODE.joint_state),
    # ROS 1 (converted bags, e.g. Raven-II / dVRK recordings)
    ("ros1", "sensor_msgs/CompressedImage"): SchemaDecoder("image", ros1.DECODE.compressed_image),
    ("ros1", "sensor_msgs/Image"): SchemaDecoder("image", ros1.DECODE.raw_image),
    ("ros1", "sensor_msgs/CameraInfo"): SchemaDecoder("camera_info", ros1.DECODE.camera_info),
    ("ros1", "geometry_msgs/PoseStamped"): SchemaDecoder("pose", ros1.DECODE.pose_stamped),
    ("ros1", "geometry_msgs/TransformStamped"): SchemaDecoder(
        "pose", partial(ros_common.transform_stamped, ros=ros1.FLAVOR)),
    ("ros1", "tf2_msgs/TFMessage"): SchemaDecoder("transforms", ros1.DECODE.tf_message),
    ("ros1", "tf/tfMessage"): SchemaDecoder("transforms", ros1.DECODE.tf_message),
    ("ros1", "sensor_msgs/JointState"): SchemaDecoder("joint_states", ros1.DECODE.joint_state),
    # Foxglove, protobuf
    ("protobuf", "foxglove.CompressedImage"): SchemaDecoder("image", foxglove.compressed_image),
    ("protobuf", "foxglove.RawImage"): SchemaDecoder("image", foxglove.raw_image),
    ("protobuf", "foxglove.CompressedVideo"): SchemaDecoder("image", foxglove.compressed_video),
    ("protobuf", "foxglove.CameraCalibration"): SchemaDecoder(
        "camera_info", foxglove.camera_calibration
    ),
    ("protobuf", "foxglove.PoseInFrame"): SchemaDecoder("pose", foxglove.pose_in_frame),
    ("protobuf", "foxglove.FrameTransform"): SchemaDecoder("transforms", foxglove.frame_transform),
    ("protobuf", "foxglove.FrameTransforms"): SchemaDecoder(
        "transforms", foxglove.frame_transforms
    ),
    ("protobuf", "foxglove.JointStates"): SchemaDecoder("joint_states", foxglove.joint_states),
    # Foxglove, JSON
    ("json", "foxglove.CompressedImage"): SchemaDecoder("image", foxglove.compressed_image),
    ("json", "foxglove.RawImage"): SchemaDecoder("image", foxglove.raw_image),
    ("json", "foxglove.CompressedVideo"): SchemaDecoder("image", foxglove.compressed_video),
    ("json", "foxglove.CameraCalibration"): SchemaDecoder(
        "camera_info", foxglove.camera_calibration
    ),
    ("json", "foxglove.PoseInFrame"): SchemaDecoder("pose", foxglove.pose_in_frame),
    ("json", "foxglove.FrameTransform"): SchemaDecoder("transforms", foxglove.frame_transform),
    ("json", "foxglove.FrameTransforms"): SchemaDecoder("transforms", foxglove.frame_transforms),
    ("json", "foxglove.JointStates"): SchemaDecoder("joint_states", foxglove.joint_states),
}

JSON_JOINT_STATES = SchemaDecoder("joint_states", foxglove.json_joint_states)
"""Joint states in any other JSON schema: an object with `name` and `position` arrays."""

DESERIALIZERS: dict[str, Callable[[], Deserializer]] = {
    "cdr": ros2.Ros2Deserializer,
    "ros1": ros1.Ros1Deserializer,
    "protobuf": foxglove.ProtobufDeserializer,
    "json": foxglove.JsonDeserializer,
}


def find_decoder(
    message_encoding: str, schema_name: str, kinds: tuple[str, ...]
) -> SchemaDecoder | None:
    """The decoder for a channel if its schema carries one of `kinds`, else None."""
    decoder = DECODERS.get((message_encoding, schema_name))
    if decoder is None and message_encoding == "json" and "joint_states" in kinds:
        decoder = JSON_JOINT_STATES
    if decoder is None or decoder.kind not in kinds:
        return None
    return decoder


def supported(kinds: tuple[str, ...]) -> list[str]:
    """'schema (encoding)' of every supported schema carrying one of `kinds`."""
    out = [f"{name} ({enc})" for (enc, name), dec in DECODERS.items() if dec.kind in kinds]
    if "joint_states" in kinds:
        out.append("any JSON with name/position arrays (json)")
    return out


def no_images_message(path: object) -> str:
    """The one line for a log with no channel of an image schema (info and ingest say it)."""
    return (f"{path}: no camera images in this log (no channel of an image schema surgrecon "
            "reads, e.g. sensor_msgs/msg/CompressedImage or foxglove.CompressedImage); surgrecon "
            "reconstructs from camera images, so no [topics] config can make it run on this log")
