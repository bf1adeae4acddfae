"""The TF tree (core.sync.tf_tree) and the transform channels of MCAP logs (io.logs.transforms):
composition through the common ancestor, interpolation and its limits, static edges, clear
errors, and /tf + /tf_static decoded from every encoding (multi-transform messages too)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import synth_log
from mcap.writer import Writer

from surgrecon_cli.core.geometry.poses import invert_pose, make_pose
from surgrecon_cli.core.sync.tf_samples import concat_samples, make_samples
from surgrecon_cli.core.sync.tf_tree import build_tf_tree
from surgrecon_cli.errors import InputError
from surgrecon_cli.io.logs.records import PoseRecord
from surgrecon_cli.io.logs.transforms import is_static_channel, read_transforms
from surgrecon_cli.sim.log_writer import ENCODINGS, write_log

T0 = synth_log.T0
MS = synth_log.MS
GAP = 100 * MS
CAMERAS = (0, 1, 2)


# -- a TF tree: world -> tracker -> endoscope_c_marker -> endoscope_c_optical, -------------
# --            world -> psm1_base -> psm1_tool_tip  (static edges: S, dynamic: D) ------------
def _quat(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.append(np.sin(angle / 2) * axis, np.cos(angle / 2))


WORLD_TRACKER = (np.array([0.5, -0.2, 1.0]), _quat([0, 0, 1], 0.7))        # S
HAND_EYE = {c: (np.array([0.01 * c, 0.02, 0.15]), _quat([1, c, 0.5], 0.3)) for c in CAMERAS}
WORLD_BASE = (np.array([-0.3, 0.4, 0.2]), _quat([0, 1, 0], -0.4))           # S


def marker_pose(c: int, t_ns: np.ndarray) -> np.ndarray:
    """Marker of camera c in the tracker (D, 40 Hz), linear + constant-axis rotation: exact
    under linear + slerp interpolation."""
    return synth_log.camera_pose(c, t_ns)


def tip_pose(t_ns: np.ndarray) -> np.ndarray:
    """Tool tip in the robot base (D, 100 Hz)."""
    p = synth_log.tool_position(t_ns)
    return make_pose(p, np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(p), 4)))


def truth(frame: str, t_ns: np.ndarray) -> np.ndarray:
    """T_world_frame (Q, 4, 4)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if frame == "world":
        return np.broadcast_to(np.eye(4), (len(t_ns), 4, 4)).copy()
    tracker = make_pose(*WORLD_TRACKER)
    base = make_pose(*WORLD_BASE)
    if frame == "tracker":
        return np.broadcast_to(tracker, (len(t_ns), 4, 4)).copy()
    if frame.endswith("_marker") or frame.endswith("_optical"):
        c = int(frame.split("_")[1])
        out = tracker @ marker_pose(c, t_ns)
        return out @ make_pose(*HAND_EYE[c]) if frame.endswith("_optical") else out
    if frame == "psm1_base":
        return np.broadcast_to(base, (len(t_ns), 4, 4)).copy()
    return base @ tip_pose(t_ns)


TRACKER_STAMPS = np.arange(T0, T0 + 1000 * MS, 25 * MS)
ROBOT_STAMPS = np.arange(T0, T0 + 1000 * MS, 10 * MS)


def tf_messages() -> list[tuple[str, int, list[PoseRecord]]]:
    """(topic, log time, transforms) of the tree: every tracker message holds all markers;
    /tf_static once at the start and once again (latched re-publication)."""
    out = []
    static = [PoseRecord(T0, "world", "tracker", *WORLD_TRACKER),
              PoseRecord(T0, "world", "psm1_base", *WORLD_BASE)]
    static += [PoseRecord(T0, f"endoscope_{c}_marker", f"endoscope_{c}_optical", *HAND_EYE[c])
               for c in CAMERAS]
    out.append(("/tf_static", T0 - MS, static))
    for t in TRACKER_STAMPS:
        recs = []
        for c in CAMERAS:
            T = marker_pose(c, np.array([t]))[0]
            recs.append(PoseRecord(int(t), "tracker", f"endoscope_{c}_marker", T[:3, 3],
                                   synth_log.camera_quat(c, np.array([t]))[0]))
        out.append(("/tf", int(t) + MS, recs))
    for t in ROBOT_STAMPS:
        p = synth_log.tool_position(np.array([t]))[0]
        out.append(("/tf", int(t) + 2 * MS,
                    [PoseRecord(int(t), "psm1_base", "psm1_tool_tip", p,
                                np.array([0.0, 0, 0, 1]))]))
    out.append(("/tf_static", T0 + 500 * MS, static))
    out.sort(key=lambda m: m[1])
    return out


def _tree_samples():
    msgs = tf_messages()
    recs = [(r, topic == "/tf_static") for topic, _, rs in msgs for r in rs]
    return make_samples([r.frame_id for r, _ in recs], [r.child_frame_id for r, _ in recs],
                        [r.stamp_ns for r, _ in recs], [r.position for r, _ in recs],
                        [r.orientation for r, _ in recs], [s for _, s in recs])


# -- core ------------------------------------------------------------------------------------
def test_lookup_composes_up_and_down_through_the_common_ancestor():
    tree = build_tf_tree(_tree_samples())
    q = np.array([T0 + 30 * MS, T0 + 412 * MS + 7, T0 + 975 * MS])  # between samples
    for frame in ("endoscope_0_optical", "endoscope_2_optical", "psm1_tool_tip", "tracker"):
        np.testing.assert_allclose(tree.lookup("world", frame, q, GAP), truth(frame, q),
                                   atol=1e-9)
    # camera 1 in camera 0 (common ancestor: tracker), the tool in camera 2 (ancestor: world)
    np.testing.assert_allclose(
        tree.lookup("endoscope_0_optical", "endoscope_1_optical", q, GAP),
        invert_pose(truth("endoscope_0_optical", q)) @ truth("endoscope_1_optical", q),
        atol=1e-9)
    np.testing.assert_allclose(
        tree.lookup("endoscope_2_optical", "psm1_tool_tip", q, GAP),
        invert_pose(truth("endoscope_2_optical", q)) @ truth("psm1_tool_tip", q), atol=1e-9)
    np.testing.assert_allclose(tree.lookup("tracker", "tracker", q, GAP),
                               np.broadcast_to(np.eye(4), (3, 4, 4)))
    up, down = tree.chain("psm1_tool_tip", "endoscope_0_optical")
    assert [e.child for e in up] == ["endoscope_0_optical", "endoscope_0_marker", "tracker"]
    assert [e.child for e in down] == ["psm1_tool_tip", "psm1_base"]


def test_static_edges_hold_for_the_whole_log_and_dynamic_ones_are_never_extrapolated():
    tree = build_tf_tree(_tree_samples())
    last = int(TRACKER_STAMPS[-1])
    q = np.array([T0 - 10_000 * MS, T0, last, last + 1, T0 + 99_000 * MS])
    static = tree.lookup("world", "psm1_base", q, GAP)  # static chain: valid at any stamp
    np.testing.assert_allclose(static, truth("psm1_base", q))
    cam = tree.lookup("world", "endoscope_1_optical", q, GAP)
    assert np.isfinite(cam[:, 0, 0]).tolist() == [False, True, True, False, False]
    assert np.isnan(cam[[0, 3, 4]]).all()  # whole matrices NaN, not just some entries
    np.testing.assert_allclose(cam[[1, 2]], truth("endoscope_1_optical", q[[1, 2]]), atol=1e-9)
    # a gap longer than the tolerance: invalid; shorter: interpolated
    s = _tree_samples()
    k = s.static | (s.stamps_ns < T0 + 300 * MS) | (s.stamps_ns > T0 + 500 * MS)
    gappy = build_tf_tree(make_samples(s.parent[k], s.child[k], s.stamps_ns[k],
                                       s.translations[k], s.quats[k], s.static[k]))
    mid = np.array([T0 + 400 * MS])
    assert np.isnan(gappy.lookup("world", "endoscope_0_optical", mid, GAP)).all()
    assert np.isfinite(gappy.lookup("world", "endoscope_0_optical", mid, 300 * MS)).all()


def test_lookup_is_vectorised_over_stamps_in_any_order():
    tree = build_tf_tree(_tree_samples())
    q = np.random.default_rng(3).integers(T0, T0 + 975 * MS, 5000)
    out = tree.lookup("psm1_tool_tip", "endoscope_0_optical", q, GAP)
    assert out.shape == (5000, 4, 4) and np.isfinite(out).all()
    np.testing.assert_allclose(
        out, invert_pose(truth("psm1_tool_tip", q)) @ truth("endoscope_0_optical", q),
        atol=1e-9)


def test_describe_lists_frames_parents_kinds_and_rates():
    tree = build_tf_tree(_tree_samples())
    rows = {s.frame: s for s in tree.describe()}
    assert [s.frame for s in tree.describe()][:3] == ["world", "psm1_base", "psm1_tool_tip"]
    assert rows["world"].parent == "" and rows["world"].depth == 0
    assert rows["tracker"].static and rows["tracker"].samples == 2  # published twice
    marker = rows["endoscope_1_marker"]
    assert (marker.parent, marker.static, marker.samples, marker.depth) == (
        "tracker", False, 40, 2)
    assert marker.rate_hz == pytest.approx(40.0)
    assert rows["psm1_tool_tip"].rate_hz == pytest.approx(100.0)
    assert rows["endoscope_1_optical"].depth == 3
    assert tree.roots == ("world",) and len(tree.frames) == 10
    assert tree.parent("endoscope_2_optical") == "endoscope_2_marker"
    assert tree.parent("world") is None


def test_the_last_static_transform_wins():
    a = make_samples(["w", "w"], ["s", "s"], [T0 + 5, T0], [[1, 0, 0], [2, 0, 0]],
                     [[0, 0, 0, 1]] * 2, True)
    tree = build_tf_tree(a)
    np.testing.assert_allclose(tree.lookup("w", "s", [0], GAP)[0, :3, 3], [2, 0, 0])


def test_errors_name_the_frames():
    tree = build_tf_tree(concat_samples([
        _tree_samples(),
        make_samples(["map"], ["odom"], [T0], [[0, 0, 0]], [[0, 0, 0, 1]], True)]))
    with pytest.raises(InputError) as exc:
        tree.lookup("world", "odom", [T0], GAP)
    msg = str(exc.value)
    assert "'world' and 'odom' are not connected" in msg and "under 'map'" in msg
    assert "frames in the tree: endoscope_0_marker" in msg and "\n" not in msg
    with pytest.raises(InputError, match="'camera_9' is not in the TF tree; frames in the tree"):
        tree.lookup("world", "camera_9", [T0], GAP)

    two = make_samples(["world", "tracker", "tracker"], ["cam", "cam", "cam"], [T0, T0, T0 + 1],
                       np.zeros((3, 3)), [[0, 0, 0, 1]] * 3)
    # a bad edge is left out (tf2 only warns); a lookup that needs it says why
    with pytest.raises(InputError, match=r"'cam' has 2 parents: 'tracker' \(2 transforms\), "
                                         r"'world' \(1 transform\)"):
        build_tf_tree(two).lookup("world", "cam", [T0], GAP)
    cycle = make_samples(["a", "b", "c"], ["b", "c", "a"], [T0] * 3, np.zeros((3, 3)),
                         [[0, 0, 0, 1]] * 3)
    with pytest.raises(InputError, match="cycle: a -> b -> c -> a"):
        build_tf_tree(cycle).lookup("a", "b", [T0], GAP)
    mixed = make_samples(["w", "w"], ["c", "c"], [T0, T0 + 1], np.zeros((2, 3)),
                         [[0, 0, 0, 1]] * 2, [True, False])
    with pytest.raises(InputError, match=r"both as static .* and as dynamic"):
        build_tf_tree(mixed).lookup("w", "c", [T0], GAP)
    bad_q = make_samples(["w"], ["c"], [T0], [[0, 0, 0]], [[0, 0, 0, 2]])
    with pytest.raises(InputError, match=r"'w' -> 'c'.*non-unit quaternion"):
        build_tf_tree(bad_q).lookup("w", "c", [T0], GAP)


def test_problems_on_frames_nobody_uses_leave_the_rest_of_the_tree_usable():
    """NaN, a second parent, a cycle or a self-transform on frames off the camera's chain:
    the tree is built without them, the camera's pose is exact, the problems are listed."""
    good = _tree_samples()
    bad = make_samples(
        ["world", "world", "tracker", "x", "y", "z", "z"],
        ["nan_frame", "two_parents", "two_parents", "y", "x", "z", "z"],
        [T0] * 7, [[np.nan, 0, 0], *[[0, 0, 0]] * 6], [[0, 0, 0, 1]] * 7)
    tree = build_tf_tree(concat_samples([good, bad]))
    q = TRACKER_STAMPS[1:-1] + 7 * MS
    np.testing.assert_allclose(tree.lookup("world", "endoscope_1_optical", q, GAP),
                               truth("endoscope_1_optical", q), atol=1e-9)
    assert set(tree.problems) == {"nan_frame", "two_parents", "x", "y", "z"}
    assert "non-finite" in tree.problems["nan_frame"]
    assert "to itself" in tree.problems["z"] and "cycle" in tree.problems["x"]
    assert "np.str_" not in " ".join(tree.problems.values())
    with pytest.raises(InputError, match="non-finite"):
        tree.lookup("world", "nan_frame", [T0], GAP)


def test_empty_tree():
    tree = build_tf_tree(make_samples([], [], [], [], []))
    assert tree.frames == () and tree.describe() == ()


# -- decoding /tf and /tf_static from MCAP -------------------------------------------------
def _check_decoded(path: Path, **kwargs):
    log = read_transforms(path, **kwargs)
    assert log.topics == {"/tf": False, "/tf_static": True}
    assert log.counts == {"/tf": 3 * len(TRACKER_STAMPS) + len(ROBOT_STAMPS), "/tf_static": 10}
    tree = build_tf_tree(log.samples)
    q = TRACKER_STAMPS[1:-1] + 7 * MS
    for frame in ("endoscope_1_optical", "psm1_tool_tip"):
        np.testing.assert_allclose(tree.lookup("world", frame, q, GAP), truth(frame, q),
                                   atol=1e-9)
    return log


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_single_transform_messages_of_every_encoding(tmp_path: Path, encoding: str):
    """The simulator's writer: one transform per TFMessage / FrameTransforms."""
    path = tmp_path / "tf.mcap"
    write_log(path, [(topic, t, r) for topic, t, rs in tf_messages() for r in rs], encoding)
    log = _check_decoded(path)
    assert log.scan.indexed


def _ros_msg(records, ros1: bool):
    from surgrecon_cli.sim.ros_encoding import ros_message

    msgs = [ros_message(r, ros1=ros1)[1]["transforms"][0] for r in records]
    return {"transforms": msgs}


def _write_multi(path: Path, encoding: str, indexed: bool = True):
    """Several transforms per message, written with the ROS / protobuf / JSON writers;
    Foxglove /tf_static as single `foxglove.FrameTransform` messages."""
    from mcap_protobuf.schema import register_schema

    from surgrecon_cli.sim.foxglove_encoding import foxglove_message
    from surgrecon_cli.sim.ros_encoding import MSGS_ROS1, MSGS_ROS2, full_text, ros1_serialize

    if encoding == "ros2":
        from mcap_ros2.writer import Writer as Ros2Writer

        with open(path, "wb") as f:
            w = Ros2Writer(f)
            schema = w.register_msgdef("tf2_msgs/msg/TFMessage",
                                       full_text("tf2_msgs/TFMessage", MSGS_ROS2))
            for topic, t, recs in tf_messages():
                w.write_message(topic, schema, _ros_msg(recs, False), log_time=t, publish_time=t)
            w.finish()
        return
    opts = {} if indexed else {"use_summary_offsets": False, "use_statistics": False,
                               "use_chunking": False}
    with open(path, "wb") as f:
        w = Writer(f, **opts)
        w.start(profile="ros1" if encoding == "ros1" else "")
        channels: dict[str, int] = {}
        for topic, t, recs in tf_messages():
            if encoding == "ros1":
                name, data = "tf2_msgs/TFMessage", [ros1_serialize(
                    "tf2_msgs/TFMessage", _ros_msg(recs, True), MSGS_ROS1)]
                schema_data, schema_enc = full_text(name, MSGS_ROS1).encode(), "ros1msg"
            else:
                from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
                from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

                transforms = [foxglove_message(r, json_mode=True)[1]["transforms"][0]
                              for r in recs]
                for tr in transforms:
                    sec, nsec = tr["timestamp"]
                    tr["timestamp"] = ({"sec": sec, "nsec": nsec} if encoding == "json"
                                       else {"seconds": sec, "nanos": nsec})
                single = topic == "/tf_static"
                name = "foxglove.FrameTransform" if single else "foxglove.FrameTransforms"
                cls = FrameTransform if single else FrameTransforms
                if encoding == "json":
                    data = ([json.dumps(tr).encode() for tr in transforms] if single
                            else [json.dumps({"transforms": transforms}).encode()])
                    schema_data, schema_enc = b"{}", "jsonschema"
                else:
                    data = ([cls(**tr).SerializeToString() for tr in transforms] if single
                            else [cls(transforms=transforms).SerializeToString()])
                    schema_data, schema_enc = cls, "protobuf"
            if topic not in channels:
                sid = (register_schema(w, schema_data) if schema_enc == "protobuf"
                       else w.register_schema(name, schema_enc, schema_data))
                channels[topic] = w.register_channel(
                    topic, {"ros1": "ros1", "json": "json"}.get(encoding, "protobuf"), sid)
            for d in data:
                w.add_message(channels[topic], t, d, t)
        w.finish()


@pytest.mark.parametrize("encoding", ["ros2", "ros1", "protobuf", "json"])
def test_multi_transform_messages_of_every_encoding(tmp_path: Path, encoding: str):
    path = tmp_path / "tf.mcap"
    _write_multi(path, encoding)
    _check_decoded(path)


def test_unindexed_log_is_streamed_and_damage_is_reported(tmp_path: Path):
    path = tmp_path / "tf.mcap"
    _write_multi(path, "json", indexed=False)
    log = _check_decoded(path)
    assert not log.scan.indexed and log.scan.damage is None
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    with pytest.raises(InputError, match=r"valid data ends at byte .*--allow-truncated"):
        read_transforms(cut)
    partial = read_transforms(cut, allow_truncated=True)
    assert 0 < len(partial.samples) < len(log.samples) and partial.scan.damage


def test_stamps_fall_back_to_log_time_and_can_be_forced(tmp_path: Path):
    path = tmp_path / "tf.mcap"
    recs = [("/tf", T0 + 5, PoseRecord(0, "w", "a", np.zeros(3), np.array([0.0, 0, 0, 1]))),
            ("/tf", T0 + 9, PoseRecord(T0, "w", "a", np.ones(3), np.array([0.0, 0, 0, 1])))]
    write_log(path, recs, "ros2")
    assert read_transforms(path).samples.stamps_ns.tolist() == [T0 + 5, T0]
    assert read_transforms(path, time_source="log_time").samples.stamps_ns.tolist() == [
        T0 + 5, T0 + 9]


def test_static_channels():
    assert is_static_channel("/tf_static") and is_static_channel("/robot/tf_static")
    assert not is_static_channel("/tf") and not is_static_channel("/tf_static_debug")
    assert is_static_channel("/tf2", {"latching": "1"})
    qos = "- history: 3\n  depth: 0\n  reliability: 1\n  durability: 1\n"
    assert is_static_channel("/calib", {"offered_qos_profiles": qos})
    assert not is_static_channel("/tf", {"offered_qos_profiles": qos.replace(
        "durability: 1", "durability: 2")})
