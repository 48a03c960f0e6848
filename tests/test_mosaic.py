"""pipeline.mosaic: rendering frames into map shards, pyramid levels and quality layers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mapstore.grid import MapGrid
from pipeline.mosaic import (
    INTERPOLATIONS,
    accumulate_frame,
    assign_to_shards,
    composite_over,
    coverage_layer,
    downsample2,
    feather_weight,
    finish,
    frame_boxes,
    interpolation_margin_px,
    shard_box,
    reduced_uniqueness_params,
    texture_layer,
    uniqueness_cells,
    uniqueness_layer,
    weight_ones_box,
)
import pipeline.mosaic as mosaic_module

PIXEL_M = 0.0025
OVERSAMPLE = 3  # world raster per map pixel (odd: map pixel centres fall on world pixels)
MAP_SHAPE = (96, 128)
FRAME_SHAPE = (40, 56)
FEATHER_PX = 8.0


def band_limited(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float,
                 mean: float = 128.0, std: float = 30.0) -> np.ndarray:
    """Gaussian-filtered white noise (float32 grey levels)."""
    a = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma_px)
    return (mean + std * (a - a.mean()) / a.std()).astype(np.float32)


def uint8_texture(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float = 1.0) -> np.ndarray:
    return np.clip(np.rint(band_limited(rng, shape, sigma_px)), 1, 255).astype(np.uint8)


class World:
    """A band-limited floor (sigma 1 map pixel) on a fine raster, the map grid over it,
    and frames cut out of it at known poses."""

    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        h, w = MAP_SHAPE
        self.fine_grid = MapGrid(1.0, 2.0, PIXEL_M / OVERSAMPLE, w * OVERSAMPLE, h * OVERSAMPLE)
        self.grid = self.fine_grid.coarsened(OVERSAMPLE)
        self.fine = band_limited(rng, self.fine_grid.shape, 1.0 * OVERSAMPLE)
        mid = OVERSAMPLE // 2
        self.truth = self.fine[mid::OVERSAMPLE, mid::OVERSAMPLE]  # at the map pixel centres

    def poses(self, n: int, frame_pixel_m: float, seed: int) -> np.ndarray:
        """Poses with the frames inside the map, subpixel positions, any heading."""
        rng = np.random.default_rng(seed)
        half = 0.5 * np.hypot(*FRAME_SHAPE) * frame_pixel_m
        xmin, ymin, xmax, ymax = self.grid.bounds
        x = rng.uniform(xmin + half, xmax - half, n)
        y = rng.uniform(ymin + half, ymax - half, n)
        return np.column_stack([x, y, rng.uniform(-np.pi, np.pi, n)])

    def frame(self, pose: np.ndarray, frame_pixel_m: float) -> np.ndarray:
        f2w = self.fine_grid.frame_to_grid_affine(pose, FRAME_SHAPE, frame_pixel_m)
        return cv2.warpAffine(self.fine, f2w, FRAME_SHAPE[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REFLECT)


def frame_valid() -> np.ndarray:
    """A rectified frame's valid area: not the whole rectangle (cut corners)."""
    h, w = FRAME_SHAPE
    rr, cc = np.mgrid[0:h, 0:w]
    return ((rr - (h - 1) / 2) / (0.62 * h)) ** 2 + ((cc - (w - 1) / 2) / (0.62 * w)) ** 2 <= 1.0


def render(grid, box, frames, poses, gains, frame_pixel_m, interpolation=cv2.INTER_CUBIC, indices=None):
    r0, r1, c0, c1 = box
    acc = np.zeros((r1 - r0, c1 - c0), np.float32)
    wacc = np.zeros_like(acc)
    count = np.zeros(acc.shape, np.uint16)
    valid = frame_valid()
    weight = feather_weight(valid, FEATHER_PX, interpolation_margin_px(interpolation))
    for k in range(len(frames)) if indices is None else indices:
        img = np.where(valid, frames[k], 0).astype(np.float32)  # invalid pixels hold 0, as ingest stores them
        accumulate_frame(acc, wacc, count, box, grid, img, weight, poses[k], frame_pixel_m, gains[k], interpolation)
    return acc, wacc, count


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


@pytest.fixture(scope="module")
def world() -> World:
    return World()


# --- rendering ---------------------------------------------------------------------------


@pytest.mark.parametrize("frame_pixel_m", [PIXEL_M, 0.8 * PIXEL_M])
@pytest.mark.parametrize("with_gains", [False, True])
def test_render_reproduces_world(world, frame_pixel_m, with_gains):
    n = 40
    poses = world.poses(n, frame_pixel_m, seed=10)
    gains = np.exp(np.random.default_rng(11).normal(0.0, 0.2, n)) if with_gains else np.ones(n)
    frames = [world.frame(p, frame_pixel_m) * g for p, g in zip(poses, gains)]
    box = (0, MAP_SHAPE[0], 0, MAP_SHAPE[1])
    acc, wacc, count = render(world.grid, box, frames, poses, gains, frame_pixel_m)
    out = finish(acc, wacc)
    covered = out > 0
    assert covered.mean() > 0.4
    assert np.array_equal(covered, wacc > 0) and np.array_equal(count > 0, covered)
    got, want = out[covered].astype(np.float64), world.truth[covered].astype(np.float64)
    err = got - want
    rms, c = float(np.sqrt(np.mean(err**2))), ncc(got, want)
    assert c > 0.99 and rms < 1.5, f"NCC {c:.5f}, error RMS {rms:.3f} grey levels, max {np.abs(err).max():.1f}"
    # The frames' own edges (cut corners, zero-filled) leave no fringe at the coverage edge.
    edge = covered & ~cv2.erode(covered.view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    edge_rms = float(np.sqrt(np.mean((out[edge] - world.truth[edge].astype(np.float64)) ** 2)))
    assert edge_rms < 3.0, f"coverage-edge error RMS {edge_rms:.2f} grey levels"


@pytest.mark.parametrize("name", sorted(INTERPOLATIONS))
def test_render_every_interpolation(world, name):
    poses = world.poses(12, PIXEL_M, seed=12)
    frames = [world.frame(p, PIXEL_M) for p in poses]
    acc, wacc, _ = render(world.grid, (0, MAP_SHAPE[0], 0, MAP_SHAPE[1]), frames, poses, np.ones(12), PIXEL_M,
                          INTERPOLATIONS[name])
    out = finish(acc, wacc)
    cov = out > 0
    got, want = out[cov].astype(np.float64), world.truth[cov].astype(np.float64)
    rms = float(np.sqrt(np.mean((got - want) ** 2)))
    assert ncc(got, want) > 0.99 and rms < 4.0, f"{name}: NCC {ncc(got, want):.5f}, error RMS {rms:.3f} grey levels"


def test_render_is_deterministic(world):
    poses = world.poses(15, PIXEL_M, seed=13)
    frames = [world.frame(p, PIXEL_M) for p in poses]
    box = (10, 80, 5, 120)
    outs = [finish(*render(world.grid, box, frames, poses, np.ones(15), PIXEL_M)[:2]) for _ in range(2)]
    assert outs[0].tobytes() == outs[1].tobytes()


def test_shards_render_like_one_box(world):
    """Shards rendered from the frames assign_to_shards gives them tile the whole box."""
    poses = world.poses(30, PIXEL_M, seed=14)
    frames = [world.frame(p, PIXEL_M) for p in poses]
    gains = np.ones(30)
    whole = finish(*render(world.grid, (0, MAP_SHAPE[0], 0, MAP_SHAPE[1]), frames, poses, gains, PIXEL_M)[:2])
    shard_px = 40
    boxes = frame_boxes(world.grid, poses, FRAME_SHAPE, PIXEL_M)
    tiled = np.zeros_like(whole)
    for ij, idx in assign_to_shards(boxes, MAP_SHAPE, shard_px).items():
        r0, r1, c0, c1 = b = shard_box(ij, MAP_SHAPE, shard_px)
        tiled[r0:r1, c0:c1] = finish(*render(world.grid, b, frames, poses, gains, PIXEL_M, indices=idx)[:2])
    diff = np.abs(tiled.astype(int) - whole)
    assert np.array_equal(tiled > 0, whole > 0)
    assert diff.max() <= 1 and np.mean(diff > 0) < 0.01


@pytest.mark.parametrize("feathered", [False, True])
def test_accumulate_touches_only_the_frame_box(world, feathered):
    poses = world.poses(10, PIXEL_M, seed=15)
    ones = np.ones(FRAME_SHAPE, np.float32)
    # A weight nonzero on the frame's border reaches 1 px beyond its outer pixel centres
    # (0.5 px beyond the footprint's edges); a feathered one stays inside the footprint.
    weight, pad = (feather_weight(frame_valid(), FEATHER_PX, 1.0), 0) if feathered else (ones, 1)
    boxes = frame_boxes(world.grid, poses, FRAME_SHAPE, PIXEL_M, pad_px=pad)
    for pose, (r0, r1, c0, c1) in zip(poses, boxes):
        acc = np.zeros(MAP_SHAPE, np.float32)
        wacc, count = np.zeros_like(acc), np.zeros(MAP_SHAPE, np.uint16)
        accumulate_frame(acc, wacc, count, (0, MAP_SHAPE[0], 0, MAP_SHAPE[1]), world.grid, ones * 100, weight,
                         pose, PIXEL_M, 2.0, cv2.INTER_LINEAR)
        rows, cols = np.nonzero(wacc)
        assert rows.min() >= r0 and rows.max() < r1 and cols.min() >= c0 and cols.max() < c1
        assert np.array_equal(count > 0, wacc > 0) and count.max() == 1
        if feathered:  # the kernel stays inside the frame where the weight is nonzero
            assert np.allclose(acc[wacc > 0] / wacc[wacc > 0], 50.0, atol=1e-3)  # grey levels / gain
    # A frame wholly outside the box leaves the accumulators alone.
    acc = np.zeros((5, 5), np.float32)
    accumulate_frame(acc, acc.copy(), np.zeros((5, 5), np.uint16), (500, 505, 500, 505), world.grid,
                     ones, ones, poses[0], PIXEL_M, 1.0, cv2.INTER_CUBIC)
    assert not acc.any()


# --- boxes and shards --------------------------------------------------------------------


def test_frame_boxes_contain_footprint_corners():
    rng = np.random.default_rng(3)
    grid = MapGrid(-1.0, 1.0, PIXEL_M, 800, 800)
    poses = np.column_stack([rng.uniform(-1.2, 1.2, (50, 2)), rng.uniform(-np.pi, np.pi, 50)])
    h, w = FRAME_SHAPE
    corners = np.array([[-0.5, -0.5, 1], [w - 0.5, -0.5, 1], [w - 0.5, h - 0.5, 1], [-0.5, h - 0.5, 1]]).T
    for fpm in (PIXEL_M, 1.7 * PIXEL_M):
        boxes = frame_boxes(grid, poses, FRAME_SHAPE, fpm, pad_px=0)
        padded = frame_boxes(grid, poses, FRAME_SHAPE, fpm)
        assert boxes.shape == (50, 4) and boxes.dtype == np.int64
        assert np.array_equal(padded, boxes + [-2, 2, -2, 2])
        for pose, (r0, r1, c0, c1) in zip(poses, boxes):
            gc, gr = grid.frame_to_grid_affine(pose, FRAME_SHAPE, fpm) @ corners
            assert np.all((r0 <= gr) & (gr < r1) & (c0 <= gc) & (gc < c1))
            # Tight: each side is within a pixel of a corner.
            assert gr.min() - r0 < 1 and r1 - gr.max() <= 1 and gc.min() - c0 < 1 and c1 - gc.max() <= 1
    assert frame_boxes(grid, np.zeros((0, 3)), FRAME_SHAPE, PIXEL_M).shape == (0, 4)


def test_assign_to_shards_matches_brute_force():
    rng = np.random.default_rng(4)
    shape, shard_px = (230, 170), 64
    r0 = rng.integers(-80, 260, 300)
    c0 = rng.integers(-80, 200, 300)
    boxes = np.column_stack([r0, r0 + rng.integers(1, 90, 300), c0, c0 + rng.integers(1, 90, 300)])
    got = assign_to_shards(boxes, shape, shard_px)
    want = {}
    for i in range(-(-shape[0] // shard_px)):
        for j in range(-(-shape[1] // shard_px)):
            sb = shard_box((i, j), shape, shard_px)
            hit = [k for k, b in enumerate(boxes)
                   if max(b[0], sb[0]) < min(b[1], sb[1]) and max(b[2], sb[2]) < min(b[3], sb[3])]
            if hit:
                want[(i, j)] = hit
    assert list(got) == sorted(want)
    for key, idx in got.items():
        assert idx.dtype == np.int64 and idx.tolist() == want[key]
    outside = np.array([[-50, -1, 0, 10], [0, 10, 170, 200], [240, 250, 0, 10]])
    assert assign_to_shards(outside, shape, shard_px) == {}
    assert assign_to_shards(np.zeros((0, 4), np.int64), shape, shard_px) == {}


def test_shard_box_clipped_at_grid_edges():
    assert shard_box((0, 0), (100, 70), 32) == (0, 32, 0, 32)
    assert shard_box((3, 2), (100, 70), 32) == (96, 100, 64, 70)
    with pytest.raises(ValueError):
        shard_box((4, 0), (100, 70), 32)


# --- feathering, finishing, compositing ----------------------------------------------------


def test_feather_weight():
    valid = np.ones((60, 80), bool)
    valid[20:30, 50:60] = False  # a hole
    w = feather_weight(valid, 10.0)
    assert w.dtype == np.float32 and w.shape == valid.shape
    assert np.all(w[~valid] == 0)
    assert np.all(w[0] == 0) and np.all(w[-1] == 0) and np.all(w[:, 0] == 0) and np.all(w[:, -1] == 0)
    assert np.all(w[12:48, 12:38] == 1.0)  # deeper than 1 + 10 px from every edge
    assert np.all((w >= 0) & (w <= 1))
    row = w[40, :40]  # from the left border inwards
    assert np.all(np.diff(row[:15]) >= 0) and 0 < row[1] < 0.05 and row[15] == 1.0
    # A margin keeps the weight at 0 deeper, then the same ramp.
    wm = feather_weight(valid, 10.0, margin_px=2.0)
    assert np.all(wm[40, :3] == 0) and np.allclose(wm[40, 2:30], w[40, :28])
    assert interpolation_margin_px(cv2.INTER_LINEAR) == 1 and interpolation_margin_px(cv2.INTER_CUBIC) == 2
    assert interpolation_margin_px(cv2.INTER_LANCZOS4) == 5


def test_finish():
    acc = np.array([[0.0, 10.0, 500.0, 1.0, 0.0]], np.float32)
    wacc = np.array([[0.0, 4.0, 1.0, 2.0, 1e-3]], np.float32)
    assert finish(acc, wacc).tolist() == [[0, 2, 255, 1, 1]]  # 2.5 rounds to even; clipped to 1..255
    assert finish(acc, wacc).dtype == np.uint8


def test_composite_over():
    old = np.array([0, 0, 100, 100, 100, 100, 200], np.uint8)
    new = np.array([0, 50, 0, 50, 50, 50, 1], np.uint8)
    wacc = np.array([0.0, 0.2, 0.0, 0.0, 0.5, 3.0, 0.9], np.float32)
    got = composite_over(old, new, wacc)
    assert got.dtype == np.uint8
    assert got.tolist() == [0, 50, 100, 100, 75, 50, 21]


# --- pyramid and layers --------------------------------------------------------------------


def test_downsample2_odd_sizes_and_no_data():
    rng = np.random.default_rng(5)
    img = rng.integers(1, 256, (7, 5)).astype(np.uint8)
    img[rng.random(img.shape) < 0.3] = 0
    img[0:2, 0:2] = 0  # an empty block
    img[2:4, 2:4] = [[10, 0], [0, 13]]  # mean 11.5 rounds half up
    out = downsample2(img)
    assert out.shape == (4, 3) and out.dtype == np.uint8
    for r in range(4):
        for c in range(3):
            block = img[2 * r : 2 * r + 2, 2 * c : 2 * c + 2]
            v = block[block > 0].astype(float)
            assert out[r, c] == (int(np.floor(v.mean() + 0.5)) if v.size else 0), (r, c)
    assert out[0, 0] == 0 and out[1, 1] == 12
    # The shape and pixel centres of MapGrid.level(1).
    grid = MapGrid(3.0, 4.0, PIXEL_M, 5, 7)
    assert out.shape == grid.level(1).shape
    fine_x, fine_y = grid.pixel_to_world(np.array([2, 3, 2, 3]), np.array([4, 4, 5, 5]))
    assert np.allclose(grid.level(1).pixel_to_world(1, 2), (fine_x.mean(), fine_y.mean()))
    assert downsample2(np.full((1, 1), 9, np.uint8)).tolist() == [[9]]


def test_coverage_layer_max():
    rng = np.random.default_rng(6)
    count = rng.integers(0, 9, (37, 50)).astype(np.uint16)
    lay = coverage_layer(count, 16)
    assert lay.shape == (3, 4) and lay.dtype == np.uint16
    for i in range(3):
        for j in range(4):
            assert lay[i, j] == count[16 * i : 16 * i + 16, 16 * j : 16 * j + 16].max()


def test_texture_layer():
    rng = np.random.default_rng(7)
    img = np.full((128, 160), 100, np.uint8)
    img[:, :80] = uint8_texture(rng, (128, 80))
    img[40:72, 100:140] = 0  # no data inside the flat half
    img[:, 144:] = 0  # and a no-data strip
    lay = texture_layer(img, 16, 17, 1.0)
    assert lay.shape == (8, 10) and lay.dtype == np.float32
    nodata_cells = np.zeros(lay.shape, bool)
    nodata_cells[:, 9] = nodata_cells[3, 7] = True
    assert np.array_equal(np.isnan(lay), nodata_cells)
    textured, flat = lay[:, :4], lay[:, 6:9]
    assert textured.min() > 20 and np.nanmax(flat) < 1.0  # no fake gradients at no-data edges
    # Partial cells: an image not a multiple of the cell.
    assert texture_layer(img[:100, :150], 16, 17, 1.0).shape == (7, 10)
    # A halo gives context only.
    assert np.allclose(texture_layer(img, 16, 17, 1.0, halo_px=16), texture_layer(img, 16, 17, 1.0)[1:-1, 1:-1],
                       rtol=0.2, equal_nan=True)


def _uniqueness_reference(img, i, j, cell, tp, radius, excl):
    """Kelly's (2000) recipe for one cell with cv2.matchTemplate (NaN where not covered)."""
    cy, cx = i * cell + cell // 2, j * cell + cell // 2
    y0, x0 = cy - tp // 2 - radius, cx - tp // 2 - radius
    side = tp + 2 * radius
    if y0 < 0 or x0 < 0 or y0 + side > img.shape[0] or x0 + side > img.shape[1]:
        return np.nan
    win = img[y0 : y0 + side, x0 : x0 + side].astype(np.float32)
    if (win == 0).any():
        return np.nan
    surf = cv2.matchTemplate(win, win[radius : radius + tp, radius : radius + tp], cv2.TM_CCOEFF_NORMED)
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return surf[radius, radius] - surf[np.maximum(abs(yy), abs(xx)) >= excl].max()


def test_uniqueness_layer_matches_match_template():
    rng = np.random.default_rng(8)
    img = uint8_texture(rng, (150, 200), 1.5)
    img[60:70, 90:95] = 0
    lay = uniqueness_layer(img, 16, 17, 8, 3)
    assert lay.shape == (10, 13) and lay.dtype == np.float32
    ref = np.array([[_uniqueness_reference(img, i, j, 16, 17, 8, 3) for j in range(13)] for i in range(10)])
    assert np.array_equal(np.isnan(lay), np.isnan(ref))
    assert np.nanmax(np.abs(lay - ref)) < 1e-4
    # Windows leave the array at the border cells; a halo supplies them.
    assert np.isnan(lay[0]).all() and np.isnan(lay[:, 0]).all()
    inner = uniqueness_layer(img, 16, 17, 8, 3, halo_px=16)
    assert inner.shape == (8, 11)
    assert np.array_equal(inner, lay[1:9, 1:12], equal_nan=True)


def test_uniqueness_layer_texture_stripes_and_no_data():
    rng = np.random.default_rng(9)
    tex = uint8_texture(rng, (160, 160))
    u = uniqueness_layer(tex, 16, 17, 8, 3)
    assert np.nanmin(u) > 0.5, np.nanmin(u)
    cols = np.arange(160)
    stripes = np.tile(np.rint(128 + 60 * np.sin(2 * np.pi * cols / 5.0)).astype(np.uint8), (160, 1))
    s = uniqueness_layer(stripes, 16, 17, 8, 3)
    assert np.nanmax(s) < 0.2, np.nanmax(s)
    holey = tex.copy()
    holey[70:90, 70:90] = 0
    h = uniqueness_layer(holey, 16, 17, 8, 3)
    # Windows reach 16 px from the cell centre (8 px into the cell): cells 3..5 see the hole.
    assert np.isnan(h[3:6, 3:6]).all()
    assert np.allclose(h[1:3, 1:9], u[1:3, 1:9]) and not np.isnan(h[1:3, 1:9]).any()
    flat = np.full((64, 64), 90, np.uint8)
    assert np.isnan(uniqueness_layer(flat, 16, 17, 8, 3)).all()
    assert np.isnan(uniqueness_layer(np.zeros((64, 64), np.uint8), 16, 17, 8, 3)).all()


def test_uniqueness_layer_is_the_same_in_any_slab_and_batch(monkeypatch):
    """The cells are computed in bands of cell rows and batches of cells: their sizes only
    decide the memory used, never a value (a band of one cell row, batches of 1 or 5 cells)."""
    rng = np.random.default_rng(12)
    img = uint8_texture(rng, (230, 170), 1.5)
    img[100:118, 40:70] = 0
    whole = uniqueness_layer(img, 16, 17, 8, 3, halo_px=16)
    for slab_px, batch_bytes in ((1, 1), (170 * 16 * 3, 5 * 17 * 17 * 33 * 4), (1 << 30, 1 << 30)):
        monkeypatch.setattr(mosaic_module, "_UNIQUENESS_SLAB_PX", slab_px)
        monkeypatch.setattr(mosaic_module, "_UNIQUENESS_BATCH_BYTES", batch_bytes)
        assert np.array_equal(uniqueness_layer(img, 16, 17, 8, 3, halo_px=16), whole, equal_nan=True)


def test_uniqueness_on_level_1_is_the_reduced_search_on_the_reduced_mosaic():
    rng = np.random.default_rng(13)
    img = uint8_texture(rng, (2 * 16 + 150, 2 * 16 + 203), 1.5)
    assert reduced_uniqueness_params(17, 8, 3) == (9, 4, 2)
    u1 = uniqueness_cells(img, 16, 17, 8, 3, level=1, halo_px=16)
    u0 = uniqueness_cells(img, 16, 17, 8, 3, level=0, halo_px=16)
    # The cells of level 0 (partial ones at the bottom and right included), on the level-1 pixels.
    assert u1.shape == u0.shape == (10, 13)
    assert np.array_equal(u1, uniqueness_layer(downsample2(img), 8, 9, 4, 2, halo_px=8), equal_nan=True)
    assert np.array_equal(u1, uniqueness_cells(img, 16, 17, 8, 3, level=1, halo_px=16, reduced=downsample2(img)),
                          equal_nan=True)
    assert np.array_equal(u0, uniqueness_layer(img, 16, 17, 8, 3, halo_px=16), equal_nan=True)
    with pytest.raises(ValueError, match="even"):
        uniqueness_cells(img, 15, 17, 8, 3, level=1, halo_px=16)
    with pytest.raises(ValueError, match="0 or 1"):
        uniqueness_cells(img, 16, 17, 8, 3, level=2, halo_px=16)


def test_uniqueness_of_some_cells_is_their_value_among_all():
    """``where``: the chosen cells measured alone (their windows gathered side by side) give
    the bit-identical values of the whole layer; the others are NaN; no-data stays NaN."""
    rng = np.random.default_rng(21)
    img = uint8_texture(rng, (2 * 16 + 170, 2 * 16 + 230), 1.5)
    img[60:90, 100:140] = 0
    whole = uniqueness_layer(img, 16, 17, 8, 3, halo_px=16)
    for fraction in (0.0, 0.07, 0.5, 1.0):
        where = rng.random(whole.shape) < fraction
        some = uniqueness_layer(img, 16, 17, 8, 3, halo_px=16, where=where)
        assert np.array_equal(some, np.where(where, whole, np.nan), equal_nan=True)
    assert np.isnan(whole).any() and np.isfinite(whole).sum() > 100
    with pytest.raises(ValueError, match="does not match"):
        uniqueness_layer(img, 16, 17, 8, 3, halo_px=16, where=np.ones((3, 3), bool))


def test_uniqueness_on_level_1_rechecks_the_cells_near_the_threshold_on_level_0():
    """``recheck`` (lo, hi): level-1 cells in [lo, hi) take their level-0 value, the rest keep
    the level-1 one; a band holding every value gives level 0 wherever level 0 has one."""
    rng = np.random.default_rng(22)
    tex = uint8_texture(rng, (2 * 16 + 160, 2 * 16 + 160), 1.5)
    stripes = np.tile(np.rint(128 + 60 * np.sin(2 * np.pi * np.arange(tex.shape[1]) / 10.0)).astype(np.uint8),
                      (tex.shape[0], 1))
    img = np.where(np.arange(tex.shape[1])[None, :] < tex.shape[1] // 2, tex, stripes).astype(np.uint8)
    u0 = uniqueness_cells(img, 16, 17, 8, 3, level=0, halo_px=16)
    u1 = uniqueness_cells(img, 16, 17, 8, 3, level=1, halo_px=16)
    lo, hi = float(np.nanpercentile(u1, 30)), float(np.nanpercentile(u1, 70))
    mixed = uniqueness_cells(img, 16, 17, 8, 3, level=1, halo_px=16, recheck=(lo, hi))
    near = (u1 >= lo) & (u1 < hi)
    assert near.any() and (~near & np.isfinite(u1)).any()
    assert np.array_equal(mixed[near], u0[near]) and np.array_equal(mixed[~near], u1[~near], equal_nan=True)
    every = uniqueness_cells(img, 16, 17, 8, 3, level=1, halo_px=16, recheck=(-2.0, 3.0))
    assert np.array_equal(every, u0, equal_nan=True)


def test_uniqueness_on_level_1_keeps_the_cells_on_the_same_side_of_0_2():
    """Distinct texture reads unique on both levels, stripes (10 px period: 5 on level 1) and
    a texture repeating every 6 px poor on both; no-data cells stay no-data."""
    rng = np.random.default_rng(14)
    tex = uint8_texture(rng, (288, 288), 1.5)
    cols = np.arange(288)
    stripes = np.tile(np.rint(128 + 60 * np.sin(2 * np.pi * cols / 10.0)).astype(np.uint8), (288, 1))
    tile = uint8_texture(rng, (6, 6), 1.0)
    periodic = np.tile(tile, (48, 48))
    for img, poor in ((tex, False), (stripes, True), (periodic, True)):
        u0 = uniqueness_cells(img, 16, 17, 8, 3, level=0, halo_px=16)
        u1 = uniqueness_cells(img, 16, 17, 8, 3, level=1, halo_px=16)
        assert np.isfinite(u0).all() and np.isfinite(u1).all()
        assert ((u0 < 0.2) == poor).all() and ((u1 < 0.2) == poor).all(), (np.nanmax(u1), np.nanmin(u1))
    holey = tex.copy()
    holey[100:140, 100:140] = 0
    assert np.isnan(uniqueness_cells(holey, 16, 17, 8, 3, level=1, halo_px=16)[5:7, 5:7]).all()


def test_threshold_agreement_counts_cells_on_each_side():
    from pipeline.evaluate import threshold_agreement

    nan = np.nan
    ref = np.array([[0.1, 0.3, 0.5], [0.19, nan, 0.25]])
    oth = np.array([[0.15, 0.1, 0.6], [nan, 0.4, 0.2]])
    a = threshold_agreement(ref, oth, 0.2)
    # reference cells 5: same side 0.1/0.15, 0.5/0.6, 0.25/0.2; 0.3/0.1 not; 0.19 has no other value
    assert (a.cells, a.same, a.missing, a.extra) == (5, 3, 1, 1)
    assert a.fraction == pytest.approx(0.6) and (a.below_reference, a.below_other) == (2, 2)
    assert threshold_agreement(np.full((2, 2), nan), np.ones((2, 2)), 0.2).fraction == 1.0
    with pytest.raises(ValueError):
        threshold_agreement(ref, oth[:1], 0.2)


def test_weight_ones_box_holds_only_ones():
    rect = feather_weight(np.ones((60, 80), bool), 8.0, 1.0)
    assert weight_ones_box(rect) == (9, 51, 9, 71)  # d = index + 1 >= 1 + 1 + 8 from every edge
    yy, xx = np.mgrid[:90, :90]
    disc = feather_weight(np.hypot(yy - 44.5, xx - 44.5) < 40, 6.0)
    r0, r1, c0, c1 = weight_ones_box(disc)
    assert (disc[r0:r1, c0:c1] == 1).all() and (r1 - r0) * (c1 - c0) > 0.4 * np.count_nonzero(disc == 1)
    assert weight_ones_box(feather_weight(np.ones((10, 10), bool), 8.0)) is None


@pytest.mark.parametrize("theta", [0.0, 0.02, np.pi - 0.03, 0.5 * np.pi + 0.01, 0.25 * np.pi, 2.0])
def test_weight_warped_around_its_ones_as_warped_whole(world, theta):
    """Output pixels sampling only weights of 1 skip the weight's warp: the accumulators match
    a whole warp to OpenCV's 1/32 px position rounding, at any heading."""
    weight = feather_weight(np.ones(FRAME_SHAPE, bool), FEATHER_PX, interpolation_margin_px(cv2.INTER_CUBIC))
    ones = weight_ones_box(weight)
    assert ones is not None
    img = np.random.default_rng(3).uniform(20, 230, FRAME_SHAPE).astype(np.float32)
    pose = np.array([1.0 + 0.5 * MAP_SHAPE[1] * PIXEL_M + 0.0011, 2.0 - 0.5 * MAP_SHAPE[0] * PIXEL_M + 0.0007, theta])
    out = []
    for wo in (None, ones):
        acc, wacc = np.zeros(MAP_SHAPE, np.float32), np.zeros(MAP_SHAPE, np.float32)
        count = np.zeros(MAP_SHAPE, np.uint16)
        accumulate_frame(acc, wacc, count, (0, MAP_SHAPE[0], 0, MAP_SHAPE[1]), world.grid, img, weight, pose, PIXEL_M,
                         1.0, cv2.INTER_CUBIC, weight_ones=wo)
        out.append((acc, wacc, count))
    (a0, w0, n0), (a1, w1, n1) = out
    assert (w1 == 1).sum() > 0.3 * (w0 > 0).sum()  # most of the frame skipped its weight's warp
    # a 1/32 px position step on the steepest part of the feather (1.5 / FEATHER_PX per px)
    assert np.abs(w1 - w0).max() < 1.6 / FEATHER_PX / 32 and np.abs(a1 - a0).max() < 255 * 1.6 / FEATHER_PX / 32
    assert np.count_nonzero(n1 != n0) <= 4


def test_accumulate_uint16_with_intensity_scale_matches_float(world):
    """Frames as the store keeps them (uint16, 1/256 grey level) render as the float frames."""
    poses = world.poses(12, PIXEL_M, seed=16)
    frames = [world.frame(p, PIXEL_M) for p in poses]
    box = (0, MAP_SHAPE[0], 0, MAP_SHAPE[1])
    weight = feather_weight(frame_valid(), FEATHER_PX, interpolation_margin_px(cv2.INTER_CUBIC))
    outs = []
    for as_u16 in (False, True):
        acc, wacc = np.zeros(MAP_SHAPE, np.float32), np.zeros(MAP_SHAPE, np.float32)
        count = np.zeros(MAP_SHAPE, np.uint16)
        for f, pose in zip(frames, poses):
            img = np.where(frame_valid(), f, 0).astype(np.float32)
            if as_u16:
                img = np.clip(np.rint(img * 256), 0, 65535).astype(np.uint16)
            accumulate_frame(acc, wacc, count, box, world.grid, img, weight, pose, PIXEL_M, 1.3, cv2.INTER_CUBIC,
                             intensity_scale=1 / 256 if as_u16 else 1.0)
        outs.append((acc, wacc, count))
    (a0, w0, n0), (a1, w1, n1) = outs
    assert np.array_equal(w0, w1) and np.array_equal(n0, n1)
    cov = w0 > 0
    assert np.abs(a0[cov] / w0[cov] - a1[cov] / w1[cov]).max() < 0.02  # grey levels


def test_texture_layer_sampled_lattice_is_close_to_every_pixel():
    rng = np.random.default_rng(17)
    img = uint8_texture(rng, (200, 230), 1.5)
    img[:, :40] = np.clip(img[:, :40] // 4 + 100, 1, 255)  # a weaker texture
    img[150:, 100:] = 0  # no data
    img[60:63, 30:90] = 0  # a thin gap: cells covered only off the lattice
    every = texture_layer(img, 16, 17, 1.0, halo_px=8)
    for step in (2, 4, 8):
        lat = texture_layer(img, 16, 17, 1.0, halo_px=8, sample_px=step)
        assert np.array_equal(np.isnan(lat), np.isnan(every))
        m = ~np.isnan(every)
        rel = np.abs(lat[m] - every[m]) / every[m]
        # a cell's median over its lattice differs most where coverage cuts it (few samples)
        assert np.median(rel) < 0.05 and np.percentile(rel, 90) < 0.2, (step, np.median(rel), np.percentile(rel, 90))
    with pytest.raises(ValueError):
        texture_layer(img, 16, 17, 1.0, sample_px=3)


def test_finish_into_buffers_in_place():
    """``finish(out=..., in_place=True)`` writes the same bytes as a fresh finish."""
    rng = np.random.default_rng(3)
    acc = rng.random((37, 53), dtype=np.float32) * 300.0
    wacc = rng.random((37, 53), dtype=np.float32)
    wacc[:5] = 0.0
    wacc[7, :9] = 0.25  # acc / wacc above 255 saturates
    ref = finish(acc, wacc)
    out = np.full(acc.shape, 77, np.uint8)
    got = finish(acc.copy(), wacc, out=out, in_place=True)
    assert got is out
    np.testing.assert_array_equal(got, ref)
    assert (ref[:5] == 0).all() and (ref[5:] >= 1).all()


def _frames_content(rng, kind: str) -> np.ndarray:
    """A 12 x 20 frame in grey levels: ``noise`` (zstd cannot shrink its uint16 values) or
    ``steps`` (whole grey levels in a few runs: it can)."""
    if kind == "noise":
        return rng.random((12, 20)).astype(np.float32) * 255.0
    return np.repeat(rng.integers(0, 256, (12, 4)), 5, axis=1).astype(np.float32)


@pytest.mark.parametrize("kind", ["noise", "steps"])
@pytest.mark.parametrize("count", [16, 21, 35])
def test_frames_store_direct_shard_reads_match_zarr(tmp_path, count, kind):
    """The frames store's direct shard-file reader returns zarr's frames for any range
    (whole shards, runs inside one, runs across shards, a partial last shard), stored
    compressed (frames zstd shrinks) or not (frames of noise)."""
    from pipeline.framestore import LogFramesWriter, ShardFileReader, create_store

    rng = np.random.default_rng(count)
    root = create_store(tmp_path / "frames.zarr", PIXEL_M)
    writer = LogFramesWriter(root, 0, {"log_id": "t"}, np.ones((12, 20), bool), shard_frames=8)
    for i in range(count):
        writer.append(_frames_content(rng, kind), float(i), np.zeros(3), i, (0.0,) * 6)
    writer.close()
    root.attrs["logs"] = [{"log_id": "t"}]
    from pipeline.framestore import FrameStore

    lf = FrameStore(tmp_path / "frames.zarr").logs[0]
    assert isinstance(lf._direct, ShardFileReader)
    assert lf._direct.compressed == (kind == "steps")
    assert (lf.group["images"].compressors != ()) == (kind == "steps")
    images = lf.group["images"]
    for a, b in [(0, count), (0, 8), (3, 5), (6, 11), (count - 2, count), (count - 1, count + 4)]:
        np.testing.assert_array_equal(lf.images_uint16(a, b), images[a:b])
        separate = lf.images_uint16(a, b, separate=True)  # each frame decoded into its own array
        assert isinstance(separate, list) and all(f.flags.owndata for f in separate)
        np.testing.assert_array_equal(np.array(separate).reshape(-1, 12, 20), images[a:b])
    np.testing.assert_array_equal(lf.images(2, 9), images[2:9].astype(np.float32) / 256.0)
    np.testing.assert_array_equal(lf.image(count - 1), images[count - 1].astype(np.float32) / 256.0)


@pytest.mark.parametrize("kind", ["noise", "steps"])
def test_frames_store_direct_reader_refuses_a_damaged_shard(tmp_path, kind):
    """A flipped byte in a shard's index fails its crc32c; a chunk that decodes short (or,
    uncompressed, holds less than a frame) is named."""
    from numcodecs import Zstd

    from pipeline.framestore import FrameStore, LogFramesWriter, create_store

    rng = np.random.default_rng(0)
    root = create_store(tmp_path / "frames.zarr", PIXEL_M)
    writer = LogFramesWriter(root, 0, {"log_id": "t"}, np.ones((12, 20), bool), shard_frames=4)
    for i in range(4):
        writer.append(_frames_content(rng, kind), float(i), np.zeros(3), i, (0.0,) * 6)
    writer.close()
    root.attrs["logs"] = [{"log_id": "t"}]
    lf = FrameStore(tmp_path / "frames.zarr").logs[0]
    shard = next(p for p in (tmp_path / "frames.zarr").rglob("c/0/0/0") if p.is_file())
    good = shard.read_bytes()
    bad = bytearray(good)
    bad[-10] ^= 0xFF  # inside the index
    shard.write_bytes(bytes(bad))
    with pytest.raises(OSError, match="checksum"):
        lf._direct.read(0, 4)
    # a shard whose first chunk holds half a frame (its index rewritten consistently)
    short = np.zeros(120, np.uint16).tobytes()
    if kind == "steps":
        short = Zstd().encode(short)
    said = "decodes to 240 bytes" if kind == "steps" else "holds 240 bytes"
    n_index = 4 * 16 + 4
    index = np.frombuffer(good[-n_index:-4], "<u8").reshape(4, 2).copy()
    body = good[: len(good) - n_index]
    index[0] = (len(body), len(short))
    from numcodecs import CRC32C

    shard.write_bytes(body + short + bytes(CRC32C().encode(index.tobytes())))
    with pytest.raises(OSError, match=said):
        lf._direct.read(0, 1)
    with pytest.raises(OSError, match=said):  # into frames' own arrays too
        lf.images_uint16(0, 2, separate=True)
