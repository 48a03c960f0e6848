"""The omni simulator (`mosaicmap simulate omni`): drive log, determinism, repeat runs, options."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mapstore.grid import interpolate_trajectory, se2_between
from pipeline.cli import cli
from pipeline.config import load_config
from pipeline.drivelog import read_drive_log, read_pose_csv
from pipeline.errors import BadInput
from pipeline.fsutil import link_tree
from pipeline.images import read_grey
from pipeline.simulate.omni import camera_from_config, load_world
from tracker.omnicam import HyperboloidCamera

TINY = """
[simulate.omni]
room_m = [7.0, 5.0]
[simulate.omni.camera]
frame_size = [160, 120]
[simulate.omni.motion]
frame_spacing_m = 0.6
[simulate.omni.routes]
inset_m = 1.5
[simulate.omni.world]
objects = 4
object_size_m = [0.2, 0.6]
object_height_m = [1.2, 2.0]
texel_m = 0.02
"""


@pytest.fixture(scope="module")
def tiny_cfg(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cfg") / "tiny.toml"
    p.write_text(TINY)
    return p


def run(*args: str):
    return CliRunner().invoke(cli, ["simulate", "omni", *map(str, args)])


def simulate(out: Path, cfg: Path, *args) -> Path:
    r = run(out, "--config", cfg, "--quiet", *args)
    assert r.exit_code == 0, r.output
    return out


def files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def day1(tmp_path_factory, tiny_cfg) -> Path:
    return simulate(tmp_path_factory.mktemp("logs") / "day1", tiny_cfg, "--seed", "3")


def test_log_is_valid(day1, tiny_cfg):
    log = read_drive_log(day1)
    assert log.camera.is_omni and isinstance(log.camera.omni, HyperboloidCamera)
    cfg = load_config(tiny_cfg)
    assert log.camera.omni == camera_from_config(cfg["simulate"]["omni"]["camera"])
    assert log.camera.vignetting == (-0.25, 0.0)
    n = len(log.frame_images)
    assert n >= 10
    cam = log.camera.omni
    mask = cam.image_mask((120, 160), margin_px=1.5)
    outside = ~cam.image_mask((120, 160), margin_px=-1.5)
    outside &= np.hypot(*np.mgrid[0:120, 0:160][::-1] - np.array([cam.cx, cam.cy])[:, None, None]) > cam.rim_radius_px
    for i in (0, n - 1):
        img = read_grey(log.image_path(i))
        assert img.shape == (120, 160)
        assert img[mask].mean() > 40 and img[mask].std() > 10  # a textured scene in the annulus
        assert img[outside].mean() < 12  # dark outside the image circle
    gt = read_pose_csv(day1 / "ground_truth.csv")
    np.testing.assert_array_equal(gt[:, 0], log.frame_t)
    steps = np.hypot(*np.diff(gt[:, 1:3], axis=0).T)
    assert np.all(np.abs(steps - 0.6) < 0.02)  # frames every frame_spacing_m (chords of a gentle route)
    # odometry covers the frames, starts at the truth (world frame) and drifts a little
    assert log.odometry[0, 0] <= log.frame_t[0] and log.odometry[-1, 0] >= log.frame_t[-1]
    odo = interpolate_trajectory(log.odometry, log.frame_t)
    err = np.hypot(*(odo[:, :2] - gt[:, 1:3]).T)
    assert err[0] < 1e-3 and 0 < err.max() < 0.05 * 12
    # the world is there and reloads
    world, route = load_world(day1)
    assert len(world.objects) == 4 and route.length > 5


def test_same_seed_same_bytes(tmp_path, tiny_cfg, day1):
    again = simulate(tmp_path / "day1", tiny_cfg, "--seed", "3")
    a, b = files(day1), files(again)
    a.pop("drive.toml"), b.pop("drive.toml")  # holds the log id only as its directory name; same here
    assert a == b
    assert (day1 / "drive.toml").read_bytes() == (again / "drive.toml").read_bytes()


def test_repeat_run_reuses_the_world(tmp_path, tiny_cfg, day1):
    day2 = simulate(tmp_path / "day2", tiny_cfg, "--seed", "9", "--world", day1, "--noise", "0")
    assert (day2 / "world" / "atlas.png").read_bytes() == (day1 / "world" / "atlas.png").read_bytes()
    g1, g2 = read_pose_csv(day1 / "ground_truth.csv"), read_pose_csv(day2 / "ground_truth.csv")
    np.testing.assert_allclose(g1, g2)  # the same route (odometry and noise differ)
    a, b = read_grey(day1 / "images" / "000002.png"), read_grey(day2 / "images" / "000002.png")
    a, b = a - a.mean(), b - b.mean()
    assert (a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()) > 0.97
    assert not np.array_equal(read_pose_csv(day1 / "odometry.csv"), read_pose_csv(day2 / "odometry.csv"))


def test_options_change_what_they_say(tmp_path, tiny_cfg, day1):
    night = simulate(tmp_path / "night", tiny_cfg, "--seed", "3", "--world", day1, "--night",
                     "--height-offset", "0.01")
    toml = (night / "drive.toml").read_text()
    assert "rendered_height_m = 1.01" in toml and "height_m = 1.0\n" in toml
    d, n = read_grey(day1 / "images" / "000001.png"), read_grey(night / "images" / "000001.png")
    assert np.abs(d.astype(float) - n).mean() > 10
    moved = simulate(tmp_path / "moved", tiny_cfg, "--seed", "4", "--world", day1, "--move-objects", "0.25")
    world, _ = load_world(moved)
    assert 0.15 <= world.meta["moved_fraction"] <= 0.35 and world.meta["moved_objects"]
    off = simulate(tmp_path / "off", tiny_cfg, "--world", day1, "--offset", "0.2", "--odometry-drift", "0")
    _, route = load_world(day1)
    gt = read_pose_csv(off / "ground_truth.csv")
    nominal = np.stack([route.x, route.y], 1)
    dist = np.min(np.hypot(gt[:, None, 1] - nominal[None, :, 0], gt[:, None, 2] - nominal[None, :, 1]), axis=1)
    np.testing.assert_allclose(dist, 0.2, atol=0.01)
    across = simulate(tmp_path / "across", tiny_cfg, "--world", day1, "--angle", "30")
    gt = read_pose_csv(across / "ground_truth.csv")
    rel = se2_between(gt[:-1, 1:], gt[1:, 1:])
    assert np.abs(rel[:, 2]).max() > math.radians(20)  # zig-zagging across the memorized path


@pytest.mark.parametrize(
    "args, where",
    [
        (["--move-objects", "1.5"], "--move-objects"),
        (["--angle", "90"], "--angle"),
        (["--height-offset", "3"], "--height-offset"),
        (["--route", "spiral"], "--route"),
        (["--world", "/nonexistent/log"], "/nonexistent/log"),
        (["--seed", "-1"], "--seed"),
    ],
)
def test_bad_options_exit_2(tmp_path, tiny_cfg, args, where):
    r = run(tmp_path / "o", "--config", tiny_cfg, "-q", *args)
    assert r.exit_code == 2, r.output
    assert where in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_drive_toml_omni_fields(tmp_path, day1):
    log = tmp_path / "log"
    log.mkdir()
    for name in ("frames.csv", "odometry.csv"):
        (log / name).write_bytes((day1 / name).read_bytes())
    link_tree(day1 / "images", log / "images")  # a symlink out of the log would be refused
    text = (day1 / "drive.toml").read_text().split("[simulation]")[0]
    (log / "drive.toml").write_text(text.replace("a_m = 0.0281\n", ""))
    with pytest.raises(BadInput) as e:
        read_drive_log(log)
    assert e.value.where.endswith("drive.toml[camera.a_m]") and "missing calibration field" in e.value.what
    (log / "drive.toml").write_text(text.replace('mirror = "hyperboloid"', 'mirror = "conic"'))
    with pytest.raises(BadInput, match=r"\[camera.mirror\]"):
        read_drive_log(log)
    # Mei's model parses too
    mei = text.split("mirror =")[0] + 'mirror = "mei"\nxi = 0.9\nfx = 150.0\nfy = 150.0\ncx = 80.0\ncy = 60.0\nheight_m = 1.0\n'
    (log / "drive.toml").write_text(mei)
    assert read_drive_log(log).camera.omni.mirror == "mei"
    # the CLI: one line naming the field, exit 2; a valid omni log ingests (bird's-eye frames,
    # horizon lines: tests/test_omni_ingest.py)
    (log / "drive.toml").write_text(text.replace("a_m = 0.0281\n", ""))
    r = CliRunner().invoke(cli, ["build", str(log), "-w", str(tmp_path / "w"), "--until", "ingest", "-q"])
    assert r.exit_code == 2 and "drive.toml[camera.a_m]: missing calibration field" in r.output, r.output
    (tmp_path / "px.toml").write_text("[map]\npixel_size_m = 0.05\n")
    r = CliRunner().invoke(cli, ["build", str(day1), "-w", str(tmp_path / "w2"), "--until", "ingest", "-q",
                                 "--config", str(tmp_path / "px.toml")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "w2" / "ingest" / "horizons" / "000.npz").is_file()
    assert read_drive_log(day1).route_id == "loop"  # [route] id: the route kind


def test_world_run_without_seed_is_a_new_run(tmp_path):
    """`--world PREV` without --seed takes PREV's seed + 1 (the same seed would duplicate PREV)."""
    from pipeline.simulate.omni import previous_seed

    log = tmp_path / "prev"
    log.mkdir()
    (log / "drive.toml").write_text("format_version = 1\n[simulation]\nseed = 7\n")
    assert previous_seed(log) == 7
    (log / "drive.toml").write_text("format_version = 1\n")
    assert previous_seed(log) == 0
