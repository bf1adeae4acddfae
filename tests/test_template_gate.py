"""The template gate fits the images: the verified matches a pair needs follow the features
found (small images link at the defaults), an unlinkable frame names its pairs, their
counts and the keys to change, and camera groups whose poses disagree are reported."""

from __future__ import annotations

import re
from dataclasses import replace

import pytest
from scenes import render_frames

from surgrecon_cli.config import Config
from surgrecon_cli.core.evaluate.scoring import distance_stats_mm, map_to_surface
from surgrecon_cli.core.template.build import BuildOptions, TemplateFrame, build_template
from surgrecon_cli.core.template.gate import pair_minimums
from surgrecon_cli.errors import GeometryError
from surgrecon_cli.sim.scene import SimConfig


@pytest.fixture(scope="module")
def small():
    """4 cameras of 300x250 px: a few hundred features per image, a few dozen matches."""
    return render_frames(SimConfig(cameras=4, frames=2, width=300, height=250, seed=3), [0])


def _build(scene, poses=None, **template):
    cfg = Config()
    frame = TemplateFrame(scene.images[0], scene.poses[0] if poses is None else poses,
                          scene.tool_poses[0])
    return build_template(frame, scene.models, replace(cfg.template, **template), cfg.tool,
                          BuildOptions(names=["left", "right", "cam2", "cam3"]))


def test_minimum_follows_the_poorer_image():
    got = pair_minimums([3000, 600, 4000], floor=15, fraction=0.01)
    assert got[0, 2] == 30 and got[2, 2] == 40  # 1 % of the poorer image's 3000 / 4000
    assert got[0, 1] == 15 and got[1, 2] == 15  # the floor: 1 % of 600 is 6


def test_small_images_link_every_camera_at_the_defaults(small):
    result = _build(small)
    assert result.plan.groups == [[0, 1, 2, 3]]
    assert result.stats["disagreeing_groups"] == []
    assert max(result.stats["pair_minimums"].values()) < 40  # the former fixed minimum
    stats = distance_stats_mm(map_to_surface(result.points, small.vertices[0],
                                             small.faces).distance)
    assert len(result.points) >= 100 and stats["p95_mm"] <= 1.0


def test_an_unlinkable_frame_names_pairs_counts_and_keys(small):
    with pytest.raises(GeometryError) as err:
        _build(small, min_pair_matches=500)
    text = str(err.value)
    assert len(text.splitlines()) == 1
    counts = dict(re.findall(r"(\w+-\w+) (\d+)/500", text))
    assert "left-right" in counts and len(counts) >= 4, text
    assert "template.min_pair_matches" in text and "template.min_pair_match_fraction" in text


def test_groups_whose_poses_disagree_are_reported(small):
    """Cameras 2 and 3 displaced together by 3 mm (as with another calibration): their pairs
    with 0 and 1 no longer verify, and the groups' images agree while their poses do not."""
    poses = small.poses[0].copy()
    poses[2:, :3, 3] += [0.003, 0.0, 0.0]
    result = _build(small, poses)
    assert result.plan.groups == [[0, 1], [2, 3]]
    ((a, b, px),) = result.stats["disagreeing_groups"]
    assert (a, b) == ([0, 1], [2, 3]) and px > 3 * Config().template.epipolar_px
