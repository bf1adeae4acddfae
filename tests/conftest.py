"""Shared fixtures. Several test modules add fixtures here: append, do not overwrite."""

from __future__ import annotations

from pathlib import Path

import pytest


# ---- pipeline: one small simulated log, run through every stage once per session --------
@pytest.fixture(scope="session")
def pipeline_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated log (6 cameras, 320x240, 6 frames) with NAME.gt.npz beside it."""
    from surgrecon_cli.sim.scene import SimConfig
    from surgrecon_cli.sim.simulate import simulate

    out = tmp_path_factory.mktemp("pipeline_log") / "sim.mcap"
    simulate(out, SimConfig(cameras=6, frames=6, width=320, height=240))
    return out


@pytest.fixture(scope="session")
def pipeline_run(pipeline_log: Path, tmp_path_factory: pytest.TempPathFactory):
    """`run_pipeline` on `pipeline_log` (evaluated against its ground truth): the finished
    run folder and the PipelineResult. Read-only: copy it (`copy_run`) before changing it."""
    from surgrecon_cli.config import Config
    from surgrecon_cli.pipeline import run_pipeline

    run_dir = tmp_path_factory.mktemp("pipeline_run") / "run"
    result = run_pipeline(pipeline_log, run_dir, Config())
    return run_dir, result


@pytest.fixture
def copy_run(pipeline_run, tmp_path: Path):
    """A private copy of the session's finished run folder."""
    import shutil

    run_dir = tmp_path / "run"
    shutil.copytree(pipeline_run[0], run_dir)
    return run_dir
