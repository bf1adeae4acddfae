"""`surgrecon run`: every stage in order on one run folder, resumable; `run_many`: many
logs, one run folder each, over one executor.

ingest -> build-template -> register -> classify -> [evaluate] -> report

Rerunning on the same folder skips what is finished and still valid, and resumes the
register stage frame by frame. Validity is checked against run.json:
- the input log's SHA-256: another log restarts everything (a warning says so);
- the config sections each stage depends on (`SECTIONS`, cumulative along the pipeline):
  the recorded value is the one the stage wrote into its own run.json entry (`config`),
  else run.json's `config`, which this module keeps equal to the config every finished
  stage was made with. A changed section reruns the first stage that depends on it and
  everything after it; their old outputs are deleted first, so results never mix;
- evaluate also reruns when the ground-truth file changed; report reruns whenever
  anything before it ran.
"""

from __future__ import annotations

import json
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
from .errors import InputError, SurgReconError
from .executors import Executor, make_executor
from .io.atomic import remove_leftovers, write_text
from .io.ground_truth import gt_path_beside
from .io.run_folder import RunFolder, file_sha256

logger = logging.getLogger(__name__)

STAGES = ("ingest", "build-template", "register", "classify", "evaluate", "report")
_OWN_SECTIONS = {
    "ingest": ("topics", "ingest"),
    "build-template": ("tool", "template"),
    "register": ("target", "registration"),
    "classify": ("classify",),
    "evaluate": ("labels",),
    "report": (),
}
SECTIONS: dict[str, tuple[str, ...]] = {}
_acc: tuple[str, ...] = ()
for _stage in STAGES:
    _acc = _acc + _OWN_SECTIONS[_stage]
    SECTIONS[_stage] = _acc
# What each stage writes (relative to RUN); deleted before the stage reruns from scratch.
OUTPUTS = {
    "ingest": ("ingest",),
    "build-template": ("template.ply", "template", "clouds"),
    "register": ("registration", "clouds/*.ply"),  # except clouds/000000.ply (the template's)
    "classify": ("classify",),
    "evaluate": ("metrics/evaluation.json", "metrics/evaluation_errors.npz"),
    "report": ("metrics/frames.csv", "metrics/summary.json", "report.html"),
}
# A finished stage whose key output is missing is not finished (e.g. a file deleted by hand).
KEY_OUTPUT = {"ingest": "ingest/frames.npz", "build-template": "template.ply",
              "register": "registration", "classify": "classify/labels.npz",
              "evaluate": "metrics/evaluation.json", "report": "report.html"}
# Share of the overall progress bar per stage (normalised over the stages that run).
WEIGHTS = {"ingest": 10, "build-template": 20, "register": 50, "classify": 5, "evaluate": 5,
           "report": 10}

Progress = Callable[[str, float], None]
# Modules of the task functions, imported by parallel workers as they start.
TASK_MODULES = ("surgrecon_cli.core.template", "surgrecon_cli.stages.register",
                "surgrecon_cli.stages.classify", "surgrecon_cli.io.plots")


def open_executor(config: Config) -> closing[Executor]:
    """The config's `[run]` executor, its workers importing TASK_MODULES as they start;
    use as `with open_executor(config) as executor:` (closed at the end)."""
    return closing(make_executor(config.run, TASK_MODULES))


@dataclass
class PipelineResult:
    """What `run_pipeline` did: per stage "ran", "resumed" or "skipped" (or "-" when not
    applicable, e.g. evaluate without ground truth), seconds per stage, and outputs."""

    run_dir: Path
    actions: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    report: Path | None = None
    evaluation: dict[str, Any] | None = None
    ground_truth: Path | None = None


def _plain(obj: Any) -> Any:
    return json.loads(json.dumps(obj))


def find_ground_truth(log: Path, given: Path | None) -> Path | None:
    """`given`, else NAME.gt.npz beside the log if it exists, else None."""
    if given is not None:
        if not Path(given).is_file():
            raise InputError(f"{given}: no such ground-truth file")
        return Path(given)
    beside = gt_path_beside(log)
    return beside if beside.is_file() else None


class _Planner:
    """Decides which stages are still valid in a run folder for this log and config."""

    def __init__(self, run: RunFolder, config: Config, gt_sha: str | None):
        self.run = run
        self.current = _plain(to_dict(config))
        self.gt_sha = gt_sha

    def recorded(self, stage: str, section: str) -> Any:
        data = self.run.read()
        own = data.get("stages", {}).get(stage, {}).get("config", {})
        if isinstance(own, dict) and section in own:
            return own[section]
        return data.get("config", {}).get(section)

    def changed_sections(self, stage: str) -> list[str]:
        return [s for s in SECTIONS[stage] if self.recorded(stage, s) != self.current[s]]

    def first_stale(self, wanted: tuple[str, ...]) -> tuple[str | None, str]:
        """The first stage (in pipeline order) that must run from scratch, and why."""
        for stage in wanted:
            entry = self.run.stage(stage)
            changed = self.changed_sections(stage) if entry else []
            if changed:
                return stage, f"config changed ({', '.join(changed)})"
            if stage == "register" and not self.run.is_done(stage):
                continue  # resumable frame by frame (it checks its own config fingerprint)
            if not self.run.is_done(stage):
                return stage, "not done"
            if not (self.run.path / KEY_OUTPUT[stage]).exists():
                return stage, f"{KEY_OUTPUT[stage]} is missing"
            if stage == "evaluate":
                recorded = entry.get("ground_truth", {}).get("sha256")
                if recorded != self.gt_sha:
                    return stage, "ground truth changed"
        return None, ""


def _delete_outputs(run_dir: Path, stages: tuple[str, ...]) -> None:
    for stage in stages:
        for pattern in OUTPUTS[stage]:
            for path in run_dir.glob(pattern):
                if stage == "register" and path.name == "000000.ply":
                    continue
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
    data["config"] = _plain(to_dict(config))
    run.write(data)
    write_text(run.path / "config.toml", to_toml(config))


def run_pipeline(log: Path, run_dir: Path, config: Config, ground_truth: Path | None = None,
                 allow_truncated: bool = False, on_progress: Progress | None = None,
                 on_stage: Callable[[str, str], None] | None = None,
                 executor: Executor | None = None) -> PipelineResult:
    """Run (or resume) every stage on `run_dir` for `log`.

    ground_truth: GT file to evaluate against (default: NAME.gt.npz beside the log if any).
    on_progress(stage, fraction_of_whole_run) and on_stage(stage, action) report progress.
    executor: where the stages' tasks run (default: the config's `[run]` executor, started
    and closed by this call).
    """
    if executor is None:
        with open_executor(config) as own:
            return run_pipeline(log, run_dir, config, ground_truth, allow_truncated,
                                on_progress, on_stage, own)
    from .stages.classify import classify_task, run_classify
    from .stages.evaluate import run_evaluate
    from .stages.ingest import ingest
    from .stages.register import run_register
    from .stages.report import run_report
    from .stages.template import run_build_template

    log, run_dir = Path(log), Path(run_dir)
    if not log.is_file():
        raise InputError(f"{log}: no such file")
    gt = find_ground_truth(log, ground_truth)
    wanted = tuple(s for s in STAGES if s != "evaluate" or gt is not None)
    result = PipelineResult(run_dir=run_dir, ground_truth=gt)
    run = RunFolder(run_dir)
    force_ingest = False
    if run.exists():
        if remove_leftovers(run_dir):
            logger.info("%s: removed the temporary files of an interrupted run", run_dir)
        recorded = run.input_hash
        if recorded and recorded != file_sha256(log):
            logger.warning("%s was made from another log than %s (SHA-256 differs): starting "
                           "over", run_dir, log)
            _delete_outputs(run_dir, STAGES[1:])
            force_ingest = True
    planner = _Planner(run, config, file_sha256(gt) if gt else None)
    stale = None
    if run.exists() and not force_ingest:
        stale, why = planner.first_stale(wanted)
        if stale == "ingest" and run.is_done("ingest"):
            force_ingest = True
            _delete_outputs(run_dir, STAGES[1:])
        elif stale is not None:
            index = STAGES.index(stale)
            if why != "not done" or stale != "report":
                logger.info("%s: %s", stale, why)
            _invalidate(run, config, STAGES[index:])
    total_weight = sum(WEIGHTS[s] for s in wanted)
    base = 0.0

    def reporter(stage: str) -> Callable[[float], None]:
        start = base

        def report(fraction: float) -> None:
            if on_progress is not None:
                on_progress(stage, (start + WEIGHTS[stage] * min(max(fraction, 0.0), 1.0))
                            / total_weight)
        return report

    ran_any = False
    classified: dict[int, Any] = {}  # classify_one_frame results of frames registered now
    for stage in wanted:
        progress = reporter(stage)
        action = _action(run, stage, ran_any or force_ingest)
        if on_stage is not None:
            on_stage(stage, action)
        result.actions[stage] = action
        start = time.perf_counter()
        if action != "skipped":
            ran_any = True
            if stage == "ingest":
                size = max(log.stat().st_size, 1)
                read = [0]

                def on_bytes(n: int, size: int = size, read: list[int] = read,
                             progress: Callable[[float], None] = progress) -> None:
                    read[0] += n
                    progress(read[0] / size)

                ingest(log, run_dir, config, allow_truncated=allow_truncated,
                       force=force_ingest, on_bytes=on_bytes)
                force_ingest = False
            elif stage == "build-template":
                from .core.template import STEPS

                def on_step(name: str, progress: Callable[[float], None] = progress) -> None:
                    progress((STEPS.index(name) + 1) / len(STEPS))

                run_build_template(run_dir, config, on_step=on_step, executor=executor)
            elif stage == "register":
                frames = [0]

                def on_frame(_frame: int, n: int, frames: list[int] = frames,
                             progress: Callable[[float], None] = progress) -> None:
                    frames[0] += 1
                    progress(frames[0] / max(n - 1, 1))

                # Frames are classified as they are registered, on workers the chain of
                # base frames leaves idle; classify then has only the rest to do.
                run_register(run_dir, config, on_frame=on_frame, executor=executor,
                             after_frame=partial(classify_task, run_dir, config),
                             on_after=classified.__setitem__)
            elif stage == "classify":
                run_classify(run_dir, config, on_step=lambda d, t, p=progress: p(d / t),
                             executor=executor, classified=classified)
                classified.clear()  # T x N labels and measures: not needed any more
            elif stage == "evaluate" and gt is not None:  # only wanted with ground truth
                result.evaluation = run_evaluate(run_dir, config, gt,
                                                 on_step=lambda d, t, p=progress: p(d / t))
            elif stage == "report":
                run_report(run_dir, config, on_step=lambda d, t, p=progress: p(d / t),
                           executor=executor)
            result.seconds[stage] = round(time.perf_counter() - start, 3)
            _record_seconds(run, stage, result.seconds[stage])
        progress(1.0)
        base += WEIGHTS[stage]
    if "evaluate" in wanted and result.evaluation is None:
        from .stages.evaluate import evaluation_path

        result.evaluation = json.loads(evaluation_path(run_dir).read_text(encoding="utf-8"))
    result.report = run_dir / "report.html"
    return result


def _action(run: RunFolder, stage: str, upstream_ran: bool) -> str:
    """"skipped" when done and nothing before it ran, "resumed" for a register stage with
    frames already done, else "ran"."""
    if stage == "register" and not run.is_done(stage) and run.stage(stage).get("frames_done"):
        return "resumed"
    if run.is_done(stage) and not upstream_ran:
        return "skipped"
    return "ran"


def _record_seconds(run: RunFolder, stage: str, seconds: float) -> None:
    data = run.read()
    data.setdefault("pipeline", {}).setdefault("seconds", {})[stage] = seconds
    run.write(data)


def run_folders_for(logs: list[Path], runs_root: Path) -> list[Path]:
    """One run folder per log under `runs_root`, named after the log's file name without
    `.mcap`; InputError when two logs would share a folder."""
    names = [Path(log).name.removesuffix(".mcap") for log in logs]
    folders = [Path(runs_root) / (n if n not in ("", ".", "..") else Path(log).name)
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
             ) -> list[PipelineResult | SurgReconError]:
    """`run_pipeline` for each log into RUNS/NAME/, every log's frames on one executor.

    Logs run concurrently (one driver thread each, as many as the executor has workers),
    so that the tasks of all logs keep the workers busy. A log that fails (e.g.
    corrupt) does not stop the others: its entry in the returned list is the error.
    on_progress(log, stage, fraction) reports each log's progress.
    """
    if executor is None:
        with open_executor(config) as own:
            return run_many(logs, runs_root, config, allow_truncated, own, on_progress)
    folders = run_folders_for(logs, runs_root)
    Path(runs_root).mkdir(parents=True, exist_ok=True)

    def one(log: Path, folder: Path) -> PipelineResult | SurgReconError:
        report = None if on_progress is None else partial(on_progress, log)
        try:
            return run_pipeline(log, folder, config, allow_truncated=allow_truncated,
                                on_progress=report, executor=executor)
        except SurgReconError as exc:
            return exc

    threads = 1 if executor.kind == "serial" else max(min(len(logs), executor.workers), 1)
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(pool.map(one, logs, folders))
