"""The register stage's own bookkeeping: composed transforms when the template is re-based."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.config import load_config
from surgrecon_cli.io.artefacts import read_template
from surgrecon_cli.io.run_layout import RunLayout
from surgrecon_cli.pipeline import run_pipeline


def test_template_update_keeps_transforms_relative_to_frame_0(copy_run, pipeline_log):
    base = {}
    n_frames = len(list((copy_run / "registration").glob("*.npz"))) + 1
    for k in range(1, n_frames):
        with np.load(RunLayout(copy_run).registration(k)) as z:
            base[k] = z["registered"]
    config = load_config(overrides=["registration.template_update_every=3"])
    result = run_pipeline(pipeline_log, copy_run, config)
    assert result.actions["register"] == "ran"
    template = read_template(RunLayout(copy_run)).points
    homogeneous = np.column_stack([template, np.ones(len(template))])
    for k in range(1, n_frames):
        with np.load(RunLayout(copy_run).registration(k)) as z:
            transforms, registered = z["transforms"].astype(float), z["registered"]
        # Transforms map the frame-0 template to the frame, whatever the current base.
        applied = np.einsum("nij,nj->ni", transforms, homogeneous)
        assert np.median(np.linalg.norm(applied - registered, axis=1)) < 1e-5
        # Another base changes the chain, not the answer: within 0.3 mm of N_T = 2.
        assert np.median(np.linalg.norm(registered - base[k], axis=1)) < 0.3e-3
