"""Commands ``ingest`` and ``build``: the nightly build's stages over drive logs.

Thin over :func:`pipeline.stages.build.run_build`: options to configuration, then one line per
stage, printed as the stage finishes (``run_build``'s ``on_stage``), so a long build shows
where it is; between them the stages' own progress (:mod:`pipeline.progress`).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import click

from pipeline.cli.common import config_option, quiet_option, report_option, setup, write_report


@click.command("ingest")
@click.argument("logs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--workdir", "-w", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Work directory; the frames store goes to WORKDIR/ingest.")
@config_option
@report_option
@quiet_option
def ingest_cmd(logs: tuple[Path, ...], workdir: Path, config_file, report, quiet) -> None:
    """Validate, decode, rectify and quality-check the frames of drive LOGS."""
    from pipeline.stages.build import run_build

    cfg = setup(config_file, quiet)
    result = run_build(list(logs), workdir, cfg, until="ingest", only="ingest", quiet=quiet, on_stage=echo_stage)
    write_report(report, result)


@click.command("build")
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
    from pipeline.stages.build import default_workdir, run_build

    cfg = setup(config_file, quiet)
    if branch is not None:
        cfg["publish"]["branch"] = branch
    if scheduler is not None:
        cfg["register"]["scheduler"] = cfg["render"]["scheduler"] = scheduler
    workdir = workdir or default_workdir(list(logs))
    result = run_build(list(logs), workdir, cfg, until=until, quiet=quiet, map_url=map_url, tag=tag,
                       on_stage=echo_stage)
    if report is not None:
        result["plots"] = _plots_beside(report, workdir)
    write_report(report, result)


def echo_stage(stage: str, report: dict) -> None:
    """Print the line of ``stage``, just finished (``run_build``'s ``on_stage``)."""
    from pipeline.progress import note_output

    click.echo(_stage_line(report, stage))
    note_output()


def _plots_beside(report: Path, workdir: Path) -> dict:
    """Copy the build's plots next to the report (REPORT_STEM.trajectory.png, ...)."""
    from pipeline.stages.workspace import PLOTS, Workspace

    out = {}
    for name in PLOTS:
        src = Workspace(workdir).plot(name)
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
