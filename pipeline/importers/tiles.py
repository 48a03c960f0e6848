"""``mosaicmap import-tiles``: a microscope/stage tile grid -> drive log v1.

Two ways in, mirroring Fiji's Grid/Collection stitching:

Input 1: a tile configuration (``import-tiles TILECONFIG OUT``)
    A Grid/Collection ``TileConfiguration.txt``: an optional ``dim = 2`` line (a file
    without one is 2-D; any other ``dim`` is refused), comment lines (``#``) and blank
    lines, and one line per tile ``file; ; (x, y)`` with the position of the tile's top-left
    pixel corner in mosaic pixels (x along image columns, y along image rows; the middle
    field, a series index of multi-series files, must be empty). Tile files are found
    relative to the configuration file's folder. Frames are in file order.

Input 2: a folder of tiles and the scan's grid (``import-tiles DIR OUT --grid CxR ...``)
    No configuration file: the tiles of DIR in acquisition order, either ``--pattern``
    (file names with the tile index: Python's ``{i}`` / ``{i:04d}`` or Fiji's ``{iiii}``,
    indices ``--first-index`` (1) onwards) or ``--glob`` (default: every ``*.tif``,
    ``*.tiff``, ``*.png``, ``*.jpg``, ``*.jpeg``), sorted by name with digit runs compared as
    numbers (``tile2`` before ``tile10``). The number of files must equal the number of grid
    cells (fewer or more is bad input naming both counts). ``--grid CxR`` is C columns by R
    rows; ``--order`` the scan (Fiji's grid types): ``row-by-row``, ``column-by-column``,
    ``snake-rows`` (snake by rows: every other row runs back), ``snake-columns``; ``--first``
    the corner of the first tile: ``top-left`` (default), ``top-right``, ``bottom-left``,
    ``bottom-right``. The first row (or column) runs away from that corner, so for
    ``row-by-row`` / ``snake-rows`` Fiji's "Right & Down" is ``top-left``, "Left & Down"
    ``top-right``, "Right & Up" ``bottom-left``, "Left & Up" ``bottom-right``; for the column
    orders "Down & Right" is ``top-left``, "Down & Left" ``top-right``, "Up & Right"
    ``bottom-left``, "Up & Left" ``bottom-right`` (:func:`grid_cells`). The step between
    neighbouring tiles is ``--step PX`` or ``--step PX,PY`` (mosaic pixels), or ``--overlap
    F`` / ``F,FY`` (a fraction: step = tile size x (1 - F) per axis, tile width for x, height
    for y). The tile in grid column c, row r (0 at the left and top) has its top-left corner
    at ``(c * step_x, r * step_y)`` pixels, as in the TileConfiguration Fiji writes.

Tiles
    The images are taken as rectified ground images (camera normal to the plane) of
    ``--pixel-size M`` metres per pixel; every tile must have the same size.

Output (a drive log, written atomically: the whole log appears under OUT, or nothing)
    ``images/<file name>``: the tiles byte for byte, as hard links to the source files
    (copies where the file system does not allow one). Taking them as they are (instead
    of re-encoding to PNG) keeps the bit depth, colour and metadata exactly and lets a
    checksum tie each frame to its source; a hard link costs no copy (100 tiles of
    1024 x 1024 px: 0.45 s less) and, unlike a symlink, stays inside the log.
    ``frames.csv``: one frame per tile at ``t = 0, 1, 2, ...`` seconds in acquisition order
    (file order, or the grid's scan order). ``odometry.csv``: one sample per tile at its
    frame's time, the nominal stage position converted with :mod:`mapstore.grid`'s
    conventions (:func:`tile_pose`): the pose is the tile's image *centre* on a north-up
    grid whose pixel (0, 0) centre is the world origin, i.e.
    ``x = (X + (W - 1) / 2) * M``, ``y = -(Y + (H - 1) / 2) * M``, ``theta = 0``.
    ``drive.toml``: ``[camera] pixel_size_m = M``, an ``[odometry]`` table (the stage's
    error model, :mod:`pipeline.odometry_model`: ``kind = "absolute"``, a stage's position
    errors do not grow along the scan and it does not rotate; ``--stage-error E`` pixels is
    the largest error of a tile's position: ``sigma_m = E / 2 x M``, so that the build's
    search (3 sigma of two tiles' relative position, 2.1 E) covers two tiles off by E in
    opposite directions; ``heading_sigma_rad = 0.002``) and a ``[source]`` table (provenance). The default E is 5 % of the tile's
    shorter side.

Ground truth (evaluation only)
    ``--truth FILE``: a tile configuration of the tiles' *true* positions (e.g. from a
    simulator), converted the same way and written as ``ground_truth.csv`` (``t,x,y,theta``,
    one row per frame, the odometry's convention), so that builds report their errors
    against it. The build never reads it for building.

Peer positions (evaluation only)
    ``--peer FILE`` (e.g. Fiji's ``TileConfiguration.registered.txt``): another tile
    configuration of the same tiles, converted the same way and written as
    ``peer_positions.csv`` (``t,x,y,theta``, one row per frame). It is somebody else's
    answer, not ground truth, so it is not named ``ground_truth.csv``; the build never
    reads it. :func:`tile_positions_from_poses` converts poses back to tile positions in
    pixels for comparisons with such a file.

    ``--truth`` and ``--peer`` files must list every tile of the log and no other; a tile is
    matched by its name as written, else by its file name.

Report keys (``--report FILE``): ``tile_configuration`` (file, or null with ``--grid``),
``tile_dir`` (the tiles' folder), ``grid`` (null, or ``{columns, rows, order, first,
step_px: [x, y], files}`` with ``--grid``), ``out``, ``frames``, ``tile_width``,
``tile_height``, ``pixel_size_m``, ``stage_error_px``, ``extent_px`` ([width, height] of the nominal mosaic),
``ground_truth`` (file name or null), ``truth_rms_offset_px`` (RMS of true minus nominal
tile positions, or null), ``peer_positions`` (file name or null), ``peer_rms_offset_px``
(RMS of peer minus nominal tile positions, or null), ``seconds``.
"""

from __future__ import annotations

import fnmatch
import logging
import math
import re
import time
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from mapstore.grid import MapGrid, frame_centre
from pipeline.drivelog import CameraSpec, read_drive_log, write_drive_log, write_pose_csv
from pipeline.errors import BadInput, JobFailed
from pipeline.fsutil import atomic_dir, link_or_copy
from pipeline.images import check_image_header, check_image_size
from pipeline.progress import progress

log = logging.getLogger(__name__)

PEER_FILE = "peer_positions.csv"
# --stage-error default: the largest error of a tile's nominal position, as a fraction of the
# tile's shorter side; and the heading sigma of a stage (it does not rotate: 2 mrad allows for
# the small apparent rotations of lens distortion).
STAGE_ERROR_FRACTION = 0.05
STAGE_HEADING_SIGMA_RAD = 0.002
TRUTH_FILE = "ground_truth.csv"

GRID_ORDERS = ("row-by-row", "column-by-column", "snake-rows", "snake-columns")
GRID_CORNERS = ("top-left", "top-right", "bottom-left", "bottom-right")
# --grid without --pattern or --glob: every file of the folder with one of these suffixes.
TILE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg")
DEFAULT_GLOB = "*.tif, *.tiff, *.png, *.jpg, *.jpeg"

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_TILE_LINE = re.compile(rf"^(?P<file>[^;]+);(?P<series>[^;]*);\s*\(\s*(?P<x>{_NUM})\s*,\s*(?P<y>{_NUM})\s*\)\s*$")
_TILE_LINE_3D = re.compile(rf"^[^;]+;[^;]*;\s*\(\s*{_NUM}\s*,\s*{_NUM}\s*,\s*{_NUM}\s*\)\s*$")
_DIM_LINE = re.compile(r"^dim\s*=\s*(?P<dim>\S+)\s*$")
# A file-name pattern's tile index: Fiji's {i}, {ii}, ... (zero-padded to the count of i)
# or Python's {i} / {i:04d} / {i:4d}.
_INDEX_FIELD = re.compile(r"\{(?:(?P<fiji>i+)|i:(?P<fill>0?)(?P<width>\d*)d)\}")


# --- pure helpers ------------------------------------------------------------------------


def read_tile_configuration(path: str | Path) -> list[tuple[str, float, float]]:
    """Parse a Fiji Grid/Collection ``TileConfiguration.txt`` -> ``[(file, x_px, y_px), ...]``.

    Positions are the tiles' top-left corners in mosaic pixels, in file order. A file
    without a ``dim`` line is 2-D.

    Raises:
        BadInput: missing file, ``dim`` other than 2, a 3-D or malformed tile line, a
            duplicate tile, no tiles (naming ``file:line``).
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
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{lineno}"
        m = _DIM_LINE.match(line)
        if m:
            if m["dim"] != "2":
                raise BadInput(where, f"dim = {m['dim']}: only 2-D tile configurations are supported")
            continue
        m = _TILE_LINE.match(line)
        if not m:
            if _TILE_LINE_3D.match(line):
                raise BadInput(where, f"3-D position in {line!r}: only 2-D tile configurations are supported")
            raise BadInput(where, f"malformed tile line {line!r} (expected 'file; ; (x, y)')")
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
    if not tiles:
        raise BadInput(path, "lists no tiles")
    return tiles


def grid_cells(columns: int, rows: int, order: str, first: str) -> list[tuple[int, int]]:
    """The grid cells ``(column, row)`` (0 at the left and top) in acquisition order.

    ``order``: one of :data:`GRID_ORDERS` (Fiji's row-by-row, column-by-column, snake by
    rows, snake by columns); ``first``: the corner of the first tile, one of
    :data:`GRID_CORNERS`. The first row (column) runs away from that corner; a snake's
    next row (column) runs back, and rows (columns) follow each other away from it.
    """
    if order not in GRID_ORDERS:
        raise ValueError(f"order must be one of {', '.join(GRID_ORDERS)}, got {order!r}")
    if first not in GRID_CORNERS:
        raise ValueError(f"first must be one of {', '.join(GRID_CORNERS)}, got {first!r}")
    if columns < 1 or rows < 1:
        raise ValueError(f"the grid must have at least one column and row, got {columns} x {rows}")
    right_to_left = first.endswith("right")
    bottom_up = first.startswith("bottom")
    by_rows = order in ("row-by-row", "snake-rows")
    snake = order.startswith("snake")
    outer, inner = (rows, columns) if by_rows else (columns, rows)
    cells = []
    for k in range(columns * rows):
        o, i = divmod(k, inner)
        if snake and o % 2 == 1:
            i = inner - 1 - i
        c, r = (i, o) if by_rows else (o, i)
        if right_to_left:
            c = columns - 1 - c
        if bottom_up:
            r = rows - 1 - r
        cells.append((c, r))
    return cells


def parse_grid(text: str) -> tuple[int, int]:
    """``"9x7"`` -> ``(columns, rows)``; BadInput naming ``--grid`` otherwise."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX*]\s*(\d+)\s*", text)
    if not m or int(m[1]) < 1 or int(m[2]) < 1:
        raise BadInput("--grid", f"expected COLUMNSxROWS such as 9x7, got {text!r}")
    return int(m[1]), int(m[2])


def _parse_xy(option: str, value: str | float | tuple[float, float]) -> tuple[float, float]:
    """``"460"``, ``"460,455"``, ``460`` or ``(460, 455)`` -> ``(x, y)`` (one number for both axes)."""
    if isinstance(value, (int, float)):
        value = str(value)
    elif not isinstance(value, str):
        value = ",".join(str(v) for v in value)
    text = value
    parts = [p.strip() for p in text.split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) not in (1, 2) or not all(math.isfinite(v) for v in vals):
        raise BadInput(option, f"expected a number or two separated by a comma (x,y), got {text!r}")
    return (vals[0], vals[-1])


def _natural_key(name: str) -> list:
    return [(0, int(t), t) if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name)]


def _pattern_fields(pattern: str) -> tuple[str, str, int, bool]:
    """``(prefix, suffix, width, zero_padded)`` of a file-name pattern with one tile index field."""
    found = list(_INDEX_FIELD.finditer(pattern))
    if len(found) != 1:
        raise BadInput("--pattern", f"{pattern!r} must contain exactly one tile index field "
                                    "such as {i}, {i:04d} or Fiji's {iiii}")
    m = found[0]
    if m["fiji"]:
        width, zero = len(m["fiji"]), True
    else:
        width, zero = int(m["width"] or 0), bool(m["fill"])
    prefix, suffix = pattern[: m.start()], pattern[m.end():]
    if "/" in prefix + suffix or "{" in prefix + suffix or "}" in prefix + suffix:
        raise BadInput("--pattern", f"{pattern!r}: a file name in the folder with one index field, no '/' or other braces")
    return prefix, suffix, width, zero


def grid_files(tile_dir: Path, cells: int, *, pattern: str | None, glob: str | None,
               first_index: int = 1) -> list[str]:
    """The file names (relative to ``tile_dir``) of the tiles in acquisition order.

    Raises:
        BadInput: fewer or more files than ``cells`` (naming both counts), a bad pattern.
    """
    names = sorted(p.name for p in tile_dir.iterdir() if p.is_file())
    if pattern is not None:
        prefix, suffix, width, zero = _pattern_fields(pattern)
        rx = re.compile(re.escape(prefix) + r"(\d+)" + re.escape(suffix))
        matching = [n for n in names if rx.fullmatch(n)]
        wanted = [f"{prefix}{i:{'0' if zero else ''}{width}d}{suffix}" for i in range(first_index, first_index + cells)]
        present = set(names)
        missing = [n for n in wanted if n not in present]
        what = f"--pattern {pattern!r} (indices from {first_index})"
        if missing:
            raise BadInput(tile_dir, f"{what}: {cells - len(missing)} of the grid's {cells} tiles found "
                                     f"({len(matching)} files match the pattern); fewer files than grid cells "
                                     f"(first missing: {missing[0]!r})")
        extra = [n for n in matching if n not in set(wanted)]
        if extra:
            raise BadInput(tile_dir, f"{what}: {len(matching)} files match, the grid has {cells} cells; more "
                                     f"files than grid cells (e.g. {sorted(extra, key=_natural_key)[0]!r})")
        return wanted
    if glob is not None:
        files = [n for n in names if fnmatch.fnmatchcase(n, glob)]
        what = f"--glob {glob!r}"
    else:
        files = [n for n in names if n.lower().endswith(TILE_SUFFIXES)]
        what = f"image files ({DEFAULT_GLOB})"
    files.sort(key=_natural_key)
    if len(files) != cells:
        if not files:
            raise BadInput(tile_dir, f"{what}: no files match, the grid has {cells} cells")
        more = "more" if len(files) > cells else "fewer"
        raise BadInput(tile_dir, f"{what}: {len(files)} files, the grid has {cells} cells ({more} files than grid "
                                 f"cells; first {files[0]!r}, last {files[-1]!r})")
    return files


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
    check_image_size(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = (oiio.geterror().strip() or "cannot open").splitlines()[0]
        raise BadInput(where, f"tile image {str(path)!r} is unreadable: {msg}")
    try:
        spec = inp.spec()
        check_image_header(path, spec)  # the import decodes it later: the caps hold before that
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


def other_positions(names: list[str], path: Path, source: str) -> np.ndarray:
    """Positions ``(N, 2)`` (pixels) that the tile configuration ``path`` gives the tiles ``names``.

    A tile is matched by its name as written, else by its file name (when unique in
    ``path``). Raises BadInput naming ``path`` when a tile is missing or ``path`` lists
    another tile (``source`` names where the tiles come from, for the message).
    """
    listed = read_tile_configuration(path)
    exact = {n: (x, y) for n, x, y in listed}
    base_count: dict[str, int] = {}
    for n, _, _ in listed:
        base_count[Path(n).name] = base_count.get(Path(n).name, 0) + 1
    by_base = {Path(n).name: (n, x, y) for n, x, y in listed if base_count[Path(n).name] == 1}
    used, out, missing = set(), [], []
    for name in names:
        if name in exact:
            used.add(name)
            out.append(exact[name])
        elif Path(name).name in by_base:
            n, x, y = by_base[Path(name).name]
            used.add(n)
            out.append((x, y))
        else:
            missing.append(name)
    if missing:
        raise BadInput(path, f"has no position for tile {missing[0]!r} ({len(missing)} of {len(names)} tiles missing)")
    extra = [n for n, _, _ in listed if n not in used]
    if extra:
        raise BadInput(path, f"lists tile {extra[0]!r}, which {source} does not ({len(extra)} extra)")
    return np.array(out, dtype=float).reshape(-1, 2)


# --- import ------------------------------------------------------------------------------


def import_tiles(
    tile_config: str | Path,
    out: str | Path,
    *,
    pixel_size: float,
    peer: str | Path | None = None,
    truth: str | Path | None = None,
    grid: str | tuple[int, int] | None = None,
    order: str = "row-by-row",
    first: str = "top-left",
    step: str | tuple[float, float] | None = None,
    overlap: str | tuple[float, float] | None = None,
    pattern: str | None = None,
    glob: str | None = None,
    first_index: int = 1,
    stage_error: float | None = None,
    quiet: bool = True,
) -> dict:
    """Import a tile configuration (or, with ``grid``, a folder of tiles) as a new drive log ``out``.

    ``tile_config``: a TileConfiguration file, or with ``grid`` (``"9x7"`` or ``(columns,
    rows)``) the folder of tiles, with ``order``, ``first``, ``step`` (pixels, ``"460"``,
    ``"460,455"`` or ``(x, y)``) or ``overlap`` (fraction, same forms), ``pattern`` or
    ``glob``, ``first_index`` (see the module docstring). ``pixel_size``: metres per pixel.
    ``stage_error``: the largest error of a tile's nominal position (pixels; None: 5 % of
    the tile's shorter side), written as the log's ``[odometry]`` error model.
    ``truth`` / ``peer``: tile configurations written as ``ground_truth.csv`` /
    ``peer_positions.csv``. Returns the summary.

    Raises :class:`BadInput` on bad input; nothing is left under ``out`` then.
    """
    t_begin = time.perf_counter()
    tile_config, out = Path(tile_config), Path(out)
    if not math.isfinite(pixel_size) or pixel_size <= 0:
        raise BadInput("--pixel-size", f"must be a positive number of metres, got {pixel_size}")
    if stage_error is not None and (not math.isfinite(stage_error) or stage_error < 0):
        raise BadInput("--stage-error", f"must be a non-negative number of pixels, got {stage_error}")
    grid_opts = {"--order": order != "row-by-row", "--first": first != "top-left", "--step": step is not None,
                 "--overlap": overlap is not None, "--pattern": pattern is not None, "--glob": glob is not None,
                 "--first-index": first_index != 1}
    grid_info = None
    if grid is None:
        given = [k for k, v in grid_opts.items() if v]
        if given:
            raise BadInput(given[0], "only with --grid (a folder of tiles without a TileConfiguration)")
        if tile_config.is_dir():
            raise BadInput(tile_config, "is a folder: give its TileConfiguration file, or --grid COLUMNSxROWS "
                                        "(with --order, --first and --step or --overlap) to import its tiles by grid")
    else:
        columns, rows = parse_grid(grid) if isinstance(grid, str) else (int(grid[0]), int(grid[1]))
        if columns < 1 or rows < 1:
            raise BadInput("--grid", f"needs at least one column and row, got {columns} x {rows}")
        if order not in GRID_ORDERS:
            raise BadInput("--order", f"must be one of {', '.join(GRID_ORDERS)}, got {order!r}")
        if first not in GRID_CORNERS:
            raise BadInput("--first", f"must be one of {', '.join(GRID_CORNERS)}, got {first!r}")
        if (step is None) == (overlap is None):
            raise BadInput("--grid", "give the tile step: either --step PX[,PY] or --overlap FRACTION[,FY]")
        if pattern is not None and glob is not None:
            raise BadInput("--pattern", "give either --pattern or --glob, not both")
        if first_index < 0:
            raise BadInput("--first-index", f"must be 0 or more, got {first_index}")
        if step is not None:
            step_xy = _parse_xy("--step", step)
            if min(step_xy) <= 0 or not all(math.isfinite(v) for v in step_xy):
                raise BadInput("--step", f"must be positive pixels, got {step_xy}")
        else:
            ov = _parse_xy("--overlap", overlap)
            if not all(math.isfinite(v) and 0.0 <= v < 1.0 for v in ov):
                raise BadInput("--overlap", f"must be a fraction in [0, 1) such as 0.10 for 10 %, got {overlap}")
        if not tile_config.is_dir():
            raise BadInput(tile_config, "with --grid, give the folder of the tiles (not a file)")
    replace = check_out_dir(out)

    if grid is None:
        tiles = read_tile_configuration(tile_config)
        lines = _tile_lines(tile_config)
        base = tile_config.parent
        where_of = {name: f"{tile_config}:{lines.get(name, '?')}" for name, _, _ in tiles}
        source_name = str(tile_config)
    else:
        cells = grid_cells(columns, rows, order, first)
        files = grid_files(tile_config, len(cells), pattern=pattern, glob=glob, first_index=first_index)
        base = tile_config
        where_of = {name: str(tile_config / name) for name in files}
        source_name = f"the {columns}x{rows} grid of {tile_config}"
        tiles = [(name, 0.0, 0.0) for name in files]  # positions once the tile size is known
    if len(tiles) < 2:
        raise BadInput(tile_config, f"has {len(tiles)} tile, a drive log needs at least 2 (odometry needs 2 samples)")

    # Sources, destinations and a common tile size.
    shape = None
    sources, names = [], []
    for name, _, _ in tiles:
        where = where_of[name]
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

    if grid is not None:
        if step is None:
            step_xy = (shape[1] * (1.0 - ov[0]), shape[0] * (1.0 - ov[1]))
        tiles = [(name, c * step_xy[0], r * step_xy[1]) for name, (c, r) in zip(files, cells)]
        grid_info = {"columns": columns, "rows": rows, "order": order, "first": first,
                     "step_px": [float(step_xy[0]), float(step_xy[1])],
                     "files": (f"--pattern {pattern} from {first_index}" if pattern is not None
                               else f"--glob {glob}" if glob is not None else DEFAULT_GLOB)}

    frame_t = np.arange(len(tiles), dtype=float)
    nominal = np.array([(x, y) for _, x, y in tiles])
    poses = np.array([tile_pose(x, y, shape, pixel_size) for _, x, y in tiles])
    odometry = np.column_stack([frame_t, poses])
    tile_names = [name for name, _, _ in tiles]

    def converted(path: Path) -> tuple[np.ndarray, float]:
        pos = other_positions(tile_names, path, source_name)
        rms = float(np.sqrt(np.mean(np.sum((pos - nominal) ** 2, axis=1))))
        return np.column_stack([frame_t, [tile_pose(x, y, shape, pixel_size) for x, y in pos]]), rms

    peer_odo = peer_rms = truth_odo = truth_rms = None
    if peer is not None:
        peer = Path(peer)
        peer_odo, peer_rms = converted(peer)
    if truth is not None:
        truth = Path(truth)
        truth_odo, truth_rms = converted(truth)

    source = {
        "kind": "tile_configuration" if grid is None else "tile_grid",
        "tile_width_px": shape[1],
        "tile_height_px": shape[0],
        "frame_times": "t = 0, 1, 2, ... s in acquisition order; odometry = nominal stage positions",
    }
    if grid is None:
        source["tile_configuration"] = str(tile_config.resolve())
    else:
        source["tile_dir"] = str(tile_config.resolve())
        source["grid"] = f"{columns}x{rows}"
        source["grid_order"] = order
        source["grid_first"] = first
        source["grid_step_px"] = grid_info["step_px"]
        source["grid_files"] = grid_info["files"]
    if peer is not None:
        source["peer_configuration"] = str(peer.resolve())
        source["peer_positions"] = PEER_FILE
        source["peer_positions_note"] = "a peer's registration, for evaluation only; not ground truth, never read by the build"
    if truth is not None:
        source["truth_configuration"] = str(truth.resolve())
        source["ground_truth"] = TRUTH_FILE

    error_px = float(stage_error) if stage_error is not None else STAGE_ERROR_FRACTION * min(shape)
    odometry_model = {
        "kind": "absolute",
        "sigma_m": max(error_px, 1.0) / 2.0 * float(pixel_size),
        "heading_sigma_rad": STAGE_HEADING_SIGMA_RAD,
    }
    source["stage_error_px"] = error_px
    with atomic_dir(out, replace=replace) as tmp:
        (tmp / "images").mkdir()
        for src, dst in progress(list(zip(sources, names)), label="import-tiles", unit="tiles", quiet=quiet):
            link_or_copy(src, tmp / dst)
        write_drive_log(
            tmp, CameraSpec(pixel_size_m=float(pixel_size)), frame_t, names, odometry,
            ground_truth=truth_odo, log_id=out.name, extra={"odometry": odometry_model, "source": source},
        )
        if peer_odo is not None:
            write_pose_csv(tmp / PEER_FILE, peer_odo)
        try:
            read_drive_log(tmp)
        except BadInput as e:
            raise JobFailed(f"{out}: the written drive log does not validate: {e}") from None

    xs, ys = nominal[:, 0], nominal[:, 1]
    return {
        "tile_configuration": str(tile_config) if grid is None else None,
        "tile_dir": str(base),
        "grid": grid_info,
        "out": str(out),
        "frames": len(tiles),
        "tile_width": shape[1],
        "tile_height": shape[0],
        "pixel_size_m": float(pixel_size),
        "stage_error_px": error_px,
        "extent_px": [float(xs.max() - xs.min() + shape[1]), float(ys.max() - ys.min() + shape[0])],
        "ground_truth": TRUTH_FILE if truth is not None else None,
        "truth_rms_offset_px": truth_rms,
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
    g = s["grid"]
    grid = f" ({g['columns']}x{g['rows']} grid, {g['order']} from {g['first']})" if g else ""
    truth = f", ground truth (RMS offset {s['truth_rms_offset_px']:.2f} px)" if s["ground_truth"] else ""
    peer = f", peer positions (RMS offset {s['peer_rms_offset_px']:.2f} px)" if s["peer_positions"] else ""
    return (
        f"import-tiles: {s['frames']} tiles of {s['tile_width']} x {s['tile_height']} px{grid} at "
        f"{s['pixel_size_m']} m/px, mosaic {s['extent_px'][0]:.0f} x {s['extent_px'][1]:.0f} px{truth}{peer} -> {s['out']}"
    )
