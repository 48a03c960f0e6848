"""Omni camera models (tracker/omnicam.py): round trips, cv2.omnidir, Yagi et al.'s (2005) eq. 3, unwarping."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mapstore.grid import world_to_frame_pixels
from pipeline.config import load_config
from pipeline.simulate.omni import OmniRenderer, camera_from_config, generate_world
from tracker.omnicam import (
    MEI_ROTATION,
    CameraFieldError,
    HyperboloidCamera,
    MeiCamera,
    azimuth_elevation_to_directions,
    birdseye_unwarp,
    camera_from_table,
    panorama_unwarp,
)

HYPER = HyperboloidCamera(a_m=0.0281, b_m=0.0234, f_px=331.0, cx=320.1, cy=239.1, height_m=1.0,
                          rim_radius_px=230.0, hole_radius_px=29.0)
MEI = MeiCamera(xi=0.92, fx=205.0, fy=201.0, cx=318.7, cy=241.2, height_m=0.8, skew=0.4,
                k1=-0.06, k2=0.012, p1=0.0015, p2=-0.001, rim_radius_px=235.0)


def scene_points(n: int = 2000, seed: int = 0) -> np.ndarray:
    """Points around the camera between 60 deg below and 15 deg above the horizon, 0.3..8 m away."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(-60, 15, n))
    return azimuth_elevation_to_directions(az, el) * rng.uniform(0.3, 8.0, n)[:, None]


@pytest.mark.parametrize("cam", [HYPER, MEI], ids=["hyperboloid", "mei"])
def test_round_trips(cam):
    p = scene_points()
    uv = cam.project(p)
    assert np.isfinite(uv).all()
    d = cam.ray(uv)
    np.testing.assert_allclose(d, p / np.linalg.norm(p, axis=1, keepdims=True), atol=1e-10)
    # pixels -> rays -> pixels over the image annulus
    rng = np.random.default_rng(1)
    r, a = rng.uniform(35, 225, 2000), rng.uniform(-np.pi, np.pi, 2000)
    pix = np.stack([cam.cx + r * np.cos(a), cam.cy + r * np.sin(a)], 1)
    np.testing.assert_allclose(cam.project(cam.ray(pix) * 3.0), pix, atol=1e-8)


def test_mei_matches_cv2_omnidir():
    p = scene_points(500)
    rvec, _ = cv2.Rodrigues(MEI_ROTATION)
    ref, _ = cv2.omnidir.projectPoints(p.reshape(-1, 1, 3), rvec, np.zeros(3), MEI.camera_matrix(), MEI.xi,
                                       MEI.distortion())
    np.testing.assert_allclose(MEI.project(p), ref.reshape(-1, 2), atol=1e-8)


def test_hyperboloid_geometry_and_seed_equations():
    p = scene_points(500)
    # the hyperboloid is Mei's model with xi = 2bc/(b^2+c^2), gamma = f a^2/(b^2+c^2)
    np.testing.assert_allclose(HYPER.as_mei().project(p), HYPER.project(p), atol=1e-9)
    # eq. 2: the azimuth is preserved (on screen counter-clockwise, +x up, +y left)
    uv = HYPER.project(p)
    np.testing.assert_allclose(np.arctan2(-(uv[:, 0] - HYPER.cx), -(uv[:, 1] - HYPER.cy)),
                               np.arctan2(p[:, 1], p[:, 0]), atol=1e-9)
    # eq. 3: elevation from the image radius
    el = np.arcsin(p[:, 2] / np.linalg.norm(p, axis=1))
    np.testing.assert_allclose(HYPER.elevation_of_radius(HYPER.radius_px(uv)), el, atol=1e-9)
    # eq. 4: the horizon circle, (b^2 + c^2) sin g = 2 b c with tan g = f / r (g from the image plane)
    b, c = HYPER.b_m, HYPER.c_m
    r_h = float(HYPER.radius_of_elevation(0.0))
    assert math.isclose((b * b + c * c) * math.sin(math.atan2(HYPER.f_px, r_h)), 2 * b * c, rel_tol=1e-12)
    # the mirror point really lies on the hyperboloid and the reflection law holds there
    u = p[:3] / np.linalg.norm(p[:3], axis=1, keepdims=True)
    lam = HYPER.a_m**2 / (b - c * u[:, 2])
    m = u * lam[:, None] + np.array([0, 0, c])  # mirror coordinates (centre at the origin)
    np.testing.assert_allclose((m[:, 0] ** 2 + m[:, 1] ** 2) / HYPER.a_m**2 - m[:, 2] ** 2 / b**2, -1.0, atol=1e-9)
    normal = np.stack([2 * m[:, 0] / HYPER.a_m**2, 2 * m[:, 1] / HYPER.a_m**2, -2 * m[:, 2] / b**2], 1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    to_oc = np.array([0, 0, -c]) - m
    to_oc /= np.linalg.norm(to_oc, axis=1, keepdims=True)
    incoming = -u  # travelling from the scene point towards O_M
    reflected = incoming - 2 * (incoming * normal).sum(1, keepdims=True) * normal
    np.testing.assert_allclose(reflected, to_oc, atol=1e-9)
    # nothing above the asymptote
    assert np.isnan(HYPER.project(np.array([[1.0, 0.0, 1.0]]))).all()


def test_camera_from_table():
    t = HYPER.to_toml_dict()
    assert camera_from_table(t) == HYPER
    assert camera_from_table(MEI.to_toml_dict()) == MEI
    bad = {k: v for k, v in t.items() if k != "a_m"}
    with pytest.raises(CameraFieldError) as e:
        camera_from_table(bad)
    assert e.value.field == "a_m" and "missing" in e.value.what
    with pytest.raises(CameraFieldError, match="mirror"):
        camera_from_table({**t, "mirror": "parabolic"})
    with pytest.raises(CameraFieldError) as e:
        camera_from_table({**t, "k9": 1.0})
    assert e.value.field == "k9"
    with pytest.raises(CameraFieldError) as e:
        camera_from_table({**t, "f_px": -3.0})
    assert e.value.field == "f_px"


@pytest.mark.parametrize("spd", [1.0, 2.0])
def test_panorama_column_of_known_azimuth(spd):
    pan = panorama_unwarp(HYPER, samples_per_degree=spd, elevation_range_deg=(-20, 10))
    assert pan.unwarp.shape == (int(30 * spd) + 1, int(360 * spd))
    assert pan.horizon_row == int(10 * spd)
    img = np.zeros((480, 640), np.float32)
    for az_deg in (0.0, 73.0, 181.5, 300.0):
        img[:] = 0
        u, v = HYPER.project(azimuth_elevation_to_directions(math.radians(az_deg), 0.0) * 4.0)
        # a small bright blob at the projected pixel
        rows, cols = np.mgrid[0:480, 0:640]
        img[:] = np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * 1.5**2))
        out = pan.apply(img)
        r, c = np.unravel_index(np.argmax(out), out.shape)
        assert r == pan.horizon_row
        assert abs(c - az_deg * spd) <= 0.6 * spd + 0.5, (c, az_deg)
        assert math.isclose(float(pan.column_of_azimuth(math.radians(az_deg))), az_deg * spd, abs_tol=1e-9)
    assert pan.unwarp.valid[pan.horizon_row].all()


def test_birdseye_of_a_simulated_floor_point():
    """The simulator renders a mark on the floor; the bird's-eye view puts it where the grid says."""
    cfg = load_config()
    om = cfg["simulate"]["omni"]
    om["world"]["objects"] = 0
    cam = camera_from_config(om["camera"])
    route_xy = np.array([[1.0, 1.0], [5.0, 3.0]])
    world = generate_world(np.random.default_rng(0), np.random.default_rng(1), cfg, (6.0, 4.0), route_xy, 0.5, 0)
    # paint a smooth bright mark on a flat patch of the floor at (X, Y)
    X, Y = 3.37, 2.21
    c0, r0, w, h = world.regions["floor"]
    grid = world.floor_grid()
    rows, cols = np.mgrid[0:h, 0:w]
    gc, gr = grid.world_to_pixel(X, Y)
    d2 = (cols - gc) ** 2 + (rows - gr) ** 2
    floor = world.atlas[r0 : r0 + h, c0 : c0 + w]
    floor[d2 < 40**2] = 90.0
    floor += (150.0 * np.exp(-d2 / (2 * 2.0**2))).astype(np.float32)
    renderer = OmniRenderer(cam, (480, 640), world, cam.height_m, False, om)
    pose = np.array([2.9, 1.8, 0.6])
    img = renderer.clean(pose)
    s = 0.01
    be = birdseye_unwarp(cam, s, (3.0, 3.0))
    view = be.apply(img, exact=True)
    assert be.valid.sum() > 0.3 * be.valid.size
    want_c, want_r = world_to_frame_pixels(pose, X, Y, be.shape, s)
    # the peak near the prediction (walls and windows appear elsewhere in a floor view)
    r0_, c0_ = int(round(want_r)) - 25, int(round(want_c)) - 25
    crop = view[r0_ : r0_ + 51, c0_ : c0_ + 51]
    r, c = np.unravel_index(np.argmax(crop), crop.shape)
    r, c = r + r0_, c + c0_
    assert 10 < r - r0_ < 40 and 10 < c - c0_ < 40
    win = view[r - 3 : r + 4, c - 3 : c + 4] - 90.0
    rr, cc = np.mgrid[r - 3 : r + 4, c - 3 : c + 4]
    got_c, got_r = (cc * win).sum() / win.sum(), (rr * win).sum() / win.sum()
    assert math.hypot(got_c - want_c, got_r - want_r) < 0.3, (got_c, got_r, want_c, want_r)
