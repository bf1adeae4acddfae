"""Tiny synthetic multi-camera logs with a known trajectory, for the MCAP and ingest tests.

Camera c moves with position linear in time and rotation at a constant rate about a fixed
axis, so linear + slerp interpolation reproduces it exactly between tracker samples.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from surgrecon_cli.core.geometry.poses import make_pose
from surgrecon_cli.io.logs.records import (
    CameraInfoRecord,
    ImageRecord,
    JointStateRecord,
    PoseRecord,
    Record,
)
from surgrecon_cli.sim.log_writer import write_log

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
W, H = 64, 48
JOINTS = ("shoulder", "elbow", "insertion")

Message = tuple[str, int, Record]


def camera_position(c: int, t_ns: np.ndarray) -> np.ndarray:
    """(N, 3) m: linear in time."""
    s = (np.asarray(t_ns, dtype=np.int64) - T0) * 1e-9
    return np.stack([0.01 * c + 0.02 * s, -0.01 * s, 0.1 + 0.003 * c * s], axis=-1)


def camera_quat(c: int, t_ns: np.ndarray) -> np.ndarray:
    """(N, 4) x y z w: rotation about a fixed axis at a constant rate."""
    s = (np.asarray(t_ns, dtype=np.int64) - T0) * 1e-9
    axis = np.array([1.0, 2.0, 2.0 + c]) / np.linalg.norm([1.0, 2.0, 2.0 + c])
    half = 0.5 * (0.1 * c + 0.6 * s)
    return np.concatenate([np.sin(half)[:, None] * axis, np.cos(half)[:, None]], axis=1)


def camera_pose(c: int, t_ns: np.ndarray) -> np.ndarray:
    """(N, 4, 4) true camera-to-world poses."""
    return make_pose(camera_position(c, t_ns), camera_quat(c, t_ns))


def tool_position(t_ns: np.ndarray) -> np.ndarray:
    s = (np.asarray(t_ns, dtype=np.int64) - T0) * 1e-9
    return np.stack([0.05 * s, 0.01 + 0 * s, 0.08 - 0.01 * s], axis=-1)


def joint_values(t_ns: np.ndarray) -> np.ndarray:
    s = (np.asarray(t_ns, dtype=np.int64) - T0) * 1e-9
    return np.stack([0.1 * s, -0.2 * s, 0.05 + 0.01 * s], axis=-1)


def intrinsics(c: int) -> np.ndarray:
    return np.array([[50.0 + c, 0, 31.5], [0, 50.0 + c, 23.5], [0, 0, 1]])


def image_rgb(c: int, k: int) -> np.ndarray:
    """(H, W, 3) uint8: smooth (JPEG-friendly) and different per camera and frame."""
    yy, xx = np.mgrid[0:H, 0:W]
    r = (xx * 4 + 10 * k) % 256
    g = (yy * 5 + 40 * c) % 256
    b = ((xx + yy) * 2 + 7 * c * k) % 256
    return np.stack([r, g, b], axis=-1).astype(np.uint8)


def encode(rgb: np.ndarray, fmt: str) -> bytes:
    ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    return buf.tobytes()


@dataclass
class SynthSpec:
    """What to put in a log; defaults follow the simulator's (= the config's default) topics."""

    cameras: tuple[int, ...] = (0, 1, 2)
    frames: int = 6
    image_period_ms: int = 100
    camera_offset_ms: int = 3  # camera c is stamped c * offset after the frame time
    tracker_period_ms: int = 40
    robot_period_ms: int = 50
    image_format: str = "png"  # png / jpeg / rgb8 (raw)
    image_topic: str = "/endoscope_{c}/color/compressed"
    info_topic: str = "/endoscope_{c}/calibration"
    pose_topic: str = "/navigation/endoscope_{c}/pose"
    tool_topic: str = "/raven/tool_tip"
    joint_topic: str | None = "/raven/joint_states"
    tf_topic: str | None = None  # camera (and tool) poses as transforms on this topic
    camera_frame: str = "endoscope_{c}_optical"
    tool_frame: str = "raven_tool_tip"
    info_first: bool = True  # CameraInfo before the first image (else after the last)
    skip_info: tuple[int, ...] = ()
    tracker_gap: tuple[int, int, int] | None = None  # (camera, start ms, end ms) without poses
    mutate: Callable[[list[Message]], list[Message]] | None = None
    extra: list[Message] = field(default_factory=list)

    def frame_time(self, k: int) -> int:
        return T0 + 200 * MS + k * self.image_period_ms * MS

    def image_stamp(self, c: int, k: int) -> int:
        return self.frame_time(k) + c * self.camera_offset_ms * MS

    def end(self) -> int:
        return self.frame_time(self.frames) + 200 * MS


def _image(spec: SynthSpec, c: int, k: int) -> ImageRecord:
    rgb = image_rgb(c, k)
    stamp = spec.image_stamp(c, k)
    frame = spec.camera_frame.format(c=c)
    if spec.image_format in ("png", "jpeg"):
        return ImageRecord(stamp, frame, spec.image_format, encode(rgb, spec.image_format))
    return ImageRecord(stamp, frame, "rgb8", rgb.tobytes(), W, H, W * 3)


def messages(spec: SynthSpec) -> list[Message]:
    """All messages of the log, sorted by log time (= stamp + 1 ms)."""
    out: list[Message] = []
    for c in spec.cameras:
        t = T0 + 100 * MS if spec.info_first else spec.end() - 50 * MS
        if c not in spec.skip_info:
            out.append((spec.info_topic.format(c=c), t + MS, CameraInfoRecord(
                t, spec.camera_frame.format(c=c), W, H, intrinsics(c),
                np.array([-0.01 * c, 0.001, 0, 0, 0]))))
        for k in range(spec.frames):
            rec = _image(spec, c, k)
            out.append((spec.image_topic.format(c=c), rec.stamp_ns + MS, rec))
        for t in range(T0, spec.end(), spec.tracker_period_ms * MS):
            if spec.tracker_gap and spec.tracker_gap[0] == c and (
                    T0 + spec.tracker_gap[1] * MS <= t < T0 + spec.tracker_gap[2] * MS):
                continue
            p = camera_position(c, np.array([t]))[0]
            q = camera_quat(c, np.array([t]))[0]
            if spec.tf_topic:
                out.append((spec.tf_topic, t + MS,
                            PoseRecord(t, "world", spec.camera_frame.format(c=c), p, q)))
            else:
                out.append((spec.pose_topic.format(c=c), t + MS, PoseRecord(t, "world", "", p, q)))
    for t in range(T0, spec.end(), spec.robot_period_ms * MS):
        p = tool_position(np.array([t]))[0]
        q = np.array([0.0, 0.0, 0.0, 1.0])
        if spec.tf_topic:
            out.append((spec.tf_topic, t + MS, PoseRecord(t, "world", spec.tool_frame, p, q)))
        else:
            out.append((spec.tool_topic, t + MS, PoseRecord(t, "world", "", p, q)))
        if spec.joint_topic:
            out.append((spec.joint_topic, t + MS,
                        JointStateRecord(t, JOINTS, joint_values(np.array([t]))[0])))
    out += spec.extra
    if spec.mutate is not None:
        out = spec.mutate(out)
    out.sort(key=lambda m: m[1])
    return out


def write(path: Path, spec: SynthSpec | None = None, encoding: str = "ros2",
          chunk_size: int = 16 * 1024) -> Path:
    """Write the synthetic log (small chunks, so that damage tests hit a middle chunk)."""
    write_log(path, messages(spec or SynthSpec()), encoding, chunk_size=chunk_size)
    return path


# A stereo pair calibrated as ROS does it: x_right = STEREO_R x_left + STEREO_T (m).
STEREO_R = cv2.Rodrigues(np.array([0.01, -0.03, 0.005]))[0]
STEREO_T = np.array([-0.0055, 0.0002, 0.0003])


def _stereo_rectify() -> tuple[np.ndarray, ...]:
    """cv2.stereoRectify of cameras 0 and 1 for STEREO_R, STEREO_T: R1, R2, P1, P2."""
    K = [intrinsics(c) for c in (0, 1)]
    D = [np.array([-0.01 * c, 0.001, 0, 0, 0]) for c in (0, 1)]
    return cv2.stereoRectify(K[0], D[0], K[1], D[1], (W, H), STEREO_R, STEREO_T)[:4]


def ros_stereo_projections() -> tuple[np.ndarray, np.ndarray]:
    """The projections P (3, 4) `ros_stereo` gives cameras 0 and 1."""
    return _stereo_rectify()[2], _stereo_rectify()[3]


def ros_stereo(messages: list[Message]) -> list[Message]:
    """Cameras 0 and 1 without poses, their CameraInfo carrying the rectification R and
    projection P that cv2.stereoRectify gives for STEREO_R, STEREO_T (Tx = -fx' B)."""
    R1, R2, P1, P2 = _stereo_rectify()
    out = []
    for topic, t, rec in messages:
        if topic.endswith("/pose"):
            continue
        if topic.endswith("/calibration"):
            c = int(topic.split("_")[1].split("/")[0])
            rec = replace(rec, R=(R1, R2)[c], P=(P1, P2)[c])
        out.append((topic, t, rec))
    return out
