"""Which frames the render warps: a minimal subset that still sees every cell ``depth`` times.

A drive's consecutive frames overlap far more than blending needs. After the render's
decimation along each log (:func:`pipeline.stages.render.decimate_frames`), this chooses, over the
whole map at once, a subset of the remaining frames such that every selection cell (a
square of ``cell_px`` level-0 pixels) that at least one candidate sees with its full blend
weight is seen with full weight by at least ``min(depth, candidates that do)`` selected
frames, by greedy set cover (the frame adding the most missing cell-views first, ties to
the lower frame index: deterministic). The choice is made once per build for the whole map,
not per shard, so that neighbouring shards (and the halos the layers read) blend the same
frames and no seam appears at shard borders.

The covered area is kept exactly, in two more steps: a second greedy pass covers, ``depth``
times where candidates allow, the cells seen only through nonzero (feathered) weight (gaps
between lanes); then a cell that some candidate's weight reaches but that no candidate holds
wholly inside its nonzero weight (the coverage's outer edge) keeps every candidate reaching
it. The tests are exact at the cell scale without assuming convex footprints: a frame
covers a cell with full weight when the cell's centre lies in the frame's full-weight (or
nonzero-weight) region eroded by half the cell's diagonal (+2.5 px), and reaches it when the
centre lies within the weight's support dilated by as much (frame pixels, each test a
nearest-pixel lookup of a precomputed mask per log).

Everything in level-0 grid pixels and frame pixels; transforms from :mod:`mapstore.grid`.
"""

from __future__ import annotations

import heapq
import math

import cv2
import numpy as np

from mapstore.grid import MapGrid

__all__ = ["frame_cell_masks", "select_frames"]


def frame_cell_masks(weight: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(full, inside, reach_dist) of a frame's pixels, ``weight``'s shape.

    ``full`` (bool): pixels more than ``radius_px`` + 2.5 (frame pixels) from any pixel
    whose weight is below 1 or from the image border (a cell whose centre rounds to such a
    pixel lies, with the bilinear support of its pixels, inside the full-weight region);
    ``inside`` (bool): the same for the nonzero weight; ``reach_dist`` (float32): distance
    from each pixel to the nearest pixel of nonzero weight (0 on them; inf when the weight
    is 0 everywhere).
    """
    def interior(mask: np.ndarray) -> np.ndarray:
        m = cv2.copyMakeBorder(mask.astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
        return cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1] > radius_px + 2.5

    zero = (weight <= 0).astype(np.uint8)
    if zero.all():
        none = np.zeros(weight.shape, bool)
        return none, none, np.full(weight.shape, np.inf, np.float32)
    reach_dist = cv2.distanceTransform(zero, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) if zero.any() \
        else np.zeros(weight.shape, np.float32)
    return interior(weight >= 1.0), interior(weight > 0), reach_dist


def _cells_of_frames(grid: MapGrid, cell_px: int, poses: np.ndarray, shape: tuple[int, int], fpx: np.ndarray,
                     masks: tuple, radius_px: np.ndarray, ncells: tuple[int, int]) -> list[tuple[np.ndarray, ...]]:
    """For each of a batch of frames of one log sharing ``masks`` (``poses`` (B, 3), ``fpx``
    (B,) metres per frame pixel, ``radius_px`` (B,) half a cell's diagonal in its frame
    pixels, as the masks were made for): the flat indices of the selection cells it covers with full
    weight, with nonzero weight, and that its weight reaches (``masks``:
    :func:`frame_cell_masks`), row-major; int32 (int64 on a grid of 2^31 cells or more).

    Vectorized over the batch: each frame's box of candidate cells is padded to the
    batch's largest and the padding masked out (one pass of array operations for all the
    frames instead of one per frame)."""
    full, support, reach_dist = masks
    h, w = shape
    nr, nc = ncells
    idx = np.int32 if nr * nc < 2**31 else np.int64
    n = len(poses)
    f2g = np.stack([grid.frame_to_grid_affine(p, shape, float(f)) for p, f in zip(poses, fpx)]) if n \
        else np.zeros((0, 2, 3))
    g2f = np.stack([cv2.invertAffineTransform(m) for m in f2g]) if n else np.zeros((0, 2, 3))
    corners = f2g @ np.array([[-2, w + 1, w + 1, -2], [-2, -2, h + 1, h + 1], [1, 1, 1, 1]], float)  # (B, 2, 4)
    radius_px = np.asarray(radius_px, float)
    pad = radius_px * (grid.pixel_size / np.asarray(fpx, float)) + 2  # frame px -> grid px, generously
    i0 = np.maximum(np.floor((corners[:, 1].min(axis=1) - pad) / cell_px).astype(np.int64), 0)
    i1 = np.minimum(np.floor((corners[:, 1].max(axis=1) + pad) / cell_px).astype(np.int64) + 1, nr)
    j0 = np.maximum(np.floor((corners[:, 0].min(axis=1) - pad) / cell_px).astype(np.int64), 0)
    j1 = np.minimum(np.floor((corners[:, 0].max(axis=1) + pad) / cell_px).astype(np.int64) + 1, nc)
    hb, wb = np.maximum(i1 - i0, 0), np.maximum(j1 - j0, 0)
    if not n or not (hb * wb).any():
        e = np.zeros(0, idx)
        return [(e, e, e) for _ in range(n)]
    ii = i0[:, None, None] + np.arange(int(hb.max()))[None, :, None]  # (B, H, 1)
    jj = j0[:, None, None] + np.arange(int(wb.max()))[None, None, :]  # (B, 1, W)
    in_box = (ii < i1[:, None, None]) & (jj < j1[:, None, None])
    # cell centres in grid pixels (cell (i, j) spans rows i*cell_px .. (i+1)*cell_px - 1)
    gr = ii * cell_px + 0.5 * (cell_px - 1)
    gc = jj * cell_px + 0.5 * (cell_px - 1)
    a = g2f[:, :, :, None, None]  # (B, 2, 3, 1, 1)
    fc = a[:, 0, 0] * gc + a[:, 0, 1] * gr + a[:, 0, 2]
    fr = a[:, 1, 0] * gc + a[:, 1, 1] * gr + a[:, 1, 2]
    c = np.rint(fc).astype(np.int64)
    r = np.rint(fr).astype(np.int64)
    inside = in_box & (r >= 0) & (r < h) & (c >= 0) & (c < w)
    rc, cc = np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)
    is_full = inside & full[rc, cc]
    is_in = inside & support[rc, cc]
    # reach: distance (frame px) from the centre to the weight's support <= radius + 1.5,
    # outside the frame measured to the nearest frame pixel plus the distance to it.
    outside_d = np.hypot(fc - np.clip(fc, 0, w - 1), fr - np.clip(fr, 0, h - 1))
    # generous: a bilinear weight reaches 1 px beyond its support, the lookup rounds by <= 0.71 px
    is_reach = in_box & (reach_dist[rc, cc] + outside_d <= (radius_px + 2.0 + math.sqrt(2.0))[:, None, None])
    flat = (ii * nc + jj).astype(idx)
    # int32 where the grid allows (every candidate's three lists are held at once: ~30 KB
    # per frame in int64, 380 MB of a 40 x 40 m floor's render)
    out = []
    for m in (is_full, is_in, is_reach):
        counts = m.reshape(n, -1).sum(axis=1)
        out.append(np.split(np.broadcast_to(flat, m.shape)[m], np.cumsum(counts)[:-1]))
    return list(zip(*out))


# Frames per batch of :func:`_cells_of_frames`: at most this many, and at most about
# _BATCH_CELLS candidate cells in all (each array of the batch's temporaries ~8 bytes a cell:
# ~40 x 60 cells a frame on the render benchmarks, 128 frames ~2.5 MB; large aerial frames
# over small cells get smaller batches)
_BATCH_FRAMES = 128
_BATCH_CELLS = 400_000


def select_frames(grid: MapGrid, poses: np.ndarray, frame_shape_of: list[tuple[int, int]], log_of: np.ndarray,
                  weights: list[np.ndarray], frame_pixel_size: np.ndarray, candidates: np.ndarray,
                  depth: int, cell_px: int) -> np.ndarray:
    """(N,) bool: the frames to render, a subset of ``candidates`` (see the module docstring).

    Args:
        grid: the level-0 map grid.
        poses: (N, 3) optimized poses ``x, y, theta`` (metres, radians, world frame).
        frame_shape_of: ``(H, W)`` of each log's rectified frames (pixels).
        log_of: (N,) log index of each frame.
        weights: each log's blend weight (:func:`pipeline.mosaic.feather_weight`), float32.
        frame_pixel_size: (N,) metres per frame pixel (nominal x scale for similarity poses).
        candidates: (N,) bool, the frames the decimation kept.
        depth: full-weight views wanted per cell; 0 keeps every candidate.
        cell_px: selection cell side (level-0 pixels).
    """
    candidates = np.asarray(candidates, bool)
    if depth <= 0 or not candidates.any():
        return candidates.copy()
    nr, nc = -(-grid.height // cell_px), -(-grid.width // cell_px)
    ncell = nr * nc
    # Half the cell's diagonal in frame pixels (the largest frame pixel: the smallest scale).
    radius_grid = 0.5 * math.sqrt(2.0) * cell_px
    masks: dict = {}
    groups: dict = {}  # (log, radius) -> its frames, in order
    for g in np.flatnonzero(candidates).tolist():
        k = int(log_of[g])
        radius = radius_grid * grid.pixel_size / float(frame_pixel_size[g])
        key = (k, round(radius, 3))
        if key not in masks:
            masks[key] = frame_cell_masks(weights[k], radius)
        groups.setdefault(key, []).append((g, radius))
    found: dict = {}
    for key, members in groups.items():
        h, w = frame_shape_of[key[0]]
        fpx_max = max(float(frame_pixel_size[g]) for g, _ in members)
        side = math.hypot(h, w) * fpx_max / grid.pixel_size / cell_px + 4  # a frame box's cells per side, padded
        per = max(1, min(_BATCH_FRAMES, int(_BATCH_CELLS // (side * side))))
        for b in range(0, len(members), per):
            batch = members[b : b + per]
            gs = np.array([g for g, _ in batch])
            cells = _cells_of_frames(grid, cell_px, poses[gs], frame_shape_of[key[0]], frame_pixel_size[gs],
                                     masks[key], np.array([r for _, r in batch]), (nr, nc))
            found.update(zip(gs.tolist(), cells))
    full_cells = {g: c[0] for g, c in found.items()}
    in_cells = {g: c[1] for g, c in found.items()}
    reach_cells = {g: c[2] for g, c in found.items()}
    chosen = np.zeros(len(candidates), bool)
    # First every cell seen with full weight `depth` times where candidates allow, then
    # with nonzero weight (gaps between lanes seen only through feathered edges).
    for cells_of in (full_cells, in_cells):
        avail = _views(cells_of.values(), ncell)
        have = _views([c for g, c in cells_of.items() if chosen[g]], ncell)
        _greedy_cover(cells_of, np.minimum(avail, depth), have, chosen)
    # Cells some weight reaches but none covers wholly (the coverage's outer edge): every
    # frame reaching them stays, so that the covered pixels are exactly those of all candidates.
    reached = _views(reach_cells.values(), ncell) > 0
    edge = reached & (avail == 0)
    for g, cells in reach_cells.items():
        if not chosen[g] and edge[cells].any():
            chosen[g] = True
    return chosen


def _views(cell_lists, ncell: int) -> np.ndarray:
    """(ncell,) int32: in how many of the lists (flat cell indices, each cell at most once
    per list) each cell appears."""
    lists = [c for c in cell_lists if len(c)]
    if not lists:
        return np.zeros(ncell, np.int32)
    return np.bincount(np.concatenate(lists), minlength=ncell).astype(np.int32)


def _greedy_cover(cells_of: dict, need: np.ndarray, have: np.ndarray, chosen: np.ndarray) -> None:
    """Lazy greedy set cover, in place: add to ``chosen`` the frame whose cells (flat
    indices, ``cells_of[g]``) have the most ``have < need``, until none has any; ties go to
    the lower frame index."""
    heap = [(-len(c), g) for g, c in cells_of.items() if len(c) and not chosen[g]]
    heapq.heapify(heap)
    while heap:
        _, g = heapq.heappop(heap)
        cells = cells_of[g]
        gain = int(np.count_nonzero(have[cells] < need[cells]))
        if gain == 0:
            continue
        if heap and gain < -heap[0][0]:
            heapq.heappush(heap, (-gain, g))  # stale: re-queue with its current gain
            continue
        chosen[g] = True
        have[cells] += 1
