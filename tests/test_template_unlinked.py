"""build-template names the cameras that give no template point and the separately linked
groups (issue 23: d-lfd's pair 3, 6 of 15 matches, must not vanish silently)."""

import numpy as np

from surgrecon_cli.core.template.gate import link_warnings

NAMES = ["p1l", "p1r", "p2l", "p2r", "p3l", "p3r"]
MINIMUMS = np.full((6, 6), 15)


def test_unlinked_cameras_and_separate_groups_are_named():
    counts = {(0, 1): 20, (2, 3): 20, (4, 5): 6, (3, 4): 1}
    lines = link_warnings([[0, 1], [2, 3], [4], [5]], counts, MINIMUMS, NAMES, [])
    assert len(lines) == 3
    assert lines[0].startswith("camera p3l ") and "p3l-p3r has 6 matches of the 15" in lines[0]
    assert lines[1].startswith("camera p3r ")
    assert "p1l p1r; p2l p2r" in lines[2]


def test_disagreeing_groups_are_named_instead_of_unchecked():
    lines = link_warnings([[0, 1], [2, 3]], {(0, 1): 30, (2, 3): 30}, MINIMUMS, NAMES,
                          [([0, 1], [2, 3], 7.5)])
    assert len(lines) == 1
    assert lines[0].startswith("cameras p1l p1r and cameras p2l p2r are not linked")
    assert "7.5 px" in lines[0]


def test_one_linked_group_reports_nothing():
    assert link_warnings([[0, 1]], {(0, 1): 30}, MINIMUMS, NAMES[:2], []) == []
