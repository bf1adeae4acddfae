"""The frame step's cheap paths: KLT depth from the measured motion (the tracks beyond its
reach retried from their neighbours' flow) and the tool contact folded into one
registration."""

from __future__ import annotations

import numpy as np
from scenes import render_frames

from surgrecon_cli.config import Config
from surgrecon_cli.core.geometry.tool import push_out_of_tool
from surgrecon_cli.core.registration import register
from surgrecon_cli.core.registration.frame_step import DataTerm, register_with_contact
from surgrecon_cli.core.target.tracking import (
    TrackPrior,
    klt_levels_for,
    klt_track,
    retrack_from_neighbours,
    track_adaptive,
    track_first,
    tracking_view,
)
from surgrecon_cli.sim.scene import SimConfig


def test_levels_follow_the_motion_and_window():
    # A 21 px window reaches 21/4 px at level 0 and doubles per level.
    assert klt_levels_for(0.5, 21, 3) == 0
    assert klt_levels_for(5.0, 21, 3) == 0
    assert klt_levels_for(8.0, 21, 3) == 1
    assert klt_levels_for(20.0, 21, 3) == 2
    assert klt_levels_for(500.0, 21, 3) == 3
    assert klt_levels_for(float("nan"), 21, 3) == 3


def _texture(shift_x: float, size: int = 200) -> np.ndarray:
    """RGB image of smooth random blobs, moved right by shift_x px (exact: analytic)."""
    rng = np.random.default_rng(3)
    centres = rng.uniform(0, size, (120, 2))
    widths = rng.uniform(3, 7, 120)
    levels = rng.uniform(-1, 1, 120)
    v, u = np.mgrid[0:size, 0:size].astype(float)
    grey = np.zeros((size, size))
    for (cx, cy), w, a in zip(centres, widths, levels, strict=True):
        grey += a * np.exp(-((u - cx - shift_x) ** 2 + (v - cy) ** 2) / (2 * w * w))
    grey = np.clip(128 + 60 * grey, 0, 255).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def test_a_motion_beyond_the_chosen_depth_is_found_by_the_neighbour_retries():
    # The image moved 14 px; the guesses miss it by 0 px on the left growing to 14 px on
    # the right, and the expected motion says 1 px (depth 0 reaches ~5 px): the first
    # tracks beyond that reach fail (none is kept where it slid), and the retries from
    # their found neighbours' departures find them, ring by ring.
    cfg = Config().target
    prev, cur = tracking_view(_texture(0.0)), tracking_view(_texture(14.0))
    g = np.arange(50.0, 150.0, 12.0)
    start = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    miss = 14.0 * (start[:, 0] - 50.0) / 100.0
    guess = start + np.column_stack([14.0 - miss, np.zeros(len(start))])
    truth = start + np.array([14.0, 0.0])
    first, ok_first, _ = track_first(prev, cur, start, TrackPrior(guess, 1.0), cfg)
    assert ok_first[miss < 4.0].all() and not ok_first[miss > 6.0].any()
    assert np.abs(first[ok_first] - truth[ok_first]).max() < 0.25
    tracked, ok, _ = track_adaptive(prev, cur, start, TrackPrior(guess, 1.0), cfg)
    assert ok.mean() > 0.9
    assert np.median(np.abs(tracked[ok] - truth[ok])) < 0.05


def test_of_two_priors_the_one_whose_pilot_tracks_more_points_is_used():
    # The image moved 14 px; one prior (a stale projection) is 74 px off, beyond the
    # pyramid's reach (only the retries from the found tracks' flow rescue some of its
    # tracks); the other (no motion) is 14 px off: the tracks start from it.
    cfg = Config().target
    prev, cur = tracking_view(_texture(0.0)), tracking_view(_texture(14.0))
    g = np.arange(50.0, 150.0, 8.0)
    start = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    stale = start - [60.0, 0.0]
    _, ok_stale, _ = track_adaptive(prev, cur, start, TrackPrior(stale), cfg)
    tracked, ok, _ = track_adaptive(prev, cur, start,
                                    TrackPrior(stale, alternative=start.copy()), cfg)
    assert ok.mean() > 0.9 and ok.mean() > ok_stale.mean() + 0.1
    assert np.median(np.abs(tracked[ok] - (start[ok] + [14.0, 0.0]))) < 0.05


def test_the_chosen_depth_tracks_as_the_full_depth_on_a_simulated_frame_pair():
    sim = SimConfig(cameras=1, frames=20, width=320, height=256, seed=5)
    scene = render_frames(sim, [5, 6])
    cfg = Config().target
    prev, cur = tracking_view(scene.images[0][0]), tracking_view(scene.images[1][0])
    rng = np.random.default_rng(0)
    start = rng.uniform([30, 30], [290, 226], (300, 2))
    full, ok_full = klt_track(prev, cur, start, start.copy(), cfg, cfg.klt_levels)
    chosen, ok, _ = track_adaptive(prev, cur, start, TrackPrior(start.copy(), 1.0), cfg)
    both = ok & ok_full
    assert both.sum() >= 0.95 * ok_full.sum()
    # Within the tracker's own stopping tolerance (an update below 0.01 px ends it).
    assert np.percentile(np.linalg.norm(chosen[both] - full[both], axis=1), 95) < 1e-2


def test_retries_for_wanted_tracks_alone_give_those_tracks():
    # A 14 px motion guessed as none at depth 0: most tracks fail and are retried from
    # their neighbours' flow. Retrying only where the wanted tracks' retries look gives
    # the wanted tracks of retrying every one, with fewer KLT points.
    cfg = Config().target
    prev, cur = tracking_view(_texture(0.0)), tracking_view(_texture(14.0))
    g = np.arange(30.0, 170.0, 7.0)
    start = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    guess = start.copy()
    first = klt_track(prev, cur, start, guess, cfg, 0)
    moved = start[:, 0] < 80.0  # found (at the truth) left of x = 80, lost right of it
    found = (np.where(moved[:, None], start + np.array([14.0, 0.0]), first[0]), first[1] & moved)
    every = retrack_from_neighbours((prev, cur), start, guess, found, cfg)
    wanted = np.linalg.norm(start - [90.0, 100.0], axis=1) < 8.0
    alone = retrack_from_neighbours((prev, cur), start, guess, found, cfg, wanted)
    assert (~found[1] & wanted).any() and every[1][wanted].any()
    np.testing.assert_array_equal(alone[1][wanted], every[1][wanted])
    np.testing.assert_array_equal(alone[0][wanted], every[0][wanted])
    assert (alone[1] != every[1]).any()  # the others were not all retried


def test_contact_is_folded_into_one_registration_and_keeps_the_tissue_out_of_the_tool(
        monkeypatch):
    # A flat 18 mm patch; the tool (4 mm radius, rounded end) presses 2 mm into its centre,
    # where the cameras see no tissue (weight 0); the rest is observed still. Tissue cannot
    # be inside the tool: under it, it lies on the tool's rounded end.
    import surgrecon_cli.core.registration.frame_step as frame_step

    solves = []
    monkeypatch.setattr(frame_step, "register",
                        lambda *a, **k: solves.append(1) or register(*a, **k))
    config = Config()
    g = np.arange(-9e-3, 9e-3 + 1e-9, 0.6e-3)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    source = np.c_[xy, np.zeros(len(xy))]
    rgb = np.full((len(source), 3), 128, np.uint8)
    seen = np.linalg.norm(xy, axis=1) > 6e-3
    ids = np.flatnonzero(seen)
    tool = np.eye(4)
    tool[:3, 3] = [0.0, 0.0, -2e-3]  # tip 2 mm into the surface, shaft along +z
    data = DataTerm(source[ids], rgb[ids], ids, seen.astype(float))
    result, n_contact = register_with_contact(source, rgb, data, tool, config)
    assert len(solves) == 1
    r = np.linalg.norm(xy, axis=1)
    # The rounded end (centre 2 mm above the surface) cuts the plane in a circle of radius
    # sqrt(4² - 2²) mm: every point within it is in contact.
    assert n_contact == (r < np.sqrt(12) * 1e-3).sum() > 80
    _, pushed = push_out_of_tool(result.registered, tool, config.tool)
    assert np.linalg.norm(pushed - result.registered, axis=1).max() < 2e-6
    under = r < 3.3e-3
    on_tool = 2e-3 - np.sqrt(4e-3**2 - r[under] ** 2)  # the rounded end's surface z (m)
    # Within 3x the solver's tolerance (registration.tolerance_mm = 0.02): a point may stop
    # that far beyond the surface (measured: 0.051 mm with 5 ADMM iterations per
    # intermediate outer step, under 0.05 with 15).
    assert np.abs(result.registered[under, 2] - on_tool).max() < 0.06e-3
    moved = np.einsum("nij,nj->ni", result.transforms[:, :, :3], source) + result.transforms[
        :, :, 3]
    np.testing.assert_allclose(moved, result.registered, atol=1e-9)
    still = np.linalg.norm(result.registered[seen] - source[seen], axis=1)
    assert np.median(still) < 0.05e-3
