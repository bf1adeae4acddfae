"""The frame step as one object (`core/frame_step.FrameRegistrar`): a register worker
builds it once per run and registers every frame with it; each frame lands on the
simulator's truth (bounds of SPEC section 6, as tests/test_register_stage.py)."""

from __future__ import annotations

import numpy as np

from surgrecon_cli.config import Config
from surgrecon_cli.core.evaluate.scoring import map_to_surface
from surgrecon_cli.io.run.artefacts import read_registration, read_template
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.stages import register as stage


def test_one_registrar_per_run_registers_every_frame_to_the_truth(copy_run, pipeline_log):
    layout = RunLayout(copy_run)
    template = read_template(layout).points
    with np.load(pipeline_log.with_name(pipeline_log.stem + ".gt.npz")) as gt:
        vertices, faces = gt["vertices"], gt["faces"]
    mapping = map_to_surface(template, vertices[0], faces)
    stage._registrar.cache_clear()
    for k in range(1, len(vertices)):
        out = stage.register_frame(copy_run, k, Config())
        assert "failed" not in out
        reg = read_registration(layout, k, len(template))
        error_mm = np.linalg.norm(reg.registered - mapping.follow(vertices[k], faces),
                                  axis=1) * 1e3
        assert np.median(error_mm) <= 0.35 and np.percentile(error_mm, 95) <= 1.0
    info = stage._registrar.cache_info()
    assert info.misses == 1 and info.hits == len(vertices) - 2
