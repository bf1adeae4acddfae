"""`surgrecon simulate`: render a synthetic multi-camera log with ground truth.

Streams: per camera JPEG images at `frame_rate` (each camera with its own small clock
offset and jitter) and CameraInfo; per camera tracker poses at `tracker_rate` with noise;
robot tool-tip pose and joint states at `robot_rate`. Ground truth (`NAME.gt.npz`,
io/logs/ground_truth.py) holds the true surface at every frame and its labels by the rule of
core/classify/labels.py, the true tool-tip pose at every frame and the simulator's dent depth.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..config import LabelsConfig
from ..core.classify.labels import CLASS_NAMES, true_labels
from ..core.geometry.cameras import CameraModel
from ..core.geometry.poses import make_pose, matrix_to_quat, quat_to_matrix
from ..io.logs.records import CameraInfoRecord, ImageRecord, JointStateRecord, PoseRecord
from ..io.run.atomic import write_npz
from .conventions import CONVENTIONS, Message
from .degrade import degrade
from .log_writer import write_log
from .motion import Motion
from .render import Renderer, tool_mesh
from .scene import SimConfig, make_tissue, vertex_normals
from .texture import make_texture
from .video import VideoEncoder

T0_NS = 1_700_000_000_000_000_000  # fixed epoch so that logs are bit-for-bit reproducible
WORLD = "world"
JOINTS = ("shoulder", "elbow", "insertion", "tool_roll", "wrist", "grasp1", "grasp2")


@dataclass(frozen=True)
class SimResult:
    """What `simulate` wrote and the class fractions of its ground truth."""

    log_path: Path
    gt_path: Path
    n_frames: int
    n_messages: int
    class_fractions: dict[str, float]


def camera_models(cfg: SimConfig, rng: np.random.Generator) -> list[CameraModel]:
    """Endoscope-like intrinsics: ~70 deg horizontal field of view, mild barrel distortion,
    in the lens model `cfg.lens` (the same random draws for every model: plumb_bob's
    k1 k2 p1 p2; rational_polynomial adds a denominator k4 = -k1 / 2; equidistant keeps
    k1 k2 scaled to the fisheye model's smaller coefficients)."""
    models = []
    for _ in range(cfg.cameras):
        f = cfg.width / (2 * np.tan(np.radians(35))) * rng.uniform(0.97, 1.03)
        K = np.array(
            [
                [f, 0, cfg.width / 2 - 0.5 + rng.uniform(-3, 3)],
                [0, f, cfg.height / 2 - 0.5 + rng.uniform(-3, 3)],
                [0, 0, 1],
            ]
        )
        dist = np.array(
            [
                rng.uniform(-0.16, -0.10),
                rng.uniform(0.02, 0.05),
                rng.uniform(-5e-4, 5e-4),
                rng.uniform(-5e-4, 5e-4),
                0.0,
            ]
        )
        if cfg.lens == "rational_polynomial":
            dist = np.array([*dist, -dist[0] / 2, 0.0, 0.0])
        elif cfg.lens == "equidistant":
            dist = np.array([dist[0] / 4, dist[1] / 4, 0.0, 0.0])
        models.append(CameraModel(K, dist, cfg.width, cfg.height, model=cfg.lens))
    return models


def _noisy_pose(
    T: np.ndarray, cfg: SimConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Tracker measurement of a true pose: isotropic position and rotation noise."""
    p = T[:3, 3] + rng.normal(0, cfg.tracker_noise_pos / np.sqrt(3), 3)
    rotvec = rng.normal(0, np.radians(cfg.tracker_noise_deg) / np.sqrt(3), 3)
    R = cv2.Rodrigues(rotvec)[0] @ T[:3, :3]
    return p, matrix_to_quat(R)


def _compose(
    position: np.ndarray, quat: np.ndarray, offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A measured pose (position, quaternion) composed with a fixed offset (4, 4) on the right."""
    T = make_pose(position, quat) @ offset
    return T[:3, 3], matrix_to_quat(T[:3, :3])


def _ns(t: float) -> int:
    return T0_NS + round(t * 1e9)


class LogBuilder:
    """Builds the time-ordered message stream of one simulated recording."""

    def __init__(self, cfg: SimConfig, video: str | None = None):
        self.cfg = cfg
        self.video = video  # None: JPEG images; "h264"/"h265": CompressedVideo (sim/video.py)
        self.mesh = make_tissue(cfg)
        self.motion = Motion(cfg, self.mesh)
        rng = np.random.default_rng(cfg.seed)
        self.models = camera_models(cfg, rng)
        self.clock_offset = rng.uniform(-0.004, 0.004, cfg.cameras)
        self.jitter = rng.uniform(-0.001, 0.001, (cfg.frames, cfg.cameras))
        self.tracker_phase = rng.uniform(0, 1 / cfg.tracker_rate, cfg.cameras)
        if self.motion.stereo_offset is not None:
            # One stereo head: its two sensors share a clock, and one tracker marker.
            self.clock_offset[1] = self.clock_offset[0]
            self.jitter[:, 1] = self.jitter[:, 0]
            self.tracker_phase[1] = self.tracker_phase[0]
        self.noise_rng = np.random.default_rng(cfg.seed + 303)
        self.render_rng = np.random.default_rng(cfg.seed + 404)
        self.degrade_rng = np.random.default_rng(cfg.seed + 606)
        self.texture = make_texture(cfg.seed)
        self.frame_times = np.arange(cfg.frames) / cfg.frame_rate

    def image_stamp(self, frame: int, cam: int) -> float:
        return self.frame_times[frame] + self.clock_offset[cam] + self.jitter[frame, cam]

    def true_vertices(self) -> np.ndarray:
        return np.stack([self.motion.tissue_vertices(t) for t in self.frame_times])

    # ---- streams ------------------------------------------------------------------------
    def _pose_messages(self) -> list[Message]:
        cfg, motion = self.cfg, self.motion
        t_end = self.frame_times[-1] + 0.1
        out: list[Message] = []
        head: list[tuple[np.ndarray, np.ndarray]] = []  # camera 0's measurements (stereo)
        for cam in range(cfg.cameras):
            times = np.arange(-0.1 + self.tracker_phase[cam], t_end, 1 / cfg.tracker_rate)
            for k, t in enumerate(times):
                if motion.stereo_offset is not None and cam == 1:
                    # The head's one marker: camera 0's measured pose with the fixed offset.
                    p, q = _compose(*head[k], motion.stereo_offset)
                else:
                    p, q = _noisy_pose(motion.camera_pose(cam, t), cfg, self.noise_rng)
                    if motion.stereo_offset is not None and cam == 0:
                        head.append((p, q))
                out.append(
                    (
                        f"/navigation/endoscope_{cam}/pose",
                        _ns(t) + 1_000_000,
                        PoseRecord(_ns(t), WORLD, "", p, q),
                    )
                )
        for t in np.arange(-0.1, t_end, 1 / cfg.robot_rate) if cfg.robot else ():
            p, q = motion.tool_pose(t)
            out.append(("/raven/tool_tip", _ns(t) + 500_000, PoseRecord(_ns(t), WORLD, "", p, q)))
            out.append(
                (
                    "/raven/joint_states",
                    _ns(t) + 500_000,
                    JointStateRecord(_ns(t), JOINTS, motion.joint_positions(t)),
                )
            )
        out.sort(key=lambda m: (m[1], m[0]))
        return out

    def _image_messages(self, on_frame: Callable[[int], None] | None) -> Iterator[Message]:
        cfg, motion, mesh = self.cfg, self.motion, self.mesh
        renderer = Renderer(self.texture, cfg.image_noise, self.render_rng)
        encoders = [VideoEncoder(self.video, cfg.width, cfg.height, cfg.frame_rate)
                    for _ in range(cfg.cameras)] if self.video else None
        for frame, t in enumerate(self.frame_times):
            vertices = motion.tissue_vertices(t)
            normals = vertex_normals(vertices, mesh.faces)
            tip, quat = motion.tool_pose(t)
            tool = tool_mesh(tip, quat_to_matrix(quat)[:, 2], cfg.tool_radius, cfg.tool_length)
            batch: list[Message] = []
            for cam in range(cfg.cameras):
                stamp = self.image_stamp(frame, cam)
                rgb = renderer.render(
                    cam,
                    self.models[cam],
                    motion.camera_pose(cam, stamp),
                    vertices,
                    normals,
                    mesh.faces,
                    mesh.material_xy,
                    tool,
                )
                rgb = degrade(rgb, self.degrade_rng, cfg.warp_px, cfg.blur_px, cfg.vignetting,
                              cfg.interlace_px)
                model = self.models[cam]
                log_ns = _ns(stamp) + 3_000_000
                frame_id = f"endoscope_{cam}_optical"
                if encoders is not None:
                    image = ImageRecord(_ns(stamp), frame_id, encoders[cam].codec,
                                        encoders[cam].encode(rgb))
                else:
                    ok, jpeg = cv2.imencode(
                        ".jpg",
                        cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                        [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality],
                    )
                    if not ok:  # pragma: no cover - OpenCV cannot fail on a valid uint8 image
                        raise RuntimeError("JPEG encoding failed")
                    image = ImageRecord(_ns(stamp), frame_id, "jpeg", jpeg.tobytes())
                batch.append(
                    (
                        f"/endoscope_{cam}/calibration",
                        log_ns,
                        CameraInfoRecord(
                            _ns(stamp), frame_id, model.width, model.height, model.K, model.dist,
                            model.model,
                        ),
                    )
                )
                batch.append((f"/endoscope_{cam}/color/compressed", log_ns, image))
            batch.sort(key=lambda m: (m[1], m[0]))
            yield from batch
            if on_frame is not None:
                on_frame(frame)

    def messages(self, on_frame: Callable[[int], None] | None = None) -> Iterator[Message]:
        """All messages merged in log-time order; images are rendered lazily, frame by frame."""
        return heapq.merge(
            self._pose_messages(), self._image_messages(on_frame), key=lambda m: (m[1], m[0])
        )


def class_fractions(labels: np.ndarray) -> dict[str, float]:
    """Fraction of (frame, vertex) pairs in each class, frames >= 1 (frame 0 is all static)."""
    later = labels[1:] if len(labels) > 1 else labels
    return {name: float((later == code).mean()) for code, name in CLASS_NAMES.items()}


def gt_path_for(log_path: Path) -> Path:
    """`NAME.mcap` -> `NAME.gt.npz` beside it."""
    return log_path.with_name(log_path.name.removesuffix(".mcap") + ".gt.npz")


def simulate(
    out: Path,
    cfg: SimConfig,
    encoding: str = "ros2",
    convention: str = "topics",
    labels: LabelsConfig | None = None,
    on_frame: Callable[[int], None] | None = None,
    video: str | None = None,
) -> SimResult:
    """Render the log to `out` and its ground truth to `NAME.gt.npz` (both atomically), its
    poses in `convention` (sim/conventions.py); `video` "h264"/"h265" writes the images as
    foxglove.CompressedVideo (Foxglove encodings only) instead of JPEG."""
    labels = labels or LabelsConfig()
    if video and not encoding.startswith("foxglove"):
        raise ValueError(f"video images are foxglove.CompressedVideo; encoding {encoding!r} "
                         "is not a Foxglove one (foxglove-protobuf, foxglove-json)")
    builder = LogBuilder(cfg, video)
    stream = builder.messages(on_frame)
    rewrite = CONVENTIONS[convention].rewrite
    if rewrite is not None:
        stream = rewrite(stream)
    counted = _Counter(stream)
    write_log(Path(out), counted, encoding)
    vertices = builder.true_vertices()
    gt_labels = true_labels(
        vertices, labels.static_mm, labels.neighbourhood_mm, labels.rigid_rms_mm
    )
    gt_path = gt_path_for(Path(out))
    tool_poses = np.stack([make_pose(*builder.motion.tool_pose(t)) for t in builder.frame_times])
    write_npz(
        gt_path,
        faces=builder.mesh.faces.astype(np.int32),
        vertices=vertices.astype(np.float64),
        labels=gt_labels.astype(np.uint8),
        stamps_ns=np.array([_ns(t) for t in builder.frame_times], dtype=np.int64),
        tool_poses=tool_poses.astype(np.float64),
        indentation_m=np.array([builder.motion.indentation(t) for t in builder.frame_times]),
    )
    return SimResult(Path(out), gt_path, cfg.frames, counted.count, class_fractions(gt_labels))


class _Counter:
    """Iterator wrapper counting the messages that pass through."""

    def __init__(self, messages: Iterator[Message]):
        self._it = iter(messages)
        self.count = 0

    def __iter__(self) -> Iterator[Message]:
        return self

    def __next__(self) -> Message:
        item = next(self._it)
        self.count += 1
        return item
