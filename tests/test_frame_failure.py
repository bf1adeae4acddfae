"""A frame that cannot be registered is isolated and named; the run goes on."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np

from surgrecon_cli.config import Config
from surgrecon_cli.core.classify.labels import UNKNOWN, UNOBSERVED
from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.stages.classify import run_classify
from surgrecon_cli.stages.register import run_register


def _drop_frame_images(run_dir, frame: int) -> None:
    """Make every camera unusable at `frame`, as a log with lost images would."""
    path = run_dir / "ingest" / "frames.npz"
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["usable"][frame] = False
    np.savez(path, **arrays)
    run = json.loads((run_dir / "run.json").read_text())
    for stage in ("register", "classify", "evaluate", "report"):
        run["stages"].pop(stage, None)
    (run_dir / "run.json").write_text(json.dumps(run))
    shutil.rmtree(run_dir / "registration")


def test_failed_frame_is_isolated_and_named(copy_run, caplog):
    config = Config()
    _drop_frame_images(copy_run, 2)
    with caplog.at_level(logging.WARNING):
        run_register(copy_run, config)
    assert any("frame 2 failed" in r.getMessage() for r in caplog.records)
    entry = RunFolder(copy_run).stage("register")
    assert entry["status"] == "done"
    assert set(entry["frames_failed"]) == {"2"}
    message = entry["frames_failed"]["2"]
    assert "tracked" in message and "unobserved" in message and "{" not in message
    # and why: the cameras without an image in that frame (here every one of them)
    cameras = json.loads((copy_run / "run.json").read_text())["ingest"]["cameras"]
    assert f"cameras {', '.join(repr(c) for c in cameras)} had no usable image" in message
    with np.load(RunLayout(copy_run).registration(2)) as z:
        assert bool(z["failed"]) and np.isnan(z["registered"]).all()
        # nothing was seen: unobserved, not outliers
        assert (z["status"] == UNOBSERVED).all()
    # Frame 3's base (N_T = 2) is the failed frame 2: it is registered from frame 0 instead.
    with np.load(RunLayout(copy_run).registration(3)) as z:
        assert not bool(z["failed"]) and np.isfinite(z["registered"]).all()
    run_classify(copy_run, config)
    with np.load(RunLayout(copy_run).labels) as z:
        labels = z["labels"]
    assert (labels[2] == UNKNOWN).all()
    assert (labels[3] != UNKNOWN).mean() > 0.9
    # A resume with the same config does not retry it silently: it says so again.
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert run_register(copy_run, config) == []
    assert any("frame 2 failed in an earlier run" in r.getMessage() for r in caplog.records)
