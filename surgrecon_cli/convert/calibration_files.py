"""Calibration files -> plain nested dicts (numbers, lists, numpy matrices), never executing
anything from the file.

- OpenCV FileStorage (YAML `%YAML:1.0` with `!!opencv-matrix`, or XML): read by
  `cv2.FileStorage`, matrices as numpy arrays;
- other YAML (ROS `camera_info` files, hand-written): `yaml.safe_load` (no Python tags);
- JSON;
- a text file of five numbers `fx fy cx cy baseline` (a rectified pair).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from ..errors import InputError

RECTIFIED_KEYS = ("fx", "fy", "cx", "cy", "baseline")


def read_calibration_file(path: Path) -> dict[str, Any]:
    """The file's content as a dict. InputError naming the file if it is missing, unreadable or
    not a mapping."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"calibration file {path}: cannot be read ({exc.strerror or exc})"
                         ) from None
    text = raw.decode("utf-8", errors="replace")
    head = text.lstrip()[:200]
    if head.startswith(("%YAML:1", "<?xml", "<opencv_storage")) or "!!opencv-matrix" in text:
        data: Any = _filestorage(path)
    elif path.suffix.lower() == ".json" or head.startswith("{"):
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise InputError(f"calibration file {path}: not valid JSON ({exc})") from None
    else:
        data = _numbers(text)
        if data is None:
            try:
                data = yaml.safe_load(text)
            except yaml.YAMLError as exc:
                reason = str(exc).splitlines()[0]
                raise InputError(f"calibration file {path}: not valid YAML ({reason})") from None
    if not isinstance(data, dict) or not data:
        raise InputError(f"calibration file {path}: holds no calibration (expected a mapping of "
                         "named values, e.g. M1 D1 M2 D2 R T, or five numbers fx fy cx cy "
                         "baseline)")
    return data


def _numbers(text: str) -> dict[str, Any] | None:
    """`fx fy cx cy baseline` as five numbers (whitespace or comma separated, `#` comments)."""
    lines = [line.split("#", 1)[0] for line in text.splitlines()]
    words = " ".join(lines).replace(",", " ").split()
    try:
        values = [float(w) for w in words]
    except ValueError:
        return None
    if len(values) != len(RECTIFIED_KEYS):
        return None
    return dict(zip(RECTIFIED_KEYS, values, strict=True))


def _filestorage(path: Path) -> dict[str, Any]:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # SystemError: a cv2.error raised in the binding
        reason = str(exc.__cause__ or exc).strip().splitlines()[-1]
        raise InputError(f"calibration file {path}: OpenCV cannot parse it ({reason})") from None
    try:
        if not fs.isOpened():
            raise InputError(f"calibration file {path}: OpenCV cannot open it")
        return _node(fs.root()) or {}
    finally:
        fs.release()


def _node(node: Any) -> Any:
    """A FileStorage node -> matrix / dict / list / number / string."""
    if node.isMap():
        keys = node.keys()
        if {"rows", "cols", "dt", "data"} <= set(keys):  # an !!opencv-matrix
            return np.asarray(node.mat(), dtype=float)
        return {key: _node(node.getNode(key)) for key in keys}
    if node.isSeq():
        return [_node(node.at(i)) for i in range(node.size())]
    if node.isInt() or node.isReal():
        return float(node.real())
    if node.isString():
        return node.string()
    return None
