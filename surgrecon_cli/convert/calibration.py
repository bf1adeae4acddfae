"""Calibration dicts (`calibration_files`) -> a `Rig`: each camera's intrinsics and its pose
in the rig frame (the first camera's optical frame), in metres.

Layouts understood (key names case-sensitive, as the tools write them):

- stereo, as `cv2.stereoCalibrate` users save it: `M1 D1 M2 D2 R T` (or `K1 K2`,
  `cameraMatrix1 ...`, `distCoeffs1 ...`), or `left` / `right` blocks each with `K` (or
  `M`, `camera_matrix`) and `D` (or `dist`, `distortion_coefficients`) and `R T` at the top or
  in the `right` block. OpenCV's convention: a point x1 in the first camera is
  x2 = R x1 + T in the second.
- `cameras`: a mapping name -> block (`K D`, optional `R T` in the same convention from the
  first camera, or `pose`: the 4x4 camera-to-rig pose in any common frame, e.g. a robot base
  from hand-eye calibration; optional `width height`), for more than two cameras.
- ROS `camera_info` YAML, one file per camera (`camera_matrix`, `distortion_model`,
  `distortion_coefficients`, `rectification_matrix`, `projection_matrix`): the cameras are
  placed from the projection matrices (Tx = -fx' B) and rectification rotations.
- a rectified pair `fx fy cx cy baseline` (no distortion, identity R, the second camera
  `baseline` to the right).
- Kalibr's `camchain.yaml`: `cam0`, `cam1`, ... each with `intrinsics` [fu fv pu pv]
  (`camera_model: pinhole`), `distortion_model` radtan / equidistant / none with
  `distortion_coeffs`, `resolution` [w h] and, from cam1 on, `T_cn_cnm1` (4x4: a point in the
  camera before is x_n = T x_n-1), in metres.

Lengths (T, baseline, ROS Tx/fx') are in the file's unit: metres or millimetres. Unless told
(`units` given, or a `units: mm|m` key in the file), the largest camera offset decides:
above 1 it is millimetres (no stereo endoscope or surgical camera rig is a metre wide), else
metres.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.geometry.distortion import DISTORTION_MODELS
from ..core.geometry.poses import invert_pose, nearest_rotation, rectified_rig_pose
from ..errors import GeometryError, InputError
from .calibration_files import RECTIFIED_KEYS, read_calibration_file

logger = logging.getLogger(__name__)

UNITS = {"m": 1.0, "mm": 1e-3}
_K_KEYS = ("K", "M", "camera_matrix", "cameraMatrix", "intrinsics", "k")
_D_KEYS = ("D", "dist", "distortion", "distortion_coefficients", "distCoeffs", "d")
_MODEL_ALIASES = {"": "plumb_bob", "radtan": "plumb_bob", "radial-tangential": "plumb_bob",
                  "fisheye": "equidistant", "kannala_brandt": "equidistant",
                  "kb4": "equidistant", **{m: m for m in DISTORTION_MODELS}}
_MIN_BASELINE_M = 1e-5


@dataclass(frozen=True)
class CameraCalibration:
    """One camera: K (3, 3) px, D coefficients of `model`, image size px (0 = not stated),
    to_rig (4, 4): the camera-to-rig pose (optical frame, metres; file units while a file
    is read)."""

    name: str
    K: np.ndarray
    D: np.ndarray
    model: str
    width: int
    height: int
    to_rig: np.ndarray


@dataclass(frozen=True)
class Rig:
    """The calibrated cameras, in the file's order; `units` says how lengths were read. The
    rig frame is the first camera's optical frame, or the frame `cameras` poses are in."""

    cameras: tuple[CameraCalibration, ...]
    units: str


def load_rig(paths: Sequence[Path], units: str | None = None,
             names: Sequence[str] = ()) -> Rig:
    """Read the calibration file(s). Several files: one camera each (ROS camera_info or a
    `K D` block), named by `names` (else the file's `camera_name`, else cam0, cam1, ...).
    units: 'mm' / 'm' overrides the guess. InputError naming the file on anything missing."""
    if not paths:
        raise InputError("no calibration file given (--calibration FILE)")
    if len(paths) == 1:
        d = read_calibration_file(paths[0])
        raw = _cameras(d, paths[0])
        if units is None and str(d.get("units", "")).strip() in UNITS:
            units = str(d["units"]).strip()
        if units is None and _is_kalibr(d):
            units = "m"  # Kalibr writes metres
    else:
        raw = []
        for i, path in enumerate(paths):
            d = read_calibration_file(path)
            fallback = names[i] if i < len(names) else str(d.get("camera_name") or f"cam{i}")
            raw.append(_single(d, path, fallback, ros_rig=True))
        raw = _relative_to_first(raw)
    return _in_metres(raw, units, paths[0])


def _cameras(d: Mapping[str, Any], path: Path) -> list[CameraCalibration]:
    if isinstance(d.get("cameras"), Mapping):
        out = [replace(_single(block, path, str(name)),
                       to_rig=_extrinsic(block, path, required=False))
               for name, block in d["cameras"].items()]
        if not out:
            raise InputError(f"calibration file {path}: 'cameras' is empty")
        return out
    if all(k in d for k in RECTIFIED_KEYS):
        fx, fy, cx, cy, baseline = (_number(d[k], k, path) for k in RECTIFIED_KEYS)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        right = np.eye(4)
        right[0, 3] = baseline
        size = _size(d, path)
        return [CameraCalibration("left", K, np.zeros(5), "plumb_bob", *size, np.eye(4)),
                CameraCalibration("right", K.copy(), np.zeros(5), "plumb_bob", *size, right)]
    if _is_kalibr(d):
        return _kalibr(d, path)
    blocks = _stereo_blocks(d)
    if blocks is None:
        if _find(d, _K_KEYS) is not None:
            raise InputError(f"calibration file {path}: holds one camera; give one file per "
                             "camera (--calibration left.yaml --calibration right.yaml) or a "
                             "stereo file with R and T")
        raise InputError(f"calibration file {path}: no stereo calibration found (expected "
                         "M1 D1 M2 D2 R T, K1 K2, left/right blocks, 'cameras', or "
                         "fx fy cx cy baseline)")
    left, right, extr = blocks
    return [_single(left, path, "left"),
            replace(_single(right, path, "right"), to_rig=_extrinsic(extr, path, required=True))]


def _is_kalibr(d: Mapping[str, Any]) -> bool:
    """A Kalibr camchain: `cam0` with `intrinsics` and no 3x3 camera matrix."""
    cam0 = d.get("cam0")
    return isinstance(cam0, Mapping) and "intrinsics" in cam0 and (
        "camera_model" in cam0 or np.size(_matrix_values(cam0["intrinsics"])) != 9)


def _kalibr(d: Mapping[str, Any], path: Path) -> list[CameraCalibration]:
    """The cameras of a Kalibr camchain (cam0, cam1, ... in order; see the module docstring),
    each placed in cam0's frame by chaining the T_cn_cnm1."""
    cams: list[CameraCalibration] = []
    to_rig = np.eye(4)
    for k in range(len(d)):
        block = d.get(f"cam{k}")
        if not isinstance(block, Mapping):
            break
        name = f"cam{k}"
        model = str(block.get("camera_model", "pinhole")).strip().lower()
        if model != "pinhole":
            raise InputError(f"calibration file {path}: {name} has Kalibr camera_model "
                             f"{model!r}; only pinhole is read")
        fu, fv, pu, pv = _shaped(block.get("intrinsics"), (4,), f"{name} intrinsics", path)
        K = np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]])
        distortion = str(block.get("distortion_model", "none")).strip().lower()
        kind = {"radtan": "plumb_bob", "none": "plumb_bob", "equidistant": "equidistant"}.get(
            distortion)
        if kind is None:
            raise InputError(f"calibration file {path}: {name} has Kalibr distortion_model "
                             f"{distortion!r}; supported: radtan, equidistant, none")
        coeffs = np.asarray(_matrix_values(block.get("distortion_coeffs", [])), float).ravel()
        D = _coefficients(coeffs if distortion != "none" else np.zeros(0), kind, name, path)
        if k:
            if "T_cn_cnm1" not in block:
                raise InputError(f"calibration file {path}: {name} has no T_cn_cnm1 (its pose "
                                 f"from cam{k - 1})")
            T = _shaped(block["T_cn_cnm1"], (4, 4), f"{name} T_cn_cnm1", path)
            T[:3, :3] = nearest_rotation(T[:3, :3])
            to_rig = to_rig @ invert_pose(T)
        cams.append(CameraCalibration(name, K, D, kind, *_size(block, path), to_rig.copy()))
    return cams


def _stereo_blocks(d: Mapping[str, Any]) -> tuple[Any, Any, Any] | None:
    """(left block, right block, block holding R and T), or None."""
    for lk, rk in (("left", "right"), ("Left", "Right"), ("cam0", "cam1"), ("camera1", "camera2")):
        if isinstance(d.get(lk), Mapping) and isinstance(d.get(rk), Mapping):
            extr = d if "R" in d or "T" in d else d[rk]
            return d[lk], d[rk], extr
    for k1, k2, d1, d2 in (("M1", "M2", "D1", "D2"), ("K1", "K2", "D1", "D2"),
                           ("cameraMatrix1", "cameraMatrix2", "distCoeffs1", "distCoeffs2")):
        if k1 in d and k2 in d and np.size(_matrix_values(d[k1])) == 9:
            left = {"K": d[k1], "D": d.get(d1, []), **_size_keys(d, "1")}
            right = {"K": d[k2], "D": d.get(d2, []), **_size_keys(d, "2")}
            return left, right, d
    return None


def _size_keys(d: Mapping[str, Any], suffix: str) -> dict[str, Any]:
    """Image size keys of a flat stereo file (shared, or suffixed per camera)."""
    out = {k: d[k] for k in ("width", "height", "image_width", "image_height", "imageSize",
                             "image_size") if k in d}
    out.update({k.removesuffix(suffix): d[k] for k in (f"width{suffix}", f"height{suffix}")
                if k in d})
    return out


def _single(d: Any, path: Path, name: str, ros_rig: bool = False) -> CameraCalibration:
    if not isinstance(d, Mapping):
        raise InputError(f"calibration file {path}: camera {name!r} is not a mapping")
    K_value = _find(d, _K_KEYS)
    if K_value is None:
        raise InputError(f"calibration file {path}: camera {name!r} has no camera matrix "
                         f"(one of {', '.join(_K_KEYS)})")
    K = _shaped(K_value, (3, 3), f"{name} camera matrix", path)
    D_value = _find(d, _D_KEYS)
    D = np.zeros(0) if D_value is None else np.asarray(_matrix_values(D_value), float).ravel()
    model_name = str(d.get("distortion_model", d.get("model", ""))).strip().lower()
    model = _MODEL_ALIASES.get(model_name)
    if model is None:
        raise InputError(f"calibration file {path}: camera {name!r} has distortion model "
                         f"{model_name!r}; supported: {', '.join(DISTORTION_MODELS)}")
    if not model_name and D.size > 5:
        model = "rational_polynomial"
    D = _coefficients(D, model, name, path)
    to_rig = np.eye(4)
    if ros_rig and "projection_matrix" in d:
        to_rig = _ros_pose(d, path, name)
    return CameraCalibration(name, K, D, model, *_size(d, path), to_rig)


def _coefficients(D: np.ndarray, model: str, name: str, path: Path) -> np.ndarray:
    """Coefficients padded to the model's count; beyond it (thin prism, tilt) only zeros."""
    n = DISTORTION_MODELS[model]
    if D.size > n and np.any(D[n:] != 0):
        raise InputError(f"calibration file {path}: camera {name!r} has {D.size} distortion "
                         f"coefficients; supported: plumb_bob (5), rational_polynomial (8), "
                         "equidistant (4)")
    return np.concatenate([D[:n], np.zeros(max(0, n - D.size))])


def _ros_pose(d: Mapping[str, Any], path: Path, name: str) -> np.ndarray:
    """Camera-to-(rectified first camera) pose from a ROS camera_info's P and R (file units,
    `core.geometry.poses.rectified_rig_pose`)."""
    P = _shaped(d["projection_matrix"], (3, 4), f"{name} projection_matrix", path)
    R = _shaped(d.get("rectification_matrix", np.eye(3)), (3, 3),
                f"{name} rectification_matrix", path)
    try:
        return rectified_rig_pose(R, P)
    except GeometryError as exc:
        raise InputError(f"calibration file {path}: camera {name!r}: {exc}") from exc


def _relative_to_first(cams: list[CameraCalibration]) -> list[CameraCalibration]:
    """Re-base poses given in the first camera's rectified frame onto its raw frame."""
    to_first = invert_pose(cams[0].to_rig)
    return [replace(cam, to_rig=to_first @ cam.to_rig) for cam in cams]


def _extrinsic(d: Any, path: Path, required: bool) -> np.ndarray:
    """Camera-to-rig pose from OpenCV's R, T (x_cam = R x_rig + T), or a `pose` (4, 4) that is
    the camera-to-rig pose itself (e.g. a hand-eye result), in file units."""
    if isinstance(d, Mapping) and "pose" in d:
        pose = _shaped(d["pose"], (4, 4), "pose", path)
        if not np.allclose(pose[3], [0, 0, 0, 1]):
            raise InputError(f"calibration file {path}: a pose's last row must be 0 0 0 1")
        pose[:3, :3] = nearest_rotation(pose[:3, :3])
        return pose
    if not isinstance(d, Mapping) or ("R" not in d and "T" not in d):
        if required:
            raise InputError(f"calibration file {path}: no R and T between the cameras")
        return np.eye(4)
    if "R" not in d or "T" not in d:
        raise InputError(f"calibration file {path}: has {'R' if 'R' in d else 'T'} but not "
                         f"{'T' if 'R' in d else 'R'}")
    values = np.asarray(_matrix_values(d["R"]), float).ravel()
    if values.size == 3:  # a Rodrigues vector
        import cv2

        R = cv2.Rodrigues(values)[0]
    else:
        R = nearest_rotation(_shaped(d["R"], (3, 3), "R", path))
    pose = np.eye(4)
    pose[:3, :3] = R
    pose[:3, 3] = _shaped(d["T"], (3,), "T", path)
    return invert_pose(pose)


def _in_metres(raw: list[CameraCalibration], units: str | None, path: Path) -> Rig:
    offsets = [float(np.linalg.norm(c.to_rig[:3, 3])) for c in raw]
    largest = max(offsets)
    unit = units or ("mm" if largest > 1.0 else "m")
    if unit not in UNITS:
        raise InputError(f"--units {unit!r}: use 'mm' or 'm'")
    if largest and not 1e-3 <= largest * UNITS[unit] <= 1.0:  # only a stated unit gets here
        other = "mm" if unit == "m" else "m"
        logger.warning("calibration file %s: in %s (as stated) the cameras are up to %.4g m "
                       "apart, which no endoscope rig is; if its lengths are in %s, give "
                       "--units %s", path, unit, largest * UNITS[unit], other, other)
    cams = []
    for cam in raw:
        pose = cam.to_rig.copy()
        pose[:3, 3] *= UNITS[unit]
        cams.append(replace(cam, to_rig=pose))
    for i, a in enumerate(cams):
        for b in cams[i + 1:]:
            if np.linalg.norm(a.to_rig[:3, 3] - b.to_rig[:3, 3]) < _MIN_BASELINE_M:
                raise InputError(f"calibration file {path}: cameras {a.name!r} and {b.name!r} "
                                 "are at the same place (no baseline): a stereo calibration "
                                 "needs R and T, or ROS projection matrices with Tx")
    return Rig(tuple(cams), unit)


def _find(d: Mapping[str, Any], keys: Sequence[str]) -> Any:
    return next((d[k] for k in keys if k in d), None)


def _matrix_values(value: Any) -> Any:
    """ROS/OpenCV-JSON `{rows, cols, data}` -> data; anything else as it is."""
    if isinstance(value, Mapping) and "data" in value:
        return value["data"]
    return value


def _shaped(value: Any, shape: tuple[int, ...], what: str, path: Path) -> np.ndarray:
    try:
        arr = np.asarray(_matrix_values(value), dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"calibration file {path}: {what} is not numeric") from None
    if arr.size != int(np.prod(shape)) or not np.isfinite(arr).all():
        raise InputError(f"calibration file {path}: {what} has {arr.size} values, expected "
                         f"{int(np.prod(shape))} finite numbers")
    return arr.reshape(shape)


def _number(value: Any, what: str, path: Path) -> float:
    return float(_shaped(value, (1,), what, path)[0])


def _size(d: Mapping[str, Any], path: Path) -> tuple[int, int]:
    """(width, height) px the calibration states, (0, 0) when it does not."""
    for key in ("imageSize", "image_size", "resolution"):
        if key in d:
            w, h = _shaped(d[key], (2,), key, path)
            return int(w), int(h)
    for wk, hk in (("width", "height"), ("image_width", "image_height")):
        if wk in d and hk in d:
            return int(_number(d[wk], wk, path)), int(_number(d[hk], hk, path))
    return 0, 0
