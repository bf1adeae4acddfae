"""Keeping freed memory in the process while a burst of large allocations runs.

glibc serves allocations above its mmap threshold (at most 32 MB) with fresh pages from the
kernel and returns them on free, so a call that builds and frees hundreds of MB (SIFT's
scale space of a 1080p image is ~0.5 GB, rebuilt per image) pays the kernel's page faults
each time: measured 0.1-0.9 s of system CPU per 1920x1080 image on our 2-core VM, ~1.4 s of
a 6-camera template. `kept_heap()` serves everything from the heap and keeps it while the
block runs, then gives the memory back. Only the memory's reuse changes, never a result;
without glibc (no `mallopt`) it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
from collections.abc import Iterator

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
_MMAP_MAX_DEFAULT = 65536  # glibc's default
# afterwards: the values glibc's dynamic threshold reaches once large blocks were freed
# (mallopt turns the dynamic adjustment off): 32 MB, trim at twice it
_MMAP_THRESHOLD_AFTER = 32 << 20
_TRIM_THRESHOLD_AFTER = 64 << 20
_KEEP = (1 << 31) - 1  # no trimming while kept (an int)


def _libc() -> ctypes.CDLL | None:
    """The C library when it has glibc's mallopt and malloc_trim, else None."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
    except (OSError, AttributeError, TypeError):
        return None
    return libc


@contextlib.contextmanager
def kept_heap() -> Iterator[None]:
    """Within the block, no allocation is mmapped and freed memory is not returned to the
    kernel (no page faults on reuse); on exit the mmap threshold is glibc's fully adapted
    one (32 MB) and the free memory is returned (`malloc_trim`)."""
    libc = _libc()
    if libc is None:
        yield
        return
    libc.mallopt(_M_TRIM_THRESHOLD, _KEEP)
    libc.mallopt(_M_MMAP_MAX, 0)
    try:
        yield
    finally:
        libc.mallopt(_M_MMAP_MAX, _MMAP_MAX_DEFAULT)
        libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_AFTER)
        libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD_AFTER)
        libc.malloc_trim(0)


def adapted_heap() -> None:
    """Set glibc's thresholds at once to the values its dynamic adjustment reaches once
    large blocks were freed (mmap above 32 MB, trim above 64 MB): a process that allocates
    and frees image-sized buffers every frame (a register worker: 4-5 MB a 1280x1024 image,
    several per image) serves them from its heap instead of fresh pages from the kernel
    (measured: 7-9 ms less CPU a 2-camera 1280x1024 frame). Only the memory's reuse
    changes, never a result; without glibc it does nothing."""
    libc = _libc()
    if libc is None:
        return
    libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_AFTER)
    libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD_AFTER)
