"""Stage ``render``: the optimized frames warped into map shards, pyramid and layers.

Output: ``WORKDIR/render/map.zarr``, a plain zarr directory in the map layout
(:mod:`mapstore.layout`) holding only the shards this build touched, and ``touched.json``
listing them per array; ``publish`` copies exactly those shards into the repository.

Frames rendered: along each log every frame that moved a fraction of a footprint from the
last one kept (:func:`decimate_frames`), then, over the whole map at once, a greedy subset
of those that still sees every cell ``[render] coverage_depth`` times with full weight and
keeps the covered area exactly (:mod:`pipeline.render_select`; one choice for the map, so
neighbouring shards blend the same frames).

One dask task per block of ``task_block_shards`` x ``task_block_shards`` level-0 shards
(aligned; 1 x 1 when that would give fewer than 4 tasks): a task owns whole shards, never
two tasks one shard. Per task:

1. the frames whose footprint reaches its shards (:func:`pipeline.mosaic.assign_to_shards`),
   each read once from the frames store (uint16, as stored) and warped once into the
   block's accumulators, with its optimized pose, divided by its exposure gain
   (:mod:`pipeline.gains`), feather-weighted and averaged (:mod:`pipeline.mosaic`): with
   ``[render] composite = "seams"`` (the default) each cell is drawn from its
   ``seam_frames`` deepest frames, feathered across the seams (:mod:`pipeline.seams`; a
   frame is warped only near the cells it draws, and not read when it draws none), with
   ``"blend"`` every frame over its whole footprint;
2. over an existing map the result is composited over the published pixels (new frames
   replace the old pixels where their weight saturates, blending over the feather width);
3. per shard, the coverage, texture and uniqueness cells and the ``updated`` tiles;
4. with an even block side, the level-1 shards above the block, reduced in memory.

Then level by level (from level 2, or 1 for odd blocks), each touched level-k shard is
reduced from the 2 x 2 level-(k-1) shards below it, read from this build where it touched
them and from the published map elsewhere. Memory per task is a few block-sized arrays,
whatever the map's size.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import dask
import numpy as np
import zarr

from mapstore.grid import MapGrid
from mapstore.layout import LAYERS_GROUP, FloorInfo, LayoutSpec, create_floor, levels_for, read_floor
from pipeline.progress import counter
from pipeline.errors import BadInput, JobFailed
from pipeline.framestore import INTENSITY_SCALE, FrameStore, store_version
from pipeline.fsutil import write_json_atomic
from pipeline.gains import solve_log_gains
from pipeline.geometry_gate import dropped_mask
from pipeline.links import read_link_gains
from pipeline.mosaic import (
    INTERPOLATIONS,
    accumulate_frame,
    assign_to_shards,
    composite_over,
    coverage_layer,
    downsample2,
    edge_distance,
    feather_from_distance,
    feather_weight,
    finish,
    frame_boxes,
    interpolation_margin_px,
    release_scratch,
    shard_box,
    texture_layer,
    uniqueness_cells,
    weight_ones_box,
)
from pipeline.stages.optimize import read_poses_table
from pipeline.parallel import dask_scheduler
from pipeline.render_select import select_frames
from pipeline.seams import CellLattice, block_seams, pixel_weights, seam_radius_cells
from pipeline.shardfile import DirectWriter, write_region
from pipeline.stages.stage import Stage, StageParams, process_cpu_seconds
from pipeline.stages.workspace import Workspace

log = logging.getLogger(__name__)


def read_stage_poses(path: Path) -> np.ndarray:
    """(N, 3) poses (x, y, theta) of ``optimize/poses.csv``, in frames-store order."""
    data = read_poses_table(path)
    return np.column_stack([data["x"], data["y"], data["theta"]]).astype(float).reshape(-1, 3)


def read_stage_scales(path: Path) -> np.ndarray | None:
    """(N,) frame scales of ``optimize/poses.csv`` (``[optimize] pose_model = "similarity2"``:
    a frame's pixels span ``pixel_size x scale`` metres), or None when it has no scale column."""
    data = read_poses_table(path)
    if "scale" not in (data.dtype.names or ()):
        return None
    return np.asarray(data["scale"], float).reshape(-1)


def frame_log_gains(ws: Workspace, n: int, cfg_render: dict) -> np.ndarray:
    """(N,) log exposure gains of the build's frames from the accepted links' ratios."""
    if not cfg_render["gain_compensation"]:
        return np.zeros(n)
    parts = [read_link_gains(ws.optimize_links)]
    if ws.optimize_map_links.exists():
        parts.append(read_link_gains(ws.optimize_map_links))
    a, b, gain, accepted = (np.concatenate(c) for c in zip(*parts))
    use = accepted & (gain > 0)
    return solve_log_gains(n, a[use], b[use], np.log(gain[use]), cfg_render["gain_prior_sigma"],
                           cfg_render["gain_link_sigma"])


def plan_grid(boxes_world: np.ndarray, pixel_size: float, margin_m: float, base: MapGrid | None,
              site_extent: list | tuple = ()) -> MapGrid:
    """The map grid: the published one grown to cover the frames, or a new one (over the
    site extent and the frames, or around the frames with ``margin_m``).

    ``boxes_world``: (N, 4) xmin, ymin, xmax, ymax of the frames' footprints (metres);
    ``site_extent``: () or (xmin, ymin, xmax, ymax) metres.
    """
    xmin, ymin = boxes_world[:, 0].min(), boxes_world[:, 1].min()
    xmax, ymax = boxes_world[:, 2].max(), boxes_world[:, 3].max()
    if base is None:
        if len(site_extent):
            if len(site_extent) != 4 or not site_extent[0] < site_extent[2] or not site_extent[1] < site_extent[3]:
                raise BadInput("config[map.site_extent_m]", f"need [xmin, ymin, xmax, ymax] with min < max, got {site_extent}")
            ex = site_extent
            return MapGrid.covering(min(ex[0], xmin), min(ex[1], ymin), max(ex[2], xmax), max(ex[3], ymax), pixel_size)
        m = margin_m
        return MapGrid.covering(xmin - m, ymin - m, xmax + m, ymax + m, pixel_size)
    if abs(base.pixel_size - pixel_size) > 1e-12:
        raise JobFailed(f"the frames are rectified at {pixel_size} m per pixel, the published map has "
                        f"{base.pixel_size} m: set [map] pixel_size_m to the map's")
    try:
        return base.extended(xmin, ymin, xmax, ymax)
    except ValueError as e:
        raise JobFailed(f"new frames lie outside the published map's grid: {e}; the map grows only "
                        "to the right and bottom (raise [map] margin_m for the first build)") from None


def world_footprints(poses: np.ndarray, shapes: list[tuple[int, int]], log_of: np.ndarray, px: float) -> np.ndarray:
    """(N, 4) world boxes xmin, ymin, xmax, ymax (metres) of the frames' footprints."""
    out = np.empty((len(poses), 4))
    for k, shape in enumerate(shapes):
        sel = log_of == k
        if not sel.any():
            continue
        half = 0.5 * np.hypot(*shape) * px
        out[sel] = np.column_stack([poses[sel, 0] - half, poses[sel, 1] - half, poses[sel, 0] + half, poses[sel, 1] + half])
    return out


def decimate_frames(poses: np.ndarray, log_of: np.ndarray, min_step_m: np.ndarray | float,
                    min_turn_rad: float) -> np.ndarray:
    """(N,) bool: the frames the render uses.

    Along each log a frame is kept when it moved at least ``min_step_m`` (metres; per log
    or scalar) or turned at least ``min_turn_rad`` from the last kept frame; the last frame
    of a log is always kept. Consecutive frames of a drive overlap by far more than the
    blend needs (10 cm apart for 60 cm footprints: every pixel seen 6-12 times); keeping
    frames a fraction of a footprint apart still covers every pixel several times while
    warping several times fewer pixels.
    """
    keep = np.zeros(len(poses), bool)
    step = np.broadcast_to(np.asarray(min_step_m, float), (int(log_of.max()) + 1 if len(log_of) else 1,))
    for k in np.unique(log_of):
        idx = np.flatnonzero(log_of == k)
        last = None
        for i in idx:
            p = poses[i]
            if last is None or np.hypot(p[0] - last[0], p[1] - last[1]) >= step[k] or \
                    abs(np.angle(np.exp(1j * (p[2] - last[2])))) >= min_turn_rad:
                keep[i] = True
                last = p
        keep[idx[-1]] = True
    return keep


def frames_to_render(store: FrameStore, poses: np.ndarray, log_of: np.ndarray, grid: MapGrid, rcfg: dict,
                     scales: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(decimated, used): (N,) bool masks of the frames kept by :func:`decimate_frames` and,
    of those, the ones rendered (:func:`pipeline.render_select.select_frames` with
    ``[render] coverage_depth`` and ``select_cell_px``)."""
    px = store.pixel_size
    shapes = [lf.valid.shape for lf in store.logs]
    step = np.array([rcfg["frame_step_fraction"] * min(shape) * px for shape in shapes])
    decimated = decimate_frames(poses, log_of, step, rcfg["frame_turn_rad"])
    interp = INTERPOLATIONS[rcfg["interpolation"]]
    log_weights = [feather_weight(lf.valid, rcfg["feather_px"], interpolation_margin_px(interp)) for lf in store.logs]
    fpx = np.full(len(poses), px) if scales is None else px * np.asarray(scales, float)
    used = select_frames(grid, poses, shapes, log_of, log_weights, fpx, decimated, int(rcfg["coverage_depth"]),
                         int(rcfg["select_cell_px"]))
    return decimated, used


class _Source:
    """Reads a level's pixels from this build's shards where it touched them, from the
    published map elsewhere (zeros = no data where neither has them)."""

    def __init__(self, staging: zarr.Array, base: zarr.Array | None, touched: set, shard_px: int):
        self.staging, self.base, self.touched, self.shard_px = staging, base, touched, shard_px

    def read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        out = np.zeros((r1 - r0, c1 - c0), np.uint8)
        s = self.shard_px
        for i in range(r0 // s, (r1 - 1) // s + 1):
            for j in range(c0 // s, (c1 - 1) // s + 1):
                src = self.staging if (i, j) in self.touched else self.base
                if src is None:
                    continue
                h, w = src.shape
                a0, a1 = max(r0, i * s), min(r1, (i + 1) * s, h)
                b0, b1 = max(c0, j * s), min(c1, (j + 1) * s, w)
                if a0 < a1 and b0 < b1:
                    out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = src[a0:a1, b0:b1]
        return out


def _open_base(base: dict | None) -> zarr.Group | None:
    if base is None:
        return None
    from mapstore.repository import MapRepository

    return zarr.open_group(MapRepository.open(base["url"]).readonly(base["snapshot"]).store, mode="r")


def _clipped(arr: zarr.Array | None, r0: int, r1: int, c0: int, c1: int, fill) -> np.ndarray:
    """``arr[r0:r1, c0:c1]`` where it exists, ``fill`` beyond its edges (or without it);
    the box may reach outside the array on any side."""
    dtype = np.dtype(type(fill)) if arr is None else arr.dtype
    out = np.full((r1 - r0, c1 - c0), fill, dtype=dtype)
    if arr is not None:
        h, w = arr.shape
        a0, a1, b0, b1 = max(r0, 0), min(r1, h), max(c0, 0), min(c1, w)
        if a0 < a1 and b0 < b1:
            out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = arr[a0:a1, b0:b1]
    return out


def frame_reach_px(params: dict, cell_px: int) -> int:
    """Level-0 pixels around a block's shards within which a frame's footprint must be
    given to its task: the layers' halo, and with the seam composite the cells around it
    whose ownership the seams' ramp reads (:func:`_seam_regions`), plus a cell for rounding."""
    reach = layer_halo_px(params)
    if params["composite"] == "seams":
        reach += (seam_radius_cells(params["feather_px"], cell_px) + 2) * cell_px
    return reach


def layer_halo_px(params: dict) -> int:
    """Pixels of context around a shard that its texture and uniqueness cells read (even: a
    shard's box with its halo starts on a level-1 pixel, for the uniqueness on level 1)."""
    halo = int(max(params["uniqueness_template_px"] // 2 + params["uniqueness_search_radius_px"],
                   params["texture_window_px"] // 2 + 3 * params["texture_sigma_px"] + 1))
    return halo + halo % 2


class _FrameBlocks:
    """Frames of a frames store as stored (uint16), for the render's tasks.

    A task asks for its sorted frames; each run of consecutive frames not yet held is read
    in one call (:meth:`pipeline.framestore.LogFrames.images_uint16`: the shard file read
    directly, only the run's chunks read: ~0.15 ms per 640 x 480 frame stored uncompressed,
    ~0.5 ms zstd-compressed; through zarr ~1-3 ms). Frames are kept in a per-process LRU of
    ``cache_mb``, shared by the tasks of neighbouring blocks on the threads scheduler (a
    frame near a block border is read once for both)."""

    def __init__(self, store: str, cache_mb: float):
        self.store = FrameStore(store)
        self.offsets = np.cumsum([0] + [lf.count for lf in self.store.logs])
        self.cache_bytes = cache_mb * 1e6
        self.held: OrderedDict[int, np.ndarray] = OrderedDict()
        self.held_bytes = 0
        self.lock = threading.Lock()

    def _cached(self, g: int) -> np.ndarray | None:
        with self.lock:
            data = self.held.get(g)
            if data is not None:
                self.held.move_to_end(g)
            return data

    def _keep(self, g: int, data: np.ndarray) -> None:
        with self.lock:
            if g not in self.held:
                self.held[g] = data
                self.held_bytes += data.nbytes
            while len(self.held) > 1 and self.held_bytes > self.cache_bytes:
                self.held_bytes -= self.held.popitem(last=False)[1].nbytes

    def logs_of(self, frames: np.ndarray) -> np.ndarray:
        """(F,) log index of each global frame index."""
        return np.searchsorted(self.offsets, frames, side="right") - 1

    def frames(self, frames: np.ndarray):
        """Yield ``(g, uint16 image, log index)`` for sorted global frame indices."""
        frames = np.asarray(frames, np.int64)
        k_of = self.logs_of(frames)
        local = frames - self.offsets[k_of]
        held = [self._cached(int(g)) for g in frames]
        n = 0
        while n < len(frames):
            k = int(k_of[n])
            if held[n] is not None:
                yield int(frames[n]), held[n], k
                n += 1
                continue
            m = n + 1  # a run of consecutive frames of one log, none held: one read
            while m < len(frames) and held[m] is None and k_of[m] == k and local[m] == local[m - 1] + 1:
                m += 1
            # each frame its own array (decoded into it): the cache holds what it counts
            run = self.store.logs[k].images_uint16(int(local[n]), int(local[m - 1]) + 1, separate=True)
            for q in range(n, m):
                img = run[q - n]
                self._keep(int(frames[q]), img)
                yield int(frames[q]), img, k
            n = m


@lru_cache(maxsize=2)
def _frame_blocks(store: str, version: int, cache_mb: float) -> _FrameBlocks:
    """One frame source per process and frames store (``version``: :func:`store_version`, so a
    store rewritten by a later ingest is not served from the old cache)."""
    return _FrameBlocks(store, cache_mb)


# Per thread (ident): the buffers of :func:`_workspace`; run_render drops them when done.
_WORKSPACES: dict[int, tuple[np.ndarray, ...]] = {}


def _workspace(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Zeroed contiguous (acc float32, wacc float32, count uint16) and an uninitialised
    uint8 intensity of ``shape``, from buffers kept per thread and reused by its next tasks.

    A block's accumulators are ~200 MB: fresh ones are new memory maps every task, whose
    first touch costs a page fault per 4 KiB (~20 % of the render's CPU, in the kernel);
    reused pages cost one memset."""
    n = shape[0] * shape[1]
    bufs = _WORKSPACES.get(threading.get_ident())
    if bufs is None or bufs[0].size < n:
        _WORKSPACES.pop(threading.get_ident(), None)
        bufs = _WORKSPACES[threading.get_ident()] = (np.empty(n, np.float32), np.empty(n, np.float32),
                                                     np.empty(n, np.uint16), np.empty(n, np.uint8))
    views = tuple(b[:n].reshape(shape) for b in bufs)
    for v in views[:3]:
        v.fill(0)
    return views


def _zero_outside(a: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> None:
    """Zero ``a`` outside rows ``r0:r1`` and columns ``c0:c1``, in place."""
    a[:r0] = 0
    a[r1:] = 0
    a[:, :c0] = 0
    a[:, c1:] = 0


def _small_pages(enabled: bool = False) -> bool:
    """Whether numpy asks the kernel for transparent huge pages (``madvise``) for its arrays
    of 4 MB and more, set in this process; returns the previous setting (True when numpy has
    no such switch).

    The render allocates many block- and shard-sized arrays for short whiles. Where huge
    pages are given on request (``/sys/kernel/mm/transparent_hugepage/enabled`` =
    ``madvise``, with defrag on request), each of their faults zeroes, and may compact, 2 MB:
    3 blocks of the 40 x 40 m benchmark on one thread took 1.6 s of kernel time with numpy's
    default and 0.4 s without, ~20 % less CPU in all (2026-12-02)."""
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:
        return True
    return bool(_set_madvise_hugepage(enabled))


def _block_of(ij: tuple[int, int], side: int) -> tuple[int, int]:
    return ij[0] // side, ij[1] // side


def _level0_task(work: dict, shards: list[tuple[int, int]], frames: np.ndarray, n_frames: list[int]) -> dict:
    """Render a block of level-0 shards (their cells and tiles; with an even block side
    also the level-1 shards above it) from the sorted global frame indices ``frames``
    (``n_frames``: how many of them reach each shard, for the statistics).

    Returns per-shard statistics, the level-1 shards written and per-phase seconds."""
    _small_pages()  # (worker processes: set in each; the threads scheduler's by run_render)
    clock = time.perf_counter
    t_start = clock()
    phases = dict.fromkeys(("seams", "read", "warp", "blend_finish", "layers", "texture", "uniqueness", "write",
                            "level1"), 0.0)
    grid = MapGrid.from_attrs(work["grid"])
    spec = LayoutSpec(**work["spec"])
    p = work["params"]
    staging = zarr.open_group(work["staging"], mode="r+")
    base = _open_base(work["base"])
    source = _frame_blocks(work["store"], store_version(Path(work["store"])), float(p["frame_cache_mb"]))
    store = source.store
    poses, gains = work["poses"], np.exp(work["log_gains"])
    interp = INTERPOLATIONS[p["interpolation"]]
    cell, tile, sp = spec.layer_cell_px, spec.chunk_px, spec.shard_px
    halo = layer_halo_px(p)
    side = work["block_side"]
    # The block's level-0 box (whole shards, clipped to the grid) plus the layers' halo.
    bi, bj = _block_of(shards[0], side)
    b0 = shard_box((bi * side, bj * side), grid.shape, sp)
    r1b, c1b = min((bi + 1) * side * sp, grid.height), min((bj + 1) * side * sp, grid.width)
    ext = (b0[0] - halo, r1b + halo, b0[2] - halo, c1b + halo)
    shape = (ext[1] - ext[0], ext[3] - ext[2])
    acc, wacc, count, out_ext = _workspace(shape)
    weights: dict[int, tuple] = {}  # log -> (feather weight, its box of ones, its edge distance)

    def log_weight(k: int) -> tuple:
        if k not in weights:
            dist = edge_distance(store.logs[k].valid, interpolation_margin_px(interp))
            wk = feather_from_distance(dist, p["feather_px"])
            weights[k] = (wk, weight_ones_box(wk), dist)
        return weights[k]

    def frame_px(g: int) -> float:
        return work["pixel_size"] if work.get("scales") is None else work["pixel_size"] * float(work["scales"][g])

    seen = lattice = None
    regions: dict[int, tuple] = {}
    if p["composite"] == "seams":
        t = clock()
        frames, regions, lattice, seen = _seam_regions(work, grid, source.logs_of(frames), frames, ext, cell,
                                                       log_weight, frame_px)
        phases["seams"] += clock() - t
    t = clock()
    for g, img, k in source.frames(frames):
        t1 = clock()
        phases["read"] += t1 - t
        wk = log_weight(k)
        region = None
        if lattice is not None:  # the frame's seam weights on the block's pixels
            region = pixel_weights(lattice, *regions[g], ext)
        if lattice is None or region is not None:
            accumulate_frame(acc, wacc, count, ext, grid, img, wk[0], poses[g], frame_px(g), float(gains[g]), interp,
                             intensity_scale=INTENSITY_SCALE, weight_ones=wk[1], region=region)
        t = clock()
        phases["warp"] += t - t1
    phases["read"] += clock() - t
    t = clock()
    finish(acc, wacc, out=out_ext, in_place=True)
    del acc
    # no data beyond the grid's edges
    gr0, gc0 = max(0, -ext[0]), max(0, -ext[2])
    gr1, gc1 = shape[0] - max(0, ext[1] - grid.height), shape[1] - max(0, ext[3] - grid.width)
    _zero_outside(out_ext, gr0, gr1, gc0, gc1)
    if base is not None:
        # the published pixels under the new ones (and as they are where no new frame reaches)
        old_ext = _clipped(base["floor/0"], *ext, np.uint8(0))
        _zero_outside(old_ext, gr0, gr1, gc0, gc1)
        out_ext = composite_over(old_ext, out_ext, wacc)
        del old_ext
    del wacc
    phases["blend_finish"] += clock() - t
    t = clock()
    # The block's level-1 pixels (its box starts on an even row and column: shards and the
    # halo are even): the uniqueness cells on level 1 and the level-1 shards above the block.
    level1_block = side % 2 == 0 and work["levels"] > 1
    half = downsample2(out_ext) if level1_block or p["uniqueness_level"] == 1 else None
    phases["level1"] += clock() - t
    layers = staging[LAYERS_GROUP]
    # Whole shards and layer chunks go straight to their files (pipeline.shardfile).
    writers = {name: (arr, DirectWriter.for_array(arr)) for name, arr in
               [("floor/0", staging["floor/0"])] + [(n, layers[n]) for n in ("coverage", "texture", "uniqueness",
                                                                              "updated")]}
    stats = []
    for ij in shards:
        r0, r1, c0, c1 = shard_box(ij, grid.shape, sp)
        t = clock()
        # the shard plus its halo, in block coordinates
        sl = (slice(r0 - halo - ext[0], r1 + halo - ext[0]), slice(c0 - halo - ext[2], c1 + halo - ext[2]))
        sh_ext = np.ascontiguousarray(out_ext[sl])
        inner = (slice(halo, halo + r1 - r0), slice(halo, halo + c1 - c0))
        cnt = count[sl][inner]
        lr0, lr1, lc0, lc1 = r0 // cell, -(-r1 // cell), c0 // cell, -(-c1 // cell)
        tr0, tr1, tc0, tc1 = r0 // tile, -(-r1 // tile), c0 // tile, -(-c1 // tile)
        cov = coverage_layer(cnt, cell)
        if seen is not None:  # frames whose weight covers the cell's centre, not only those blended there
            a0, b0 = lr0 - lattice.i0, lc0 - lattice.j0
            np.maximum(cov, seen[a0 : a0 + cov.shape[0], b0 : b0 + cov.shape[1]], out=cov)
        upd = np.full((tr1 - tr0, tc1 - tc0), work["version"], np.int32)
        tiles_hit = coverage_layer(cnt, tile) > 0
        if base is not None:
            old_cov = _clipped(base[f"{LAYERS_GROUP}/coverage"], lr0, lr1, lc0, lc1, np.uint16(0))
            cov = np.where(cov > 0, cov, old_cov)
            old_upd = _clipped(base[f"{LAYERS_GROUP}/updated"], tr0, tr1, tc0, tc1, np.int32(0))
            upd = np.where(tiles_hit, upd, old_upd)
        else:
            upd = np.where(tiles_hit, upd, 0).astype(np.int32)
        t1 = clock()
        phases["layers"] += t1 - t  # coverage and updated
        tex = texture_layer(sh_ext, cell, p["texture_window_px"], p["texture_sigma_px"], halo_px=halo,
                            sample_px=p["texture_sample_px"])
        t2 = clock()
        phases["texture"] += t2 - t1
        reduced = None
        if half is not None:  # the shard and its halo on level 1
            h0, w0 = (r0 - halo - ext[0]) // 2, (c0 - halo - ext[2]) // 2
            reduced = half[h0 : h0 + halo + -(-(r1 - r0) // 2), w0 : w0 + halo + -(-(c1 - c0) // 2)]
        uni = uniqueness_cells(sh_ext, cell, p["uniqueness_template_px"], p["uniqueness_search_radius_px"],
                               p["uniqueness_exclusion_px"], level=p["uniqueness_level"], halo_px=halo,
                               reduced=reduced, recheck=tuple(p["uniqueness_recheck"]))
        t1 = clock()
        phases["uniqueness"] += t1 - t2
        out = sh_ext[inner]
        write_region(*writers["floor/0"], r0, c0, out)
        write_region(*writers["coverage"], lr0, lc0, cov)
        write_region(*writers["texture"], lr0, lc0, tex)
        write_region(*writers["uniqueness"], lr0, lc0, uni)
        write_region(*writers["updated"], tr0, tc0, upd)
        phases["write"] += clock() - t1
        stats.append({"shard": list(ij), "frames": int(n_frames[len(stats)]), "pixels": int(out.size),
                      "covered": int(np.count_nonzero(out))})
    level1 = []
    if level1_block:
        # The level-1 shards above the block: 2 x 2 level-0 shards each, all inside it
        # (this build's pixels where it touched them, the published ones elsewhere; no
        # data beyond the grid).
        t = clock()
        g1 = grid.level(1)
        arr1 = staging["floor/1"]
        w1 = DirectWriter.for_array(arr1)
        for ij1 in sorted({(i // 2, j // 2) for i, j in shards}):
            R0, R1, C0, C1 = shard_box(ij1, g1.shape, sp)
            a0, c0_ = (2 * R0 - ext[0]) // 2, (2 * C0 - ext[2]) // 2
            write_region(arr1, w1, R0, C0, half[a0 : a0 + R1 - R0, c0_ : c0_ + C1 - C0])
            level1.append(list(ij1))
        phases["level1"] += clock() - t
    return {"stats": stats, "level1": level1, "phases": phases, "seconds": clock() - t_start}


def _seam_regions(work: dict, grid: MapGrid, k_of: np.ndarray, frames: np.ndarray, ext: tuple, cell: int,
                  log_weight, frame_px) -> tuple[np.ndarray, dict, CellLattice, np.ndarray]:
    """The seam composite's plan for a block whose level-0 box with its halo is ``ext``
    (:func:`pipeline.seams.block_seams`, cells of the map's ``cell`` px; ``k_of``: each
    frame's log): (the frames that may contribute, sorted; frame -> its cells and cell
    weights; the lattice; per cell, the frames whose weight covers its centre)."""
    lattice, cell_weights, seen = block_seams(
        grid, ext, cell, work["poses"][frames], [log_weight(k)[2] for k in k_of.tolist()],
        np.array([frame_px(g) for g in frames.tolist()]), work["params"]["feather_px"],
        work["params"]["seam_frames"])
    regions = {g: cw for g, cw in zip(frames.tolist(), cell_weights) if cw is not None}
    return np.array(sorted(regions), np.int64), regions, lattice, seen


def _pyramid_task(work: dict, level: int, shards: list[tuple[int, int]], below: list) -> int:
    """Reduce level ``level`` shards from the level below; returns pixels written."""
    _small_pages()
    spec = LayoutSpec(**work["spec"])
    grid = MapGrid.from_attrs(work["grid"])
    staging = zarr.open_group(work["staging"], mode="r+")
    base = _open_base(work["base"])
    base_arr = None
    if base is not None and str(level - 1) in base["floor"]:
        base_arr = base[f"floor/{level - 1}"]
    src = _Source(staging[f"floor/{level - 1}"], base_arr, {tuple(t) for t in below}, spec.shard_px)
    lower = grid.level(level - 1).shape
    arr = staging[f"floor/{level}"]
    writer = DirectWriter.for_array(arr)
    written = 0
    for ij in shards:
        r0, r1, c0, c1 = shard_box(ij, grid.level(level).shape, spec.shard_px)
        block = src.read(2 * r0, min(2 * r1, lower[0]), 2 * c0, min(2 * c1, lower[1]))
        out = downsample2(block)
        write_region(arr, writer, r0, c0, out)
        written += out.size
    return written


@dataclass
class _RenderPlan:
    """What the render draws from: the frames, their poses and the grid they go on.

    ``poses``: (N, 3) optimized poses (metres, radians); ``scales``: (N,) similarity frame
    scales or None; ``px``: the frames store's pixel size (metres); ``fpx``: each frame's
    pixel size (metres: ``px``, or (N,) ``px x scale``); ``keep``: (N,) frames not dropped by
    optimize; ``footprints``: (K, 4) the kept frames' footprints (metres, xmin ymin xmax ymax);
    ``version``: the version being rendered."""

    store_path: Path
    store: FrameStore
    poses: np.ndarray
    scales: np.ndarray | None
    shapes: list
    log_of: np.ndarray
    px: float
    fpx: np.ndarray | float
    spec: LayoutSpec
    base_root: zarr.Group | None
    base_info: FloorInfo | None
    keep: np.ndarray
    footprints: np.ndarray
    grid: MapGrid
    version: int


def _plan(ws: Workspace, cfg: dict, base: dict | None) -> _RenderPlan:
    """Check the configuration and the optimize stage's output, read the frames and poses,
    and plan the grid (the published one grown, or a new one)."""
    rcfg, mcfg = cfg["render"], cfg["map"]
    if rcfg["interpolation"] not in INTERPOLATIONS:
        raise JobFailed(f"[render] interpolation: unknown {rcfg['interpolation']!r} (one of {', '.join(INTERPOLATIONS)})")
    store_path = ws.frames_store
    store = FrameStore(store_path)
    poses = read_stage_poses(ws.poses)
    shapes = [lf.valid.shape for lf in store.logs]
    log_of = np.concatenate([np.full(lf.count, k) for k, lf in enumerate(store.logs)])
    if len(poses) != len(log_of):
        raise JobFailed(f"{ws.poses}: {len(poses)} poses for {len(log_of)} frames")
    px = store.pixel_size
    # Similarity poses: each frame at its own pixel size (px x scale; footprints at the largest).
    scales = read_stage_scales(ws.poses)
    fpx = px if scales is None else px * scales
    spec = LayoutSpec.from_config(mcfg)
    base_root = _open_base(base)
    base_info = read_floor(base_root) if base_root is not None else None
    if base_info is not None:
        spec = base_info.spec  # a map keeps its storage layout
    if rcfg["uniqueness_level"] == 1 and spec.layer_cell_px % 2:
        raise BadInput("config[render.uniqueness_level]", f"1 needs an even [map] layer_cell_px, the map's is "
                                                          f"{spec.layer_cell_px} (set 0)")
    # Frames the optimize stage dropped (a wild prior, pipeline.geometry_gate) are not rendered.
    keep = ~dropped_mask(ws.dropped, len(poses))
    if not keep.any():
        raise JobFailed(f"{ws.dropped}: every frame was dropped; nothing to render")
    footprints = world_footprints(poses, shapes, log_of, px if scales is None else px * float(scales.max()))[keep]
    grid = plan_grid(footprints, px, mcfg["margin_m"],
                     None if base_info is None else base_info.grid, mcfg["site_extent_m"])
    version = (0 if base_info is None else base_info.version) + 1
    return _RenderPlan(store_path, store, poses, scales, shapes, log_of, px, fpx, spec, base_root, base_info, keep,
                       footprints, grid, version)


def _write_gains(ws: Workspace, plan: _RenderPlan, rcfg: dict) -> np.ndarray:
    """(N,) log exposure gains of the frames, also written (as gains) to ``ws.gains``."""
    log_gains = frame_log_gains(ws, len(plan.poses), rcfg)
    np.savetxt(ws.gains, np.exp(log_gains), fmt="%.6f", header="gain", comments="")
    return log_gains


def _create_staging(ws: Workspace, plan: _RenderPlan) -> Path:
    """A new, empty map layout at ``ws.render_store`` on the plan's grid (the published
    map's id when extending it); returns its path."""
    staging_path = ws.render_store
    create_floor(zarr.open_group(str(staging_path), mode="w"), plan.grid, plan.spec,
                 map_id=None if plan.base_root is None else str(plan.base_root.attrs.get("map_id")))
    return staging_path


def _work_params(rcfg: dict) -> dict:
    """The ``[render]`` knobs the tasks read."""
    return {k: rcfg[k] for k in ("interpolation", "composite", "seam_frames", "feather_px", "frame_cache_mb",
                                 "texture_window_px", "texture_sigma_px", "texture_sample_px", "uniqueness_template_px",
                                 "uniqueness_search_radius_px", "uniqueness_exclusion_px", "uniqueness_level",
                                 "uniqueness_recheck")}


def _write_touched(ws: Workspace, plan: _RenderPlan, levels: int, base: dict | None, touched: dict) -> None:
    """``ws.touched``: the grid, layout, version and the shards written per level,
    for ``publish``."""
    write_json_atomic(ws.touched, {
        "grid": plan.grid.to_attrs(), "spec": plan.spec.to_attrs(), "version": plan.version, "levels": levels,
        "base": base, "shards": {str(k): [list(t) for t in v] for k, v in touched.items()},
    })


def _select(plan: _RenderPlan, rcfg: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """(decimated, used, seconds): :func:`frames_to_render`'s masks without the dropped frames,
    and the wall time of the selection."""
    t_select = time.perf_counter()
    decimated, used = frames_to_render(plan.store, plan.poses, plan.log_of, plan.grid, rcfg, plan.scales)
    decimated &= plan.keep
    used &= plan.keep
    return decimated, used, time.perf_counter() - t_select


def _assign_shards(plan: _RenderPlan, used: np.ndarray, work_params: dict) -> tuple[list, dict]:
    """(sorted level-0 shards the used frames reach, shard -> sorted global frame indices)."""
    grid, poses, px, fpx = plan.grid, plan.poses, plan.px, plan.fpx
    touched0: dict = {}
    for k, shape in enumerate(plan.shapes):
        sel = np.flatnonzero((plan.log_of == k) & used)
        if len(sel) == 0:
            continue
        boxes = frame_boxes(grid, poses[sel], shape, px if plan.scales is None else fpx[sel],
                            pad_px=2 + frame_reach_px(work_params, plan.spec.layer_cell_px))
        part = assign_to_shards(boxes, grid.shape, plan.spec.shard_px)
        for ij, idx in part.items():
            touched0.setdefault(ij, []).append(sel[idx])
    shards = sorted(touched0)
    frame_lists = {ij: np.sort(np.concatenate(touched0[ij])) for ij in shards}
    return shards, frame_lists


def _task_blocks(shards: list, rcfg: dict) -> tuple[int, dict]:
    """(block side, block -> its shards)."""
    # Tasks: aligned blocks of side x side shards (frames read and warped once per block),
    # single shards when blocks would leave fewer than 4 tasks (both cores busy on small maps).
    side = max(int(rcfg["task_block_shards"]), 1)
    if len({_block_of(ij, side) for ij in shards}) < 4:
        side = 1
    blocks: dict = {}
    for ij in shards:
        blocks.setdefault(_block_of(ij, side), []).append(ij)
    return side, blocks


def _render_level0(run, work: dict, blocks: dict, frame_lists: dict,
                   quiet: bool) -> tuple[list[dict], dict, set]:
    """Run the level-0 tasks (with the progress bar): (per-shard statistics,
    phase -> seconds summed over the tasks, level-1 shards the tasks wrote)."""
    stats: list[dict] = []
    phases: dict = {}
    done1: set = set()
    jobs = []
    for key in sorted(blocks):
        bs = blocks[key]
        jobs.append((bs, np.unique(np.concatenate([frame_lists[ij] for ij in bs]))))
    # The blocks with the most frames first, so that the last to end are small ones: dask
    # runs independent tasks in descending order of their keys (dask 2026.8), so each key
    # carries its rank by frames (and a token: keys are unique on a shared cluster).
    rank = np.argsort(np.argsort([len(f) for _, f in jobs], kind="stable"), kind="stable")
    token = uuid.uuid4().hex[:12]
    tasks = [dask.delayed(_level0_task)(work, bs, frames, [len(frame_lists[ij]) for ij in bs],
                                        dask_key_name=f"_level0_task-{int(r):05d}-{token}")
             for (bs, frames), r in zip(jobs, rank)]
    # All in one go, the bar moved as each task ends: batches for the bar were barriers
    # where a worker idled while a batch's last task ran (2 workers: 1.49x one, 2026-12-03).
    with counter(len(tasks), label="render", unit="blocks", quiet=quiet) as bar:
        parts = run(tasks, done=bar.advance)
    for part in parts:
        stats.extend(part["stats"])
        done1.update(tuple(t) for t in part["level1"])
        for name, sec in part["phases"].items():
            phases[name] = phases.get(name, 0.0) + sec
    return stats, phases, done1


def _render_pyramid(run, work: dict, plan: _RenderPlan, levels: int, touched: dict, done1: set, per: int) -> None:
    """Reduce levels 1 .. ``levels - 1`` over the touched shards (``touched``: level ->
    shards, level 0 given; filled in), ``per`` shards per task; level-1 shards in ``done1``
    were written by the level-0 tasks."""
    grid, spec, base_info = plan.grid, plan.spec, plan.base_info
    for level in range(1, levels):
        up = sorted({(i // 2, j // 2) for i, j in touched[level - 1]})
        if base_info is not None and level >= base_info.levels:
            # a level the published map did not have (the map grew): all of it
            lh, lw = grid.level(level).shape
            up = [(i, j) for i in range(-(-lh // spec.shard_px)) for j in range(-(-lw // spec.shard_px))]
        touched[level] = up
        todo = [ij for ij in up if level != 1 or ij not in done1]
        below = [list(t) for t in touched[level - 1]]
        run([dask.delayed(_pyramid_task)(work, level, todo[i : i + per], below) for i in range(0, len(todo), per)])


def _clear_caches() -> None:
    """Drop the per-thread workspaces and the cached frames: not needed after the render."""
    _WORKSPACES.clear()
    release_scratch()  # the layers' per-thread buffers
    _frame_blocks.cache_clear()  # the cached frames are not needed after the render


def _report(plan: _RenderPlan, *, shards: list, levels: int, stats: list[dict], used: np.ndarray,
            decimated: np.ndarray, select_seconds: float, tasks: int, side: int, log_gains: np.ndarray,
            seconds: float, cpu_seconds: float, level0_seconds: float, phases: dict, t0: float, scheduler: str,
            workers: int) -> dict:
    """The stage's report (``seconds``: wall time of the level-0 tasks and the pyramid;
    ``t0``: ``time.perf_counter()`` at the stage's start)."""
    grid, footprints, keep, version = plan.grid, plan.footprints, plan.keep, plan.version
    mpix = sum(s["pixels"] for s in stats) / 1e6
    covered = sum(s["covered"] for s in stats)
    return {
        "render": {
            "shards": len(shards),
            "levels": levels,
            "grid_px": list(grid.shape),
            "level0_mpix": mpix,
            "covered_mpix": covered / 1e6,
            "frames_used": int(used.sum()),
            "frames_dropped": int((~keep).sum()),
            # the kept frames' footprints (metres, xmin ymin xmax ymax): the publish gate's extent
            "extent_m": [float(footprints[:, 0].min()), float(footprints[:, 1].min()),
                         float(footprints[:, 2].max()), float(footprints[:, 3].max())],
            "frames_decimated": int(decimated.sum()),
            "select_seconds": select_seconds,
            "tasks": tasks,
            "block_side": side,
            "frames_per_shard_mean": float(np.mean([s["frames"] for s in stats])) if stats else 0.0,
            "gain_min": float(np.exp(log_gains.min())) if len(log_gains) else 1.0,
            "gain_max": float(np.exp(log_gains.max())) if len(log_gains) else 1.0,
            "seconds": seconds,
            "mpix_per_s": mpix / seconds if seconds > 0 else 0.0,
            # CPU seconds of this process (all its threads) and of its worker processes
            # (a dask.distributed cluster's workers are not counted)
            "cpu_seconds": cpu_seconds,
            "scheduler": scheduler,
            "workers": workers,
            "mpix_per_cpu_s": mpix / cpu_seconds if cpu_seconds > 0 else 0.0,
            "level0_seconds": level0_seconds,
            "pyramid_seconds": seconds - level0_seconds,
            # summed over the level-0 tasks (wall seconds inside the tasks, all workers)
            "phase_seconds": phases,
            "stage_seconds": time.perf_counter() - t0,
            "version": version,
        }
    }


def render_plan(rcfg: dict, grid: MapGrid) -> tuple[str, int]:
    """Where the render runs: ``(scheduler, workers)`` from ``[render] scheduler`` and
    ``workers`` (0 = one per core).

    ``auto``: on spawned worker processes, one per core, when the level-0 grid holds
    ``processes_min_mpix`` MPix or more (no interpreter shared: on the 40 x 40 m benchmark,
    2 processes rendered 1.75x faster than one and 1.24x faster than 2 threads, whose frame
    reads and Python between the OpenCV calls wait for each other), else on threads (a
    small map is done before processes would have started). Other schedulers as named."""
    cores = os.cpu_count() or 1
    workers = int(rcfg["workers"]) or cores
    sched = rcfg["scheduler"]
    if sched != "auto":
        return sched, workers
    if workers > 1 and grid.height * grid.width >= rcfg["processes_min_mpix"] * 1e6:
        return "processes", workers
    return "threads", workers


def run_render(ws: Workspace, params: StageParams) -> dict:
    """Stage entry: render this build's frames into ``ws.render_store`` (see the module docstring).

    ``base`` (``params.build.base``): ``{"url", "snapshot", "version"}`` of the published map
    to extend, or None.
    """
    t0 = time.perf_counter()
    cfg, base, quiet = params.cfg, params.build.base, params.quiet
    rcfg = cfg["render"]
    plan = _plan(ws, cfg, base)
    scheduler, workers = render_plan(rcfg, plan.grid)
    # (worker processes start, and import this module, while the tasks are prepared)
    with dask_scheduler(scheduler, workers, warm=(__name__,)) as run:
        grid, spec, version = plan.grid, plan.spec, plan.version
        log_gains = _write_gains(ws, plan, rcfg)
        staging_path = _create_staging(ws, plan)
        work_params = _work_params(rcfg)
        decimated, used, select_seconds = _select(plan, rcfg)
        shards, frame_lists = _assign_shards(plan, used, work_params)
        levels = levels_for(grid, spec.chunk_px)
        side, blocks = _task_blocks(shards, rcfg)
        work = {
            "grid": grid.to_attrs(), "spec": spec.to_attrs(), "staging": str(staging_path),
            "store": str(plan.store_path), "base": base, "poses": plan.poses, "log_gains": log_gains,
            "pixel_size": plan.px, "version": version, "scales": plan.scales, "params": work_params,
            "block_side": side, "levels": levels,
        }
        touched = {0: shards}
        t_render = time.perf_counter()
        cpu0 = process_cpu_seconds()  # (the pool's workers count once it closes: reaped)
        huge = _small_pages()
        try:
            stats, phases, done1 = _render_level0(run, work, blocks, frame_lists, quiet)
            level0_seconds = time.perf_counter() - t_render
            _render_pyramid(run, work, plan, levels, touched, done1, side * side)
        finally:
            _small_pages(huge)  # the rest of the build as it was
    _clear_caches()
    seconds = time.perf_counter() - t_render
    cpu_seconds = process_cpu_seconds() - cpu0
    _write_touched(ws, plan, levels, base, touched)
    return _report(plan, shards=shards, levels=levels, stats=stats, used=used, decimated=decimated,
                   select_seconds=select_seconds, tasks=len(blocks), side=side, log_gains=log_gains, seconds=seconds,
                   cpu_seconds=cpu_seconds, level0_seconds=level0_seconds, phases=phases, t0=t0,
                   scheduler=scheduler, workers=workers)


STAGE = Stage("render", run_render, params_tables=("map", "render"), reads_base=True, needs_map=True, gated=True)
