"""Command ``mosaicmap track``: thin over :func:`pipeline.track_run.track_log` (the replay,
on a floor map or on a route panorama; its module docstring says how)."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.common import config_option, quiet_option, report_option, setup, write_report


@click.command("track")
@click.argument("bundle", type=click.Path(path_type=Path))
@click.argument("log", type=click.Path(file_okay=False, path_type=Path))
@report_option
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="PNG",
              help="Plot the run: trajectory (truth, odometry, fixes by status) and the error per frame.")
@click.option("--poses", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="CSV",
              help="Write the tracked poses: t,x,y,theta,status,mode,sigma_x,sigma_y,sigma_theta (world frame).")
@click.option("--start", default="odometry", show_default=True, metavar="odometry|truth|none|X,Y,THETA",
              help="Starting pose: the odometry's first pose, the ground truth's, none (relocalize first), or "
                   "an explicit pose (metres, radians), with [tracker.session] start_sigma.")
@click.option("--frames", "frame_range", default=None, metavar="FIRST:LAST",
              help="Replay only frame rows FIRST..LAST-1 of frames.csv.")
@click.option("--route", "route_id", default=None, metavar="ID",
              help="Omni logs: the bundle's route panorama to track on (default: the only one, else the one "
                   "nearest the start pose).")
@click.option("--key", "keys", multiple=True, metavar="PUB",
              help="A trusted public key (KEY.pub of `mosaicmap keys new`; repeatable), beside [tracker.bundle] "
                   "trusted_keys: the bundle is loaded only when its signature checks against one of them.")
@click.option("--insecure", is_flag=True,
              help="Development only: also load an unsigned bundle (or a zarr directory), unchecked.")
@config_option
@quiet_option
def track_cmd(bundle: Path, log: Path, report: Path | None, plot: Path | None, poses: Path | None, start: str,
              frame_range: str | None, route_id: str | None, keys: tuple[str, ...], insecure: bool,
              config_file: Path | None, quiet: bool) -> None:
    """Replay drive LOG against map BUNDLE: the vehicle's tracker, frame by frame.

    Per frame: a prior from the odometry, a pose fix against the map (status ok,
    low_texture, ambiguous, lost or off_map), frame-to-frame motion where the map has no
    data, relocalization when lost. Prints the ok rate, speed and latency of the fixes,
    relocalizations and, when the log has ground_truth.csv, the errors of the ok fixes
    (map pixels) and the wrong ones (ok but off by more than 2 px).

    An omni LOG is tracked on one of the bundle's route panoramas (--route; BUNDLE may
    also be a zarr directory holding /routes): statuses ok, weak, masked, jump, off_route,
    lost, ambiguous; errors in metres (wrong: ok but off by more than 10 cm).

    BUNDLE is loaded only when its signature checks against a trusted key (--key,
    [tracker.bundle] trusted_keys); each member is checked against the signed manifest
    when first read. --insecure (development) also accepts unsigned bundles.
    """
    from pipeline.track_run import track_log

    cfg = setup(config_file, quiet)
    rep, lines = track_log(bundle, log, cfg, start=start, frames=frame_range, route_id=route_id, keys=keys,
                           insecure=insecure, plot=plot, poses=poses, quiet=quiet,
                           warn=lambda text: click.echo(f"mosaicmap: warning: {text}", err=True))
    write_report(report, rep)
    for line in lines:
        click.echo(line)
