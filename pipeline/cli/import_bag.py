"""Command ``mosaicmap import-bag``: thin over :func:`pipeline.importers.bag.import_bag`."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.common import config_option, quiet_option, report_option, setup, write_report
from pipeline.importers.bag import camera_from_options, import_bag, summary_line


@click.command("import-bag")
@click.argument("bag", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--image-topic", required=True, help="sensor_msgs/Image or sensor_msgs/CompressedImage topic.")
@click.option("--odom-topic", required=True, help="nav_msgs/Odometry topic.")
@click.option("--camera", "camera_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="TOML file with a [camera] table as in drive.toml (calibration of the images).")
@click.option("--pixel-size", type=float, default=None,
              help="The images are rectified ground images of this many metres per pixel.")
@config_option
@report_option
@quiet_option
def import_bag_cmd(bag: Path, out: Path, image_topic: str, odom_topic: str, camera_file: Path | None,
                   pixel_size: float | None, config_file, report, quiet) -> None:
    """Import an image and an odometry topic of a ROS 1/2 BAG as a drive log OUT.

    BAG is a ROS 1 .bag file or a ROS 2 bag directory (sqlite3 or mcap). Frame times are
    the header stamps (the bag receive time only where a header stamp is zero).
    Exactly one of --camera FILE or --pixel-size M is required.
    """
    cfg = setup(config_file, quiet)
    camera = camera_from_options(camera_file, pixel_size)
    tol = float(cfg["ingest"]["odometry_time_tolerance_s"])
    summary = import_bag(
        bag, out, image_topic=image_topic, odom_topic=odom_topic, camera=camera,
        camera_file=camera_file, time_tolerance_s=tol, quiet=quiet,
    )
    write_report(report, summary)
    click.echo(summary_line(summary))
