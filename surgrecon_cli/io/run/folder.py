"""`RUN/run.json`: what a run folder holds, read and updated atomically by every stage.

run.json layout:
  {"surgrecon": version, "input": {"path", "sha256", "bytes"}, "config": {...},
   "versions": {package: version}, "stages": {name: {"status": ..., ...info}},
   "ingest": {"cameras": [...], "frames": T}}
Stage status is "running", "done" or "failed"; only "done" means the stage's outputs are
complete. Every update rewrites the file atomically (temporary name, then rename).
One command at a time works on a run folder (io/run/lock.py).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import shlex
from pathlib import Path
from typing import Any

from ... import __version__
from ...config import Config, to_dict, to_toml
from ...errors import RunFolderError
from ..logs.log_input import resolve_log
from .atomic import write_json, write_text
from .layout import RunLayout

STATUSES = ("running", "done", "failed")
_PACKAGES = {
    "surgrecon": ("surgrecon",),
    "numpy": ("numpy",),
    "scipy": ("scipy",),
    "opencv": ("opencv-python-headless", "opencv-python", "opencv-contrib-python"),
    "open3d": ("open3d-cpu", "open3d"),
    "mcap": ("mcap",),
}


def package_versions() -> dict[str, str]:
    """Installed versions of surgrecon and its main dependencies ("" if not installed)."""
    out = {}
    for key, dists in _PACKAGES.items():
        out[key] = ""
        for dist in dists:
            try:
                out[key] = importlib.metadata.version(dist)
                break
            except importlib.metadata.PackageNotFoundError:
                continue
    if not out["surgrecon"]:
        out["surgrecon"] = __version__
    return out


def file_sha256(path: Path) -> str:
    """SHA-256 hex digest of a file, read in 1 MiB blocks."""
    sha = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            sha.update(block)
    return sha.hexdigest()


def plain(obj: Any) -> Any:
    """JSON round trip (tuples -> lists), for comparing a config with the recorded one."""
    return json.loads(json.dumps(obj))


def config_value(config: dict[str, Any], key: str) -> Any:
    """The value of a section ("target") or `section.key` in a config dict (None if
    absent)."""
    value: Any = config
    for part in key.split("."):
        if not isinstance(value, dict):
            return None
        value = value.get(part)
    return value


class RunFolder:
    """A run folder and its run.json."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)

    @property
    def run_json(self) -> Path:
        return RunLayout(self.path).run_json

    def exists(self) -> bool:
        return self.run_json.is_file()

    def read(self) -> dict[str, Any]:
        """Parsed run.json; RunFolderError if missing or unreadable."""
        try:
            data = json.loads(self.run_json.read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise RunFolderError(f"{self.path}: not a run folder (no run.json); run "
                                 "`surgrecon ingest LOG.mcap -o RUN` first") from exc
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise RunFolderError(f"{self.run_json}: unreadable ({exc})") from exc
        tables = ("stages", "input", "config", "ingest", "pipeline")
        if (not isinstance(data, dict) or "surgrecon" not in data
                or not all(isinstance(data.get(k, {}), dict) for k in tables)
                or not all(isinstance(v, dict) for v in data.get("stages", {}).values())):
            raise RunFolderError(f"{self.run_json}: not a surgrecon run.json (another tool's, "
                                 "or damaged); use a new run folder")
        return data

    def write(self, data: dict[str, Any]) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        write_json(self.run_json, data)

    def start(self, input_path: Path, config: Config) -> None:
        """A fresh run.json for `input_path` (any earlier stage status is dropped) and the
        effective config as RUN/config.toml (written second: a folder with a config.toml and
        no run.json would not be recognised as a run folder)."""
        self.path.mkdir(parents=True, exist_ok=True)
        self.write({
            "surgrecon": __version__,
            "input": {"path": str(Path(input_path).resolve()), "sha256": None,
                      "bytes": resolve_log(input_path).size},
            "config": plain(to_dict(config)),
            "versions": package_versions(),
            "stages": {},
        })
        write_text(RunLayout(self.path).config_toml, to_toml(config))

    def update(self, **fields: Any) -> None:
        """Set top-level fields of run.json (e.g. input=..., ingest=...)."""
        data = self.read()
        data.update(plain(fields))
        self.write(data)

    def stage(self, name: str) -> dict[str, Any]:
        """The stage's entry ({} if it never ran)."""
        if not self.exists():
            return {}
        return dict(self.read().get("stages", {}).get(name, {}))

    def stage_status(self, name: str) -> str | None:
        return self.stage(name).get("status")

    def is_done(self, name: str) -> bool:
        return self.stage_status(name) == "done"

    def require_done(self, name: str) -> None:
        """RunFolderError unless stage `name` completed."""
        if not self.is_done(name):
            status = self.stage_status(name) or "not run"
            where = shlex.quote(str(self.path))
            hint = (f"surgrecon ingest LOG.mcap -o {where}" if name == "ingest"
                    else f"surgrecon {name} {where}")
            raise RunFolderError(f"{self.path}: stage {name} is {status}; run `{hint}` first")

    def mark_stage(self, name: str, status: str, **info: Any) -> None:
        """Record a stage's status ("running", "done", "failed") and info, atomically."""
        if status not in STATUSES:
            raise ValueError(f"stage status must be one of {STATUSES}, got {status!r}")
        data = self.read()
        data.setdefault("stages", {})[name] = {"status": status, **plain(info)}
        self.write(data)

    @property
    def input_hash(self) -> str | None:
        """SHA-256 of the input log recorded at ingest (None before ingest finished)."""
        return self.read().get("input", {}).get("sha256")

    def check_input(self, input_path: Path) -> None:
        """RunFolderError if `input_path` is not the log this run was made from."""
        recorded = self.input_hash
        if recorded and resolve_log(input_path).sha256() != recorded:
            raise RunFolderError(f"{self.path} was made from another log than {input_path} "
                                 "(SHA-256 differs); use a new run folder")

    def check_config(self, config: Config, keys: tuple[str, ...] | None = None) -> None:
        """RunFolderError naming the first key where `config` differs from the recorded one,
        among `keys` (sections such as "topics" or `section.key`s; default all)."""
        recorded = self.read().get("config", {})
        current = plain(to_dict(config))
        for key in current if keys is None else keys:
            old, new = config_value(recorded, key), config_value(current, key)
            if not isinstance(old, dict) or not isinstance(new, dict):
                old, new = {key: old}, {key: new}
                prefix = ""
            else:
                prefix = f"{key}."
            for name in sorted(set(old) | set(new)):
                if old.get(name) != new.get(name):
                    raise RunFolderError(
                        f"{self.path} was made with {prefix}{name} = {old.get(name)!r}, now "
                        f"{new.get(name)!r}; use the run's config.toml or a new run folder")


class FrameProgress:
    """An append-only record of the frames a resumable stage finished, one JSON line each:
    {"frame": k} or {"frame": k, "failed": why}. Recording a frame appends one short line
    (constant cost, whatever the log's length); run.json keeps only counts. A line cut by a
    kill is ignored when read (that frame is redone), and `restart` rewrites the record
    atomically without it before new lines are appended."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def read(self) -> dict[int, str]:
        """{frame: "" or why it failed} of every complete line (later lines win)."""
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return {}
        out: dict[int, str] = {}
        for line in text.split("\n")[:-1]:  # the part after the last newline is incomplete
            try:
                entry = json.loads(line)
                out[int(entry["frame"])] = str(entry.get("failed", ""))
            except (ValueError, KeyError, TypeError):
                continue
        return out

    def restart(self, frames: dict[int, str]) -> None:
        """Replace the record by `frames` ({frame: "" or why it failed}), atomically."""
        write_text(self.path, "".join(self._line(k, frames[k]) for k in sorted(frames)))

    def append(self, frame: int, failed: str = "") -> None:
        """Record one finished frame (one write of one line, flushed to the OS: it survives
        the process being killed)."""
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(self._line(frame, failed))

    @staticmethod
    def _line(frame: int, failed: str) -> str:
        entry: dict[str, Any] = {"frame": int(frame)}
        if failed:
            entry["failed"] = failed
        return json.dumps(entry) + "\n"
