"""`register_pair` (issue 28): a colour decision strays cannot make, the same at any density
and stray share; points without target surface follow their supported neighbours and stay
put beside static ones; an error estimate that sees the along-surface error where colour does.

Truth from the simulator (sim/pairs_stray.py: which target points are strays, where every
source point truly went); acceptance seeds (100+) only: the weights were tuned on 0-4.
"""

from __future__ import annotations

import numpy as np
import pytest

from surgrecon_cli.config import RegistrationConfig
from surgrecon_cli.core.registration.colour import decide_colour
from surgrecon_cli.core.registration.overlap import (
    ColouredPoints,
    across_only,
    coupled_to_unsupported,
    explained_by_identity,
    follow_supported,
    matched_onto_cut,
    stay_where_better,
    target_rim,
)
from surgrecon_cli.core.registration.pair import error_estimate_mm, pair_config
from surgrecon_cli.core.registration.surface import smallest_axis
from surgrecon_cli.registration import register_pair
from surgrecon_cli.sim.pairs_catalog import make_pair
from surgrecon_cli.sim.pairs_stray import stray_colour_pair

GATE_M = 5e-3


def _decide(pair):  # as register_pair decides: on every target point
    return decide_colour(pair.target, pair.target_rgb, GATE_M)


def test_colour_decision_is_the_same_from_1k_to_100k_points_and_0_to_30_percent_strays():
    weights = []
    for n, strays in ((1000, 0.2), (5000, 0.0), (5000, 0.2), (5000, 0.3), (20000, 0.2),
                      (100000, 0.3)):
        d = _decide(stray_colour_pair(n, 100, strays=strays))
        assert d.weight_mm > 0, (n, strays, d.reason)
        weights.append(d.weight_mm)
    assert max(weights) < 2.0 * min(weights)


def test_random_coloured_strays_on_the_surface_are_told_apart_by_colour():
    pair = stray_colour_pair(5000, 101)
    d = _decide(pair)
    assert np.mean(~d.agree[pair.target_outlier]) > 0.75  # strays flagged
    assert np.mean(d.agree[~pair.target_outlier]) > 0.9  # tissue kept


def test_flat_colour_with_random_strays_is_not_used():
    pair = stray_colour_pair(5000, 102)
    rng = np.random.default_rng(0)
    flat = np.clip(0.6 + rng.normal(0, 4 / 255, pair.target_rgb.shape), 0, 1)
    flat[pair.target_outlier] = rng.uniform(0, 1, (int(pair.target_outlier.sum()), 3))
    assert decide_colour(pair.target, flat, GATE_M).weight_mm == 0.0


@pytest.mark.parametrize("strays", [0.0, 0.2])
def test_colour_is_used_with_and_without_strays_and_registers_within_the_goals(strays):
    # issue 28's 2k goals (median <= 0.5 mm, p95 <= 1.5 mm), and far below doing nothing
    pair = stray_colour_pair(2000, 102, strays=strays)
    res = register_pair(pair.source, pair.target, pair.source_rgb, pair.target_rgb)
    assert "more than" in res.stats[0]["colour_reason"]
    assert res.stats[0]["colour_weight_mm"] > 0
    err = np.linalg.norm(res.registered - pair.truth, axis=1) * 1e3
    still = np.linalg.norm(pair.source - pair.truth, axis=1) * 1e3
    assert np.median(err) < min(0.5, 0.35 * np.median(still))
    assert np.percentile(err, 95) < 1.5
    if strays:  # strays are left out of the target, not matched
        assert res.stats[0]["colour_strays"] > 0.5 * pair.target_outlier.sum()
        free = res.correspondences[res.correspondences >= 0]
        assert pair.target_outlier[free].mean() < 0.02


def test_pair_config_replaces_only_the_defaults():
    cfg = pair_config(RegistrationConfig(max_nodes=600), 20000)
    default = RegistrationConfig()
    assert cfg.max_nodes == 600  # set by the caller: kept
    assert cfg.rigid_iterations < default.rigid_iterations
    assert cfg.outer_iterations > default.outer_iterations  # dense: more outer steps
    assert pair_config(default, 2000).outer_iterations == default.outer_iterations
    assert pair_config(RegistrationConfig(outer_iterations=3), 20000).outer_iterations == 3
    # the mutual check never narrower than a quarter of the 5 mm gate, however dense
    for spacing_m in (0.1e-3, 0.4e-3, 1e-3):
        wide = pair_config(default, 5000, spacing_m).mutual_spacings * spacing_m
        assert wide >= 0.25 * default.max_correspondence_mm * 1e-3 - 1e-12
    assert pair_config(default, 5000, 1e-3).mutual_spacings > default.mutual_spacings
    # the last step's ADMM iterations capped, unless the caller chose them
    assert pair_config(default, 5000).final_admm_iterations < default.final_admm_iterations
    assert pair_config(RegistrationConfig(final_admm_iterations=80),
                       5000).final_admm_iterations == 80


def test_the_colour_decisions_neighbour_lists_give_the_same_rim_and_planes():
    # register_pair hands the colour decision's k-d tree and neighbour lists of the agreeing
    # target points on to the rim and plane analysis: the same as measuring them again
    pair = stray_colour_pair(3000, 105)
    d = _decide(pair)
    assert d.neighbours is not None
    xyz, rgb = pair.target[d.agree], pair.target_rgb[d.agree]
    shared = ColouredPoints.analysed(xyz, rgb, d.neighbours)
    alone = ColouredPoints.analysed(xyz, rgb)
    assert shared.rim is not None and alone.rim is not None and shared.rim.any()
    np.testing.assert_array_equal(shared.rim, alone.rim)
    np.testing.assert_allclose(shared.centre, alone.centre, rtol=0, atol=1e-12)
    assert shared.tree is d.neighbours.tree
    probe = pair.source[:50]
    np.testing.assert_array_equal(shared.tree.query(probe, k=3)[1],
                                  alone.tree.query(probe, k=3)[1])


def test_unsupported_points_follow_near_supported_ones_and_keep_their_own_far_away():
    rng = np.random.default_rng(3)
    src = np.c_[rng.uniform(0, 0.03, (3000, 2)), np.zeros(3000)]
    supported = src[:, 0] < 0.015
    shift = np.array([0.5e-3, -1e-3, 2e-3])
    reg = src + shift * supported[:, None]
    out = follow_supported(src, reg, supported, reach=(0.1, 0.2))  # 4.2 / 8.5 mm
    gap = src[:, 0] - 0.015
    near, far = ~supported & (gap < 3e-3), ~supported & (gap > 9e-3)
    np.testing.assert_allclose(out[near] - src[near], np.tile(shift, (near.sum(), 1)),
                               atol=1e-9)
    np.testing.assert_allclose(out[far], src[far], atol=1e-12)
    np.testing.assert_array_equal(out[supported], reg[supported])


@pytest.fixture(scope="module")
def partial_run():
    pair = stray_colour_pair(2000, 103, partial=0.3)
    return pair, register_pair(pair.source, pair.target, pair.source_rgb, pair.target_rgb)


def test_points_without_target_surface_are_not_worse_than_not_moving(partial_run):
    pair, res = partial_run
    err = np.linalg.norm(res.registered - pair.truth, axis=1)
    still = np.linalg.norm(pair.source - pair.truth, axis=1)
    lost = ~res.supported
    assert lost.sum() > 0.15 * len(err)  # the cut side is found
    assert np.median(err[lost]) < np.median(still[lost]) + 0.1e-3
    assert np.median(err) < 0.5e-3  # the supported part is registered


def test_error_estimate_is_within_10x_of_the_true_error_and_says_what_it_sees(partial_run):
    pair, res = partial_run
    true_median = np.median(np.linalg.norm(res.registered - pair.truth, axis=1)) * 1e3
    median, p95, sees = error_estimate_mm(res, pair.source)
    assert true_median / 10 < median < 10 * true_median and p95 >= median
    assert "along" in sees and "colour" in sees and "cannot be seen" in sees


def test_without_colour_the_estimate_counts_the_motion_a_slide_could_hide():
    pair = make_pair("blob", 1500, 104)
    res = register_pair(pair.source, pair.target)
    true_median = np.median(np.linalg.norm(res.registered - pair.truth, axis=1)) * 1e3
    median, _, sees = error_estimate_mm(res, pair.source)
    assert median > true_median / 10 and "cannot be seen" in sees
    across = np.nanmedian(res.residuals) * 1e3
    assert median > 2 * across  # more than the across-surface part alone


def test_coincident_target_points_leave_colour_out():
    rng = np.random.default_rng(5)
    d = decide_colour(np.zeros((60, 3)), rng.uniform(0, 1, (60, 3)), GATE_M)
    assert d.weight_mm == 0.0


def test_known_pairs_keep_the_callers_target_indices_when_strays_are_left_out():
    pair = stray_colour_pair(1500, 104)
    m = len(pair.target)
    stray = int(np.flatnonzero(pair.target_outlier)[0])  # a landmark may name any target
    ids = np.full(m, -1)
    ids[7] = 3
    res = register_pair(pair.source, pair.target, pair.source_rgb, pair.target_rgb,
                        landmarks=np.array([[0, 5], [10, stray]]), target_ids=ids)
    assert res.stats[0]["colour_strays"] > 0.5 * pair.target_outlier.sum()
    assert list(res.correspondences[[0, 10, 3]]) == [5, stray, 7]
    free = res.correspondences[res.correspondences >= 0]
    assert free.max() < m and pair.target_outlier[free].mean() < 0.02


def test_static_tissue_dragged_along_the_surface_goes_back_and_moving_tissue_keeps_its_motion():
    # registered = the simulator's truth, except static tissue (true motion < 0.05 mm) slid
    # 0.6 mm along the surface, as the shared solver drags it next to moving tissue
    pair = stray_colour_pair(5000, 102)
    d = _decide(pair)
    move = np.linalg.norm(pair.truth - pair.source, axis=1)
    static, moving = move < 0.05e-3, move > 1e-3
    assert static.sum() > 300 and moving.sum() > 300
    centred = pair.source - pair.source.mean(0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    along = np.cross(normal, [1.0, 0.0, 0.0])
    registered = pair.truth + np.where(static[:, None], 0.6e-3 * along / np.linalg.norm(along),
                                       0.0)
    share = stay_where_better(pair.source, registered, np.ones(len(pair.source), bool),
                              pair.source_rgb,
                              ColouredPoints(pair.target[d.agree], pair.target_rgb[d.agree]), d)
    corrected = pair.source + share[:, None] * (registered - pair.source)
    err = np.linalg.norm(corrected - pair.truth, axis=1)
    assert np.median(err[static]) < 0.2e-3  # from 0.6 mm
    assert np.median(err[moving]) < 0.1e-3  # the true motion (> 1 mm) is kept


def _curved_sheet(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n random points of a gently curved 40 mm square sheet, tilted, and each one's
    distance to the square's border (mm, in the sheet's own coordinates)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0.0, 40.0, (n, 2))
    xyz = np.c_[uv, 0.004 * (uv[:, 0] - 20.0) ** 2 + 0.002 * uv[:, 1] ** 2] * 1e-3
    c, s = np.cos(0.6), np.sin(0.6)
    xyz = xyz @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return xyz, np.minimum(uv, 40.0 - uv).min(axis=1)


def test_target_rim_finds_the_border_of_a_randomly_sampled_sheet_and_little_inside():
    xyz, border_mm = _curved_sheet(4000, 7)
    spacing_mm = 40.0 / np.sqrt(4000)  # ~0.63 mm between neighbours
    rim = target_rim(xyz)
    assert np.mean(rim[border_mm < 0.3 * spacing_mm]) > 0.5  # on the edge: mostly found
    assert np.mean(border_mm[rim] < 2.0 * spacing_mm) > 0.9  # what is found is at the edge
    assert np.mean(rim[border_mm > 4.0 * spacing_mm]) < 0.005  # inside: almost never


def test_smallest_axis_matches_eigh():
    a = np.random.default_rng(3).normal(size=(500, 3, 3))
    cov = a @ a.transpose(0, 2, 1)
    ref = np.linalg.eigh(cov)[1][:, :, 0]  # independent reference
    assert np.all(np.abs((smallest_axis(cov) * ref).sum(axis=1)) > 1 - 1e-6)
    # collinear points (two zero eigenvalues): still a unit vector across their line
    line = np.outer(np.linspace(-1.0, 1.0, 10), [1.0, 2.0, 0.5])
    axis = smallest_axis((line.T @ line)[None])[0]
    assert abs(np.linalg.norm(axis) - 1.0) < 1e-9 and abs(axis @ [1.0, 2.0, 0.5]) < 1e-6



@pytest.mark.parametrize("seed", [200, 208, 396, 518, 926])
def test_a_cut_pair_is_nowhere_worse_than_doing_nothing_beyond_the_targets_noise(seed):
    # issue 28: no 5 mm cell of the source (>= 10 points) with a median error more than the
    # target's noise (0.2 mm) above doing nothing's; seeds neither tuning 0-9 nor acceptance
    # 100-104: on 200 the code before this test left +0.35 mm; on 208, static tissue at the
    # target's rim (a border both clouds share) dragged 0.3-0.5 mm inwards, +0.34 mm before
    # the identity test let the neighbours inside decide for points at the rim; on 518 (a seed
    # outside every set tuned or checked on), +0.44 mm before the identity test's colour
    # misfit counted robustly (`robust_colour`); on 926 (picked among 900-939 after the
    # change), +0.69 mm before `colour_flow` pooled the along-surface motion over the nodes;
    # on 396, static tissue 1 mm past a cut's rim, +0.31 mm before the identity test let a
    # plane extrapolated there tell less (`rim_and_planes`' tilt)
    pair = stray_colour_pair(5000, seed, partial=0.3)
    res = register_pair(pair.source, pair.target, pair.source_rgb, pair.target_rgb)
    err = np.linalg.norm(res.registered - pair.truth, axis=1)
    still = np.linalg.norm(pair.source - pair.truth, axis=1)
    _, cell = np.unique(np.floor(pair.source / 5e-3).astype(int), axis=0, return_inverse=True)
    cell = cell.ravel()
    worst = max(np.median(err[cell == c]) - np.median(still[cell == c])
                for c in np.flatnonzero(np.bincount(cell) >= 10))
    assert worst <= 0.2e-3
    static = still < 0.05e-3  # the static side stays within the noise
    assert static.sum() > 500 and np.median(err[static]) < 0.1e-3
    assert np.median(err) < min(0.4e-3, 0.3 * np.median(still))


def test_static_tissue_dragged_a_little_is_explained_by_not_moving_and_moving_tissue_is_not():
    # registered = the truth, except static tissue (true motion < 0.05 mm) slid 0.3 mm along
    # the surface: half of what `stay_where_better` needs to see
    pair = stray_colour_pair(5000, 103)
    d = _decide(pair)
    move = np.linalg.norm(pair.truth - pair.source, axis=1)
    static, moving = move < 0.05e-3, move > 1e-3
    centred = pair.source - pair.source.mean(0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    along = np.cross(normal, [1.0, 0.0, 0.0])
    registered = pair.truth + np.where(static[:, None], 0.3e-3 * along / np.linalg.norm(along),
                                       0.0)
    everywhere = np.ones(len(pair.source), bool)
    target = ColouredPoints(pair.target[d.agree], pair.target_rgb[d.agree])
    still = explained_by_identity(pair.source, registered, everywhere, pair.source_rgb, target,
                                  d)
    assert np.mean(still[static]) > 0.8
    assert np.mean(still[moving]) < 0.02
    # not supported: never tested
    assert not explained_by_identity(pair.source, registered, ~everywhere, pair.source_rgb,
                                     target, d).any()


def test_a_planes_tilt_is_its_normals_error_and_grows_where_its_points_span_a_strip():
    # a flat sheet and a 1.5 mm strip, 0.2 mm noise across them: the tilt (the normal's
    # standard error) is what the normals are off by, and on the strip larger
    rng = np.random.default_rng(5)

    def planes(width_m: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        uv = rng.uniform(0.0, 1.0, (n, 2)) * [0.04, width_m]
        target = ColouredPoints.analysed(np.c_[uv, rng.normal(0.0, 0.2e-3, n)],
                                         np.zeros((n, 3)))
        assert target.tilt is not None and target.normal is not None
        inside = (uv[:, 0] > 0.004) & (uv[:, 0] < 0.036)
        off = np.arccos(np.minimum(np.abs(target.normal[inside, 2]), 1.0))
        return np.median(target.tilt[inside]), np.median(off)

    sheet, sheet_off = planes(0.04, 4000)
    strip, strip_off = planes(0.0015, 150)
    assert 0.7 < sheet / sheet_off < 1.3 and 0.7 < strip / strip_off < 1.5
    assert strip > 1.3 * sheet


def test_only_points_matched_onto_the_rim_of_a_cut_are_taken_for_unmeasured():
    # a sheet whose target lost its side u > 25 mm; the source's own border is shared
    xyz, _ = _curved_sheet(4000, 8)
    uv_u = np.random.default_rng(8).uniform(0.0, 40.0, (4000, 2))[:, 0]  # _curved_sheet's u
    keep = uv_u < 25.0
    target = ColouredPoints.analysed(xyz[keep], np.zeros((int(keep.sum()), 3)))
    spacing = 40e-3 / np.sqrt(4000)
    at_cut = matched_onto_cut(xyz, xyz, keep, target, spacing)
    assert at_cut.sum() > 20
    assert np.mean(np.abs(uv_u[at_cut] - 25.0) < 3 * spacing * 1e3) > 0.7  # along the cut
    assert not at_cut[uv_u < 20.0].any()  # not on the border both clouds share
    assert not matched_onto_cut(xyz, xyz, np.ones(4000, bool), target, spacing).any()


def test_points_past_the_rim_of_a_cut_but_within_the_support_gate_are_taken_for_unmeasured():
    # issue 28, stray_colour_partial 5k seed 8: points whose true position lies 1-3 mm past a
    # cut target's rim slid onto it, stayed within `register`'s support gate (3 spacings)
    # 0.8-1.5 mm past the rim and kept a motion nothing measured (+0.11 mm cell). Here: a
    # sheet whose target lost its side u > 25 mm; source points up to 3 spacings past the cut
    # count as supported, those farther not
    xyz, _ = _curved_sheet(4000, 8)
    uv_u = np.random.default_rng(8).uniform(0.0, 40.0, (4000, 2))[:, 0]  # _curved_sheet's u
    spacing = 40e-3 / np.sqrt(4000)
    keep = uv_u < 25.0
    target = ColouredPoints.analysed(xyz[keep], np.zeros((int(keep.sum()), 3)))
    supported = uv_u < 25.0 + 3.0 * spacing * 1e3
    at_cut = matched_onto_cut(xyz, xyz, supported, target, spacing)
    past = ~keep & supported & (uv_u > 25.0 + 2.2 * spacing * 1e3)  # beyond 2 spacings
    assert past.sum() > 20 and np.mean(at_cut[past]) > 0.8
    assert not at_cut[uv_u < 20.0].any()  # not inside, nor on the border both clouds share


def test_unsupported_points_can_fade_to_not_moving():
    rng = np.random.default_rng(4)
    src = np.c_[rng.uniform(0, 0.03, (3000, 2)), np.zeros(3000)]
    supported = src[:, 0] < 0.015
    reg = src + np.array([1e-3, 0.0, 0.0])  # the solver moved everything
    out = follow_supported(src, reg, supported, reach=(0.0, 0.1), beyond=src)  # 4.2 mm
    far = src[:, 0] > 0.015 + 4.3e-3
    np.testing.assert_allclose(out[far], src[far], atol=1e-12)
    np.testing.assert_array_equal(out[supported], reg[supported])


def test_points_next_to_a_cut_away_part_are_coupled_to_it_and_a_missed_border_sample_is_not():
    # a 40 mm sheet of 5000 points, 250 nodes (about 2.5 mm apart): the part u > 28 mm has no
    # target surface; the points coupled to it lie next to it (the blend of 4 nodes, then one
    # ring of smoothness neighbours: all within 2 node spacings of the cut, some out to 4)
    xyz, _ = _curved_sheet(5000, 11)
    u = np.random.default_rng(11).uniform(0.0, 40.0, (5000, 2))[:, 0]  # _curved_sheet's u
    supported = u < 28.0
    coupled = coupled_to_unsupported(xyz, supported, 250, 4, 8)
    assert not coupled[~supported].any()
    assert coupled[(u > 26.0) & supported].mean() > 0.9  # right at the cut
    assert coupled[(u > 23.0) & supported].mean() > 0.9
    assert not coupled[u < 15.0].any()  # 13 mm (5 node spacings) inside: untouched
    # a full sheet with a few scattered points the resampling left without target surface
    scattered = np.ones(5000, bool)
    scattered[np.random.default_rng(12).choice(5000, 12, replace=False)] = False
    assert not coupled_to_unsupported(xyz, scattered, 250, 4, 8).any()


def test_across_only_keeps_the_motion_along_the_targets_normal_and_drops_the_slide():
    xyz, _ = _curved_sheet(3000, 13)
    target = ColouredPoints.analysed(xyz, np.zeros((3000, 3)))
    normal = target.normal
    assert normal is not None
    # each point moved 0.3 mm along its local normal and slid 1 mm along the surface
    slide = np.cross(normal, [0.0, 0.0, 1.0])
    slide /= np.linalg.norm(slide, axis=1)[:, None]
    registered = xyz + 0.3e-3 * normal + 1e-3 * slide
    d = np.linalg.norm(across_only(xyz, registered, target) - (xyz + 0.3e-3 * normal), axis=1)
    assert np.median(d) < 0.05e-3  # the 1 mm slide gone, the 0.3 mm across kept

