"""MCAP writing (sim.log_writer) and reading (io.logs): every encoding round-trips records;
dispatch by schema; stamps; damage handling; deterministic, atomic writes."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
import synth_log
from mcap.reader import make_reader

from surgrecon_cli.config import IngestConfig, TopicsConfig
from surgrecon_cli.errors import InputError, TopicError
from surgrecon_cli.io.logs.encodings.registry import DECODERS
from surgrecon_cli.io.logs.reader import LogReader
from surgrecon_cli.io.logs.records import (
    CameraInfoRecord,
    ImageRecord,
    JointStateRecord,
    PoseRecord,
)
from surgrecon_cli.io.logs.transforms import read_transforms
from surgrecon_cli.sim.log_writer import ENCODINGS, write_log

T0 = synth_log.T0
MS = synth_log.MS
TOPICS = TopicsConfig(
    image="/cam_{camera}/image", camera_info="/cam_{camera}/info", camera_pose="/tf",
    camera_frame="cam_{camera}_optical", tool_pose="/tool", joint_states="/joints",
)
SCHEMAS = {
    "ros2": {"sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image",
             "sensor_msgs/msg/CameraInfo", "geometry_msgs/msg/PoseStamped",
             "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/JointState"},
    "ros1": {"sensor_msgs/CompressedImage", "sensor_msgs/Image", "sensor_msgs/CameraInfo",
             "geometry_msgs/PoseStamped", "tf2_msgs/TFMessage", "sensor_msgs/JointState"},
    "foxglove-protobuf": {"foxglove.CompressedImage", "foxglove.RawImage",
                          "foxglove.CameraCalibration", "foxglove.PoseInFrame",
                          "foxglove.FrameTransforms", "foxglove.JointStates"},
    "foxglove-json": {"foxglove.CompressedImage", "foxglove.RawImage",
                      "foxglove.CameraCalibration", "foxglove.PoseInFrame",
                      "foxglove.FrameTransforms", "surgrecon.JointStates"},
}


def _records():
    rgb = synth_log.image_rgb(1, 2)
    K = synth_log.intrinsics(1)
    return [
        ("/cam_1/info", T0 + 1, CameraInfoRecord(T0, "cam_1_optical", 64, 48, K,
                                                 np.array([-0.1, 0.01, 1e-4, -2e-4, 0.001]))),
        ("/cam_1/image", T0 + 2, ImageRecord(T0 + 5 * MS, "cam_1_optical", "png",
                                             synth_log.encode(rgb, "png"))),
        ("/cam_2/image", T0 + 3, ImageRecord(T0 + 6 * MS, "cam_2_optical", "rgb8",
                                             rgb.tobytes(), 64, 48, 192)),
        ("/tf", T0 + 4, PoseRecord(T0 + 7 * MS, "world", "cam_1_optical",
                                   np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.6, 0.0, 0.8]))),
        ("/tf", T0 + 4, PoseRecord(T0 + 7 * MS, "world", "unrelated_frame",
                                   np.array([9.0, 9, 9]), np.array([0.0, 0, 0, 1]))),
        ("/tool", T0 + 5, PoseRecord(T0 + 8 * MS, "world", "", np.array([-1.0, 2, -3]),
                                     np.array([0.5, 0.5, 0.5, 0.5]))),
        ("/joints", T0 + 6, JointStateRecord(T0 + 9 * MS, ("a", "b"), np.array([0.25, -1.5]))),
        ("/unrelated", T0 + 7, JointStateRecord(T0, ("z",), np.array([1.0]))),
    ]


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_round_trip_every_record_type(tmp_path: Path, encoding: str):
    path = tmp_path / "log.mcap"
    written = _records()
    write_log(path, written, encoding)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        names = {s.name for s in summary.schemas.values()}
        header = reader.get_header()
    assert names == SCHEMAS[encoding]
    assert header.profile == {"ros1": "ros1", "ros2": "ros2"}.get(encoding, "")

    reader = LogReader(path, TOPICS)
    items = list(reader)
    reader.check_roles()
    # Transforms (/tf) go to the TF tree, not through the role stream.
    assert [(i.role, i.camera, i.topic) for i in items] == [
        ("camera_info", "1", "/cam_1/info"), ("image", "1", "/cam_1/image"),
        ("image", "2", "/cam_2/image"), ("tool_pose", "", "/tool"),
        ("joint_states", "", "/joints"),
    ]
    expected = [r for _, _, r in written]
    tf = read_transforms(path).samples  # every transform, whatever its frames
    assert list(zip(tf.parent, tf.child, strict=True)) == [
        (r.frame_id, r.child_frame_id) for r in expected[3:5]]
    for k, want_tf in enumerate(expected[3:5]):
        np.testing.assert_array_equal(tf.translations[k], want_tf.position)
        np.testing.assert_array_equal(tf.quats[k], want_tf.orientation)
    for item, want in zip(items, [expected[i] for i in (0, 1, 2, 5, 6)], strict=True):
        got = item.record
        assert type(got) is type(want) and got.stamp_ns == want.stamp_ns
        if isinstance(want, CameraInfoRecord):
            np.testing.assert_array_equal(got.K, want.K)
            np.testing.assert_array_equal(got.D, want.D)
            assert (got.width, got.height, got.frame_id) == (64, 48, "cam_1_optical")
        elif isinstance(want, ImageRecord):
            assert (got.format, got.data, got.width, got.height, got.step) == (
                want.format, want.data, want.width, want.height, want.step)
        elif isinstance(want, PoseRecord):
            np.testing.assert_array_equal(got.position, want.position)
            np.testing.assert_array_equal(got.orientation, want.orientation)
            assert (got.frame_id, got.child_frame_id) == (want.frame_id, want.child_frame_id)
        else:
            assert got.names == want.names
            np.testing.assert_array_equal(got.positions, want.positions)
    assert reader.damage is None and reader.valid_bytes == path.stat().st_size
    assert len(reader.sha256) == 64


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_writer_is_deterministic_and_atomic(tmp_path: Path, encoding: str):
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    write_log(a, _records(), encoding)
    write_log(b, _records(), encoding)
    assert a.read_bytes() == b.read_bytes()

    def failing():
        yield from _records()[:3]
        raise RuntimeError("renderer crashed")

    with pytest.raises(RuntimeError):
        write_log(tmp_path / "c.mcap", failing(), encoding)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap"]


def test_writer_rejects_bad_input(tmp_path: Path):
    recs = _records()
    with pytest.raises(ValueError, match="log times must not decrease"):
        write_log(tmp_path / "x.mcap", [recs[1], recs[0]], "ros2")
    with pytest.raises(ValueError, match="unknown log encoding"):
        write_log(tmp_path / "x.mcap", recs, "rosbag")
    assert not (tmp_path / "x.mcap").exists()


def test_zero_stamp_uses_log_time_and_config_can_force_log_time(tmp_path: Path):
    path = tmp_path / "log.mcap"
    pose = PoseRecord(0, "world", "", np.zeros(3), np.array([0.0, 0, 0, 1]))
    write_log(path, [("/tool", T0 + 42, pose),
                     ("/joints", T0 + 50, JointStateRecord(T0 + 7, ("a",), np.zeros(1)))], "ros2")
    items = list(LogReader(path, TOPICS, require_roles=False))
    assert [i.record.stamp_ns for i in items] == [T0 + 42, T0 + 7]
    forced = list(LogReader(path, TOPICS, IngestConfig(time_source="log_time").time_source,
                            require_roles=False))
    assert [i.record.stamp_ns for i in forced] == [T0 + 42, T0 + 50]


def test_roles_come_from_schema_not_topic_name(tmp_path: Path):
    # A CameraInfo on the image topic: named error listing the supported image schemas.
    path = tmp_path / "log.mcap"
    recs = _records()
    write_log(path, [("/cam_1/image", T0, recs[0][2])], "foxglove-protobuf")
    with pytest.raises(TopicError) as exc:
        list(LogReader(path, TOPICS))
    msg = str(exc.value)
    assert "/cam_1/image" in msg and "foxglove.CameraCalibration" in msg
    assert "sensor_msgs/msg/CompressedImage" in msg and "\n" not in msg
    # Poses on a topic named like an image topic are not images: no role, ignored.
    write_log(path, [("/images/not_really", T0, recs[5][2])], "ros2")
    assert list(LogReader(path, TOPICS, require_roles=False)) == []


def test_registry_covers_the_spec_table():
    keys = set(DECODERS)
    for name in ("CompressedImage", "RawImage", "CameraCalibration", "PoseInFrame",
                 "FrameTransform", "FrameTransforms", "JointStates"):
        assert ("protobuf", f"foxglove.{name}") in keys and ("json", f"foxglove.{name}") in keys
    for name in ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image",
                 "sensor_msgs/msg/CameraInfo", "geometry_msgs/msg/PoseStamped",
                 "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/JointState"):
        assert ("cdr", name) in keys and ("ros1", name.replace("/msg/", "/")) in keys


def test_missing_role_lists_existing_topics(tmp_path: Path):
    path = tmp_path / "log.mcap"
    write_log(path, _records()[:3], "ros1")
    with pytest.raises(TopicError) as exc:
        list(LogReader(path, TOPICS))  # found from the summary, before streaming
    msg = str(exc.value)
    assert "topics.camera_pose = '/tf'" in msg and "topics.tool_pose = '/tool'" in msg
    assert "/cam_1/info  sensor_msgs/CameraInfo (ros1)" in exc.value.details


def _summary_start(data: bytes) -> int:
    return struct.unpack("<Q", data[-28:-20])[0]


def test_truncated_log_error_and_allow_truncated(tmp_path: Path):
    full = synth_log.write(tmp_path / "full.mcap", chunk_size=4096)
    data = full.read_bytes()
    n_all = len(list(LogReader(full, TopicsConfig())))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: _summary_start(data) // 2])
    with pytest.raises(InputError) as exc:
        list(LogReader(cut, TopicsConfig()))
    msg = str(exc.value)
    assert "truncated" in msg and "--allow-truncated" in msg and "valid data ends at byte" in msg
    reader = LogReader(cut, TopicsConfig(), allow_truncated=True)
    n_cut = len(list(reader))
    assert 0 < n_cut < n_all
    assert reader.damage is not None and 0 < reader.valid_bytes < len(data) // 2


def test_not_an_mcap_file(tmp_path: Path):
    path = tmp_path / "log.mcap"
    path.write_text("this is a bag file\n")
    with pytest.raises(InputError, match="not an MCAP file"):
        list(LogReader(path, TopicsConfig()))


def test_json_frame_transform_generic_joint_states_and_ros1_tf(tmp_path: Path):
    import json

    from mcap.writer import Writer

    path = tmp_path / "log.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        tf = w.register_schema("foxglove.FrameTransform", "jsonschema", b"{}")
        js = w.register_schema("dvrk.JointStateCurrent", "jsonschema", b"{}")
        ch_tf = w.register_channel("/tf", "json", tf)
        ch_js = w.register_channel("/joints", "json", js)
        msg = {"timestamp": {"sec": 3, "nsec": 4}, "parent_frame_id": "world",
               "child_frame_id": "cam_5_optical", "translation": {"x": 1, "y": 2, "z": 3},
               "rotation": {"x": 0, "y": 0, "z": 1, "w": 0}}
        w.add_message(ch_tf, 10, json.dumps(msg).encode(), 10)
        w.add_message(ch_js, 11, json.dumps({"name": ["a"], "position": [0.5]}).encode(), 11)
        w.finish()
    items = list(LogReader(path, TOPICS, require_roles=False))
    assert [(i.role, i.camera) for i in items] == [("joint_states", "")]
    joints = items[0].record
    assert joints.stamp_ns == 11
    assert joints.names == ("a",) and joints.positions.tolist() == [0.5]
    tf = read_transforms(path).samples  # the transform goes to the TF tree
    assert (list(tf.parent), list(tf.child)) == (["world"], ["cam_5_optical"])
    assert tf.stamps_ns.tolist() == [3_000_000_004]
    np.testing.assert_array_equal(tf.quats[0], [0, 0, 1, 0])
    np.testing.assert_array_equal(tf.translations[0], [1, 2, 3])


def test_cache_dropping_writer_keeps_every_byte(tmp_path: Path):
    """Writes that cross the drop interval many times (syncs in flight meanwhile) give the
    file a plain write gives, and `tell` counts every byte."""
    from surgrecon_cli.io.run.atomic import CacheDropping, atomic_open

    rng = np.random.default_rng(3)
    parts = [rng.integers(0, 256, int(n), dtype=np.uint8).tobytes()
             for n in rng.integers(1, 5000, 200)]
    with atomic_open(tmp_path / "a.bin", "wb") as handle:
        stream = CacheDropping(handle, every=4096)
        for part in parts:
            stream.write(part)
        assert stream.tell() == sum(len(p) for p in parts)
        stream.close()
    assert (tmp_path / "a.bin").read_bytes() == b"".join(parts)
