"""Options and helpers shared by every mosaicmap command (same names everywhere, as in rio).

Every command either takes ``--config`` / ``--quiet`` (:data:`config_option`,
:data:`quiet_option`) or says in its help why not (:func:`no_config`, :func:`no_quiet`):
``tests/test_cli_surface.py`` checks that over the whole command table.
"""

from __future__ import annotations

import inspect
import logging
import sys
from pathlib import Path
from typing import Callable, TypeVar

import click

from pipeline.config import load_config
from pipeline.fsutil import write_json_atomic

F = TypeVar("F", bound=Callable)

config_option = click.option(
    "--config",
    "config_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="TOML file overriding the defaults in configs/ (see `mosaicmap config show`).",
)
quiet_option = click.option("--quiet", "-q", is_flag=True,
                            help="No progress (bars or lines) and no info lines: warnings, errors and the result only.")
report_option = click.option(
    "--report",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write a JSON report (counts, timings, errors) to this file.",
)

# Long enough for any command's first sentence: `--help` lists descriptions whole (wrapped).
SHORT_HELP_LIMIT = 10_000


class FullHelpGroup(click.Group):
    """A group whose help lists its commands with their whole one-line descriptions (click
    cuts them at the terminal width minus the longest name, with "...")."""

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = []
        for name in self.list_commands(ctx):
            cmd = self.get_command(ctx, name)
            if cmd is not None and not cmd.hidden:
                rows.append((name, cmd.get_short_help_str(SHORT_HELP_LIMIT)))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


# The sentences a command's help ends with when an option does not apply to it.
NO_CONFIG = "No --config: nothing this command does is configured."
NO_QUIET = "No --quiet: it prints no progress, only its result (errors on stderr)."


def _append_help(cmd: click.Command, sentence: str) -> None:
    cmd.help = f"{inspect.cleandoc(cmd.help or '')}\n\n{sentence}"


def no_config(cmd: F) -> F:
    """Mark a command (decorate it above ``@click.command``) as taking no ``--config``: its
    help says so."""
    _append_help(cmd, NO_CONFIG)  # type: ignore[arg-type]
    return cmd


def no_quiet(cmd: F) -> F:
    """Mark a command as taking no ``--quiet`` (it prints no progress): its help says so."""
    _append_help(cmd, NO_QUIET)  # type: ignore[arg-type]
    return cmd


class _PlainFormatter(logging.Formatter):
    """Log lines as a user reads them: the message alone for info, ``warning: ...`` above."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        if record.levelno >= logging.WARNING:
            return f"{record.levelname.lower()}: {text}"
        return text


_verbose = [False]
# time.monotonic() when the process running the command line started importing it (set by
# pipeline.cli.main; None when a program calls the group itself): the command's first
# "working" line counts from there.
STARTED: list[float | None] = [None]


def setup_logging(verbose: bool) -> None:
    """Logging to stderr: plain lines (no time stamp, no logger name) at info level, or
    with ``verbose`` time-stamped debug lines naming the logger. As ``logging.basicConfig``,
    a handler someone else installed (a test harness, an embedding program) is left alone."""
    _verbose[0] = verbose
    root = logging.getLogger()
    for h in list(root.handlers):
        if getattr(h, "_mosaicmap", False):
            root.removeHandler(h)
    if not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        if verbose:
            handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        else:
            handler.setFormatter(_PlainFormatter("%(message)s"))
        handler._mosaicmap = True  # type: ignore[attr-defined]
        root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose else logging.INFO)


def setup(config_file: Path | None, quiet: bool) -> dict:
    """Per-command setup: the logging level (info; ``quiet``: warnings only; ``-v``: debug
    whatever else), the effective configuration, and (unless ``quiet``) an
    :func:`pipeline.progress.activity` for the rest of the command: ``simulate floor:
    working, 10 s`` whenever the command printed nothing for a while."""
    from pipeline.progress import activity

    logging.getLogger().setLevel(logging.DEBUG if _verbose[0] else logging.WARNING if quiet else logging.INFO)
    cfg = load_config(config_file)
    ctx = click.get_current_context(silent=True)
    if ctx is not None and not quiet:
        label = " ".join(ctx.command_path.split()[1:]) or ctx.command_path
        ctx.with_resource(activity(label, since=STARTED[0]))
    return cfg


def write_report(path: Path | None, report: dict) -> None:
    """Write ``report`` as JSON to ``path`` (atomically) when one was given."""
    if path is not None:
        write_json_atomic(path, report)
