"""The seam composite (pipeline.seams): ownership, partition of unity, weak cells, upsampling,
and a block rendered with it against the weighted blend and the world."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mapstore.grid import MapGrid
from pipeline.mosaic import accumulate_frame, edge_distance, feather_weight, finish, frame_boxes, weight_ones_box
from pipeline.seams import (
    CellLattice,
    FrameCells,
    block_seams,
    frame_cells,
    pixel_weights,
    seam_cell_weights,
    seam_radius_cells,
)

CELL = 16


def test_lattice_cells_are_aligned_on_the_grid_and_cover_a_box():
    lat = CellLattice.around((-20, 100, 40, 75), CELL, 2)
    # rows -20..99 -> grid cells -2..6 (+-2): -4..8; cols 40..74 -> cells 2..4 (+-2): 0..6
    assert (lat.i0, lat.j0, lat.rows, lat.cols) == (-4, 0, 13, 7)
    assert lat.pixel_box((0, 1, 0, 1)) == (-64, -48, 0, 16)
    assert lat.cells_over((-64, -47, 0, 16)) == (0, 2, 0, 1)
    assert lat.cells_over((10_000, 10_100, 0, 16)) is None
    assert seam_radius_cells(24.0, 16) == 1 and seam_radius_cells(0.0, 16) == 1 and seam_radius_cells(70.0, 16) == 3


def _two_frames(d_left: np.ndarray, d_right: np.ndarray):
    lat = CellLattice(0, 0, d_left.shape[0], d_left.shape[1], CELL)
    cells = (0, lat.rows, 0, lat.cols)
    return lat, [FrameCells(cells, d_left.astype(np.float32)), FrameCells(cells, d_right.astype(np.float32))]


def test_the_deepest_frame_owns_a_cell_and_the_weights_sum_to_one():
    # two frames over 6 x 12 cells: depth falls left to right for the first, rises for the second
    cols = np.arange(12, dtype=float)
    d0 = np.tile(400.0 - 30 * cols, (6, 1))
    d1 = np.tile(70.0 + 30 * cols, (6, 1))
    lat, views = _two_frames(d0, d1)
    out, seen = seam_cell_weights(lat, views, np.array([0.0025, 0.0025]), np.array([40.0, 40.0]), 1)
    w0, w1 = out[0][1], out[1][1]
    np.testing.assert_allclose(w0 + w1, 1.0, atol=1e-6)  # a partition of unity on strong cells
    # frame 0 deeper up to column 5 (400 - 150 = 250 > 220), frame 1 from column 6
    assert (w0[:, :5] == 1).all() and (w1[:, 7:] == 1).all()
    np.testing.assert_allclose(w0[0, 4:8], [1.0, 2 / 3, 1 / 3, 0.0], atol=1e-6)
    assert (seen == 2).all()


def test_a_tie_goes_to_the_earlier_frame_and_metres_decide_between_scales():
    d = np.full((3, 3), 200.0)
    lat, views = _two_frames(d, d)
    out, _ = seam_cell_weights(lat, views, np.array([0.0025, 0.0025]), np.array([40.0, 40.0]), 1)
    assert (out[0][1] == 1).all() and out[1] is None  # frame 1 contributes nothing: not read
    # the same depth in pixels, but frame 1's pixels are larger: it sees deeper in metres
    out, _ = seam_cell_weights(lat, views, np.array([0.0025, 0.003]), np.array([40.0, 40.0]), 1)
    assert out[0] is None and (out[1][1] == 1).all()


def test_cells_no_frame_holds_with_full_weight_keep_every_frame_feathered():
    # depths below the full threshold everywhere: every cell weak, both frames weight 1
    d0 = np.full((4, 4), 20.0)
    d1 = np.full((4, 4), 30.0)
    lat, views = _two_frames(d0, d1)
    out, seen = seam_cell_weights(lat, views, np.array([0.0025, 0.0025]), np.array([40.0, 40.0]), 1)
    assert (out[0][1] == 1).all() and (out[1][1] == 1).all() and (seen == 2).all()
    # outside a frame (depth -inf): not seen there
    d0[:, :2] = -np.inf
    lat, views = _two_frames(d0, d1)
    _, seen = seam_cell_weights(lat, views, np.array([0.0025, 0.0025]), np.array([40.0, 40.0]), 1)
    assert (seen[:, :2] == 1).all() and (seen[:, 2:] == 2).all()


def test_pixel_weights_interpolate_between_cell_centres_and_are_cut_to_their_support():
    lat = CellLattice(0, 0, 5, 6, CELL)
    w = np.zeros((5, 6), np.float32)
    w[2, 2:4] = 1.0
    box, px = pixel_weights(lat, (0, 5, 0, 6), w, (-1000, 1000, -1000, 1000))
    full = cv2.resize(w, (6 * CELL, 5 * CELL), interpolation=cv2.INTER_LINEAR)
    r0, r1, c0, c1 = box
    np.testing.assert_array_equal(px, full[r0:r1, c0:c1])
    outside = full.copy()
    outside[r0:r1, c0:c1] = 0
    assert not outside.any()  # nothing nonzero left out
    assert (px > 0).any(axis=1).all() and (px > 0).any(axis=0).all()  # no zero row or column kept
    c = CELL // 2  # centre pixel (rounded down) of a cell
    assert full[2 * CELL + c, 2 * CELL + c] == pytest.approx(1.0, abs=0.04)
    # cut to a box
    box2, px2 = pixel_weights(lat, (0, 5, 0, 6), w, (0, 40, 0, 50))
    assert box2 == (max(r0, 0), min(r1, 40), max(c0, 0), min(c1, 50))
    assert pixel_weights(lat, (0, 5, 0, 6), np.zeros((5, 6), np.float32), (0, 80, 0, 96)) is None


def _world(size: int, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(cv2.GaussianBlur(rng.normal(128, 60, (size, size)).astype(np.float32), (0, 0), 2.0), 1, 255)


def _render_block(composite: str, grid: MapGrid, world: np.ndarray, poses: np.ndarray, shape, feather: float,
                  frames_per_cell: int = 1):
    """The block over the whole grid, each frame sampled from the world at its pose."""
    h, w = shape
    valid = np.ones(shape, bool)
    weight = feather_weight(valid, feather, 2.0)
    ones = weight_ones_box(weight)
    edge = edge_distance(valid, 2.0)
    box = (0, grid.height, 0, grid.width)
    acc = np.zeros(grid.shape, np.float32)
    wacc = np.zeros(grid.shape, np.float32)
    count = np.zeros(grid.shape, np.uint16)
    regions = [None] * len(poses)
    seen = None
    if composite == "seams":
        lattice, cells, seen = block_seams(grid, box, CELL, poses, [edge] * len(poses),
                                           np.full(len(poses), grid.pixel_size), feather, frames_per_cell)
        regions = [None if c is None else pixel_weights(lattice, *c, box) for c in cells]
    for n, pose in enumerate(poses):
        f2g = grid.frame_to_grid_affine(pose, shape, grid.pixel_size)
        image = cv2.warpAffine(world, f2g, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        if composite == "seams" and regions[n] is None:
            continue
        accumulate_frame(acc, wacc, count, box, grid, image, weight, pose, grid.pixel_size, 1.0, cv2.INTER_CUBIC,
                         weight_ones=ones, region=regions[n])
    return finish(acc, wacc), wacc, seen


@pytest.mark.parametrize("frames_per_cell", [1, 2])
def test_a_block_rendered_with_seams_covers_what_the_blend_covers_and_matches_the_world(frames_per_cell):
    px = 0.0025
    grid = MapGrid(0.0, 1.0, px, 400, 400)
    world = _world(400)
    shape = (160, 240)
    rng = np.random.default_rng(1)
    # a lawnmower of four lanes 0.15 m apart, frames 0.1 m apart, poses jittered and turned
    poses = np.array([[x + rng.normal(0, 0.003), y + rng.normal(0, 0.003), rng.normal(0, 0.03)]
                      for y in (0.75, 0.6, 0.45, 0.3) for x in np.arange(0.35, 0.66, 0.1)])
    seams, wsum, seen = _render_block("seams", grid, world, poses, shape, 24.0, frames_per_cell)
    blend, _, _ = _render_block("blend", grid, world, poses, shape, 24.0)
    np.testing.assert_array_equal(seams > 0, blend > 0)  # the same pixels covered
    covered = blend > 0
    inner = cv2.erode(covered.astype(np.uint8), np.ones((41, 41), np.uint8)) > 0
    truth = np.clip(np.rint(world), 1, 255)
    err = np.abs(seams[inner].astype(float) - truth[inner])
    assert err.mean() < 1.0 and np.corrcoef(seams[inner], truth[inner])[0, 1] > 0.995
    # away from the coverage's edge (where no frame holds a whole cell with full weight and
    # every frame keeps its feathered weight) each pixel is drawn from one frame or a seam
    # between a few: the weights sum to 1 there (a partition of unity; a little less where a
    # ramp passes into another frame's feather: by < 1 %)
    deep = cv2.erode(covered.astype(np.uint8), np.ones((201, 201), np.uint8)) > 0
    assert deep.sum() > 10_000 and np.allclose(wsum[deep], 1.0, atol=0.01)
    assert (np.abs(wsum[deep] - 1.0) < 1e-3).mean() > 0.95
    assert seen.max() >= 8


def test_frames_reaching_a_cell_only_through_a_neighbour_block_decide_it_alike():
    """Two blocks side by side, each given the frames reaching its lattice: the pixels
    along their border come out the same from both (no seam at block borders)."""
    px = 0.0025
    grid = MapGrid(0.0, 1.0, px, 400, 400)
    world = _world(400, seed=4)
    shape = (120, 160)
    poses = np.array([[x, y, 0.02 * k] for k, (y, x) in enumerate(
        (y, x) for y in (0.75, 0.5, 0.25) for x in np.arange(0.2, 0.85, 0.13))])
    valid = np.ones(shape, bool)
    weight = feather_weight(valid, 24.0, 2.0)
    edge = edge_distance(valid, 2.0)
    radius = seam_radius_cells(24.0, CELL)
    outs = []
    for box in ((0, 400, 0, 208), (0, 400, 192, 400)):  # overlapping by a cell around column 200
        reach = (radius + 2) * CELL
        fb = frame_boxes(grid, poses, shape, px)
        sel = np.flatnonzero((fb[:, 1] > box[0] - reach) & (fb[:, 0] < box[1] + reach)
                             & (fb[:, 3] > box[2] - reach) & (fb[:, 2] < box[3] + reach))
        lattice, cells, _ = block_seams(grid, box, CELL, poses[sel], [edge] * len(sel), np.full(len(sel), px), 24.0)
        shape_b = (box[1] - box[0], box[3] - box[2])
        acc, wacc, cnt = (np.zeros(shape_b, np.float32), np.zeros(shape_b, np.float32), np.zeros(shape_b, np.uint16))
        for n, c in zip(sel, cells):
            if c is None:
                continue
            region = pixel_weights(lattice, *c, box)
            if region is None:
                continue
            f2g = grid.frame_to_grid_affine(poses[n], shape, px)
            image = cv2.warpAffine(world, f2g, (shape[1], shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
            accumulate_frame(acc, wacc, cnt, box, grid, image, weight, poses[n], px, 1.0, cv2.INTER_CUBIC,
                             region=region)
        outs.append((finish(acc, wacc), wacc))
    (left, wl), (right, wr) = outs
    # the same frames with the same weights (another owner would move them by >= 1/9; the
    # feathered ones and the values by OpenCV's 1/32 px sample positions, fixed point
    # relative to each warped box)
    np.testing.assert_allclose(wl[:, 192:208], wr[:, 0:16], atol=5e-3)
    diff = np.abs(left[:, 192:208].astype(int) - right[:, 0:16])
    assert diff.max() <= 1 and (diff == 0).mean() > 0.99


def test_frame_cells_sample_the_edge_distance_at_cell_centres():
    px = 0.0025
    grid = MapGrid(0.0, 1.0, px, 200, 200)
    shape = (64, 96)
    edge = edge_distance(np.ones(shape, bool), 0.0)
    pose = np.array([0.25, 0.75, 0.0])  # frame centre at grid pixel (100, 100) - 0.5
    lat = CellLattice.around((0, 200, 0, 200), CELL, 0)
    box = tuple(int(v) for v in frame_boxes(grid, pose, shape, px)[0])
    fc = frame_cells(lat, grid, box, pose, edge, px)
    i0, i1, j0, j1 = fc.cells
    assert i0 <= 100 // CELL < i1 and j0 <= 100 // CELL < j1
    centre = fc.depth[100 // CELL - i0, 100 // CELL - j0]
    assert centre == pytest.approx(edge.max(), abs=CELL)  # deepest near the frame's centre
    assert np.isneginf(fc.depth).any() and (fc.depth[np.isfinite(fc.depth)] >= -1.0).all()
    assert math.isfinite(float(centre))


def test_two_frames_per_cell_share_it_equally_where_both_hold_it_whole():
    cols = np.arange(8, dtype=float)
    d = [np.tile(300.0 - 20 * cols, (4, 1)), np.tile(100.0 + 20 * cols, (4, 1)), np.full((4, 8), 150.0)]
    lat = CellLattice(0, 0, 4, 8, CELL)
    views = [FrameCells((0, 4, 0, 8), x.astype(np.float32)) for x in d]
    px = np.full(3, 0.0025)
    full = np.array([40.0, 40.0, 160.0])  # frame 2 never holds a cell whole
    out, _ = seam_cell_weights(lat, views, px, full, 1, frames_per_cell=2)
    total = sum(o[1] for o in out if o is not None)
    np.testing.assert_allclose(total, 1.0, atol=1e-6)
    # columns 0-2: frames 0 (300..260) and 2 (150, not whole) deepest: frame 0 alone; from
    # column 3 frames 0 and 1 both whole: half each (column 4: the box mean of equal shares)
    w0, w1 = out[0][1], out[1][1]
    assert w0[1, 0] == pytest.approx(1.0) and w1[1, 0] == pytest.approx(0.0)
    assert w0[1, 3] == pytest.approx(2 / 3) and w1[1, 3] == pytest.approx(1 / 3)
    assert w0[1, 4] == pytest.approx(0.5) and w1[1, 4] == pytest.approx(0.5)
    assert out[2] is None  # never among the owners of a cell it holds whole: not read
    # one frame per cell: the deepest alone
    out1, _ = seam_cell_weights(lat, views, px, full, 1, frames_per_cell=1)
    assert out1[0][1][1, 4] == pytest.approx(1.0) and out1[1][1][1, 4] == pytest.approx(0.0)


def test_a_frame_warped_over_a_region_gives_what_its_whole_warp_gives_there():
    """accumulate_frame over a small region (the frame cut to what the region reads before
    its conversion to float32) against the same frame warped over its whole footprint: the
    same to OpenCV's 1/32 px sample positions (fixed point relative to each warped box's
    origin), nothing outside the region."""
    px = 0.0025
    grid = MapGrid(0.0, 1.0, px, 400, 400)
    rng = np.random.default_rng(7)
    smooth = cv2.GaussianBlur(rng.normal(0, 1, (160, 240)).astype(np.float32), (0, 0), 2.0)
    image = np.clip(32768 + 60000 * smooth, 0, 65280).astype(np.uint16)
    weight = feather_weight(np.ones(image.shape, bool), 24.0, 2.0)
    pose = np.array([0.5, 0.5, 0.3])
    box = (0, 400, 0, 400)
    whole = [np.zeros((400, 400), np.float32), np.zeros((400, 400), np.float32), np.zeros((400, 400), np.uint16)]
    accumulate_frame(*whole, box, grid, image, weight, pose, px, 1.3, cv2.INTER_CUBIC, 1 / 256)
    part = [np.zeros((400, 400), np.float32), np.zeros((400, 400), np.float32), np.zeros((400, 400), np.uint16)]
    region = ((180, 230, 150, 260), np.ones((50, 110), np.float32))
    accumulate_frame(*part, box, grid, image, weight, pose, px, 1.3, cv2.INTER_CUBIC, 1 / 256, region=region)
    inside = (slice(180, 230), slice(150, 260))
    diff = np.abs(part[0][inside] - whole[0][inside])
    grad = np.abs(np.diff(whole[0][inside]))  # grey levels per pixel along rows
    assert diff.mean() < grad.mean() / 32 and diff.max() < grad.max() / 8
    np.testing.assert_allclose(part[1][inside], whole[1][inside], atol=1e-5)
    outside = part[1].copy()
    outside[inside] = 0
    assert not outside.any()  # nothing warped outside the region
    assert (part[1][inside] > 0.99).all()  # the region lies well inside the frame


def test_a_frame_cut_to_what_a_warp_reads_warps_to_the_same_bits():
    from pipeline.mosaic import _crop_to_reach

    rng = np.random.default_rng(8)
    image = rng.integers(0, 65280, (160, 240)).astype(np.uint16)
    a = 0.3
    s2f = np.array([[math.cos(a), -math.sin(a), 97.3], [math.sin(a), math.cos(a), 41.7]])
    for interp in (cv2.INTER_LINEAR, cv2.INTER_CUBIC, cv2.INTER_LANCZOS4):
        cut, moved = _crop_to_reach(image, s2f, (40, 30), interp)
        assert cut.size < image.size / 4
        full = cv2.warpAffine(cv2.multiply(image, 1 / 256, dtype=cv2.CV_32F), s2f, (40, 30),
                              flags=interp | cv2.WARP_INVERSE_MAP)
        part = cv2.warpAffine(cv2.multiply(cut, 1 / 256, dtype=cv2.CV_32F), moved, (40, 30),
                              flags=interp | cv2.WARP_INVERSE_MAP)
        np.testing.assert_array_equal(part, full)
