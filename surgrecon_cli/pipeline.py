"""`surgrecon run`: every stage in order on one run folder, resumable; `run_many`: many
logs, one run folder each, over one executor.

ingest -> build-template -> register -> classify -> measure -> [evaluate] -> report

Rerunning on the same folder skips what is finished and still valid, and resumes the
register stage frame by frame. Validity is checked against run.json:
- the input log's SHA-256: another log restarts everything (a warning says so);
- the config keys each stage depends on (stages/registry.py, cumulative along the
  pipeline): the recorded value is the one the stage wrote into its own run.json entry
  (`config`), else run.json's `config`, which this module keeps equal to the config every
  finished stage was made with. A changed section reruns the first stage that depends on it and
  everything after it; their old outputs are deleted first, so results never mix;
- evaluate also reruns when the ground-truth file changed; report reruns whenever
  anything before it ran.
"""

from __future__ import annotations

import functools
import logging
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import closing
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from .config import Config, to_dict, to_toml
from .errors import InputError, RunFolderError, SurgReconError
from .executors import Executor, make_executor
from .io.logs.ground_truth import gt_path_beside
from .io.logs.log_input import resolve_log
from .io.run.artefacts import read_json
from .io.run.atomic import remove_leftovers, write_text
from .io.run.folder import RunFolder, file_sha256, plain
from .io.run.layout import RunLayout
from .io.run.lock import run_folder_lock
from .planning import Planner, seed_run
from .stages import registry
from .stages.registry import StageContext
from .stages.staleness import NOT_DONE

logger = logging.getLogger(__name__)

STAGES = registry.NAMES
Progress = Callable[[str, float], None]
# Modules of the task functions, imported by parallel workers as they start.
TASK_MODULES = ("surgrecon_cli.core.template.build", "surgrecon_cli.stages.register",
                "surgrecon_cli.stages.classify", "surgrecon_cli.report.plots")


def open_executor(config: Config) -> closing[Executor]:
    """The config's `[run]` executor, its workers importing TASK_MODULES as they start;
    use as `with open_executor(config) as executor:` (closed at the end)."""
    return closing(make_executor(config.run, TASK_MODULES))


@dataclass
class PipelineResult:
    """What `run_pipeline` did: per stage "ran", "resumed" or "skipped" (or "-" when not
    applicable, e.g. evaluate without ground truth; "reused": linked from the run it was
    seeded from), seconds per stage, and outputs."""

    run_dir: Path
    actions: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    report: Path | None = None
    evaluation: dict[str, Any] | None = None
    ground_truth: Path | None = None


def find_ground_truth(log: Path, given: Path | None) -> Path | None:
    """`given`, else NAME.gt.npz beside the log if it exists, else None."""
    if given is not None:
        if not Path(given).is_file():
            raise InputError(f"{given}: no such ground-truth file")
        return Path(given)
    beside = gt_path_beside(log)
    return beside if beside.is_file() else None


def _delete_outputs(run_dir: Path, stages: tuple[str, ...]) -> None:
    layout = RunLayout(run_dir)
    for stage in stages:
        for name in registry.spec(stage).outputs:
            path = getattr(layout, name)
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)


def _invalidate(run: RunFolder, config: Config, stages: tuple[str, ...]) -> None:
    """Drop `stages` (entries and outputs) and record `config` as the run's config."""
    _delete_outputs(run.path, stages)
    data = run.read()
    for stage in stages:
        data.get("stages", {}).pop(stage, None)
    data["config"] = plain(to_dict(config))
    run.write(data)
    write_text(RunLayout(run.path).config_toml, to_toml(config))


def run_pipeline(log: Path, run_dir: Path, config: Config, ground_truth: Path | None = None,
                 allow_truncated: bool = False, on_progress: Progress | None = None,
                 on_stage: Callable[[str, str], None] | None = None,
                 executor: Executor | None = None, force: bool = False,
                 seed_from: Path | None = None) -> PipelineResult:
    """Run (or resume) every stage on `run_dir` for `log`.

    ground_truth: GT file to evaluate against (default: NAME.gt.npz beside the log if any).
    on_progress(stage, fraction_of_whole_run) and on_stage(stage, action) report progress.
    executor: where the stages' tasks run (default: the config's `[run]` executor, started
    and closed by this call). force: replace a run folder made from another log (without
    it, RunFolderError: the folder's results are not thrown away silently). seed_from: a
    run folder of the same log whose still-valid stage outputs a new `run_dir` starts from
    (hard links; planning.seed_run): those stages are "reused", not rerun.
    """
    if executor is None:
        with open_executor(config) as own:
            return run_pipeline(log, run_dir, config, ground_truth, allow_truncated,
                                on_progress, on_stage, own, force, seed_from)
    with run_folder_lock(run_dir, "run", create=True):
        return _run_locked(Path(log), Path(run_dir), config, ground_truth, allow_truncated,
                           on_progress, on_stage, executor, force, seed_from)


def _run_locked(log: Path, run_dir: Path, config: Config, ground_truth: Path | None,
                allow_truncated: bool, on_progress: Progress | None,
                on_stage: Callable[[str, str], None] | None, executor: Executor,
                force: bool, seed_from: Path | None) -> PipelineResult:
    """`run_pipeline` holding the run folder's lock."""
    log_input = resolve_log(log)
    log_sha = functools.cache(log_input.sha256)  # read the log once, if at all
    gt = find_ground_truth(log, ground_truth)
    gt_sha = file_sha256(gt) if gt else None
    reused: tuple[str, ...] = ()
    if seed_from is not None and not RunFolder(run_dir).exists():
        reused = seed_run(Path(seed_from), run_dir, config, log_sha(), gt_sha)
        if reused:
            logger.info("%s: reusing %s of %s (config keys unchanged)", run_dir,
                        ", ".join(reused), seed_from)
    wanted = tuple(s.name for s in registry.STAGES if not s.needs_ground_truth or gt)
    result = PipelineResult(run_dir=run_dir, ground_truth=gt)
    ctx = StageContext(log=log, run_dir=run_dir, config=config, executor=executor,
                       ground_truth=gt, allow_truncated=allow_truncated)
    run = RunFolder(run_dir)
    if run.exists():
        if remove_leftovers(run_dir):
            logger.info("%s: removed the temporary files of an interrupted run", run_dir)
        recorded = run.input_hash
        if recorded and recorded != log_sha():
            made_from = run.read().get("input", {}).get("path", "another log")
            if not force:
                raise RunFolderError(
                    f"{run_dir} holds the run of {made_from}, not of {log} (SHA-256 "
                    "differs); pass --force to replace it, or choose another -o folder")
            logger.warning("%s: replacing the run of %s (--force)", run_dir, made_from)
            _delete_outputs(run_dir, STAGES[1:])
            ctx.force_ingest = True
    planner = Planner(run, config, gt_sha)
    if run.exists() and not ctx.force_ingest:
        stale, why = planner.first_stale(wanted)
        if stale == "ingest" and run.is_done("ingest"):
            ctx.force_ingest = True
            _delete_outputs(run_dir, STAGES[1:])
        elif stale is not None:
            if why != NOT_DONE or stale != "report":
                logger.info("%s: %s", stale, why)
            _invalidate(run, config, STAGES[STAGES.index(stale):])
    total_weight = sum(registry.spec(s).weight for s in wanted)
    base = 0.0
    ran_any = False
    for stage in wanted:
        weight = registry.spec(stage).weight

        def progress(fraction: float, stage: str = stage, start: float = base,
                     weight: int = weight) -> None:
            if on_progress is not None:
                on_progress(stage, (start + weight * min(max(fraction, 0.0), 1.0))
                            / total_weight)

        action = ("reused" if stage in reused and not ran_any
                  else _action(run, stage, ran_any or ctx.force_ingest))
        if on_stage is not None:
            on_stage(stage, action)
        result.actions[stage] = action
        start = time.perf_counter()
        if action not in ("skipped", "reused"):
            ran_any = True
            registry.step(stage)(ctx, progress)
            result.seconds[stage] = round(time.perf_counter() - start, 3)
            _record_seconds(run, stage, result.seconds[stage])
        progress(1.0)
        base += weight
    layout = RunLayout(run_dir)
    result.evaluation = ctx.evaluation
    if gt is not None and result.evaluation is None:
        result.evaluation = read_json(layout.evaluation_json, "evaluate")
    result.report = layout.report_html
    return result


def _action(run: RunFolder, stage: str, upstream_ran: bool) -> str:
    """"skipped" when done and nothing before it ran, "resumed" for a resumable stage with
    frames already done, else "ran"."""
    if (registry.spec(stage).resumable and not run.is_done(stage)
            and run.stage(stage).get("frames_done")):
        return "resumed"
    if run.is_done(stage) and not upstream_ran:
        return "skipped"
    return "ran"


def _record_seconds(run: RunFolder, stage: str, seconds: float) -> None:
    data = run.read()
    data.setdefault("pipeline", {}).setdefault("seconds", {})[stage] = seconds
    run.write(data)


def tagged(run_dir: Path, tag: str) -> Path:
    """`RUN-tag` beside `run_dir` for a sweep's labelled run (`tag` a plain name), or
    `run_dir` without a tag; InputError for a tag that is not a plain name."""
    if not tag:
        return Path(run_dir)
    if tag in (".", "..") or "/" in tag or "\\" in tag or not tag.isprintable():
        raise InputError(f"--tag {tag!r}: use a plain folder name (letters, digits, - _ .)")
    run_dir = Path(run_dir) if Path(run_dir).name else Path(run_dir).resolve()
    return run_dir.with_name(f"{run_dir.name}-{tag}")


def run_folders_for(logs: list[Path], runs_root: Path, tag: str = "") -> list[Path]:
    """One run folder per log under `runs_root`, named after the log's file name without
    `.mcap` (a bag folder: its name), with `-tag` appended if given (RUNS/NAME-tag);
    InputError when two logs would share a folder."""
    names = [Path(log).absolute().name.removesuffix(".mcap") for log in logs]
    folders = [tagged(Path(runs_root) / (n if n not in ("", ".", "..") else Path(log).name), tag)
               for n, log in zip(names, logs, strict=True)]
    seen: dict[Path, Path] = {}
    for log, folder in zip(logs, folders, strict=True):
        if folder in seen:
            raise InputError(f"{log} and {seen[folder]} would share the run folder {folder}; "
                             "rename one of them")
        seen[folder] = log
    return folders


def run_many(logs: list[Path], runs_root: Path, config: Config,
             allow_truncated: bool = False, executor: Executor | None = None,
             on_progress: Callable[[Path, str, float], None] | None = None,
             force: bool = False, tag: str = "") -> list[PipelineResult | SurgReconError]:
    """`run_pipeline` for each log into RUNS/NAME/, every log's frames on one executor.

    Logs run concurrently (one driver thread each, as many as the executor has workers),
    so that the tasks of all logs keep the workers busy. A log that fails (e.g.
    corrupt) does not stop the others: its entry in the returned list is the error.
    on_progress(log, stage, fraction) reports each log's progress. With a `tag`, each
    RUNS/NAME-tag starts from RUNS/NAME's still-valid outputs (`run_pipeline`'s seed_from).
    """
    if executor is None:
        with open_executor(config) as own:
            return run_many(logs, runs_root, config, allow_truncated, own, on_progress, force,
                            tag)
    folders = run_folders_for(logs, runs_root, tag)
    bases = dict(zip(folders, run_folders_for(logs, runs_root) if tag else [None] * len(logs),
                     strict=True))
    Path(runs_root).mkdir(parents=True, exist_ok=True)

    def one(log: Path, folder: Path) -> PipelineResult | SurgReconError:
        report = None if on_progress is None else partial(on_progress, log)
        try:
            return run_pipeline(log, folder, config, allow_truncated=allow_truncated,
                                on_progress=report, executor=executor, force=force,
                                seed_from=bases[folder])
        except SurgReconError as exc:
            return exc

    threads = 1 if executor.kind == "serial" else max(min(len(logs), executor.workers), 1)
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(pool.map(one, logs, folders))
