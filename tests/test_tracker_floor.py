"""The floor tracker's fix (tracker.floor) on frames cut from a known map: subpixel accuracy
from a loose prior, and never a confident wrong fix."""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from mapstore.grid import MapGrid
from pipeline.testing.synthmap import periodic_texture
from tracker.correlate import match_stack, ncc_peak, noise_sigma, peak_of, peaks_of, subpixel_offset, weakest_direction_score
from tracker.floor import FloorTracker, FloorTrackerParams, fit_rigid, half_frame, select_templates
from tracker.tiles import ArrayTiles, TileCache

PX = 0.0025
FRAME = (240, 320)


@pytest.fixture(scope="module")
def world():
    m = np.clip(np.rint(periodic_texture(11, 1024)), 1, 255).astype(np.uint8)
    grid = MapGrid(0.0, (m.shape[0] - 1) * PX, PX, m.shape[1], m.shape[0])
    return m, grid


def frame_at(m, grid, pose, rng, noise=5.0, gain=1.0):
    a = grid.frame_to_grid_affine(pose, FRAME, PX)
    f = cv2.warpAffine(m, a, FRAME[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP).astype(np.float32)
    return np.clip(gain * f + rng.normal(0, noise, f.shape), 0, 255).astype(np.uint8)


def random_pose(rng, grid):
    x0, y0, x1, y1 = grid.bounds
    return np.array([rng.uniform(x0 + 0.5, x1 - 0.5), rng.uniform(y0 + 0.5, y1 - 0.5), rng.uniform(-np.pi, np.pi)])


def test_subpixel_offset_and_peak():
    assert subpixel_offset(0.5, 1.0, 0.5) == 0.0
    assert subpixel_offset(0.0, 1.0, 1.0) == 0.5
    assert abs(subpixel_offset(0.8, 1.0, 0.6) + 0.1666) < 1e-3
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.normal(128, 40, (64, 64)).astype(np.float32), (0, 0), 1.5)
    pk = ncc_peak(img[20:47, 22:49].copy(), img[25:42, 24:41].copy(), 3)  # true offset (-3, 0)
    assert pk.interior and abs(pk.dx + 3) < 0.05 and abs(pk.dy) < 0.05 and pk.c1 > 0.999 and pk.uniqueness > 0.2


def test_match_stack_and_peaks_of():
    from numpy.lib.stride_tricks import sliding_window_view

    rng = np.random.default_rng(6)
    img = np.rint(cv2.GaussianBlur(rng.normal(128, 40, (200, 200)), (0, 0), 1.5)).astype(np.float32)
    for s, t in ((45, 9), (23, 17)):
        wins = np.stack([img[20 * i : 20 * i + s, 9 * i : 9 * i + s] for i in range(5)])
        tpls = np.stack([img[20 * i + 4 : 20 * i + 4 + t, 9 * i + 2 : 9 * i + 2 + t] for i in range(5)])
        wins[3] = 77.0  # flat window
        todo = np.array([True, True, True, True, False])
        res = match_stack(wins, tpls, todo)
        assert res.shape == (5, s - t + 1, s - t + 1) and (res[4] == -1).all()
        for i in range(3):  # against a float64 brute-force NCC
            v = sliding_window_view(wins[i].astype(np.float64), (t, t))
            vz, tz = v - v.mean(axis=(2, 3), keepdims=True), tpls[i] - tpls[i].mean()
            ref = np.einsum("ijkl,kl->ij", vz, tz) / np.sqrt((vz**2).sum(axis=(2, 3)) * (tz**2).sum())
            assert np.abs(res[i] - ref).max() < 1e-5
        pk = peaks_of(res.copy(), 3, todo)
        for i in range(4):
            q = peak_of(res[i].copy(), 3)
            assert abs(pk.dx[i] - q.dx) < 1e-6 and abs(pk.dy[i] - q.dy) < 1e-6 and pk.interior[i] == q.interior
            assert abs(pk.c1[i] - q.c1) < 1e-6 and abs(pk.c2[i] - q.c2) < 1e-6
        r = (s - t) // 2  # the template's true place is (2, 4) from the window's corner
        assert abs(pk.dx[0] - (2 - r)) < 0.05 and abs(pk.dy[0] - (4 - r)) < 0.05 and pk.c1[0] > 0.999
        assert pk.c1[4] == -1 and not pk.interior[4]
        assert np.isnan(peaks_of(res.copy(), None, todo).c2).sum() == 0 and (peaks_of(res, None).c2 == -1).all()


def test_half_frame_and_select_templates():
    rng = np.random.default_rng(7)
    frame = rng.integers(0, 256, (241, 321)).astype(np.uint8)
    small = half_frame(frame)
    assert small.shape == (120, 160)
    assert abs(float(small[10, 20]) - frame[20:22, 40:42].mean()) <= 0.5
    p = FloorTrackerParams()
    c, sc, n = select_templates(frame, None, p)
    c2, sc2, n2 = select_templates(frame, None, p, small=small)
    assert np.array_equal(c, c2) and np.array_equal(sc, sc2) and n == n2 == 12 and len(c) == p.n_templates
    assert np.all(np.diff(sc) <= 0)
    half = p.template_px // 2
    assert (c >= half).all() and (c[:, 0] < 321 - half).all() and (c[:, 1] < 241 - half).all()
    valid = np.ones(frame.shape, bool)
    valid[:, :160] = False
    cv_, _, _ = select_templates(frame, valid, p)
    assert (cv_[:, 0] - half >= 160).all()


def test_coarse_to_fine_matches_the_full_resolution_search(world):
    m, grid = world
    rng = np.random.default_rng(9)
    sigma = np.array([0.02, 0.02, 0.01])  # radius 36 px: coarse to fine by default
    c2f = FloorTracker(ArrayTiles(m), grid, PX)
    full = FloorTracker(ArrayTiles(m), grid, PX, FloorTrackerParams(coarse_min_radius_px=100))
    for _ in range(8):
        gt = random_pose(rng, grid)
        frame, prior = frame_at(m, grid, gt, rng, noise=10.0), gt + rng.normal(0, 1, 3) * sigma
        a, b = c2f.fix(frame, prior, sigma), full.fix(frame, prior, sigma)
        # the uniqueness is the coarse search's (another figure): a template may differ
        assert a.ok and b.ok and abs(a.inliers - b.inliers) <= 1
        assert np.hypot(*(a.pose[:2] - b.pose[:2])) / PX < 0.05
        assert np.hypot(*(a.pose[:2] - gt[:2])) / PX < 0.25 and a.uniqueness >= 0.2


def test_fit_rigid_exact():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(6, 2))
    th, t = 0.3, np.array([1.0, -2.0])
    dst = src @ np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]]) + t
    th2, t2 = fit_rigid(src, dst)
    assert abs(th2 - th) < 1e-12 and np.allclose(t2, t)


def test_fit_rigid_weighted_equals_the_unweighted_fit_of_repeated_points():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(5, 2))
    dst = src @ np.array([[0.9, 0.2], [-0.2, 0.9]]) + rng.normal(scale=0.05, size=(5, 2)) + 3.0
    w = np.array([1.0, 2.0, 1.0, 3.0, 1.0])
    th_w, t_w = fit_rigid(src, dst, w)
    rep = np.repeat(np.arange(5), w.astype(int))
    th_r, t_r = fit_rigid(src[rep], dst[rep])
    assert th_w == pytest.approx(th_r, abs=1e-12) and np.allclose(t_w, t_r, atol=1e-12)


def test_weakest_direction_score_is_twice_the_smaller_eigenvalue_of_the_mean_tensor(world):
    """The one-call score equals the structure tensor spelled out: Sobel 3x3 / 8 gradients,
    their products averaged over the window, twice the smaller eigenvalue (away from the
    border, where the two reflect differently)."""
    m, _ = world
    img = m[100:220, 300:460].copy()
    w = 9
    gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT_101) / 8.0
    gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT_101) / 8.0
    sxx, syy, sxy = (cv2.blur(a, (w, w)) for a in (gx * gx, gy * gy, gx * gy))
    ref = sxx + syy - np.sqrt((sxx - syy) ** 2 + 4 * sxy * sxy)
    got = weakest_direction_score(img, w)
    k = w // 2 + 1
    assert got.dtype == np.float32 and got.shape == img.shape
    assert np.allclose(got[k:-k, k:-k], ref[k:-k, k:-k], rtol=1e-4, atol=1e-3 * ref.max())
    # a straight edge scores ~0, a corner does not
    edge = np.zeros((40, 40), np.uint8)
    edge[:, 20:] = 200
    assert np.abs(weakest_direction_score(edge, w)[10:30, 10:30]).max() < 1e-3 * 200 ** 2 / 64
    corner = edge.copy()
    corner[20:, :] = 200
    assert weakest_direction_score(corner, w)[20, 20] > 100.0


def test_noise_sigma_reads_uint8_and_float_frames_alike():
    rng = np.random.default_rng(4)
    f = np.clip(rng.normal(120.0, 6.0, (160, 160)), 0, 255)
    assert noise_sigma(f) == pytest.approx(noise_sigma(f.astype(np.float32)), rel=1e-6)
    assert noise_sigma(np.rint(f).astype(np.uint8)) == pytest.approx(6.0, rel=0.1)


def test_tile_cache_windows_and_lru():
    a = np.arange(100 * 90, dtype=np.int32).reshape(100, 90)
    reads = []

    def read(tr, tc):
        reads.append((tr, tc))
        return None if (tr, tc) == (3, 2) else a[tr * 32 : (tr + 1) * 32, tc * 32 : (tc + 1) * 32]

    tc = TileCache(read, a.shape, 32, capacity=4, dtype=np.int32, fill=-1)
    w = tc.window(-5, 40, 80, 95)
    assert w.shape == (45, 15)
    assert (w[:5] == -1).all() and (w[:, 10:] == -1).all() and np.array_equal(w[5:, :10], a[0:40, 80:90])
    assert (tc.window(97, 100, 85, 90) == -1).all()  # tile (3, 2): the source holds no data
    n = len(reads)
    tc.window(0, 10, 80, 90)
    assert len(reads) == n  # cached
    for k in range(4):
        tc.tile(0, k % 3)
        tc.tile(1, k % 3)
    assert len(tc._tiles) <= 4
    assert np.array_equal(ArrayTiles(a, 32).window(10, 50, 20, 70), a[10:50, 20:70])


def test_fix_accuracy_from_loose_prior(world):
    m, grid = world
    rng = np.random.default_rng(2)
    trk = FloorTracker(ArrayTiles(m), grid, PX)
    sigma = np.array([0.0067, 0.0067, 0.003])
    errs = []
    for _ in range(25):
        gt = random_pose(rng, grid)
        f = trk.fix(frame_at(m, grid, gt, rng, gain=0.8), gt + rng.normal(0, 1, 3) * sigma, sigma)
        assert f.status == "ok", f
        errs.append(np.hypot(*(f.pose[:2] - gt[:2])) / PX)
        assert abs(f.pose[2] - gt[2]) < 1e-3
        assert f.inliers >= 4 and f.rms_px < 0.4 and np.all(np.linalg.eigvalsh(f.cov) > 0)
    assert np.sqrt(np.mean(np.square(errs))) < 0.1 and max(errs) < 0.25


def test_never_ok_and_wrong(world):
    m, grid = world
    rng = np.random.default_rng(3)
    trk = FloorTracker(ArrayTiles(m), grid, PX)
    sigma = np.array([0.0067, 0.0067, 0.003])
    statuses = []
    for i in range(30):
        gt = random_pose(rng, grid)
        if i % 3 == 0:   # very noisy frame
            frame = frame_at(m, grid, gt, rng, noise=60.0)
        elif i % 3 == 1:  # a prior 5 cm off: the true place is outside the search window
            frame = frame_at(m, grid, gt, rng)
            gt_prior = gt + np.array([0.05, -0.03, 0.0])
            f = trk.fix(frame, gt_prior, sigma)
            statuses.append(f.status)
            assert f.status != "ok" or np.hypot(*(f.pose[:2] - gt[:2])) / PX < 2
            continue
        else:            # another place of the floor entirely
            frame = frame_at(m, grid, random_pose(rng, grid), rng)
        f = trk.fix(frame, gt, sigma)
        statuses.append(f.status)
        assert f.status != "ok" or np.hypot(*(f.pose[:2] - gt[:2])) / PX < 2, f
    assert statuses.count("ok") < len(statuses)


def test_low_texture_and_off_map(world):
    m, grid = world
    trk = FloorTracker(ArrayTiles(m), grid, PX)
    flat = np.full(FRAME, 128, np.uint8)
    f = trk.fix(flat, np.array([1.0, 1.0, 0.0]), np.array([0.005, 0.005, 0.002]))
    assert f.status == "low_texture" and np.array_equal(f.pose, [1.0, 1.0, 0.0])
    rng = np.random.default_rng(4)
    frame = frame_at(m, grid, np.array([1.2, 1.2, 0.0]), rng)
    f = trk.fix(frame, np.array([-3.0, -3.0, 0.0]), np.array([0.005, 0.005, 0.002]))
    assert f.status == "lost" and f.reasons["no_map"] > 0


def test_params_from_dict():
    p = FloorTrackerParams.from_dict({"n_templates": 6, "grid_cells": [2, 3]})
    assert p.n_templates == 6 and p.grid_cells == (2, 3)
    with pytest.raises(ValueError, match="unknown"):
        FloorTrackerParams.from_dict({"bogus": 1})


def test_tracker_imports_nothing_from_pipeline():
    from conftest import modules_pulled_in

    mods = ["tracker.floor", "tracker.tiles", "tracker.correlate", "tracker.coverage", "tracker.relative",
            "tracker.session", "tracker.reloc", "tracker.bundle_map", "tracker.omnicam", "tracker.orp"]
    assert modules_pulled_in(mods, ("pipeline", "icechunk", "click", "dask")) == []


def test_relocalization_without_prior(world):
    from tracker.reloc import RelocParams, Relocalizer, build_index

    m, grid = world
    tiles = ArrayTiles(m)
    index = build_index(tiles, grid)
    assert len(index) > 500 and index.descriptors.shape[1] == 32
    x0, y0, x1, y1 = grid.bounds
    assert (index.xy[:, 0] >= x0).all() and (index.xy[:, 0] <= x1).all()
    rl = Relocalizer(index, FloorTracker(tiles, grid, PX))
    rng = np.random.default_rng(5)
    ok = 0
    for _ in range(8):
        gt = random_pose(rng, grid)
        f = rl.locate(frame_at(m, grid, gt, rng, noise=8.0, gain=0.8))
        if f.ok:
            ok += 1
            assert np.hypot(*(f.pose[:2] - gt[:2])) / PX < 0.5
    assert ok >= 7
    # a frame of another floor: never ok
    other = np.clip(np.rint(periodic_texture(99, 512)), 1, 255).astype(np.uint8)[:240, :320]
    f = rl.locate(other)
    assert f.status == "lost" and np.isnan(f.pose).all()
    with pytest.raises(ValueError, match="unknown"):
        RelocParams.from_dict({"nope": 1})


def test_fix_against_an_exported_bundle(tmp_path):
    import copy

    from click.testing import CliRunner

    from pipeline.cli import cli
    from pipeline.config import load_config
    from pipeline.testing.synthmap import publish_raster, texture_tile_fn
    from tracker.bundle_map import open_bundle

    cfg = copy.deepcopy(load_config(None))
    grid = MapGrid(0.0, 2.0, PX, 801, 801)
    tex = periodic_texture(7, 1024)
    publish_raster(str(tmp_path / "map"), grid, texture_tile_fn(tex, grid), cfg=cfg, tag="v1")
    r = CliRunner().invoke(cli, ["export", str(tmp_path / "map"), "--region", "0.2,0.2,1.8,1.8", "--quiet",
                                 str(tmp_path / "b.zip")], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    m = np.clip(np.rint(texture_tile_fn(tex, grid)(0, 801, 0, 801)), 1, 255).astype(np.uint8)
    rng = np.random.default_rng(8)
    with open_bundle(tmp_path / "b.zip", cache_tiles=8, insecure=True) as tm:
        assert tm.grid == grid
        trk = tm.floor_tracker(PX)
        sigma = np.array([0.005, 0.005, 0.002])
        for pose in ([1.0, 1.0, 0.3], [0.7, 1.3, -2.0]):
            gt = np.array(pose)
            f = trk.fix(frame_at(m, grid, gt, rng), gt + np.array([0.004, -0.003, 0.001]), sigma)
            assert f.ok and np.hypot(*(f.pose[:2] - gt[:2])) / PX < 0.15
        # half outside the exported region (no data there): templates only on the map's side
        gt = np.array([1.7, 1.0, 0.0])
        f = trk.fix(frame_at(m, grid, gt, rng), gt + np.array([0.004, -0.003, 0.001]), sigma)
        assert 0.2 < f.coverage < 0.8 and f.reasons["no_map"] == 0
        assert f.ok and np.hypot(*(f.pose[:2] - gt[:2])) / PX < 0.25
        # mostly outside (textured, but the map's data ends near its edge): lost, not low texture
        gt = np.array([2.05, 1.0, 0.0])
        f = trk.fix(frame_at(m, grid, gt, rng), gt, sigma)
        assert f.status == "lost" and f.coverage < 0.15 and f.reasons["no_map"] > 0, f
        assert tm.tiles.misses <= tm.tiles.capacity + 20
    r = CliRunner().invoke(cli, ["export", str(tmp_path / "map"), "--levels", "1", "--quiet",
                                 str(tmp_path / "c.zip")], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    with pytest.raises(ValueError, match="level-0"):
        open_bundle(tmp_path / "c.zip", insecure=True)


def test_configs_tracker_toml_equals_the_defaults():
    from pipeline.config import load_config
    from tracker.reloc import RelocParams
    from tracker.session import SessionParams

    cfg = load_config(None)["tracker"]
    assert FloorTrackerParams.from_dict(cfg["floor"]) == FloorTrackerParams()
    assert RelocParams.from_dict(cfg["reloc"]) == RelocParams()
    assert SessionParams.from_dict(cfg["session"]) == SessionParams()
    with pytest.raises(ValueError, match=r"\[tracker.session\] lost_afterr: unknown key"):
        SessionParams.from_dict({"lost_afterr": 3})


def test_noise_sigma_estimates_sensor_noise(world):
    from tracker.correlate import noise_sigma

    m, grid = world
    rng = np.random.default_rng(12)
    clean = frame_at(m, grid, np.array([1.0, 1.0, 0.2]), rng, noise=0.0)
    for sigma in (10.0, 40.0):
        noisy = np.clip(clean + rng.normal(0, sigma, clean.shape), 0, 255).astype(np.uint8)
        # the texture adds a little to the estimate: within a few grey levels
        assert abs(noise_sigma(noisy) - sigma) < 0.15 * sigma + 3.0, (sigma, noise_sigma(noisy))


def test_noisy_frames_are_prefiltered_and_still_never_wrong(world):
    m, grid = world
    rng = np.random.default_rng(13)
    sigma = np.array([0.005, 0.005, 0.003])
    with_pf = FloorTracker(ArrayTiles(m), grid, PX)
    without = FloorTracker(ArrayTiles(m), grid, PX, FloorTrackerParams(prefilter_noise=0.0))
    ok = {"with": 0, "without": 0}
    for _ in range(20):
        gt = random_pose(rng, grid)
        frame = frame_at(m, grid, gt, rng, noise=50.0)
        prior = gt + rng.normal(0, 1, 3) * sigma
        for name, trk in (("with", with_pf), ("without", without)):
            f = trk.fix(frame, prior, sigma)
            assert f.status != "ok" or np.hypot(*(f.pose[:2] - gt[:2])) / PX < 1.0, (name, f)
            ok[name] += f.ok
        assert f.reasons.get("noise_grey", 0) > 25 or f.status == "low_texture"
    assert ok["with"] > ok["without"] and ok["with"] >= 14, ok


def test_predict_grows_the_sigma_linearly_with_distance():
    from tracker.session_core import CoreParams, SessionCore

    core = SessionCore()
    core.p = CoreParams(error_gradient=0.02, heading_gradient=0.01)
    core.start(np.array([1.0, 1.0, np.pi / 2]), np.array([0.001, 0.001, 0.002]))
    for _ in range(10):  # 10 x 0.1 m at 2 % (m/m) and 1 % (rad/m): Kelly's (2000) error = gradient x distance
        core._predict(np.array([0.1, 0.0, 0.0]))
    assert np.allclose(core.s.pose, [1.0, 2.0, np.pi / 2]) and np.allclose(core.sigma, [0.021, 0.021, 0.012])
