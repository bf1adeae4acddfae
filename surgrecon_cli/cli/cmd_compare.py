"""`surgrecon compare RUN RUN...`: key figures of runs side by side, and their config
differences."""

from __future__ import annotations

from pathlib import Path

import click

from .common import quiet_options


@click.command("compare")
@click.argument("run_dirs", nargs=-1, required=True,
                type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--html", "html_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Also write the comparison as a self-contained HTML page with the runs' "
                   "per-frame figures overlaid.")
@quiet_options
def compare_cmd(run_dirs: tuple[Path, ...], html_path: Path | None, quiet: bool) -> None:
    """Compare runs: template size and error, registration error, F1, label fractions,
    noise figures and timings (from metrics/summary.json, metrics/evaluation.json and
    run.json), then the config keys whose values differ between the runs.

    Figures a run lacks (e.g. not evaluated, no report) show as "-".

    \b
    Examples:
      surgrecon compare runs/sample runs/sample-alpha
      surgrecon compare runs/sweep/* --html sweep.html
    """
    from ..report.compare import format_comparison, load_runs

    runs = load_runs(list(run_dirs))
    click.echo(format_comparison(runs))
    if html_path is not None:
        from ..io.run.atomic import write_text
        from ..report.compare_html import comparison_html

        write_text(html_path, comparison_html(runs))
        click.echo(f"html -> {html_path}")
