"""Kill and resume: `surgrecon run` killed (SIGKILL) at seeded random moments spread over
every stage, then rerun to completion, ends with the same clouds, labels and metrics as an
uninterrupted run; and at every kill point the run folder is consistent: no truncated file
under a final name, run.json claims no stage done (and no frame registered) whose outputs
are missing, and a resumed register stage never forgets the frames it had recorded.

The uninterrupted run's stage timings (run.json `pipeline.seconds`, plus the process
start-up) give each stage's duration. Each trial kills a fresh run at a random moment: inside
one stage (a random offset into its duration after run.json shows it running, so that the
kills cover every stage however fast the machine), or anywhere in the run's duration. Two
trials kill after some frames are registered, then kill the resumed run as soon as its
register stage rewrites its run.json entry or its progress record (where a restarting
stage used to forget its frames). Two lanes run trials in parallel, one per core.
"""

from __future__ import annotations

import csv
import io
import json
import os
import random
import re
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.io.run.folder import FrameProgress, RunFolder
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.io.run.ply import read_ply
from surgrecon_cli.pipeline import STAGES

SEED = 7
LANES = 2
SURGRECON = [sys.executable, "-c",
             "import sys; from surgrecon_cli.cli.main import main; sys.exit(main())"]
TIMING_KEYS = ("seconds",)  # metrics keys / columns starting with these are wall times
HANG_GUARD_S = 600  # wall-clock limit that only a hung run reaches, however loaded the machine


def start_run(log: Path, run: Path) -> subprocess.Popen:
    return subprocess.Popen([*SURGRECON, "run", str(log), "-o", str(run), "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)


def run_to_end(log: Path, run: Path) -> tuple[float, str]:
    start = time.perf_counter()
    proc = start_run(log, run)
    out, err = proc.communicate(timeout=HANG_GUARD_S)
    assert proc.returncode == 0, err.decode()
    return time.perf_counter() - start, out.decode()


def registered(run: Path) -> list[int]:
    """The frames the register stage's progress record says are registered."""
    return sorted(FrameProgress(RunLayout(run).register_progress).read())


def stage_entry(run: Path, stage: str) -> dict | None:
    try:
        return json.loads((run / "run.json").read_text(encoding="utf-8"))["stages"].get(stage)
    except (OSError, ValueError, KeyError):
        return None


def run_and_kill(log: Path, run: Path, when: Callable[[float], bool],
                 poll: float = 0.005) -> float | None:
    """Start a run, poll `when(seconds since start)` every `poll` s and SIGKILL the run when
    it says so; returns the kill time, None if the run finished first."""
    start = time.perf_counter()
    proc = start_run(log, run)
    while proc.poll() is None:
        elapsed = time.perf_counter() - start
        if when(elapsed):
            os.killpg(proc.pid, signal.SIGKILL)
            _, err = proc.communicate()
            text = err.decode(errors="replace")
            assert "error" not in text and "Traceback" not in text, text[-500:]
            return elapsed
        time.sleep(poll)
    assert proc.returncode == 0, proc.stderr.read().decode() if proc.stderr else ""
    return None


def after_start_of(run: Path, stage: str, offset: float) -> Callable[[float], bool]:
    """Kill `offset` s after run.json first shows `stage` running ("start-up": after the
    process started)."""
    seen: list[float] = []

    def when(elapsed: float) -> bool:
        if not seen and (stage == "start-up" or (stage_entry(run, stage) or {}).get(
                "status") == "running"):
            seen.append(elapsed)
        return bool(seen) and elapsed >= seen[0] + offset
    return when


def when_register_changes(run: Path) -> Callable[[float], bool]:
    """Kill as soon as the register entry of run.json or its progress record differs from
    now (the resumed register stage rewrites its record, marks itself running, or records a
    frame)."""
    before = stage_entry(run, "register"), registered(run)
    return lambda _: (stage_entry(run, "register"), registered(run)) != before


# ----------------------------------------------------------------------------- checks
def _final_files(run: Path) -> list[Path]:
    """Files under final names (no hidden path component: staging folders, temp files)."""
    return [p for p in run.rglob("*") if p.is_file()
            and not any(part.startswith(".") for part in p.relative_to(run).parts)]


def _load(path: Path) -> None:
    """Raise unless the file is complete and parses by its type."""
    suffix = path.suffix
    if suffix == ".ply":
        read_ply(path)
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            for key in z.files:
                z[key]
    elif suffix == ".json":
        json.loads(path.read_text(encoding="utf-8"))
    elif suffix == ".jsonl":  # append-only: a line cut by the kill is ignored when read
        FrameProgress(path).read()
    elif suffix == ".toml":
        tomllib.loads(path.read_text(encoding="utf-8"))
    elif suffix == ".csv":
        rows = list(csv.reader(io.StringIO(path.read_text(encoding="utf-8"))))
        assert rows and all(len(r) == len(rows[0]) for r in rows), path
    elif suffix in (".png", ".jpg"):
        assert cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED) is not None, path
    elif suffix == ".html":
        assert path.read_text(encoding="utf-8").rstrip().endswith("</html>"), path
    else:
        raise AssertionError(f"unexpected file {path}")


def _outputs(run: Path, n_frames: int) -> dict[str, list[Path]]:
    """What each stage's "done" promises."""
    reg = [run / "registration" / f"{k:06d}.npz" for k in range(1, n_frames)]
    return {
        "ingest": [run / "ingest" / "frames.npz", run / "ingest" / "cameras.json"],
        "build-template": [run / "template.ply", run / "template" / "observations.npz"],
        "register": reg,
        "classify": [run / "classify" / "labels.npz",
                     *(run / "clouds" / f"{k:06d}.ply" for k in range(n_frames))],
        "measure": [run / "measure" / "deformation.npz", run / "metrics" / "deformation.csv"],
        "evaluate": [run / "metrics" / "evaluation.json",
                     run / "metrics" / "evaluation_errors.npz"],
        "report": [run / "report.html", run / "metrics" / "frames.csv",
                   run / "metrics" / "summary.json"],
    }


def check_consistent(run: Path, n_frames: int) -> tuple[str, list[int]]:
    """Assert the killed run folder is consistent; returns the stage it was in (first not
    done, "start-up" before run.json) and the frames run.json says are registered."""
    for path in _final_files(run):
        try:
            _load(path)
        except Exception as exc:
            raise AssertionError(f"{path} is broken after a kill: {exc}") from exc
    if not (run / "run.json").exists():
        return "start-up", []
    meta = RunFolder(run).read()
    stages = meta.get("stages", {})
    outputs = _outputs(run, n_frames)
    for stage, entry in stages.items():
        if entry.get("status") == "done":
            missing = [str(p) for p in outputs[stage] if not p.is_file()]
            assert not missing, f"run.json says {stage} done, but {missing} are missing"
    if stages.get("ingest", {}).get("status") == "done":
        with np.load(run / "ingest" / "frames.npz") as z:
            paths = [p for p in z["image_paths"].ravel() if p]
        assert all((run / "ingest" / p).is_file() for p in paths)
    frames = registered(run) if "register" in stages else []
    for k in frames:
        path = run / "registration" / f"{k:06d}.npz"
        assert path.is_file(), f"run.json says frame {k} registered, {path} is missing"
    at = next((s for s in STAGES if stages.get(s, {}).get("status") != "done"), "finished")
    return at, frames


def _strip_timings(obj):
    if isinstance(obj, dict):
        return {k: _strip_timings(v) for k, v in obj.items() if not k.startswith(TIMING_KEYS)}
    if isinstance(obj, list):
        return [_strip_timings(v) for v in obj]
    return obj


def _npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files if not k.startswith(TIMING_KEYS)}


def assert_same_results(ref: Path, run: Path, n_frames: int) -> None:
    """Clouds, registration, labels and metrics equal (wall times aside)."""
    for k in range(n_frames):
        name = f"clouds/{k:06d}.ply"
        assert (run / name).read_bytes() == (ref / name).read_bytes(), name
    npz = [f"registration/{k:06d}.npz" for k in range(1, n_frames)]
    npz += ["classify/labels.npz", "template/observations.npz", "ingest/frames.npz",
            "metrics/evaluation_errors.npz"]
    for name in npz:
        a, b = _npz(ref / name), _npz(run / name)
        assert a.keys() == b.keys(), name
        for key in a:
            assert np.array_equal(a[key], b[key], equal_nan=a[key].dtype.kind == "f"), (name, key)
    assert (run / "template.ply").read_bytes() == (ref / "template.ply").read_bytes()
    for name in ("metrics/evaluation.json", "metrics/summary.json"):
        a = json.loads((ref / name).read_text(encoding="utf-8"))
        b = json.loads((run / name).read_text(encoding="utf-8"))
        assert _strip_timings(a) == _strip_timings(b), name
    rows = [list(csv.DictReader(io.StringIO((d / "metrics/frames.csv").read_text())))
            for d in (ref, run)]
    assert _strip_timings(rows[0]) == _strip_timings(rows[1])
    meta = RunFolder(run).read()
    assert all(meta["stages"][s]["status"] == "done" for s in STAGES), meta["stages"]
    leftovers = [p for p in run.rglob(".*") if p != RunLayout(run).lock_file]
    assert not leftovers, f"temporary files left behind: {leftovers[:5]}"


# ----------------------------------------------------------------------------- the test
def _windows(ref: Path, total: float) -> dict[str, tuple[float, float]]:
    """Each stage's (start, end) in s after the process started, from the reference run."""
    seconds = RunFolder(ref).read()["pipeline"]["seconds"]
    startup = max(total - sum(seconds.values()) - 0.1, 0.2)
    out, t = {"start-up": (0.0, startup)}, startup
    for stage in STAGES:
        out[stage] = (t, t + seconds[stage])
        t += seconds[stage]
    return out


def after_frames(run: Path, n: int) -> Callable[[float], bool]:
    """Kill once run.json records `n` registered frames."""
    return lambda _: len(registered(run)) >= n


def _schedule(windows: dict[str, tuple[float, float]], rng: random.Random, total: float,
              n_frames: int) -> list[list[tuple[str, float]]]:
    """Per trial, its kills as (kind, offset s or frame count): one in every stage (offset
    into it), four anywhere (offset from the start), and two that kill after some frames are
    registered, then as soon as the resumed register stage rewrites its run.json entry."""
    trials = [[(stage, rng.uniform(0, 0.8 * (b - a)))] for stage, (a, b) in windows.items()]
    trials += [[("anywhere", rng.uniform(0.2, total))] for _ in range(4)]
    trials += [[("register-frames", rng.randint(1, n_frames - 2)), ("register-restart", 0)]
               for _ in range(2)]
    return trials


def _trigger(run: Path, kind: str, offset: float) -> Callable[[float], bool]:
    if kind == "anywhere":
        return lambda elapsed: elapsed >= offset
    if kind == "register-frames":
        return after_frames(run, int(offset))
    if kind == "register-restart":
        return when_register_changes(run)
    return after_start_of(run, kind, offset)


@pytest.mark.slow
def test_kill_and_resume(pipeline_log: Path, tmp_path: Path):
    t0 = time.perf_counter()
    refs = [tmp_path / f"ref{i}" for i in range(LANES)]
    with ThreadPoolExecutor(LANES) as pool:  # timed under the same load as the trials
        totals = [t for t, _ in pool.map(lambda r: run_to_end(pipeline_log, r), refs)]
    ref, total = refs[0], float(np.mean(totals))
    n_frames = RunFolder(ref).read()["ingest"]["frames"]
    assert_same_results(ref, refs[1], n_frames)  # the pipeline is deterministic
    windows = _windows(ref, total)
    trials = _schedule(windows, random.Random(SEED), total, n_frames)

    def trial(k: int) -> list[tuple[str, float | None, str, list[int]]]:
        run = tmp_path / f"run{k:02d}"
        kills = []
        for kind, offset in trials[k]:
            at = run_and_kill(pipeline_log, run, _trigger(run, kind, offset),
                              poll=0.001 if kind == "register-restart" else 0.005)
            stage, frames = check_consistent(run, n_frames)
            if kills and kills[-1][2] == "register" and stage == "register":
                lost = set(kills[-1][3]) - set(frames)
                assert not lost, (f"run {k}: frames {sorted(lost)} forgotten by the resumed run: "
                                  f"{stage_entry(run, 'register')}")
            kills.append((kind, at, stage, frames))
        run_to_end(pipeline_log, run)
        assert_same_results(ref, run, n_frames)
        return kills

    with ThreadPoolExecutor(LANES) as pool:
        results = list(pool.map(trial, range(len(trials))))
    kills = [k for r in results for k in r]
    print(f"\nkill/resume: uninterrupted run {total:.1f} s; windows "
          + ", ".join(f"{s} {a:.2f}-{b:.2f}" for s, (a, b) in windows.items()))
    for k, r in enumerate(results):
        print(f"  trial {k:2d}: " + "; ".join(
            (f"{kind}: killed at {at:.2f} s in {stage}" if at is not None
             else f"{kind}: finished first") + (f" (frames {frames})" if frames else "")
            for kind, at, stage, frames in r))
    done = [k for k in kills if k[1] is not None]
    print(f"  {len(done)} kills, {time.perf_counter() - t0:.1f} s")
    assert len(done) >= 10
    # a stage of a few ms (classify, evaluate) can end between two polls: most, not all
    assert len({k[2] for k in done}) >= 5, "kills did not spread over the stages"


@pytest.mark.parametrize("leftover", [".run.json.k2j3h4ab.tmp", ".config.toml.x8b1qz_9.tmp"])
def test_killed_at_the_first_write(pipeline_log: Path, tmp_path: Path, leftover: str):
    """A run killed while writing its first file leaves only a temporary file: the folder
    is still usable (rarely hit by a timed kill, so set up here)."""
    run = tmp_path / "run"
    run.mkdir()
    (run / leftover).write_bytes(b'{"surgrecon": "0.')
    assert main(["ingest", str(pipeline_log), "-o", str(run), "-q"]) == 0
    assert RunFolder(run).is_done("ingest")
    (run / leftover).write_bytes(b"")
    RunFolder(run).mark_stage("ingest", "running")  # killed again, later
    assert main(["ingest", str(pipeline_log), "-o", str(run), "-q"]) == 0


@pytest.fixture(scope="module")
def interruptible_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`pipeline_log`'s rig over 16 frames: after the first registered frame, registering
    is left for a second or more, whatever the machine's load."""
    from surgrecon_cli.sim.scene import SimConfig
    from surgrecon_cli.sim.simulate import simulate

    out = tmp_path_factory.mktemp("interruptible_log") / "sim.mcap"
    simulate(out, SimConfig(cameras=6, frames=16, width=320, height=240))
    return out


def terminal_sigint() -> None:
    """In the child, before exec: SIGINT as a terminal's foreground program has it. A shell
    running a job in the background (`make test-slow &`, a CI runner's script) ignores
    SIGINT, the child inherits that, and Python then installs no KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["serial", "processes"])
def test_ctrl_c_keeps_registered_frames(interruptible_log: Path, tmp_path: Path,
                                        executor: str):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) during register keeps
    the frames recorded so far, as SIGKILL does; the rerun resumes from them."""
    run = tmp_path / "run"
    pipeline_log = interruptible_log
    proc = subprocess.Popen([*SURGRECON, "run", str(pipeline_log), "-o", str(run), "-q",
                             "--executor", executor, "--workers", "2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, preexec_fn=terminal_sigint)
    seen: list[int] = []
    deadline = time.perf_counter() + HANG_GUARD_S
    while proc.poll() is None and time.perf_counter() < deadline:
        seen = registered(run)
        if seen:
            os.killpg(proc.pid, signal.SIGINT)
            break
        time.sleep(0.01)
    _, err = proc.communicate(timeout=HANG_GUARD_S)
    if proc.returncode == 0:
        pytest.fail(f"the run exited 0 although Ctrl-C came after frames {seen}" if seen
                    else "the run finished before it could be interrupted")
    assert proc.returncode == 130, err.decode()
    entry = stage_entry(run, "register")
    assert entry["status"] == "failed" and "Ctrl-C" in entry["error"]
    assert set(seen) <= set(registered(run))
    out = subprocess.run([*SURGRECON, "run", str(pipeline_log), "-o", str(run)],
                         capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert out.returncode == 0, out.stderr
    assert re.search(r"register\s+resumed", out.stdout + out.stderr)
