"""`colour_flow` (issue 28): a slide along the surface is taken back from the target's colour
pooled over deformation nodes, and points at their true positions stay there.

Truth from the simulator (sim/pairs_stray.py: where every source point truly went); seeds
900+ (neither tuned nor checked on while the step was designed).
"""

from __future__ import annotations

import numpy as np
import pytest

from surgrecon_cli.core.registration import graph
from surgrecon_cli.core.registration.colour import decide_colour
from surgrecon_cli.core.registration.colour_flow import colour_flow
from surgrecon_cli.core.registration.overlap import ColouredPoints, MotionTest
from surgrecon_cli.sim.pairs_stray import stray_colour_pair


def _along_mm(pos: np.ndarray, truth: np.ndarray, normal: np.ndarray) -> np.ndarray:
    d = pos - truth
    return np.linalg.norm(d - (d * normal).sum(axis=1)[:, None] * normal, axis=1) * 1e3


@pytest.fixture(scope="module")
def flow_case():
    pair = stray_colour_pair(5000, 900)
    decision = decide_colour(pair.target, pair.target_rgb, 5e-3)
    agree = decision.agree
    target = ColouredPoints.analysed(pair.target[agree], pair.target_rgb[agree],
                                     decision.neighbours)
    nodes = graph.node_blend(pair.source, 250, 4, 8)
    # the truth's normals, one side (the tissue is a sheet), from its own neighbourhoods
    _, nn = ColouredPoints(pair.truth, pair.source_rgb).tree.query(pair.truth, k=16)
    nb = pair.truth[nn] - pair.truth[nn].mean(axis=1, keepdims=True)
    normal = np.linalg.eigh(np.einsum("pki,pkj->pij", nb, nb))[1][:, :, 0]
    centred = pair.truth - pair.truth.mean(axis=0)
    sheet = np.linalg.eigh(centred.T @ centred)[1][:, 0]
    normal *= np.sign(normal @ sheet)[:, None]
    return pair, decision, target, nodes, normal


@pytest.mark.parametrize("slide_mm", [0.3, 0.8])
def test_a_slide_along_the_surface_is_taken_back(flow_case, slide_mm):
    # every source point slid by slide_mm along the surface, the same way (a smooth field):
    # the nearest match in position + colour follows 0.6 of such a slide at 5k points; the
    # pooled colour shifts take it back to within the noise of a node's estimate
    pair, decision, target, nodes, normal = flow_case
    way = np.cross(normal, [1.0, 0.3, 0.1])
    way /= np.linalg.norm(way, axis=1)[:, None]
    slid = pair.truth + slide_mm * 1e-3 * way
    everyone = np.ones(len(slid), bool)
    out = colour_flow(MotionTest(pair.source, slid, everyone, pair.source_rgb), target,
                      decision, nodes)
    along = _along_mm(out, pair.truth, normal)
    assert np.median(along) < 0.4 * slide_mm
    left = ((out - pair.truth) * way).sum(axis=1).mean() * 1e3  # what remains of the slide
    assert abs(left) < 0.25 * slide_mm


def test_points_at_their_true_positions_stay_and_points_not_supported_do_not_move(flow_case):
    pair, decision, target, nodes, normal = flow_case
    supported = pair.source[:, 0] < np.median(pair.source[:, 0])
    out = colour_flow(MotionTest(pair.source, pair.truth, supported, pair.source_rgb),
                      target, decision, nodes)
    assert np.array_equal(out[~supported], pair.truth[~supported])
    along = _along_mm(out[supported], pair.truth[supported], normal[supported])
    # a node moves only where its gain beats noise: most stay put, the rest within ~0.2 mm
    assert np.median(along) < 0.05 and np.percentile(along, 90) < 0.25

