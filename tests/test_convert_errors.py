"""`surgrecon convert` on bad input: one line naming what is wrong, exit 2, and neither the
MCAP nor its config left behind."""

from __future__ import annotations

from pathlib import Path

import pytest
from convert_inputs import opencv_calibration, stereo_folder

from surgrecon_cli.cli.main import main


def _fails(capsys, tmp_path: Path, *args: object) -> str:
    out = tmp_path / "out.mcap"
    code = main(["convert", *(str(a) for a in args), "-o", str(out), "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err
    assert not out.exists() and not out.with_suffix(".toml").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith((".out", "out"))]
    return err


@pytest.fixture
def rec(tmp_path: Path) -> Path:
    stereo_folder(tmp_path / "rec", frames=3, ext=".png")
    opencv_calibration(tmp_path / "calib.yaml", size=(320, 240))
    return tmp_path / "rec"


def test_an_image_of_another_size_than_the_calibration(tmp_path: Path, rec: Path, capsys):
    stereo_folder(tmp_path / "small", frames=1, ext=".png", size=(160, 120))
    (tmp_path / "small" / "right" / "000000.png").replace(rec / "right" / "000002.png")
    err = _fails(capsys, tmp_path, rec, "--calibration", tmp_path / "calib.yaml")
    assert str(rec / "right" / "000002.png") in err and "160x120" in err and "320x240" in err


def test_an_image_of_another_size_than_the_first(tmp_path: Path, rec: Path, capsys):
    opencv_calibration(tmp_path / "nosize.yaml")
    stereo_folder(tmp_path / "small", frames=1, ext=".png", size=(160, 120))
    (tmp_path / "small" / "left" / "000000.png").replace(rec / "left" / "000001.png")
    err = _fails(capsys, tmp_path, rec, "--calibration", tmp_path / "nosize.yaml")
    assert str(rec / "left" / "000001.png") in err and "its first image is 320x240" in err


@pytest.mark.parametrize("content,needle", [(b"\xff\xd8\xff\xe0garbage", "corrupt header"),
                                            (b"not an image", "not an image OpenCV can read")])
def test_an_unreadable_image(tmp_path: Path, rec: Path, capsys, content: bytes, needle: str):
    (rec / "left" / "000001.png").write_bytes(content)
    err = _fails(capsys, tmp_path, rec, "--calibration", tmp_path / "calib.yaml")
    assert str(rec / "left" / "000001.png") in err and needle in err


@pytest.mark.parametrize("ext", [".png", ".jpg"])
@pytest.mark.parametrize("keep", [0.5, -1])
def test_a_truncated_image(tmp_path: Path, capsys, ext: str, keep: float):
    """A file cut short (half of it, or only its last byte missing) is named: its header
    still gives the right size, so only the structure check can find it."""
    stereo_folder(tmp_path / "rec", frames=3, ext=ext)
    opencv_calibration(tmp_path / "calib.yaml", size=(320, 240))
    path = tmp_path / "rec" / "right" / f"000001{ext}"
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep) if keep > 0 else -1])
    err = _fails(capsys, tmp_path, tmp_path / "rec", "--calibration", tmp_path / "calib.yaml")
    assert str(path) in err and "truncated" in err


def test_folders_with_different_image_counts(tmp_path: Path, rec: Path, capsys):
    (rec / "right" / "000002.png").unlink()
    err = _fails(capsys, tmp_path, rec, "--calibration", tmp_path / "calib.yaml")
    assert f"{rec / 'left'} 3" in err and f"{rec / 'right'} 2" in err


def test_no_stereo_folders(tmp_path: Path, rec: Path, capsys):
    err = _fails(capsys, tmp_path, tmp_path, "--calibration", tmp_path / "calib.yaml")
    assert "no stereo image folders" in err and "--left/--right" in err
    err = _fails(capsys, tmp_path, rec, "--calibration", tmp_path / "calib.yaml",
                 "--left", "left", "--right", "missing")
    assert str(rec / "missing") in err


def test_a_missing_calibration_file_and_a_missing_source(tmp_path: Path, rec: Path, capsys):
    err = _fails(capsys, tmp_path, rec, "--calibration", tmp_path / "nope.yaml")
    assert "nope.yaml" in err
    err = _fails(capsys, tmp_path, tmp_path / "gone.mp4", "--calibration",
                 tmp_path / "calib.yaml")
    assert "gone.mp4" in err and "does not exist" in err


def test_a_video_that_is_not_one(tmp_path: Path, rec: Path, capsys):
    (tmp_path / "broken.mp4").write_bytes(b"\x00" * 100)
    err = _fails(capsys, tmp_path, tmp_path / "broken.mp4", "--calibration",
                 tmp_path / "calib.yaml")
    assert "broken.mp4" in err and "cannot be read" in err


def test_bad_stamps_and_pose_files(tmp_path: Path, rec: Path, capsys):
    calib = tmp_path / "calib.yaml"
    (tmp_path / "stamps.txt").write_text("1.0\n1.1\n", encoding="utf-8")
    err = _fails(capsys, tmp_path, rec, "--calibration", calib, "--stamps",
                 tmp_path / "stamps.txt")
    assert "stamps.txt" in err and "has 2 stamps" in err
    (tmp_path / "stamps.txt").write_text("1.0\n1.2\n1.1\n", encoding="utf-8")
    err = _fails(capsys, tmp_path, rec, "--calibration", calib, "--stamps",
                 tmp_path / "stamps.txt")
    assert "must increase" in err
    (tmp_path / "poses.tum").write_text("1.0 0 0 0 0 0 0 1\n1.1 0 0 0 0 0 1\n", encoding="utf-8")
    err = _fails(capsys, tmp_path, rec, "--calibration", calib, "--camera-poses",
                 tmp_path / "poses.tum")
    assert "poses.tum line 2" in err and "expected 8 values" in err


def test_per_camera_videos_of_different_lengths_are_warned_of(tmp_path: Path, rec: Path,
                                                              capsys):
    # One video per camera pairs frames by index: videos of 3 and 2 frames were cut to 2
    # without a word (folders of different counts are refused), though a frame lost inside
    # one of them shifts every later pair.
    import av
    from convert_inputs import read_log, texture

    for name, frames in (("left", 3), ("right", 2)):
        with av.open(str(tmp_path / f"{name}.mkv"), "w") as container:
            stream = container.add_stream("ffv1", rate=25)
            stream.width, stream.height, stream.pix_fmt = 320, 240, "bgr0"
            for i in range(frames):
                image = texture(240, 320, 10 * i + (name == "right"))
                container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")))
            container.mux(stream.encode(None))
    out = tmp_path / "out.mcap"
    capsys.readouterr()
    assert main(["convert", "-o", str(out), "--calibration", str(tmp_path / "calib.yaml"),
                 "--camera", f"left={tmp_path / 'left.mkv'}",
                 "--camera", f"right={tmp_path / 'right.mkv'}", "-q"]) == 0
    err = capsys.readouterr().err
    assert f"{tmp_path / 'left.mkv'} 3, {tmp_path / 'right.mkv'} 2" in err
    assert "first 2" in err
    assert len(read_log(out)["/camera/left/image/compressed"]) == 2
