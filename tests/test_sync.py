"""core.sync.streams: frame grouping, pose/joint interpolation, pose validation (pure numpy)."""

from __future__ import annotations

import numpy as np
import pytest

from surgrecon_cli.core.geometry.poses import make_pose, quat_to_matrix
from surgrecon_cli.core.sync.streams import (
    base_to_world_pose,
    group_frames,
    interpolate_values,
    poses_at,
    rate_hz,
    select_frames,
    validate_pose_stream,
)
from surgrecon_cli.errors import InputError

MS = 1_000_000


def test_group_frames_median_stamp_and_offsets():
    base = np.arange(5) * 100 * MS
    stamps = [base, base + 4 * MS, base + 10 * MS]
    g = group_frames(stamps, 15 * MS)
    assert g.n_frames == 5
    np.testing.assert_array_equal(g.stamps_ns, base + 4 * MS)
    np.testing.assert_array_equal(g.image_index, np.tile(np.arange(5)[:, None], (1, 3)))
    assert g.duplicates.sum() == 0 and g.late.sum() == 0


def test_group_frames_missing_duplicate_and_late_images():
    base = np.arange(4) * 100 * MS
    cam0 = base
    cam1 = np.delete(base, 2) + 2 * MS  # dropped at frame 2
    cam2 = np.sort(np.concatenate([base + 1 * MS, [105 * MS]]))  # duplicate in frame 1
    cam3 = np.array([0, 100, 240, 300]) * MS  # 240 ms: late, matches nobody
    g = group_frames([cam0, cam1, cam2, cam3], 15 * MS)
    assert g.n_frames == 5
    assert g.image_index[2, 1] == -1
    assert list(g.duplicates) == [0, 0, 1, 0]
    assert list(g.late) == [0, 0, 0, 1]
    late_frame = int(np.flatnonzero(g.stamps_ns == 240 * MS)[0])
    assert (g.image_index[late_frame] >= 0).sum() == 1


def test_group_frames_independent_of_camera_order():
    rng = np.random.default_rng(3)
    stamps = [np.sort(rng.integers(0, 10**9, 30)) for _ in range(4)]
    a = group_frames(stamps, 15 * MS)
    b = group_frames(stamps[::-1], 15 * MS)
    np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
    np.testing.assert_array_equal(a.image_index, b.image_index[:, ::-1])


def test_group_frames_rejects_unsorted():
    with pytest.raises(ValueError, match="sorted"):
        group_frames([np.array([3, 1])], 5)


def _rot_stream(stamps):
    angle = 0.8 * stamps * 1e-9
    axis = np.array([0.0, 0.6, 0.8])
    q = np.concatenate([np.sin(angle / 2)[:, None] * axis, np.cos(angle / 2)[:, None]], axis=1)
    p = np.stack([stamps * 1e-9, 2 * stamps * 1e-9, np.ones(len(stamps))], axis=1)
    return p, q


def test_poses_at_exact_for_linear_motion_and_constant_rotation_rate():
    stamps = np.arange(0, 1000, 40) * MS
    p, q = _rot_stream(stamps)
    stream = validate_pose_stream("/pose", stamps, p, q)
    query = np.array([13, 500, 777]) * MS
    poses, valid = poses_at(stream, query, 100 * MS)
    assert valid.all()
    p_true, q_true = _rot_stream(query)
    np.testing.assert_allclose(poses[:, :3, 3], p_true, atol=1e-12)
    np.testing.assert_allclose(poses[:, :3, :3], quat_to_matrix(q_true), atol=1e-12)


def test_poses_at_never_extrapolates_and_respects_gap():
    stamps = np.array([0, 40, 200, 240]) * MS
    p, q = _rot_stream(stamps)
    stream = validate_pose_stream("/pose", stamps, p, q)
    poses, valid = poses_at(stream, np.array([-1, 20, 100, 240, 241]) * MS, 100 * MS)
    assert list(valid) == [False, True, False, True, False]
    assert np.isnan(poses[~valid]).all()


def test_validate_pose_stream_errors_name_topic_and_stamp():
    stamps = np.array([1, 2, 3]) * 10**9
    p = np.zeros((3, 3))
    q = np.tile([0.0, 0, 0, 1], (3, 1))
    bad = p.copy()
    bad[1, 2] = np.nan
    with pytest.raises(InputError, match=r"/tracker: pose at stamp 2\.000000000 s has non-finite"):
        validate_pose_stream("/tracker", stamps, bad, q)
    badq = q.copy()
    badq[2] *= 1.01
    with pytest.raises(InputError, match=r"/tracker: pose at stamp 3\.000000000 s .*non-unit"):
        validate_pose_stream("/tracker", stamps, p, badq)


def test_validate_pose_stream_sorts_dedupes_and_normalises():
    stamps = np.array([3, 1, 2, 2])
    q = np.tile([0.0, 0, 0, 1.0005], (4, 1))
    positions = np.arange(12.0).reshape(4, 3)
    positions[3] = positions[2] + [2e-4, 0, 0]  # within 1 mm of the sample it repeats
    s = validate_pose_stream("x", stamps, positions, q)
    assert list(s.stamps_ns) == [1, 2, 3] and len(s.conflict_stamps_ns) == 0
    np.testing.assert_allclose(np.linalg.norm(s.quats, axis=1), 1.0)
    np.testing.assert_allclose(s.positions[1], [6, 7, 8])  # first of the repeated stamp
    # samples at one stamp 5 cm or 1° apart conflict: both dropped, and listed
    for moved, turned in ((0.05, 0.0), (0.0, 1.0)):
        positions[3] = positions[2] + [moved, 0, 0]
        q[3] = [np.sin(np.radians(turned) / 2), 0, 0, np.cos(np.radians(turned) / 2)]
        s = validate_pose_stream("x", stamps, positions, q)
        assert list(s.stamps_ns) == [1, 3] and list(s.conflict_stamps_ns) == [2]
        np.testing.assert_allclose(s.conflict_sizes, [[moved, np.radians(turned)]], atol=1e-6)


def test_interpolate_values_linear_gap_and_bounds():
    stamps = np.array([0, 10, 20, 200])
    values = np.stack([stamps * 2.0, -stamps * 1.0], axis=1)
    out = interpolate_values(stamps, values, np.array([-1, 0, 5, 15, 100, 200, 201]), 50)
    np.testing.assert_allclose(out[1:4], [[0, 0], [10, -5], [30, -15]])
    np.testing.assert_allclose(out[5], [400, -200])
    assert np.isnan(out[[0, 4, 6]]).all()


def test_base_to_world_pose_and_rate():
    T = base_to_world_pose([1, 2, 3, 0, 0, 0, 1])
    np.testing.assert_allclose(T, make_pose(np.array([1.0, 2, 3]), np.array([0.0, 0, 0, 1])))
    with pytest.raises(InputError, match="base_to_world"):
        base_to_world_pose([0, 0, 0, 0, 0, 0, 2])
    assert rate_hz(np.arange(11) * 100 * MS) == pytest.approx(10.0)
    assert rate_hz(np.array([5])) == 0.0


def test_a_part_of_the_frames_is_selected_by_time_and_step():
    """start_s / duration_s from the first frame (the window half-open), every N-th of
    those: 10 Hz frames over 5 s, 1.0-3.0 s every 3rd -> frames 10, 13, ..., 28."""
    stamps = 1_000_000_000 + np.arange(50) * 100_000_000
    np.testing.assert_array_equal(select_frames(stamps, 1.0, 2.0, 3), np.arange(10, 30, 3))
    np.testing.assert_array_equal(select_frames(stamps, 0.0, 0.0, 1), np.arange(50))
    np.testing.assert_array_equal(select_frames(stamps, 4.55, 0.0, 2), [46, 48])
    assert len(select_frames(stamps, 5.0, 1.0, 1)) == 0
