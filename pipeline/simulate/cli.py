"""``mosaicmap simulate``: simulators that write drive logs with ground truth."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli_common import config_option, quiet_option, setup


@click.group("simulate")
def simulate_group() -> None:
    """Simulate drive logs (with ground truth and the world) for tests and benchmarks."""


@simulate_group.command("floor")
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--seed", type=int, default=None, help="Random seed (same seed and options: identical output).")
@click.option("--area", default=None, help="Floor area XxY in metres, e.g. 5x5.")
@click.option("--pixel-size", type=float, default=None, help="Map pixel size in metres (camera ground pixel).")
@click.option("--frame-size", default=None, help="Raw frame WIDTHxHEIGHT in pixels, e.g. 320x240.")
@click.option("--route", default=None, help="Route: lawnmower, loop, figure8 or random.")
@click.option("--odometry-drift", type=float, default=None,
              help="Odometry error gradient alpha (error ~ alpha x distance); 0 = perfect odometry.")
@click.option("--noise", type=float, default=None, help="Gaussian sensor noise sigma, grey levels.")
@click.option("--texture", default=None, help="'procedural' or the path of a photograph of a floor.")
@click.option("--world", type=click.Path(path_type=Path), default=None,
              help="Reuse the world of a previous simulated log (a later day).")
@click.option("--changes", type=int, default=None, help="Number of floor changes applied to the world.")
@click.option("--illumination", type=float, default=None, help="Global illumination factor (0.8 = 20 % darker).")
@click.option("--height-jitter", type=float, default=None,
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
@click.option("--seed", type=int, default=None, help="Random seed (same seed and options: identical output; with --world, default the previous log's seed + 1: a new run).")
@click.option("--room", default=None, help="Room size XxY in metres, e.g. 11x6 (a fresh world only).")
@click.option("--route", default=None, help="Route: loop, figure8, random or lawnmower (a fresh world only).")
@click.option("--world", type=click.Path(path_type=Path), default=None,
              help="Reuse the world and route of a previous omni log (a repeat run).")
@click.option("--night", is_flag=True, default=None, help="Night lighting: ceiling lamps, dark windows.")
@click.option("--height-offset", type=float, default=None,
              help="Render the camera this many metres above its declared height (a height error).")
@click.option("--move-objects", type=float, default=None,
              help="Move objects so that about this fraction of horizon azimuths sees them differently.")
@click.option("--offset", type=float, default=None, help="Drive parallel to the route, this many metres to its left.")
@click.option("--angle", type=float, default=None,
              help="Drive across the route at this angle (degrees), zig-zagging within the configured amplitude.")
@click.option("--noise", type=float, default=None, help="Gaussian sensor noise sigma, grey levels.")
@click.option("--odometry-drift", type=float, default=None,
              help="Odometry error gradient alpha (error ~ alpha x distance); 0 = perfect odometry.")
@click.option("--route-id", default=None,
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
