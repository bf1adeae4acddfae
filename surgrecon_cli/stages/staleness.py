"""Whether a stage's outputs in a run folder are still valid for a config: the one place
that decides it.

A stage's outputs depend on the config keys the registry lists for it (`config_keys`: its
own and those of every stage before it). The values they were made with are recorded in
the stage's run.json entry (`recorded_config`, written when the stage finishes), else in
run.json's `config`. A stage must run again (`why_stale`) when one of those values
changed, when it is not done, when its key output is missing, or, for a stage that reads
ground truth, when the ground-truth file changed. The planner (planning.py), `run --tag`'s
reuse, `stage_run` and the register stage's frame-by-frame resumption all ask here.
"""

from __future__ import annotations

from typing import Any

from ..config import Config, to_dict
from ..io.run.folder import RunFolder, config_value, plain
from ..io.run.layout import RunLayout
from .registry import config_keys, spec, upstream_config_keys

NOT_DONE = "not done"


def recorded_config(config: Config, stage: str) -> dict[str, Any]:
    """{key: value} of the config keys stage `stage`'s outputs depend on, as recorded in
    its run.json entry when it finishes."""
    current = plain(to_dict(config))
    return {key: config_value(current, key) for key in config_keys(stage)}


def changed_keys(run: RunFolder, stage: str, config: Config) -> list[str]:
    """The config keys stage `stage`'s outputs depend on whose value in `config` differs
    from the one recorded in its run.json entry (else in run.json's `config`), in registry
    order; [] when none did."""
    data = run.read()
    own = data.get("stages", {}).get(stage, {}).get("config", {})
    current = plain(to_dict(config))
    changed = []
    for key in config_keys(stage):
        if isinstance(own, dict) and key in own:
            recorded = own[key]
        else:
            recorded = config_value(data.get("config", {}), key)
        if recorded != config_value(current, key):
            changed.append(key)
    return changed


def why_stale(run: RunFolder, stage: str, config: Config, gt_sha: str | None,
              resume: bool = False) -> str:
    """Why stage `stage` must run (again) in `run` for `config` and the ground truth of
    SHA-256 `gt_sha` (None: none): "config changed (KEYS)", `NOT_DONE`, "PATH is missing"
    or "ground truth changed"; "" when its outputs are valid. With `resume`, a resumable
    stage that is not done but whose config is unchanged is valid too (it resumes frame by
    frame)."""
    stage_spec = spec(stage)
    entry = run.stage(stage)
    changed = changed_keys(run, stage, config) if entry else []
    if changed:
        return f"config changed ({', '.join(changed)})"
    if not run.is_done(stage):
        return "" if resume and stage_spec.resumable else NOT_DONE
    layout = RunLayout(run.path)
    key = getattr(layout, stage_spec.key_output)
    if not key.exists():
        return f"{layout.relative(key)} is missing"
    if stage_spec.needs_ground_truth and entry.get("ground_truth", {}).get("sha256") != gt_sha:
        return "ground truth changed"
    return ""


def same_config(run: RunFolder, stage: str, config: Config) -> bool:
    """Whether the config stage `stage` last ran (or started) with in `run` is `config`, on
    the keys its outputs depend on: its frame-by-frame progress may then be resumed."""
    return run.stage(stage).get("config") == recorded_config(config, stage)


def check_upstream(run: RunFolder, stage: str, config: Config) -> None:
    """RunFolderError when stage `stage` reads upstream config keys (the registry's
    `checks_upstream_config`) and `config` differs from the one the earlier stages were
    made with on them; the message names the first differing key."""
    if spec(stage).checks_upstream_config:
        run.check_config(config, upstream_config_keys(stage))
