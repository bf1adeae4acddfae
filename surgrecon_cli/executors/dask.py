"""The Dask executor: tasks on Dask distributed workers (optional extra `surgrecon[dask]`).

Without a scheduler address a `LocalCluster` of `workers` single-threaded worker processes
is started for the executor's lifetime; with one (`--scheduler tcp://host:8786`) the
tasks go to that cluster's workers, which must have surgrecon installed and see the run
folder at the same path (a shared filesystem). Tasks are submitted as their dependencies
finish (`run_graph`: Dask would otherwise pin a chain's side branches to the worker that
ran the dependency), with the length of their longest path as the priority; a failed or
lost task is retried `retries` times without touching the others; progress is driven by
completed futures.
"""

from __future__ import annotations

import importlib.util
import logging
import threading
import uuid
from collections.abc import Sequence
from typing import Any

from . import ExecutorError, OnDone, Task, call_task, preload, run_graph

logger = logging.getLogger(__name__)
_LOCAL_CLUSTER = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                  "distributed.worker.profile.enabled": False,
                  "distributed.admin.system-monitor.gil.enabled": False}


class DaskExecutor:
    """A Dask `Client` on a LocalCluster or on the scheduler at `scheduler`.

    A scheduler address is connected to at once (a wrong address fails before any work);
    a LocalCluster starts in the background (~1 s on 2 cores) while the driver goes on
    (e.g. with ingest), and the first graph waits for it."""

    kind = "dask"

    def __init__(self, workers: int, scheduler: str = "", retries: int = 2,
                 modules: tuple[str, ...] = ()):
        if importlib.util.find_spec("distributed") is None:  # imported where it is used
            raise ExecutorError("--executor dask needs Dask distributed: pip install "
                                "'surgrecon[dask]'")
        self.retries = retries
        self.workers = workers
        self._cluster: Any = None
        self._client: Any = None
        self._failure: BaseException | None = None
        self._starting: threading.Thread | None = None
        if scheduler:
            self._connect(scheduler, modules)
        else:
            self._starting = threading.Thread(target=self._start_local, args=(workers, modules),
                                              name="dask-local-cluster", daemon=True)
            self._starting.start()

    def _connect(self, scheduler: str, modules: tuple[str, ...]) -> None:
        from distributed import Client

        try:
            self._client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise ExecutorError(f"cannot reach the Dask scheduler {scheduler!r}: {exc}") from exc
        self._warm_up(modules)

    def _start_local(self, workers: int, modules: tuple[str, ...]) -> None:
        import dask
        from distributed import Client, LocalCluster

        try:
            # Measured on the pipeline's tasks: glibc's trim threshold, which Dask sets for
            # its workers, makes them ~15 % slower (large numpy temporaries are then mapped
            # and unmapped each time); the statistical profiler and the GIL monitor,
            # sampling every 10 ms and 1 ms, cost ~5 % more.
            with dask.config.set(_LOCAL_CLUSTER):
                self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1,
                                             processes=True, dashboard_address=":0",
                                             silence_logs=logging.WARNING)
            self._client = Client(self._cluster)
            logger.info("Dask LocalCluster: %d workers, dashboard %s", workers,
                        self._client.dashboard_link)
            self._warm_up(modules)
        except Exception as exc:  # reported by the first graph (`_ready`)
            self._failure = exc

    def _warm_up(self, modules: tuple[str, ...]) -> None:
        addresses = list(self._client.scheduler_info().get("workers", {}))
        self.workers = max(len(addresses), 1)
        # Held so that the start-up imports are not cancelled as unreferenced futures.
        self._warm = [self._client.submit(preload, modules, workers=[address], pure=False)
                      for address in addresses]

    def _ready(self) -> Any:
        """The client, once the LocalCluster (if any) has started (several driver threads
        may wait here at once: joining a finished thread returns at once)."""
        if self._starting is not None:
            self._starting.join()
        if self._failure is not None:
            raise ExecutorError(f"the Dask LocalCluster did not start: "
                                f"{self._failure}") from self._failure
        if self._client is None:
            raise ExecutorError("the Dask executor is closed")
        return self._client

    @property
    def client(self) -> Any:
        """The `distributed.Client` (e.g. to inspect or restart workers)."""
        return self._ready()

    def run(self, tasks: Sequence[Task], on_done: OnDone | None = None) -> dict[str, Any]:
        from distributed import wait

        client = self._ready()
        run_id = uuid.uuid4().hex[:8]

        def submit(task: Task, priority: int) -> Any:
            return client.submit(call_task, task.fn, task.args, key=f"{task.key}-{run_id}",
                                 retries=self.retries, priority=priority, pure=False)

        return run_graph(tasks, submit, lambda fs: wait(fs, return_when="FIRST_COMPLETED").done,
                         on_done, gather=client.gather)

    def close(self) -> None:
        if self._starting is not None:
            self._starting.join()
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
