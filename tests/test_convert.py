"""`surgrecon convert`: generated stereo folders (PNG, JPEG, 16-bit, BMP/TIFF) and videos become
a ROS 2 MCAP whose images, intrinsics, stamps and transforms are what went in (read back by
mcap_ros2, not by surgrecon), and the written config ingests it as written."""

from __future__ import annotations

import shlex
from pathlib import Path

import cv2
import numpy as np
import pytest
from convert_inputs import (
    D_LEFT,
    K_LEFT,
    K_RIGHT,
    opencv_calibration,
    read_log,
    right_in_left_m,
    static_pose,
    stereo_folder,
    stereo_video,
)

from surgrecon_cli.cli.main import main

IMAGE = "/camera/{}/image/compressed"
INFO = "/camera/{}/camera_info"


def _convert(*args: object) -> int:
    return main(["convert", *(str(a) for a in args), "-q"])


def _stamps(log, topic: str) -> list[int]:
    return [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in log[topic]]


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_jpeg_and_png_bytes_are_copied(tmp_path: Path, ext: str):
    files = stereo_folder(tmp_path / "rec", frames=3, ext=ext)
    opencv_calibration(tmp_path / "calib.yaml")
    out = tmp_path / "out.mcap"
    assert _convert(tmp_path / "rec", "-o", out, "--calibration", tmp_path / "calib.yaml",
                    "--fps", 20) == 0
    log = read_log(out)
    for side in ("left", "right"):
        msgs = [m for _, m in log[IMAGE.format(side)]]
        assert [bytes(m.data) for m in msgs] == [p.read_bytes() for p in files[side]]
        assert {m.format for m in msgs} == {"jpeg" if ext == ".jpg" else "png"}
        assert {m.header.frame_id for m in msgs} == {f"{side}_optical_frame"}
        # frame i at the default start (1 s) + i / fps
        assert _stamps(log, IMAGE.format(side)) == [10**9, 10**9 + 5 * 10**7, 10**9 + 10**8]
    info = log[INFO.format("left")][0][1]
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)), K_LEFT)
    np.testing.assert_allclose(info.d, D_LEFT)
    assert (info.width, info.height, info.distortion_model) == (320, 240, "plumb_bob")
    np.testing.assert_allclose(np.reshape(log[INFO.format("right")][0][1].k, (3, 3)), K_RIGHT)
    rot, pos = static_pose(log, "right_optical_frame")
    want_rot, want_pos = right_in_left_m()
    np.testing.assert_allclose(rot, want_rot, atol=1e-9)
    np.testing.assert_allclose(pos, want_pos, atol=1e-12)
    assert len(log["/tf"]) == 3  # world -> rig, once per frame
    text = out.with_suffix(".toml").read_text(encoding="utf-8")
    assert 'tool_pose = ""' in text and 'camera_pose = "/tf"' in text


def test_16_bit_png_stays_16_bit_and_tiff_bmp_become_lossless_png(tmp_path: Path):
    # Four folder layouts, each read left first: left/right, image_0/image_1, cam0/cam1 and
    # Hamlyn's rectified image01/image02.
    png16 = stereo_folder(tmp_path / "a", frames=2, ext=".png", depth16=True)
    tiff = stereo_folder(tmp_path / "b", frames=2, ext=".tiff", depth16=True,
                         names=("image_0", "image_1"))
    bmp = stereo_folder(tmp_path / "c", frames=2, ext=".bmp", names=("cam0", "cam1"))
    hamlyn = stereo_folder(tmp_path / "d", frames=2, ext=".png", names=("image01", "image02"))
    opencv_calibration(tmp_path / "calib.yaml")
    for src, files in (("a", png16), ("b", tiff), ("c", bmp), ("d", hamlyn)):
        out = tmp_path / f"{src}.mcap"
        assert _convert(tmp_path / src, "-o", out, "--calibration", tmp_path / "calib.yaml") == 0
        log = read_log(out)
        first = sorted(files)[0]
        for msg, path in zip([m for _, m in log[IMAGE.format("left")]], files[first],
                             strict=True):
            assert msg.format == "png"
            decoded = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8),
                                   cv2.IMREAD_UNCHANGED)
            original = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            assert decoded.dtype == original.dtype
            np.testing.assert_array_equal(decoded, original)


@pytest.mark.parametrize("layout", ["side-by-side", "top-bottom"])
def test_stereo_video_is_split_and_keeps_its_times(tmp_path: Path, layout: str):
    views = stereo_video(tmp_path / "v.mkv", frames=3, layout=layout, fps=25)
    opencv_calibration(tmp_path / "calib.yaml", size=(320, 240))  # auto layout from the size
    out = tmp_path / "v.mcap"
    assert _convert(tmp_path / "v.mkv", "-o", out, "--calibration", tmp_path / "calib.yaml",
                    "--image-format", "png") == 0
    log = read_log(out)
    for k, side in enumerate(("left", "right")):
        for (_, msg), frame in zip(log[IMAGE.format(side)], views, strict=True):
            decoded = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
            np.testing.assert_array_equal(decoded, frame[k])  # FFV1 + PNG: lossless
        assert _stamps(log, IMAGE.format(side)) == [10**9, 10**9 + 4 * 10**7,
                                                    10**9 + 8 * 10**7]


def test_video_frames_default_to_jpeg_quality_95(tmp_path: Path):
    views = stereo_video(tmp_path / "v.mkv", frames=2)
    opencv_calibration(tmp_path / "calib.yaml")
    out = tmp_path / "v.mcap"
    assert _convert(tmp_path / "v.mkv", "-o", out, "--calibration", tmp_path / "calib.yaml",
                    "--frames", "1:") == 0
    msgs = [m for _, m in read_log(out)[IMAGE.format("right")]]
    assert [m.format for m in msgs] == ["jpeg"]
    decoded = cv2.imdecode(np.frombuffer(bytes(msgs[0].data), np.uint8), cv2.IMREAD_COLOR)
    assert np.abs(decoded.astype(int) - views[1][1]).mean() < 4.0  # 4:2:0 chroma of a
    # saturated random texture; lossless would be 0


def test_the_written_config_ingests_the_log_with_its_geometry(tmp_path: Path):
    stereo_folder(tmp_path / "rec", frames=3, ext=".jpg", names=("Left", "Right"))
    opencv_calibration(tmp_path / "calib.yaml")
    out = tmp_path / "rec.mcap"
    assert _convert(tmp_path / "rec", "-o", out, "--calibration", tmp_path / "calib.yaml") == 0
    run = tmp_path / "run"
    assert main(["ingest", str(out), "-o", str(run), "--config", str(out.with_suffix(".toml")),
                 "-q"]) == 0
    from surgrecon_cli.io.run.ingest_store import load_ingested

    ingested = load_ingested(run / "ingest")
    assert ingested.cameras == ("left", "right") and ingested.n_frames == 3
    assert ingested.usable.all()
    want_rot, want_pos = right_in_left_m()
    np.testing.assert_allclose(ingested.poses[:, 0], np.broadcast_to(np.eye(4), (3, 4, 4)),
                               atol=1e-12)
    np.testing.assert_allclose(ingested.poses[:, 1, :3, :3], np.broadcast_to(want_rot, (3, 3, 3)),
                               atol=1e-9)
    np.testing.assert_allclose(ingested.poses[:, 1, :3, 3], np.broadcast_to(want_pos, (3, 3)),
                               atol=1e-12)
    np.testing.assert_allclose(ingested.models[1].K, K_RIGHT)


def test_tum_poses_and_stamps_file(tmp_path: Path):
    """The rig moves as the camera pose file says, the tool as the tool file says, and the
    frames take the stamps file's times; ingest interpolates both to the image times."""
    from scipy.spatial.transform import Rotation

    stereo_folder(tmp_path / "rec", frames=3, ext=".png")
    opencv_calibration(tmp_path / "calib.yaml")
    (tmp_path / "stamps.txt").write_text("# t [s]\n100.0\n100.1\n100.25\n", encoding="utf-8")
    # rig: turns 10 deg about z and moves 10 mm along x every 0.1 s, from 99.95 s
    quats = Rotation.from_euler("z", [[0], [10], [20], [30]], degrees=True).as_quat()
    pose_times = [99.95, 100.05, 100.15, 100.25]
    rows = [f"{t} {0.01 * k} 0.0 0.1 {' '.join(map(str, q))}"
            for k, (t, q) in enumerate(zip(pose_times, quats, strict=True))]
    (tmp_path / "cam.tum").write_text("\n".join(rows) + "\n", encoding="utf-8")
    (tmp_path / "tool.tum").write_text(
        "".join(f"{100 + k / 10:.1f} {0.01 * k} 0 0.05 0 0 0 1\n" for k in range(4)),
        encoding="utf-8")
    out = tmp_path / "rec.mcap"
    assert _convert(tmp_path / "rec", "-o", out, "--calibration", tmp_path / "calib.yaml",
                    "--stamps", tmp_path / "stamps.txt", "--camera-poses", tmp_path / "cam.tum",
                    "--tool-poses", tmp_path / "tool.tum") == 0
    log = read_log(out)
    assert _stamps(log, IMAGE.format("left")) == [100 * 10**9, 100_100_000_000, 100_250_000_000]
    tf = [(t.header.stamp.sec * 10**9 + t.header.stamp.nanosec, t.child_frame_id)
          for _, m in log["/tf"] for t in m.transforms]
    assert [t for t, child in tf if child == "rig"] == [round(t * 1e9) for t in pose_times]
    assert [t for t, child in tf if child == "tool_tip"] == [100 * 10**9 + k * 10**8
                                                             for k in range(4)]
    assert 'tool_pose = "/tf"' in out.with_suffix(".toml").read_text(encoding="utf-8")

    run = tmp_path / "run"
    assert main(["ingest", str(out), "-o", str(run), "--config", str(out.with_suffix(".toml")),
                 "-q"]) == 0
    from surgrecon_cli.io.run.ingest_store import load_ingested

    ingested = load_ingested(run / "ingest")
    assert ingested.usable.all()
    want_rot, want_pos = right_in_left_m()
    for f, t in enumerate([100.0, 100.1, 100.25]):
        k = (t - 99.95) / 0.1  # rig pose index, fractional
        rig_rot = Rotation.from_euler("z", 10 * k, degrees=True).as_matrix()
        rig_pos = np.array([0.01 * k, 0.0, 0.1])
        np.testing.assert_allclose(ingested.poses[f, 0, :3, :3], rig_rot, atol=1e-9)
        np.testing.assert_allclose(ingested.poses[f, 0, :3, 3], rig_pos, atol=1e-9)
        if f == 2:  # at a pose stamp; between them ingest interpolates each camera's chain
            np.testing.assert_allclose(ingested.poses[f, 1, :3, :3], rig_rot @ want_rot,
                                       atol=1e-9)
            np.testing.assert_allclose(ingested.poses[f, 1, :3, 3],
                                       rig_rot @ want_pos + rig_pos, atol=1e-9)
        np.testing.assert_allclose(ingested.tool_poses[f, :3, 3],
                                   [0.01 * (t - 100) / 0.1, 0, 0.05], atol=1e-9)


def test_each_tool_poses_file_is_a_tool(tmp_path: Path):
    """Two --tool-poses files (a dVRK's two arms): the second is a [[tools]] table on its own
    TF frame, and ingest gives each arm the positions its file says."""
    from surgrecon_cli.config import load_config
    from surgrecon_cli.io.run.ingest_store import load_ingested

    stereo_folder(tmp_path / "rec", frames=3, ext=".png")
    opencv_calibration(tmp_path / "calib.yaml")
    for name, y in (("psm1", 0.0), ("psm2", 0.02)):
        (tmp_path / f"{name}.tum").write_text(
            "".join(f"{1 + k / 30:.6f} {0.01 * k} {y} 0.05 0 0 0 1\n" for k in range(3)),
            encoding="utf-8")
    out = tmp_path / "rec.mcap"
    assert _convert(tmp_path / "rec", "-o", out, "--calibration", tmp_path / "calib.yaml",
                    "--tool-poses", tmp_path / "psm1.tum",
                    "--tool-poses", tmp_path / "psm2.tum") == 0
    config = load_config(out.with_suffix(".toml"))
    assert config.topics.tool_pose == "/tf" and len(config.tools) == 1
    run = tmp_path / "run"
    assert main(["ingest", str(out), "-o", str(run), "--config", str(out.with_suffix(".toml")),
                 "-q"]) == 0
    ingested = load_ingested(run / "ingest")
    assert ingested.extra_tool_poses.shape == (3, 1, 4, 4)
    for f in range(3):  # frames at 1 s + f / 30 (the default 30 fps), on the files' stamps
        np.testing.assert_allclose(ingested.tool_poses[f, :3, 3], [0.01 * f, 0, 0.05],
                                   atol=1e-6)
        np.testing.assert_allclose(ingested.extra_tool_poses[f, 0, :3, 3],
                                   [0.01 * f, 0.02, 0.05], atol=1e-6)


def test_one_folder_per_camera(tmp_path: Path):
    import json

    for k, name in enumerate(("a", "b", "c")):
        files = stereo_folder(tmp_path / name, frames=2, ext=".jpg", names=("img",))
        for path in files["img"]:  # each camera its own view (identical images are refused)
            assert cv2.imwrite(str(path), np.roll(cv2.imread(str(path)), 7 * k, axis=1))
    (tmp_path / "rig.json").write_text(json.dumps({"cameras": {
        "c": {"K": K_LEFT.tolist(), "D": [], "R": np.eye(3).tolist(), "T": [0, 0, 0]},
        "a": {"K": K_RIGHT.tolist(), "D": [], "R": np.eye(3).tolist(), "T": [-5, 0, 0]},
        "b": {"K": K_RIGHT.tolist(), "D": [], "R": np.eye(3).tolist(), "T": [0, -5, 0]},
    }}), encoding="utf-8")
    out = tmp_path / "three.mcap"
    assert _convert("-o", out, "--calibration", tmp_path / "rig.json",
                    *[x for n in "abc" for x in ("--camera", f"{n}={tmp_path / n / 'img'}")]) == 0
    log = read_log(out)
    assert {t for t in log if t.startswith("/camera/")} == {
        IMAGE.format(n) for n in "abc"} | {INFO.format(n) for n in "abc"}
    np.testing.assert_allclose(static_pose(log, "a_optical_frame")[1], [0.005, 0, 0])
    np.testing.assert_allclose(static_pose(log, "b_optical_frame")[1], [0, 0.005, 0])


def test_resized_images_scale_the_calibration_when_asked(tmp_path: Path, capsys):
    """Calibrated at 320x240, recorded at 160x120: an error naming both sizes, or with
    --scale-calibration K for the half-size image (pixel centres: u' = (u + 0.5) / 2 - 0.5)."""
    stereo_folder(tmp_path / "rec", frames=2, ext=".jpg", size=(160, 120))
    opencv_calibration(tmp_path / "calib.yaml", size=(320, 240))
    out = tmp_path / "rec.mcap"
    assert _convert(tmp_path / "rec", "-o", out, "--calibration", tmp_path / "calib.yaml") == 2
    assert "--scale-calibration" in capsys.readouterr().err
    assert _convert(tmp_path / "rec", "-o", out, "--calibration", tmp_path / "calib.yaml",
                    "--scale-calibration") == 0
    info = read_log(out)[INFO.format("right")][0][1]
    assert (info.width, info.height) == (160, 120)
    K = np.reshape(info.k, (3, 3))
    np.testing.assert_allclose(K[[0, 1], [0, 1]], K_RIGHT[[0, 1], [0, 1]] / 2)
    np.testing.assert_allclose(K[[0, 1], [2, 2]], (K_RIGHT[[0, 1], [2, 2]] + 0.5) / 2 - 0.5)


def test_scale_calibration_without_a_calibrated_size_is_refused(tmp_path: Path, capsys):
    """A calibration that states no image size gives --scale-calibration nothing to scale
    from: a one-line error naming the camera and the missing keys, and no log written."""
    stereo_folder(tmp_path / "rec", frames=2, ext=".jpg", size=(160, 120))
    opencv_calibration(tmp_path / "calib.yaml", size=None)
    out = tmp_path / "rec.mcap"
    assert _convert(tmp_path / "rec", "-o", out, "--calibration", tmp_path / "calib.yaml",
                    "--scale-calibration") == 2
    err = capsys.readouterr().err
    assert "no image size" in err and "imageSize" in err
    assert not out.exists()


def test_printed_commands_survive_spaces_in_paths(tmp_path: Path, capsys):
    """The commands convert prints (and writes atop OUT.toml), and ingest's hint at the
    config beside the log, are split by a POSIX shell (shlex.split) into the same words as
    the paths: a folder or name with a space or an accent was printed bare and the copied
    command ran on `my` and `recs/é`."""
    stereo_folder(tmp_path / "rec", frames=2, ext=".png")
    opencv_calibration(tmp_path / "calib.yaml")
    out = tmp_path / "my recs" / "é x.mcap"
    out.parent.mkdir()
    capsys.readouterr()
    assert main(["convert", str(tmp_path / "rec"), "-o", str(out), "--calibration",
                 str(tmp_path / "calib.yaml")]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    words = shlex.split(line.split("run it with", 1)[1])
    assert words == ["surgrecon", "run", str(out), "-o", "RUN", "--config",
                     str(out.with_suffix(".toml"))]
    header = out.with_suffix(".toml").read_text(encoding="utf-8").splitlines()[1]
    assert shlex.split(header.lstrip("# ")) == ["surgrecon", "run", "é x.mcap", "-o",
                                                "runs/é x", "--config", "é x.toml"]
    assert main(["ingest", str(out), "-o", str(tmp_path / "run"), "-q"]) == 2
    err = capsys.readouterr().err
    assert shlex.split(err.split("file: --config", 1)[1])[0] == str(out.with_suffix(".toml"))
    info = err.split("`")[3]  # `surgrecon convert`, then `surgrecon info LOG --write-config FILE`
    assert shlex.split(info) == ["surgrecon", "info", str(out), "--write-config", "FILE"]
