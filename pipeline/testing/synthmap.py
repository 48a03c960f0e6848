"""Synthetic maps published straight into a map repository, without frames.

For benchmarks and tests of what comes after the build (diff, export, the tracker) on maps
far larger than the simulator and the render can make in seconds: a 40 x 40 m floor at
2.5 mm (256 MPix) is written in about a minute. The pixels come from a *tile function*
``tile_fn(r0, r1, c0, c1) -> uint8 (r1 - r0, c1 - c0)`` giving level-0 pixels of any window
of the grid (0 = no data); everything else is what a build would publish
(:mod:`mapstore.layout`): the pyramid (:func:`pipeline.mosaic.downsample2`), the coverage
(1 frame wherever there is data), texture and uniqueness cells (the render's own functions
with the render's parameters and halo), the ``updated`` tiles, the floor version, one
icechunk commit and a tag.

A first call creates the map and writes every level-0 shard (a shard with no data is left
unwritten); a later call rewrites only the level-0 shards it is given, as the next version,
and the pyramid shards above them, like an incremental build. ``updated`` is set to the new
version for the level-0 tiles whose pixels changed.

Content: :func:`periodic_texture` is band-limited noise that tiles seamlessly (made in the
Fourier domain), :func:`texture_tile_fn` repeats it over the grid and can paint
:class:`Patch` changes (a box of other texture, brighter or darker) over it.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np
import zarr

from mapstore.grid import MapGrid
from mapstore.layout import LAYERS_GROUP, LayoutSpec, create_floor, read_floor, set_version
from pipeline.mosaic import coverage_layer, downsample2, release_scratch, shard_box, texture_layer, uniqueness_cells
from pipeline.stages.render import layer_halo_px

__all__ = ["Patch", "TileFn", "periodic_texture", "texture_tile_fn", "shards_for_box", "publish_raster", "publish_repainted"]

log = logging.getLogger(__name__)

TileFn = Callable[[int, int, int, int], np.ndarray]


def periodic_texture(seed: int, period_px: int = 4096, mean: float = 128.0, std: float = 35.0) -> np.ndarray:
    """float32 ``(period_px, period_px)`` band-limited random texture that tiles seamlessly.

    White noise filtered in the Fourier domain (so the filter wraps around) at two scales,
    Gaussian sigmas 1.5 px and 12 px (the second at half the weight), scaled to ``mean +-
    std`` grey levels and clipped to 1..254.
    """
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(period_px).astype(np.float32)
    f2 = f[:, None] ** 2 + f[None, :] ** 2
    spec = np.fft.rfft2(rng.standard_normal((period_px, period_px), dtype=np.float32))
    half = f2[:, : period_px // 2 + 1]
    out = np.zeros((period_px, period_px), np.float32)
    for sigma, weight in ((1.5, 1.0), (12.0, 0.5)):
        band = np.fft.irfft2(spec * np.exp(-2.0 * np.pi**2 * sigma**2 * half), s=(period_px, period_px))
        out += np.float32(weight) * (band / band.std()).astype(np.float32)
    out *= np.float32(std / out.std())
    out += np.float32(mean)
    return np.clip(out, 1.0, 254.0, out=out)


@dataclass(frozen=True)
class Patch:
    """A floor change painted over the texture: inside the world box ``[x0, x1] x [y0, y1]``
    (metres) the texture is read ``shift_px`` (rows, cols) away and ``delta`` grey levels
    are added (a repainted patch; ``shift_px = (0, 0)`` and ``delta != 0`` is a stain)."""

    x0: float
    y0: float
    x1: float
    y1: float
    shift_px: tuple[int, int] = (1021, 2039)
    delta: float = 0.0

    def pixel_box(self, grid: MapGrid) -> tuple[int, int, int, int]:
        """``(r0, r1, c0, c1)``: the level-0 pixels whose centres lie in the box."""
        c0, r0 = grid.world_to_pixel(self.x0, self.y1)
        c1, r1 = grid.world_to_pixel(self.x1, self.y0)
        return int(np.ceil(r0)), int(np.floor(r1)) + 1, int(np.ceil(c0)), int(np.floor(c1)) + 1


def texture_tile_fn(texture: np.ndarray, grid: MapGrid, patches: Sequence[Patch] = ()) -> TileFn:
    """A tile function repeating ``texture`` (float32, grey levels) over ``grid`` (pixel
    (r, c) = texture[r mod P, c mod P]) with ``patches`` painted over it; uint8 1..255."""
    ph, pw = texture.shape
    boxes = [(p.pixel_box(grid), p) for p in patches]

    def sample(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        return texture[np.ix_(rows % ph, cols % pw)]

    def tile(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        rows, cols = np.arange(r0, r1), np.arange(c0, c1)
        out = sample(rows, cols)
        for (pr0, pr1, pc0, pc1), p in boxes:
            a0, a1, b0, b1 = max(r0, pr0), min(r1, pr1), max(c0, pc0), min(c1, pc1)
            if a0 < a1 and b0 < b1:
                sub = sample(np.arange(a0, a1) + p.shift_px[0], np.arange(b0, b1) + p.shift_px[1])
                out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = sub + np.float32(p.delta)
        return np.clip(np.rint(out), 1, 255).astype(np.uint8)

    return tile


def shards_for_box(grid: MapGrid, shard_px: int, x0: float, y0: float, x1: float, y1: float,
                   pad_px: int = 0) -> set[tuple[int, int]]:
    """Level-0 shard indices (row, col) reached by the world box (metres) grown by
    ``pad_px`` pixels, clipped to the grid."""
    c0, r0 = grid.world_to_pixel(x0, y1)
    c1, r1 = grid.world_to_pixel(x1, y0)
    r0, c0 = max(0, int(np.floor(r0)) - pad_px), max(0, int(np.floor(c0)) - pad_px)
    r1, c1 = min(grid.height - 1, int(np.ceil(r1)) + pad_px), min(grid.width - 1, int(np.ceil(c1)) + pad_px)
    return {(i, j) for i in range(r0 // shard_px, r1 // shard_px + 1) for j in range(c0 // shard_px, c1 // shard_px + 1)}


def _window(tile_fn: TileFn, grid: MapGrid, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """``tile_fn`` over a window that may reach beyond the grid (0 = no data there)."""
    out = np.zeros((r1 - r0, c1 - c0), np.uint8)
    a0, a1, b0, b1 = max(r0, 0), min(r1, grid.height), max(c0, 0), min(c1, grid.width)
    if a0 < a1 and b0 < b1:
        out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = tile_fn(a0, a1, b0, b1)
    return out


def _write_level0_shard(root: zarr.Group, grid: MapGrid, spec: LayoutSpec, params: dict, tile_fn: TileFn,
                        ij: tuple[int, int], version: int, fresh: bool) -> int:
    """Write one level-0 shard with its cells and tiles; returns covered pixels."""
    halo = layer_halo_px(params)
    r0, r1, c0, c1 = shard_box(ij, grid.shape, spec.shard_px)
    ext = _window(tile_fn, grid, r0 - halo, r1 + halo, c0 - halo, c1 + halo)
    out = ext[halo : halo + r1 - r0, halo : halo + c1 - c0]
    cell, tile = spec.layer_cell_px, spec.chunk_px
    level0 = root["floor/0"]
    old = np.zeros_like(out) if fresh else level0[r0:r1, c0:c1]
    if not out.any() and not old.any():
        return 0
    level0[r0:r1, c0:c1] = out
    layers = root[LAYERS_GROUP]
    lsl = (slice(r0 // cell, -(-r1 // cell)), slice(c0 // cell, -(-c1 // cell)))
    layers["coverage"][lsl] = coverage_layer((out > 0).astype(np.uint16), cell)
    layers["texture"][lsl] = texture_layer(ext, cell, params["texture_window_px"], params["texture_sigma_px"],
                                           halo_px=halo)
    layers["uniqueness"][lsl] = uniqueness_cells(
        ext, cell, params["uniqueness_template_px"], params["uniqueness_search_radius_px"],
        params["uniqueness_exclusion_px"], level=params["uniqueness_level"], halo_px=halo,
        recheck=tuple(params["uniqueness_recheck"]))
    tsl = (slice(r0 // tile, -(-r1 // tile)), slice(c0 // tile, -(-c1 // tile)))
    changed = coverage_layer((out != old).astype(np.uint16), tile) > 0
    prev = np.zeros(changed.shape, np.int32) if fresh else layers["updated"][tsl]
    layers["updated"][tsl] = np.where(changed, np.int32(version), prev)
    return int(np.count_nonzero(out))


def publish_raster(url: str, grid: MapGrid, tile_fn: TileFn, *, cfg: dict, tag: str | None = None,
                   shards: Iterable[tuple[int, int]] | None = None, message: str = "synthetic map",
                   branch: str = "main", workers: int = 2) -> str:
    """Publish ``tile_fn``'s pixels as the next version of the map at ``url``.

    Args:
        url: map repository (created when absent).
        grid: the level-0 grid; must equal the map's when the map exists.
        tile_fn: level-0 pixels of a window, see the module docstring.
        cfg: the effective configuration (``[map]`` for a new map's layout, ``[render]``
            for the layer parameters).
        tag: tag of the new version (default: the ``[publish] tag_format``).
        shards: level-0 shards to (re)write; None = all (required for a new map).
        workers: threads writing level-0 shards (each owns whole shards).

    Returns the new snapshot id.
    """
    from mapstore.repository import MapRepository

    repo = MapRepository.open_or_create(url)
    with repo.commit_lock():
        session = repo.writable(branch)
        root = zarr.open_group(session.store, mode="a")
        fresh = "floor" not in root
        if fresh:
            create_floor(root, grid, LayoutSpec.from_config(cfg["map"]))
        info = read_floor(root)
        if info.grid != grid:
            raise ValueError(f"grid {grid} differs from the map's {info.grid}")
        spec, version = info.spec, info.version + 1
        n_sr, n_sc = (-(-n // spec.shard_px) for n in grid.shape)
        todo = sorted({(i, j) for i in range(n_sr) for j in range(n_sc)} if shards is None else set(shards))
        if fresh and shards is not None:
            raise ValueError("a new map is written whole: shards must be None")
        with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            covered = sum(pool.map(lambda ij: _write_level0_shard(root, grid, spec, cfg["render"], tile_fn, ij,
                                                                  version, fresh), todo))
        release_scratch()  # the layers' per-thread buffers
        below = set(todo)
        for k in range(1, info.levels):
            shape, lower = grid.level(k).shape, grid.level(k - 1).shape
            level = {(i // 2, j // 2) for i, j in below}
            for ij in sorted(level):
                r0, r1, c0, c1 = shard_box(ij, shape, spec.shard_px)
                block = root[f"floor/{k - 1}"][2 * r0 : min(2 * r1, lower[0]), 2 * c0 : min(2 * c1, lower[1])]
                root[f"floor/{k}"][r0:r1, c0:c1] = downsample2(block)
            below = level
        set_version(root, version)
        name = tag or repo.next_tag(cfg["publish"]["tag_format"])
        snapshot = repo.commit(session, f"{message}: version {version}",
                               metadata={"version": version, "tag": name, "synthetic": True,
                                         "shards_written": len(todo), "covered_px": covered})
        repo.tag(snapshot, name)
    log.info("%s: version %d (%s) = %s, %d level-0 shards", url, version, name, snapshot, len(todo))
    return snapshot


def publish_repainted(url: str, grid: MapGrid, texture: np.ndarray, patch: Patch, *, cfg: dict,
                      pad_px: int = 16) -> tuple[str, str]:
    """A two-version map at ``url``: version 1 (tag ``v1``) ``texture`` over ``grid``,
    version 2 (tag ``v2``) the same with ``patch`` painted, only the level-0 shards within
    ``pad_px`` of it rewritten (``[map] shard_px`` of ``cfg``). Returns the two snapshot ids."""
    v1 = publish_raster(url, grid, texture_tile_fn(texture, grid), cfg=cfg, tag="v1")
    shards = shards_for_box(grid, cfg["map"]["shard_px"], patch.x0, patch.y0, patch.x1, patch.y1, pad_px=pad_px)
    v2 = publish_raster(url, grid, texture_tile_fn(texture, grid, [patch]), cfg=cfg, tag="v2", shards=shards)
    return v1, v2

