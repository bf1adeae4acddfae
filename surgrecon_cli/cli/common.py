"""Options every subcommand shares, logging set-up, and error -> one line + exit code."""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

STATE = {"debug": False}


QUIET_HELP = "No progress bars or stage lines: warnings, errors and where the result is."

def _set_debug(ctx: click.Context, param: click.Parameter, value: bool) -> bool:
    if value:
        STATE["debug"] = True
    return value


def common_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Add --config FILE, --set section.key=value (repeatable), --debug and --quiet."""

    @click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path),
                  help="TOML config; keys not given keep their defaults.")
    @click.option("--set", "overrides", multiple=True, metavar="SECTION.KEY=VALUE",
                  help="Override one config key (repeatable), e.g. --set registration.alpha=0.1.")
    @click.option("--debug", is_flag=True, expose_value=False, is_eager=True, callback=_set_debug,
                  help="Show tracebacks and debug logging.")
    @click.option("--quiet", "-q", is_flag=True, help=QUIET_HELP)
    @functools.wraps(func)
    def wrapper(*args: Any, config_path: Path | None, overrides: tuple[str, ...], quiet: bool,
                **kwargs: Any) -> Any:
        from ..config import load_config

        setup_logging(quiet)
        config = load_config(config_path, overrides)
        return func(*args, config=config, quiet=quiet, **kwargs)

    return wrapper


class _AboveBars(logging.StreamHandler):
    """Log lines to stderr through tqdm.write: a line logged while a progress bar is drawn
    goes above it on a line of its own, not onto the end of the bar."""

    def emit(self, record: logging.LogRecord) -> None:
        from tqdm import tqdm

        try:
            tqdm.write(self.format(record), file=self.stream)
        except Exception:  # logging's contract: emit never raises
            self.handleError(record)


def setup_logging(quiet: bool) -> None:
    level = logging.DEBUG if STATE["debug"] else (logging.WARNING if quiet else logging.INFO)
    if not STATE["debug"]:  # Dask reads this when imported (also in its worker processes)
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    logging.basicConfig(level=level, format="%(message)s", force=True,
                        handlers=[_AboveBars()])
    for noisy in ("matplotlib", "PIL"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def progress(quiet: bool) -> Callable[..., Any]:
    """A factory of tqdm bars (disabled with --quiet) for pipeline callbacks."""
    from tqdm import tqdm

    return functools.partial(tqdm, disable=True if quiet else None, dynamic_ncols=True,
                             leave=False)


def executor_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Add --executor, --workers and --scheduler (shortcuts for the `[run]` config keys);
    goes below `common_options`, whose config it updates."""

    @click.option("--executor", type=click.Choice(["serial", "processes", "dask"]),
                  help="Where the stages' tasks run (default: run.executor, 'serial').")
    @click.option("--workers", type=click.IntRange(min=0),
                  help="Worker processes for processes / a Dask LocalCluster (0 = one per core).")
    @click.option("--scheduler", metavar="ADDRESS",
                  help="Dask scheduler to use, e.g. tcp://10.0.0.5:8786 (implies --executor dask).")
    @functools.wraps(func)
    def wrapper(*args: Any, config: Any, executor: str | None, workers: int | None,
                scheduler: str | None, **kwargs: Any) -> Any:
        from ..config import from_dict

        chosen = {"executor": executor, "workers": workers, "scheduler": scheduler}
        if scheduler and executor is None:
            chosen["executor"] = "dask"
        updates = {k: v for k, v in chosen.items() if v is not None}
        if updates:
            config = from_dict({"run": updates}, config)
        return func(*args, config=config, **kwargs)

    return wrapper


def locks_run_folder(create: bool = False, writes: bool = True) -> Callable[..., Any]:
    """Hold the lock of the command's `run_dir` (io/run_folder.run_folder_lock) for the whole
    command: a second command on the same folder refuses at once. create: make the folder;
    writes=False: the command only reads the run (a read-only archive is read unlocked)."""

    def decorate(func: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            from ..io.run.lock import run_folder_lock

            command = click.get_current_context().info_name or func.__name__
            with run_folder_lock(kwargs["run_dir"], command, create=create, writes=writes):
                return func(*args, **kwargs)

        return wrapper

    return decorate


def quiet_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Add --debug and --quiet (for commands that read a run's own config, not a new one)."""

    @click.option("--debug", is_flag=True, expose_value=False, is_eager=True, callback=_set_debug,
                  help="Show tracebacks and debug logging.")
    @click.option("--quiet", "-q", is_flag=True, help=QUIET_HELP)
    @functools.wraps(func)
    def wrapper(*args: Any, quiet: bool, **kwargs: Any) -> Any:
        setup_logging(quiet)
        return func(*args, quiet=quiet, **kwargs)

    return wrapper
