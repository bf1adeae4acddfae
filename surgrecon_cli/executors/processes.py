"""The processes executor: a pool of local worker processes (spawned, single-threaded).

The driver keeps the graph: a task is submitted when its dependencies have finished, and
results are collected in completion order. A task that raises stops the graph (tasks not
yet started are cancelled, running ones finish) and its exception is re-raised; a worker
that dies (killed, out of memory) is reported as an ExecutorError — rerunning resumes from
what the finished tasks wrote.
"""

from __future__ import annotations

import multiprocessing
import threading
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from . import ExecutorError, OnDone, Task, call_task, check_graph, single_threaded


class ProcessExecutor:
    """`workers` spawned processes shared by every graph run on this executor."""

    kind = "processes"

    def __init__(self, workers: int):
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def _get_pool(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                    initializer=single_threaded)
            return self._pool

    def run(self, tasks: Sequence[Task], on_done: OnDone | None = None) -> dict[str, Any]:
        by_key = check_graph(tasks)
        pool = self._get_pool()
        results: dict[str, Any] = {}
        waiting = dict(by_key)
        running: dict[Future, str] = {}

        def submit_ready() -> None:
            for key in [k for k, t in waiting.items() if all(d in results for d in t.deps)]:
                task = waiting.pop(key)
                running[pool.submit(call_task, task.fn, task.args)] = key

        try:
            submit_ready()
            while running:
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in finished:
                    key = running.pop(future)
                    results[key] = future.result()
                    if on_done is not None:
                        on_done(key, results[key])
                submit_ready()
            if waiting:
                raise ExecutorError(f"tasks {list(waiting)[:5]} depend on each other in a cycle")
        except BrokenProcessPool as exc:
            self.close()
            raise ExecutorError(f"a worker process died ({exc}); rerun to resume from the "
                                "finished tasks") from exc
        finally:
            for future in running:
                future.cancel()
            if running:
                wait(running)
        return results

    def close(self) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None
