"""`surgrecon` entry point: a click group of thin subcommands.

Heavy imports happen inside the commands, so `--help` is instant.
"""

from __future__ import annotations

import sys

import click

from .. import __version__
from ..errors import cut
from .common import STATE

MESSAGE_LIMIT = 2000  # characters of an error line (a name from a log could be megabytes)


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="surgrecon")
def cli() -> None:
    """Multi-camera 3D reconstruction of dynamic surgical cavities.

    \b
    From a recorded MCAP log (several tracked endoscope cameras, robot kinematics):
    build a 3D template of the tissue, register every later frame to it non-rigidly and
    label every point static / shifting / deforming (Su, Huang & Hannaford, IROS 2019).

    \b
    Example, the whole pipeline on the shipped sample:
      surgrecon run sample_data/sample.mcap -o runs/sample
    """


def _register_commands() -> None:
    from . import commands

    for command in commands.ALL:
        cli.add_command(command)


_register_commands()


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; known errors become one line on stderr and exit code 2."""
    from ..errors import WRITE_ERRNOS, SurgReconError

    STATE["debug"] = False  # set again by --debug while parsing this call's arguments
    try:
        cli.main(args=argv, prog_name="surgrecon", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        return 130
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except SurgReconError as exc:
        if STATE["debug"]:
            raise
        click.echo(f"error: {_one_line(exc)}", err=True)
        for item in exc.details:
            click.echo(f"  {_one_line(Exception(item))}", err=True)
        return 2
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        return 130
    except Exception as exc:
        if STATE["debug"]:
            raise
        if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS:  # the system's, not a bug
            where = f"{exc.filename}: " if exc.filename else ""
            click.echo(f"error: {_one_line(Exception(where + str(exc.strerror)))}; free space "
                       "or choose a writable folder", err=True)
            return 2
        click.echo(f"internal error: {type(exc).__name__}: {_one_line(exc)} (re-run with --debug)",
                   err=True)
        return 3
    return 0


def _one_line(exc: BaseException) -> str:
    """The message on one line: line breaks and other control characters escaped (names
    taken from a log may hold any character), cut to MESSAGE_LIMIT characters."""
    text = cut(str(exc).strip(), MESSAGE_LIMIT)
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


if __name__ == "__main__":
    sys.exit(main())
