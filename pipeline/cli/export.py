"""Commands: export, verify, apply-delta (vehicle bundles and OME-Zarr extracts).

Each command parses its options, calls one function of :mod:`pipeline.export_run` (where the
work and its documentation are: :func:`~pipeline.export_run.export_map`,
:func:`~pipeline.export_run.verify_file`, :func:`~pipeline.export_run.apply_delta_file`),
writes the report and prints the summary. ``keys new`` makes the map owner's key pair
(:mod:`pipeline.cli.keys`); ``export --sign KEY`` signs bundles and deltas.
"""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.common import config_option, no_config, no_quiet, quiet_option, report_option, setup, write_report
from pipeline.cli.map import branch_option, version_option
from pipeline.errors import BadInput


# --- options ------------------------------------------------------------------------------


def _parse_region(text: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise BadInput("--region", f"expected x0,y0,x1,y1 in metres, got {text!r}") from None
    if len(values) != 4:
        raise BadInput("--region", f"expected 4 numbers x0,y0,x1,y1, got {len(values)}")
    return values


def _parse_levels(text: str) -> list[int]:
    try:
        return [int(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise BadInput("--levels", f"expected level numbers like 0,1,2, got {text!r}") from None


def _parse_layers(text: str) -> list[str]:
    names = [p.strip() for p in text.split(",") if p.strip()]
    if not names:
        raise BadInput("--layers", "no layer named")
    return names


# --- export -------------------------------------------------------------------------------


@click.command("export")
@click.argument("repo")
@click.argument("out", type=click.Path(path_type=Path))
@version_option
@branch_option
@click.option("--region", default=None, metavar="X0,Y0,X1,Y1",
              help="Export the world box with these opposite corners (metres).")
@click.option("--corridor", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="PATH.csv",
              help="Export a corridor along this polyline: a CSV with columns x,y in metres "
                   "(a drive log's t,x,y,theta file works too).")
@click.option("--width", type=float, default=None, metavar="METRES",
              help="Corridor width in metres (default [export] corridor_width_m).")
@click.option("--levels", default=None, metavar="0,1,2",
              help="Pyramid levels of the intensity (default [export] levels; empty = all).")
@click.option("--layers", default=None, metavar="intensity,texture",
              help="Layers: intensity, coverage, texture, uniqueness, updated (default [export] layers).")
@click.option("--routes", "routes", default=None, metavar="all|none|ID[,ID...]",
              help="Route panoramas (/routes/<id>) to export: all, none or these ids (default [export] "
                   "routes). With --region or --corridor a route is cut to its rows whose poses lie within "
                   "[export] route_margin_m of the selection; a route without such a row is left out.")
@click.option("--since", default=None, metavar="VERSION",
              help="Write a delta: only the tiles changed since VERSION (an ancestor), to apply with "
                   "`mosaicmap apply-delta` to the bundle of VERSION with the same selection.")
@click.option("--format", "fmt", type=click.Choice(["bundle", "ome-zarr"]), default="bundle", show_default=True,
              help="bundle: one sealed zip file for vehicles; ome-zarr: a plain OME-Zarr directory for "
                   "viewers: open OUT/map.zarr/floor (intensity) or OUT/map.zarr/layers/<name> in napari or "
                   "neuroglancer; OUT/manifest.json lists the files.")
@click.option("--sign", "sign_key", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="KEY",
              help="Sign the bundle or delta with this private key (`mosaicmap keys new`): vehicles load only "
                   "bundles signed by a key they trust. A signed delta also carries the signature of the bundle "
                   "apply-delta makes from it, which costs a full export's encoding of the new version.")
@click.option("--reloc-index/--no-reloc-index", "reloc_index", default=None,
              help="Store the tracker's relocalization index (ORB features per level-0 tile, "
                   "[tracker.reloc]) in the bundle. Default: [export] reloc_index (true) when intensity "
                   "level 0 is exported; never by default in an OME-Zarr directory.")
@config_option
@report_option
@quiet_option
def export_cmd(repo: str, out: Path, version: str | None, branch: str, region: str | None, corridor: Path | None,
               width: float | None, levels: str | None, layers: str | None, routes: str | None, since: str | None,
               fmt: str, sign_key: Path | None, reloc_index: bool | None, config_file, report, quiet) -> None:
    """Export a region or corridor of a map version in REPO to OUT: a vehicle bundle, a
    delta (--since) or an OME-Zarr directory (--format ome-zarr); --sign KEY signs it."""
    from pipeline.export_run import export_map, export_summary

    cfg = setup(config_file, quiet)
    rep = export_map(repo, out, cfg=cfg, version=version, branch=branch,
                     region=_parse_region(region) if region is not None else None, corridor=corridor,
                     width_m=width, levels=_parse_levels(levels) if levels is not None else None,
                     layers=_parse_layers(layers) if layers is not None else None, routes=routes, since=since,
                     fmt=fmt, sign_key=sign_key, reloc_index=reloc_index, quiet=quiet)
    write_report(report, rep)
    click.echo(export_summary(rep))


# --- verify, apply-delta ------------------------------------------------------------------


key_option = click.option(
    "--key", "keys", multiple=True, metavar="PUB",
    help="A trusted public key (KEY.pub of `mosaicmap keys new`; repeatable): the bundle must be signed by one "
         "of them.")


@no_config
@no_quiet
@click.command("verify")
@click.argument("bundle", type=click.Path(path_type=Path))
@key_option
@report_option
def verify_cmd(bundle: Path, keys: tuple[str, ...], report: Path | None) -> None:
    """Check BUNDLE (or a delta) completely: its seal, manifest, every member's name,
    checksum and size bounds, and with --key its signature. Exit code 2 naming the bad
    part when anything is wrong."""
    from pipeline.export_run import verify_file, verify_problem, verify_summary

    rep = verify_file(bundle, keys=keys)
    write_report(report, rep)
    if not rep["ok"]:
        raise BadInput(bundle, verify_problem(rep))
    click.echo(verify_summary(rep))


@no_config
@no_quiet
@click.command("apply-delta")
@click.argument("base", type=click.Path(path_type=Path))
@click.argument("delta", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@key_option
@report_option
def apply_delta_cmd(base: Path, delta: Path, out: Path, keys: tuple[str, ...], report: Path | None) -> None:
    """Patch bundle BASE with DELTA into the new bundle OUT (both inputs and the result
    are verified; a delta made for another base is refused with exit code 2). With --key
    both inputs must be signed by a trusted key, and OUT carries the map owner's
    signature of the patched bundle (which a signed delta holds)."""
    from pipeline.export_run import apply_delta_file, apply_delta_summary

    rep = apply_delta_file(base, delta, out, keys=keys)
    write_report(report, rep)
    click.echo(apply_delta_summary(rep))
