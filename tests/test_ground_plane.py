"""Aerial frames' tilt and height from the images (pipeline/ground_plane.py) and their correction at ingest."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import smooth_texture
from mapstore.grid import MapGrid
from pipeline.camera import Rectifier
from pipeline.config import load_config
from pipeline.drivelog import CameraSpec, read_drive_log, write_drive_log
from pipeline.framestore import FrameStore
from pipeline.images import write_grey
from pipeline.stages.build import run_build
from pipeline.ground_plane import (
    GroundPlaneParams,
    combine_normals,
    estimate_ground_plane,
    frame_pairs,
    nadir_rotation,
    pair_normals,
    positions_scale,
    solve_heights,
    tilt_angle,
)

CAM = CameraSpec(fx=300.0, fy=300.0, cx=159.5, cy=119.5, height_m=1.0)
SHAPE = (240, 320)
PX = 1.0 / 300.0  # the camera's nadir ground pixel at 1 m (metres)


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _normal(roll_rad: float, pitch_rad: float) -> np.ndarray:
    """The ground's normal in the coordinates of a camera tilted by a rotation about its y
    axis (roll) and its x axis (pitch) from nadir."""
    cr, sr, cp, sp = np.cos(roll_rad), np.sin(roll_rad), np.cos(pitch_rad), np.sin(pitch_rad)
    ry = np.array([[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    n = rx @ ry @ np.array([0.0, 0.0, 1.0])
    return n / np.linalg.norm(n)


def _render(tex: np.ndarray, grid: MapGrid, pose: np.ndarray, normal: np.ndarray, height: float) -> np.ndarray:
    """The raw view of ``tex`` from a camera at ``pose`` (x, y of its position over the floor,
    heading; metres, radians) and ``height`` metres, tilted so that the ground's normal is
    ``normal`` in its coordinates (no distortion)."""
    rows, cols = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(np.float64)
    rays = np.stack([(cols - CAM.cx) / CAM.fx, (rows - CAM.cy) / CAM.fy, np.ones_like(cols)], -1)
    d = rays @ nadir_rotation(normal).T  # nadir camera coordinates
    right, down = height * d[..., 0] / d[..., 2], height * d[..., 1] / d[..., 2]
    xv, yv = right, -down  # vehicle frame (mapstore.grid: x along the image's columns, y up the image)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    gx, gy = grid.world_to_pixel(pose[0] + c * xv - s * yv, pose[1] + s * xv + c * yv)
    return cv2.remap(tex, gx.astype(np.float32), gy.astype(np.float32), cv2.INTER_CUBIC)


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(11)
    grid = MapGrid.covering(-1.2, -1.0, 2.4, 1.0, 0.0025)
    return smooth_texture(rng, grid.shape), grid


def _flight(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera poses along x (0.18 m apart, heading 0.3 rad), heights and tilt normals (3-12 deg)."""
    rng = np.random.default_rng(seed)
    poses = np.column_stack([0.18 * np.arange(n), 0.05 * np.sin(np.arange(n)), np.full(n, 0.3)])
    heights = 1.0 + 0.05 * rng.uniform(-1, 1, n)
    tilts = np.radians(rng.uniform(3, 12, n))
    az = rng.uniform(-np.pi, np.pi, n)
    normals = np.stack([_normal(t * np.cos(a), t * np.sin(a)) for t, a in zip(tilts, az)])
    return poses, heights, normals


def test_nadir_rotation_takes_the_normal_to_the_axis_and_keeps_heading():
    n = _normal(0.1, -0.2)
    r = nadir_rotation(n)
    assert np.allclose(r @ n, [0, 0, 1], atol=1e-12)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.linalg.det(r) == pytest.approx(1.0)
    # the smallest rotation: its axis lies in the image plane (no turn about the optical axis)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    assert abs(axis[2]) < 1e-12
    assert np.allclose(nadir_rotation([0, 0, 1]), np.eye(3))
    assert tilt_angle(n) == pytest.approx(np.arccos(n[2]))


def test_combine_normals_takes_the_mode_and_needs_agreement():
    good = _normal(0.05, 0.08)
    wrong = _normal(-0.2, 0.01)
    cands = np.array([good, _normal(0.052, 0.079), wrong, _normal(0.049, 0.081)])
    n, support = combine_normals(cands, 0.03)
    assert support == 3
    assert np.degrees(np.arccos(n @ good)) < 0.2
    assert combine_normals(np.zeros((0, 3)), 0.03)[1] == 0


def test_pair_normals_recover_the_plane_from_a_homography():
    """A synthetic homography between two tilted views of a plane: one decomposition is the truth."""
    K = CAM.camera_matrix()
    na, nb = _normal(0.1, 0.05), _normal(-0.04, 0.12)
    ra, rb = nadir_rotation(na), nadir_rotation(nb)
    # ground points (nadir camera a's coordinates: plane z = 1), camera b 0.4 m to the right at height 1.1
    g = np.random.default_rng(0).uniform(-0.4, 0.4, (200, 2))
    pg = np.column_stack([g, np.ones(200)])
    xa = pg @ ra  # a's tilted camera coordinates (ra.T applied to each row vector)
    xb = (pg - [0.4, 0.0, -0.1]) @ rb
    pa = (xa @ K.T)[:, :2] / xa[:, 2:]
    pb = (xb @ K.T)[:, :2] / xb[:, 2:]
    sols = pair_normals(pa, pb, K)
    assert 1 <= len(sols) <= 2
    err = min(np.degrees(np.arccos(min(1.0, s[0] @ na))) + np.degrees(np.arccos(min(1.0, s[1] @ nb))) for s in sols)
    assert err < 0.01


def test_frame_pairs_take_the_next_frames_and_near_neighbours():
    p = GroundPlaneParams(pair_span=1, neighbours=2, neighbour_distance=0.5)
    pos = np.array([[0, 0], [10, 0], [20, 0], [0, 3], [100, 0]], float)
    pairs = frame_pairs(pos, 5, p, footprint_m=10.0)
    assert (0, 1) in pairs and (3, 4) in pairs  # sequential
    assert (0, 3) in pairs  # 3 m apart: a neighbour
    assert (0, 4) not in pairs and (2, 4) not in pairs  # far
    assert frame_pairs(None, 3, p) == [(0, 1), (1, 2)]


def test_estimate_ground_plane_from_rendered_views(world):
    tex, grid = world
    poses, heights, normals = _flight(8, seed=3)
    imgs = [_render(tex, grid, p, n, h) for p, n, h in zip(poses, normals, heights)]
    recorded = heights * (1.0 + 0.03 * np.random.default_rng(1).choice([-1.0, 1.0], 8))  # records 3 % off
    est = estimate_ground_plane(lambda i: imgs[i], len(imgs), CAM.camera_matrix(), None,
                                GroundPlaneParams(min_inliers=30), heights=recorded,
                                pairs=frame_pairs(poses[:, :2], 8, GroundPlaneParams(), footprint_m=0.8), workers=2)
    assert est.estimated.all(), est.describe()
    err = np.degrees(np.arccos(np.clip(np.sum(est.normals * normals, 1), -1, 1)))
    assert err.max() < 0.5, err
    # relative heights from the images (to 0.3 %), the overall scale from the records
    rel = est.heights / heights
    assert rel.max() / rel.min() - 1.0 < 0.003, rel
    assert abs(np.log(rel).mean() - np.log(recorded / heights).mean()) < 0.003
    assert est.heights_estimated.all() and np.allclose(est.recorded_heights, recorded)
    d = est.describe()
    assert d["frames_estimated"] == 8 and 3 <= d["tilt_median_deg"] <= 12
    assert d["heights_estimated"] == 8 and 1.0 < d["height_change_median_pct"] < 5.0
    # records 10 % high on top: the positions (the cameras', metres) set the overall scale
    est2 = estimate_ground_plane(lambda i: imgs[i], len(imgs), CAM.camera_matrix(), None,
                                 GroundPlaneParams(min_inliers=30), heights=recorded * 1.1, positions=poses[:, :2],
                                 min_step_m=0.1, pairs=frame_pairs(poses[:, :2], 8, GroundPlaneParams(),
                                                                   footprint_m=0.8))
    assert np.abs(est2.heights / heights - 1.0).max() < 0.005, est2.heights / heights
    assert est2.height_scale_pairs >= 7 and est2.describe()["height_scale_from_positions"] < 0.95


def test_solve_heights_follows_the_pairs_and_resists_an_outlier():
    true = np.array([60.0, 62.0, 65.0, 61.0, 70.0, 68.0])
    recorded = true * np.array([1.02, 0.98, 1.03, 0.99, 0.97, 1.01])
    pairs = [(k, k + 1) for k in range(5)] + [(0, 2), (1, 3), (2, 4), (3, 5)]
    scales = [(i, j, float(np.log(true[i] / true[j])), 0.001) for i, j in pairs]
    scales.append((0, 5, np.log(true[0] / true[5]) + 0.2, 0.001))  # one pair 20 % off
    h, measured = solve_heights(recorded, scales, 0.05, 0.002)
    assert measured.all()
    rel = h / true
    assert rel.max() / rel.min() - 1.0 < 0.002, rel
    h2, m2 = solve_heights(np.array([50.0, 51.0, 52.0]), [(0, 1, 0.0, 0.001)], 0.05, 0.002)
    assert m2.tolist() == [True, True, False] and h2[2] == pytest.approx(52.0)
    assert h2[0] == pytest.approx(h2[1], rel=1e-3) and 50.0 < h2[0] < 51.0
    h3, m3 = solve_heights(np.array([50.0, 51.0]), [], 0.05, 0.002)
    assert not m3.any() and np.allclose(h3, [50.0, 51.0])


def test_positions_scale_is_the_median_step_ratio():
    pos = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [20.5, 0.0]])
    h = np.array([50.0, 50.0, 50.0, 50.0])
    # image steps (in units of h_b) say 11, 11 and 12.4 m (the last pair too short to count)
    steps = [(0, 1, 11.0 / 50.0), (1, 2, 11.0 / 50.0), (2, 3, 0.62 / 50.0), (0, 2, 22.0 / 50.0)]
    f, n = positions_scale(h, steps, pos, min_step_m=5.0)
    assert n == 3 and f == pytest.approx(10.0 / 11.0)
    assert positions_scale(h, [], pos, 5.0) == (1.0, 0)
    p = GroundPlaneParams()
    assert p.scale_from_positions(has_heights=True) and not p.scale_from_positions(has_heights=False)
    assert not GroundPlaneParams(height_scale="records").scale_from_positions(has_heights=True)


def test_unusable_frames_keep_no_estimate(world):
    tex, grid = world
    poses, heights, normals = _flight(4, seed=4)
    imgs = [_render(tex, grid, p, n, h) for p, n, h in zip(poses, normals, heights)]
    imgs[3] = None  # unreadable
    imgs[2] = np.full(SHAPE, 100.0, np.float32)  # blank: no features
    est = estimate_ground_plane(lambda i: imgs[i], 4, CAM.camera_matrix(), None, GroundPlaneParams(min_inliers=30))
    assert not est.estimated[2:].any()
    assert np.allclose(est.rotations[2:], np.eye(3))
    assert np.allclose(est.normals[2:], [0, 0, 1])


def test_rectifier_turns_a_tilted_view_into_the_nadir_view(world):
    """The corrected frame is the world seen from above, centred on the optical axis' ground point."""
    tex, grid = world
    pose = np.array([0.3, 0.1, 0.4])
    n = _normal(0.12, -0.15)
    raw = _render(tex, grid, pose, n, 1.0)
    rect = Rectifier(CAM, SHAPE, 0.004, rotations=nadir_rotation(n)[None], interpolation="cubic")
    img = rect(raw, None, 0)
    a = nadir_rotation(n) @ [0, 0, 1.0]
    right, down = a[0] / a[2], a[1] / a[2]  # metres at 1 m height
    c, s = np.cos(pose[2]), np.sin(pose[2])
    centre = np.array([pose[0] + c * right + s * down, pose[1] + s * right - c * down, pose[2]])
    ref = cv2.warpAffine(tex, grid.frame_to_grid_affine(centre, img.shape, 0.004), img.shape[::-1],
                         flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    v = rect.valid
    assert v.mean() > 0.6
    assert _ncc(img[v], ref[v]) > 0.98
    plain = Rectifier(CAM, SHAPE, 0.004, interpolation="cubic")(raw)
    assert _ncc(plain[v], ref[v]) < 0.8  # without the correction: neither placed nor shaped right


def _tilted_log(path: Path, tex, grid, n: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    poses, heights, normals = _flight(n, seed=5)
    (path / "images").mkdir(parents=True)
    names = []
    for i, (p, nrm, h) in enumerate(zip(poses, normals, heights)):
        names.append(f"images/{i:06d}.png")
        write_grey(path / names[-1], _render(tex, grid, p, nrm, h), bits=16)
    t = 0.5 * np.arange(1, n + 1)
    odo = np.column_stack([np.r_[0.0, t, t[-1] + 0.5], np.vstack([poses[:1], poses, poses[-1:]])])
    write_drive_log(path, CAM, t, names, odo)
    frames_csv = path / "frames.csv"
    lines = frames_csv.read_text().splitlines()
    recorded = heights * (1.0 + 0.03 * np.resize([1.0, -1.0, -1.0, 1.0], n))  # records 3 % off, mean right
    frames_csv.write_text("t,image,height_m\n" + "\n".join(f"{ln},{h}" for ln, h in zip(lines[1:], recorded)) + "\n")
    return poses, heights, normals


def test_ingest_corrects_tilt_of_an_aerial_log(tmp_path: Path, world):
    """Frames with their own heights (an aircraft) are measured and corrected by default:
    each stored frame matches the world from above at the map's scale (its recorded height
    was 3 % off) at its stored prior, which moved from the camera's position to its optical
    axis' ground point."""
    tex, grid = world
    poses, heights, normals = _tilted_log(tmp_path / "log", tex, grid)
    cfg = load_config()
    cfg["ingest"]["flatfield"]["mode"] = "none"
    cfg["ingest"]["ground_plane"]["min_inliers"] = 30
    cfg["map"]["pixel_size_m"] = 0.004
    report = run_build([tmp_path / "log"], tmp_path / "w", cfg, until="ingest", quiet=True)
    assert report["ingest"]["logs"][0]["ground_plane"]["frames_estimated"] == 8
    lf = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0]
    assert lf.attrs["ground_plane"]["frames_estimated"] == 8
    prior = lf.prior
    for i in range(8):
        a = nadir_rotation(normals[i]) @ [0, 0, 1.0]
        right, down = heights[i] * a[0] / a[2], heights[i] * a[1] / a[2]
        c, s = np.cos(poses[i, 2]), np.sin(poses[i, 2])
        centre = np.array([poses[i, 0] + c * right + s * down, poses[i, 1] + s * right - c * down])
        assert np.hypot(*(prior[i, :2] - centre)) < 0.01 * heights[i]  # 0.6 deg of tilt
        img = lf.image(i)
        ref = cv2.warpAffine(tex, grid.frame_to_grid_affine(prior[i], img.shape, 0.004), img.shape[::-1],
                             flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
        assert _ncc(img[lf.valid], ref[lf.valid]) > 0.95


def test_tilt_mode_none_and_ground_robots_are_left_alone(tmp_path: Path, world):
    """``mode = "none"`` turns it off; ``auto`` leaves logs without per-frame heights alone."""
    tex, grid = world
    _tilted_log(tmp_path / "log", tex, grid, n=3)
    cfg = load_config()
    cfg["ingest"]["flatfield"]["mode"] = "none"
    cfg["map"]["pixel_size_m"] = 0.004
    cfg["ingest"]["ground_plane"]["mode"] = "none"
    run_build([tmp_path / "log"], tmp_path / "w", cfg, until="ingest", quiet=True)
    assert "ground_plane" not in FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0].attrs
    p = GroundPlaneParams()
    assert not p.applies(has_intrinsics=True, has_heights=False)
    assert p.applies(has_intrinsics=True, has_heights=True)
    assert not p.applies(has_intrinsics=False, has_heights=True)
    assert GroundPlaneParams(mode="images").applies(has_intrinsics=True, has_heights=False)
    assert read_drive_log(tmp_path / "log").frame_heights is not None
