"""``mosaicmap import-tiles``: a Fiji/ImageJ tile grid (``TileConfiguration.txt``) -> drive log v1.

Input
    A Grid/Collection stitching ``TileConfiguration.txt``: a ``dim = 2`` line, comment lines
    (``#``) and blank lines, and one line per tile ``file; ; (x, y)`` with the position of the
    tile's top-left pixel corner in mosaic pixels (x along image columns, y along image
    rows; the middle field, a series index of multi-series files, must be empty). Tile
    files are found relative to the configuration file's folder. The images are taken as
    rectified ground images (camera normal to the plane) of ``--pixel-size M`` metres per
    pixel; every tile must have the same size.

Output (a drive log, written atomically: the whole log appears under OUT, or nothing)
    ``images/<file name>``: the tiles copied byte for byte. Copying (instead of
    re-encoding to PNG) keeps the bit depth, colour and metadata exactly, lets a checksum
    tie each frame to its source, and costs only a file copy (12 x 3 MB for the real set).
    ``frames.csv``: one frame per tile at ``t = 0, 1, 2, ...`` seconds in file order (the
    acquisition order of a stage scan). ``odometry.csv``: one sample per tile at its
    frame's time, the nominal stage position converted with :mod:`mapstore.grid`'s
    conventions (:func:`tile_pose`): the pose is the tile's image *centre* on a north-up
    grid whose pixel (0, 0) centre is the world origin, i.e.
    ``x = (X + (W - 1) / 2) * M``, ``y = -(Y + (H - 1) / 2) * M``, ``theta = 0``.
    ``drive.toml``: ``[camera] pixel_size_m = M`` and a ``[source]`` table (provenance).

Peer positions (evaluation only)
    ``--peer FILE`` (e.g. Fiji's ``TileConfiguration.registered.txt``): another tile
    configuration of the same tiles, converted the same way and written as
    ``peer_positions.csv`` (``t,x,y,theta``, one row per frame). It is somebody else's
    answer, not ground truth, so it is not named ``ground_truth.csv``; the build never
    reads it. :func:`tile_positions_from_poses` converts poses back to tile positions in
    pixels for comparisons with such a file.

Report keys (``--report FILE``): ``tile_configuration``, ``out``, ``frames``,
``tile_width``, ``tile_height``, ``pixel_size_m``, ``extent_px`` ([width, height] of the
nominal mosaic), ``peer_positions`` (file name or null), ``peer_rms_offset_px`` (RMS of
peer minus nominal tile positions, or null), ``seconds``.
"""

from __future__ import annotations

import logging
import math
import re
import shutil
import time
from pathlib import Path

import click
import numpy as np
import OpenImageIO as oiio

from mapstore.grid import MapGrid, frame_centre
from pipeline.cli_common import config_option, progress, quiet_option, report_option, setup, write_report
from pipeline.drivelog import CameraSpec, read_drive_log, write_drive_log, write_pose_csv
from pipeline.errors import BadInput, JobFailed
from pipeline.fsutil import atomic_dir

log = logging.getLogger(__name__)

PEER_FILE = "peer_positions.csv"

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_TILE_LINE = re.compile(rf"^(?P<file>[^;]+);(?P<series>[^;]*);\s*\(\s*(?P<x>{_NUM})\s*,\s*(?P<y>{_NUM})\s*\)\s*$")
_DIM_LINE = re.compile(r"^dim\s*=\s*(?P<dim>\S+)\s*$")


# --- pure helpers ------------------------------------------------------------------------


def read_tile_configuration(path: str | Path) -> list[tuple[str, float, float]]:
    """Parse a Fiji Grid/Collection ``TileConfiguration.txt`` -> ``[(file, x_px, y_px), ...]``.

    Positions are the tiles' top-left corners in mosaic pixels, in file order.

    Raises:
        BadInput: missing file, ``dim`` other than 2 or missing, a malformed tile line,
            a duplicate tile, no tiles (naming ``file:line``).
    """
    path = Path(path)
    if not path.is_file():
        raise BadInput(path, "tile configuration not found")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise BadInput(path, "not a UTF-8 text file") from None
    tiles: list[tuple[str, float, float]] = []
    seen: dict[str, int] = {}
    dim_seen = False
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{lineno}"
        m = _DIM_LINE.match(line)
        if m:
            if m["dim"] != "2":
                raise BadInput(where, f"dim = {m['dim']}: only 2-D tile configurations are supported")
            dim_seen = True
            continue
        m = _TILE_LINE.match(line)
        if not m:
            raise BadInput(where, f"malformed tile line {line!r} (expected 'file; ; (x, y)')")
        if not dim_seen:
            raise BadInput(where, "tile line before the 'dim = 2' line")
        name = m["file"].strip()
        if not name:
            raise BadInput(where, "empty tile file name")
        if m["series"].strip():
            raise BadInput(where, f"series index {m['series'].strip()!r}: multi-series tile files are not supported")
        x, y = float(m["x"]), float(m["y"])
        if not (math.isfinite(x) and math.isfinite(y)):
            raise BadInput(where, f"position ({m['x']}, {m['y']}) is not finite")
        if name in seen:
            raise BadInput(where, f"tile {name!r} is listed twice (also on line {seen[name]})")
        seen[name] = lineno
        tiles.append((name, x, y))
    if not dim_seen:
        raise BadInput(path, "no 'dim = 2' line (not a Fiji TileConfiguration file?)")
    if not tiles:
        raise BadInput(path, "lists no tiles")
    return tiles


def _tile_grid(pixel_size: float) -> MapGrid:
    """The mosaic's pixel grid: pixel (0, 0) centred on the world origin, north up."""
    return MapGrid(0.0, 0.0, float(pixel_size), 1, 1)


def tile_pose(x_px: float, y_px: float, shape: tuple[int, int], pixel_size: float) -> np.ndarray:
    """Pose ``(x, y, theta)`` (metres, radians) of a tile whose top-left pixel is at mosaic ``(x_px, y_px)``.

    The pose is the tile's image centre (:func:`mapstore.grid.frame_centre`) on the mosaic
    grid; ``theta = 0`` (tile columns along +x, rows along -y).
    """
    cx, cy = frame_centre(shape)
    x, y = _tile_grid(pixel_size).pixel_to_world(x_px + cx, y_px + cy)
    return np.array([float(x), float(y), 0.0])


def tile_positions_from_poses(poses: np.ndarray, shape: tuple[int, int], pixel_size: float) -> np.ndarray:
    """Inverse of :func:`tile_pose`: poses ``(N, 3)`` (or ``(N, 4)`` with t first) -> ``(N, 2)`` tile positions in pixels.

    The result is the TileConfiguration-style top-left corner ``(x_px, y_px)`` of a tile
    whose image centre is at the pose. Fiji's model is translation only; a pose's small
    rotation is ignored (the centre is what is compared, so it does not bias the result).
    """
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] not in (3, 4):
        raise ValueError(f"poses must have shape (N, 3) or (N, 4), got {poses.shape}")
    xy = poses[:, -3:-1]
    cx, cy = frame_centre(shape)
    col, row = _tile_grid(pixel_size).world_to_pixel(xy[:, 0], xy[:, 1])
    return np.stack([col - cx, row - cy], axis=1)


def _image_shape(path: Path, where: str) -> tuple[int, int]:
    """``(H, W)`` of an image file from its header (no pixel decoding)."""
    if not path.is_file():
        raise BadInput(where, f"tile image {str(path)!r} not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = (oiio.geterror().strip() or "cannot open").splitlines()[0]
        raise BadInput(where, f"tile image {str(path)!r} is unreadable: {msg}")
    try:
        spec = inp.spec()
        return spec.height, spec.width
    finally:
        inp.close()


def _tile_lines(path: Path) -> dict[str, int]:
    """Line number of each tile in a (valid) tile configuration, for messages."""
    out = {}
    for lineno, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        m = _TILE_LINE.match(raw.strip())
        if m:
            out.setdefault(m["file"].strip(), lineno)
    return out


# --- import ------------------------------------------------------------------------------


def import_tiles(
    tile_config: str | Path,
    out: str | Path,
    *,
    pixel_size: float,
    peer: str | Path | None = None,
    quiet: bool = True,
) -> dict:
    """Import the tiles of ``tile_config`` as a new drive log ``out``; returns the summary.

    Raises :class:`BadInput` on bad input; nothing is left under ``out`` then.
    """
    t_begin = time.perf_counter()
    tile_config, out = Path(tile_config), Path(out)
    if not math.isfinite(pixel_size) or pixel_size <= 0:
        raise BadInput("--pixel-size", f"must be a positive number of metres, got {pixel_size}")
    replace = check_out_dir(out)
    tiles = read_tile_configuration(tile_config)
    if len(tiles) < 2:
        raise BadInput(tile_config, f"lists {len(tiles)} tile, a drive log needs at least 2 (odometry needs 2 samples)")
    lines = _tile_lines(tile_config)

    # Sources, destinations and a common tile size.
    base = tile_config.parent
    shape = None
    sources, names = [], []
    for name, _, _ in tiles:
        where = f"{tile_config}:{lines.get(name, '?')}"
        src = Path(name) if Path(name).is_absolute() else base / name
        s = _image_shape(src, where)
        if shape is None:
            shape = s
        elif s != shape:
            raise BadInput(
                where,
                f"tile {name!r} is {s[1]} x {s[0]} pixels, the first tile {shape[1]} x {shape[0]} "
                "(all frames of a drive log must have the same size)",
            )
        dst = f"images/{src.name}"
        if dst in names:
            raise BadInput(where, f"two tiles have the file name {src.name!r}")
        sources.append(src)
        names.append(dst)

    frame_t = np.arange(len(tiles), dtype=float)
    poses = np.array([tile_pose(x, y, shape, pixel_size) for _, x, y in tiles])
    odometry = np.column_stack([frame_t, poses])

    peer_odo = None
    peer_rms = None
    if peer is not None:
        peer = Path(peer)
        ptiles = {name: (x, y) for name, x, y in read_tile_configuration(peer)}
        missing = [name for name, _, _ in tiles if name not in ptiles]
        if missing:
            raise BadInput(peer, f"has no position for tile {missing[0]!r} ({len(missing)} tiles missing)")
        extra = sorted(set(ptiles) - {name for name, _, _ in tiles})
        if extra:
            raise BadInput(peer, f"lists tile {extra[0]!r}, which {tile_config} does not")
        ppos = np.array([tile_pose(*ptiles[name], shape, pixel_size) for name, _, _ in tiles])
        peer_odo = np.column_stack([frame_t, ppos])
        d = np.array([ptiles[name] for name, _, _ in tiles]) - np.array([(x, y) for _, x, y in tiles])
        peer_rms = float(np.sqrt(np.mean(np.sum(d**2, axis=1))))

    source = {
        "kind": "tile_configuration",
        "tile_configuration": str(tile_config.resolve()),
        "tile_width_px": shape[1],
        "tile_height_px": shape[0],
        "frame_times": "t = 0, 1, 2, ... s in file order; odometry = nominal stage positions",
    }
    if peer is not None:
        source["peer_configuration"] = str(peer.resolve())
        source["peer_positions"] = PEER_FILE
        source["peer_positions_note"] = "a peer's registration, for evaluation only; not ground truth, never read by the build"

    with atomic_dir(out, replace=replace) as tmp:
        (tmp / "images").mkdir()
        for src, dst in progress(list(zip(sources, names)), label="import-tiles", quiet=quiet):
            shutil.copyfile(src, tmp / dst)
        write_drive_log(
            tmp, CameraSpec(pixel_size_m=float(pixel_size)), frame_t, names, odometry,
            log_id=out.name, extra={"source": source},
        )
        if peer_odo is not None:
            write_pose_csv(tmp / PEER_FILE, peer_odo)
        try:
            read_drive_log(tmp)
        except BadInput as e:
            raise JobFailed(f"{out}: the written drive log does not validate: {e}") from None

    xs = np.array([x for _, x, _ in tiles])
    ys = np.array([y for _, _, y in tiles])
    return {
        "tile_configuration": str(tile_config),
        "out": str(out),
        "frames": len(tiles),
        "tile_width": shape[1],
        "tile_height": shape[0],
        "pixel_size_m": float(pixel_size),
        "extent_px": [float(xs.max() - xs.min() + shape[1]), float(ys.max() - ys.min() + shape[0])],
        "peer_positions": PEER_FILE if peer is not None else None,
        "peer_rms_offset_px": peer_rms,
        "seconds": time.perf_counter() - t_begin,
    }


def check_out_dir(out: Path) -> bool:
    """Refuse a non-empty existing OUT; True when an empty OUT directory is to be replaced."""
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise BadInput(out, "exists and is not a directory")
        if any(out.iterdir()):
            raise BadInput(out, "output directory exists and is not empty (refusing to overwrite)")
        return True
    return False


def summary_line(s: dict) -> str:
    peer = f", peer positions (RMS offset {s['peer_rms_offset_px']:.2f} px)" if s["peer_positions"] else ""
    return (
        f"import-tiles: {s['frames']} tiles of {s['tile_width']} x {s['tile_height']} px at "
        f"{s['pixel_size_m']} m/px, mosaic {s['extent_px'][0]:.0f} x {s['extent_px'][1]:.0f} px{peer} -> {s['out']}"
    )


@click.command("import-tiles")
@click.argument("tile_config", metavar="TILECONFIG", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--pixel-size", type=float, required=True,
              help="Metres per pixel of the tiles (rectified images, camera normal to the plane).")
@click.option("--peer", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Another TileConfiguration of the same tiles (e.g. Fiji's registered one), "
                   "written as peer_positions.csv for evaluation only.")
@config_option
@report_option
@quiet_option
def import_tiles_cmd(tile_config: Path, out: Path, pixel_size: float, peer: Path | None, config_file, report, quiet) -> None:
    """Import a Fiji/ImageJ TILECONFIG (TileConfiguration.txt) as a drive log OUT.

    Tiles are copied byte for byte, one frame per tile at t = 0, 1, 2, ... in file order;
    the odometry is the nominal stage position of each tile's centre.
    """
    setup(config_file, quiet)
    summary = import_tiles(tile_config, out, pixel_size=pixel_size, peer=peer, quiet=quiet)
    write_report(report, summary)
    click.echo(summary_line(summary))
