"""The serial executor: every task in this process, in dependency order (the reference)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from typing import Any

from . import OnDone, Task, topological_order


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """BLAS and OpenCV on one thread while tasks run, as in the worker processes, so that
    serial results equal the parallel executors' (restored afterwards)."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(before)


class SerialExecutor:
    """Runs tasks one after another in the calling process."""

    kind = "serial"
    workers = 1

    def run(self, tasks: Sequence[Task], on_done: OnDone | None = None) -> dict[str, Any]:
        results: dict[str, Any] = {}
        with _one_thread():
            for task in topological_order(tasks):
                results[task.key] = task.fn(*task.args)
                if on_done is not None:
                    on_done(task.key, results[task.key])
        return results

    def close(self) -> None:
        pass
