"""Omni logs at ingest (issue 7): bird's-eye floor frames, valid mask, horizon lines files,
route ids, errors, and a floor map built from an omni log."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mapstore.grid import frame_pixels_to_vehicle, interpolate_trajectory, vehicle_to_frame_pixels
from pipeline.cli import cli
from pipeline.config import load_config
from pipeline.drivelog import read_drive_log
from pipeline.errors import BadInput
from pipeline.framestore import STORE_NAME, FrameStore
from pipeline.images import read_grey
from pipeline.omni_ingest import (
    BirdseyeRectifier,
    OmniFloorParams,
    floor_annulus,
    ground_pixel_size,
    horizon_sampler,
    read_horizons,
)
from pipeline.simulate.omni import camera_from_config
from tracker.omnicam import HyperboloidCamera

CFG = load_config()
CAMERA = camera_from_config(CFG["simulate"]["omni"]["camera"])  # 640 x 480, 1 m, the simulator's
PARAMS = OmniFloorParams.from_config(CFG["omni"])
RAW = (480, 640)


def _floor_image(camera: HyperboloidCamera, shape: tuple[int, int], pattern) -> np.ndarray:
    """A raw omni image of a floor whose grey level at vehicle (xv, yv) metres is ``pattern``."""
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    d = camera.ray(np.stack([cols, rows], -1))
    with np.errstate(invalid="ignore", divide="ignore"):
        t = -camera.height_m / d[..., 2]
    xv, yv = t * d[..., 0], t * d[..., 1]
    img = np.where((d[..., 2] < 0) & np.isfinite(xv), pattern(np.nan_to_num(xv), np.nan_to_num(yv)), 0.0)
    return img.astype(np.float32)


def test_birdseye_geometry_known_floor_point():
    """A floor spot at vehicle (0.62, -0.31) m lands at its grid-convention pixel (+-0.05 px)."""
    s = 0.01
    rect = BirdseyeRectifier(CAMERA, RAW, s, PARAMS, interpolation="lanczos4", erode_px=2)
    x0, y0, sigma = 0.62, -0.31, 0.04
    raw = _floor_image(CAMERA, RAW, lambda x, y: 50 + 150 * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * sigma**2)))
    bird = rect(rect.correct(raw))
    assert rect.out_shape[0] == rect.out_shape[1] and rect.out_shape[0] % 2 == 1
    c_exp, r_exp = vehicle_to_frame_pixels(x0, y0, rect.out_shape, s)
    r0, c0 = int(round(r_exp)), int(round(c_exp))
    win = bird[r0 - 8 : r0 + 9, c0 - 8 : c0 + 9] - 50.0
    assert rect.valid[r0 - 8 : r0 + 9, c0 - 8 : c0 + 9].all()
    rr, cc = np.mgrid[r0 - 8 : r0 + 9, c0 - 8 : c0 + 9]
    c_got, r_got = (win * cc).sum() / win.sum(), (win * rr).sum() / win.sum()
    assert abs(c_got - c_exp) < 0.05 and abs(r_got - r_exp) < 0.05, (c_got, r_got, c_exp, r_exp)
    # and everywhere: the bird's-eye frame is the floor pattern in the grid convention
    hh, ww = rect.out_shape
    rows, cols = np.mgrid[0:hh, 0:ww].astype(np.float64)
    xv, yv = frame_pixels_to_vehicle(cols, rows, rect.out_shape, s)
    truth = 50 + 150 * np.exp(-((xv - x0) ** 2 + (yv - y0) ** 2) / (2 * sigma**2))
    assert np.abs(bird - truth)[rect.valid].max() < 3.0


def test_valid_mask_is_the_floor_annulus():
    s = 0.01
    rect = BirdseyeRectifier(CAMERA, RAW, s, PARAMS, erode_px=2)
    a = rect.annulus
    # inner edge: outside the camera's reflection (hole 28.8 px = 0.41 m of floor) plus the margin
    hole_ground = 1.0 * math.tan(math.pi / 2 + float(CAMERA.elevation_of_radius(CAMERA.hole_radius_px)))
    assert hole_ground < a.inner_m < hole_ground + 0.1
    uv = CAMERA.project(np.array([a.inner_m, 0.0, -1.0]))
    assert CAMERA.radius_px(uv) >= CAMERA.hole_radius_px + PARAMS.hole_margin_px - 0.5
    assert a.outer_m == pytest.approx(PARAMS.outer_radius_m, abs=0.01)
    h, w = rect.out_shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    xv, yv = frame_pixels_to_vehicle(cols, rows, rect.out_shape, s)
    rho = np.hypot(xv, yv)
    assert (rho[rect.valid] >= a.inner_m - 1e-9).all() and (rho[rect.valid] <= a.outer_m + 1e-9).all()
    ring = (rho >= a.inner_m + 0.01) & (rho <= a.outer_m - 0.01)
    assert rect.valid[ring].all()  # the whole annulus, no holes (the image sees all of it)
    assert not rect.valid[0].any() and not rect.valid[h // 2, w // 2]
    # the raw pixels seeing that annulus: an image ring around the axis
    r_raw = CAMERA.radius_px(np.stack(np.mgrid[0:480, 0:640][::-1], -1).astype(float))[rect.raw_floor]
    assert r_raw.min() > CAMERA.hole_radius_px and r_raw.max() < CAMERA.rim_radius_px
    # the outer radius shrinks where the radial ground pixel grows past max_pixel_ratio x finest
    wide = floor_annulus(CAMERA, s, dataclasses.replace(PARAMS, outer_radius_m=3.0))
    assert wide.limited_by == "resolution" and 1.0 < wide.outer_m < 1.3
    radial, _ = ground_pixel_size(CAMERA, np.array([wide.outer_m]))
    assert radial[0] == pytest.approx(PARAMS.max_pixel_ratio * wide.finest_m, rel=0.03)
    with pytest.raises(ValueError, match=r"\[omni\] outer_radius_m: -1.0 is out of range; allowed: x > 0"):
        OmniFloorParams.from_config({**CFG["omni"], "outer_radius_m": -1.0})


def test_ground_pixel_size_matches_the_mirror_model():
    """Radial ground pixel from the model's closed form (eq. 3) at 0.6 m: d rho / d r."""
    rho = 0.6
    radial, tang = ground_pixel_size(CAMERA, np.array([rho]))
    r0 = float(CAMERA.radius_of_elevation(-math.atan2(1.0, rho)))
    r1 = float(CAMERA.radius_of_elevation(-math.atan2(1.0, rho + 1e-4)))
    assert radial[0] == pytest.approx(1e-4 / (r1 - r0), rel=0.01)
    assert tang[0] == pytest.approx(rho / r0, rel=0.01)
    assert 0.013 < tang[0] < radial[0] < 0.02  # the numbers configs/omni.toml quotes


# --- drive logs ------------------------------------------------------------------------------

SIM = """
[simulate.omni]
room_m = [5.0, 4.0]
[simulate.omni.camera]
frame_size = [320, 240]
[simulate.omni.motion]
frame_spacing_m = 0.05
[simulate.omni.routes]
random_length_m = 1.2
inset_m = 1.4
[simulate.omni.world]
objects = 2
object_size_m = [0.2, 0.4]
object_route_clearance_m = 1.0
"""
BUILD = """
[map]
pixel_size_m = 0.02
[ingest]
on_bad_image = "skip"
max_bad_fraction = 0.2
"""


def invoke(*args):
    return CliRunner().invoke(cli, [*map(str, args)])


@pytest.fixture(scope="module")
def small_log(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("omni")
    (d / "sim.toml").write_text(SIM)
    (d / "build.toml").write_text(BUILD)
    r = invoke("simulate", "omni", d / "log", "--route", "random", "--seed", "5", "--config", d / "sim.toml", "-q")
    assert r.exit_code == 0, r.output
    return d / "log", d / "build.toml"


def _copy_log(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for name in ("drive.toml", "frames.csv", "odometry.csv", "ground_truth.csv"):
        (dst / name).write_bytes((src / name).read_bytes())
    (dst / "images").mkdir()
    for p in sorted((src / "images").iterdir()):
        (dst / "images" / p.name).write_bytes(p.read_bytes())
    return dst


def test_route_id_parsing_and_errors(tmp_path, small_log):
    log, _ = small_log
    assert read_drive_log(log).route_id == "random"  # the simulator writes the route kind
    bad = _copy_log(log, tmp_path / "bad")
    text = (log / "drive.toml").read_text()
    assert '[route]\nid = "random"' in text
    cases = [
        ('[route]\nid = "two words"', "drive.toml[route.id]", "route id 'two words'"),
        ('[route]\nid = 7', "drive.toml[route.id]", "route id 7"),
        ('[route]\nname = "x"', "drive.toml[route.id]", "missing field"),
        ('[route]\nid = "a"\nlane = 2', "drive.toml[route.lane]", "unknown field"),
    ]
    for table, where, what in cases:
        (bad / "drive.toml").write_text(text.replace('[route]\nid = "random"', table))
        with pytest.raises(BadInput) as e:
            read_drive_log(bad)
        assert e.value.where.endswith(where) and what in e.value.what, (e.value.where, e.value.what)
    # the CLI: exit 2, one line naming drive.toml[route.id]
    (bad / "drive.toml").write_text(text.replace('id = "random"', 'id = "a/b"'))
    r = invoke("build", bad, "-w", tmp_path / "w", "--until", "ingest", "-q")
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "drive.toml[route.id]" in r.output
    # absent: None
    (bad / "drive.toml").write_text(text.replace('[route]\nid = "random"\n', ""))
    assert read_drive_log(bad).route_id is None


def test_simulator_route_ids(tmp_path, small_log):
    log, _ = small_log
    sim = log.parent / "sim.toml"
    again = tmp_path / "again"
    r = invoke("simulate", "omni", again, "--world", log, "--seed", "6", "--config", sim, "-q")
    assert r.exit_code == 0, r.output
    assert read_drive_log(again).route_id == "random"  # a --world run keeps PREV's id
    named = tmp_path / "named"
    r = invoke("simulate", "omni", named, "--world", log, "--route-id", "corridor-2", "--config", sim, "-q")
    assert r.exit_code == 0 and read_drive_log(named).route_id == "corridor-2"
    r = invoke("simulate", "omni", tmp_path / "x", "--route-id", "no way", "--config", sim, "-q")
    assert r.exit_code == 2 and "--route-id" in r.output and len(r.output.strip().splitlines()) == 1


def test_ingest_small_omni_log(tmp_path, small_log):
    """Frames store and horizon lines file of an omni log with one corrupt frame (skipped)."""
    src, build_cfg = small_log
    log = _copy_log(src, tmp_path / "log")
    (log / "images" / "000003.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    r = invoke("build", log, "-w", tmp_path / "w", "--until", "ingest", "--config", build_cfg, "-q",
               "--report", tmp_path / "r.json")
    assert r.exit_code == 0, r.output
    lg = read_drive_log(log)
    n = len(lg.frame_images)
    rep = json.loads((tmp_path / "r.json").read_text())
    summary = rep["ingest"]["logs"][0]
    assert summary["omni"]["route_id"] == "random" and summary["omni"]["horizon_lines"] == n - 1
    store = FrameStore(tmp_path / "w" / "ingest" / STORE_NAME)
    lf = store.logs[0]
    assert store.pixel_size == 0.02 and lf.valid.shape == tuple(summary["omni"]["frame_shape"])
    assert 0 < lf.count <= n - 1 and 3 not in lf.source_index.tolist()
    assert lf.attrs["omni"]["inner_radius_m"] < lf.attrs["omni"]["outer_radius_m"]
    # the horizon lines file (contract 2)
    h = read_horizons(tmp_path / "w" / "ingest" / "horizons" / "000.npz")
    frames = np.array([i for i in range(n) if i != 3])
    assert h["lines"].dtype == np.float32 and h["lines"].shape == (n - 1, 360)
    assert h["t"].dtype == np.float64 and h["frame"].dtype == np.int32 and h["odometry"].dtype == np.float64
    np.testing.assert_array_equal(h["frame"], frames)
    np.testing.assert_array_equal(h["t"], lg.frame_t[frames])
    np.testing.assert_allclose(h["odometry"], interpolate_trajectory(lg.odometry, lg.frame_t)[frames])
    m = h["meta"]
    assert m["log_id"] == "log" and m["route_id"] == "random" and m["path"] == str(log.resolve())
    assert (m["samples_per_degree"], m["horizon_band_deg"], m["oversample"]) == (1.0, 1.0, 3)
    assert m["camera"] == lg.camera.omni.to_toml_dict() and len(m["sha256"]) == 64
    assert m["sha256"] == rep["logs"][0]["sha256"]  # the build's input checksum
    # the lines are the vehicle's sampling of the flat-field corrected frame, unrounded
    sampler = horizon_sampler(lg.camera.omni, CFG["tracker"]["orp"])
    raw = read_grey(log / lg.frame_images[5])
    gain = lg.camera.omni.vignetting_gain(raw.shape, lg.camera.vignetting)
    np.testing.assert_allclose(h["lines"][4], sampler.line(raw / gain), atol=1e-3)
    assert not np.allclose(h["lines"][4], np.round(h["lines"][4]))
    # the vehicle's path (`mosaicmap track`): the same flat field and line, bit for bit, from
    # the corrected raw window only
    from pipeline.omni_ingest import CorrectedHorizonLines, flat_corrected, inverse_flat_field, omni_flat_field

    flat, _ = omni_flat_field(lg, raw.shape, CFG["ingest"]["flatfield"]["mode"])
    live = CorrectedHorizonLines(sampler, raw.shape, flat)
    rows, cols = live.window
    assert (rows.stop - rows.start) * (cols.stop - cols.start) < raw.size  # a window, not the frame
    for k, i in ((0, 0), (4, 5), (n - 2, n - 1)):
        frame = read_grey(log / lg.frame_images[i])
        np.testing.assert_array_equal(live(frame), h["lines"][k])
        np.testing.assert_array_equal(live(frame), sampler.line(flat_corrected(frame, inverse_flat_field(flat))))
    bare = CorrectedHorizonLines(sampler, raw.shape, None)
    np.testing.assert_array_equal(bare(raw), sampler.line(raw.astype(np.float32)))
    # with the defaults (skip, but at most max_bad_fraction = 2 % of a log: 1 of these 20-odd
    # frames is more): exit 2, one line naming the image
    r = invoke("build", log, "-w", tmp_path / "w2", "--until", "ingest", "-q")
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "000003.png" in r.output


def test_omni_calibration_errors_exit_2(tmp_path, small_log):
    src, build_cfg = small_log
    log = _copy_log(src, tmp_path / "log")
    text = (src / "drive.toml").read_text()
    (log / "drive.toml").write_text(text.replace("f_px = ", "focal = "))
    r = invoke("build", log, "-w", tmp_path / "w", "--until", "ingest", "--config", build_cfg, "-q")
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1
    assert "drive.toml[camera.f_px]: missing calibration field" in r.output, r.output
    # a camera whose reflection hides all the floor the annulus allows: one line naming [omni]
    (log / "drive.toml").write_text(re.sub(r"hole_radius_px = [0-9.]+", "hole_radius_px = 100.0", text))
    assert "hole_radius_px = 100.0" in (log / "drive.toml").read_text()
    r = invoke("build", log, "-w", tmp_path / "w3", "--until", "ingest", "--config", build_cfg, "-q")
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "[omni]" in r.output, r.output


@pytest.mark.slow
def test_build_floor_map_from_omni_log(tmp_path):
    """simulate omni (640 x 480) -> build --map at 10 mm: a published floor map, poses within 1 mm."""
    (tmp_path / "sim.toml").write_text(
        "[simulate.omni.routes]\nrandom_length_m = 1.0\n[simulate.omni.world]\nobject_route_clearance_m = 1.1\n")
    (tmp_path / "build.toml").write_text("[map]\npixel_size_m = 0.01\n")
    r = invoke("simulate", "omni", tmp_path / "log", "--route", "random", "--seed", "2", "--config",
               tmp_path / "sim.toml", "-q")
    assert r.exit_code == 0, r.output
    r = invoke("build", tmp_path / "log", "-w", tmp_path / "w", "--map", tmp_path / "map", "--config",
               tmp_path / "build.toml", "-q", "--report", tmp_path / "r.json")
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["links"]["accepted"] >= 0.8 * rep["links"]["candidates"]
    assert rep["ground_truth"]["pose_rms_px"] < 0.1  # 1 mm at 10 mm pixels
    assert rep["render"]["covered_mpix"] > 0.01 and rep["publish"]["version"] == 1


def test_omni_flat_field_as_declared(tmp_path):
    """flat_field image (normalized at the mirror axis' image), vignetting, none; bad sizes."""
    from pipeline.drivelog import CameraSpec, DriveLog
    from pipeline.images import write_grey
    from pipeline.omni_ingest import omni_flat_field

    gain = CAMERA.vignetting_gain(RAW, (-0.3, 0.05))
    write_grey(tmp_path / "flat.png", 200.0 * gain, bits=16)
    odo = np.array([[0.0, 0, 0, 0], [1.0, 0, 0, 0]])

    def log(**kw) -> DriveLog:
        return DriveLog(tmp_path, "f", CameraSpec(model="omni", omni=CAMERA, **kw), np.array([0.5]), ["x.png"], odo)

    flat, info = omni_flat_field(log(flat_field="flat.png"), RAW, "auto")
    assert info["source"] == "flat_field image"
    np.testing.assert_allclose(flat, gain, atol=2e-3)  # 16-bit quantization
    flat, info = omni_flat_field(log(vignetting=(-0.3, 0.05)), RAW, "calibration")
    np.testing.assert_allclose(flat, gain, rtol=1e-6)
    assert omni_flat_field(log(vignetting=(-0.3, 0.05)), RAW, "none")[0] is None
    assert omni_flat_field(log(), RAW, "auto")[0] is None  # omni logs: no estimate
    with pytest.raises(BadInput, match="flat-field image is 640x480, frames are 320x240"):
        omni_flat_field(log(flat_field="flat.png"), (240, 320), "auto")
