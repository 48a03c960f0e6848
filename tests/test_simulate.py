"""The floor simulator: determinism, routes, odometry, rendering, worlds, changes, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from mapstore.grid import MapGrid, se2_between, se2_compose
from pipeline.camera import Rectifier, raw_pixel_ground_offsets
from pipeline.cli import cli
from pipeline.config import load_config
from pipeline.drivelog import read_drive_log, read_pose_csv
from pipeline.images import read_grey
from pipeline.simulate.floor import FrameRenderer, camera_from_config
from pipeline.simulate.odometry import odometry_error, simulate_odometry
from pipeline.simulate.route import ROUTES, make_route
from pipeline.simulate.texture import read_float_tiff

REAL_TEXTURE = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "lscm_speckle_3x4"
    / "x100_epr-jerem_10pct_001_A001_I.tif"
)
SMALL = ["--frame-size", "160x120", "--quiet"]


def run(args: list[str]):
    return CliRunner().invoke(cli, ["simulate", "floor", *args])


def simulate(out: Path, *args: str, area: str | None = "1x1") -> Path:
    """A small log; ``area=None`` leaves --area out (e.g. to take it from --world)."""
    r = run([str(out), *SMALL, *(["--area", area] if area else []), *args])
    assert r.exit_code == 0, r.output
    return out


def world(log: Path) -> tuple[np.ndarray, MapGrid]:
    grid = MapGrid.from_attrs(json.loads((log / "world" / "grid.json").read_text()))
    return read_float_tiff(log / "world" / "texture.tif"), grid


def files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def write_config(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


CLEAN = """
[simulate.floor.camera]
vignetting = [0.0, 0.0]
[simulate.floor.motion]
exposure_s = 0.0
[simulate.floor.sensor]
noise_sigma = 0.0
exposure_drift = 0.0
"""


# --- the log and determinism ---------------------------------------------------------------


def test_log_is_valid_and_reproducible(tmp_path):
    a = simulate(tmp_path / "a", "--seed", "3")
    b = simulate(tmp_path / "b", "--seed", "3")
    c = simulate(tmp_path / "c", "--seed", "4")
    log = read_drive_log(a)
    assert len(log.frame_images) >= 10
    assert not log.camera.rectified and log.camera.k1 != 0 and log.camera.vignetting is not None
    assert log.meta["simulation"]["seed"] == 3
    gt = read_pose_csv(a / "ground_truth.csv")
    np.testing.assert_array_equal(gt[:, 0], log.frame_t)
    assert log.odometry[0, 0] <= log.frame_t[0] and log.odometry[-1, 0] >= log.frame_t[-1]
    fa, fb, fc = files(a), files(b), files(c)
    fa.pop("drive.toml"), fb.pop("drive.toml")  # carries the log id (the directory name)
    assert fa.keys() == fb.keys()
    assert all(fa[k] == fb[k] for k in fa), [k for k in fa if fa[k] != fb[k]]
    assert fa["images/000000.png"] != fc["images/000000.png"]
    assert fa["world/texture.tif"] != fc["world/texture.tif"]
    tex, grid = world(a)
    assert tex.shape == grid.shape and tex.dtype == np.float32
    assert 110 < tex.mean() < 145 and 20 < tex.std() < 45
    img = read_grey(a / log.frame_images[0])
    assert img.shape == (120, 160)


def test_sixteen_bit_frames_and_illumination(tmp_path):
    cfg = write_config(tmp_path / "c.toml", "[simulate.floor]\nimage_bits = 16\n")
    a = simulate(tmp_path / "a", "--seed", "1", "--config", str(cfg))
    b = simulate(tmp_path / "b", "--seed", "1", "--illumination", "0.5")
    import OpenImageIO as oiio

    assert oiio.ImageBuf(str(a / "images/000000.png")).spec().format == oiio.UINT16
    ia, ib = read_grey(a / "images/000003.png"), read_grey(b / "images/000003.png")
    assert ib.mean() == pytest.approx(0.5 * ia.mean(), rel=0.05)
    read_drive_log(a)


# --- routes -------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ROUTES)
def test_routes_stay_inside_with_even_spacing(kind):
    cfg = load_config()["simulate"]["floor"]
    area = (2.0, 1.5)
    route = make_route(kind, area, np.random.default_rng(0), cfg["routes"], 0.6)
    spacing = cfg["motion"]["frame_spacing_m"]
    s = route.samples(spacing)
    p = route.at(s)
    assert (p[:, 0] >= 0).all() and (p[:, 0] <= area[0]).all()
    assert (p[:, 1] >= 0).all() and (p[:, 1] <= area[1]).all()
    step = np.hypot(*np.diff(p[:, :2], axis=0).T)
    assert step.max() <= spacing + 1e-6 and step.min() > 0.8 * spacing
    # heading along the direction of travel
    d = np.diff(route.at(np.concatenate([s[:-1, None], s[:-1, None] + 0.01], axis=1))[..., :2], axis=1)[:, 0]
    along = np.arctan2(d[:, 1], d[:, 0])
    err = np.angle(np.exp(1j * (along - p[:-1, 2])))
    assert np.abs(err).max() < 0.05


def test_default_lawnmower_frame_count():
    cfg = load_config()["simulate"]["floor"]
    route = make_route("lawnmower", (5.0, 5.0), np.random.default_rng(0), cfg["routes"], 240 * 0.0025)
    n = len(route.samples(cfg["motion"]["frame_spacing_m"]))
    assert 550 <= n <= 650
    lanes = np.unique(np.round(route.y[np.abs(np.sin(route.theta)) < 1e-6], 6))
    assert len(lanes) >= 10
    assert np.diff(lanes).max() <= 0.6 * (1 - cfg["routes"]["lane_overlap"]) + 1e-6  # adjacent lanes overlap


# --- odometry -----------------------------------------------------------------------------


def test_odometry_drift_scales_with_alpha():
    cfg = load_config()["simulate"]["floor"]
    route = make_route("lawnmower", (5.0, 5.0), np.random.default_rng(0), cfg["routes"], 0.6)
    s = np.arange(0.0, route.length, 0.02)
    gt = route.at(s)
    alpha = 0.01
    ratios = []
    for seed in range(40):
        odo = simulate_odometry(gt, alpha, np.random.default_rng(seed), cfg["odometry"])
        err = odometry_error(odo, gt, cfg["odometry"]["frame"])
        ratios.append(err[-1] / (alpha * s[-1]))
    med = float(np.median(ratios))
    assert 0.2 < med < 5.0, med
    # ten times the drift, about ten times the error
    odo10 = [odometry_error(simulate_odometry(gt, 10 * alpha, np.random.default_rng(k), cfg["odometry"]), gt,
                            "origin")[-1] for k in range(40)]
    assert 4 < np.median(odo10) / (med * alpha * s[-1]) < 25


def test_zero_drift_odometry_equals_ground_truth(tmp_path):
    log = simulate(tmp_path / "a", "--odometry-drift", "0", "--route", "loop")
    odo = read_pose_csv(log / "odometry.csv")
    gt = read_pose_csv(log / "ground_truth.csv")
    # frame times fall on the odometry sampling lattice here (0.1 s vs 50 Hz)
    idx = np.searchsorted(odo[:, 0], gt[:, 0] - 1e-9)
    np.testing.assert_allclose(odo[idx, 0], gt[:, 0], atol=1e-9)
    first = np.searchsorted(odo[:, 0], gt[0, 0] - 1e-9)
    assert first == 0
    # odometry frame "world" (the default): the odometry is the ground truth itself
    np.testing.assert_allclose(odo[idx, 1:3], gt[:, 1:3], atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (odo[idx, 3] - gt[:, 3]))), 0, atol=1e-9)
    # odometry frame "origin": the ground truth relative to its first pose
    cfg = write_config(tmp_path / "origin.toml", '[simulate.floor.odometry]\nframe = "origin"\n')
    log = simulate(tmp_path / "b", "--odometry-drift", "0", "--route", "loop", "--config", str(cfg))
    odo = read_pose_csv(log / "odometry.csv")
    rel = se2_between(gt[0, 1:], gt[:, 1:])
    np.testing.assert_allclose(odo[idx, 1:3], rel[:, :2], atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (odo[idx, 3] - rel[:, 2]))), 0, atol=1e-9)


# --- rendering ----------------------------------------------------------------------------


def test_raw_frame_is_the_world_seen_through_the_camera(tmp_path):
    cfg = write_config(tmp_path / "clean.toml", CLEAN)
    log_dir = simulate(tmp_path / "a", "--config", str(cfg), "--seed", "2", "--route", "random",
                       area="1.5x1.2")
    log = read_drive_log(log_dir)
    tex, grid = world(log_dir)
    gt = read_pose_csv(log_dir / "ground_truth.csv")
    raw = read_grey(log.image_path(0))
    h, w = raw.shape
    # reference: every raw pixel's floor point (shared camera model) through mapstore.grid
    xv, yv = raw_pixel_ground_offsets(log.camera, (h, w))
    for i in (0, len(gt) // 2):
        raw = read_grey(log.image_path(i))
        pts = se2_compose(gt[i, 1:], np.stack([xv, yv, np.zeros_like(xv)], axis=-1))
        col, row = grid.world_to_pixel(pts[..., 0], pts[..., 1])
        ref = cv2.remap(tex, col.astype(np.float32), row.astype(np.float32), cv2.INTER_LINEAR)
        assert ncc(raw, ref) > 0.99
    # independently: ingest's rectifier + the grid's frame affine agree with the world
    rect = Rectifier(log.camera, (h, w), grid.pixel_size, interpolation="cubic")
    i = len(gt) // 2
    frame = rect(read_grey(log.image_path(i)))
    a = grid.frame_to_grid_affine(gt[i, 1:], frame.shape, grid.pixel_size)
    ref = cv2.warpAffine(tex, a, frame.shape[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    assert ncc(frame[rect.valid], ref[rect.valid]) > 0.98


def test_renderer_effects():
    cfg = load_config()["simulate"]["floor"]
    cam = camera_from_config(cfg["camera"], (64, 48), 0.0025)
    grid = MapGrid.covering(-0.2, -0.2, 0.2, 0.2, 0.0025)
    tex = np.full(grid.shape, 100.0, np.float32)
    r = FrameRenderer(cam, (48, 64), tex, grid, (-0.3, 0.0))
    pose = np.zeros((1, 3))
    img = r.render(pose, 1.0, 0.0, np.random.default_rng(0)).astype(float)
    assert img[24, 32] == 100 and img[0, 0] < img[24, 32]  # vignetting darkens the corners
    noisy = r.render(pose, 1.0, 5.0, np.random.default_rng(0)).astype(float)
    assert 4.0 < (noisy - img).std() < 6.0


# --- worlds and changes -------------------------------------------------------------------


def test_world_reuse_and_changes(tmp_path):
    day1 = simulate(tmp_path / "day1", "--seed", "1", area="2x1")
    same = simulate(tmp_path / "same", "--world", str(day1), "--seed", "7", "--route", "loop", area=None)
    t1, g1 = world(day1)
    ts, gs = world(same)
    assert gs == g1 and np.array_equal(ts, t1)
    assert json.loads((same / "world" / "world.json").read_text())["area_m"] == [2.0, 1.0]
    assert read_pose_csv(same / "ground_truth.csv")[:, 1].max() > 1.0  # the area came along
    day2 = simulate(tmp_path / "day2", "--world", str(day1), "--seed", "8", "--changes", "4", area=None)
    t2, g2 = world(day2)
    assert g2 == g1
    mask = read_grey(day2 / "world" / "changes.png") > 127
    changes = json.loads((day2 / "world" / "changes.json").read_text())
    assert len(changes) == 4 and mask.any()
    assert {c["kind"] for c in changes} <= {"stain", "repaint", "marking"}
    assert sum(c["area_m2"] for c in changes) == pytest.approx(mask.sum() * g1.pixel_size**2, rel=0.01)
    # identical outside the changes' boxes
    inside_boxes = np.zeros(g1.shape, bool)
    for c in changes:
        x0, y0, x1, y1 = c["bbox_m"]
        c0, r0 = g1.world_to_pixel(x0, y1)
        c1, r1 = g1.world_to_pixel(x1, y0)
        inside_boxes[max(0, int(np.floor(r0))): int(np.ceil(r1)) + 1, max(0, int(np.floor(c0))): int(np.ceil(c1)) + 1] = True
    assert np.array_equal(t2[~inside_boxes], t1[~inside_boxes])
    # the texture differs where the mask says so
    diff = np.abs(t2 - t1)
    near = cv2.dilate(mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    big = diff > 5.0
    assert big[near].sum() >= 0.99 * big.sum()
    assert diff[mask].mean() > 10.0
    read_drive_log(day2)


def test_a_world_is_read_back_within_its_own_grid_not_the_log_image_caps(tmp_path, monkeypatch):
    """A reused world's texture is bounded by its grid (float32 pixels + 1 MiB), so a world
    larger than the drive-log image caps (a 40 x 40 m world is ~1 GB) is read back; a file
    larger than its grid says is refused, naming the file, before decoding."""
    import pipeline.images as images
    from pipeline.errors import BadInput
    from pipeline.simulate.texture import write_float_tiff

    tex = np.random.default_rng(0).random((60, 80)).astype(np.float32)
    path = tmp_path / "texture.tif"
    write_float_tiff(path, tex)
    monkeypatch.setattr(images, "DEFAULT_LIMITS", images.ImageLimits(max_pixels=100, max_bytes=1000))
    with pytest.raises(BadInput, match="max_image_bytes"):
        read_float_tiff(path)  # the drive-log caps (made tiny here)
    assert np.array_equal(read_float_tiff(path, (60, 80)), tex)
    with pytest.raises(BadInput, match=r"texture.tif.*more than its grid's 20 x 20 px"):
        read_float_tiff(path, (20, 20))


def test_changes_on_a_fresh_world(tmp_path):
    a = simulate(tmp_path / "a", "--seed", "5")
    b = simulate(tmp_path / "b", "--seed", "5", "--changes", "2")
    ta, _ = world(a)
    tb, _ = world(b)
    mask = read_grey(b / "world" / "changes.png") > 127
    assert mask.any() and (np.abs(tb - ta)[mask]).mean() > 10.0
    assert np.array_equal(ta[~cv2.dilate(mask.astype(np.uint8), np.ones((41, 41), np.uint8)).astype(bool)],
                          tb[~cv2.dilate(mask.astype(np.uint8), np.ones((41, 41), np.uint8)).astype(bool)])


@pytest.mark.realdata
def test_photo_texture(tmp_path):
    if not REAL_TEXTURE.exists():
        pytest.skip(f"real image {REAL_TEXTURE} absent (../shared not checked out beside the repo)")
    log = simulate(tmp_path / "a", "--texture", str(REAL_TEXTURE))
    tex, grid = world(log)
    assert abs(tex.mean() - 128) < 5 and 20 < tex.std() < 45
    assert json.loads((log / "world" / "world.json").read_text())["source"].startswith("photo:")
    read_drive_log(log)


# --- command line -------------------------------------------------------------------------


def test_cli_summary_line(tmp_path):
    r = run([str(tmp_path / "a"), "--area", "1x1", "--frame-size", "160x120", "--seed", "1"])
    assert r.exit_code == 0, r.output
    line = r.output.strip().splitlines()[-1]
    assert "frames" in line and " m" in line and " s " in line


@pytest.mark.parametrize(
    "args, culprit",
    [
        (["--area", "5by5"], "--area"),
        (["--area", "0x3"], "--area"),
        (["--frame-size", "320x2.5"], "--frame-size"),
        (["--noise", "-1"], "--noise"),
        (["--odometry-drift", "-0.1"], "--odometry-drift"),
        (["--route", "spiral"], "--route"),
        (["--illumination", "0"], "--illumination"),
        (["--changes", "-2"], "--changes"),
        (["--pixel-size", "0"], "--pixel-size"),
        (["--texture", "/nonexistent/floor.png"], "/nonexistent/floor.png"),
    ],
)
def test_bad_options(tmp_path, args, culprit):
    r = run([str(tmp_path / "out"), "--area", "1x1", "--quiet", *args])
    assert r.exit_code == 2, r.output
    assert culprit in r.output
    assert not (tmp_path / "out").exists()


def test_bad_inputs(tmp_path):
    junk = tmp_path / "junk.png"
    junk.write_text("not an image")
    r = run([str(tmp_path / "o1"), *SMALL, "--area", "1x1", "--texture", str(junk)])
    assert r.exit_code == 2 and str(junk) in r.output
    (tmp_path / "nolog").mkdir()
    r = run([str(tmp_path / "o2"), *SMALL, "--area", "1x1", "--world", str(tmp_path / "nolog")])
    assert r.exit_code == 2 and "nolog" in r.output and "world" in r.output
    full = tmp_path / "full"
    full.mkdir()
    (full / "x").write_text("x")
    r = run([str(full), *SMALL, "--area", "1x1"])
    assert r.exit_code == 2 and str(full) in r.output
    bad_cfg = write_config(tmp_path / "bad.toml", "[simulate.floor]\nno_such_knob = 1\n")
    r = run([str(tmp_path / "o3"), *SMALL, "--config", str(bad_cfg)])
    assert r.exit_code == 2 and "no_such_knob" in r.output
    day1 = simulate(tmp_path / "day1")
    r = run([str(tmp_path / "o4"), *SMALL, "--world", str(day1), "--area", "4x4"])
    assert r.exit_code == 2 and "world" in r.output
    for d in ("o1", "o2", "o3", "o4"):
        assert not (tmp_path / d).exists()
