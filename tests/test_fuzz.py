"""Fuzzed inputs: seeded mutations of tiny MCAP logs (`surgrecon ingest`) and PLY clouds
(`surgrecon register-pair`). Every case must end in exit 0 with a correct result, or exit 2
with exactly one `error: ...` line on stderr: never exit 3, a traceback, a hang or an
allocation of more than ~1 GB.

Cases are generated in memory from logs built with tests/synth_log.py (2 cameras, 64x48 px,
3 frames; ROS 2, ROS 1, Foxglove protobuf and JSON), written to tmp_path, and run by two
worker subprocesses (one per core) that call `surgrecon_cli.cli.main.main` in-process under
RLIMIT_AS = their start-up size + 1 GiB, with a limit of 10 s of CPU time per case (CPU, not
wall-clock time: a loaded machine does not turn a slow case into a hang; a worker blocked
without using CPU is caught by its 240 s wall-clock guard). A worker that dies is restarted
after the case it died on (reported as a crash).

Case ids name the mutation family: MCAP ones in tests/fuzz_mcap.py (byte level, inside
chunks, message level), PLY ones in tests/fuzz_ply.py. Run with `pytest -s` to see the case
count and timings.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import random
import signal
import struct
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np
import pytest
from fuzz_mcap import (
    BYTE_FAMILIES,
    CHUNK_FAMILIES,
    MESSAGE_FAMILIES,
    Base,
    build_log,
    byte_mutation,
    chunk_mutation,
    make_bases,
    message_mutation,
    real_zstd_bomb,
)
from fuzz_ply import ply_cases

SEED = 20240611
MIN_CASES = 500
CASE_TIMEOUT_S = 10  # s of CPU time
MEMORY_HEADROOM = 1 << 30  # bytes of address space a case may add to the worker's start-up size
WORKERS = 2
WORKER_TIMEOUT_S = 240
MAX_ERROR_LINE = 2100  # characters (cli/main.MESSAGE_LIMIT and the cut's marker)


@dataclasses.dataclass
class Case:
    """One fuzz case: `argv` for `main`, what exit code is acceptable ("0", "2" or "any") and
    how to check an exit-0 result ("same": equal to the unmutated log's ingest, "prefix":
    the first frames of it, "sane": a consistent run folder, "ply": a registered cloud)."""

    id: str
    argv: list[str]
    expect: str = "any"
    check: str = "sane"
    base: str = ""


# ============================================================================ generation
def generate(tmp: Path) -> list[Case]:
    rng = random.Random(SEED)
    nprng = np.random.default_rng(SEED)
    bases = make_bases(tmp)
    cases: list[Case] = []

    def add_log(family: str, base: Base, data: bytes, expect: str, check: str,
                allow_truncated: bool = False) -> None:
        folder = tmp / f"{len(cases):04d}"
        folder.mkdir()
        (folder / "log.mcap").write_bytes(data)
        argv = ["ingest", str(folder / "log.mcap"), "-o", str(folder / "run"), "--quiet"]
        if base.config:
            (folder / "topics.toml").write_text(base.config)
            argv += ["--config", str(folder / "topics.toml")]
        if allow_truncated:
            argv.append("--allow-truncated")
            check = "prefix" if check == "same" else check
        cases.append(Case(f"{len(cases):04d}-{family}-{base.name}", argv, expect, check,
                          base.name))

    for base in bases:  # the unmutated logs ingest exactly
        add_log("unmutated", base, base.data, "0", "same")
    for k in range(270):
        base = rng.choice(bases)
        family = BYTE_FAMILIES[k % len(BYTE_FAMILIES)]
        data, check = byte_mutation(base, rng, family)
        add_log(family, base, data, "any", check, allow_truncated=rng.random() < 0.4)
    add_log("real_zstd_bomb", bases[0], real_zstd_bomb(bases[0]), "2", "same")
    for k in range(150):
        base = rng.choice(bases)
        family = CHUNK_FAMILIES[k % len(CHUNK_FAMILIES)]
        add_log(family, base, chunk_mutation(base, rng, family), "any", "sane",
                allow_truncated=rng.random() < 0.3)
    for k in range(200):
        base = rng.choice(bases)
        family = MESSAGE_FAMILIES[k % len(MESSAGE_FAMILIES)]
        mutate, expect = message_mutation(family, rng)
        spec = dataclasses.replace(base.spec, mutate=mutate)
        try:
            data = build_log(tmp, spec, base.encoding)
        except (ValueError, OverflowError, struct.error, TypeError):
            continue  # the writer cannot encode this mutation (e.g. a stamp out of range)
        add_log(family, base, data, expect, "sane")
    for family, src, dst, expect, extra, files in ply_cases(rng, nprng, 130):
        folder = tmp / f"{len(cases):04d}"
        folder.mkdir()
        (folder / "src.ply").write_bytes(src)
        (folder / "dst.ply").write_bytes(dst)
        for name, content in files.items():
            (folder / name).write_bytes(content)
        argv = ["register-pair", str(folder / "src.ply"), str(folder / "dst.ply"), "-o",
                str(folder / "out.ply"), "--quiet", *(a.format(dir=folder) for a in extra)]
        cases.append(Case(f"{len(cases):04d}-ply_{family}", argv, expect, "ply"))
    return cases


# ============================================================================ the worker
class CaseTimeout(BaseException):
    """Raised by SIGPROF in a worker: the case used more than CASE_TIMEOUT_S of CPU time."""


def _alarm(signum, frame):
    raise CaseTimeout()


def worker(cases_file: str, results_file: str) -> None:
    """Run every case of `cases_file` in-process; one JSON line per case to `results_file`."""
    import resource

    import cv2

    # what the cases import is loaded before the start-up size is measured
    import surgrecon_cli.cli.cmd_register_pair
    import surgrecon_cli.stages.ingest  # noqa: F401
    from surgrecon_cli.cli.main import main

    cv2.setNumThreads(1)
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        main(["--help"])
    vm = next(int(line.split()[1]) * 1024 for line in Path("/proc/self/status").read_text()
              .splitlines() if line.startswith("VmSize:"))
    resource.setrlimit(resource.RLIMIT_AS, (vm + MEMORY_HEADROOM, vm + MEMORY_HEADROOM))
    signal.signal(signal.SIGPROF, _alarm)
    native = Path(results_file).with_suffix(".fd2")
    saved_fd2 = os.dup(2)
    with open(cases_file) as f, open(results_file, "a") as results:
        for case in json.load(f):
            out, err = io.StringIO(), io.StringIO()
            fd = os.open(native, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            os.dup2(fd, 2)
            os.close(fd)
            start = time.perf_counter()
            signal.setitimer(signal.ITIMER_PROF, CASE_TIMEOUT_S)  # CPU time of the process
            try:
                with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                    rc: int | str = main(case["argv"])
            except CaseTimeout:
                rc = "timeout"
            except BaseException:
                rc = "raised"
                err.write(traceback.format_exc())
            finally:
                signal.setitimer(signal.ITIMER_PROF, 0)
                os.dup2(saved_fd2, 2)
            results.write(json.dumps({"id": case["id"], "rc": rc, "stderr": err.getvalue(),
                                      "native_stderr": native.read_text(errors="replace"),
                                      "seconds": round(time.perf_counter() - start, 3)}) + "\n")
            results.flush()


def run_workers(cases: list[Case], tmp: Path) -> dict[str, dict]:
    """Run the cases in WORKERS subprocesses; restart a worker after a case that kills it."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
               MALLOC_ARENA_MAX="2")
    lanes = [cases[i::WORKERS] for i in range(WORKERS)]
    results: dict[str, dict] = {}
    pending = {w: lane for w, lane in enumerate(lanes) if lane}
    attempts = 0
    while pending:
        procs = {}
        for w, lane in pending.items():
            (tmp / f"lane{w}.json").write_text(json.dumps([dataclasses.asdict(c) for c in lane]))
            procs[w] = subprocess.Popen(
                [sys.executable, __file__, "--worker", str(tmp / f"lane{w}.json"),
                 str(tmp / f"lane{w}.jsonl")], env=env, cwd=tmp,
                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        next_pending = {}
        for w, proc in procs.items():
            try:  # a hang inside C code is not interrupted by the CPU timer
                _, worker_err = proc.communicate(timeout=WORKER_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, worker_err = proc.communicate()
            done = {}
            path = tmp / f"lane{w}.jsonl"
            if path.exists():
                for line in path.read_text().splitlines():
                    r = json.loads(line)
                    done[r["id"]] = r
            results.update(done)
            rest = [c for c in pending[w] if c.id not in done]
            if rest:  # the worker died on rest[0]
                results[rest[0].id] = {"id": rest[0].id, "rc": f"worker died ({proc.returncode})",
                                       "stderr": worker_err.decode(errors="replace")[-2000:],
                                       "native_stderr": "", "seconds": 0}
                if rest[1:]:
                    next_pending[w] = rest[1:]
        pending = next_pending
        attempts += 1
        assert attempts < 50, "workers keep dying"
    return results


# ============================================================================ checks
def _baseline(tmp: Path, cases: list[Case], results: dict[str, dict]) -> dict[str, Path]:
    """Run folders of the unmutated logs, by base name."""
    out = {}
    for case in cases:
        if "-unmutated-" in case.id and results[case.id]["rc"] == 0:
            out[case.base] = Path(case.argv[case.argv.index("-o") + 1])
    return out


def _check_ingest(case: Case, baseline: dict[str, Path]) -> str:
    """'' if the exit-0 run folder is right, else what is wrong."""
    from surgrecon_cli.io.run.folder import RunFolder
    from surgrecon_cli.io.run.ingest_store import load_ingested

    run = Path(case.argv[case.argv.index("-o") + 1])
    if not RunFolder(run).is_done("ingest"):
        return "exit 0 but run.json does not say ingest done"
    log = load_ingested(run / "ingest")
    if log.n_frames < 1 or not log.cameras or list(log.cameras) != sorted(log.cameras):
        return f"exit 0 with {log.n_frames} frames, cameras {log.cameras}"
    for t in range(log.n_frames):
        for c in range(len(log.cameras)):
            if log.image_paths[t][c]:
                log.load_image(t, c)
    if not np.isfinite(log.poses[log.usable]).all():
        return "non-finite pose of a usable camera"
    if case.check in ("same", "prefix") and case.base in baseline:
        # "same": what the unmutated log gives; "prefix" (data before damage): its first
        # frames, of the cameras seen before the damage
        ref = load_ingested(baseline[case.base] / "ingest")
        n = log.n_frames if case.check == "prefix" else ref.n_frames
        if case.check == "same" and not (
                log.cameras == ref.cameras and np.array_equal(log.stamps_ns, ref.stamps_ns)
                and np.array_equal(log.tool_poses, ref.tool_poses, equal_nan=True)
                and np.array_equal(log.joint_positions, ref.joint_positions, equal_nan=True)):
            return "frames, cameras, tool or joints differ from the unmutated log's"
        if log.n_frames != n or n > ref.n_frames or not set(log.cameras) <= set(ref.cameras):
            return f"{log.n_frames} frames of cameras {log.cameras}, expected {ref.n_frames}"
        cols = [ref.cameras.index(cid) for cid in log.cameras]
        usable = log.usable
        if not (np.array_equal(log.image_stamps_ns, ref.image_stamps_ns[:n, cols])
                and np.array_equal(log.poses[usable], ref.poses[:n, cols][usable])):
            return "frames differ from the unmutated log's"
        for t in range(n):
            for c, rc in enumerate(cols):
                a, b = log.image_paths[t][c], ref.image_paths[t][rc]
                if (a and b) and (run / "ingest" / a).read_bytes() != (
                        baseline[case.base] / "ingest" / b).read_bytes():
                    return f"image {a} differs from the unmutated log's"
    return ""


def _check_ply(case: Case) -> str:
    """'' if the registered cloud has every finite source point (and, for the intact pairs,
    lies closer to the target than the source did), else what is wrong."""
    from scipy.spatial import cKDTree

    from surgrecon_cli.io.run.ply import read_ply, read_ply_counted

    out = Path(case.argv[case.argv.index("-o") + 1])
    if not out.is_file():
        return "exit 0 but no output cloud"
    cloud = read_ply(out)
    src, _ = read_ply_counted(case.argv[1])
    if len(cloud["x"]) != len(src["x"]):
        return f"{len(cloud['x'])} registered points for {len(src['x'])} finite source points"
    if "-ply_valid" in case.id:
        dst, _ = read_ply_counted(case.argv[2])
        tree = cKDTree(np.c_[dst["x"], dst["y"], dst["z"]])
        before = np.median(tree.query(np.c_[src["x"], src["y"], src["z"]])[0])
        after = np.median(tree.query(np.c_[cloud["x"], cloud["y"], cloud["z"]])[0])
        if not after < before:
            return f"registration moved the source away: median {before:.2e} -> {after:.2e} m"
    return ""


def judge(case: Case, result: dict, baseline: dict[str, Path]) -> str:
    """'' if the case behaved, else a failure class with details."""
    rc, stderr = result["rc"], result["stderr"] + result["native_stderr"]
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    if rc == "timeout":
        return f"hang (> {CASE_TIMEOUT_S} s of CPU time)"
    if "MemoryError" in stderr or "Insufficient memory" in stderr:
        return "allocation over the limit: " + stderr.strip().splitlines()[-1][:300]
    if "Traceback" in stderr or rc not in (0, 2):
        last = lines[-1][:300] if lines else ""
        return f"exit {rc}: {last}"
    if case.expect != "any" and str(rc) != case.expect:
        return f"exit {rc}, expected {case.expect}: {lines[-1][:300] if lines else ''}"
    errors = [ln for ln in lines if ln.startswith("error:")]
    if rc == 2:
        # The error is the last line but for its details (a list, one indented item each).
        tail = lines[lines.index(errors[0]) + 1:] if len(errors) == 1 else []
        if len(errors) != 1 or not all(ln.startswith("  ") for ln in tail):
            return f"exit 2 without exactly one final 'error:' line: {lines[-3:]}"
        if len(errors[0]) > MAX_ERROR_LINE:
            return f"an error line of {len(errors[0])} characters: {errors[0][:200]}"
        if result["native_stderr"].strip():
            return f"native stderr output: {result['native_stderr'].strip()[:200]}"
        return ""
    if errors or result["native_stderr"].strip():
        return f"exit 0 with error output: {lines[-3:]}"
    try:
        return _check_ply(case) if case.check == "ply" else _check_ingest(case, baseline)
    except Exception as exc:
        return f"exit 0 but the result does not load: {type(exc).__name__}: {exc}"


@pytest.mark.slow
def test_fuzzed_inputs(tmp_path: Path, capsys):
    start = time.perf_counter()
    cases = generate(tmp_path)
    generated = time.perf_counter() - start
    results = run_workers(cases, tmp_path)
    baseline = _baseline(tmp_path, cases, results)
    failures = {}
    for case in cases:
        why = judge(case, results[case.id], baseline)
        if why:
            failures[case.id] = why
    n_mcap = sum(c.check != "ply" for c in cases)
    with capsys.disabled():  # the case count belongs in every test log, -q or not
        _print_summary(cases, results, n_mcap, generated, start, failures)
    assert len(cases) >= MIN_CASES
    assert len(baseline) == sum("-unmutated-" in c.id for c in cases)  # the bases ingest
    assert not failures, f"{len(failures)} of {len(cases)} fuzz cases failed (see above)"


def _print_summary(cases: list, results: dict, n_mcap: int, generated: float, start: float,
                   failures: dict) -> None:
    print(f"\nfuzz: {len(cases)} cases ({n_mcap} MCAP logs, {len(cases) - n_mcap} PLY pairs), "
          f"{sum(results[c.id]['rc'] == 0 for c in cases)} exit 0, "
          f"{sum(results[c.id]['rc'] == 2 for c in cases)} exit 2; generated in "
          f"{generated:.1f} s, total {time.perf_counter() - start:.1f} s; "
          f"slowest case {max(r['seconds'] for r in results.values()):.2f} s")
    for case_id, why in failures.items():
        print(f"FAIL {case_id}: {why}")


if __name__ == "__main__" and len(sys.argv) == 4 and sys.argv[1] == "--worker":
    worker(sys.argv[2], sys.argv[3])
