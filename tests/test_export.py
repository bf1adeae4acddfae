"""`surgrecon export`: the MCAP read back with `mcap` and the protobuf decoders (counts per
topic, point fields bit for bit against the PLY clouds, stamps, Foxglove schemas), and the
TUM trajectories read back with evo's file rules."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.schema import build_file_descriptor_set
from scipy.spatial.transform import Rotation

from surgrecon_cli.cli.main import main
from surgrecon_cli.core.classify.labels import UNKNOWN
from surgrecon_cli.io.export.foxglove_pack import stamp_ns, unpack_points
from surgrecon_cli.io.export.foxglove_scene import CLASS_RGBA
from surgrecon_cli.io.export.to_mcap import shipped_layout
from surgrecon_cli.io.run.artefacts import read_labels
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.io.run.ply import read_ply

PER_FRAME = {"/surgrecon/cloud": PointCloud, "/surgrecon/target": PointCloud,
             "/surgrecon/tf": FrameTransforms, "/surgrecon/scene": SceneUpdate}
PER_IMAGE = {"image": CompressedImage, "calibration": CameraCalibration,
             "annotations": ImageAnnotations}


@pytest.fixture(scope="module")
def exported(pipeline_run, tmp_path_factory):
    """The session's finished run exported once: (run folder, MCAP path, TUM folder)."""
    out = tmp_path_factory.mktemp("export")
    run_dir = pipeline_run[0]
    mcap, tum = out / "run.mcap", out / "tum"
    assert main(["export", str(run_dir), "--mcap", str(mcap), "--tum", str(tum), "-q"]) == 0
    return run_dir, mcap, tum


@pytest.fixture(scope="module")
def messages(exported):
    """Every message: (topic, schema name, schema encoding, log time, publish time, data,
    decoded) in file order; JSON messages decoded with json.loads."""
    out = []
    with open(exported[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            out.append((channel.topic, schema.name, schema.encoding, channel.message_encoding,
                        message.log_time, message.publish_time, message.data, schema.data))
    return out


def by_topic(messages, topic):
    return [m for m in messages if m[0] == topic]


def decoded(messages, topic, cls):
    return [cls.FromString(m[6]) for m in by_topic(messages, topic)]


def test_message_counts_are_frames_times_topics(exported, messages):
    log = load_ingested(RunLayout(exported[0]).ingest_dir)
    counts: dict[str, int] = {}
    for m in messages:
        counts[m[0]] = counts.get(m[0], 0) + 1
    expected = dict.fromkeys([*PER_FRAME, "/surgrecon/frame_metrics", "/surgrecon/deformation"],
                             log.n_frames)
    expected["/surgrecon/template_cloud"] = 1
    for c in range(len(log.cameras)):
        with_image = sum(bool(row[c]) for row in log.image_paths)
        expected.update({f"/cameras/{c:02d}/{kind}": with_image for kind in PER_IMAGE})
    assert counts == expected
    assert log.n_frames == 6 and len(log.cameras) == 6


def test_every_message_is_its_foxglove_type(messages):
    """Protobuf channels: the schema is the official Foxglove FileDescriptorSet and every
    message parses as that type with nothing left over; the JSON channel holds JSON objects
    with the schema's required types."""
    types = {cls.DESCRIPTOR.full_name: cls for cls in [*PER_FRAME.values(), *PER_IMAGE.values()]}
    seen = set()
    for topic, schema_name, encoding, message_encoding, _, _, data, schema in messages:
        if encoding == "jsonschema":
            assert message_encoding == "json"
            obj, spec = json.loads(data), json.loads(schema)
            assert spec["type"] == "object" and isinstance(obj["frame"], int)
            kinds = {"number": (int, float), "boolean": (bool,), "string": (str,)}
            for key, value in obj.items():  # every value declared, of its declared type
                declared = spec["properties"][key]["type"]
                assert isinstance(value, kinds[declared]), key
                assert declared != "number" or not isinstance(value, bool), key
            continue
        assert (encoding, message_encoding) == ("protobuf", "protobuf"), topic
        cls = types[schema_name]
        assert schema == build_file_descriptor_set(cls).SerializeToString()
        message = cls.FromString(data)
        assert message.SerializeToString() == data  # no unknown or malformed fields
        seen.add(schema_name)
    assert seen == set(types)


def test_stamps_are_the_frame_stamps(exported, messages):
    log = load_ingested(RunLayout(exported[0]).ingest_dir)
    stamps = [int(s) for s in log.stamps_ns]
    topics = {m[0] for m in messages} - {"/surgrecon/template_cloud"}
    for topic in topics:
        got = by_topic(messages, topic)
        frames = [k for k in range(log.n_frames) if not topic.startswith("/cameras/")
                  or log.image_paths[k][int(topic.split("/")[2])]]
        assert [m[4] for m in got] == [stamps[k] for k in frames], topic
        assert [m[5] for m in got] == [stamps[k] for k in frames], topic
    for topic, cls in {**PER_FRAME, **{f"/cameras/00/{k}": c for k, c in PER_IMAGE.items()}
                       }.items():
        for k, message in enumerate(decoded(messages, topic, cls)):
            inner = message.transforms if cls is FrameTransforms else (
                message.entities if cls is SceneUpdate else [message])
            assert {stamp_ns(x.timestamp) for x in inner} == {stamps[k]}, topic
    (template,) = decoded(messages, "/surgrecon/template_cloud", PointCloud)
    assert stamp_ns(template.timestamp) == stamps[0]


def test_cloud_fields_equal_the_ply_bit_for_bit(exported, messages):
    layout = RunLayout(exported[0])
    clouds = decoded(messages, "/surgrecon/cloud", PointCloud)
    n = len(read_ply(layout.template_ply)["x"])
    labels = read_labels(layout, (len(clouds), n))
    for k, message in enumerate(clouds):
        got, ply = unpack_points(message), read_ply(layout.cloud(k))
        assert message.frame_id == "world" and message.point_stride == sum(
            v.dtype.itemsize for v in got.values())
        shared = set(got) & set(ply)
        assert {"x", "y", "z", "point_id", "label", "residual", "sigma"} <= shared
        assert k == 0 or "deform_floor" in shared
        for name in shared - {"red", "green", "blue"}:  # colours are by class, not texture
            assert got[name].dtype == ply[name].dtype, name
            assert got[name].tobytes() == ply[name].tobytes(), (k, name)
        expected = labels.displacement_mm[k][ply["point_id"]].astype(np.float32)
        assert got["displacement_mm"].tobytes() == expected.tobytes()
        rgba = np.column_stack([got["red"], got["green"], got["blue"], got["alpha"]])
        for code, colour in CLASS_RGBA.items():
            assert (rgba[got["label"] == code] == colour).all()
        assert np.isnan(got["residual"]).any() == np.isnan(ply["residual"]).any()
    assert (unpack_points(clouds[0])["label"] != UNKNOWN).all()


def test_template_and_targets(exported, messages):
    layout = RunLayout(exported[0])
    (template,) = decoded(messages, "/surgrecon/template_cloud", PointCloud)
    got, ply = unpack_points(template), read_ply(layout.template_ply)
    for name in ("x", "y", "z", "red", "green", "blue", "point_id", "sigma"):
        assert got[name].tobytes() == ply[name].astype(got[name].dtype).tobytes(), name
    targets = decoded(messages, "/surgrecon/target", PointCloud)
    for k, message in enumerate(targets[1:], start=1):
        data = np.load(layout.registration(k))
        fields = unpack_points(message)
        ids = fields["point_id"]
        has = np.isfinite(data["target"]).all(1) & np.isfinite(data["target_sigma"])
        np.testing.assert_array_equal(ids, np.flatnonzero(has))
        np.testing.assert_array_equal(fields["x"], data["target"][ids, 0].astype(np.float32))


def test_transforms_and_scene(exported, messages):
    log = load_ingested(RunLayout(exported[0]).ingest_dir)
    for k, message in enumerate(decoded(messages, "/surgrecon/tf", FrameTransforms)):
        frames = {t.child_frame_id: t for t in message.transforms}
        poses = [(f"camera_{c:02d}", log.usable_poses(k)[c]) for c in range(len(log.cameras))]
        poses.append(("tool", log.tool_poses[k]))
        for name, pose in poses:
            if not np.isfinite(pose).all():
                assert name not in frames
                continue
            t = frames[name]
            assert t.parent_frame_id == "world"
            np.testing.assert_allclose([t.translation.x, t.translation.y, t.translation.z],
                                       pose[:3, 3], rtol=0, atol=1e-12)
            q = [t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w]
            np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), pose[:3, :3],
                                       atol=1e-9)
    scene = decoded(messages, "/surgrecon/scene", SceneUpdate)[-1]
    (tool,) = [e for e in scene.entities if e.id == "tool"]
    assert tool.frame_id == "tool" and tool.frame_locked
    radius, length = 0.004, 0.15  # the default tool.shaft_radius_m and shaft_length_m
    assert tool.cylinders[0].size.x == pytest.approx(2 * radius)
    assert tool.cylinders[0].size.z == pytest.approx(length - radius)
    assert tool.spheres[0].pose.position.z == pytest.approx(radius)
    frusta = [e for e in scene.entities if e.id.startswith("camera_")]
    assert len(frusta) == len(log.cameras) and all(len(e.lines[0].points) == 16 for e in frusta)


def test_images_and_annotations(exported, messages):
    log = load_ingested(RunLayout(exported[0]).ingest_dir)
    images = decoded(messages, "/cameras/01/image", CompressedImage)
    for k, image in enumerate(images):
        assert image.data == (log.root / log.image_paths[k][1]).read_bytes()
        assert image.format in ("jpeg", "png") and image.frame_id == "camera_01"
    (calibration, *_) = decoded(messages, "/cameras/01/calibration", CameraCalibration)
    np.testing.assert_array_equal(np.reshape(calibration.K, (3, 3)), log.models[1].K)
    model = log.models[1]
    for annotation in decoded(messages, "/cameras/01/annotations", ImageAnnotations):
        assert annotation.points, "every frame has labelled points in view"
        for group in annotation.points:
            uv = np.array([(p.x, p.y) for p in group.points])
            assert ((uv >= 0) & (uv <= [model.width - 1, model.height - 1])).all()
            colour = tuple(round(v * 255) for v in (group.fill_color.r, group.fill_color.g,
                                                     group.fill_color.b, group.fill_color.a))
            assert colour in CLASS_RGBA.values()


def test_layout_is_shipped_and_written_beside(exported, messages):
    layout = json.loads(shipped_layout())
    beside = RunLayout.foxglove_layout_beside(exported[1])
    assert json.loads(beside.read_text()) == layout
    panels = layout["configById"]
    assert {key.split("!")[0] for key in panels} >= {"3D", "Image", "Plot"}
    topics = {m[0] for m in messages}
    assert set(panels["3D!surgrecon"]["topics"]) <= topics
    image = panels["Image!surgrecon"]["imageMode"]
    assert {image["imageTopic"], image["calibrationTopic"], *image["annotations"]} <= topics
    metrics = json.loads(by_topic(messages, "/surgrecon/frame_metrics")[-1][6])
    for panel in (p for key, p in panels.items() if key.startswith("Plot")):
        for path in panel["paths"]:
            topic, field = path["value"].split(".")
            assert topic == "/surgrecon/frame_metrics" and field in metrics


def read_tum_like_evo(path: Path) -> np.ndarray:
    """evo's `file_interface.read_tum_trajectory_file` rules: lines starting with `#` are
    comments, the others hold 8 whitespace-separated numbers `t x y z qx qy qz qw`, and
    the stamps must increase."""
    rows = [line.split() for line in path.read_text().splitlines()
            if line.strip() and not line.lstrip().startswith("#")]
    assert rows and all(len(r) == 8 for r in rows), path
    table = np.array(rows, dtype=float)
    assert (np.diff(table[:, 0]) > 0).all()
    return table


def test_tum_files_equal_the_ingested_poses(exported):
    log = load_ingested(RunLayout(exported[0]).ingest_dir)
    tum = exported[2]
    tracks = [(RunLayout.tum_camera(tum, c), log.image_stamps_ns[:, c], log.poses[:, c])
              for c in range(len(log.cameras))]
    tracks.append((RunLayout.tum_tool(tum), log.stamps_ns, log.tool_poses))
    for path, stamps, poses in tracks:
        table = read_tum_like_evo(path)
        keep = np.isfinite(poses).all((1, 2)) & (stamps >= 0)
        assert len(table) == keep.sum()
        nanoseconds = [int(line.split()[0].replace(".", "")) for line in
                       path.read_text().splitlines() if not line.startswith("#")]
        assert nanoseconds == stamps[keep].tolist()  # t: every digit of the stamp
        np.testing.assert_allclose(table[:, 0], stamps[keep] * 1e-9, rtol=0, atol=1e-6)
        np.testing.assert_allclose(table[:, 1:4], poses[keep, :3, 3], rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.linalg.norm(table[:, 4:], axis=1), 1.0, atol=1e-12)
        rotations = Rotation.from_quat(table[:, 4:]).as_matrix()  # x y z w, as TUM orders
        np.testing.assert_allclose(rotations, poses[keep, :3, :3], rtol=0, atol=1e-9)


def test_export_errors_are_one_line(exported, tmp_path, capsys):
    run_dir, mcap, _ = exported
    assert main(["export", str(run_dir), "-q"]) == 2
    assert main(["export", str(run_dir), "--mcap", str(mcap), "-q"]) == 2  # no --force
    assert main(["export", str(tmp_path), "--mcap", str(tmp_path / "x.mcap"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("error: ") for line in err)
    assert "--force" in err[1] and "run.json" in err[2]
    assert not (tmp_path / "x.mcap").exists()


def test_run_export_mcap_writes_it_into_the_run(pipeline_log, copy_run, capsys):
    assert main(["run", str(pipeline_log), "-o", str(copy_run), "--export", "mcap", "-q"]) == 0
    path = RunLayout(copy_run).export_mcap
    assert f"mcap: {path}" in capsys.readouterr().out
    assert RunLayout.foxglove_layout_beside(path).is_file()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count > 0


def test_metrics_without_a_report_are_the_class_counts(copy_run, tmp_path):
    layout = RunLayout(copy_run)
    layout.frames_csv.unlink()
    out = tmp_path / "bare.mcap"
    assert main(["export", str(copy_run), "--mcap", str(out), "-q"]) == 0
    with open(out, "rb") as f:
        rows = [json.loads(m.data) for _, _, m in
                make_reader(f).iter_messages(topics=["/surgrecon/frame_metrics"])]
    log = load_ingested(layout.ingest_dir)
    labels = read_labels(layout, (log.n_frames, len(read_ply(layout.template_ply)["x"])))
    assert [r["frame"] for r in rows] == list(range(log.n_frames))
    for k, row in enumerate(rows):
        assert row["static"] + row["shifting"] + row["deforming"] + row["unknown"] == \
            labels.labels.shape[1]
        assert row["deforming"] == int((labels.labels[k] == 2).sum())


def test_tum_of_the_recorded_streams_interpolate_to_the_ingested_poses(exported):
    """camera_CC_tracker.tum / tool_robot.tum hold the streams as recorded (in the world):
    interpolated to the image stamps as ingest does, they give its poses."""
    from surgrecon_cli.core.sync.streams import PoseStream, poses_at

    log = load_ingested(RunLayout(exported[0]).ingest_dir)
    tum = exported[2]
    gap = 10**9
    for c in range(len(log.cameras)):
        table = read_tum_like_evo(RunLayout.tum_tracker(tum, c))
        assert len(table) > log.n_frames  # the tracker runs faster than the cameras
        lines = [ln for ln in RunLayout.tum_tracker(tum, c).read_text().splitlines()
                 if not ln.startswith("#")]
        stamps = np.array([int(ln.split()[0].replace(".", "")) for ln in lines])
        stream = PoseStream(stamps, table[:, 1:4], table[:, 4:])
        usable = log.usable[:, c]
        poses, valid = poses_at(stream, log.image_stamps_ns[usable, c], gap)
        assert valid.all()
        np.testing.assert_allclose(poses, log.poses[usable, c], rtol=0, atol=1e-9)
    assert len(read_tum_like_evo(RunLayout.tum_robot(tum))) > log.n_frames


def test_tum_export_of_a_run_without_robot_is_read_by_evo(tmp_path: Path, capsys):
    """A run without a robot has no tool pose: tool.tum is not written at all, as evo's
    `read_tum_trajectory_file` refuses a file without a pose line ("TUM trajectory files
    must have 8 entries per row"), so `evo_traj tum DIR/*.tum` failed on every converted
    log. The cameras' files are written as before."""
    log, run_dir, tum = tmp_path / "nr.mcap", tmp_path / "run", tmp_path / "tum"
    assert main(["simulate", str(log), "--no-robot", "--frames", "2", "--cameras", "2",
                 "--width", "64", "--height", "48", "-q"]) == 0
    assert main(["ingest", str(log), "-o", str(run_dir), "-q", "--set", 'topics.tool_pose=""',
                 "--set", 'topics.joint_states=""']) == 0
    capsys.readouterr()
    assert main(["export", str(run_dir), "--tum", str(tum), "-q"]) == 0
    written = sorted(p.name for p in tum.glob("*.tum"))
    assert written and "tool.tum" not in written and "tool_robot.tum" not in written
    for path in tum.glob("*.tum"):
        read_tum_like_evo(path)
    assert len(read_tum_like_evo(RunLayout.tum_camera(tum, 0))) == 2  # one pose per frame
    out = capsys.readouterr().out
    assert "tool.tum not written" in out and "0 poses" not in out and "2 poses" in out
