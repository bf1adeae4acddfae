"""The run-folder lock (io/run_folder.run_folder_lock): one command at a time per folder.

A second process refuses at once in one line naming the holder's pid and start time,
leaving the holder's folder as it was; a holder killed with SIGKILL never blocks the next
command (the kernel drops the lock with the process)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from surgrecon_cli.cli.main import main
from surgrecon_cli.errors import RunFolderError
from surgrecon_cli.io.run.layout import RunLayout
from surgrecon_cli.io.run.lock import run_folder_lock

SURGRECON = [sys.executable, "-c",
             "import sys; from surgrecon_cli.cli.main import main; sys.exit(main())"]
# A second process that takes the lock as a command does and keeps it until stdin closes.
HOLDER = ("import sys; from surgrecon_cli.io.run.lock import run_folder_lock\n"
          "with run_folder_lock(sys.argv[1], 'register'):\n"
          "    print('locked', flush=True); sys.stdin.read()\n")


def start_holder(run: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(run)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "locked"
    return proc


def digest(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under `folder` but the lock file."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*"))
            if p.is_file() and p != RunLayout(folder).lock_file}


def test_second_process_refuses_at_once_and_the_first_keeps_its_outputs(
        copy_run: Path, pipeline_log: Path):
    before = digest(copy_run)
    holder = start_holder(copy_run)
    try:
        second = subprocess.run([*SURGRECON, "run", str(pipeline_log), "-o", str(copy_run),
                                 "-q"], capture_output=True, text=True, timeout=120)
        assert second.returncode == 2, second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1
        assert f"pid {holder.pid}" in lines[0] and "started 20" in lines[0]
        assert "surgrecon register" in lines[0] and str(copy_run) in lines[0]
    finally:
        holder.communicate("", timeout=30)
    assert holder.returncode == 0
    assert digest(copy_run) == before


def test_a_real_command_holds_the_lock_for_its_whole_run(copy_run: Path, pipeline_log: Path):
    """`surgrecon report` frozen (SIGSTOP) while it holds the lock: `surgrecon run` on the
    same folder refuses at once naming it; resumed, the report finishes as if alone."""
    layout = RunLayout(copy_run)
    before = digest(copy_run)
    first = subprocess.Popen([*SURGRECON, "report", str(copy_run), "-q"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(6000):  # until it holds the lock (its pid in the lock file)
            if layout.lock_file.exists() and f'"pid": {first.pid}' in \
                    layout.lock_file.read_text():
                break
            assert first.poll() is None, first.communicate()
            time.sleep(0.01)
        first.send_signal(signal.SIGSTOP)
        second = subprocess.run([*SURGRECON, "run", str(pipeline_log), "-o", str(copy_run),
                                 "-q"], capture_output=True, text=True, timeout=120)
    finally:
        first.send_signal(signal.SIGCONT)
        _, err = first.communicate(timeout=300)
    assert second.returncode == 2 and f"pid {first.pid}" in second.stderr, second.stderr
    assert "surgrecon report" in second.stderr
    assert first.returncode == 0, err
    rewritten = {layout.relative(p) for p in (layout.report_html, layout.summary_json,
                                              layout.frames_csv, layout.run_json)}
    after = digest(copy_run)
    assert {k: v for k, v in after.items() if k not in rewritten} == {
        k: v for k, v in before.items() if k not in rewritten}
    assert json.loads(layout.summary_json.read_text())
    assert all(s["status"] == "done" for s in json.loads(layout.run_json.read_text())["stages"]
               .values())


@pytest.mark.parametrize("command", ["build-template", "register", "classify", "measure",
                                     "report", "evaluate", "export", "ingest"])
def test_every_command_on_a_run_folder_takes_the_lock(copy_run: Path, pipeline_log: Path,
                                                      command: str, capsys):
    args = {"ingest": [str(pipeline_log), "-o", str(copy_run), "--force"],
            "export": [str(copy_run), "--tum", str(copy_run.parent / "tum")]}
    holder = start_holder(copy_run)
    try:
        assert main([command, *args.get(command, [str(copy_run)]), "-q"]) == 2
        assert f"pid {holder.pid}" in capsys.readouterr().err
    finally:
        holder.communicate("", timeout=30)


def test_a_killed_holder_does_not_block_the_next_command(copy_run: Path, capsys):
    holder = start_holder(copy_run)
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait(timeout=30)
    assert RunLayout(copy_run).lock_file.read_text()  # the dead holder's record stays
    assert main(["report", str(copy_run), "-q"]) == 0, capsys.readouterr().err


def test_lock_is_reentrant_within_a_process_and_released_after(tmp_path: Path):
    run = tmp_path / "new" / "run"
    with run_folder_lock(run, "run", create=True):
        with run_folder_lock(run, "ingest"):
            pass
        holder = subprocess.run([sys.executable, "-c", HOLDER, str(run)], input="",
                                capture_output=True, text=True, timeout=60)
        assert holder.returncode != 0 and "in use by surgrecon run" in holder.stderr
    holder = subprocess.run([sys.executable, "-c", HOLDER, str(run)], input="",
                            capture_output=True, text=True, timeout=60)
    assert holder.returncode == 0, holder.stderr


def test_lock_file_that_is_a_link_or_unwritable_folder_is_one_line(tmp_path: Path):
    run = tmp_path / "run"
    run.mkdir()
    (run / ".surgrecon.lock").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(RunFolderError, match="lock file"), run_folder_lock(run, "run"):
        pass
    assert not (tmp_path / "elsewhere").exists()
    with pytest.raises(RunFolderError, match="not a folder"), \
            run_folder_lock(Path(os.devnull), "run", create=True):
        pass


def test_a_read_only_archive_is_read_unlocked_but_never_written(copy_run: Path, monkeypatch):
    import errno

    lock = RunLayout(copy_run).lock_file
    lock.unlink(missing_ok=True)
    real_open = os.open

    def read_only(path, flags, *args):
        if Path(path) == lock:
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(os, "open", read_only)
    with run_folder_lock(copy_run, "export", writes=False):
        pass
    with pytest.raises(RunFolderError, match="Read-only file system"), \
            run_folder_lock(copy_run, "report"):
        pass
