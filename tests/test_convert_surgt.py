"""Real stereo endoscopy (tests/data/surgt: SurgT, Apache-2.0): the side-by-side video and the
same frames as an image folder convert with the shipped OpenCV calibration, and both run with
the written config as it is, to templates that agree."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from convert_inputs import read_log, static_pose

from surgrecon_cli.cli.main import main

SURGT = Path(__file__).parent / "data" / "surgt"
# data/calibration.yaml of the clip: M1's diagonal (px) and T (mm).
FX_LEFT, FY_LEFT = 1035.30811, 1035.08765
T_MM = np.array([-4.14339018, -0.0238197036, -0.00190685259])


def _frames_as_folder(root: Path, count: int) -> None:
    """The video's first frames as left/ and right/ PNG files (lossless of the decoded frame)."""
    import av

    with av.open(str(SURGT / "video.mp4")) as container:
        for i, frame in zip(range(count), container.decode(video=0), strict=False):
            img = frame.to_ndarray(format="bgr24")
            for side, view in (("left", img[:, :1280]), ("right", img[:, 1280:])):
                (root / side).mkdir(parents=True, exist_ok=True)
                assert cv2.imwrite(str(root / side / f"{i:06d}.png"), view)


def test_the_video_converts_with_its_calibration(tmp_path: Path):
    out = tmp_path / "surgt.mcap"
    assert main(["convert", str(SURGT / "video.mp4"), "-o", str(out), "--calibration",
                 str(SURGT / "calibration.yaml"), "--frames", "0:2", "-q"]) == 0
    log = read_log(out)
    info = log["/camera/left/camera_info"][0][1]
    assert (info.width, info.height) == (1280, 1024)  # half of the 2560 x 1024 frame
    np.testing.assert_allclose([info.k[0], info.k[4]], [FX_LEFT, FY_LEFT], rtol=1e-6)
    _, position = static_pose(log, "right_optical_frame")
    assert np.linalg.norm(position) == pytest.approx(np.linalg.norm(T_MM) / 1000, rel=1e-5)
    assert position[0] > 0.004  # T is in mm and points left: the right eye is at +x
    # 25 fps: the video's own times after the 1 s start
    stamps = [t for t, _ in log["/camera/right/image/compressed"]]
    assert stamps == [10**9, 10**9 + 4 * 10**7]


@pytest.mark.slow
def test_folder_and_video_run_to_the_same_template(tmp_path: Path):
    _frames_as_folder(tmp_path / "surgt", 3)
    outputs = {"folder": (tmp_path / "surgt", tmp_path / "folder.mcap"),
               "video": (SURGT / "video.mp4", tmp_path / "video.mcap")}
    points = {}
    for name, (src, out) in outputs.items():
        assert main(["convert", str(src), "-o", str(out), "--calibration",
                     str(SURGT / "calibration.yaml"), "--frames", "0:3", "-q"]) == 0
        run = tmp_path / f"run_{name}"
        assert main(["run", str(out), "-o", str(run), "--config", str(out.with_suffix(".toml")),
                     "-q"]) == 0
        summary = json.loads((run / "metrics" / "summary.json").read_text(encoding="utf-8"))
        assert summary["frames"] == 3 and summary["cameras"] == ["left", "right"]
        from surgrecon_cli.io.run.ply import read_ply

        cloud = read_ply(run / "template.ply")
        points[name] = np.column_stack([cloud["x"], cloud["y"], cloud["z"]])
    n_folder, n_video = len(points["folder"]), len(points["video"])
    assert n_folder > 500
    assert abs(n_video - n_folder) <= 0.1 * n_folder
    # Same surface: the video's (JPEG q95) points lie on the folder's (PNG) cloud.
    from scipy.spatial import cKDTree

    gaps, _ = cKDTree(points["folder"]).query(points["video"])
    spacing, _ = cKDTree(points["folder"]).query(points["folder"], k=2)
    assert np.median(gaps) < 2 * np.median(spacing[:, 1])
