"""Options and helpers shared by every mosaicmap command (same names everywhere, as in rio)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Iterable, Iterator, TypeVar

import click

from pipeline.config import load_config
from pipeline.fsutil import write_json_atomic

T = TypeVar("T")

config_option = click.option(
    "--config",
    "config_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="TOML file overriding the defaults in configs/ (see `mosaicmap config show`).",
)
quiet_option = click.option("--quiet", "-q", is_flag=True, help="No progress bars, warnings and errors only.")
report_option = click.option(
    "--report",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write a JSON report (counts, timings, errors) to this file.",
)


def setup(config_file: Path | None, quiet: bool) -> dict:
    """Per-command setup: logging level and the effective configuration."""
    logging.getLogger().setLevel(logging.WARNING if quiet else logging.INFO)
    return load_config(config_file)


def progress(items: Iterable[T], *, length: int | None = None, label: str = "", quiet: bool = False) -> Iterator[T]:
    """Iterate with a progress bar on stderr when it is a terminal and not ``quiet``."""
    if quiet or not sys.stderr.isatty():
        yield from items
        return
    with click.progressbar(items, length=length, label=label, file=sys.stderr, show_pos=True) as bar:
        yield from bar


def write_report(path: Path | None, report: dict) -> None:
    if path is not None:
        write_json_atomic(path, report)
