"""Command ``mosaicmap import-tiles``: thin over :func:`pipeline.importers.tiles.import_tiles`."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.common import no_config, quiet_option, report_option, setup, write_report
from pipeline.importers.tiles import GRID_CORNERS, GRID_ORDERS, import_tiles, summary_line


@no_config
@click.command("import-tiles")
@click.argument("tile_config", metavar="TILECONFIG|DIR", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--pixel-size", type=float, default=0.001, show_default=True,
              help="Metres per pixel of the tiles (rectified images, camera normal to the plane). Where the "
                   "physical size does not matter, the default 1 mm keeps every figure in pixels x 0.001.")
@click.option("--stage-error", type=float, default=None, metavar="PX",
              help="The largest error of a tile's nominal position, pixels (default: 5 % of the tile's shorter "
                   "side); tiles are searched for within twice that of their neighbours.")
@click.option("--truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="A TileConfiguration of the tiles' true positions (e.g. from a simulator), written as "
                   "ground_truth.csv: builds report their errors against it; never used for building.")
@click.option("--peer", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Another TileConfiguration of the same tiles (e.g. Fiji's registered one), "
                   "written as peer_positions.csv for evaluation only.")
@click.option("--grid", default=None, metavar="CxR",
              help="Import the folder DIR by grid instead of a TileConfiguration: C columns by R rows of tiles.")
@click.option("--order", type=click.Choice(GRID_ORDERS), default="row-by-row", show_default=True,
              help="With --grid: the scan order (Fiji's grid types; snake: every other row/column runs back).")
@click.option("--first", type=click.Choice(GRID_CORNERS), default="top-left", show_default=True,
              help="With --grid: the corner of the first tile; the first row (column) runs away from it "
                   "(e.g. Fiji's 'Left & Down' is top-right).")
@click.option("--step", default=None, metavar="PX[,PY]",
              help="With --grid: mosaic pixels between neighbouring tiles (one value for both axes, or x,y).")
@click.option("--overlap", default=None, metavar="F[,FY]",
              help="With --grid, instead of --step: the tiles' overlap as a fraction (0.10 = 10 %); "
                   "step = tile size x (1 - F) per axis.")
@click.option("--pattern", default=None,
              help="With --grid: the tiles' file names with their index, e.g. 'tile{i:04d}.tif' or Fiji's "
                   "'tile{iiii}.tif'; indices from --first-index on, in acquisition order.")
@click.option("--first-index", type=int, default=1, show_default=True, help="With --pattern: the first tile's index.")
@click.option("--glob", default=None,
              help="With --grid, instead of --pattern: the tiles' files (e.g. '*.tif'), in name order with "
                   "numbers compared as numbers. Default: every .tif, .tiff, .png, .jpg, .jpeg of DIR.")
@report_option
@quiet_option
def import_tiles_cmd(tile_config: Path, out: Path, pixel_size: float, stage_error: float | None, truth: Path | None,
                     peer: Path | None, grid, order, first, step, overlap, pattern, first_index, glob,
                     report, quiet) -> None:
    """Import a stage tile grid as a drive log OUT: a Fiji/ImageJ TILECONFIG
    (TileConfiguration.txt), or a folder DIR of tiles with --grid.

    Tiles are copied byte for byte, one frame per tile at t = 0, 1, 2, ... in acquisition
    order (file order, or the grid's scan order); the odometry is the nominal stage
    position of each tile's centre. Example (a 9 x 7 snake scan starting top right, 460 px
    steps):

    \b
      mosaicmap import-tiles TILES OUT --pixel-size 0.001 --grid 9x7 \\
          --order snake-rows --first top-right --step 460 --glob '*.tif'
    """
    setup(None, quiet)
    summary = import_tiles(tile_config, out, pixel_size=pixel_size, peer=peer, truth=truth, grid=grid, order=order,
                           first=first, step=step, overlap=overlap, pattern=pattern, glob=glob,
                           first_index=first_index, stage_error=stage_error, quiet=quiet)
    write_report(report, summary)
    click.echo(summary_line(summary))
