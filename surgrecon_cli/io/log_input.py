"""What the user names as a log: one `.mcap` file, a ROS 1 `.bag` or ROS 2 sqlite3 `.db3`
file (read through rosbags: io/mcap/rosbag.py), or a folder holding one recording split into
several files (a rosbag2 bag folder with its `metadata.yaml`, storage `mcap` or `sqlite3`, or
split `.mcap` files without one, taken in natural name order: rec_2 before rec_10).

A log's identity is the SHA-256 of its files' bytes concatenated in order (for one file,
that file's SHA-256), so a run folder knows when it is handed another recording.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import yaml

from ..errors import InputError

METADATA = "metadata.yaml"
STORAGE_SUFFIX = {"mcap": ".mcap", "sqlite3": ".db3"}
"""rosbag2 storage identifier -> the suffix of its files."""


@dataclass(frozen=True)
class LogInput:
    """path: what was named (file or folder); files: its MCAP (or bag) files in recording
    order."""

    path: Path
    files: tuple[Path, ...]

    @property
    def size(self) -> int:
        """Bytes over all files."""
        return sum(f.stat().st_size for f in self.files)

    @property
    def name(self) -> str:
        """The recording's name: the file name without its suffix, or the folder's name."""
        return self.path.stem if self.path.is_file() else self.path.name

    def sha256(self) -> str:
        """SHA-256 of the files' bytes, concatenated in order, read in 1 MiB blocks."""
        sha = hashlib.sha256()
        for path in self.files:
            with open(path, "rb") as f:
                while block := f.read(1 << 20):
                    sha.update(block)
        return sha.hexdigest()


def _natural(name: str) -> list[object]:
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]


def _from_metadata(folder: Path) -> tuple[Path, ...]:
    path = folder / METADATA
    try:
        meta = yaml.safe_load(path.read_text(encoding="utf-8"))
        info = meta["rosbag2_bagfile_information"]
        storage = str(info.get("storage_identifier", "mcap"))
        names = [str(n) for n in info.get("relative_file_paths") or []]
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError,
            AttributeError) as exc:
        raise InputError(f"{path}: not a readable rosbag2 metadata file ({exc})") from exc
    suffix = STORAGE_SUFFIX.get(storage)
    if suffix is None:
        raise InputError(f"{folder}: a rosbag2 bag stored as {storage!r}; surgrecon reads "
                         f"storage {' or '.join(STORAGE_SUFFIX)}: convert it with `ros2 bag "
                         f"convert -i {folder} -o OUT.yaml` (storage_id mcap)")
    files = []
    for name in names:
        file = (folder / name).resolve()
        if folder.resolve() not in file.parents:
            raise InputError(f"{path}: file {name!r} lies outside the bag folder")
        if file.suffix != suffix:
            raise InputError(f"{path}: storage {storage!r} but it lists {name!r}, not a "
                             f"{suffix} file; fix the metadata or name the files themselves")
        if not file.is_file():
            raise InputError(f"{path} lists {name!r}, which is missing from {folder}")
        files.append(file)
    if not files:
        raise InputError(f"{path}: lists no files")
    return tuple(files)


def resolve_log(path: Path | str) -> LogInput:
    """The log named by `path`; InputError (one line) when there is none."""
    path = Path(path)
    if path.is_file():
        return LogInput(path, (path,))
    if not path.is_dir():
        raise InputError(f"{path}: no such file or folder")
    if (path / METADATA).is_file():
        return LogInput(path, _from_metadata(path))
    files = tuple(sorted((f for f in path.glob("*.mcap") if f.is_file()),
                         key=lambda f: _natural(f.name)))
    if not files:
        raise InputError(f"{path}: a folder without {METADATA} and without .mcap files; "
                         "name an .mcap file or a rosbag2 bag folder")
    return LogInput(path, files)
