"""`surgrecon config`: print the effective configuration as TOML."""

from __future__ import annotations

import click

from .common import common_options


@click.command("config")
@common_options
def config_cmd(config, quiet: bool) -> None:
    """Print the effective config (defaults + --config + --set) as annotated TOML.

    \b
    Example:
      surgrecon config --set registration.alpha=0.1 > my.toml
    """
    from ..config import to_toml

    click.echo(to_toml(config), nl=False)
