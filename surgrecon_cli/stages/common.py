"""Bookkeeping shared by the pipeline stages: run.json status around a stage's work."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config
from ..core.geometry.tool import camera_tool_poses
from ..errors import InputError, SurgReconError
from ..io.run.folder import RunFolder
from ..io.run.ingest_store import IngestedLog
from .registry import spec
from .staleness import check_upstream, recorded_config


def _mark_failed(run: RunFolder, name: str, keep: tuple[str, ...], error: str) -> None:
    """Mark a stage failed, keeping its progress (`keep` keys of its entry as it is now,
    e.g. the frames a resumable stage finished before Ctrl-C), so a rerun resumes."""
    current = run.stage(name)
    run.mark_stage(name, "failed", error=error, **{k: current[k] for k in keep if k in current})


@contextlib.contextmanager
def stage_run(run_dir: Path, name: str, config: Config,
              keep: tuple[str, ...] = ()) -> Iterator[dict[str, Any]]:
    """Mark stage `name` running; on success mark it done with the info the body put in the
    yielded dict, its wall time and the config its outputs depend on; on a SurgReconError
    mark it failed and re-raise.

    The stages the registry says it needs must be done; a stage that reads upstream config
    refuses a config that differs from the one the earlier stages were made with. `keep`:
    keys of the stage's previous entry carried into the "running" one (a resumable stage's
    progress, so that a run killed before it records new progress does not lose the old).
    """
    run = RunFolder(run_dir)
    for needed in spec(name).needs:
        run.require_done(needed)
    check_upstream(run, name, config)
    previous = run.stage(name)
    run.mark_stage(name, "running", **{k: previous[k] for k in keep if k in previous})
    info: dict[str, Any] = {}
    start = time.perf_counter()
    try:
        yield info
    except SurgReconError as exc:
        _mark_failed(run, name, keep, str(exc))
        raise
    except KeyboardInterrupt:
        _mark_failed(run, name, keep, "interrupted (Ctrl-C)")
        raise
    except BaseException:
        _mark_failed(run, name, keep, "interrupted or internal error")
        raise
    run.mark_stage(name, "done", seconds=round(time.perf_counter() - start, 3),
                   **{"config": recorded_config(config, name), **info})


def tool_poses(log: IngestedLog, config: Config, frame: int) -> np.ndarray:
    """Every tool's pose (K, 4, 4) in the world at `frame`, in `Config.tool_configs()` order
    (NaN where unknown). InputError when the log was ingested with another number of tools
    than the config names (a `[[tools]]` entry added or removed after ingest)."""
    tools = log.all_tool_poses(frame)
    wanted = len(config.tool_configs())
    if len(tools) != wanted:
        raise InputError(f"{log.root}: ingested with {len(tools)} tools, the config has "
                         f"{wanted}; ingest again with this config")
    return tools


def tools_per_camera(tools: np.ndarray, log: IngestedLog, config: Config
                     ) -> np.ndarray | None:
    """The tools' poses (K, 4, 4) in the world as each camera sees them, (C, K, 4, 4), when
    a tool has `camera_offsets` (`camera_tool_poses`); None when none has."""
    try:
        return camera_tool_poses(tools, config.tool_configs(), list(log.cameras))
    except ValueError as exc:
        raise InputError(str(exc)) from exc


def tools_as_seen(log: IngestedLog, config: Config, frame: int) -> np.ndarray:
    """The tools' poses at `frame`: (K, 4, 4) in the world, or (C, K, 4, 4) per camera when
    a tool has `camera_offsets` (`tools_per_camera`)."""
    tools = tool_poses(log, config, frame)
    per_camera = tools_per_camera(tools, log, config)
    return tools if per_camera is None else per_camera
