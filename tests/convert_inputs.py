"""Inputs for the `convert` tests: textured images in stereo folders, stereo videos, calibration
files in each flavour, and an independent reader of the written MCAP (mcap_ros2's)."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

# A stereo rig as cv2.stereoCalibrate gives it: x_right = R x_left + T (T in mm).
K_LEFT = np.array([[520.0, 0.0, 161.0], [0.0, 518.0, 119.5], [0.0, 0.0, 1.0]])
K_RIGHT = np.array([[522.0, 0.0, 158.0], [0.0, 521.0, 121.0], [0.0, 0.0, 1.0]])
D_LEFT = np.array([-0.12, 0.05, 0.001, -0.002, 0.0])
D_RIGHT = np.array([-0.10, 0.04, 0.0, 0.001, 0.01])
R_STEREO = Rotation.from_euler("xyz", [0.5, -2.0, 0.3], degrees=True).as_matrix()
T_STEREO_MM = np.array([-4.5, 0.08, 0.2])


def right_in_left_m(R: np.ndarray = R_STEREO, T_mm: np.ndarray = T_STEREO_MM
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The right camera's pose in the left camera's frame, (rotation, position m), from the
    definition x_right = R x_left + T: its centre is -R^T T, its axes R^T."""
    return R.T, -R.T @ T_mm / 1000.0


def texture(height: int, width: int, seed: int, depth16: bool = False) -> np.ndarray:
    """A smooth random BGR image (H, W, 3), uint8 or uint16."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 1, (max(2, height // 8), max(2, width // 8), 3)).astype(np.float32)
    img = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC).clip(0, 1)
    return (img * (65535 if depth16 else 255)).astype(np.uint16 if depth16 else np.uint8)


def stereo_folder(root: Path, frames: int = 3, ext: str = ".png",
                  size: tuple[int, int] = (320, 240), names: tuple[str, ...] = ("left", "right"),
                  depth16: bool = False) -> dict[str, list[Path]]:
    """`root/<name>/000000<ext>...`: textured images per side; returns the files."""
    files: dict[str, list[Path]] = {}
    for k, name in enumerate(names):
        (root / name).mkdir(parents=True, exist_ok=True)
        files[name] = []
        for i in range(frames):
            path = root / name / f"{i:06d}{ext}"
            params = [cv2.IMWRITE_JPEG_QUALITY, 90] if ext in (".jpg", ".jpeg") else []
            assert cv2.imwrite(str(path), texture(size[1], size[0], 10 * i + k, depth16), params)
            files[name].append(path)
    return files


def stereo_video(path: Path, frames: int = 3, size: tuple[int, int] = (320, 240),
                 layout: str = "side-by-side", fps: int = 25) -> list[tuple[np.ndarray, ...]]:
    """A lossless (FFV1) stereo video of textured views; returns the (left, right) views."""
    import av

    views = [(texture(size[1], size[0], 10 * i), texture(size[1], size[0], 10 * i + 1))
             for i in range(frames)]
    axis = 1 if layout == "side-by-side" else 0
    with av.open(str(path), "w") as container:
        stream = container.add_stream("ffv1", rate=fps)
        stream.width = size[0] * (2 if axis == 1 else 1)
        stream.height = size[1] * (2 if axis == 0 else 1)
        stream.pix_fmt = "bgr0"
        for left, right in views:
            frame = av.VideoFrame.from_ndarray(np.concatenate([left, right], axis=axis),
                                               format="bgr24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    return views


def opencv_calibration(path: Path, names: tuple[str, ...] = ("M1", "D1", "M2", "D2"),
                       T: np.ndarray = T_STEREO_MM, size: tuple[int, int] | None = None) -> None:
    """An OpenCV FileStorage file (YAML or XML by suffix) of the stereo rig."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, value in zip(names, (K_LEFT, D_LEFT[None], K_RIGHT, D_RIGHT[None]), strict=True):
        fs.write(name, value)
    fs.write("R", R_STEREO)
    fs.write("T", np.asarray(T, float).reshape(3, 1))
    if size is not None:
        fs.write("width", size[0])
        fs.write("height", size[1])
    fs.release()


def json_calibration(path: Path) -> None:
    """`left`/`right` blocks (`K` as {rows, cols, data}, `D` as a list) and R, T at the top."""
    path.write_text(json.dumps({
        "left": {"K": {"rows": 3, "cols": 3, "data": K_LEFT.ravel().tolist()},
                 "D": D_LEFT.tolist()},
        "right": {"camera_matrix": K_RIGHT.tolist(), "dist": D_RIGHT.tolist()},
        "R": R_STEREO.tolist(), "T": T_STEREO_MM.tolist()}), encoding="utf-8")


def ros_camera_info(path: Path, name: str, K: np.ndarray, D: np.ndarray, R_rect: np.ndarray,
                    P: np.ndarray, size: tuple[int, int] = (320, 240)) -> None:
    """A ROS `camera_calibration` YAML (what camera_info_manager reads)."""
    def block(a: np.ndarray) -> str:
        rows, cols = (1, a.size) if a.ndim == 1 else a.shape
        return f"\n  rows: {rows}\n  cols: {cols}\n  data: {[float(x) for x in a.ravel()]}"

    path.write_text(
        f"image_width: {size[0]}\nimage_height: {size[1]}\ncamera_name: {name}\n"
        f"camera_matrix:{block(K)}\ndistortion_model: plumb_bob\n"
        f"distortion_coefficients:{block(D)}\nrectification_matrix:{block(R_rect)}\n"
        f"projection_matrix:{block(P)}\n", encoding="utf-8")


def read_log(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """topic -> [(log time ns, decoded ROS 2 message)], read by mcap_ros2 (not surgrecon)."""
    from mcap_ros2.reader import read_ros2_messages

    out: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    for m in read_ros2_messages(str(path)):
        out[m.channel.topic].append((m.log_time_ns, m.ros_msg))
    return dict(out)


def static_pose(log: dict[str, list[tuple[int, Any]]], child: str
                ) -> tuple[np.ndarray, np.ndarray]:
    """(rotation (3, 3), position (3,)) of `child` in its parent, from /tf_static."""
    for _, msg in log["/tf_static"]:
        for t in msg.transforms:
            if t.child_frame_id == child:
                q = t.transform.rotation
                p = t.transform.translation
                return (Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(),
                        np.array([p.x, p.y, p.z]))
    raise AssertionError(f"{child} not on /tf_static")
