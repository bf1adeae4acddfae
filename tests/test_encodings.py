"""Issue 12, encodings: raw Bayer / YUV 4:2:2 images, CameraInfo distortion models, binning
and ROI, and geometry_msgs/TransformStamped poses, read from ROS 1 and ROS 2 logs (and
Foxglove where the schema has the field)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
import synth_log
from mcap.reader import make_reader
from synth_log import SynthSpec

from surgrecon_cli.cli.main import main
from surgrecon_cli.config import TopicsConfig
from surgrecon_cli.core.geometry.cameras import CameraModel, project
from surgrecon_cli.core.geometry.poses import make_pose
from surgrecon_cli.errors import GeometryError, InputError
from surgrecon_cli.io.logs.images import prepare_image
from surgrecon_cli.io.logs.reader import LogItem, LogReader
from surgrecon_cli.io.logs.records import CameraInfoRecord, ImageRecord, PoseRecord
from surgrecon_cli.io.run.ingest_store import load_ingested
from surgrecon_cli.sim import log_writer, ros_encoding
from surgrecon_cli.sim.log_writer import ENCODINGS, write_log
from surgrecon_cli.stages.ingest_streams import StreamCollector

T0 = synth_log.T0
MS = synth_log.MS
TOPICS = TopicsConfig(image="/cam_{camera}/image", camera_info="/cam_{camera}/info",
                      camera_pose="/cam_{camera}/pose", tool_pose="/tool",
                      joint_states="/joints")
ROS = ("ros1", "ros2")


def smooth_rgb(width: int = 96, height: int = 64) -> np.ndarray:
    """(H, W, 3) uint8: low-frequency colour (so demosaicing and chroma subsampling are
    nearly lossless) covering most of the value range."""
    yy, xx = np.mgrid[0:height, 0:width] / np.array([height, width])[:, None, None]
    r = 128 + 100 * np.sin(2.0 * xx + 1.0 * yy)
    g = 128 + 90 * np.cos(1.5 * yy - 0.7 * xx)
    b = 120 + 80 * np.sin(1.2 * (xx + yy) + 2.0)
    return np.rint(np.stack([r, g, b], -1)).astype(np.uint8)


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """Bayer mosaic (H, W) of an RGB image; pattern = colours of the top-left 2x2 block in
    row order, e.g. "rggb": R at (0, 0), G at (0, 1) and (1, 0), B at (1, 1)."""
    channel = np.array(["rgb".index(ch) for ch in pattern]).reshape(2, 2)
    h, w = rgb.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    return np.take_along_axis(rgb, channel[yy % 2, xx % 2][..., None], axis=2)[..., 0]


def yuv422(rgb: np.ndarray, order: str) -> np.ndarray:
    """(H, W * 2) uint8 4:2:2 bytes, BT.601 limited range (Y 16..235, U/V 16..240), chroma
    the mean of each horizontal pixel pair; order "uyvy" or "yuyv"."""
    c = rgb.astype(float) / 255.0
    r, g, b = c[..., 0], c[..., 1], c[..., 2]
    y = 16 + 65.481 * r + 128.553 * g + 24.966 * b
    u = 128 - 37.797 * r - 74.203 * g + 112.0 * b
    v = 128 + 112.0 * r - 93.786 * g - 18.214 * b
    u = 0.5 * (u[:, 0::2] + u[:, 1::2])
    v = 0.5 * (v[:, 0::2] + v[:, 1::2])
    planes = {"y0": y[:, 0::2], "y1": y[:, 1::2], "u": u, "v": v}
    names = ("u", "y0", "v", "y1") if order == "uyvy" else ("y0", "u", "y1", "v")
    out = np.stack([planes[n] for n in names], -1)  # (H, W/2, 4)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8).reshape(rgb.shape[0], -1)


def raw_record(rgb: np.ndarray, encoding: str, pad: int = 6,
               big_endian: bool = False) -> ImageRecord:
    """`rgb` in a raw encoding, each row padded by `pad` bytes (step > width * bytes)."""
    if encoding.startswith("bayer_"):
        data = mosaic(rgb, encoding[6:10])
        if encoding.endswith("16"):
            data = data.astype(np.uint16) * 257
            data = data.astype(">u2" if big_endian else "<u2")
    else:
        data = yuv422(rgb, "uyvy" if encoding == "yuv422" else "yuyv")
    rows = data.reshape(rgb.shape[0], -1).view(np.uint8)
    rows = np.concatenate([rows, np.full((len(rows), pad), 7, np.uint8)], axis=1)
    return ImageRecord(T0, "cam", encoding, rows.tobytes(), rgb.shape[1], rgb.shape[0],
                       rows.shape[1], big_endian)


def decoded_rgb(record: ImageRecord) -> np.ndarray:
    stored = prepare_image(record)
    img = cv2.imdecode(np.frombuffer(stored.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img.dtype == np.uint16:
        img = np.rint(img / 257.0).astype(np.uint8)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_records(path: Path, topics: TopicsConfig = TOPICS) -> list[LogItem]:
    return list(LogReader(path, topics, require_roles=False))


RAW = ("bayer_rggb8", "bayer_bggr8", "bayer_gbrg8", "bayer_grbg8", "bayer_rggb16",
       "bayer_bggr16", "bayer_gbrg16", "bayer_grbg16", "yuv422", "yuv422_yuy2")
TOLERANCE = {"bayer": 2, "yuv422": 2}  # grey levels (measured max 1 and 2)

@pytest.mark.parametrize("encoding", RAW)
@pytest.mark.parametrize("log_encoding", ENCODINGS)
def test_raw_encodings_decode_to_the_known_image(tmp_path: Path, encoding: str,
                                                 log_encoding: str):
    rgb = smooth_rgb()
    big_endian = encoding.endswith("16") and log_encoding == "ros1"  # ROS has is_bigendian
    record = raw_record(rgb, encoding, big_endian=big_endian)
    path = tmp_path / "log.mcap"
    write_log(path, [("/cam_0/image", T0, record)], log_encoding)
    (item,) = read_records(path)
    got = item.record
    assert isinstance(got, ImageRecord)
    assert (got.format, got.width, got.height, got.step, got.data) == (
        encoding, record.width, record.height, record.step, record.data)
    if log_encoding in ROS:
        assert got.big_endian == big_endian
    out = decoded_rgb(got)
    assert out.shape == rgb.shape
    err = np.abs(out.astype(int) - rgb.astype(int))
    interior = err[2:-2, 2:-2] if encoding.startswith("bayer") else err
    assert interior.max() <= TOLERANCE["bayer" if encoding.startswith("bayer") else "yuv422"]
    assert interior.mean() < 0.8


def test_raw_encoding_errors_name_encoding_and_topic(tmp_path: Path):
    rgb = smooth_rgb(10, 6)
    collector = StreamCollector(tmp_path)
    bad = ImageRecord(T0, "cam", "bayer_xyzw8", rgb[..., 0].tobytes(), 10, 6, 10)
    with pytest.raises(InputError) as info:
        collector.add(LogItem("image", "0", "/cam_0/image", T0, bad))
    message = str(info.value)
    assert "\n" not in message and "'bayer_xyzw8'" in message and "/cam_0/image" in message
    odd = dataclasses.replace(raw_record(smooth_rgb(10, 6), "yuv422"), width=9)
    with pytest.raises(ValueError, match="even width"):
        prepare_image(odd)
    short = dataclasses.replace(raw_record(rgb, "bayer_rggb16"), data=b"\0" * 30)
    with pytest.raises(ValueError, match=r"needs .* bytes"):
        prepare_image(short)


def _bayer_log(messages):
    """Every raw rgb8 image of a synthetic log as bayer_grbg8."""
    out = []
    for topic, t, rec in messages:
        if isinstance(rec, ImageRecord) and rec.format == "rgb8":
            rgb = np.frombuffer(rec.data, np.uint8).reshape(rec.height, rec.width, 3)
            rec = dataclasses.replace(raw_record(rgb, "bayer_grbg8", pad=0),
                                      stamp_ns=rec.stamp_ns, frame_id=rec.frame_id)
        out.append((topic, t, rec))
    return out


@pytest.mark.parametrize("encoding", ROS)
def test_ingest_reads_bayer_images(tmp_path: Path, encoding: str):
    spec = SynthSpec(image_format="rgb8", cameras=(0, 1), frames=3, mutate=_bayer_log)
    log = synth_log.write(tmp_path / "log.mcap", spec, encoding)
    assert main(["ingest", str(log), "-o", str(tmp_path / "run"), "--quiet"]) == 0
    ingested = load_ingested(tmp_path / "run/ingest")
    for c, cam in enumerate(spec.cameras):
        for k in range(spec.frames):
            err = np.abs(ingested.load_image(k, c).astype(int) - synth_log.image_rgb(cam, k))
            # synth_log's images wrap around (sawtooth): compare away from the wraps
            assert np.median(err[2:-2, 2:-2]) <= 1


# ---- CameraInfo: distortion model, binning, ROI ------------------------------------------

K_FULL = np.array([[610.0, 0, 655.3], [0, 604.0, 491.8], [0, 0, 1]])
DISTORTIONS = {
    "plumb_bob": np.array([-0.21, 0.06, 8e-4, -4e-4, -0.008]),
    "rational_polynomial": np.array([0.35, -0.12, 8e-4, -4e-4, 0.02, 0.62, -0.05, 0.04]),
    "equidistant": np.array([-0.03, 0.012, -0.004, 6e-4]),
}


@pytest.mark.parametrize("model", DISTORTIONS)
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_camera_info_binning_and_roi(tmp_path: Path, model: str, encoding: str):
    roi = (200, 120, 640, 480, True)
    info = CameraInfoRecord(T0, "cam_0_optical", 1280, 960, K_FULL, DISTORTIONS[model],
                            model.upper(), 2, 2, roi)
    write_log(tmp_path / "log.mcap", [("/cam_0/info", T0, info)], encoding)
    (item,) = read_records(tmp_path / "log.mcap")
    got = item.record
    assert isinstance(got, CameraInfoRecord) and got.distortion_model == model
    np.testing.assert_array_equal(got.K, K_FULL)
    np.testing.assert_array_equal(got.D, DISTORTIONS[model])
    if encoding not in ROS:  # foxglove.CameraCalibration has no binning or ROI
        assert (got.binning_x, got.binning_y, got.roi) == (0, 0, (0, 0, 0, 0, False))
        got = dataclasses.replace(got, binning_x=2, binning_y=2, roi=roi)
    assert (got.binning_x, got.binning_y, got.roi) == (2, 2, roi)

    reduced = CameraModel.from_camera_info(got.K, got.D, got.distortion_model, got.width,
                                           got.height, got.binning_x, got.binning_y, got.roi)
    full = CameraModel(K_FULL, DISTORTIONS[model], 1280, 960, model)
    assert (reduced.width, reduced.height, reduced.model) == (320, 240, model)
    rng = np.random.default_rng(3)
    pose = make_pose(np.array([0.01, -0.02, 0.0]), np.array([0.02, -0.01, 0.03, 1.0]) /
                     np.linalg.norm([0.02, -0.01, 0.03, 1.0]))
    pc = np.column_stack([rng.uniform(-0.5, 0.5, (500, 2)), np.ones(500)])
    points = pc * rng.uniform(0.03, 0.2, (500, 1)) @ pose[:3, :3].T + pose[:3, 3]
    uv_full, _ = project(points, pose, full)
    uv, _ = project(points, pose, reduced)
    mapped = (uv_full - np.array(roi[:2])) / 2.0
    np.testing.assert_allclose(uv, mapped, rtol=0, atol=1e-9)


def test_camera_info_reduction_rules():
    # binning 0 = 1, an all-zero ROI = the full image: the model is the calibration's
    same = CameraModel.from_camera_info(K_FULL, np.zeros(5), "", 1280, 960, 0, 0,
                                        (0, 0, 0, 0, False))
    np.testing.assert_array_equal(same.K, K_FULL)
    assert (same.width, same.height, same.model) == (1280, 960, "plumb_bob")
    odd = CameraModel.from_camera_info(K_FULL, np.zeros(5), "plumb_bob", 1280, 960, 3, 1,
                                       (1, 2, 100, 50, False))
    np.testing.assert_allclose(odd.K, [[610 / 3, 0, 654.3 / 3], [0, 604, 489.8], [0, 0, 1]])
    assert (odd.width, odd.height) == (33, 50)
    with pytest.raises(GeometryError, match=r"ROI .* not inside the 1280x960"):
        CameraModel.from_camera_info(K_FULL, np.zeros(5), "plumb_bob", 1280, 960, 1, 1,
                                     (1000, 0, 400, 100, False))


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_unknown_distortion_model_is_refused_in_one_line(tmp_path: Path, encoding: str):
    info = CameraInfoRecord(T0, "cam", 64, 48, synth_log.intrinsics(0),
                            np.array([0.1, 0.0, 0.0, 0.0]), "kannala_brandt")
    write_log(tmp_path / "log.mcap", [("/cam_7/info", T0, info)], encoding)
    with pytest.raises(InputError) as err:
        read_records(tmp_path / "log.mcap")
    message = str(err.value)
    assert "\n" not in message and "/cam_7/info" in message and "'kannala_brandt'" in message
    # without coefficients, an unknown (or empty) name is an undistorted plumb_bob camera
    write_log(tmp_path / "zero.mcap", [("/cam_7/info", T0, dataclasses.replace(
        info, D=np.zeros(5)))], encoding)
    assert read_records(tmp_path / "zero.mcap")[0].record.distortion_model == "plumb_bob"


# ---- poses: TransformStamped where a PoseStamped is read ---------------------------------

def _as_transform_stamped(original):
    """ros_message, but a PoseRecord with a child frame becomes a TransformStamped."""
    def encode(record, ros1, seq=0):
        name, msg = original(record, ros1, seq)
        if name == "tf2_msgs/TFMessage":
            return "geometry_msgs/TransformStamped", msg["transforms"][0]
        return name, msg
    return encode


def emit_transform_stamped(monkeypatch: pytest.MonkeyPatch) -> None:
    """From now on the ROS log writers emit geometry_msgs/TransformStamped for poses with a
    child frame (the simulator writes PoseStamped or TFMessage only)."""
    monkeypatch.setattr(log_writer, "ros_message", _as_transform_stamped(
        ros_encoding.ros_message))


POSES = [
    ("/cam_3/pose", T0 + 1, PoseRecord(T0 + 5 * MS, "tracker", "endoscope_3_optical",
                                       np.array([0.1, -0.2, 0.3]),
                                       np.array([0.1, 0.7, -0.1, 0.7]))),
    ("/tool", T0 + 2, PoseRecord(T0 + 6 * MS, "world", "raven_tool_tip",
                                 np.array([-0.05, 0.02, 0.11]),
                                 np.array([0.0, 0.0, 0.6, 0.8]))),
]


@pytest.mark.parametrize("encoding", ROS)
def test_transform_stamped_reads_as_the_pose_stamped(tmp_path: Path, encoding: str,
                                                     monkeypatch: pytest.MonkeyPatch):
    pose_stamped = [(t, lt, dataclasses.replace(r, child_frame_id="")) for t, lt, r in POSES]
    write_log(tmp_path / "pose.mcap", pose_stamped, encoding)
    emit_transform_stamped(monkeypatch)
    write_log(tmp_path / "tf.mcap", POSES, encoding)
    with open(tmp_path / "tf.mcap", "rb") as f:
        schemas = {s.name for s in make_reader(f).get_summary().schemas.values()}
    assert schemas == {"geometry_msgs/TransformStamped" if encoding == "ros1"
                       else "geometry_msgs/msg/TransformStamped"}
    got = read_records(tmp_path / "tf.mcap")
    want = read_records(tmp_path / "pose.mcap")
    assert [(i.role, i.camera, i.topic) for i in got] == [
        ("camera_pose", "3", "/cam_3/pose"), ("tool_pose", "", "/tool")]
    assert [(i.role, i.camera, i.topic) for i in want] == [(i.role, i.camera, i.topic)
                                                           for i in got]
    for a, b, (_, _, src) in zip(got, want, POSES, strict=True):
        ra, rb = a.record, b.record
        assert ra.stamp_ns == rb.stamp_ns == src.stamp_ns
        np.testing.assert_array_equal(make_pose(ra.position, ra.orientation),
                                      make_pose(rb.position, rb.orientation))
        assert (ra.frame_id, ra.child_frame_id) == (src.frame_id, src.child_frame_id)
        assert (rb.frame_id, rb.child_frame_id) == (src.frame_id, "")


def _transform_stamped_poses(messages):
    """Pose topics' records get their child frame (so they are written as TransformStamped)."""
    out = []
    for topic, t, rec in messages:
        if isinstance(rec, PoseRecord) and topic.startswith("/navigation/endoscope_"):
            rec = dataclasses.replace(rec, child_frame_id=topic.split("/")[2] + "_optical")
        elif isinstance(rec, PoseRecord):
            rec = dataclasses.replace(rec, child_frame_id="raven_tool_tip")
        out.append((topic, t, rec))
    return out


@pytest.mark.parametrize("encoding", ROS)
def test_ingest_reads_transform_stamped_poses(tmp_path: Path, encoding: str,
                                              monkeypatch: pytest.MonkeyPatch):
    spec = SynthSpec(cameras=(0, 1), frames=3)
    synth_log.write(tmp_path / "pose.mcap", spec, encoding)
    emit_transform_stamped(monkeypatch)
    synth_log.write(tmp_path / "tf.mcap",
                    dataclasses.replace(spec, mutate=_transform_stamped_poses), encoding)
    for name in ("pose", "tf"):
        assert main(["ingest", str(tmp_path / f"{name}.mcap"), "-o", str(tmp_path / name),
                     "--quiet"]) == 0
    a, b = load_ingested(tmp_path / "pose/ingest"), load_ingested(tmp_path / "tf/ingest")
    np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.tool_poses, b.tool_poses)
    assert a.usable.all() and b.usable.all()
