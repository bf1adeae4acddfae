"""`RUN/run.json`: what a run folder holds, read and updated atomically by every stage.

run.json layout:
  {"surgrecon": version, "input": {"path", "sha256", "bytes"}, "config": {...},
   "versions": {package: version}, "stages": {name: {"status": ..., ...info}},
   "ingest": {"cameras": [...], "frames": T}}
Stage status is "running", "done" or "failed"; only "done" means the stage's outputs are
complete. Every update rewrites the file atomically (temporary name, then rename).

One command at a time works on a run folder: `run_folder_lock` holds an OS file lock on
RUN/.surgrecon.lock for the whole command (the kernel drops it when the process dies, so a
killed run never blocks the next one).
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import hashlib
import importlib.metadata
import json
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .. import __version__
from ..config import Config, to_dict, to_toml
from ..errors import RunFolderError, cut
from .atomic import write_json, write_text
from .log_input import resolve_log
from .run_layout import RunLayout

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
            hint = (f"surgrecon ingest LOG.mcap -o {self.path}" if name == "ingest"
                    else f"surgrecon {name} {self.path}")
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


# Run folders this process holds the lock of: real path -> [lock file descriptor, depth].
_HELD: dict[str, list[int]] = {}
_HELD_GUARD = threading.Lock()


@contextlib.contextmanager
def run_folder_lock(path: Path | str, command: str, create: bool = False,
                    writes: bool = True) -> Iterator[None]:
    """Hold the run folder's lock while the body runs: another process holding it makes this
    raise RunFolderError at once, naming its pid, start time and command. Re-entrant within
    one process (the pipeline's stages run under the command's lock). create: make the folder
    (and its parents) first; without it a folder that does not exist is not locked (the
    command reports it). writes=False (a command that only reads the run): a read-only
    folder without a lock file is read unlocked."""
    folder = Path(path)
    if create:
        _make_folder(folder)
    elif not folder.is_dir():
        yield
        return
    key = os.path.realpath(folder)
    with _HELD_GUARD:
        if key in _HELD:
            _HELD[key][1] += 1
        else:
            _HELD[key] = [_acquire(folder, command, writes), 1]
    try:
        yield
    finally:
        with _HELD_GUARD:
            _HELD[key][1] -= 1
            if _HELD[key][1] == 0:
                fd = _HELD.pop(key)[0]
                if fd >= 0:
                    with contextlib.suppress(OSError):
                        os.ftruncate(fd, 0)
                        if not RunLayout(key).run_json.exists():  # no run folder: no trace
                            RunLayout(key).lock_file.unlink()
                    os.close(fd)  # releases the lock


def _make_folder(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError as exc:
        raise RunFolderError(f"{folder}: exists and is not a folder; give a folder "
                             "path") from exc
    except OSError as exc:
        raise RunFolderError(f"{folder}: cannot create the run folder "
                             f"({exc.strerror or type(exc).__name__})") from exc
    if not folder.is_dir():
        raise RunFolderError(f"{folder}: not a folder; give a folder path")


def _acquire(folder: Path, command: str, writes: bool) -> int:
    """Open and lock RUN/.surgrecon.lock (never following a link), record who holds it;
    returns the open descriptor (-1: a read-only folder read unlocked, see writes)."""
    lock = RunLayout(folder).lock_file
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o666)
    except OSError as exc:
        if not writes and exc.errno in (errno.EROFS, errno.EACCES) and not lock.exists():
            return -1  # nobody can write there either
        raise RunFolderError(f"{lock}: cannot open the run folder's lock file "
                             f"({exc.strerror or type(exc).__name__}); use a writable "
                             "folder") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        holder = _holder(fd) if isinstance(exc, BlockingIOError) else ""
        os.close(fd)
        if not holder:  # e.g. a file system without locks
            raise RunFolderError(f"{lock}: cannot be locked ({exc.strerror}); use a run "
                                 "folder on a local disk") from exc
        raise RunFolderError(f"{folder} is in use by {holder}; wait for it to finish or use "
                             "another folder") from exc
    if os.fstat(fd).st_ino != getattr(_stat(lock), "st_ino", None):  # unlinked meanwhile
        os.close(fd)
        return _acquire(folder, command, writes)
    started = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    record = json.dumps({"pid": os.getpid(), "started": started, "command": command})
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, record.encode("utf-8") + b"\n", 0)
    except OSError as exc:
        os.close(fd)
        raise RunFolderError(f"{lock}: cannot write ({exc.strerror or type(exc).__name__}); "
                             "free space or use another folder") from exc
    return fd


def _stat(path: Path) -> os.stat_result | None:
    with contextlib.suppress(FileNotFoundError):
        return os.stat(path, follow_symlinks=False)
    return None


def _holder(fd: int) -> str:
    """Who holds a lock, from what it wrote into the lock file."""
    try:
        entry = json.loads(os.pread(fd, 4096, 0).decode("utf-8"))
        return (f"surgrecon {cut(str(entry['command']))} (pid {int(entry['pid'])}, started "
                f"{cut(str(entry['started']))})")
    except (OSError, ValueError, KeyError, TypeError):
        return "another surgrecon process (pid not recorded yet)"


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
