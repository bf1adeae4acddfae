"""`convert` calibration files: every flavour gives the rig it describes (intrinsics, the second
camera's pose from the file's own convention), lengths in metres, and bad files one error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from convert_inputs import (
    D_LEFT,
    D_RIGHT,
    K_LEFT,
    K_RIGHT,
    R_STEREO,
    T_STEREO_MM,
    json_calibration,
    opencv_calibration,
    right_in_left_m,
    ros_camera_info,
)

from surgrecon_cli.convert.calibration import load_rig
from surgrecon_cli.errors import InputError


def _check_stereo(rig, R=R_STEREO, T_mm=T_STEREO_MM) -> None:
    left, right = rig.cameras
    np.testing.assert_allclose(left.K, K_LEFT)
    np.testing.assert_allclose(right.K, K_RIGHT)
    np.testing.assert_allclose(left.D, D_LEFT)
    np.testing.assert_allclose(right.D, D_RIGHT)
    np.testing.assert_allclose(left.to_rig, np.eye(4), atol=1e-12)
    rot, pos = right_in_left_m(R, T_mm)
    np.testing.assert_allclose(right.to_rig[:3, :3], rot, atol=1e-9)
    np.testing.assert_allclose(right.to_rig[:3, 3], pos, atol=1e-12)


@pytest.mark.parametrize("name,keys", [
    ("stereo.yaml", ("M1", "D1", "M2", "D2")),
    ("stereo.xml", ("M1", "D1", "M2", "D2")),
    ("k.yml", ("K1", "D1", "K2", "D2")),
    ("cm.yaml", ("cameraMatrix1", "distCoeffs1", "cameraMatrix2", "distCoeffs2")),
])
def test_opencv_filestorage_files(tmp_path: Path, name: str, keys):
    opencv_calibration(tmp_path / name, keys)
    rig = load_rig([tmp_path / name])
    assert rig.units == "mm"  # |T| = 4.5 > 1
    _check_stereo(rig)


def test_translation_below_one_is_metres_and_units_override(tmp_path: Path):
    opencv_calibration(tmp_path / "m.yaml", T=T_STEREO_MM / 1000)
    rig = load_rig([tmp_path / "m.yaml"])
    assert rig.units == "m"
    _check_stereo(rig)
    opencv_calibration(tmp_path / "mm.yaml")
    forced = load_rig([tmp_path / "mm.yaml"], units="m")
    assert forced.units == "m"
    np.testing.assert_allclose(np.linalg.norm(forced.cameras[1].to_rig[:3, 3]),
                               np.linalg.norm(T_STEREO_MM))


def test_json_left_right_blocks(tmp_path: Path):
    json_calibration(tmp_path / "calib.json")
    _check_stereo(load_rig([tmp_path / "calib.json"]))


def test_ros_camera_info_pair(tmp_path: Path):
    """Two camera_info files of a stereo pair: rectification rotations R1, R2 and the right
    projection's Tx = -fx' B place the raw right camera at R1^T (R2-rotated, B along x')."""
    R1 = np.eye(3)
    R2 = R_STEREO @ R1  # any rotation pair: the right raw camera is rotated R2^T ... in rect
    fx, baseline = 500.0, 0.0045
    P1 = np.array([[fx, 0, 160, 0], [0, fx, 120, 0], [0, 0, 1, 0]])
    P2 = P1.copy()
    P2[0, 3] = -fx * baseline
    ros_camera_info(tmp_path / "l.yaml", "left", K_LEFT, D_LEFT, R1, P1)
    ros_camera_info(tmp_path / "r.yaml", "right", K_RIGHT, D_RIGHT, R2, P2)
    rig = load_rig([tmp_path / "l.yaml", tmp_path / "r.yaml"])
    left, right = rig.cameras
    assert (left.name, right.name, left.width, left.height) == ("left", "right", 320, 240)
    assert rig.units == "m"
    # A point X in the right raw frame: in the right rect frame R2 X, in the left rect frame
    # R2 X + (B, 0, 0), in the left raw frame R1^T (R2 X + (B, 0, 0)).
    X = np.array([0.01, -0.02, 0.08])
    expected = R1.T @ (R2 @ X + np.array([baseline, 0, 0]))
    np.testing.assert_allclose(right.to_rig[:3, :3] @ X + right.to_rig[:3, 3], expected,
                               atol=1e-12)


@pytest.mark.parametrize("text", ["520 518 161 119.5 4.5\n", "fx: 520\nfy: 518\ncx: 161\n"
                                  "cy: 119.5\nbaseline: 4.5\n"])
def test_rectified_pair(tmp_path: Path, text: str):
    (tmp_path / "rect.txt").write_text(text, encoding="utf-8")
    rig = load_rig([tmp_path / "rect.txt"])
    left, right = rig.cameras
    np.testing.assert_allclose(left.K, [[520, 0, 161], [0, 518, 119.5], [0, 0, 1]])
    assert not left.D.any() and not right.D.any()
    np.testing.assert_allclose(right.to_rig[:3, :3], np.eye(3))
    np.testing.assert_allclose(right.to_rig[:3, 3], [0.0045, 0, 0])


def test_cameras_map_for_more_than_two(tmp_path: Path):
    """`cameras`: name -> K, D, R, T (from the first camera, OpenCV's convention)."""
    import json

    (tmp_path / "rig.json").write_text(json.dumps({"cameras": {
        "a": {"K": K_LEFT.tolist(), "D": D_LEFT.tolist(), "width": 320, "height": 240},
        "b": {"K": K_RIGHT.tolist(), "D": [0.1, 0.0, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0],
              "R": R_STEREO.tolist(), "T": T_STEREO_MM.tolist()},
        "c": {"K": K_RIGHT.tolist(), "D": [], "R": np.eye(3).tolist(), "T": [0.0, -6.0, 0.0]},
    }}), encoding="utf-8")
    rig = load_rig([tmp_path / "rig.json"])
    assert [c.name for c in rig.cameras] == ["a", "b", "c"]
    assert rig.cameras[1].model == "rational_polynomial"
    rot, pos = right_in_left_m()
    np.testing.assert_allclose(rig.cameras[1].to_rig[:3, :3], rot, atol=1e-9)
    np.testing.assert_allclose(rig.cameras[1].to_rig[:3, 3], pos, atol=1e-12)
    assert (rig.cameras[0].width, rig.cameras[0].height) == (320, 240)
    np.testing.assert_allclose(rig.cameras[2].to_rig[:3, 3], [0, 0.006, 0])


@pytest.mark.parametrize("text,needle", [
    ("%YAML:1.0\nM1: [1, 2\n  - x: {\n", "OpenCV cannot"),
    ("R: [1, 0, 0, 0, 1, 0, 0, 0, 1]\nT: [1, 2, 3]\n", "no stereo calibration found"),
    ("camera_matrix: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n", "holds one camera"),
    ("M1: [1, 0, 0]\nM2: [1, 0, 0, 0, 1, 0, 0, 0, 1]\nR: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
     "T: [1, 2, 3]\n", "no stereo calibration found"),
    ("left: {K: [1, 0, 0, 0, 1, 0, 0, 0, 1]}\nright: {K: [1, 0, 0, 0, 1, 0, 0, 0, 1]}\n",
     "no R and T"),
    ("left: {K: [1, 0, 0, 0, 1, 0, 0, 0, 1]}\nright: {K: [1, 0, 0, 0, 1, 0, 0, 0, 1]}\n"
     "R: [1, 0, 0, 0, 1, 0, 0, 0, 1]\nT: [0, 0, 0]\n", "same place"),
    ("left: {K: [1, 0, 0, 0, 1, 0, 0, 0, 1], distortion_model: weird}\nright: {K: [1]}\n",
     "distortion model 'weird'"),
    ("!!python/object/apply:os.system ['echo hacked']\n", "not valid YAML"),
])
def test_bad_calibration_files_name_the_file(tmp_path: Path, text: str, needle: str):
    path = tmp_path / "bad.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError) as err:
        load_rig([path])
    assert str(path) in str(err.value) and needle in str(err.value)
