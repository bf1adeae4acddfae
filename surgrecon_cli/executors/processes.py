"""The processes executor: a pool of local worker processes (spawned, single-threaded).

The driver keeps the graph (`run_graph`): a task is submitted when its dependencies have
finished and one of the graph's `workers` slots is free (longest path first), and results
are collected in completion order. Graphs run from several driver threads at once (many
logs) each have their own slots and share the pool first come, first served. A task that
raises stops the graph (tasks not yet started are cancelled) and its exception is
re-raised; a worker that dies (killed, out of memory) is reported as an ExecutorError —
rerunning resumes from what the finished tasks wrote.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from . import ExecutorError, OnDone, Task, call_task, preload, run_graph


def _watch_parent(parent: int, period_s: float = 0.5) -> None:
    """Exit this worker when its driver is gone (killed with SIGKILL, the pool's pipes stay
    open in the workers and would keep orphans waiting forever)."""
    while os.getppid() == parent:
        time.sleep(period_s)
    os._exit(1)


def _start_worker(parent: int, modules: tuple[str, ...]) -> None:
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()
    preload(modules)


class ProcessExecutor:
    """`workers` spawned processes shared by every graph run on this executor."""

    kind = "processes"

    def __init__(self, workers: int, modules: tuple[str, ...] = ()):
        self.workers = workers
        self.modules = modules
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()
        # The pool spawns a worker when a task finds none idle: submitting one task per
        # worker starts them all now (they import while the driver ingests).
        pool = self._get_pool()
        for _ in range(workers):
            pool.submit(int)

    def _get_pool(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                    initializer=_start_worker, initargs=(os.getpid(), self.modules))
            return self._pool

    def run(self, tasks: Sequence[Task], on_done: OnDone | None = None) -> dict[str, Any]:
        pool = self._get_pool()
        try:
            return run_graph(tasks, lambda t, _priority: pool.submit(call_task, t.fn, t.args),
                             lambda fs: wait(fs, return_when=FIRST_COMPLETED)[0], on_done,
                             slots=self.workers)
        except BrokenProcessPool as exc:
            self.close()
            raise ExecutorError(f"a worker process died ({exc}); rerun to resume from the "
                                "finished tasks") from exc

    def close(self) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None
