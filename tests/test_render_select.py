"""pipeline.render_select: the frames the render keeps still cover every pixel."""

from __future__ import annotations

import cv2
import numpy as np

from mapstore.grid import MapGrid
from pipeline.mosaic import accumulate_frame, feather_weight, interpolation_margin_px
from pipeline.render_select import select_frames

PIXEL_M = 0.0025
FRAME = (60, 80)


def lawnmower(step_m: float, lane_m: float, lanes: int, per_lane: int) -> np.ndarray:
    rows = []
    for j in range(lanes):
        xs = 0.15 + step_m * np.arange(per_lane)
        rows += [(x, 0.1 + lane_m * j, 0.0 if j % 2 == 0 else np.pi) for x in (xs if j % 2 == 0 else xs[::-1])]
    return np.array(rows)


def support(grid: MapGrid, poses: np.ndarray, weight: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(weight sum, full-weight views) per grid pixel of the kept frames."""
    acc, wacc = np.zeros(grid.shape, np.float32), np.zeros(grid.shape, np.float32)
    count = np.zeros(grid.shape, np.uint16)
    views = np.zeros(grid.shape, np.int32)
    box = (0, grid.height, 0, grid.width)
    for g in np.flatnonzero(keep):
        w0 = wacc.copy()
        accumulate_frame(acc, wacc, count, box, grid, np.ones(FRAME, np.float32), weight, poses[g], PIXEL_M, 1.0,
                         cv2.INTER_CUBIC)
        views += (wacc - w0) > 0.999
    return wacc, views


def test_selection_keeps_the_covered_pixels_and_the_depth():
    poses = lawnmower(0.03, 0.09, 4, 14)
    grid = MapGrid.covering(-0.05, -0.1, 0.65, 0.55, PIXEL_M)
    weight = feather_weight(np.ones(FRAME, bool), 6.0, interpolation_margin_px(cv2.INTER_CUBIC))
    n = len(poses)
    cand = np.ones(n, bool)
    cand[5] = False  # not a candidate: never selected
    every_w, every_views = support(grid, poses, weight, cand)
    for depth in (1, 2):
        keep = select_frames(grid, poses, [FRAME], np.zeros(n, int), [weight], np.full(n, PIXEL_M), cand, depth, 8)
        assert not keep[5] and keep.sum() < cand.sum(), (depth, keep.sum(), cand.sum())
        w, views = support(grid, poses, weight, keep)
        # exactly the pixels every candidate covers
        assert np.array_equal(w > 0, every_w > 0), depth
        # where candidates see a pixel with full weight `depth` times, so do the kept frames
        # (but for the cell discretisation at the edges of those regions)
        want = every_views >= depth + 1
        assert np.mean(views[want] >= depth) > 0.97, (depth, np.mean(views[want] >= depth))
    keep1 = select_frames(grid, poses, [FRAME], np.zeros(n, int), [weight], np.full(n, PIXEL_M), cand, 1, 8)
    keep2 = select_frames(grid, poses, [FRAME], np.zeros(n, int), [weight], np.full(n, PIXEL_M), cand, 2, 8)
    assert keep1.sum() < keep2.sum()
    assert np.array_equal(select_frames(grid, poses, [FRAME], np.zeros(n, int), [weight], np.full(n, PIXEL_M), cand,
                                        0, 8), cand)
    # deterministic
    again = select_frames(grid, poses, [FRAME], np.zeros(n, int), [weight], np.full(n, PIXEL_M), cand, 2, 8)
    assert np.array_equal(again, keep2)


def _cells_one_frame(grid, cell_px, pose, shape, fpx, masks, radius_px, ncells):
    """The cells of one frame, the plain way (one frame at a time: the batched
    _cells_of_frames must give exactly these)."""
    import math

    full, support_, reach_dist = masks
    f2g = grid.frame_to_grid_affine(pose, shape, fpx)
    h, w = shape
    nr, nc = ncells
    corners = f2g @ np.array([[-2, w + 1, w + 1, -2], [-2, -2, h + 1, h + 1], [1, 1, 1, 1]], float)
    pad = radius_px * (grid.pixel_size / fpx) + 2
    i0 = max(int(math.floor((corners[1].min() - pad) / cell_px)), 0)
    i1 = min(int(math.floor((corners[1].max() + pad) / cell_px)) + 1, nr)
    j0 = max(int(math.floor((corners[0].min() - pad) / cell_px)), 0)
    j1 = min(int(math.floor((corners[0].max() + pad) / cell_px)) + 1, nc)
    if i1 <= i0 or j1 <= j0:
        return [np.zeros(0, np.int64)] * 3
    ii, jj = np.mgrid[i0:i1, j0:j1]
    gr, gc = ii * cell_px + 0.5 * (cell_px - 1), jj * cell_px + 0.5 * (cell_px - 1)
    g2f = cv2.invertAffineTransform(f2g)
    fc = g2f[0, 0] * gc + g2f[0, 1] * gr + g2f[0, 2]
    fr = g2f[1, 0] * gc + g2f[1, 1] * gr + g2f[1, 2]
    c, r = np.rint(fc).astype(np.int64), np.rint(fr).astype(np.int64)
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    rc, cc = np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)
    outside_d = np.hypot(fc - np.clip(fc, 0, w - 1), fr - np.clip(fr, 0, h - 1))
    reach = reach_dist[rc, cc] + outside_d <= radius_px + 2.0 + math.sqrt(2.0)
    flat = ii * nc + jj
    return [flat[inside & full[rc, cc]], flat[inside & support_[rc, cc]], flat[reach]]


def test_batched_cells_match_one_frame_at_a_time():
    """Frames at any heading, scale and place (off the grid's edges too) get, batched, the
    very cells of one frame at a time, in the same order."""
    from pipeline.render_select import _cells_of_frames, frame_cell_masks

    rng = np.random.default_rng(3)
    grid = MapGrid.covering(0.0, 0.0, 0.6, 0.5, PIXEL_M)
    weight = feather_weight(np.ones(FRAME, bool), 6.0, interpolation_margin_px(cv2.INTER_CUBIC))
    n = 40
    poses = np.column_stack([rng.uniform(-0.2, 0.8, n), rng.uniform(-0.2, 0.7, n), rng.uniform(-np.pi, np.pi, n)])
    poses[0] = (5.0, 5.0, 0.0)  # far off the grid: no cells
    fpx = PIXEL_M * rng.uniform(0.8, 1.25, n)
    cell_px = 8
    ncells = (-(-grid.height // cell_px), -(-grid.width // cell_px))
    radius = 0.5 * np.sqrt(2.0) * cell_px * grid.pixel_size / fpx
    masks = frame_cell_masks(weight, float(radius[1]))
    got = _cells_of_frames(grid, cell_px, poses, FRAME, fpx, masks, radius, ncells)
    assert len(got) == n and all(len(c) == 0 for c in got[0])
    for g in range(n):
        want = _cells_one_frame(grid, cell_px, poses[g], FRAME, float(fpx[g]), masks, float(radius[g]), ncells)
        for a, b in zip(got[g], want):
            assert a.dtype == np.int32
            np.testing.assert_array_equal(a, b)
    assert sum(len(c[2]) for c in got) > 0


def test_selection_does_not_depend_on_the_batches(monkeypatch):
    """Batches of one frame (as large frames over small cells get) choose the same frames."""
    import pipeline.render_select as rs

    poses = lawnmower(0.03, 0.09, 4, 14)
    grid = MapGrid.covering(-0.05, -0.1, 0.65, 0.55, PIXEL_M)
    weight = feather_weight(np.ones(FRAME, bool), 6.0, interpolation_margin_px(cv2.INTER_CUBIC))
    n = len(poses)
    args = (grid, poses, [FRAME], np.zeros(n, int), [weight], np.full(n, PIXEL_M), np.ones(n, bool), 2, 8)
    whole = select_frames(*args)
    monkeypatch.setattr(rs, "_BATCH_CELLS", 1)
    assert np.array_equal(select_frames(*args), whole)
