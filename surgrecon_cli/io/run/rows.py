"""Per-frame arrays of long logs, one row at a time: (T, ...) arrays on disk that a stage
writes or reads frame by frame, so that its memory does not grow with the log's length.

`RowFile` is a .npy file written and read by row at its byte offset (plain reads and
writes, no memory map: a map's touched pages would count in the process's RSS);
`npz_rows` reads rows of an array stored in an uncompressed .npz (io/atomic.write_npz),
and `write_npz_rows` assembles such an .npz from RowFiles, copied in blocks of 256 KiB.
"""

from __future__ import annotations

import os
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import RunFolderError
from .atomic import atomic_open

_LOCAL_HEADER = 30  # bytes of a zip local file header before its name and extra field


class RowFile:
    """A (T, *row) array in a .npy file at `path`, row k at a fixed byte offset.

    `create` writes the header (rows not yet written read as zeros); else the header is
    read. Rows are written and read with pwrite/pread: only the row in hand is in memory."""

    def __init__(self, path: Path, shape: tuple[int, ...] | None = None,
                 dtype: Any = None, create: bool = False, offset: int = 0) -> None:
        self.path = Path(path)
        if create:
            assert shape is not None and dtype is not None
            self.shape, self.dtype = tuple(int(s) for s in shape), np.dtype(dtype)
            with open(self.path, "wb") as f:
                np.lib.format.write_array_header_1_0(f, {
                    "descr": np.lib.format.dtype_to_descr(self.dtype), "fortran_order": False,
                    "shape": self.shape})
                self.offset = f.tell()
                f.truncate(self.offset + self.row_bytes * self.shape[0])
        else:
            with open(self.path, "rb") as f:
                f.seek(offset)
                self.shape, self.dtype = _read_header(f, self.path)
                self.offset = f.tell()
        self._fd = os.open(self.path, os.O_RDWR if create else os.O_RDONLY)

    @property
    def row_bytes(self) -> int:
        return int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize

    def write(self, k: int, row: np.ndarray) -> None:
        """Row k (shape `shape[1:]`, cast to the file's dtype)."""
        data = np.ascontiguousarray(row, self.dtype)
        if data.shape != self.shape[1:]:
            raise ValueError(f"{self.path}: row of shape {data.shape}, not {self.shape[1:]}")
        os.pwrite(self._fd, data.tobytes(), self.offset + k * self.row_bytes)

    def read(self, k: int) -> np.ndarray:
        """Row k, a new array of shape `shape[1:]`."""
        data = os.pread(self._fd, self.row_bytes, self.offset + k * self.row_bytes)
        if len(data) != self.row_bytes:
            raise RunFolderError(f"{self.path}: truncated at row {k}")
        return np.frombuffer(data, self.dtype).reshape(self.shape[1:]).copy()

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> RowFile:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def _read_header(f: Any, path: Path) -> tuple[tuple[int, ...], np.dtype]:
    try:
        fmt = np.lib.format
        version = fmt.read_magic(f)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran, dtype = read(f)
    except ValueError as exc:
        raise RunFolderError(f"{path}: not a .npy array ({exc})") from exc
    if fortran or dtype.hasobject:
        raise RunFolderError(f"{path}: not a C-ordered plain array")
    return tuple(shape), dtype


def npz_rows(path: Path, name: str) -> RowFile:
    """Row access to array `name` of an uncompressed .npz (RunFolderError if compressed or
    missing): its member's data lie in the file as they would in a .npy."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as z:
            info = z.getinfo(f"{name}.npy")
    except (OSError, KeyError, zipfile.BadZipFile) as exc:
        raise RunFolderError(f"{path}: no array {name!r} ({exc})") from exc
    if info.compress_type != zipfile.ZIP_STORED:
        raise RunFolderError(f"{path}: {name} is compressed; rows need a stored member")
    with open(path, "rb") as f:
        f.seek(info.header_offset + 26)
        lengths = np.frombuffer(f.read(4), "<u2")
    start = info.header_offset + _LOCAL_HEADER + int(lengths.sum())
    return RowFile(path, offset=start)


def write_npz_rows(path: Path, members: dict[str, RowFile | np.ndarray]) -> None:
    """Write an uncompressed .npz at `path` (atomically) whose arrays are the RowFiles'
    contents, copied in 256 KiB blocks, or arrays in memory (small ones); np.load reads it
    as any np.savez file."""
    with atomic_open(path, "wb") as out, zipfile.ZipFile(out, "w", zipfile.ZIP_STORED,
                                                        allowZip64=True) as z:
        for name, rows in members.items():
            with z.open(f"{name}.npy", "w", force_zip64=True) as dst:
                if isinstance(rows, RowFile):
                    with open(rows.path, "rb") as src:
                        shutil.copyfileobj(src, dst, 1 << 18)
                else:
                    np.lib.format.write_array(dst, np.asarray(rows), allow_pickle=False)
