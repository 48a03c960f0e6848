"""Command ``mosaicmap import-geotagged``: thin over :func:`pipeline.importers.geotagged.import_geotagged`."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.common import no_config, quiet_option, report_option, setup, write_report
from pipeline.importers.geotagged import HEADING_FROM, import_geotagged, summary_line


@no_config
@click.command("import-geotagged")
@click.argument("image_dir", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--focal-mm", type=float, default=None, help="Focal length in mm (default: Exif:FocalLength).")
@click.option("--sensor-width-mm", type=float, default=None,
              help="Sensor width in mm (default: from Exif:PixelXDimension / Exif:FocalPlaneXResolution, "
                   "else 36 mm x Exif:FocalLength / Exif:FocalLengthIn35mmFilm).")
@click.option("--height-m", type=float, default=None,
              help="Height above ground in metres for frames without their own (XMP sensefly:Height, "
                   "else drone-dji:RelativeAltitude, the height above the take-off point).")
@click.option("--heading-deg", type=float, default=None, metavar="DEG",
              help="A fixed camera heading for every frame, compass degrees clockwise from north (the "
                   "direction of the image top), overriding the metadata.")
@click.option("--heading-from", type=click.Choice(HEADING_FROM), default="metadata", show_default=True,
              help="Where frame headings come from: 'metadata' (drone-dji:GimbalYawDegree, else "
                   "drone-dji:FlightYawDegree, sensefly:Heading, GPS:ImgDirection, GPS:Track) or 'track' "
                   "(the GPS track's direction between neighbouring frames, for every frame: the image top "
                   "is taken to face the direction of travel).")
@click.option("--max-width", type=int, default=None, help="Downscale frames wider than this many pixels.")
@report_option
@quiet_option
def import_geotagged_cmd(image_dir: Path, out: Path, focal_mm, sensor_width_mm, height_m, heading_deg, heading_from,
                         max_width, report, quiet) -> None:
    """Import a folder IMAGE_DIR of geotagged aerial JPEGs as a drive log OUT.

    Frames in time order; odometry = GPS positions in a local east/north frame (metres)
    with theta from the camera heading; camera intrinsics from the focal length, sensor
    width and the median height above ground. Reads EXIF, senseFly and DJI XMP; when
    metadata is missing, one error line lists every missing field with the option that
    supplies it.
    """
    setup(None, quiet)
    summary = import_geotagged(
        image_dir, out, focal_mm=focal_mm, sensor_width_mm=sensor_width_mm, height_m=height_m,
        heading_deg=heading_deg, heading_from=heading_from, max_width=max_width, quiet=quiet,
    )
    write_report(report, summary)
    click.echo(summary_line(summary))
