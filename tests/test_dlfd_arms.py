"""d-lfd (tests/data/dlfd, MIT): the frame conventions of benchmarks/dlfd_mcap.py put both dVRK
arms on their instruments, measured against jaw tips and shaft lines marked by eye in the
videos (tests/data/dlfd/marks.json), and the other readings of the data set do not; the
shipped frames build a template at defaults with no point within 1 mm of either arm."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DLFD = ROOT / "tests" / "data" / "dlfd"


@pytest.fixture(scope="module")
def bench():
    """The benchmark modules (dlfd_conventions imports dlfd_mcap as a sibling script)."""
    import sys

    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import dlfd_check
        import dlfd_conventions
        import dlfd_mcap
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return dlfd_conventions, dlfd_mcap, dlfd_check


@pytest.fixture(scope="module")
def data(bench):
    mcap = bench[1]
    marks = json.loads((DLFD / "marks.json").read_text(encoding="utf-8"))["marks"]
    return mcap.load_shipped(DLFD), marks


@pytest.fixture(scope="module")
def fits(bench, data):
    """Per pair and arm, the shaft fitted to the shipped frame 0 (dlfd_mcap.arm_corrections)."""
    return bench[1].arm_corrections(data[0], 0)


def test_shaft_through_the_rcm_follows_the_marked_shafts(bench, data):
    conv = bench[0]
    d, marks = data
    e = conv.errors(d, conv.CHOSEN, marks)  # tip px, lateral px, angle deg per mark
    assert np.median(e[:, 2]) < 6 and e[:, 2].max() < 15
    assert np.median(e[:, 1]) < 15 and e[:, 1].max() < 45  # 1 px ~ 0.45 mm
    for axis in ("+z", "-z", "+y", "-y"):  # the published jaw frame's own axes
        e_axis = conv.errors(d, replace(conv.CHOSEN, shaft=axis), marks)
        assert np.median(e_axis[:, 2]) > 40, axis


def test_other_readings_of_the_data_set_miss_the_instruments(bench, data):
    conv = bench[0]
    d, marks = data
    inverted = conv.errors(d, replace(conv.CHOSEN, hand_eye="base-to-camera"), marks)
    assert (inverted[:, 0] > 310).all()  # every arm behind or far outside the 310 px image
    readme = conv.errors(d, replace(conv.CHOSEN, labels="arm 1 = left"), marks)
    assert np.median(readme[:, 1]) > 80


def test_the_written_config_masks_the_marked_tips_and_shafts(bench, data, fits, tmp_path):
    """With the pairs' fitted camera_offsets every marked tip and shaft point (frames 93, 170
    and 248; the fit saw frame 0 only) is in its arm's mask; the same geometry placed by the
    published hand-eye results alone misses some."""
    conv, mcap, _ = bench
    d, marks = data
    config = tmp_path / "dlfd.toml"
    config.write_text(mcap.config_text(fits), encoding="utf-8")
    hit, total, share = conv.coverage(d, marks, config)
    assert total == 3 * len(marks) and hit == total
    assert max(share.values()) < 0.45  # the masks leave the images' tissue
    config.write_text(mcap.config_text({}), encoding="utf-8")
    assert conv.coverage(d, marks, config)[0] < total


def test_shipped_frames_build_a_template_clear_of_both_arms(bench, data, tmp_path):
    from surgrecon_cli.cli.main import main

    _, mcap, check = bench
    d, _ = data
    log, config = mcap.build(d, "dlfd", 3, 0, tmp_path)
    run = tmp_path / "run"
    assert main(["ingest", str(log), "-o", str(run), "--config", str(config), "-q"]) == 0
    assert main(["build-template", str(run), "--config", str(config), "-q"]) == 0
    gaps = check.clearance(run, config)
    assert sum(n > 0 for n, _ in gaps.values()) >= 4  # two pairs link at defaults
    assert min(min(g) for _, g in gaps.values()) >= 1.0  # mm, every camera, both arms


def test_shafts_fitted_to_pair_2s_images_follow_the_marks(bench, data, fits):
    """Pair 2's hand-eye error puts both arms 18-35 px off the marked shafts; the per-arm
    translation fitted to the frame-0 images (tool_fit) brings every pair-2 mark, including
    frame 170's (not fitted), within 12 px (1 px ~ 0.45 mm)."""
    conv = bench[0]
    d, marks = data
    pair2 = [m for m in marks if m["camera"].startswith("p2")]
    lateral = conv.corrected_lateral(d, pair2, fits)
    assert lateral[:, 0].min() > 15  # the hand-eye placement: every pair-2 mark far off
    assert lateral[:, 1].max() < 12
