"""Command group ``mosaicmap simulate``: simulators that write drive logs with ground truth.

An option left out takes its value from the configuration (configs/simulate.toml, overlaid
by --config); the help shows the embedded default of each (``[default: (simulate.floor.area_m = 5x5)]``).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import click

from pipeline.cli.common import FullHelpGroup, config_option, quiet_option, setup


@lru_cache(maxsize=1)
def _defaults() -> dict:
    from pipeline.config import default_config

    return default_config()


def dflt(key: str, shown: str | None = None) -> str:
    """The help's default of an option: ``key = value``, the embedded configuration's value
    at ``key`` (dotted, e.g. ``simulate.floor.area_m``; pairs shown as AxB)."""
    if shown is None:
        v = _defaults()
        for k in key.split("."):
            v = v[k]
        if isinstance(v, list):
            shown = "x".join(f"{x:g}" if isinstance(x, float) else str(x) for x in v)
        elif isinstance(v, bool):
            shown = str(v).lower()
        else:
            shown = f"{v:g}" if isinstance(v, float) else str(v)
    return f"{key} = {shown}"


@click.group("simulate", cls=FullHelpGroup)
def simulate_group() -> None:
    """Simulate drive logs (with ground truth and the world) for tests and benchmarks."""


@simulate_group.command("floor")
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--seed", type=int, default=None,
              show_default=dflt("simulate.seed"),
              help="Random seed (same seed and options: identical output).")
@click.option("--area", default=None,
              show_default=dflt("simulate.floor.area_m"),
              help="Floor area XxY in metres, e.g. 5x5.")
@click.option("--pixel-size", type=float, default=None,
              show_default=dflt("simulate.floor.pixel_size_m"),
              help="Map pixel size in metres (camera ground pixel).")
@click.option("--frame-size", default=None,
              show_default=dflt("simulate.floor.camera.frame_size"),
              help="Raw frame WIDTHxHEIGHT in pixels, e.g. 320x240.")
@click.option("--route", default=None,
              show_default=dflt("simulate.floor.route"),
              help="Route: lawnmower, loop, figure8 or random.")
@click.option("--odometry-drift", type=float, default=None, show_default=dflt("simulate.floor.odometry.drift"),
              help="Odometry error gradient alpha (error ~ alpha x distance); 0 = perfect odometry.")
@click.option("--noise", type=float, default=None,
              show_default=dflt("simulate.floor.sensor.noise_sigma"),
              help="Gaussian sensor noise sigma, grey levels.")
@click.option("--texture", default=None,
              show_default=dflt("simulate.floor.texture"),
              help="'procedural' or the path of a photograph of a floor.")
@click.option("--world", type=click.Path(path_type=Path), default=None, show_default="none: a new world",
              help="Reuse the world of a previous simulated log (a later day).")
@click.option("--changes", type=int, default=None,
              show_default=dflt("simulate.floor.changes"),
              help="Number of floor changes applied to the world.")
@click.option("--illumination", type=float, default=None,
              show_default=dflt("simulate.floor.illumination"),
              help="Global illumination factor (0.8 = 20 % darker).")
@click.option("--height-jitter", type=float, default=None, show_default=dflt("simulate.floor.height_jitter"),
              help="Smooth camera height variation, peak fraction (0.02 = +-2 %), unknown to the log; "
                   "truth in ground_truth_height.csv.")
@config_option
@quiet_option
def floor_cmd(out: Path, seed, area, pixel_size, frame_size, route, odometry_drift, noise, texture, world,
              changes, illumination, height_jitter, config_file, quiet) -> None:
    """Simulate a downward-camera drive over a textured floor into the drive log OUT.

    Defaults come from configs/simulate.toml ([simulate.floor]); options override them.
    """
    from pipeline.simulate.floor import simulate_floor

    cfg = setup(config_file, quiet)
    given = dict(
        seed=seed, area=area, pixel_size=pixel_size, frame_size=frame_size, route=route,
        odometry_drift=odometry_drift, noise=noise, texture=texture, world=world, changes=changes,
        illumination=illumination, height_jitter=height_jitter,
    )
    r = simulate_floor(out, cfg, given, quiet=quiet)
    extra = f", {r['changes']} changes" if r["changes"] else ""
    click.echo(
        f"simulate floor: {r['frames']} frames, {r['route']} route {r['route_length_m']:.1f} m{extra}, "
        f"{r['seconds']:.1f} s -> {r['out']}"
    )


@simulate_group.command("omni")
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--seed", type=int, default=None,
              show_default=dflt("simulate.seed") + "; with --world: the previous log's seed + 1",
              help="Random seed (same seed and options: identical output; with --world, default the previous log's seed + 1: a new run).")
@click.option("--room", default=None,
              show_default=dflt("simulate.omni.room_m"),
              help="Room size XxY in metres, e.g. 11x6 (a fresh world only).")
@click.option("--route", default=None,
              show_default=dflt("simulate.omni.route"),
              help="Route: loop, figure8, random or lawnmower (a fresh world only).")
@click.option("--world", type=click.Path(path_type=Path), default=None, show_default="none: a new world",
              help="Reuse the world and route of a previous omni log (a repeat run).")
@click.option("--night", is_flag=True, default=None,
              show_default=dflt("simulate.omni.night"),
              help="Night lighting: ceiling lamps, dark windows.")
@click.option("--height-offset", type=float, default=None, show_default=dflt("simulate.omni.height_offset_m"),
              help="Render the camera this many metres above its declared height (a height error).")
@click.option("--move-objects", type=float, default=None, show_default=dflt("simulate.omni.move_objects"),
              help="Move objects so that about this fraction of horizon azimuths sees them differently.")
@click.option("--offset", type=float, default=None,
              show_default=dflt("simulate.omni.offset_m"),
              help="Drive parallel to the route, this many metres to its left.")
@click.option("--angle", type=float, default=None, show_default=dflt("simulate.omni.angle_deg"),
              help="Drive across the route at this angle (degrees), zig-zagging within the configured amplitude.")
@click.option("--noise", type=float, default=None,
              show_default=dflt("simulate.omni.sensor.noise_sigma"),
              help="Gaussian sensor noise sigma, grey levels.")
@click.option("--odometry-drift", type=float, default=None, show_default=dflt("simulate.omni.odometry.drift"),
              help="Odometry error gradient alpha (error ~ alpha x distance); 0 = perfect odometry.")
@click.option("--route-id", default=None, show_default="the route kind, or the --world log's route id",
              help="[route] id written to drive.toml (default: the route kind, or the --world log's id).")
@config_option
@quiet_option
def omni_cmd(out: Path, seed, room, route, world, night, height_offset, move_objects, offset, angle, noise,
             odometry_drift, route_id, config_file, quiet) -> None:
    """Simulate an omnidirectional (hyperboloidal-mirror) drive through a room into the drive log OUT.

    Defaults come from configs/simulate.toml ([simulate.omni]); options override them.
    """
    from pipeline.simulate.omni import simulate_omni

    cfg = setup(config_file, quiet)
    given = dict(
        seed=seed, room=room, route=route, world=world, night=night or None, height_offset=height_offset,
        move_objects=move_objects, offset=offset, angle=angle, noise=noise, odometry_drift=odometry_drift,
        route_id=route_id,
    )
    r = simulate_omni(out, cfg, given, quiet=quiet)
    moved = f", objects moved over {100 * r['moved_fraction']:.0f} % of azimuths" if r["moved_fraction"] else ""
    click.echo(
        f"simulate omni: {r['frames']} frames, {r['route']} route {r['route_length_m']:.1f} m (id {r['route_id']}){moved}, "
        f"{r['render_s_per_frame']:.3f} s/frame render, {r['seconds']:.1f} s -> {r['out']}"
    )


@simulate_group.command("tiles")
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--seed", type=int, default=None,
              show_default=dflt("simulate.seed"),
              help="Random seed (same seed and options: identical output).")
@click.option("--grid", default=None, show_default=dflt("simulate.tiles.grid"), help="Grid COLSxROWS, e.g. 5x5.")
@click.option("--tile", default=None,
              show_default=dflt("simulate.tiles.tile_size"),
              help="Tile size in pixels: PX (square) or WIDTHxHEIGHT, e.g. 512.")
@click.option("--overlap", type=float, default=None, show_default=dflt("simulate.tiles.overlap"),
              help="Overlap of neighbours, fraction of the tile (0.1 = 10 %); step = tile x (1 - overlap), whole pixels.")
@click.option("--stage-error", type=float, default=None, show_default=dflt("simulate.tiles.stage_error_px"),
              help="Stage error E in pixels: true position = nominal + uniform(-E, E) per tile and axis.")
@click.option("--order", default=None,
              show_default=dflt("simulate.tiles.order"),
              help="Scan order: row (raster) or snake.")
@click.option("--noise", type=float, default=None,
              show_default=dflt("simulate.tiles.noise_sigma"),
              help="Gaussian noise sigma, grey levels of the 0..255 signal.")
@click.option("--gain", type=float, default=None,
              show_default=dflt("simulate.tiles.gain"),
              help="Per-tile gain spread g: gain = 1 + uniform(-g, g).")
@click.option("--bits", type=int, default=None,
              show_default=dflt("simulate.tiles.bits"),
              help="Bits per sample of the TIFF tiles: 8 or 16.")
@click.option("--value-range", default=None, show_default="simulate.tiles.value_range = [], the full range of --bits",
              help="Stored values LO,HI of grey 0 and 255, e.g. 700,2011 (16-bit using 1/50 of its range).")
@click.option("--blank-tiles", default=None,
              show_default="simulate.tiles.blank_tiles = [], none",
              help="Scan indices of blank (background only) tiles, e.g. 0,7.")
@click.option("--blank-count", type=int, default=None,
              show_default=dflt("simulate.tiles.blank_count"),
              help="Number of further blank tiles drawn at random.")
@click.option("--hot-pixels", type=int, default=None,
              show_default=dflt("simulate.tiles.hot_pixels"),
              help="Hot sensor pixels (same in every tile, stored at the maximum).")
@config_option
@quiet_option
def tiles_cmd(out: Path, seed, grid, tile, overlap, stage_error, order, noise, gain, bits, value_range,
              blank_tiles, blank_count, hot_pixels, config_file, quiet) -> None:
    """Simulate a stage-scanned tile grid (microscope) into the folder OUT.

    Writes tile_000.tif ... in scan order, TileConfiguration.txt (the nominal grid: the
    prior), TileConfiguration.truth.txt (true positions) and grid.json; positions are the
    tiles' top-left pixels in mosaic pixels, x right, y down. Defaults come from
    configs/simulate.toml ([simulate.tiles]); options override them. Import the grid with
    `mosaicmap import-tiles OUT/TileConfiguration.txt LOG --pixel-size M`.
    """
    from pipeline.simulate.tiles import simulate_tiles

    cfg = setup(config_file, quiet)
    given = dict(
        seed=seed, grid=grid, tile=tile, overlap=overlap, stage_error=stage_error, order=order, noise=noise,
        gain=gain, bits=bits, value_range=value_range, blank_tiles=blank_tiles, blank_count=blank_count,
        hot_pixels=hot_pixels,
    )
    r = simulate_tiles(out, cfg, given, quiet=quiet)
    extra = ""
    if r["blank_tiles"]:
        extra += f", {len(r['blank_tiles'])} blank"
    if r["hot_pixels"]:
        extra += f", {r['hot_pixels']} hot pixels"
    click.echo(
        f"simulate tiles: {r['cols']} x {r['rows']} tiles of {r['tile_size'][0]} x {r['tile_size'][1]} px "
        f"({r['order']} order), step {r['step_px'][0]} x {r['step_px'][1]} px (overlap {r['overlap_px'][0]} x "
        f"{r['overlap_px'][1]} px), stage error +-{r['stage_error_px']:g} px, {r['bits']}-bit values "
        f"{r['value_range'][0]}..{r['value_range'][1]}{extra}, {r['seconds']:.1f} s -> {r['out']}"
    )
