"""Simulator variant `rig-sweep`: an untracked stereo endoscope sweeping 2-4 deg a frame
over still tissue, seen from its fixed logged pose (issue 24, item 3's test data)."""

from __future__ import annotations

import itertools

import numpy as np

from surgrecon_cli.core.geometry.poses import fit_rigid
from surgrecon_cli.sim.simulate import LogBuilder
from surgrecon_cli.sim.variants import variant_config


def test_the_scene_turns_rigidly_2_to_4_degrees_a_frame_before_a_fixed_rig():
    for seed in (1, 2):
        cfg = variant_config("rig-sweep", frames=5, width=48, height=40, seed=seed)
        builder = LogBuilder(cfg)
        vertices = builder.true_vertices()
        angles = []
        for a, b in itertools.pairwise(vertices):
            R, t = fit_rigid(a, b)
            assert np.abs(a @ R.T + t - b).max() < 1e-9  # rigid: nothing deforms
            angles.append(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
        assert np.allclose(angles, angles[0], rtol=1e-6) and 2.0 <= angles[0] <= 4.0
        # The rig holds still and is logged without noise: the poses say nothing moved.
        for cam in range(cfg.cameras):
            poses = [builder.motion.camera_pose(cam, t) for t in builder.frame_times]
            assert np.abs(np.array(poses) - poses[0]).max() == 0.0
        assert cfg.tracker_noise_pos == 0.0 and cfg.tracker_noise_deg == 0.0
