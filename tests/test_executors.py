"""Executors: task graphs in dependency order, errors, and the same outputs from serial,
processes and Dask LocalCluster runs of the pipeline (and with a Dask worker killed)."""

from __future__ import annotations

import json
import os
import signal
import threading
from pathlib import Path

import numpy as np
import pytest

from surgrecon_cli import errors
from surgrecon_cli.config import Config, RunConfig, load_config
from surgrecon_cli.errors import ConfigError
from surgrecon_cli.executors import (
    ExecutorError,
    Task,
    check_graph,
    make_executor,
    run_graph,
    topological_order,
)
from surgrecon_cli.io.run.folder import RunFolder
from surgrecon_cli.pipeline import run_pipeline
from surgrecon_cli.stages.classify import run_classify
from surgrecon_cli.stages.register import base_frame, tracks_locked

KINDS = ("serial", "processes", "dask")


@pytest.fixture(scope="module", params=KINDS)
def executor(request):
    ex = make_executor(RunConfig(executor=request.param, workers=2))
    yield ex
    ex.close()


def _chain(tmp_path: Path) -> list[Task]:
    """a writes a file, b (after a) reads it back, c (after b) appends to it."""
    f = tmp_path / "chain.txt"
    return [Task("c", Path.read_text, (f,), deps=("b",)),
            Task("b", Path.write_text, (f, "ab"), deps=("a",)),
            Task("a", Path.write_text, (f, "a"))]


def test_graph_runs_in_dependency_order_on_every_executor(executor, tmp_path):
    seen: list[str] = []
    results = executor.run(_chain(tmp_path), on_done=lambda key, _v: seen.append(key))
    assert seen == ["a", "b", "c"]  # each waits for the one before it
    assert results == {"a": 1, "b": 2, "c": "ab"}


def test_independent_tasks_all_complete(executor):
    tasks = [Task(str(i), pow, (i, 2)) for i in range(20)]
    assert executor.run(tasks) == {str(i): i * i for i in range(20)}


def test_failing_task_raises_its_error(executor, tmp_path):
    tasks = [Task("ok", pow, (2, 3)), Task("bad", Path.read_text, (tmp_path / "missing",))]
    with pytest.raises(FileNotFoundError):
        executor.run(tasks)


def test_graph_errors_are_named():
    with pytest.raises(ExecutorError, match="twice"):
        list(topological_order([Task("a", pow, (1, 1)), Task("a", pow, (1, 1))]))
    with pytest.raises(ExecutorError, match="unknown"):
        list(topological_order([Task("a", pow, (1, 1), deps=("z",))]))
    with pytest.raises(ExecutorError, match=r"cycle: '(a' -> 'b' -> 'a|b' -> 'a' -> 'b)'$"):
        list(topological_order([Task("a", pow, (1, 1), deps=("b",)),
                                Task("b", pow, (1, 1), deps=("a",)), Task("c", pow, (1, 1))]))
    with pytest.raises(ExecutorError, match="cycle: 'a' -> 'a'"):
        check_graph([Task("a", pow, (1, 1), deps=("a",))])


def test_executor_error_lives_in_errors_and_is_re_exported():
    assert ExecutorError is errors.ExecutorError and issubclass(ExecutorError,
                                                                 errors.SurgReconError)


def test_graph_order_is_the_given_order_where_dependencies_allow():
    tasks = [Task("d", pow, (1, 1), deps=("b", "b")), Task("c", pow, (1, 1)),
             Task("b", pow, (1, 1), deps=("a",)), Task("a", pow, (1, 1))]
    graph = check_graph(tasks)
    assert [t.key for t in graph.order] == ["c", "a", "b", "d"]
    assert graph.dependants == {"d": (), "c": (), "b": ("d",), "a": ("b",)}
    assert graph.rank == {"d": 1, "c": 1, "b": 2, "a": 3}


class _Future:
    """A finished future of the fake engine below: fn(*args) already called."""

    def __init__(self, task):
        try:
            self.value, self.error = task.fn(*task.args), None
        except Exception as exc:
            self.value, self.error = None, exc

    def result(self):
        if self.error is not None:
            raise self.error
        return self.value

    def exception(self):
        return self.error

    def cancelled(self):
        return False

    def cancel(self):
        return False


def test_driver_sends_the_longest_path_first_and_fills_free_slots_before_bookkeeping():
    """A chain a -> b -> c and three independent tasks, on one slot: the links with tasks
    after them go first (rank 3, then 2), the rest (rank 1) in the order given; the driver
    submits the next task before it calls on_done for the finished one."""
    tasks = [Task("x", pow, (1, 1)), Task("y", pow, (2, 1)), Task("a", pow, (3, 1)),
             Task("b", pow, (4, 1), deps=("a",)), Task("z", pow, (5, 1)),
             Task("c", pow, (6, 1), deps=("b",))]
    events: list[str] = []

    def submit(task, priority):
        events.append(f"submit {task.key} {priority}")
        return _Future(task)

    results = run_graph(tasks, submit, lambda futures: futures[:1],
                        on_done=lambda key, _v: events.append(f"done {key}"), slots=1)
    assert results == {"x": 1, "y": 2, "a": 3, "b": 4, "z": 5, "c": 6}
    assert [e for e in events if e.startswith("submit")] == [
        "submit a 3", "submit b 2", "submit x 1", "submit y 1", "submit z 1", "submit c 1"]
    # Bookkeeping of a finished task comes after the next task is on its way.
    assert events.index("submit b 2") < events.index("done a")
    assert events[-1] == "done c"


def test_a_failure_keeps_the_bookkeeping_of_the_tasks_that_finished_with_it():
    """Two tasks finish in one batch, one of them failing: on_done still records the other
    (e.g. a registered frame in run.json), and the failure is raised."""
    seen: list[str] = []
    tasks = [Task("ok", pow, (2, 3)), Task("bad", int, ("x",)), Task("later", pow, (1, 1),
                                                                    deps=("ok",))]
    with pytest.raises(ValueError):
        run_graph(tasks, lambda task, _priority: _Future(task), lambda futures: futures,
                  on_done=lambda key, _v: seen.append(key))
    assert seen == ["ok"]


def test_graph_order_is_stable_and_linear_in_a_long_chain():
    """5,000 frames re-based every 2 frames (the register stage's graph), and every frame
    followed by one more task: dependencies first, ranks count the longest path."""
    tasks = [Task(str(k), pow, (k, 1), (str(base_frame(k, 2)),) if base_frame(k, 2) else ())
             for k in range(1, 5001)]
    tasks += [Task(f"after-{k}", pow, (k, 1), (str(k),)) for k in range(1, 5001)]
    graph = check_graph(tasks)
    place = {task.key: i for i, task in enumerate(graph.order)}
    assert all(place[d] < place[t.key] for t in tasks for d in t.deps)
    # 2, 4, ..., 4998, then 4999 or 5000, then its follower
    assert graph.rank["2"] == 2501
    assert graph.rank["1"] == 2 and graph.rank["after-1"] == 1
    assert [t.key for t in graph.order[:3]] == ["1", "2", "3"]


def test_config_rejects_unknown_executor_and_scheduler_without_dask():
    with pytest.raises(ConfigError, match=r"run\.executor"):
        load_config(overrides=["run.executor=threads"])
    with pytest.raises(ConfigError, match=r"run\.scheduler"):
        load_config(overrides=["run.scheduler=tcp://127.0.0.1:8786"])


def test_frames_depend_only_on_their_base():
    assert [base_frame(k, 2) for k in range(1, 8)] == [0, 0, 2, 2, 4, 4, 6]
    assert [base_frame(k, 0) for k in range(1, 5)] == [0, 0, 0, 0]


@pytest.mark.parametrize("every", [0, 1, 2, 3])
def test_frames_some_later_frame_starts_from_keep_the_template_lock(every: int):
    """A frame's tracks go unlocked only where they cannot carry drift on: the frame is one
    step from its base and no later frame's base (a failed base: two steps, locked)."""
    later_bases = {base_frame(j, every) for j in range(1, 40)}
    for k in range(1, 30):
        base = base_frame(k, every)
        assert tracks_locked(k, base, every) == (k in later_bases or k - 1 != base), k
    assert tracks_locked(3, 0, 2)  # frame 2 failed: frame 3 is tracked from frame 0


# ---- the pipeline on every executor ---------------------------------------------------
def _outputs(run_dir: Path) -> dict[str, np.ndarray | bytes]:
    """Everything a run computes: cloud bytes, registration and label arrays, evaluation."""
    out: dict[str, np.ndarray | bytes] = {}
    for ply in sorted((run_dir / "clouds").glob("*.ply")):
        out[f"clouds/{ply.name}"] = ply.read_bytes()
    for npz in [*sorted((run_dir / "registration").glob("*.npz")),
                run_dir / "classify" / "labels.npz"]:
        with np.load(npz) as z:
            for key in z.files:
                if not key.startswith("seconds"):  # wall times differ by nature
                    out[f"{npz.parent.name}/{npz.name}:{key}"] = z[key]
    evaluation = json.loads((run_dir / "metrics" / "evaluation.json").read_text())
    evaluation["ground_truth"].pop("path")  # where the file was, not what it holds
    out["evaluation"] = json.dumps(evaluation).encode()
    return out


def _assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], bytes):
            assert a[key] == b[key], key
        else:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["processes", "dask"])
def test_pipeline_outputs_identical_across_executors(kind, pipeline_run, pipeline_log,
                                                     tmp_path):
    reference, _ = pipeline_run  # serial (the default)
    config = load_config(overrides=[f"run.executor={kind}", "run.workers=2"])
    result = run_pipeline(pipeline_log, tmp_path / kind, config)
    assert result.actions["register"] == "ran"
    assert len(list((tmp_path / kind / "clouds").glob("*.ply"))) == 6
    _assert_same(_outputs(reference), _outputs(tmp_path / kind))


def test_frames_classified_with_register_equal_the_classify_stage_alone(pipeline_run,
                                                                       copy_run):
    """The pipeline classifies frames as they are registered; `surgrecon classify` on the
    same registration, all frames at once, writes the same labels and clouds."""
    reference, _ = pipeline_run
    info = RunFolder(reference).stage("classify")
    assert info["classified_with_register"] == 5  # frames 1..5 of the 6-frame log
    before = _outputs(reference)
    (copy_run / "classify" / "labels.npz").unlink()
    assert run_classify(copy_run, Config())["classified_with_register"] == 0
    _assert_same(before, _outputs(copy_run))


@pytest.mark.slow
def test_dask_worker_killed_mid_run_loses_nothing(pipeline_run, pipeline_log, tmp_path):
    """SIGKILL one LocalCluster worker during register: its tasks are rerun elsewhere and
    the outputs equal the serial run's."""
    reference, _ = pipeline_run
    ex = make_executor(RunConfig(executor="dask", workers=2))
    try:
        pids = list(ex.client.run(os.getpid).values())
        killed = threading.Event()

        def on_progress(stage: str, _fraction: float) -> None:
            if stage == "register" and not killed.is_set():
                killed.set()
                os.kill(pids[0], signal.SIGKILL)

        run_pipeline(pipeline_log, tmp_path / "run", Config(), on_progress=on_progress,
                     executor=ex)
        assert killed.is_set()
    finally:
        ex.close()
    _assert_same(_outputs(reference), _outputs(tmp_path / "run"))


@pytest.mark.slow
def test_run_many_logs_one_folder_each_and_a_corrupt_log_fails_alone(pipeline_run,
                                                                      pipeline_log, tmp_path):
    """`surgrecon run A B C -o RUNS/` over 2 worker processes: A and B (the same recording)
    complete with the outputs of a single run; C (truncated) fails with one line naming it,
    without stopping the others; the exit code says something failed."""
    import shutil

    from surgrecon_cli.cli.main import main

    logs = tmp_path / "logs"
    logs.mkdir()
    for name in ("a", "b"):
        shutil.copy(pipeline_log, logs / f"{name}.mcap")
        shutil.copy(pipeline_log.with_suffix(".gt.npz"), logs / f"{name}.gt.npz")
    data = pipeline_log.read_bytes()
    (logs / "c.mcap").write_bytes(data[: len(data) // 3])
    code = main(["run", str(logs / "a.mcap"), str(logs / "b.mcap"), str(logs / "c.mcap"),
                 "-o", str(tmp_path / "runs"), "--executor", "processes", "--workers", "2",
                 "-q"])
    assert code == 2
    reference = _outputs(pipeline_run[0])
    for name in ("a", "b"):
        _assert_same(reference, _outputs(tmp_path / "runs" / name))
        assert (tmp_path / "runs" / name / "report.html").is_file()
    assert not (tmp_path / "runs" / "c" / "report.html").exists()


def _children(pid: int) -> list[int]:
    """Process ids whose parent is `pid` (from /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


@pytest.mark.slow
def test_driver_killed_during_parallel_register_resumes_and_leaves_no_workers(
        pipeline_run, pipeline_log, tmp_path):
    """SIGKILL only the driver of `surgrecon run --executor processes` once frames are
    registered: its workers exit by themselves, and the rerun completes with the serial
    run's outputs."""
    import subprocess
    import sys
    import time

    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-c", "import sys; from surgrecon_cli.cli.main import main; "
           "sys.exit(main())", "run", str(pipeline_log), "-o", str(run_dir), "-q",
           "--executor", "processes", "--workers", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 600  # only a hung run reaches it, however loaded the machine
    while not list((run_dir / "registration").glob("*.npz")):
        assert proc.poll() is None and time.monotonic() < deadline, "no frame registered"
        time.sleep(0.05)
    workers = _children(proc.pid)
    assert workers, "the pool's workers should be running"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    while any(Path(f"/proc/{w}").exists() for w in workers):
        assert time.monotonic() < deadline, f"orphaned workers {workers} still alive"
        time.sleep(0.1)
    assert subprocess.run(cmd, check=False).returncode == 0
    _assert_same(_outputs(pipeline_run[0]), _outputs(run_dir))
