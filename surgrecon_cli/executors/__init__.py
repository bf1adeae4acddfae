"""Executors: where the tasks of a run are computed (per camera, camera pair,
frame and report figure).

A stage describes its work as a small task graph — `Task`s with keys and dependencies —
and hands it to an executor:
- `serial`: in this process, in dependency order (the reference);
- `processes`: a local pool of worker processes (`concurrent.futures`, spawn);
- `dask`: Dask distributed, on a `LocalCluster` or on the scheduler at `--scheduler`.

A task's result depends only on its arguments and the files it reads (per-frame tasks
read their inputs from the run folder and write their outputs atomically), never on which
process or machine ran it: every executor gives the same outputs. Arguments and return
values travel between driver and workers, so they stay modest: a frame's summary or
labels, one camera's features, one figure's PNG. A value reaches the driver through
`on_done(key, value)`, called in the driver as tasks complete. Workers run numerical
libraries single-threaded (`single_threaded`) so that results do not depend on thread
counts and workers do not oversubscribe the cores.
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from graphlib import CycleError, TopologicalSorter
from typing import TYPE_CHECKING, Any, Protocol

from ..config import RunConfig
from ..errors import ExecutorError  # re-exported: raised by every executor

if TYPE_CHECKING:
    from ..core.template.build import MapCalls

_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass(frozen=True)
class Task:
    """One unit of work: `fn(*args)`, run after every task named in `deps` succeeded.

    fn must be a module-level function or a `functools.partial` of one (pickled by
    reference for worker processes); args must be picklable (paths, ints, frozen config
    dataclasses, numpy arrays)."""

    key: str
    fn: Callable[..., Any]
    args: tuple[Any, ...] = ()
    deps: tuple[str, ...] = field(default=())


OnDone = Callable[[str, Any], None]


class Executor(Protocol):
    """Runs task graphs; `run` may be called from several driver threads at once."""

    kind: str
    workers: int

    def run(self, tasks: Sequence[Task], on_done: OnDone | None = None) -> dict[str, Any]:
        """Run every task (respecting deps); return {key: value}. The first failing task's
        exception is raised after the other running tasks are cancelled or finished."""
        ...

    def close(self) -> None:
        """Release workers (idempotent)."""
        ...


@dataclass(frozen=True)
class Graph:
    """A checked task graph: tasks in a topological order (stable: a task comes as early
    as its dependencies allow, in the order given), the tasks that depend on each one,
    and each task's rank, the number of tasks on the longest path from it to the end."""

    order: tuple[Task, ...]
    dependants: dict[str, tuple[str, ...]]
    rank: dict[str, int]


def check_graph(tasks: Sequence[Task]) -> Graph:
    """The `Graph` of `tasks`; ExecutorError on a duplicate key, a dependency outside the
    graph or a cycle (`graphlib`), before anything runs."""
    by_key: dict[str, Task] = {}
    for task in tasks:
        if task.key in by_key:
            raise ExecutorError(f"task {task.key!r} appears twice in one graph")
        by_key[task.key] = task
    dependants: dict[str, list[str]] = {key: [] for key in by_key}
    sorter: TopologicalSorter[str] = TopologicalSorter()
    for task in tasks:
        unknown = [d for d in task.deps if d not in by_key]
        if unknown:
            raise ExecutorError(f"task {task.key!r} depends on unknown task(s) {unknown}")
        deps = tuple(dict.fromkeys(task.deps))
        for dep in deps:
            dependants[dep].append(task.key)
        sorter.add(task.key, *deps)
    try:
        sorter.prepare()
    except CycleError as exc:
        cycle = exc.args[1]  # [a, b, ..., a]
        shown = " -> ".join(map(repr, cycle[:8])) + (" -> ..." if len(cycle) > 8 else "")
        raise ExecutorError(f"tasks depend on each other in a cycle: {shown}") from exc
    position = {key: i for i, key in enumerate(by_key)}
    ready = [position[k] for k in sorter.get_ready()]
    heapq.heapify(ready)
    keys = list(by_key)
    order: list[Task] = []
    while ready:  # the earliest given of the ready tasks next: a stable order
        key = keys[heapq.heappop(ready)]
        order.append(by_key[key])
        sorter.done(key)
        for child in sorter.get_ready():
            heapq.heappush(ready, position[child])
    rank: dict[str, int] = {}
    for task in reversed(order):
        rank[task.key] = 1 + max((rank[c] for c in dependants[task.key]), default=0)
    return Graph(tuple(order), {k: tuple(v) for k, v in dependants.items()}, rank)


def topological_order(tasks: Sequence[Task]) -> list[Task]:
    """Tasks so that every task comes after its dependencies (stable for the rest);
    ExecutorError on a cycle (before anything runs)."""
    return list(check_graph(tasks).order)


def run_graph(tasks: Sequence[Task], submit: Callable[[Task, int], Any],
              wait_any: Callable[[list[Any]], Iterable[Any]],
              on_done: OnDone | None = None, slots: int | None = None,
              gather: Callable[[list[Any]], list[Any]] | None = None) -> dict[str, Any]:
    """The driver loop of the parallel executors: submit the tasks whose dependencies have
    finished, collect results as futures complete, repeat.

    `submit(task, priority)` returns a future (`.result()`, `.exception()`, `.cancel()`);
    `wait_any(futures)` blocks until at least one is done and returns the done ones;
    `gather(futures)` gives their results in one call (default: each `.result()`). Ready
    tasks go out longest path first (`Graph.rank`, also passed as the priority), so a
    dependency chain is never kept waiting behind tasks that could run later; with
    `slots`, at most that many tasks of this graph are in flight (an engine's own queue
    would otherwise run them first come, first served). Dependencies are kept here, not
    handed to the engine, so a dependent task may run on any worker (engines that place a
    task where its dependency ran would serialise a chain's side branches). New tasks are
    submitted before `on_done` runs for the finished ones, so the driver's bookkeeping
    never keeps a worker idle. On the first error, `on_done` still runs for every task
    that succeeded, the tasks not yet started are cancelled and the error is raised."""
    graph = check_graph(tasks)  # keys, dependencies and cycles, before anything runs
    by_key = {task.key: task for task in graph.order}
    position = {task.key: i for i, task in enumerate(graph.order)}
    missing = {task.key: len(set(task.deps)) for task in graph.order}
    ready = [(-graph.rank[k], position[k], k) for k, n in missing.items() if n == 0]
    heapq.heapify(ready)
    results: dict[str, Any] = {}
    running: dict[Any, str] = {}
    finished: list[str] = []

    def settle(keys: list[str]) -> None:
        if on_done is not None:
            for key in keys:
                on_done(key, results[key])

    try:
        while True:
            try:
                while ready and (slots is None or len(running) < slots):
                    key = heapq.heappop(ready)[2]
                    running[submit(by_key[key], graph.rank[key])] = key
            finally:
                settle(finished)
            if not running:
                return results
            done = list(wait_any(list(running)))
            finished = [running.pop(future) for future in done]
            try:
                values = gather(done) if gather is not None else [f.result() for f in done]
            except BaseException:
                # Keep what the other tasks of the batch finished (e.g. frames that run.json
                # then records as done), then raise the error.
                ok = [(k, f) for k, f in zip(finished, done, strict=True)
                      if not f.cancelled() and f.exception() is None]
                results.update((k, f.result()) for k, f in ok)
                settle([k for k, _ in ok])
                raise
            for key, value in zip(finished, values, strict=True):
                results[key] = value
                for child in graph.dependants[key]:
                    missing[child] -= 1
                    if missing[child] == 0:
                        heapq.heappush(ready, (-graph.rank[child], position[child], child))
    finally:
        for future in running:
            future.cancel()


_LIMITED = {"done": False}


def single_threaded() -> None:
    """Limit BLAS/OpenMP and OpenCV to one thread in this process (idempotent)."""
    if _LIMITED["done"]:
        return
    for name in _THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    import cv2
    import numpy  # noqa: F401  (load the BLAS before limiting it)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    cv2.setNumThreads(1)
    _LIMITED["done"] = True


def mapper(executor: Executor) -> MapCalls:
    """A `map_calls(fn, calls)` for core functions that take one (e.g. `build_template`):
    each `fn(*args)` is an independent task on `executor`; results come in call order."""

    def map_calls(fn: Callable[..., Any], calls: Sequence[tuple[Any, ...]]) -> list[Any]:
        name = getattr(fn, "__name__", "call")
        keys = [f"{name}-{i}" for i in range(len(calls))]
        done = executor.run([Task(key, fn, args) for key, args in zip(keys, calls, strict=True)])
        return [done[key] for key in keys]

    return map_calls


def call_task(fn: Callable[..., Any], args: tuple[Any, ...]) -> Any:
    """What a worker runs for a task: single-threaded numerics, then `fn(*args)`."""
    single_threaded()
    return fn(*args)


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return max(os.cpu_count() or 1, 1)


def preload(modules: Sequence[str]) -> None:
    """Worker start-up: single-threaded numerics, then import `modules` (the task
    functions' modules), so that the first tasks do not pay for imports."""
    import importlib

    single_threaded()
    for name in modules:
        importlib.import_module(name)


def make_executor(cfg: RunConfig, modules: Sequence[str] = ()) -> Executor:
    """The executor the `[run]` config section asks for (workers 0 = one per core).
    Parallel executors start their workers now and have them import `modules` in the
    background, while the driver goes on (e.g. with ingest and the template)."""
    workers = cfg.workers or default_workers()
    if cfg.executor == "serial":
        from .serial import SerialExecutor

        return SerialExecutor()
    if cfg.executor == "processes":
        from .processes import ProcessExecutor

        return ProcessExecutor(workers, tuple(modules))
    from .dask import DaskExecutor

    return DaskExecutor(workers, cfg.scheduler, cfg.retries, tuple(modules))
