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
