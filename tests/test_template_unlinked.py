"""build-template names the cameras that give no template point and the separately linked
groups (issue 23: d-lfd's pair 3, 6 of 15 matches, must not vanish silently)."""

from surgrecon_cli.stages.template import unlinked_report

NAMES = ["p1l", "p1r", "p2l", "p2r", "p3l", "p3r"]


def test_unlinked_cameras_and_separate_groups_are_named():
    stats = {"pair_counts": {"0-1": 20, "2-3": 20, "4-5": 6, "3-4": 1},
             "pair_minimums": {"0-1": 15, "2-3": 15, "4-5": 15, "3-4": 15},
             "disagreeing_groups": []}
    lines = unlinked_report([[0, 1], [2, 3], [4], [5]], stats, NAMES)
    assert len(lines) == 3
    assert lines[0].startswith("camera p3l ") and "p3l-p3r has 6 matches of the 15" in lines[0]
    assert lines[1].startswith("camera p3r ")
    assert "p1l p1r; p2l p2r" in lines[2]


def test_one_linked_group_reports_nothing():
    stats = {"pair_counts": {"0-1": 30}, "pair_minimums": {"0-1": 15}, "disagreeing_groups": []}
    assert unlinked_report([[0, 1]], stats, NAMES[:2]) == []
