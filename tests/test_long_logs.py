"""Long logs (issue 15): the register progress record survives a kill mid-write, the
hysteresis' streaming passes give the definition's labels, classify's label writing holds
one frame at a time (its peak allocation does not grow with the frames), and the report
keeps per-point values of a bounded number of frames."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np

from surgrecon_cli.core.classify.hysteresis import apply_hysteresis
from surgrecon_cli.core.classify.labels import DEFORMING, SHIFTING, STATIC, UNKNOWN
from surgrecon_cli.io.run.artefacts import FrameRegistration
from surgrecon_cli.io.run.folder import FrameProgress
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.io.run.rows import npz_rows
from surgrecon_cli.report.frames import SAMPLED_FRAMES, FrameAccumulator
from surgrecon_cli.sim.random_frames import write_random_classified
from surgrecon_cli.stages.classify import write_labels_streaming


def test_progress_record_ignores_a_line_cut_by_a_kill(tmp_path: Path):
    progress = FrameProgress(tmp_path / "progress.jsonl")
    progress.restart({1: ""})
    progress.append(2, "no image")
    progress.append(3)
    with open(progress.path, "a", encoding="utf-8") as f:
        f.write('{"frame": 4')  # killed in the middle of the line
    assert progress.read() == {1: "", 2: "no image", 3: ""}
    progress.restart(progress.read())  # what a resumed stage does before appending
    progress.append(4)
    assert progress.read() == {1: "", 2: "no image", 3: "", 4: ""}


def _by_definition(labels: np.ndarray, frames: int) -> np.ndarray:
    """A change at frame k is kept iff the point's next `frames` known labels from k (or all
    of them to the end) equal it; unknown entries stay unknown. Loops, per point."""
    out = labels.copy()
    for i in range(labels.shape[1]):
        current = labels[0, i]
        for k in range(1, labels.shape[0]):
            raw = labels[k, i]
            if raw != UNKNOWN and raw != current:
                ahead = [v for v in labels[k:, i] if v != UNKNOWN][:frames]
                if all(v == raw for v in ahead):
                    current = raw
            out[k, i] = UNKNOWN if raw == UNKNOWN else current
    return out


def test_hysteresis_matches_its_definition():
    rng = np.random.default_rng(11)
    for _ in range(60):
        shape = (int(rng.integers(2, 25)), int(rng.integers(1, 12)))
        p = rng.dirichlet(np.ones(4))
        labels = rng.choice([STATIC, SHIFTING, DEFORMING, UNKNOWN], size=shape,
                            p=p).astype(np.uint8)
        frames = int(rng.integers(2, 6))
        np.testing.assert_array_equal(apply_hysteresis(labels, frames),
                                      _by_definition(labels, frames))


def _peak_bytes(layout: RunLayout, n_frames: int, n: int) -> int:
    tracemalloc.start()
    try:
        write_labels_streaming(layout, n_frames, n, hysteresis_frames=3)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_label_writing_memory_is_flat_in_the_frames(tmp_path: Path):
    n, rng = 1000, np.random.default_rng(3)
    peaks = {}
    for n_frames in (80, 300):  # both past the 256 KiB blocks the .npz is copied in
        layout = RunLayout(tmp_path / str(n_frames))
        write_random_classified(layout, n_frames, n, rng)
        peaks[n_frames] = _peak_bytes(layout, n_frames, n)
        with np.load(layout.labels) as z:  # the streamed file is whole and as the passes say
            raw = z["raw_labels"]
            assert z["labels"].shape == (n_frames, n)
            np.testing.assert_array_equal(z["labels"], apply_hysteresis(raw, 3))
        with (npz_rows(layout.labels, "displacement_mm") as rows,
              np.load(layout.classified(n_frames - 1)) as z):
            np.testing.assert_array_equal(rows.read(n_frames - 1), z["displacement_mm"])
    # (T, N) arrays would add 220 frames x 1000 points x 11 bytes = 2.4 MB; one frame's
    # rows are ~20 kB.
    assert peaks[300] < peaks[80] + 100_000, peaks


def _registration(template: np.ndarray, rng: np.random.Generator) -> FrameRegistration:
    n = len(template)
    f32 = np.float32
    return FrameRegistration(
        transforms=np.tile(np.eye(3, 4, dtype=f32), (n, 1, 1)),
        registered=(template + 1e-3 * rng.standard_normal((n, 3))).astype(f32),
        target=template.astype(f32), status=np.zeros(n, np.uint8), views=np.full(n, 2, np.uint8),
        residual=np.full(n, 1e-4, f32), sigma=np.full(n, 1e-4, f32),
        target_sigma=np.full(n, 1e-4, f32), target_covariance=np.zeros((n, 3, 3), f32),
        target_pose_covariance=np.zeros((n, 3, 3), f32), support_mm=np.ones(n, f32),
        pixels=np.zeros((n, 2, 2), f32), tracking_px=0.1, base=0, converged=True, failed=False,
        error="", seconds_target=0.1, seconds_register=0.1, new_points=0, contact_points=0)


def test_report_holds_per_point_values_of_sampled_frames_only():
    rng = np.random.default_rng(5)
    template = rng.random((300, 3))
    reg = _registration(template, rng)
    labels = np.full(len(template), STATIC, np.uint8)
    held = {}
    for n_frames in (SAMPLED_FRAMES + 1, 3 * SAMPLED_FRAMES):
        acc = FrameAccumulator(template, n_frames, classified=True)
        for k in range(n_frames):
            acc.add(k, reg if k else None, labels)
        figures = acc.result()
        assert len(figures.residual_sampled) == len(figures.sampled) == SAMPLED_FRAMES
        assert figures.sampled[0] == 1 and figures.sampled[-1] == n_frames - 1
        # every point is displaced by ~1.6 mm (1e-3 m noise per axis): per-frame stats agree
        assert 1.0 < figures.displacement_mm[n_frames - 1, 0] < 2.2
        assert figures.class_counts is not None
        assert figures.class_counts[n_frames - 1, 0] == len(template)
        held[n_frames] = sum(v.nbytes for v in vars(figures).values()
                             if isinstance(v, np.ndarray))
        held[n_frames] += sum(a.nbytes for a in figures.residual_sampled)
        held[n_frames] += sum(a.nbytes for a in figures.displacement_sampled)
    # per frame only counts and statistics: (S + 3 + 3 + 4 + 2 + 1) numbers, ~150 bytes;
    # the per-point arrays (300 points x 16 bytes a frame before) stay those of 200 frames
    grown = held[3 * SAMPLED_FRAMES] - held[SAMPLED_FRAMES + 1]
    assert grown / (2 * SAMPLED_FRAMES - 1) < 200
