"""The ``mosaicmap`` command line: one command per pipeline stage, as click groups.

Exit codes: 0 success, 1 failure of the job, 2 bad input or usage (one line naming the
file, line or field and what is wrong).
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import sys
import traceback
from pathlib import Path

import click

from pipeline import __version__
from pipeline.allocator import tune_allocator
from pipeline.cli_common import config_option, quiet_option, report_option, setup, write_report
from pipeline.config import dump_toml, load_config
from pipeline.errors import STORAGE_ERRNOS, MosaicmapError, one_line, os_errno

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


class MosaicmapGroup(click.Group):
    """A click group that turns every error into its exit code and one line.

    :class:`MosaicmapError`: its exit code and message. A storage error (disk full,
    permission denied, name too long, ...: :data:`pipeline.errors.STORAGE_ERRNOS`): exit 1
    naming the path and what the command was writing. Anything else is a bug: exit 1 with
    "internal error", its traceback only with ``-v``. Messages are made one line
    (:func:`pipeline.errors.one_line`: control characters escaped).
    """

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


@click.group(cls=MosaicmapGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="mosaicmap")
@click.option("--verbose", "-v", is_flag=True, help="Debug logging.")
def cli(verbose: bool) -> None:
    """mosaicmap: build, version, diff and export floor image maps from drive logs."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    tune_allocator()


@cli.group("config")
def config_group() -> None:
    """Inspect the configuration."""


@config_group.command("show")
@config_option
def config_show(config_file: Path | None) -> None:
    """Print the effective configuration (defaults overlaid by --config) as TOML."""
    click.echo(dump_toml(load_config(config_file)))


@cli.command("ingest")
@click.argument("logs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--workdir", "-w", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Work directory; the frames store goes to WORKDIR/ingest.")
@config_option
@report_option
@quiet_option
def ingest_cmd(logs: tuple[Path, ...], workdir: Path, config_file, report, quiet) -> None:
    """Validate, decode, rectify and quality-check the frames of drive LOGS."""
    from pipeline.build import run_build

    cfg = setup(config_file, quiet)
    result = run_build(list(logs), workdir, cfg, until="ingest", only="ingest", quiet=quiet)
    write_report(report, result)
    click.echo(_stage_line(result, "ingest"))


@cli.command("build")
@click.argument("logs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--map", "map_url", default=None, metavar="REPO",
              help="Map repository (a directory, or s3://bucket/prefix with credentials from the "
                   "environment): render and publish a new version to it, extending the map it holds. "
                   "Without it the build stops after optimize.")
@click.option("--workdir", "-w", default=None, type=click.Path(file_okay=False, path_type=Path),
              help="Work directory holding each stage's output and manifest "
                   "(default: .mosaicmap-work/<hash of the logs> in the current directory).")
@click.option("--branch", default=None, help="Branch to publish on (default [publish] branch: main).")
@click.option("--tag", default=None, help="Tag of the new version (default [publish] tag_format: vYYYYMMDD-N).")
@click.option("--scheduler", default=None,
              help="Where register and render run: threads, processes, sync, or a dask.distributed "
                   "scheduler address tcp://host:port (default from the configuration).")
@click.option("--until", default=None, help="Stop after this stage (default: run every stage).")
@config_option
@report_option
@quiet_option
def build_cmd(logs: tuple[Path, ...], map_url: str | None, workdir: Path | None, branch: str | None,
              tag: str | None, scheduler: str | None, until: str | None, config_file, report, quiet) -> None:
    """Run the nightly build over drive LOGS: ingest, register, optimize, render, publish.

    Finished stages are skipped and a killed run resumes; a build failing its quality gates
    does not publish and exits 1 with the reason.
    """
    from pipeline.build import default_workdir, run_build

    cfg = setup(config_file, quiet)
    if branch is not None:
        cfg["publish"]["branch"] = branch
    if scheduler is not None:
        cfg["register"]["scheduler"] = cfg["render"]["scheduler"] = scheduler
    workdir = workdir or default_workdir(list(logs))
    result = run_build(list(logs), workdir, cfg, until=until, quiet=quiet, map_url=map_url, tag=tag)
    if report is not None:
        result["plots"] = _plots_beside(report, workdir)
    write_report(report, result)
    for stage in result["stages"]:
        click.echo(_stage_line(result, stage))


def _plots_beside(report: Path, workdir: Path) -> dict:
    """Copy the build's plots next to the report (REPORT_STEM.trajectory.png, ...)."""
    out = {}
    for name in ("trajectory", "residuals"):
        src = workdir / "optimize" / f"{name}.png"
        if src.exists():
            dst = report.with_name(f"{report.stem}.{name}.png")
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
            out[name] = str(dst)
    return out


def _stage_line(result: dict, stage: str) -> str:
    info = result["stages"][stage]
    state = "skipped (up to date)" if info["skipped"] else f"done in {info['seconds']:.2f} s"
    extra = ""
    if stage == "ingest":
        ing = result["ingest"]
        extra = f": {ing['frames_accepted']} of {ing['frames_total']} frames accepted"
    elif stage == "register":
        reg = result["registration"]
        extra = f": {reg['accepted']} of {reg['candidates']} pairs registered ({reg['pairs_per_s']:.0f} pairs/s)"
    elif stage == "optimize":
        opt, links = result["optimization"], result["links"]
        extra = (f": {opt['frames']} poses, {links['rejected_outliers']} outlier links rejected, "
                 f"residual RMS {opt['residual_rms_px']:.4f} px")
        gt = result.get("ground_truth")
        if gt:
            extra += f"; vs ground truth: RMS {gt['pose_rms_px']:.3f} px, max {gt['pose_max_px']:.3f} px"
    elif stage == "render":
        r = result["render"]
        extra = (f": {r['shards']} shards, {r['level0_mpix']:.1f} MPix level 0 + {r['levels'] - 1} pyramid levels "
                 f"({r['mpix_per_s']:.0f} MPix/s)")
    elif stage == "orp":
        o = result["orp"]
        reg = o.get("registration", {})
        extra = (f": {len(o['routes'])} route(s) from {o['runs']} run(s), {o['rows']} rows over {o['length_m']:.1f} m, "
                 f"{reg.get('fixes_accepted', 0)} of {reg.get('fixes_tried', 0)} cross-run fixes accepted")
        ogt = o.get("ground_truth")
        if ogt:
            extra += (f"; vs ground truth: RMS {100 * ogt['pose_rms_m']:.2f} cm, "
                      f"heading RMS {ogt['heading_rms_deg']:.3f} deg")
    elif stage == "publish":
        p = result["publish"]
        extra = f": version {p['version']} = snapshot {p['snapshot']}, tag {p['tag']} on {p['branch']}"
    return f"{stage}: {state}{extra}"


def _register_subcommands() -> None:
    from pipeline.bag_import import import_bag_cmd
    from pipeline.import_geotagged import import_geotagged_cmd
    from pipeline.import_tiles import import_tiles_cmd
    from pipeline.simulate.cli import simulate_group

    cli.add_command(simulate_group)
    cli.add_command(import_bag_cmd)
    cli.add_command(import_tiles_cmd)
    cli.add_command(import_geotagged_cmd)


_register_subcommands()

from pipeline.cli_map import register_map_commands  # noqa: E402  (show, log, tag, rollback, poses, quicklook)
register_map_commands(cli)
from pipeline.cli_diff import register_diff_commands  # noqa: E402  (diff)
register_diff_commands(cli)
from pipeline.cli_export import register_export_commands  # noqa: E402  (export, verify, apply-delta)
register_export_commands(cli)
from pipeline.cli_track import register_track_commands  # noqa: E402  (track)
register_track_commands(cli)


def main() -> None:
    cli(prog_name="mosaicmap")


if __name__ == "__main__":
    main()
