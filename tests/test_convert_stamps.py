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
