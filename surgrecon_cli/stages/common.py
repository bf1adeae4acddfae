"""Bookkeeping shared by the pipeline stages: run.json status around a stage's work."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..config import Config
from ..errors import SurgReconError
from ..io.run_folder import RunFolder


@contextlib.contextmanager
def stage_run(
    run_dir: Path,
    name: str,
    config: Config,
    needs: tuple[str, ...] = ("ingest",),
    config_sections: tuple[str, ...] = (),
    keep: tuple[str, ...] = (),
) -> Iterator[dict[str, Any]]:
    """Mark stage `name` running; on success mark it done with the info the body put in the
    yielded dict (plus its wall time); on a SurgReconError mark it failed and re-raise.

    Earlier stages in `needs` must be done; `config_sections` must match the run's config
    (they shaped earlier outputs this stage builds on). `keep`: keys of the stage's previous
    entry carried into the "running" one (a resumable stage's progress, so that a run killed
    before it records new progress does not lose the old).
    """
    run = RunFolder(run_dir)
    for stage in needs:
        run.require_done(stage)
    if config_sections:
        run.check_config(config, config_sections)
    previous = run.stage(name)
    run.mark_stage(name, "running", **{k: previous[k] for k in keep if k in previous})
    info: dict[str, Any] = {}
    start = time.perf_counter()
    try:
        yield info
    except SurgReconError as exc:
        run.mark_stage(name, "failed", error=str(exc))
        raise
    except BaseException:
        run.mark_stage(name, "failed", error="interrupted or internal error")
        raise
    run.mark_stage(name, "done", seconds=round(time.perf_counter() - start, 3), **info)
