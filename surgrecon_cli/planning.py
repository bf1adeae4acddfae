"""Which stage outputs of a run folder are still valid for a log and config (`Planner`),
and seeding a new run folder with those of another (`seed_run`: a `run --tag` sweep
reuses, by hard link, every stage output whose config keys did not change).
"""

from __future__ import annotations

from pathlib import Path

from .config import Config, to_dict
from .io.links import link_or_copy, link_tree
from .io.run_folder import RunFolder, config_value, plain
from .io.run_layout import RunLayout
from .stages import registry


class Planner:
    """Decides which stages are still valid in a run folder for this log and config."""

    def __init__(self, run: RunFolder, config: Config, gt_sha: str | None):
        self.run = run
        self.layout = RunLayout(run.path)
        self.current = plain(to_dict(config))
        self.gt_sha = gt_sha

    def changed_keys(self, stage: str) -> list[str]:
        """Config keys its outputs depend on whose value differs from the one recorded in
        its run.json entry (else in run.json's config)."""
        data = self.run.read()
        own = data.get("stages", {}).get(stage, {}).get("config", {})
        changed = []
        for key in registry.config_keys(stage):
            if isinstance(own, dict) and key in own:
                recorded = own[key]
            else:
                recorded = config_value(data.get("config", {}), key)
            if recorded != config_value(self.current, key):
                changed.append(key)
        return changed

    def first_stale(self, wanted: tuple[str, ...]) -> tuple[str | None, str]:
        """The first stage (in pipeline order) that must run from scratch, and why."""
        for stage in wanted:
            spec = registry.spec(stage)
            entry = self.run.stage(stage)
            changed = self.changed_keys(stage) if entry else []
            if changed:
                return stage, f"config changed ({', '.join(changed)})"
            if spec.resumable and not self.run.is_done(stage):
                continue  # resumable frame by frame (it checks its own config)
            if not self.run.is_done(stage):
                return stage, "not done"
            key = getattr(self.layout, spec.key_output)
            if not key.exists():
                return stage, f"{self.layout.relative(key)} is missing"
            if spec.needs_ground_truth:
                recorded = entry.get("ground_truth", {}).get("sha256")
                if recorded != self.gt_sha:
                    return stage, "ground truth changed"
        return None, ""


def reusable_stages(base: RunFolder, config: Config, gt_sha: str | None) -> tuple[str, ...]:
    """The leading stages of `base` (pipeline order) that are done, whose outputs exist and
    whose config keys (cumulative, stages/registry.py) have the same values in `config`;
    the report is never among them (it names its own folder)."""
    planner = Planner(base, config, gt_sha)
    out: list[str] = []
    for stage in registry.NAMES:
        spec = registry.spec(stage)
        if stage == "report" or not base.is_done(stage) or planner.changed_keys(stage):
            break
        if not getattr(planner.layout, spec.key_output).exists():
            break
        if (spec.needs_ground_truth
                and base.stage(stage).get("ground_truth", {}).get("sha256") != gt_sha):
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
