"""mapstore.grid: SE(2) algebra, frame and map-grid conventions."""

import numpy as np
import pytest

from mapstore.grid import (
    MapGrid,
    affine_box,
    frame_pixels_to_world,
    interpolate_trajectory,
    se2_between,
    se2_compose,
    se2_exp,
    se2_interpolate,
    se2_inverse,
    se2_log,
    world_to_frame_pixels,
    wrap_angle,
)

rng = np.random.default_rng(1)
POSES = np.column_stack([rng.uniform(-5, 5, (50, 2)), rng.uniform(-np.pi, np.pi, 50)])


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 1001)
    w = wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    assert np.allclose(np.cos(w), np.cos(a)) and np.allclose(np.sin(w), np.sin(a))


def test_compose_inverse_identity():
    ident = se2_compose(POSES, se2_inverse(POSES))
    assert np.allclose(ident, 0, atol=1e-12)
    b = POSES[::-1]
    assert np.allclose(se2_compose(POSES, se2_between(POSES, b)), np.column_stack([b[:, :2], wrap_angle(b[:, 2])]))


def test_exp_log_roundtrip():
    assert np.allclose(se2_exp(se2_log(POSES)), POSES, atol=1e-12)
    tiny = np.array([1e-3, -2e-3, 1e-12])
    assert np.allclose(se2_log(se2_exp(tiny)), tiny)


def test_interpolate_endpoints_and_constant_twist():
    a, b = POSES[0], POSES[1]
    assert np.allclose(se2_interpolate(a, b, 0.0), a)
    assert np.allclose(se2_interpolate(a, b, 1.0)[:2], b[:2])
    # Along a constant-twist arc, the midpoint of (0, 2) is the pose at 1.
    xi = np.array([1.0, 0.2, 0.5])
    p1, p2 = se2_exp(xi), se2_exp(2 * xi)
    assert np.allclose(se2_interpolate(np.zeros(3), p2, 0.5), p1)


def test_interpolate_trajectory():
    t = np.linspace(0, 10, 101)
    xi = np.array([0.3, 0.0, 0.1])  # constant twist per second: an arc
    samples = np.column_stack([t, se2_exp(t[:, None] * xi)])
    q = np.array([0.0, 0.37, 5.05, 9.999, 10.0])
    got = interpolate_trajectory(samples, q)
    assert np.allclose(got, se2_exp(q[:, None] * xi), atol=1e-12)


def test_frame_world_roundtrip_and_convention():
    shape, ps = (240, 320), 0.0025
    pose = np.array([1.0, 2.0, np.pi / 2])
    # Image centre -> pose position; column axis is vehicle +x (world +y at theta = 90 deg).
    x, y = frame_pixels_to_world(pose, np.array([159.5, 169.5]), np.array([119.5, 119.5]), shape, ps)
    assert np.allclose([x[0], y[0]], [1.0, 2.0])
    assert np.allclose([x[1] - x[0], y[1] - y[0]], [0.0, 10 * ps])
    # Row axis is vehicle -y: a row further down is to the vehicle's right.
    x, y = frame_pixels_to_world(pose, np.array([159.5]), np.array([129.5]), shape, ps)
    assert np.allclose([x[0] - 1.0, y[0] - 2.0], [10 * ps, 0.0])
    cols, rows = rng.uniform(0, 320, 20), rng.uniform(0, 240, 20)
    c2, r2 = world_to_frame_pixels(pose, *frame_pixels_to_world(pose, cols, rows, shape, ps), shape, ps)
    assert np.allclose(c2, cols) and np.allclose(r2, rows)


def test_map_grid_and_affine():
    g = MapGrid.covering(-1.0, -2.0, 4.0, 3.0, 0.0025)
    assert g.width == 2001 and g.height == 2001
    assert np.allclose(g.pixel_to_world(0, 0), (-1.0, 3.0))
    assert np.allclose(g.world_to_pixel(4.0, -2.0), (2000, 2000))
    b = g.bounds
    assert b[0] == pytest.approx(-1.00125) and b[3] == pytest.approx(3.00125)
    assert MapGrid.from_attrs(g.to_attrs()) == g
    pose = np.array([0.7, -0.3, 0.4])
    a = g.frame_to_grid_affine(pose, (240, 320), 0.005)
    cols, rows = rng.uniform(0, 320, 10), rng.uniform(0, 240, 10)
    gx, gy = g.world_to_pixel(*frame_pixels_to_world(pose, cols, rows, (240, 320), 0.005))
    assert np.allclose(a @ np.vstack([cols, rows, np.ones(10)]), np.vstack([gx, gy]))


def test_frame_to_frame_affine_roundtrip():
    from mapstore.grid import frame_affine_to_rel, frame_to_frame_affine

    sa, sb, ps = (240, 320), (200, 300), 0.0025
    pa, pb = np.array([1.0, 2.0, 0.3]), np.array([1.2, 1.9, 0.45])
    rel = se2_between(pa, pb)
    m = frame_to_frame_affine(rel, sb, sa, ps)
    cols, rows = rng.uniform(0, 300, 10), rng.uniform(0, 200, 10)
    wx, wy = frame_pixels_to_world(pb, cols, rows, sb, ps)
    ca, ra = world_to_frame_pixels(pa, wx, wy, sa, ps)
    assert np.allclose(m @ np.vstack([cols, rows, np.ones(10)]), np.vstack([ca, ra]))
    assert np.allclose(frame_affine_to_rel(m, sb, sa, ps), rel)


def test_coarsened_and_levels_keep_block_centres():
    g = MapGrid(1.0, 2.0, 0.0025, 1001, 603)
    for k in (1, 2, 3):
        lk = g.level(k)
        f = 2**k
        assert lk.width == -(-1001 // f) and lk.height == -(-603 // f)
        # the centre of level-k pixel (3, 5) is the mean of the level-0 block centres
        rows, cols = np.mgrid[3 * f : 4 * f, 5 * f : 6 * f]
        x, y = g.pixel_to_world(cols, rows)
        assert np.allclose(lk.pixel_to_world(5, 3), (x.mean(), y.mean()))
    assert g.coarsened(16).pixel_size == 0.04


def test_extended_keeps_origin_and_refuses_to_grow_backwards():
    g = MapGrid(0.0, 5.0, 0.01, 100, 100)
    e = g.extended(0.5, 2.0, 1.5, 4.0)
    assert (e.x0, e.y0) == (g.x0, g.y0) and e.width == 151 and e.height == 301
    assert g.extended(0.1, 4.5, 0.2, 4.9) == g
    with pytest.raises(ValueError, match="left of or above"):
        g.extended(-0.5, 2.0, 1.0, 4.0)


def test_ome_transformations_map_elements_to_metres():
    g = MapGrid(1.5, 2.0, 0.5, 10, 10)
    scale, trans = (t[t["type"]] for t in g.ome_transformations())
    row, col = 3, 4
    ome_y, ome_x = trans[0] + row * scale[0], trans[1] + col * scale[1]
    x, y = g.pixel_to_world(col, row)
    assert np.isclose(ome_x, x) and np.isclose(ome_y, -y)


def test_affine_box_bounds_the_rectangles_corners():
    r = np.random.default_rng(7)
    for _ in range(200):
        a = r.normal(size=(2, 3))
        x0, y0 = r.normal(size=2)
        x1, y1 = x0 + abs(r.normal()), y0 + abs(r.normal())
        c = np.array([[x0, y0, 1.0], [x1, y0, 1.0], [x0, y1, 1.0], [x1, y1, 1.0]]) @ a.T
        want = (c[:, 0].min(), c[:, 1].min(), c[:, 0].max(), c[:, 1].max())
        assert np.allclose(affine_box(a, x0, y0, x1, y1), want, rtol=0, atol=1e-12)


def test_frame_to_grid_affine_maps_the_frame_centre_to_the_pose():
    g = MapGrid(-2.0, 3.0, 0.01, 500, 600)
    pose = np.array([0.37, 1.21, 0.7])
    a = g.frame_to_grid_affine(pose, (240, 320), 0.0025)
    col, row = a @ np.array([159.5, 119.5, 1.0])
    assert (col, row) == pytest.approx(tuple(np.asarray(g.world_to_pixel(0.37, 1.21), float)), abs=1e-9)
    # one frame pixel to the right is 0.0025 m along the vehicle's x, heading 0.7 rad
    d = a[:, 0] * 0.01 / 0.0025
    assert d == pytest.approx([np.cos(0.7), -np.sin(0.7)], abs=1e-12)
