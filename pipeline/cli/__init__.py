"""The ``mosaicmap`` command line: the root group and the table of its commands.

One registration style (as rasterio's ``rio``): each command group lives in one module of
this package (:mod:`pipeline.cli.build`, :mod:`pipeline.cli.map`, ...), its commands thin
over library functions, and the root group names them in :data:`COMMANDS` as
``"module:attr"``, in workflow order. A command's module is imported only when that
command runs (or its help is asked for): ``mosaicmap --help`` reads the one-line
descriptions from the table (``tests/test_cli_surface.py`` checks them against the
commands' own help).

Exit codes: 0 success, 1 failure of the job, 2 bad input or usage (one line naming the
file, line or field and what is wrong).
"""

from __future__ import annotations

import errno
import importlib
import os
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import click

# When this module was first imported: the start of a `mosaicmap` process (see main()).
T_START = time.monotonic()

from pipeline import __version__  # noqa: E402
from pipeline.cli.common import FullHelpGroup, setup_logging  # noqa: E402
from pipeline.errors import STORAGE_ERRNOS, MosaicmapError, one_line, os_errno  # noqa: E402


@dataclass(frozen=True)
class CommandEntry:
    """One command of the root group: its name, where it lives (``"module:attr"``), the
    help section it is listed under and its one-line description (the first sentence of
    its help)."""

    name: str
    target: str
    section: str
    summary: str


# icechunk's log filter for a command (unless the user set ICECHUNK_LOG): its warnings, but
# not its storage module's "LocalFileSystem storage is not safe for concurrent commits" on
# every local repository: mapstore's commit lock serializes our commits. Set in the
# environment, so that worker processes inherit it.
ICECHUNK_LOG_DEFAULT = "warn,icechunk::storage=error"


def quiet_icechunk() -> None:
    """Apply :data:`ICECHUNK_LOG_DEFAULT` unless ICECHUNK_LOG is set (a user's choice wins)."""
    if "ICECHUNK_LOG" in os.environ:
        return
    os.environ["ICECHUNK_LOG"] = ICECHUNK_LOG_DEFAULT
    if "icechunk" in sys.modules:  # imported before (an embedding program): its filter is set already
        sys.modules["icechunk"].set_logs_filter(ICECHUNK_LOG_DEFAULT)


# Workflow order: make or import drive logs, build, look at and manage versions, diff,
# export for vehicles, track on the vehicle side, then setup and upkeep.
COMMANDS: tuple[CommandEntry, ...] = (
    CommandEntry("simulate", "pipeline.cli.simulate:simulate_group", "Drive logs",
                 "Simulate drive logs (with ground truth and the world) for tests and benchmarks."),
    CommandEntry("import-bag", "pipeline.cli.import_bag:import_bag_cmd", "Drive logs",
                 "Import an image and an odometry topic of a ROS 1/2 BAG as a drive log OUT."),
    CommandEntry("import-tiles", "pipeline.cli.import_tiles:import_tiles_cmd", "Drive logs",
                 "Import a stage tile grid as a drive log OUT: a Fiji/ImageJ TILECONFIG (TileConfiguration.txt), "
                 "or a folder DIR of tiles with --grid."),
    CommandEntry("import-geotagged", "pipeline.cli.import_geotagged:import_geotagged_cmd", "Drive logs",
                 "Import a folder IMAGE_DIR of geotagged aerial JPEGs as a drive log OUT."),
    CommandEntry("ingest", "pipeline.cli.build:ingest_cmd", "Build",
                 "Validate, decode, rectify and quality-check the frames of drive LOGS."),
    CommandEntry("build", "pipeline.cli.build:build_cmd", "Build",
                 "Run the nightly build over drive LOGS: ingest, register, optimize, render, publish."),
    CommandEntry("show", "pipeline.cli.map:show_cmd", "Map versions",
                 "Describe the map in REPO as stored: id, grid, levels, layers, poses, versions."),
    CommandEntry("log", "pipeline.cli.map:log_cmd", "Map versions",
                 "List the commits of a branch of REPO, newest first: id, date, tags, message, figures."),
    CommandEntry("tag", "pipeline.cli.map:tag_cmd", "Map versions",
                 "Tag version SNAPSHOT of REPO (snapshot id, prefix, tag or branch) as NAME."),
    CommandEntry("rollback", "pipeline.cli.map:rollback_cmd", "Map versions",
                 "Move a branch of REPO back to version TAG; the old tip stays reachable by a tag."),
    CommandEntry("poses", "pipeline.cli.map:poses_cmd", "Map versions",
                 "Write the poses of the frames the map in REPO was built from to a CSV."),
    CommandEntry("quicklook", "pipeline.cli.map:quicklook_cmd", "Map versions",
                 "Draw a level or a layer of the map in REPO (or a route panorama) as an image, for a quick look."),
    CommandEntry("diff", "pipeline.cli.diff:diff_cmd", "Map versions",
                 "Changes of the floor between versions FROM and TO of the map in REPO."),
    CommandEntry("export", "pipeline.cli.export:export_cmd", "Vehicle bundles",
                 "Export a region or corridor of a map version in REPO to OUT: a vehicle bundle, a delta (--since) "
                 "or an OME-Zarr directory (--format ome-zarr); --sign KEY signs it."),
    CommandEntry("verify", "pipeline.cli.export:verify_cmd", "Vehicle bundles",
                 "Check BUNDLE (or a delta) completely: its seal, manifest, every member's name, checksum and "
                 "size bounds, and with --key its signature."),
    CommandEntry("apply-delta", "pipeline.cli.export:apply_delta_cmd", "Vehicle bundles",
                 "Patch bundle BASE with DELTA into the new bundle OUT (both inputs and the result are verified; "
                 "a delta made for another base is refused with exit code 2)."),
    CommandEntry("track", "pipeline.cli.track:track_cmd", "Vehicle side",
                 "Replay drive LOG against map BUNDLE: the vehicle's tracker, frame by frame."),
    CommandEntry("config", "pipeline.cli.config:config_group", "Setup and upkeep",
                 "Inspect the configuration."),
    CommandEntry("keys", "pipeline.cli.keys:keys_group", "Setup and upkeep",
                 "Signing keys of a map owner (Ed25519)."),
    CommandEntry("gc", "pipeline.cli.map:gc_cmd", "Setup and upkeep",
                 "Free the space of snapshots no branch or tag reaches (icechunk garbage collection)."),
)

# What a command writes, for the one line of a storage error that no stage named itself.
WRITES = {
    "ingest": "the work directory", "build": "the work directory or the map repository",
    "export": "the bundle", "apply-delta": "the patched bundle", "tag": "the map repository",
    "rollback": "the map repository", "gc": "the map repository", "keys": "the key files",
    "import-tiles": "the drive log", "import-geotagged": "the drive log", "import-bag": "the drive log",
    "simulate": "the simulated log",
}
# Errors only a write gives (the others may come from reading an input too).
WRITE_ONLY_ERRNOS = frozenset(getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EFBIG", "EROFS") if hasattr(errno, n))


class MosaicmapGroup(FullHelpGroup):
    """The root group: loads its commands lazily from :data:`COMMANDS`, lists them in
    that order under their sections, and turns every error into its exit code and one line.

    :class:`MosaicmapError`: its exit code and message. A storage error (disk full,
    permission denied, name too long, ...: :data:`pipeline.errors.STORAGE_ERRNOS`): exit 1
    naming the path and what the command was writing. Anything else is a bug: exit 1 with
    "internal error", its traceback only with ``-v``. Messages are made one line
    (:func:`pipeline.errors.one_line`: control characters escaped).
    """

    def __init__(self, *args, commands_table: tuple[CommandEntry, ...] = COMMANDS, **kwargs):
        super().__init__(*args, **kwargs)
        self.table = {e.name: e for e in commands_table}

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.table) + sorted(n for n in self.commands if n not in self.table)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in self.commands and name in self.table:
            module, _, attr = self.table[name].target.partition(":")
            self.commands[name] = getattr(importlib.import_module(module), attr)
        return self.commands.get(name)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The commands by section, in workflow order, each with its whole one-line
        description (from the table: no command module is imported for the help)."""
        sections: dict[str, list[tuple[str, str]]] = {}
        for e in self.table.values():
            sections.setdefault(e.section, []).append((e.name, e.summary))
        for name in self.commands:
            if name not in self.table:
                sections.setdefault("Other", []).append((name, self.commands[name].get_short_help_str(10_000)))
        for title, rows in sections.items():
            with formatter.section(title):
                formatter.write_dl(rows)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except MosaicmapError as e:
            click.echo(f"mosaicmap: error: {one_line(str(e))}", err=True)
            ctx.exit(e.exit_code)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except Exception as e:  # noqa: BLE001 - the last resort: no traceback reaches a user
            verbose = bool(ctx.params.get("verbose"))
            if verbose:
                click.echo(traceback.format_exc().rstrip(), err=True)
            n = os_errno(e)
            command = ctx.invoked_subcommand or "mosaicmap"
            if n in STORAGE_ERRNOS:
                where = getattr(e, "filename", None) or command
                written = n in WRITE_ONLY_ERRNOS or Path(str(where)).name.startswith(".tmp-")  # temporaries are written
                if written:
                    doing = f"while {command} was writing {WRITES.get(command, 'its output')}"
                elif command in WRITES:
                    doing = f"while {command} was reading or writing {WRITES[command]}"
                else:
                    doing = f"{command} could not access it"
                click.echo(f"mosaicmap: error: {one_line(str(where))}: {os.strerror(n)} "
                           f"(errno {errno.errorcode.get(n, n)}; {doing})", err=True)
            else:
                first = (str(e).strip().splitlines() or [""])[0]
                hint = "" if verbose else "; rerun with -v for the traceback"
                click.echo(f"mosaicmap: internal error in {command}: {type(e).__name__}: {one_line(first)[:300]}"
                           f"{hint}", err=True)
            ctx.exit(1)




@click.group(cls=MosaicmapGroup, context_settings={"help_option_names": ["-h", "--help"], "show_default": True,
                                                   "max_content_width": 120})
@click.version_option(__version__, prog_name="mosaicmap")
@click.option("--verbose", "-v", is_flag=True, help="Debug logging, with time stamps and logger names; tracebacks "
                                                     "of internal errors.")
def cli(verbose: bool) -> None:
    """mosaicmap: build, version, diff and export floor image maps from drive logs.

    A first run: `make demo` (simulated logs through every command below). Each command's
    help: `mosaicmap COMMAND --help`; the configuration: `mosaicmap config show`.
    """
    from pipeline.allocator import tune_allocator

    setup_logging(verbose)
    quiet_icechunk()
    tune_allocator()


def _argv_label(argv: list[str]) -> str:
    """The command a ``mosaicmap`` command line names (``simulate floor``, ``build``), for
    its progress lines before the command itself is loaded."""
    words = [a for a in argv if not a.startswith("-")][:2]
    if not words or words[0] not in {e.name for e in COMMANDS}:
        return "mosaicmap"
    group = next(e for e in COMMANDS if e.name == words[0]).target.endswith("_group")
    return " ".join(words if group else words[:1])


def main() -> None:
    """The ``mosaicmap`` program (console script, ``python -m pipeline.cli``). While a
    command loads (importing its modules can take seconds on a busy machine), a
    ``build: working, 5 s`` line shows it started (not with --quiet, --help or --version)."""
    from pipeline.cli.common import STARTED
    from pipeline.progress import activity

    STARTED[0] = T_START
    argv = sys.argv[1:]
    silent = any(a in ("-q", "--quiet", "-h", "--help", "--version") for a in argv)
    with activity(_argv_label(argv), quiet=silent, since=T_START):
        cli(prog_name="mosaicmap")
