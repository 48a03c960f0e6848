"""Stage ingest: rectification, flat field, odometry interpolation, quality, frames store."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import smooth_texture, write_small_log
from mapstore.grid import MapGrid, interpolate_trajectory
from pipeline.stages.build import run_build
from pipeline.camera import raw_pixel_ground_offsets, vignetting_gain
from pipeline.config import load_config
from pipeline.drivelog import CameraSpec, read_drive_log, write_drive_log
from pipeline.framestore import FrameStore
from pipeline.images import write_grey
from pipeline.quality import isotropy, texture_score_map


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def render_log(path: Path, camera: CameraSpec, world: np.ndarray, grid: MapGrid, poses: np.ndarray, *, gain=None) -> None:
    """Render raw frames of ``world`` seen by ``camera`` at ``poses`` (no noise)."""
    (path / "images").mkdir(parents=True)
    shape = (240, 320)
    xv, yv = raw_pixel_ground_offsets(camera, shape)
    names = []
    for i, p in enumerate(poses):
        c, s = np.cos(p[2]), np.sin(p[2])
        gx, gy = grid.world_to_pixel(p[0] + c * xv - s * yv, p[1] + s * xv + c * yv)
        raw = cv2.remap(world, gx.astype(np.float32), gy.astype(np.float32), cv2.INTER_CUBIC)
        if gain is not None:
            raw = raw * gain
        names.append(f"images/{i:06d}.png")
        write_grey(path / names[-1], raw, bits=16)
    t = 0.1 * np.arange(1, len(poses) + 1)
    odo = np.column_stack([np.r_[0.0, t, t[-1] + 0.1], np.vstack([poses[:1], poses, poses[-1:]])])
    write_drive_log(path, camera, t, names, odo, ground_truth=np.column_stack([t, poses]))


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(7)
    grid = MapGrid.covering(-0.6, -0.6, 0.6, 0.6, 0.0025)
    return smooth_texture(rng, grid.shape), grid


CAM = CameraSpec(fx=200.0, fy=201.0, cx=161.2, cy=118.7, height_m=0.5, k1=-0.15, k2=0.02, p1=0.0005, p2=-0.0003)


def test_rectified_frame_matches_world_at_true_pose(tmp_path: Path, world):
    tex, grid = world
    poses = np.array([[0.02, -0.01, 0.3], [-0.05, 0.04, -1.2]])
    render_log(tmp_path / "log", CAM, tex, grid, poses)
    cfg = load_config()
    cfg["ingest"]["flatfield"]["mode"] = "none"
    run_build([tmp_path / "log"], tmp_path / "w", cfg, until="ingest", quiet=True)
    lf = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0]
    valid = lf.valid
    assert valid.mean() > 0.85
    for i, p in enumerate(poses):
        img = lf.image(i)
        a = grid.frame_to_grid_affine(p, img.shape, 0.0025)
        ref = cv2.warpAffine(tex, a, (img.shape[1], img.shape[0]), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
        assert ncc(img[valid], ref[valid]) >= 0.98
        assert np.abs(img[valid] - ref[valid]).mean() < 2.0  # grey levels


def test_calibrated_vignetting_is_removed(tmp_path: Path, world):
    tex, grid = world
    cam = CameraSpec(**{**CAM.__dict__, "vignetting": (-0.3, 0.05)})
    render_log(tmp_path / "log", cam, tex, grid, np.array([[0.0, 0.0, 0.0]]), gain=vignetting_gain(cam, (240, 320)))
    cfg = load_config()
    run_build([tmp_path / "log"], tmp_path / "w", cfg, until="ingest", quiet=True)
    lf = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0]
    img, valid = lf.image(0), lf.valid
    ref = cv2.warpAffine(tex, grid.frame_to_grid_affine(np.zeros(3), img.shape, 0.0025), img.shape[::-1],
                         flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    # Corners match the world's brightness again (vignetting darkened them by ~15 %).
    assert abs(img[valid].mean() - ref[valid].mean()) < 1.0


def test_vignetting_estimated_from_frames(tmp_path: Path):
    rng = np.random.default_rng(3)
    cam = CameraSpec(pixel_size_m=0.0025)
    true = CameraSpec(pixel_size_m=0.0025, vignetting=(-0.25, 0.0))
    gain = vignetting_gain(true, (96, 128))
    (tmp_path / "log" / "images").mkdir(parents=True)
    names = []
    for i in range(60):
        names.append(f"images/{i:06d}.png")
        write_grey(tmp_path / "log" / names[-1], smooth_texture(rng, (96, 128)) * gain)
    t = 0.1 * np.arange(1, 61)
    write_drive_log(tmp_path / "log", cam, t, names, np.column_stack([np.r_[0, t], np.zeros((61, 3))]))
    rep = run_build([tmp_path / "log"], tmp_path / "w", load_config(), until="ingest", quiet=True)
    ff = rep["ingest"]["logs"][0]["flat_field"]
    assert ff["source"] == "estimated"
    v1, v2 = ff["vignetting"]
    r2 = np.array([0.25, 0.5, 1.0])
    assert np.allclose(1 + v1 * r2 + v2 * r2**2, 1 - 0.25 * r2, atol=0.02)


def test_prior_is_interpolated_odometry(tmp_path: Path, small_log: Path):
    rep = run_build([small_log], tmp_path / "w", load_config(), until="ingest", quiet=True)
    lg = read_drive_log(small_log)
    lf = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0]
    assert np.allclose(lf.prior, interpolate_trajectory(lg.odometry, lg.frame_t))
    assert np.allclose(lf.t, lg.frame_t)
    assert rep["ingest"]["frames_accepted"] == 8
    assert lf.attrs["log_id"] == "log"


def test_16bit_equals_8bit(tmp_path: Path):
    a = write_small_log(tmp_path / "a", bits=8, seed=5)
    b = write_small_log(tmp_path / "b", bits=16, seed=5)
    cfg = load_config()
    run_build([a], tmp_path / "wa", cfg, until="ingest", quiet=True)
    run_build([b], tmp_path / "wb", cfg, until="ingest", quiet=True)
    fa = FrameStore(tmp_path / "wa" / "ingest" / "frames.zarr").logs[0]
    fb = FrameStore(tmp_path / "wb" / "ingest" / "frames.zarr").logs[0]
    assert np.abs(fa.image(2) - fb.image(2))[fa.valid].max() < 1.0  # 8-bit quantization only


def _quality_log(tmp_path: Path, spoil) -> dict:
    log_dir = write_small_log(tmp_path / "log", n_frames=6, size=(128, 96))
    img_path = log_dir / "images" / "000002.png"
    from pipeline.images import read_grey

    write_grey(img_path, spoil(read_grey(img_path)))
    rep = run_build([log_dir], tmp_path / "w", load_config(), until="ingest", quiet=True)
    return rep["ingest"]


@pytest.mark.parametrize(
    "spoil,reason",
    [
        (lambda im: cv2.blur(im, (15, 1)), "blurred"),
        (lambda im: np.minimum(im * 3.0, 255.0), "overexposed"),
        (lambda im: np.maximum(im - 150.0, 0.0), "underexposed"),
    ],
    ids=["motion-blur", "overexposed", "underexposed"],
)
def test_quality_rejections(tmp_path: Path, spoil, reason: str):
    ing = _quality_log(tmp_path, spoil)
    assert ing["frames_accepted"] == 5 and ing["frames_placed_by_prior"] == 0
    (rej,) = ing["rejected"]
    assert rej["frame"] == 2 and rej["reason"].startswith(reason), rej


def test_low_texture_frame_is_kept_placed_by_prior(tmp_path: Path):
    """A frame without texture is stored, flagged not registrable, and listed with its reason."""
    ing = _quality_log(tmp_path, lambda im: np.full_like(im, 120.0) + 0.3 * (im - im.mean()) / im.std())
    assert ing["frames_accepted"] == 6 and ing["frames_registrable"] == 5 and ing["rejected"] == []
    (flag,) = ing["placed_by_prior"]
    assert flag["frame"] == 2 and flag["reason"].startswith("low texture"), flag
    assert flag["image"] == "images/000002.png" and flag["log"] == "log"
    lf = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0]
    assert lf.registrable.tolist() == [True, True, False, True, True, True]
    assert "registrable" in lf.quality_columns
    manifest = json.loads((tmp_path / "w" / "ingest" / "manifest.json").read_text())
    assert manifest["counts"]["ingest"]["placed_by_prior"] == [flag]


def test_texture_score_matches_definition():
    rng = np.random.default_rng(0)
    img = rng.normal(128, 20, (64, 64)).astype(np.float32)
    tex = texture_score_map(img, window=17, sigma=0.0)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8
    direct = (gx**2 + gy**2)[32 - 8 : 32 + 9, 32 - 8 : 32 + 9].mean()
    assert tex[32, 32] == pytest.approx(direct, rel=1e-4)
    flat = np.full((64, 64), 100.0, np.float32)
    assert texture_score_map(flat).max() == pytest.approx(0.0, abs=1e-6)


def test_isotropy_orders_motion_blur_and_ignores_noise():
    rng = np.random.default_rng(0)
    img = smooth_texture(rng, (240, 320))
    valid = np.ones_like(img, bool)
    s = [isotropy(cv2.blur(img, (k, 1)), valid) for k in (1, 5, 9)]
    assert s[0] > 0.85 and s[0] > s[1] > s[2]
    noisy = img + rng.normal(0, 5, img.shape).astype(np.float32)
    assert abs(isotropy(noisy, valid) - s[0]) < 0.02


def test_rerun_skips_and_config_change_reruns(tmp_path: Path, small_log: Path):
    cfg = load_config()
    r1 = run_build([small_log], tmp_path / "w", cfg, until="ingest", quiet=True)
    assert r1["stages"]["ingest"]["skipped"] is False
    r2 = run_build([small_log], tmp_path / "w", cfg, until="ingest", quiet=True)
    assert r2["stages"]["ingest"]["skipped"] is True
    assert r2["ingest"]["frames_accepted"] == r1["ingest"]["frames_accepted"]
    cfg["ingest"]["quality"]["min_isotropy"] = 0.3
    r3 = run_build([small_log], tmp_path / "w", cfg, until="ingest", quiet=True)
    assert r3["stages"]["ingest"]["skipped"] is False
    # Changing an input image also reruns.
    write_grey(small_log / "images" / "000001.png", smooth_texture(np.random.default_rng(9), (48, 64)))
    r4 = run_build([small_log], tmp_path / "w", cfg, until="ingest", quiet=True)
    assert r4["stages"]["ingest"]["skipped"] is False


def test_killed_stage_leaves_nothing(tmp_path: Path, small_log: Path, monkeypatch):
    import pipeline.stages.ingest as ingest

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(ingest.FrameAssessor, "__call__", boom)
    with pytest.raises(KeyboardInterrupt):
        run_build([small_log], tmp_path / "w", load_config(), until="ingest", quiet=True)
    assert not (tmp_path / "w" / "ingest").exists()
    assert not list((tmp_path / "w").glob(".tmp-*"))


def test_two_logs_in_one_store(tmp_path: Path):
    a = write_small_log(tmp_path / "day1", seed=1)
    b = write_small_log(tmp_path / "day2", seed=2, size=(80, 60))
    rep = run_build([a, b], tmp_path / "w", load_config(), until="ingest", quiet=True)
    fs = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr")
    assert [lf.attrs["log_id"] for lf in fs.logs] == ["day1", "day2"]
    assert fs.logs[1].image(0).shape == (60, 80)
    assert rep["ingest"]["frames_total"] == 16
    json.dumps(rep)  # the report is JSON-serialisable


def test_per_frame_height_rectifies_to_map_scale(tmp_path: Path, world):
    """Frames taken from different heights come out at the same ground scale."""
    tex, grid = world
    poses = np.array([[0.0, 0.0, 0.2], [0.01, 0.0, 0.2]])
    heights = np.array([0.45, 0.55])
    (tmp_path / "log" / "images").mkdir(parents=True)
    names = []
    for i, (p, h) in enumerate(zip(poses, heights)):
        cam_i = CameraSpec(**{**CAM.__dict__, "height_m": float(h)})
        xv, yv = raw_pixel_ground_offsets(cam_i, (240, 320))
        c, s = np.cos(p[2]), np.sin(p[2])
        gx, gy = grid.world_to_pixel(p[0] + c * xv - s * yv, p[1] + s * xv + c * yv)
        names.append(f"images/{i:06d}.png")
        write_grey(tmp_path / "log" / names[-1], cv2.remap(tex, gx.astype(np.float32), gy.astype(np.float32), cv2.INTER_CUBIC), bits=16)
    t = np.array([0.1, 0.2])
    write_drive_log(tmp_path / "log", CAM, t, names, np.column_stack([[0.0, 0.1, 0.2, 0.3], np.zeros((4, 3))]))
    frames_csv = tmp_path / "log" / "frames.csv"
    lines = frames_csv.read_text().splitlines()
    frames_csv.write_text("t,image,height_m\n" + "\n".join(f"{ln},{h}" for ln, h in zip(lines[1:], heights)) + "\n")
    assert np.allclose(read_drive_log(tmp_path / "log").frame_heights, heights)
    cfg = load_config()
    cfg["ingest"]["flatfield"]["mode"] = "none"
    run_build([tmp_path / "log"], tmp_path / "w", cfg, until="ingest", quiet=True)
    lf = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0]
    for i, p in enumerate(poses):
        img = lf.image(i)
        ref = cv2.warpAffine(tex, grid.frame_to_grid_affine(p, img.shape, 0.0025), img.shape[::-1],
                             flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
        assert ncc(img[lf.valid], ref[lf.valid]) >= 0.98


def test_frames_writer_takes_stored_uint16_frames_as_quantized_ones(tmp_path):
    """Ingest quantizes in its workers and hands the writer uint16 frames: the store holds
    the same values as when the writer quantizes float frames itself."""
    import numpy as np
    import zarr

    from pipeline.framestore import LogFramesWriter, create_store, quantize

    rng = np.random.default_rng(3)
    frames = [(rng.random((24, 32)) * 255).astype(np.float32) for _ in range(5)]
    valid = np.ones((24, 32), bool)
    out = []
    for k, as_stored in enumerate((False, True)):
        root = create_store(tmp_path / f"s{k}.zarr", 0.001)
        w = LogFramesWriter(root, 0, {"log_id": "x"}, valid, shard_frames=2)
        for i, f in enumerate(frames):
            w.append(quantize(f) if as_stored else f, float(i), np.zeros(3), i, (0.0,) * 6)
        assert w.close() == 5
        out.append(zarr.open_group(str(tmp_path / f"s{k}.zarr"), mode="r")["log000/images"][...])
    assert out[0].dtype == np.uint16 and np.array_equal(out[0], out[1])
    assert np.array_equal(out[0][3], quantize(frames[3]))
