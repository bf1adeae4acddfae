"""Stamps and TUM files of `convert`: exact decimal seconds, integer nanoseconds (EuRoC's
data.csv), comments; frame stamps from --fps after the start time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli.convert.stamps import frame_stamps, read_stamps, read_tum
from surgrecon_cli.errors import InputError


def test_decimal_seconds_are_exact_and_nanoseconds_are_recognised(tmp_path: Path):
    (tmp_path / "s.txt").write_text("# t\n1700000000.123456789\n1700000000.2 extra\n",
                                    encoding="utf-8")
    assert read_stamps(tmp_path / "s.txt").tolist() == [1_700_000_000_123_456_789,
                                                        1_700_000_000_200_000_000]
    (tmp_path / "data.csv").write_text("#timestamp [ns],filename\n"
                                       "1403636579763555584,1403636579763555584.png\n"
                                       "1403636579813555456,1403636579813555456.png\n",
                                       encoding="utf-8")
    assert read_stamps(tmp_path / "data.csv").tolist() == [1403636579763555584,
                                                           1403636579813555456]


def test_frame_stamps_from_fps_start_at_the_start_time():
    stamps = frame_stamps([0, 2, 4], fps=10.0, stamps_file=None, default_fps=None,
                          start_ns=10**9)
    assert stamps is not None and stamps.tolist() == [10**9, 12 * 10**8, 14 * 10**8]
    assert frame_stamps([0], fps=None, stamps_file=None, default_fps=None, start_ns=0) is None


def test_tum_quaternions_are_normalised_and_bad_ones_named(tmp_path: Path):
    (tmp_path / "t.tum").write_text("0.5 1 2 3 0 0 0 1.0000001\n", encoding="utf-8")
    track = read_tum(tmp_path / "t.tum", "camera pose file")
    np.testing.assert_allclose(track.orientations, [[0, 0, 0, 1]])
    assert track.stamps_ns.tolist() == [500_000_000]
    (tmp_path / "t.tum").write_text("0.5 1 2 3 0 0 0 1\n0.6 1 2 3 0 0 0 2\n", encoding="utf-8")
    with pytest.raises(InputError, match=r"t.tum line 2: not a finite position and unit"):
        read_tum(tmp_path / "t.tum", "camera pose file")


def test_negative_times_are_refused_in_one_line(tmp_path: Path, capsys):
    # MCAP log times are unsigned 64-bit: a stamps or TUM file in seconds relative to an
    # event (-0.2, -0.16, ...) ended convert in "internal error: argument out of range".
    from convert_inputs import opencv_calibration, stereo_folder

    from surgrecon_cli.cli.main import main

    stereo_folder(tmp_path / "rec", frames=3, ext=".png")
    opencv_calibration(tmp_path / "calib.yaml")
    (tmp_path / "s.txt").write_text("-0.2\n-0.1\n0.0\n", encoding="utf-8")
    (tmp_path / "c.tum").write_text("-0.5 0 0 0 0 0 0 1\n0.5 0 0 0.001 0 0 0 1\n",
                                    encoding="utf-8")
    out = tmp_path / "out.mcap"
    base = ["convert", str(tmp_path / "rec"), "-o", str(out), "--calibration",
            str(tmp_path / "calib.yaml"), "-q"]
    capsys.readouterr()
    assert main([*base, "--stamps", str(tmp_path / "s.txt")]) == 2
    assert main([*base, "--camera-poses", str(tmp_path / "c.tum")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "s.txt" in err[0] and "c.tum" in err[1]
    assert all("negative" in line for line in err)
    assert main([*base, "--start-time", "-1"]) == 2
    assert not out.exists() and not out.with_suffix(".toml").exists()


def test_a_camera_pose_file_on_another_clock_is_refused(tmp_path: Path, capsys, monkeypatch):
    # Poses from 0 s (a tracker's own clock), frames at the default --start-time 1 s + i / 30:
    # convert wrote the log, and ingest then failed, naming the poses' topic as "" and
    # advising ingest.time_source=log_time, which could not help. Convert refuses it now;
    # ingest's message (for such a log written elsewhere) names the /tf topic.
    from convert_inputs import opencv_calibration, stereo_folder

    import surgrecon_cli.convert.write as write
    from surgrecon_cli.cli.main import main

    stereo_folder(tmp_path / "rec", frames=3, ext=".png")
    opencv_calibration(tmp_path / "calib.yaml")
    (tmp_path / "c.tum").write_text("".join(f"{k / 10} {k / 1000} 0 0 0 0 0 1\n"
                                            for k in range(5)), encoding="utf-8")
    out = tmp_path / "out.mcap"
    args = ["convert", str(tmp_path / "rec"), "-o", str(out), "--calibration",
            str(tmp_path / "calib.yaml"), "--camera-poses", str(tmp_path / "c.tum"), "-q"]
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--camera-poses {tmp_path / 'c.tum'}:" in err[0]
    assert "0.000..0.400 s" in err[0]
    assert "1.000..1.067 s" in err[0]  # frames 0..2 at 1 s + i / 30
    assert not out.exists() and not out.with_suffix(".toml").exists()
    assert main([*args, "--start-time", "0.1"]) == 0  # frames 0.1..0.167 s: within them
    tool = ["--tool-poses", str(tmp_path / "c.tum")]  # tool removal would be silently off
    before = out.read_bytes()
    assert main([*args[:-3], *tool, "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--tool-poses {tmp_path / 'c.tum'}:" in err[0]
    assert out.read_bytes() == before
    monkeypatch.setattr(write, "_within_poses", lambda stream, tracks: stream)
    assert main(args) == 0  # such a log, as another tool may write it
    assert main(["ingest", str(out), "-o", str(tmp_path / "run"), "-q", "--config",
                 str(out.with_suffix(".toml"))]) == 2
    err = capsys.readouterr().err
    assert "poses on /tf at 0.000..0.400 s" in err and "poses on  at" not in err
