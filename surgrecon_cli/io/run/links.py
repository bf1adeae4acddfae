"""Reusing a run's files in another run folder without copying their bytes: hard links, or
a copy where the file system cannot link (another device, no link support).

Safe because run-folder files are never rewritten in place once a stage is done: a file is
replaced by a rename (io/run/atomic.py) or deleted before its stage reruns, which leaves the
other folder's link intact.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path


def link_or_copy(src: Path, dst: Path) -> None:
    """`dst` as a hard link to the file `src` (a copy if linking fails); parents created."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def link_tree(src: Path, dst: Path) -> None:
    """Every file under the folder (or the single file) `src` linked (or copied) to the same
    place under `dst`; temporary files of killed writes are left out."""
    src, dst = Path(src), Path(dst)
    if src.is_file():
        link_or_copy(src, dst)
        return
    for folder, _dirs, files in os.walk(src):
        target = dst / Path(folder).relative_to(src)
        target.mkdir(parents=True, exist_ok=True)
        for name in files:
            if not name.endswith(".tmp"):
                link_or_copy(Path(folder) / name, target / name)
