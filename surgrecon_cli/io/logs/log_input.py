"""What the user names as a log: one `.mcap` file, a ROS 1 `.bag` or ROS 2 sqlite3 `.db3`
file (read through rosbags: io/logs/rosbag.py), or a folder holding one recording split into
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

from ...errors import InputError, cut, quoted
from .lfs import refuse_lfs_pointer

METADATA = "metadata.yaml"
MAX_METADATA_BYTES = 1 << 20  # a rosbag2 metadata.yaml is a few kB
STORAGE_SUFFIX = {"mcap": ".mcap", "sqlite3": ".db3"}
"""rosbag2 storage identifier -> the suffix of its files."""
# The recordings `surgrecon convert` reads (convert/sources.py), named when a user passes
# one as a log.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg", ".h264")
MEDIA_SUFFIXES = VIDEO_SUFFIXES + IMAGE_SUFFIXES
_CONVERT_HINT = ("convert it first: surgrecon convert {path} -o OUT.mcap --calibration FILE, "
                 "then surgrecon run OUT.mcap -o RUN --config OUT.toml")


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
        path = self.path.absolute()  # (`.` has no name of its own)
        return path.stem if path.is_file() else path.name

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


class _NoAliasLoader(yaml.SafeLoader):
    """PyYAML's safe loader refusing aliases (`*name`): a few hundred bytes of nested aliases
    (a "billion laughs") would otherwise expand to gigabytes when read."""

    def compose_node(self, parent: yaml.Node | None, index: int) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(None, None, "YAML aliases are not accepted",
                                              event.start_mark)
        return super().compose_node(parent, index)


def _from_metadata(folder: Path) -> tuple[Path, ...]:
    path = folder / METADATA
    try:
        if path.stat().st_size > MAX_METADATA_BYTES:
            raise InputError(f"{path}: {path.stat().st_size} bytes, more than a rosbag2 "
                             f"metadata file holds ({MAX_METADATA_BYTES} bytes at most)")
        meta = yaml.load(path.read_text(encoding="utf-8-sig"), Loader=_NoAliasLoader)
        info = meta["rosbag2_bagfile_information"]
        storage = str(info.get("storage_identifier", "mcap"))
        names = info.get("relative_file_paths") or []
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError,
            AttributeError) as exc:
        raise InputError(f"{path}: not a readable rosbag2 metadata file "
                         f"({cut(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)})"
                         ) from exc
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise InputError(f"{path}: relative_file_paths must be a list of file names")
    suffix = STORAGE_SUFFIX.get(storage)
    if suffix is None:
        raise InputError(f"{folder}: a rosbag2 bag stored as {quoted(storage)}; surgrecon reads "
                         f"storage {' or '.join(STORAGE_SUFFIX)}: convert it with `ros2 bag "
                         f"convert -i {folder} -o OUT.yaml` (storage_id mcap)")
    files = []
    for name in names:
        if Path(name).suffix != suffix:
            raise InputError(f"{path}: storage {quoted(storage)} but it lists {quoted(name)}, "
                             f"not a {suffix} file; fix the metadata or name the files themselves")
        try:
            file = (folder / name).resolve(strict=True)
        except (OSError, RuntimeError) as exc:  # missing, or a symbolic link loop
            why = "a symbolic link loop in" if "loop" in str(exc).lower() else "missing from"
            raise InputError(f"{path} lists {quoted(name)}, which is {why} {folder}") from exc
        if folder.resolve() not in file.parents:
            raise InputError(f"{path}: file {quoted(name)} lies outside the bag folder")
        if not file.is_file():
            raise InputError(f"{path} lists {quoted(name)}, which is not a file in {folder}")
        files.append(file)
    if not files:
        raise InputError(f"{path}: lists no files")
    return tuple(files)


def resolve_log(path: Path | str) -> LogInput:
    """The log named by `path`; InputError (one line) when there is none, or when one of its
    files is a Git LFS pointer (not downloaded)."""
    log = _resolve(Path(path))
    for file in log.files:
        refuse_lfs_pointer(file, "log")
    return log


def _resolve(path: Path) -> LogInput:
    if path.is_file():
        if path.suffix.lower() in MEDIA_SUFFIXES:
            raise InputError(f"{path}: a video or image, not a log; "
                             + _CONVERT_HINT.format(path=path))
        return LogInput(path, (path,))
    if not path.is_dir():
        raise InputError(f"{path}: no such file or folder")
    if (path / METADATA).is_file():
        return LogInput(path, _from_metadata(path))
    files = tuple(sorted((f for f in path.glob("*.mcap") if f.is_file()),
                         key=lambda f: _natural(f.name)))
    if not files:
        if _holds_images(path):
            raise InputError(f"{path}: a folder of images, not a log; "
                             + _CONVERT_HINT.format(path=path))
        raise InputError(f"{path}: a folder without {METADATA} and without .mcap files; "
                         "name an .mcap file or a rosbag2 bag folder")
    return LogInput(path, files)


def _holds_images(folder: Path) -> bool:
    """Whether `folder` or one of its folders (a stereo recording's left/, right/) holds
    images or videos."""
    for level in (folder, *(p for p in folder.iterdir() if p.is_dir())):
        if any(f.suffix.lower() in MEDIA_SUFFIXES for f in level.iterdir() if f.is_file()):
            return True
    return False
