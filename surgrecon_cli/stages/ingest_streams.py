"""Ingest, streaming part: consume role-tagged records once, write each image straight to a
staging folder, keep only small arrays (stamps, sizes, poses, joint values) in memory."""

from __future__ import annotations

import logging
from array import array
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.geometry.cameras import CameraModel
from ..core.geometry.intrinsics import folds_before_corners, implausible_intrinsics
from ..core.sync.streams import PoseStream, fmt_stamp, nearest_stamps, validate_pose_stream
from ..core.sync.tf_samples import frame_id_problem
from ..errors import GeometryError, InputError, quoted
from ..io.logs.images import StoredImage, prepare_image
from ..io.logs.reader import LogItem
from ..io.logs.records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord
from ..io.logs.topics import EXTRA_TOOL_ROLE
from ..io.logs.video import CODECS as VIDEO_CODECS
from ..io.logs.video import VideoDecoder
from ..io.logs.video_checks import VideoProblem
from ..io.run.ingest_store import VideoPackets, save_video
from ..io.run.layout import RunLayout

logger = logging.getLogger(__name__)

@dataclass
class Poses:
    """A pose stream being collected (compact arrays, not Python objects per sample)."""

    name: str
    stamps: array = field(default_factory=lambda: array("q"))
    values: array = field(default_factory=lambda: array("d"))  # x y z qx qy qz qw per sample
    frames: set[str] = field(default_factory=set)  # frame ids the poses are given in

    def add(self, record: PoseRecord) -> None:
        if record.frame_id not in self.frames:
            if self.frames:
                raise InputError(f"{self.name}: poses in frames {quoted(min(self.frames))} and "
                                 f"{quoted(record.frame_id)} (at {fmt_stamp(record.stamp_ns)}); "
                                 "one pose topic must keep one frame")
            self.frames.add(record.frame_id)
        self.stamps.append(record.stamp_ns)
        self.values.extend(np.concatenate([record.position, record.orientation]).tolist())

    @property
    def frame(self) -> str:
        """The frame id the poses are given in ("" if unnamed or no pose yet)."""
        return next(iter(self.frames), "")

    def validated(self) -> PoseStream:
        v = np.array(self.values, dtype=float).reshape(-1, 7)
        stamps = np.array(self.stamps, dtype=np.int64)
        return validate_pose_stream(self.name, stamps, v[:, :3], v[:, 3:])


@dataclass
class CameraStreams:
    """What ingest keeps of one camera while streaming."""

    index: int  # discovery order; names the staging folder (camera ids never become paths)
    camera_id: str = ""
    image_topic: str = ""
    stamps: array = field(default_factory=lambda: array("q"))
    sizes: array = field(default_factory=lambda: array("q"))  # width, height per image
    files: list[str] = field(default_factory=list)  # staged paths relative to the staging root
    info_topic: str = ""
    model: CameraModel | None = None
    rectification: tuple[np.ndarray, np.ndarray] | None = None  # its first CameraInfo's R, P
    info_changed: bool = False
    poses: Poses | None = None
    pose_topic: str = ""
    video: list[VideoProblem] = field(default_factory=list)  # lost / duplicated messages
    video_format: str = ""  # h264 / h265 for a video camera: its packets are kept too
    packet_stamps: array = field(default_factory=lambda: array("q"))
    packet_sizes: array = field(default_factory=lambda: array("q"))
    pixel_max: int = 0  # largest pixel value of its images (io.logs.images.StoredImage.peak)


class StreamCollector:
    """Feed `add(item)` every LogItem; images go to `root/staged/CC/NNNNNNNN.ext`."""

    def __init__(self, root: Path, rectified: bool = False) -> None:
        self.root = Path(root)
        self.rectified = rectified  # images modelled by their CameraInfo's P, no distortion
        self.cameras: dict[str, CameraStreams] = {}
        self.tool = Poses("tool pose")
        self.tool_topic = ""
        self.extra_tools: dict[int, Poses] = {}  # [[tools]] index -> its poses
        self.joint_names: tuple[str, ...] = ()
        self.joint_topic = ""
        self.joint_stamps = array("q")
        self.joint_values = array("d")
        self.empty_joint_states = 0
        self.videos: dict[str, tuple[str, VideoDecoder]] = {}  # topic -> camera, decoder

    def _camera(self, camera: str) -> CameraStreams:
        if camera not in self.cameras:
            self.cameras[camera] = CameraStreams(index=len(self.cameras), camera_id=camera)
        return self.cameras[camera]

    def add(self, item: LogItem) -> None:
        record = item.record
        if isinstance(record, PoseRecord):
            why = frame_id_problem(record.frame_id) or frame_id_problem(record.child_frame_id)
            if why is not None:
                raise InputError(f"{item.topic}: pose at stamp {fmt_stamp(record.stamp_ns)} "
                                 f"has {why}")
        if item.role == "image" and isinstance(record, ImageRecord):
            self._image(item, record)
        elif item.role == "camera_info" and isinstance(record, CameraInfoRecord):
            self._info(item, record)
        elif item.role == "camera_pose" and isinstance(record, PoseRecord):
            cam = self._camera(item.camera)
            if cam.poses is None:
                frame = f" [{record.child_frame_id}]" if record.child_frame_id else ""
                cam.poses = Poses(f"{item.topic}{frame}")
                cam.pose_topic = item.topic
            cam.poses.add(record)
        elif item.role == "tool_pose" and isinstance(record, PoseRecord):
            if not self.tool_topic:
                frame = f" [{record.child_frame_id}]" if record.child_frame_id else ""
                self.tool_topic = item.topic
                self.tool.name = f"{item.topic}{frame}"
            self.tool.add(record)
        elif item.role == EXTRA_TOOL_ROLE and isinstance(record, PoseRecord):
            k = int(item.camera)
            self.extra_tools.setdefault(k, Poses(f"{item.topic} (tools[{k}])")).add(record)
        elif item.role == "joint_states" and isinstance(record, JointStateRecord):
            self._joints(item, record)

    def _image(self, item: LogItem, record: ImageRecord) -> None:
        cam = self._camera(item.camera)
        cam.image_topic = cam.image_topic or item.topic
        if record.format in VIDEO_CODECS:  # one stateful decoder per topic (io/logs/video.py)
            if item.topic not in self.videos:
                self.videos[item.topic] = (item.camera, VideoDecoder(item.topic, record.format))
            decoder = self.videos[item.topic][1]
            for stamp, stored in decoder.decode(record):
                self._store(item.camera, stamp, stored)
            if decoder.started:  # kept as recorded, for the export (from the first keyframe)
                self._packet(cam, record)
            return
        try:
            stored = prepare_image(record)
        except ValueError as exc:
            raise InputError(f"{item.topic}: image at stamp {fmt_stamp(record.stamp_ns)} "
                             f"does not decode ({exc})") from exc
        self._store(item.camera, record.stamp_ns, stored)

    def _packet(self, cam: CameraStreams, record: ImageRecord) -> None:
        path = RunLayout.staged_video(self.root, cam.index)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "ab") as f:
            f.write(bytes(record.data))
        cam.video_format = str(record.format).lower()
        cam.packet_stamps.append(record.stamp_ns)
        cam.packet_sizes.append(len(record.data))

    def save_videos(self, staging: Path, ids: tuple[str, ...]) -> None:
        """Each video camera's packets, by its index c in the sorted `ids`, as
        `ingest/video/CC.npz` (io/ingest_store.save_video)."""
        for c, camera in enumerate(ids):
            cam = self.cameras[camera]
            if cam.video_format:
                data = RunLayout.staged_video(self.root, cam.index).read_bytes()
                save_video(staging, c, VideoPackets(
                    cam.video_format, np.frombuffer(data, np.uint8),
                    np.array(cam.packet_sizes, np.int64), np.array(cam.packet_stamps, np.int64)))

    def finish(self) -> None:
        """At the end of the log: the frames video decoders still hold."""
        for camera, decoder in self.videos.values():
            for stamp, stored in decoder.flush():
                self._store(camera, stamp, stored)
            self.cameras[camera].video.extend(decoder.problems)

    def _store(self, camera: str, stamp_ns: int, stored: StoredImage) -> None:
        cam = self.cameras[camera]
        if cam.model is not None:
            self._check_size(camera, stamp_ns, stored.width, stored.height)
        rel = RunLayout.staged_relpath(cam.index, len(cam.files), stored.ext)
        path = self.root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(stored.data)
        cam.stamps.append(stamp_ns)
        cam.sizes.extend((stored.width, stored.height))
        cam.files.append(rel)
        cam.pixel_max = max(cam.pixel_max, stored.peak)

    def _check_size(self, camera: str, stamp_ns: int, width: int, height: int) -> None:
        cam = self.cameras[camera]
        model = cam.model
        if model is not None and (width, height) != (model.width, model.height):
            raise InputError(
                f"{cam.image_topic}: image at stamp {fmt_stamp(stamp_ns)} is {width}x{height} px "
                f"but {cam.info_topic} gives {model.width}x{model.height} px")

    def _info(self, item: LogItem, record: CameraInfoRecord) -> None:
        cam = self._camera(item.camera)
        where = f"{item.topic}: intrinsics at stamp {fmt_stamp(record.stamp_ns)}"
        K, D, distortion = record.K, record.D, record.distortion_model
        if self.rectified:  # ROS image_geometry: rectified images are modelled by P
            if record.P is None:
                raise InputError(f"{where} carry no projection P for the rectified images "
                                 "(topics.image_rectified); set topics.image_rectified = "
                                 "\"no\" if the images are raw")
            K, D, distortion = np.asarray(record.P)[:, :3], np.zeros(5), "plumb_bob"
        try:
            model = CameraModel.from_camera_info(
                K, D, distortion, int(record.width), int(record.height), record.binning_x,
                record.binning_y, record.roi)
        except (GeometryError, ValueError) as exc:
            raise InputError(f"{where} are invalid ({exc})") from exc
        if cam.model is None:
            why = implausible_intrinsics(K, int(record.width), int(record.height), model)
            if why is not None:
                raise InputError(f"{where} cannot be a real camera's: {why}; fix the "
                                 "calibration, or leave the camera out of topics.image")
            corners = folds_before_corners(K, int(record.width), int(record.height), model)
            if corners is not None:
                logger.warning("%s: %s; points imaged there are misplaced", where, corners)
            cam.model = model
            cam.info_topic = item.topic
            if record.R is not None and record.P is not None:
                cam.rectification = (record.R, record.P)
            sizes = np.array(cam.sizes, dtype=np.int64).reshape(-1, 2)
            for k, (w, h) in enumerate(sizes):
                self._check_size(item.camera, cam.stamps[k], int(w), int(h))
        elif not cam.info_changed and not model.same_as(cam.model):
            cam.info_changed = True
            logger.warning("%s changes at stamp %s; the first intrinsics are used",
                           item.topic, fmt_stamp(record.stamp_ns))

    def _joints(self, item: LogItem, record: JointStateRecord) -> None:
        if not record.names:  # carries no joint: skipped (said once per log)
            if not self.empty_joint_states:
                logger.warning("%s: a joint state without joints at stamp %s; such messages "
                               "are skipped", item.topic, fmt_stamp(record.stamp_ns))
            self.empty_joint_states += 1
            return
        if not self.joint_names:
            self.joint_names = tuple(record.names)
            self.joint_topic = item.topic
        values = dict(zip(record.names, np.asarray(record.positions, float).tolist(), strict=False))
        self.joint_stamps.append(record.stamp_ns)
        self.joint_values.extend(values.get(n, float("nan")) for n in self.joint_names)

    def joints(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint stamps (M,) sorted and positions (M, J)."""
        stamps = np.array(self.joint_stamps, dtype=np.int64)
        values = np.array(self.joint_values, dtype=float)
        values = values.reshape(len(stamps), len(self.joint_names))
        order = np.argsort(stamps, kind="stable")
        return stamps[order], values[order]


def video_report(cam: CameraStreams, frame_stamps_ns: np.ndarray,
                 tolerance_ns: int) -> dict[str, int]:
    """A camera's video problems (lost and duplicated messages; io/logs/video_checks.py) as
    report counts, each warned about naming the camera and the frames (of `frame_stamps_ns`
    (T,) ns, increasing) that lost its image."""
    for p in cam.video:
        where = f"camera {cam.camera_id}: video on {cam.image_topic}"
        if p.kind == "duplicate":
            logger.warning("%s: the message at %s is a duplicate (%s); not decoded", where,
                           fmt_stamp(p.stamp_ns), p.detail)
            continue
        frames = _frames_near(np.asarray(p.damaged, np.int64), frame_stamps_ns, tolerance_ns)
        logger.warning("%s: a message is lost before %s (%s); the %d images from there to the "
                       "next keyframe are decoded against a missing reference and dropped "
                       "(frames %s)", where, fmt_stamp(p.stamp_ns), p.detail, len(p.damaged),
                       _ranges(frames) or "none formed")
    return {"video_lost": sum(p.kind == "gap" for p in cam.video),
            "video_duplicates": sum(p.kind == "duplicate" for p in cam.video),
            "video_damaged": sum(len(p.damaged) for p in cam.video)}


def _frames_near(stamps_ns: np.ndarray, frame_stamps_ns: np.ndarray,
                 tolerance_ns: int) -> list[int]:
    """Indices of the frames (stamps (T,) ns, increasing) nearest each stamp (N,) ns, for
    those within `tolerance_ns` of one."""
    if not len(frame_stamps_ns) or not len(stamps_ns):
        return []
    near, off = nearest_stamps(frame_stamps_ns, stamps_ns)
    return sorted({int(k) for k in near[off <= tolerance_ns]})


def _ranges(values: list[int]) -> str:
    """Sorted ints -> '3-5, 9'."""
    runs: list[list[int]] = []
    for v in values:
        if runs and v == runs[-1][1] + 1:
            runs[-1][1] = v
        else:
            runs.append([v, v])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in runs)
