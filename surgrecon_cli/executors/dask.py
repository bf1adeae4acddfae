"""The Dask executor: tasks on Dask distributed workers (optional extra `surgrecon[dask]`).

Without a scheduler address a `LocalCluster` of `workers` single-threaded worker processes
is started for the executor's lifetime; with one (`--scheduler tcp://host:8786`) the
tasks go to that cluster's workers, which must have surgrecon installed and see the run
folder at the same path (a shared filesystem). The whole graph is submitted at once, each
task with its dependencies' futures as arguments, so Dask itself orders the chain; a
failed or lost task is retried `retries` times without touching the others; progress is
driven by completed futures.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Sequence
from typing import Any

from . import ExecutorError, OnDone, Task, call_task, topological_order

logger = logging.getLogger(__name__)


class DaskExecutor:
    """A Dask `Client` on a LocalCluster or on the scheduler at `scheduler`."""

    kind = "dask"

    def __init__(self, workers: int, scheduler: str = "", retries: int = 2):
        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:
            raise ExecutorError("--executor dask needs Dask distributed: pip install "
                                "'surgrecon[dask]'") from exc
        self.retries = retries
        self._cluster = None
        try:
            if scheduler:
                self._client = Client(scheduler, timeout="20s")
            else:
                self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1,
                                             processes=True, dashboard_address=":0",
                                             silence_logs=logging.WARNING)
                self._client = Client(self._cluster)
                logger.info("Dask LocalCluster: %d workers, dashboard %s", workers,
                            self._client.dashboard_link)
        except (OSError, TimeoutError) as exc:
            raise ExecutorError(f"cannot reach the Dask scheduler {scheduler!r}: {exc}") from exc
        self.workers = max(len(self._client.scheduler_info().get("workers", {})), 1)

    @property
    def client(self) -> Any:
        """The `distributed.Client` (e.g. to inspect or restart workers)."""
        return self._client

    def run(self, tasks: Sequence[Task], on_done: OnDone | None = None) -> dict[str, Any]:
        from distributed import as_completed

        run_id = uuid.uuid4().hex[:8]
        futures: dict[str, Any] = {}
        for task in topological_order(tasks):
            deps = [futures[d] for d in task.deps]
            futures[task.key] = self._client.submit(
                call_task, task.fn, task.args, *deps, key=f"{task.key}-{run_id}",
                retries=self.retries, pure=False)
        keys = {future.key: key for key, future in futures.items()}
        results: dict[str, Any] = {}
        try:
            for future in as_completed(list(futures.values())):
                key = keys[future.key]
                results[key] = future.result()  # raises the task's exception
                if on_done is not None:
                    on_done(key, results[key])
        finally:
            pending = [f for f in futures.values() if not f.done()]
            if pending:
                self._client.cancel(pending)
        return results

    def close(self) -> None:
        if getattr(self, "_client", None) is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
