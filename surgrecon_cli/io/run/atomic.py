"""Atomic file writing: write to a temporary name in the same folder, fsync, then rename.

A killed process never leaves a truncated file under a final name.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import IO, Any

import numpy as np

from ...errors import WRITE_ERRNOS, OutputError

_UMASK = os.umask(0)
os.umask(_UMASK)
# The temporary name of an interrupted write: `.NAME.` + mkstemp's 8 random characters + `.tmp`.
_TEMPORARY_NAME = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


def is_temporary(name: str) -> bool:
    """Whether a file name is one of `atomic_open`'s temporaries (not, e.g., `.draft.tmp`)."""
    return _TEMPORARY_NAME.fullmatch(name) is not None


@contextlib.contextmanager
def atomic_open(path: Path | str, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary sibling of `path` for writing; rename it over `path` on success.
    (A string path stays a string: no pathlib parsing per file written, see
    `RunLayout.registration_file`.)"""
    folder, name = os.path.split(os.fspath(path))
    try:
        os.makedirs(folder or ".", exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder or ".")
    except OSError as exc:
        raise _not_written(path, exc) from exc
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp creates 0600; final files get the usual mode
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS and exc.filename is None:
            raise _not_written(path, exc) from exc  # a full disk while writing `path`
        raise


class CacheDropping:
    """A binary file handle (`write`, `tell`, `flush`; `close` waits) whose written bytes leave
    the page cache every `every` bytes: a helper thread fdatasyncs, then drops what is on disk
    (POSIX_FADV_DONTNEED) while writing goes on. A log of several GB then does not push other
    files out of the cache, and the kernel writes the next bytes into pages it just freed,
    which costs a fraction of fresh pages' CPU (on a 2-core VM 0.7 instead of 4.4 ms for
    1.9 MB; benchmarks/convert_speed.py)."""

    def __init__(self, handle: IO[bytes], every: int = 32 << 20) -> None:
        self.handle, self.every = handle, every
        self.dropped = self.pending = 0
        self.pool = ThreadPoolExecutor(max_workers=1)
        self.syncing: Future[None] | None = None

    def _drop(self, start: int, end: int) -> None:
        fd = self.handle.fileno()
        os.fdatasync(fd)
        os.posix_fadvise(fd, start, end - start, os.POSIX_FADV_DONTNEED)

    def write(self, data: bytes | bytearray | memoryview) -> int:
        written = self.handle.write(data)
        self.pending += written
        if self.pending >= self.every and hasattr(os, "posix_fadvise"):
            if self.syncing is not None:  # one sync at a time; errors surface here
                self.syncing.result()
            self.handle.flush()
            end = self.handle.tell()
            self.syncing = self.pool.submit(self._drop, self.dropped, end)
            self.dropped, self.pending = end, 0
        return written

    def tell(self) -> int:
        return self.handle.tell()

    def flush(self) -> None:
        self.handle.flush()

    def close(self) -> None:
        """Wait for the last sync (the handle stays open)."""
        if self.syncing is not None:
            self.syncing.result()
        self.pool.shutdown()


def _not_written(path: Path | str, exc: OSError) -> OutputError:
    return OutputError(f"{path}: cannot write ({exc.strerror or type(exc).__name__}); free "
                       "space or choose a writable folder")


def remove_leftovers(folder: Path | str) -> int:
    """Delete the temporary files of killed writes (`.NAME.XXXXXXXX.tmp`) anywhere under
    `folder`; returns how many. Only for a folder no other process is writing to (hold its
    lock)."""
    removed = 0
    for tmp in Path(folder).rglob(".*.tmp"):
        if is_temporary(tmp.name) and tmp.is_file() and not tmp.is_symlink():
            tmp.unlink(missing_ok=True)
            removed += 1
    return removed


def file_identity(*paths: Path | str) -> tuple[tuple[int, ...], ...]:
    """(device, inode, mtime ns, ctime ns, size) of each file: a key for a per-process
    cache of what was read from them. Files written here are replaced by a rename, never
    rewritten in place, so a new version has a new identity. Raises FileNotFoundError."""
    stats = [os.stat(path) for path in paths]
    return tuple((st.st_dev, st.st_ino, st.st_mtime_ns, st.st_ctime_ns, st.st_size)
                 for st in stats)


def write_bytes(path: Path | str, data: bytes) -> None:
    with atomic_open(path, "wb") as f:
        f.write(data)


def write_text(path: Path | str, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: Path | str, obj: Any) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def write_npz(path: Path | str, **arrays: np.ndarray | np.generic) -> None:
    """np.savez (uncompressed) atomically; loads back with allow_pickle=False."""
    kwds: dict[str, Any] = arrays  # numpy's stub: `**` could also fill savez's allow_pickle
    with atomic_open(path, "wb") as f:
        np.savez(f, **kwds)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
