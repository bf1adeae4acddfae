"""Which stage outputs of a run folder are still valid for a log and config (`Planner`,
asking stages/staleness.py), and seeding a new run folder with those of another
(`seed_run`: a `run --tag` sweep reuses, by hard link, every stage output whose config keys
did not change).
"""

from __future__ import annotations

from pathlib import Path

from .config import Config
from .io.run.folder import RunFolder
from .io.run.layout import RunLayout
from .io.run.links import link_or_copy, link_tree
from .stages import registry
from .stages.staleness import why_stale


class Planner:
    """Decides which stages are still valid in a run folder for this log and config."""

    def __init__(self, run: RunFolder, config: Config, gt_sha: str | None):
        self.run = run
        self.config = config
        self.gt_sha = gt_sha

    def first_stale(self, wanted: tuple[str, ...]) -> tuple[str | None, str]:
        """The first stage (in pipeline order) that must run from scratch, and why (a
        resumable stage not yet done with an unchanged config resumes instead)."""
        for stage in wanted:
            why = why_stale(self.run, stage, self.config, self.gt_sha, resume=True)
            if why:
                return stage, why
        return None, ""


def reusable_stages(base: RunFolder, config: Config, gt_sha: str | None) -> tuple[str, ...]:
    """The leading stages of `base` (pipeline order) that are done, whose outputs exist and
    whose config keys (cumulative, stages/registry.py) have the same values in `config`;
    the report is never among them (it names its own folder)."""
    out: list[str] = []
    for stage in registry.NAMES:
        if stage == "report" or why_stale(base, stage, config, gt_sha):
            break
        out.append(stage)
    return tuple(out)


def seed_run(base_dir: Path, run_dir: Path, config: Config, log_sha: str,
             gt_sha: str | None) -> tuple[str, ...]:
    """Start the new run folder `run_dir` from the run `base_dir` of the same log (SHA-256
    `log_sha`): the outputs of its reusable stages hard-linked (copied where linking fails)
    and their run.json entries, marked `reused_from`. Does nothing (returns ()) when
    `run_dir` is already a run folder, `base_dir` is not one, or holds another log's run;
    returns the stages reused."""
    base, new = RunFolder(base_dir), RunFolder(run_dir)
    if new.exists() or not base.exists() or base.input_hash != log_sha:
        return ()
    stages = reusable_stages(base, config, gt_sha)
    if not stages:
        return ()
    src, dst = RunLayout(base_dir), RunLayout(run_dir)
    for stage in stages:
        for name in registry.spec(stage).outputs:
            if getattr(src, name).exists():
                link_tree(getattr(src, name), getattr(dst, name))
    data = base.read()
    data["stages"] = {name: {**data["stages"][name], "reused_from": str(Path(base_dir).resolve())}
                      for name in stages}
    data.pop("pipeline", None)
    link_or_copy(src.config_toml, dst.config_toml)
    new.write(data)  # last: the folder is a run folder only once its outputs are in place
    return stages
