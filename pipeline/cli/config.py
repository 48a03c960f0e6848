"""Command group ``mosaicmap config``: the effective configuration."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.common import FullHelpGroup, config_option, no_quiet


@click.group("config", cls=FullHelpGroup)
def config_group() -> None:
    """Inspect the configuration."""


@no_quiet
@config_group.command("show")
@config_option
def config_show(config_file: Path | None) -> None:
    """Print the effective configuration (defaults overlaid by --config) as TOML."""
    from pipeline.config import dump_toml, load_config

    click.echo(dump_toml(load_config(config_file)))
