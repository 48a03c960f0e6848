"""Commands on a map repository: show, log, tag, rollback, gc, poses, quicklook.

None of them is configured or prints progress (no --config, no --quiet: their help says so).

REPO is a local directory (or ``file://DIR``) or ``s3://BUCKET/PREFIX``. A VERSION is
``latest`` (the branch tip, the default), a tag, a snapshot id (or a unique prefix of one
of at least 6 characters, as ``mosaicmap log`` prints them) or a branch name.
"""

from __future__ import annotations

import logging
from pathlib import Path

import click
import numpy as np

from pipeline.cli.common import no_config, no_quiet
from pipeline.errors import BadInput
from pipeline.map_version import open_repo, open_version

log = logging.getLogger(__name__)

QUICKLOOK_MAX_PX = 2048
SHORT_ID = 8
LAYER_CHOICES = ("intensity", "coverage", "texture", "uniqueness", "updated")

version_option = click.option(
    "--version", "version", default=None, metavar="VERSION",
    help="Map version: latest (default), a tag, a snapshot id (or unique prefix) or a branch.")
branch_option = click.option("--branch", default="main", show_default=True, help="Branch of the repository.")


# --- show ---------------------------------------------------------------------------------


def _codecs(arr) -> str:
    parts = []
    for c in arr.compressors or ():
        level = getattr(c, "level", None)
        name = type(c).__name__.removesuffix("Codec").lower()
        parts.append(f"{name}({level})" if level is not None else name)
    return "+".join(parts) or "none"


def _versions_lines(repo) -> list[str]:
    lines = ["branches:"]
    for name, sid in repo.branches().items():
        lines.append(f"  {name:<24} {sid}")
    tags = repo.tags()
    lines.append("tags:" if tags else "tags: none")
    for name, sid in tags.items():
        lines.append(f"  {name:<24} {sid}")
    return lines


@no_config
@no_quiet
@click.command("show")
@click.argument("repo")
@version_option
def show_cmd(repo: str, version: str | None) -> None:
    """Describe the map in REPO as stored: id, grid, levels, layers, poses, versions."""
    mrepo, sid, root, info = open_version(repo, version, "main", routes_only_ok=True)
    out = _floor_lines(repo, version, sid, root, info) if info is not None else [
        f"map repository: {repo}", f"version:        {version or 'latest'} = snapshot {sid}", "floor:          none"]
    out.extend(_routes_lines(root))
    out.extend(_versions_lines(mrepo))
    click.echo("\n".join(out))


def _routes_lines(root) -> list[str]:
    """``mosaicmap show``'s routes part: id, rows, length, spacing, version, sources."""
    from mapstore.routes import list_routes, read_route

    ids = list_routes(root)
    if not ids:
        return ["routes:         none"]
    out = [f"routes ({len(ids)}; /routes/<id>/lines uint8 rows x azimuths, /routes/<id>/poses float32 x, y, theta):"]
    for rid in ids:
        try:
            rec = read_route(root, rid)
        except ValueError as e:
            out.append(f"  {rid:<16} unreadable: {e}")
            continue
        out.append(f"  {rid:<16} {rec.rows:>7} rows x {rec.lines.shape[1]} azimuths  {rec.length_m:8.2f} m  "
                   f"spacing {rec.spacing_m:g} m  {rec.samples_per_degree:g} sample/deg  version {rec.version}  "
                   f"runs {rec.meta.get('runs', len(rec.sources))}")
        for src in rec.sources:
            out.append(f"      {src.get('log_id', '?')!s:<20} {src.get('frames', '?')!s:>6} frames  "
                       f"version {src.get('version', '?')}  {src.get('path', '')}")
    return out


def _geo_text(root) -> str:
    """Where the map lies on Earth (its geo_reference root attribute), for ``show``."""
    from mapstore.layout import read_geo_reference

    try:
        geo = read_geo_reference(root)
    except ValueError as e:
        return f"unreadable geo_reference ({e})"
    if geo is None:
        return "no geographic reference (x, y are local metres)"
    return (f"origin at latitude {geo.origin_latitude:.7f}, longitude {geo.origin_longitude:.7f} (WGS 84); "
            "x east, y north")


def _floor_lines(repo: str, version: str | None, sid: str, root, info) -> list[str]:
    """``mosaicmap show``'s floor part."""
    from mapstore.layout import LAYERS, read_poses

    g = info.grid
    xmin, ymin, xmax, ymax = g.bounds
    floor = root["floor"]
    out = [
        f"map repository: {repo}",
        f"version:        {version or 'latest'} = snapshot {sid}, publish version {info.version}",
        f"map id:         {info.map_id}" + (f" (created {info.created})" if info.created else ""),
        "grid (level 0):",
        f"  origin:       ({g.x0:.4f}, {g.y0:.4f}) m = centre of pixel (row 0, col 0)",
        f"  pixel size:   {g.pixel_size:g} m",
        f"  size:         {g.width} x {g.height} px (cols x rows) = {xmax - xmin:.3f} x {ymax - ymin:.3f} m",
        f"  bounds:       x {xmin:.4f} .. {xmax:.4f} m, y {ymin:.4f} .. {ymax:.4f} m",
        "  axes:         columns along +x, rows along -y (north up); OME axes (y, x) in metres, y = -world y",
        f"  geo:          {_geo_text(root)}",
        f"storage:        chunks {info.spec.chunk_px} px, shards {info.spec.shard_px} px, "
        f"layer cells {info.spec.layer_cell_px} px, zstd level {info.spec.zstd_level}",
        f"levels ({info.levels}, rows x cols, OME-Zarr 0.5 multiscales 'intensity', uint8, 0 = no data):",
    ]
    for k in range(info.levels):
        arr = floor[str(k)]
        lg = g.level(k)
        shard = "x".join(map(str, arr.shards)) if arr.shards else "none"
        out.append(f"  floor/{k:<3} {arr.shape[0]:>6} x {arr.shape[1]:<6} {arr.dtype}  pixel {lg.pixel_size:g} m  "
                   f"chunks {'x'.join(map(str, arr.chunks))}  shards {shard}  {_codecs(arr)}  "
                   f"fill {arr.fill_value}")
    out.append("layers (rows x cols):")
    for name in LAYERS:
        arr = floor["layers"][name]
        lg = info.layer_grid(name)
        attrs = arr.attrs.asdict()
        out.append(f"  floor/layers/{name:<11} {arr.shape[0]:>5} x {arr.shape[1]:<5} {arr.dtype}  "
                   f"cells of {attrs.get('cell_px')} px = {lg.pixel_size:g} m  "
                   f"chunks {'x'.join(map(str, arr.chunks))}  {_codecs(arr)}  fill {arr.fill_value}")
        out.append(f"      {attrs.get('description', '')} [{attrs.get('units', '')}]")
    poses = read_poses(root)
    out.append(f"poses:          {len(poses)} frames from {len(poses.sources)} drive log(s)")
    for i, src in enumerate(poses.sources):
        n = int(np.count_nonzero(poses.source == i))
        out.append(f"  {src.get('log_id', i)!s:<24} {n:>7} frames  version {src.get('version', '?')}  "
                   f"{src.get('path', '')}")
    return out


# --- log ----------------------------------------------------------------------------------


def _dig(d: dict, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def key_figures(metadata: dict) -> str:
    """Short summary of a commit's metadata (the build report under "report", if any)."""
    rep = metadata.get("report") if isinstance(metadata.get("report"), dict) else metadata
    parts = []
    v = metadata.get("version")
    if v is not None:
        parts.append(f"version {v}")
    frames = _dig(rep, "optimization", "frames") or _dig(rep, "ingest", "frames_accepted") or rep.get("frames")
    if frames is not None:
        parts.append(f"{frames} frames")
    acc, cand = _dig(rep, "links", "accepted"), _dig(rep, "links", "candidates")
    if acc is not None:
        parts.append(f"{acc}/{cand} links" if cand is not None else f"{acc} links")
    rms = _dig(rep, "optimization", "residual_rms_px")
    if isinstance(rms, (int, float)):
        parts.append(f"residual RMS {rms:.4f} px")
    return ", ".join(parts)


@no_config
@no_quiet
@click.command("log")
@click.argument("repo")
@branch_option
def log_cmd(repo: str, branch: str) -> None:
    """List the commits of a branch of REPO, newest first: id, date, tags, message, figures."""
    mrepo = open_repo(repo)
    try:
        entries = mrepo.log(branch)
    except ValueError as e:
        raise BadInput(repo, str(e)) from None
    for e in entries:
        tags = f" [{', '.join(e['tags'])}]" if e["tags"] else ""
        figures = key_figures(e["metadata"])
        when = e["written_at"].replace("T", " ").replace("+00:00", "Z")
        click.echo(f"{e['id'][:SHORT_ID]}  {when}{tags}  {e['message']}" + (f"  ({figures})" if figures else ""))


# --- tag, rollback ------------------------------------------------------------------------


@no_config
@no_quiet
@click.command("tag")
@click.argument("repo")
@click.argument("snapshot")
@click.argument("name")
def tag_cmd(repo: str, snapshot: str, name: str) -> None:
    """Tag version SNAPSHOT of REPO (snapshot id, prefix, tag or branch) as NAME."""
    mrepo = open_repo(repo)
    try:
        with mrepo.commit_lock():
            sid = mrepo.tag(snapshot, name)
    except ValueError as e:
        raise BadInput(repo, str(e)) from None
    click.echo(f"tagged {sid} as {name}")


def _parse_age(text: str) -> float:
    """``--older-than`` as seconds: a number with a unit s, m, h or d (``7d``, ``12h``, ``0``)."""
    units = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}
    t = text.strip().lower()
    unit = units.get(t[-1:], None)
    try:
        value = float(t[:-1] if unit else t) * (unit or 1.0)
    except ValueError:
        value = float("nan")
    if not np.isfinite(value) or value < 0:
        raise BadInput("--older-than", f"expected an age like 7d, 12h, 30m, 0 (seconds), got {text!r}")
    return value


@no_config
@no_quiet
@click.command("gc")
@click.argument("repo")
@click.option("--older-than", "older_than", default="7d", show_default=True, metavar="AGE",
              help="Only what was written longer ago than AGE (7d, 12h, 30m, 0): a build running "
                   "meanwhile keeps its fresh objects.")
@click.option("--expire", is_flag=True,
              help="First expire the history older than AGE (icechunk expiry): untagged versions before it "
                   "are freed too; tagged versions stay readable by their tags, but `log` starts at AGE.")
@click.option("--dry-run", is_flag=True, help="Report what would be freed; change nothing.")
def gc_cmd(repo: str, older_than: str, expire: bool, dry_run: bool) -> None:
    """Free the space of snapshots no branch or tag reaches (icechunk garbage collection).

    Every tagged version and every branch tip, and the history `log` shows, stay as they are;
    what nothing reaches any more (a commit whose branch was reset, a publish that lost a
    race) and was written more than AGE ago is deleted. Exit code 0; prints what was freed.
    """
    from datetime import datetime, timedelta, timezone

    age = _parse_age(older_than)
    mrepo = open_repo(repo)
    r = mrepo.gc(datetime.now(timezone.utc) - timedelta(seconds=age), expire=expire, dry_run=dry_run)
    verb = "would free" if dry_run else "freed"
    expired = ""
    if expire:
        expired = f"{'would expire' if dry_run else 'expired'} {r['expired_snapshots']} untagged snapshot(s); "
    click.echo(f"{repo}: {expired}{verb} {r['bytes_deleted']} bytes older than {older_than}: "
               f"{r['snapshots_deleted']} snapshots, "
               f"{r['manifests_deleted']} manifests, {r['chunks_deleted']} chunks, "
               f"{r['transaction_logs_deleted']} transaction logs")


@no_config
@no_quiet
@click.command("rollback")
@click.argument("repo")
@click.argument("tag")
@branch_option
def rollback_cmd(repo: str, tag: str, branch: str) -> None:
    """Move a branch of REPO back to version TAG; the old tip stays reachable by a tag."""
    mrepo = open_repo(repo)
    try:
        saved = mrepo.rollback(tag, branch)
    except ValueError as e:
        raise BadInput(repo, str(e)) from None
    click.echo(f"branch {branch} now at {tag} ({mrepo.resolve(None, branch)}); previous tip tagged {saved}")


# --- poses --------------------------------------------------------------------------------


@no_config
@no_quiet
@click.command("poses")
@click.argument("repo")
@version_option
@click.option("--out", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="CSV to write: t,x,y,theta,log_id,frame,sigma_x,sigma_y,sigma_theta,version.")
def poses_cmd(repo: str, version: str | None, out: Path) -> None:
    """Write the poses of the frames the map in REPO was built from to a CSV."""
    from mapstore.layout import read_poses

    _, sid, root, _ = open_version(repo, version, "main")
    try:
        poses = read_poses(root)
    except ValueError as e:
        raise BadInput(repo, f"version {version or 'latest'} ({sid}): {e}") from None
    poses.to_csv(out)
    click.echo(f"{len(poses)} poses from {len(poses.sources)} drive log(s) -> {out}")


# --- quicklook ----------------------------------------------------------------------------


@no_config
@no_quiet
@click.command("quicklook")
@click.argument("repo")
@version_option
@click.option("--level", "level", type=int, default=None,
              help=f"Pyramid level of the intensity (default: the finest that fits {QUICKLOOK_MAX_PX} px).")
@click.option("--layer", type=click.Choice(LAYER_CHOICES), default="intensity", show_default=True,
              help="What to draw; layers other than intensity are coloured, no data is black.")
@click.option("--out", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Image file to write (PNG; the format follows the extension).")
@click.option("--route", "route", default=None, metavar="ID",
              help="Draw the route panorama ID instead of the floor: rows = path length (one per "
                   "spacing, first row at the top), columns = azimuth (samples_per_degree per degree, "
                   "0 = vehicle forward, counter-clockwise).")
@click.option("--annotate", is_flag=True,
              help="A figure to read: axes in metres of the map frame, scale bar, north arrow (+y), colour bar "
                   "for layers, small rasters magnified (nearest) to 600 px or more; with --route, axes azimuth "
                   "(deg) and path length (m). Without it: one image pixel per stored pixel or cell.")
def quicklook_cmd(repo: str, version: str | None, level: int | None, layer: str, out: Path,
                  route: str | None, annotate: bool) -> None:
    """Draw a level or a layer of the map in REPO (or a route panorama) as an image, for a quick look."""
    from pipeline.images import write_image
    from pipeline.quicklook import annotate_layer, reduce_blocks, reduction_factor, render_layer

    _, sid, root, info = open_version(repo, version, "main", routes_only_ok=route is not None)
    if route is not None:
        _quicklook_route(root, sid, route, out, level, layer, annotate)
        return
    floor = root["floor"]
    if layer == "intensity":
        if level is None:
            level = next((k for k in range(info.levels) if max(info.grid.level(k).shape) <= QUICKLOOK_MAX_PX),
                         info.levels - 1)
        if not 0 <= level < info.levels:
            raise BadInput("--level", f"level {level} does not exist in {repo} (levels 0..{info.levels - 1})")
        data, what, grid = floor[str(level)][...], f"floor/{level}", info.grid.level(level)
    else:
        if level is not None:
            raise BadInput("--level", "applies to --layer intensity only (layers have one resolution)")
        data = floor["layers"][layer][...]
        f = reduction_factor(data.shape, QUICKLOOK_MAX_PX)
        data = reduce_blocks(data, f, "max" if layer in ("coverage", "updated") else "mean")
        what = f"floor/layers/{layer}" + (f" (reduced {f}x)" if f > 1 else "")
        grid = info.layer_grid(layer).coarsened(f)
    drawn = render_layer(layer, data)
    img, legend = drawn.pixels, drawn.legend
    if annotate:
        img = annotate_layer(drawn, grid, f"{what} of {sid[:SHORT_ID]} ({data.shape[1]} x {data.shape[0]} px)")
        legend += "; annotated: axes in metres, scale bar, north arrow"
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        write_image(out, img)
    except OSError as e:
        raise BadInput(out, f"cannot write the image: {e}") from None
    click.echo(f"{what} of {sid} ({img.shape[1]} x {img.shape[0]} px; {legend}) -> {out}")


def _quicklook_route(root, sid: str, route: str, out: Path, level: int | None, layer: str,
                     annotate: bool = False) -> None:
    """Write the ORP ``route`` as a grey image (rows x azimuths, full resolution), or
    annotated (:func:`pipeline.quicklook.annotate_route`)."""
    from mapstore.routes import list_routes, read_route
    from pipeline.images import write_image

    if level is not None or layer != "intensity":
        raise BadInput("--route", "draws the route panorama: --level and --layer do not apply")
    try:
        rec = read_route(root, route)
    except KeyError:
        raise BadInput("--route", f"the map has no route {route!r} (routes: {', '.join(list_routes(root)) or 'none'})") from None
    except ValueError as e:
        raise BadInput("--route", str(e)) from None
    img = rec.lines
    if annotate:
        from pipeline.quicklook import annotate_route

        img = annotate_route(rec, f"routes/{route} of {sid[:SHORT_ID]} ({rec.lines.shape[1]} azimuths x "
                                  f"{rec.rows} rows)")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        write_image(out, img)
    except OSError as e:
        raise BadInput(out, f"cannot write the image: {e}") from None
    click.echo(f"routes/{route} of {sid} ({rec.lines.shape[1]} azimuths x {rec.rows} rows = {rec.length_m:.2f} m "
               f"at {rec.spacing_m:g} m; grey levels{'; annotated' if annotate else ''}) -> {out}")
