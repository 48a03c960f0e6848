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
@config_option
@quiet_option
def floor_cmd(out: Path, seed, area, pixel_size, frame_size, route, odometry_drift, noise, texture, world,
              changes, illumination, config_file, quiet) -> None:
    """Simulate a downward-camera drive over a textured floor into the drive log OUT.

    Defaults come from configs/simulate.toml ([simulate.floor]); options override them.
    """
    from pipeline.simulate.floor import simulate_floor

    cfg = setup(config_file, quiet)
    given = dict(
        seed=seed, area=area, pixel_size=pixel_size, frame_size=frame_size, route=route,
        odometry_drift=odometry_drift, noise=noise, texture=texture, world=world, changes=changes,
        illumination=illumination,
    )
    r = simulate_floor(out, cfg, given, quiet=quiet)
    extra = f", {r['changes']} changes" if r["changes"] else ""
    click.echo(
        f"simulate floor: {r['frames']} frames, {r['route']} route {r['route_length_m']:.1f} m{extra}, "
        f"{r['seconds']:.1f} s -> {r['out']}"
    )
