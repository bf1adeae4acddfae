"""Git LFS pointer files: the small text file git leaves in place of a large file (a log,
the sample's ground truth) whose content was never downloaded (`git lfs pull`)."""

from __future__ import annotations

from pathlib import Path

from ...errors import InputError

LFS_POINTER_START = b"version https://git-lfs.github.com/spec/v1"
"""How every Git LFS pointer file begins (the LFS specification's version line)."""


def refuse_lfs_pointer(path: Path, what: str) -> None:
    """InputError naming `path` when it is a Git LFS pointer rather than the `what` (e.g.
    "log") itself; nothing when it is not one or cannot be read (its reader says why)."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(LFS_POINTER_START))
    except OSError:
        return
    if head == LFS_POINTER_START:
        raise InputError(f"{path}: a Git LFS pointer file, not the {what} itself (its content "
                         "was never downloaded): run `git lfs pull` in its repository (or "
                         "download the file), then pass it again")
