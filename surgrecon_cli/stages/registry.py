"""The stage registry: what each stage reads, writes and depends on, in pipeline order.

ingest -> build-template -> register -> classify -> measure -> [evaluate] -> report

`pipeline.py`, resumption and staleness (staleness.py) read only from here. A stage's
outputs depend on its own config keys and, through its inputs, on those of every stage
before it (`config_keys`). A key is a config section ("target") or one key of it
("tool.base_to_world"). Stages never import each other; their pipeline steps are looked up
by name (`step`), so importing the registry imports no stage.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import Config
from ..executors import Executor


@dataclass(frozen=True)
class StageSpec:
    """One stage.

    depends_on: config sections or `section.key`s its own work reads; needs: stages whose
    outputs it reads (they must be done); outputs: RunLayout attributes it writes (deleted
    before it reruns from scratch); key_output: the RunLayout attribute whose absence means
    the stage is not finished; weight: its share of the overall progress bar; resumable:
    resumes frame by frame instead of rerunning; needs_ground_truth: runs only with ground
    truth; step: "module:function" of its pipeline step `f(context, progress)`;
    checks_upstream_config: the stage itself reads upstream config keys (e.g. register
    reads `tool`), so run alone it refuses a config that differs from the one the earlier
    stages were made with.
    """

    name: str
    depends_on: tuple[str, ...]
    needs: tuple[str, ...]
    outputs: tuple[str, ...]
    key_output: str
    weight: int
    step: str
    resumable: bool = False
    needs_ground_truth: bool = False
    checks_upstream_config: bool = False


STAGES: tuple[StageSpec, ...] = (
    StageSpec("ingest", ("topics", "ingest", "tool.base_to_world", "tools"), (), ("ingest_dir",),
              "ingest_dir", 10, "ingest:pipeline_step"),
    StageSpec("build-template", ("tool", "template"), ("ingest",),
              ("template_ply", "template_dir"), "template_ply", 20, "template:pipeline_step",
              checks_upstream_config=True),
    StageSpec("register", ("target", "registration"), ("ingest", "build-template"),
              ("registration_dir",), "registration_dir", 50, "register:pipeline_step",
              resumable=True, checks_upstream_config=True),
    StageSpec("classify", ("classify",), ("ingest", "build-template", "register"),
              ("classify_dir", "clouds_dir"), "labels", 5, "classify:pipeline_step"),
    StageSpec("measure", ("deformation",), ("ingest", "build-template", "register"),
              ("measure_dir", "deformation_csv"), "deformation_csv", 2, "measure:pipeline_step"),
    StageSpec("evaluate", ("labels",), ("ingest", "build-template"),
              ("evaluation_json", "evaluation_errors"), "evaluation_json", 5,
              "evaluate:pipeline_step", needs_ground_truth=True),
    StageSpec("report", (), ("ingest",), ("frames_csv", "summary_json", "report_html"),
              "report_html", 10, "report:pipeline_step"),
)
NAMES = tuple(s.name for s in STAGES)
_BY_NAME = {s.name: s for s in STAGES}


def spec(name: str) -> StageSpec:
    return _BY_NAME[name]


def config_keys(name: str) -> tuple[str, ...]:
    """Every config key the outputs of stage `name` depend on: its own and those of the
    stages before it."""
    index = NAMES.index(name)
    return tuple(k for s in STAGES[: index + 1] for k in s.depends_on)


def upstream_config_keys(name: str) -> tuple[str, ...]:
    """The config keys that shaped the outputs stage `name` builds on."""
    index = NAMES.index(name)
    return config_keys(NAMES[index - 1]) if index else ()


@dataclass
class StageContext:
    """What a pipeline step gets: the input log, run folder, config and executor, and
    the state steps share within one `run` (frames classified as they were registered,
    the evaluation)."""

    log: Path
    run_dir: Path
    config: Config
    executor: Executor
    ground_truth: Path | None = None
    allow_truncated: bool = False
    force_ingest: bool = False
    classified: dict[int, Any] = field(default_factory=dict)
    evaluation: dict[str, Any] | None = None


Step = Callable[[StageContext, Callable[[float], None]], None]


def resolve(reference: str) -> Any:
    """The function "module:function" of a stage module (imported now)."""
    module, function = reference.split(":")
    return getattr(importlib.import_module(f"{__package__}.{module}"), function)


def step(name: str) -> Step:
    """The pipeline step of stage `name`."""
    return resolve(spec(name).step)


# Registered frames are classified as they finish (register's pipeline step runs them on
# workers the chain of base frames leaves idle): classify_task(run_dir, config, frame).
CLASSIFY_FRAME_TASK = "classify:classify_task"
