"""Tile-grid simulator: a stage-scanned microscope tile grid with known true tile positions.

``mosaicmap simulate tiles OUT`` cuts ``COLS x ROWS`` tiles out of one procedural texture
(:func:`pipeline.simulate.texture.procedural_texture`, the floor's worn concrete; one tile
pixel = one texture pixel) as a stage with a position error would: each tile's *true*
position is its nominal grid position plus a uniform stage error, and the nominal grid is
what a stitcher gets as its prior. Defaults: ``configs/simulate.toml`` ``[simulate.tiles]``.

Frames and units
    Tile positions are the position of a tile's pixel (0, 0) in *mosaic pixels*, x to the
    right (image columns), y down (image rows), as in Fiji's ``TileConfiguration.txt``: tile
    pixel ``(u, v)`` (column, row) shows the mosaic at ``(X + u, Y + v)``. Nominal position of
    the tile in grid column ``c``, row ``r``: ``(c * step_x, r * step_y)``, with
    ``step = round(tile size * (1 - overlap))`` per axis, **rounded to whole pixels** (a
    stage's nominal grid written by acquisition software, e.g. 461 px for 512 px tiles at
    10 %; the effective overlap is written to ``grid.json``). True position = nominal +
    ``uniform(-E, E)`` per tile and per axis (sub-pixel, ``E`` = ``stage_error_px``); so two
    neighbours' relative offset is off the nominal step by up to ``2 E``.

Scan order
    ``row``: row by row, every row left to right (raster); ``snake``: row 0 left to right,
    row 1 right to left, ... (boustrophedon). File ``tile_NNN.tif`` is the NNN-th tile in
    scan order (the stage's acquisition order).

Image formation (per tile; grey levels on the texture's 0..255 scale)
    ``signal = gain_i x texture(true position)`` (``gain_i = 1 + uniform(-g, g)``), or
    ``gain_i x blank_level`` for a *blank* tile (flat background, e.g. off the specimen);
    ``+ N(0, noise_sigma^2)``; then the stored value is ``lo + (hi - lo) x signal / 255``
    (``value_range = [lo, hi]``, i.e. offset ``lo`` and scale ``(hi - lo) / 255`` per grey
    level), rounded and clipped to the bit depth (8 or 16). ``hot_pixels``: that many
    sensor pixels (the same in every tile: a sensor defect, not noise) are stored at the
    maximum value (255 or 65535).

Sub-pixel cutting and its accuracy
    A tile is cut at its fractional position by a separable windowed-sinc (Lanczos,
    ``a = 16``: 32 taps per axis) convolution of an integer crop: one constant fractional
    shift per tile, so two 1-D kernels, no position rounding (OpenCV's ``remap`` rounds
    positions to 1/32 px) and no border effects (the crop carries the kernel's margin).
    Measured on a periodic white-noise texture band-limited like the floor's (Gaussian
    sigma 0.7 px) against an exact Fourier shift (tests/test_simulate_tiles.py checks it):
    the equivalent shift error (least-squares projection of the difference on the image
    gradient) is at most 7e-5 px with ``a = 16``; with ``a = 4`` it was 0.0025 px, with
    ``cv2.remap`` Lanczos-4 0.022 px and with :class:`pipeline.resample.ExactSampler` 0.008 px.
    Between neighbours of a simulated 5 x 5 grid (no noise, no gain, 16 bits) tile b's
    overlap matched tile a resampled (the same way) at the true offset within 0.0076 px
    (max over 40 pairs; RMS 0.0013 px; the check resamples twice, so this bounds the two
    cuts together). The truth is right to well under the 0.05 px that registration targets.

Output (written atomically: all of OUT appears, or nothing)::

    OUT/tile_000.tif ...              the tiles in scan order (grey, uint8 or uint16)
    OUT/TileConfiguration.txt         Fiji format, dim = 2: the nominal positions (the prior)
    OUT/TileConfiguration.truth.txt   the same format: the true positions (evaluation only)
    OUT/grid.json                     the parameters and per tile: file, grid column/row,
                                      nominal and true position, gain, blank

Same seed and options -> byte-identical output.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from mapstore.grid import MapGrid
from pipeline.errors import BadInput
from pipeline.fsutil import atomic_dir
from pipeline.images import write_image
from pipeline.simulate.texture import procedural_texture

__all__ = [
    "TileOptions",
    "resolve_options",
    "grid_layout",
    "shift_kernel",
    "cut_tile",
    "tile_configuration_text",
    "simulate_tiles",
    "CONFIG_FILE",
    "TRUTH_FILE",
    "GRID_FILE",
]

CONFIG_FILE = "TileConfiguration.txt"
TRUTH_FILE = "TileConfiguration.truth.txt"
GRID_FILE = "grid.json"
ORDERS = ("row", "snake")
# Lanczos window of the sub-pixel cut (taps per axis = 2 x this); see the module docstring.
LANCZOS_A = 16
# Largest texture raster generated (pixels): ~4 bytes each and ~7x that at the peak of the
# procedural texture (10 x 10 tiles of 1024 px at 3 % overlap are ~100 MPix, 2.9 GB).
MAX_TEXTURE_PIXELS = 300_000_000
MIN_TILE_PX = 16

# Independent random streams, spawned from the seed in this order (do not reorder:
# reproducibility of existing seeds depends on it).
_STREAMS = ("texture", "positions", "gains", "blank", "hot", "noise")


@dataclass(frozen=True)
class TileOptions:
    """The effective, validated options of one tile-grid simulation (units in the names)."""

    seed: int
    cols: int
    rows: int
    tile_size: tuple[int, int]  # (width, height) pixels
    overlap: float  # fraction of the tile size
    stage_error_px: float  # E: true = nominal + uniform(-E, E) per tile and axis
    order: str  # "row" or "snake"
    noise_sigma: float  # grey levels (0..255 scale)
    gain: float  # per-tile gain 1 + uniform(-gain, gain)
    bits: int  # 8 or 16
    value_range: tuple[int, int]  # stored value of grey 0 and grey 255
    blank_tiles: tuple[int, ...]  # scan indices of blank tiles (sorted)
    blank_count: int  # additional blank tiles drawn at random
    blank_level: float  # grey level of a blank tile's flat background
    hot_pixels: int  # sensor pixels stored at the maximum value, in every tile
    texture_pixel_size_m: float  # converts [simulate.floor.textures] sizes (metres) to pixels
    compression: str  # TIFF compression: "none", "zip" or "lzw"

    @property
    def step(self) -> tuple[int, int]:
        """Nominal grid step ``(x, y)`` in whole pixels."""
        w, h = self.tile_size
        return int(round(w * (1.0 - self.overlap))), int(round(h * (1.0 - self.overlap)))


_GRID = re.compile(r"^\s*(\d+)\s*[xX×]\s*(\d+)\s*$")
_SIZE = re.compile(r"^\s*(\d+)\s*(?:[xX×]\s*(\d+))?\s*$")


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _int_list(text: str, where: str) -> tuple[int, ...]:
    """``"0,5,7"`` -> (0, 5, 7); "" -> ()."""
    parts = [p.strip() for p in str(text).split(",") if p.strip()]
    try:
        return tuple(int(p) for p in parts)
    except ValueError:
        raise BadInput(where, f"expected comma-separated tile indices, got {text!r}") from None


def resolve_options(cfg: dict, given: dict) -> TileOptions:
    """Overlay command-line values ``given`` (None = not given) on ``[simulate.tiles]`` and validate.

    ``given`` keys: seed, grid ("COLSxROWS"), tile ("PX" or "WxH"), overlap, stage_error,
    order, noise, gain, bits, value_range ("LO,HI"), blank_count, blank_tiles ("I,J,..."),
    hot_pixels. Raises :class:`BadInput` naming the option (or configuration key) at fault.
    """
    sim, tl = cfg["simulate"], cfg["simulate"]["tiles"]

    def pick(opt: str, key: str):
        value = given.get(opt.replace("-", "_"))
        return (value, f"--{opt}") if value is not None else (tl[key], f"config simulate.tiles.{key}")

    seed = given.get("seed")
    seed, where = (seed, "--seed") if seed is not None else (sim["seed"], "config simulate.seed")
    if not _is_int(seed) or seed < 0:
        raise BadInput(where, f"must be a non-negative integer, got {seed!r}")

    if given.get("grid") is not None:
        m = _GRID.match(str(given["grid"]))
        if not m:
            raise BadInput("--grid", f"expected COLSxROWS (e.g. 5x5), got {given['grid']!r}")
        cols, rows, where = int(m.group(1)), int(m.group(2)), "--grid"
    else:
        g, where = tl["grid"], "config simulate.tiles.grid"
        if not (isinstance(g, list) and len(g) == 2 and all(_is_int(v) for v in g)):
            raise BadInput(where, f"must be two integers [cols, rows], got {g!r}")
        cols, rows = g
    if cols < 1 or rows < 1 or cols * rows < 2:
        raise BadInput(where, f"a grid needs at least 1 column, 1 row and 2 tiles, got {cols}x{rows}")

    if given.get("tile") is not None:
        m = _SIZE.match(str(given["tile"]))
        if not m:
            raise BadInput("--tile", f"expected a tile size in pixels, PX or WIDTHxHEIGHT (e.g. 512), got {given['tile']!r}")
        tw = int(m.group(1))
        th = int(m.group(2)) if m.group(2) else tw
        where = "--tile"
    else:
        t, where = tl["tile_size"], "config simulate.tiles.tile_size"
        if not (isinstance(t, list) and len(t) == 2 and all(_is_int(v) for v in t)):
            raise BadInput(where, f"must be two integers [width, height], got {t!r}")
        tw, th = t
    if min(tw, th) < MIN_TILE_PX or max(tw, th) > 16384:
        raise BadInput(where, f"tiles must be {MIN_TILE_PX} to 16384 pixels each way, got {tw}x{th}")

    overlap, where = pick("overlap", "overlap")
    if not (_is_num(overlap) and 0.0 <= overlap < 0.9):
        raise BadInput(where, f"must be a fraction of the tile in [0, 0.9), got {overlap!r}")
    err, where = pick("stage-error", "stage_error_px")
    if not (_is_num(err) and 0.0 <= err <= min(tw, th) / 2):
        raise BadInput(where, f"must be a number of pixels in [0, half the tile = {min(tw, th) / 2:g}], got {err!r}")
    order, where = pick("order", "order")
    if order not in ORDERS:
        raise BadInput(where, f"unknown scan order {order!r} (known: {', '.join(ORDERS)})")
    noise, where = pick("noise", "noise_sigma")
    if not (_is_num(noise) and noise >= 0):
        raise BadInput(where, f"noise sigma must be >= 0 grey levels, got {noise!r}")
    gain, where = pick("gain", "gain")
    if not (_is_num(gain) and 0 <= gain < 1):
        raise BadInput(where, f"per-tile gain spread must be in [0, 1), got {gain!r}")
    bits, where = pick("bits", "bits")
    if bits not in (8, 16) or isinstance(bits, bool):
        raise BadInput(where, f"must be 8 or 16, got {bits!r}")
    top = (1 << bits) - 1
    if given.get("value_range") is not None:
        where = "--value-range"
        vr = _int_list(given["value_range"], where)
    else:
        where = "config simulate.tiles.value_range"
        vr = tl["value_range"]
        if not (isinstance(vr, list) and all(_is_int(v) for v in vr)):
            raise BadInput(where, f"must be [] or two integers [lo, hi], got {vr!r}")
    if len(vr) == 0:
        vr = (0, top)
    if len(vr) != 2 or not (0 <= vr[0] < vr[1] <= top):
        raise BadInput(where, f"must be two values LO,HI with 0 <= LO < HI <= {top} ({bits}-bit), got {vr!r}")
    n = cols * rows
    if given.get("blank_tiles") is not None:
        where = "--blank-tiles"
        blanks = _int_list(given["blank_tiles"], where)
    else:
        where = "config simulate.tiles.blank_tiles"
        blanks = tl["blank_tiles"]
        if not (isinstance(blanks, list) and all(_is_int(v) for v in blanks)):
            raise BadInput(where, f"must be a list of tile indices, got {blanks!r}")
        blanks = tuple(blanks)
    bad = [i for i in blanks if not 0 <= i < n]
    if bad:
        raise BadInput(where, f"tile index {bad[0]} is outside the grid's {n} tiles (0..{n - 1}, scan order)")
    if len(set(blanks)) != len(blanks):
        raise BadInput(where, f"lists a tile twice: {list(blanks)}")
    count, where = pick("blank-count", "blank_count")
    if not (_is_int(count) and 0 <= count <= n - len(blanks)):
        raise BadInput(where, f"must be an integer in [0, {n - len(blanks)}] (tiles not already blank), got {count!r}")
    level, where = pick("blank-level", "blank_level")
    if not (_is_num(level) and 0 <= level <= 255):
        raise BadInput(where, f"must be a grey level in [0, 255], got {level!r}")
    hot, where = pick("hot-pixels", "hot_pixels")
    if not (_is_int(hot) and 0 <= hot <= tw * th // 100):
        raise BadInput(where, f"must be an integer in [0, 1 % of the tile's pixels = {tw * th // 100}], got {hot!r}")
    ps, where = tl["texture_pixel_size_m"], "config simulate.tiles.texture_pixel_size_m"
    if not (_is_num(ps) and ps > 0):
        raise BadInput(where, f"must be a positive number of metres, got {ps!r}")
    comp, where = tl["compression"], "config simulate.tiles.compression"
    if comp not in ("none", "zip", "lzw"):
        raise BadInput(where, f"must be 'none', 'zip' or 'lzw', got {comp!r}")

    opts = TileOptions(
        seed=seed, cols=cols, rows=rows, tile_size=(tw, th), overlap=float(overlap),
        stage_error_px=float(err), order=order, noise_sigma=float(noise), gain=float(gain), bits=bits,
        value_range=(int(vr[0]), int(vr[1])), blank_tiles=tuple(sorted(blanks)), blank_count=count,
        blank_level=float(level), hot_pixels=hot, texture_pixel_size_m=float(ps), compression=comp,
    )
    sx, sy = opts.step
    if sx < 1 or sy < 1:
        raise BadInput("--overlap", f"leaves a grid step below one pixel ({sx} x {sy})")
    tex_w, tex_h = _texture_shape(opts)
    if tex_w * tex_h > MAX_TEXTURE_PIXELS:
        raise BadInput("--grid", f"the mosaic ({tex_w} x {tex_h} px) exceeds the simulator's "
                                 f"{MAX_TEXTURE_PIXELS / 1e6:.0f} MPix limit: fewer or smaller tiles")
    return opts


def grid_layout(cols: int, rows: int, order: str) -> list[tuple[int, int]]:
    """Grid ``(column, row)`` of each tile in scan order (``row``: raster; ``snake``: every
    odd row right to left). Column 0 is the left, row 0 the top."""
    out = []
    for r in range(rows):
        cs = range(cols - 1, -1, -1) if (order == "snake" and r % 2 == 1) else range(cols)
        out += [(c, r) for c in cs]
    return out


def _margin(opts: TileOptions) -> int:
    """Texture pixels left of / above mosaic (0, 0): the stage error plus the kernel's support."""
    return int(math.ceil(opts.stage_error_px)) + LANCZOS_A + 2


def _texture_shape(opts: TileOptions) -> tuple[int, int]:
    """``(width, height)`` of the texture raster covering every possible true tile position."""
    m = _margin(opts)
    sx, sy = opts.step
    w, h = opts.tile_size
    return (opts.cols - 1) * sx + w + 2 * m, (opts.rows - 1) * sy + h + 2 * m


def shift_kernel(frac: float, a: int = LANCZOS_A) -> np.ndarray:
    """1-D Lanczos-``a`` kernel (``2 a`` taps, sum 1) that samples at ``k + frac``.

    ``out[i] = sum_j kernel[j] src[i + j - (a - 1)]`` = the windowed-sinc interpolation of
    ``src`` at ``i + frac`` (``0 <= frac < 1``; ``frac = 0`` gives a unit impulse).
    """
    k = np.arange(-a + 1, a + 1, dtype=np.float64)
    x = k - frac
    kern = np.sinc(x) * np.sinc(x / a)
    kern[np.abs(x) >= a] = 0.0
    return kern / kern.sum()


def cut_tile(texture: np.ndarray, x: float, y: float, shape: tuple[int, int], a: int = LANCZOS_A) -> np.ndarray:
    """Samples of ``texture`` at ``(x + u, y + v)`` for tile pixels ``u < W``, ``v < H``.

    ``x, y``: texture pixel coordinates (column, row; pixel centres at integers) of the
    tile's pixel (0, 0), sub-pixel. ``shape`` = ``(H, W)``. float32 ``(H, W)``. The texture
    must hold the kernel's support: ``a - 1`` pixels before and ``a`` after the tile.
    """
    h, w = shape
    ix, iy = math.floor(x), math.floor(y)
    fx, fy = x - ix, y - iy
    x0, y0 = ix - (a - 1), iy - (a - 1)
    if x0 < 0 or y0 < 0 or ix + w + a > texture.shape[1] or iy + h + a > texture.shape[0]:
        raise ValueError(f"tile at ({x:.3f}, {y:.3f}) + kernel support leaves the texture {texture.shape}")
    crop = np.ascontiguousarray(texture[y0 : iy + h + a, x0 : ix + w + a], np.float32)
    out = cv2.sepFilter2D(crop, cv2.CV_32F, shift_kernel(fx, a).astype(np.float32),
                          shift_kernel(fy, a).astype(np.float32), anchor=(a - 1, a - 1),
                          borderType=cv2.BORDER_REFLECT)
    return out[a - 1 : a - 1 + h, a - 1 : a - 1 + w]


def tile_configuration_text(files: list[str], positions: np.ndarray, comment: str) -> str:
    """A Fiji Grid/Collection ``TileConfiguration.txt`` (dim = 2): ``file; ; (x, y)`` per tile,
    positions in pixels (top-left, x right, y down), 4 decimals."""
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += ["# Define the number of dimensions we are working on", "dim = 2", "",
              "# Define the image coordinates"]
    lines += [f"{f}; ; ({x:.4f}, {y:.4f})" for f, (x, y) in zip(files, positions)]
    return "\n".join(lines) + "\n"


def _to_stored(signal: np.ndarray, opts: TileOptions) -> np.ndarray:
    lo, hi = opts.value_range
    top = (1 << opts.bits) - 1
    v = np.rint(np.float32(lo) + signal * np.float32((hi - lo) / 255.0))
    return np.clip(v, 0, top).astype(np.uint8 if opts.bits == 8 else np.uint16)


def _compact_json(obj: dict) -> str:
    """One top-level key per line (and one tile per line): small and readable."""
    lines = []
    for k, v in obj.items():
        if isinstance(v, list) and v and isinstance(v[0], dict):
            inner = ",\n".join("  " + json.dumps(e) for e in v)
            lines.append(f" {json.dumps(k)}: [\n{inner}\n ]")
        else:
            lines.append(f" {json.dumps(k)}: {json.dumps(v)}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def simulate_tiles(out: str | Path, cfg: dict, given: dict, *, quiet: bool = False) -> dict:
    """Simulate a tile grid into the folder ``out`` (see the module docstring); the summary.

    Raises :class:`BadInput` on bad options or an existing non-empty ``out``; nothing is
    left under ``out`` then.
    """
    t_begin = time.perf_counter()
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise BadInput(out, "output already exists and is not an empty directory")
    opts = resolve_options(cfg, given)
    streams = dict(zip(_STREAMS, np.random.SeedSequence(opts.seed).spawn(len(_STREAMS))))
    n = opts.cols * opts.rows
    w, h = opts.tile_size
    sx, sy = opts.step
    E = opts.stage_error_px

    layout = grid_layout(opts.cols, opts.rows, opts.order)
    nominal = np.array([(c * sx, r * sy) for c, r in layout], dtype=np.float64)
    err = np.random.default_rng(streams["positions"]).uniform(-E, E, size=(n, 2)) if E > 0 else np.zeros((n, 2))
    truth = nominal + err
    gains = 1.0 + np.random.default_rng(streams["gains"]).uniform(-opts.gain, opts.gain, size=n)
    blank = set(opts.blank_tiles)
    if opts.blank_count:
        free = np.array([i for i in range(n) if i not in blank])
        blank |= set(np.random.default_rng(streams["blank"]).choice(free, opts.blank_count, replace=False).tolist())
    hot_rng = np.random.default_rng(streams["hot"])
    hot = hot_rng.choice(w * h, opts.hot_pixels, replace=False) if opts.hot_pixels else np.zeros(0, int)
    noise_seeds = streams["noise"].spawn(n)

    tex_w, tex_h = _texture_shape(opts)
    ps = opts.texture_pixel_size_m
    tex_grid = MapGrid(0.0, 0.0, ps, tex_w, tex_h)
    texture = procedural_texture(np.random.default_rng(streams["texture"]), tex_grid,
                                 cfg["simulate"]["floor"]["textures"], tex_w * tex_h * ps * ps)
    m = _margin(opts)
    files = [f"tile_{i:0{max(3, len(str(n - 1)))}d}.tif" for i in range(n)]
    top = (1 << opts.bits) - 1
    attrs = {"compression": opts.compression, "DateTime": "2000:01:01 00:00:00"}

    def render(tmp: Path, i: int) -> None:
        if i in blank:
            signal = np.full((h, w), opts.blank_level, np.float32)
        else:
            signal = cut_tile(texture, truth[i, 0] + m, truth[i, 1] + m, (h, w))
        signal *= np.float32(gains[i])
        if opts.noise_sigma > 0:
            signal += np.random.default_rng(noise_seeds[i]).standard_normal((h, w), dtype=np.float32) * np.float32(
                opts.noise_sigma)
        img = _to_stored(signal, opts)
        if hot.size:
            img.reshape(-1)[hot] = top
        write_image(tmp / files[i], img, attrs)

    workers = cfg["simulate"]["workers"] or os.cpu_count() or 1
    blank_sorted = sorted(int(i) for i in blank)
    lo, hi = opts.value_range
    params = {
        "format": "mosaicmap-sim-tiles", "format_version": 1,
        "cols": opts.cols, "rows": opts.rows, "order": opts.order,
        "tile_size": list(opts.tile_size), "overlap": opts.overlap, "step_px": [sx, sy],
        "overlap_px": [w - sx, h - sy], "stage_error_px": E, "seed": opts.seed,
        "noise_sigma": opts.noise_sigma, "noise_units": "grey levels (0..255 signal scale, before value_range)",
        "gain": opts.gain, "bits": opts.bits, "value_range": [lo, hi],
        "value_note": "stored = lo + (hi - lo) * grey / 255, rounded and clipped",
        "blank_tiles": blank_sorted, "blank_level": opts.blank_level,
        "hot_pixels": opts.hot_pixels,
        "hot_pixel_xy": [[int(p % w), int(p // w)] for p in hot],
        "texture": {"kind": "procedural", "pixel_size_m": ps, "raster": [tex_w, tex_h], "margin_px": m},
        "resample": {"kernel": "lanczos", "a": LANCZOS_A},
        "frames": "positions in mosaic pixels: tile pixel (u, v) shows mosaic (x + u, y + v); x right, y down",
        "files": {"tiles": len(files), "prior": CONFIG_FILE, "truth": TRUTH_FILE},
        "tiles": [
            {"file": files[i], "col": layout[i][0], "row": layout[i][1],
             "nominal": [float(nominal[i, 0]), float(nominal[i, 1])],
             "truth": [round(float(truth[i, 0]), 6), round(float(truth[i, 1]), 6)],
             "gain": round(float(gains[i]), 6), "blank": i in blank}
            for i in range(n)
        ],
    }
    with atomic_dir(out, replace=out.exists()) as tmp:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            list(pool.map(lambda i: render(tmp, i), range(n)))
        head = (f"mosaicmap simulate tiles: {opts.cols} x {opts.rows} tiles of {w} x {h} px, "
                f"{opts.order} order, seed {opts.seed}")
        (tmp / CONFIG_FILE).write_text(tile_configuration_text(
            files, nominal, f"{head}\nnominal stage positions (the prior), pixels, top-left, x right, y down"))
        (tmp / TRUTH_FILE).write_text(tile_configuration_text(
            files, np.round(truth, 4), f"{head}\ntrue positions (evaluation only), pixels, top-left, x right, y down"))
        (tmp / GRID_FILE).write_text(_compact_json(params))
    return {
        "out": str(out), "tiles": n, "cols": opts.cols, "rows": opts.rows, "tile_size": [w, h],
        "step_px": [sx, sy], "overlap_px": [w - sx, h - sy], "order": opts.order, "stage_error_px": E,
        "bits": opts.bits, "value_range": [lo, hi], "blank_tiles": blank_sorted, "hot_pixels": opts.hot_pixels,
        "options": asdict(opts), "seconds": time.perf_counter() - t_begin,
    }
