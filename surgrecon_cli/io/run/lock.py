"""One command at a time on a run folder: `run_folder_lock` holds an OS file lock (flock) on
RUN/.surgrecon.lock for the whole command, with the holder's pid, start time and command
written into it. The kernel drops the lock when the process dies, so a killed run never
blocks the next one; a second command refuses at once, naming the holder.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import json
import os
import threading
from collections.abc import Iterator
from pathlib import Path

from ...errors import RunFolderError, cut
from .layout import RunLayout

# Run folders this process holds the lock of: real path -> [lock fd, depth, made it].
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
    made = create and not folder.exists()  # removed again if it stays empty
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
            _HELD[key] = [_acquire(folder, command, writes), 1, made]
    try:
        yield
    finally:
        with _HELD_GUARD:
            _HELD[key][1] -= 1
            if _HELD[key][1] == 0:
                fd, _, made_here = _HELD.pop(key)
                if fd >= 0:
                    with contextlib.suppress(OSError):
                        os.ftruncate(fd, 0)
                        if not RunLayout(key).run_json.exists():  # no run folder: no trace
                            RunLayout(key).lock_file.unlink()
                            if made_here:
                                os.rmdir(key)  # only if this command made it and it is empty
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

