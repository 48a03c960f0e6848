"""Route panoramas (ORP) and the ORP localizer (tracker/orp.py, issue 7, Yagi et al. (2005)).

The localizer tests use an analytic world: a rectangular room whose walls carry a panel
texture along the perimeter; a horizon line at a pose is computed by casting one ray per
azimuth (3 sub-samples per degree averaged, as the horizon sampler does) to the walls. One
test runs the omni simulator (small frames) end to end: frames -> horizon lines -> ORP ->
a frame of a second run localized.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from mapstore.grid import interpolate_trajectory, se2_compose
from tracker.orp import (ORP, HorizonSampler, ORPLocalizer, ORPParams, build_orp, estimate_row_flow, path_length,
                         prepare_lines)

ROOM = (8.0, 5.0)
PERIM = 2 * (ROOM[0] + ROOM[1])


def wall_texture(seed: int = 0, n: int = 4096) -> np.ndarray:
    """Grey levels along the perimeter (n samples): random panels 5-40 cm wide, smoothed."""
    rng = np.random.default_rng(seed)
    tex = np.empty(n)
    i = 0
    while i < n:
        w = int(rng.integers(int(0.05 / PERIM * n) + 1, int(0.4 / PERIM * n) + 2))
        tex[i : i + w] = rng.uniform(40, 220)
        i += w
    k = np.exp(-0.5 * (np.arange(-5, 6) / 1.5) ** 2)
    return np.convolve(np.concatenate([tex[-5:], tex, tex[:5]]), k / k.sum(), mode="valid")


TEX = wall_texture()


def horizon_line(pose: np.ndarray, tex: np.ndarray = TEX, spd: int = 1, sub: int = 3) -> np.ndarray:
    """The horizon line (360 spd,) of the analytic room at ``pose`` (x, y, theta; world frame)."""
    x, y, th = pose
    n = 360 * spd * sub
    az = th + np.radians((np.arange(n) - sub // 2) / (spd * sub))
    dx, dy = np.cos(az), np.sin(az)
    with np.errstate(divide="ignore"):
        tx = np.where(dx > 0, (ROOM[0] - x) / dx, np.where(dx < 0, -x / dx, np.inf))
        ty = np.where(dy > 0, (ROOM[1] - y) / dy, np.where(dy < 0, -y / dy, np.inf))
    t = np.minimum(tx, ty)
    hx, hy = x + t * dx, y + t * dy
    rx, ry = ROOM
    per = np.where(tx < ty, np.where(dx > 0, rx + hy, 2 * rx + ry + (ry - hy)),
                   np.where(dy < 0, hx, rx + ry + (rx - hx)))
    v = np.interp(per / PERIM * len(tex), np.arange(len(tex) + 1), np.append(tex, tex[0]))
    return v.reshape(-1, sub).mean(1).astype(np.float32)


def straight_route(n: int = 301, step: float = 0.02) -> np.ndarray:
    """Poses along y = 2.5 from x = 1 (heading +x), ``step`` metres apart."""
    s = np.arange(n) * step
    return np.stack([1.0 + s, np.full(n, 2.5), np.zeros(n)], 1)


@pytest.fixture(scope="module")
def memorized():
    poses = straight_route()
    lines = np.stack([horizon_line(p) for p in poses])
    orp = build_orp(lines, poses, 0.02, 1.0)
    return orp, ORPLocalizer(orp, ORPParams())


def test_orp_construction_shape_spacing_and_bytes():
    poses = straight_route(n=501, step=0.02)  # 10 m
    lines = np.stack([horizon_line(p) for p in poses])
    orp = build_orp(lines, poses, 0.10, 1.0)
    assert isinstance(orp, ORP)
    assert orp.lines.shape == (101, 360) and orp.lines.dtype == np.uint8
    assert orp.poses.shape == (101, 3)
    np.testing.assert_allclose(np.diff(orp.s), 0.10)
    np.testing.assert_allclose(orp.poses[:, 0], 1.0 + orp.s, atol=1e-5)
    np.testing.assert_allclose(path_length(orp.poses), orp.s, atol=1e-4)
    # rows at the frames' positions are those frames' lines (rounded to uint8)
    np.testing.assert_allclose(orp.lines[7], np.rint(lines[35]), atol=0.51)
    # storage: 360 bytes per line + 12 bytes of pose per 10 cm: 3.72 MB per km (target <= 4)
    assert orp.nbytes == 101 * (360 + 12)
    assert 3.6e6 < orp.bytes_per_km() <= 4.0e6
    # stationary frames are merged, a resampled row between two frames is their blend
    dup = build_orp(np.concatenate([lines[:1], lines]), np.concatenate([poses[:1], poses]), 0.01, 1.0)
    assert len(dup.lines) == 1001
    np.testing.assert_allclose(dup.lines[1].astype(float), (lines[0] + lines[1]) / 2, atol=0.51)


@pytest.mark.parametrize("truth_offset", [(0.0, 0.0, 0.0), (0.011, 0.15, 0.2), (0.0, -0.25, -0.5)])
def test_localizer_recovers_a_known_offset(memorized, truth_offset):
    orp, loc = memorized
    truth = se2_compose(np.array([3.5, 2.5, 0.0]), np.array(truth_offset))
    line = horizon_line(truth)
    prior = se2_compose(truth, np.array([0.04, -0.03, math.radians(2.0)]))
    fix = loc.localize(line, prior)
    assert fix.ok, fix
    assert np.hypot(*(fix.pose[:2] - truth[:2])) < 0.003, (fix.pose, truth)
    assert abs(fix.pose[2] - truth[2]) < math.radians(0.1)
    assert abs(fix.s - (truth[0] - 1.0)) < 0.02 and fix.masked_fraction == 0.0


@pytest.mark.parametrize("kind", ["reversed", "shifted"])
def test_masking_drops_a_corrupted_sector(memorized, kind):
    orp, loc = memorized
    truth = np.array([3.2, 2.62, 0.05])
    line = horizon_line(truth)
    bad = line.copy()
    # 90 degrees (six 15-degree mask sectors) changed: contrast reversed (a window dark at
    # night) or the pattern displaced by 6 degrees (a moved object): pulls an unmasked fit away
    sector = slice(30, 120)
    bad[sector] = (255 - line if kind == "reversed" else np.roll(line, 6))[sector]
    prior = se2_compose(truth, np.array([0.03, 0.03, math.radians(-1.5)]))
    masked = loc.localize(bad, prior, masking=True)
    plain = loc.localize(bad, prior, masking=False)
    assert masked.mask[sector].all() and masked.mask.mean() < 0.3 and masked.ok
    assert not plain.mask.any()
    err_m = np.hypot(*(masked.pose[:2] - truth[:2]))
    err_p = np.hypot(*(plain.pose[:2] - truth[:2]))
    assert err_m < 0.003 and err_p > 0.05, (err_m, err_p)


def periodic_texture(seed: int = 1, n_az: int = 360, max_cycles: int = 40):
    """A smooth periodic grey-level function of the column (samples), random Fourier terms."""
    rng = np.random.default_rng(seed)
    k = np.arange(1, max_cycles + 1)
    amp = rng.uniform(0.5, 1.0, len(k)) / np.sqrt(k)
    ph = rng.uniform(0, 2 * np.pi, len(k))

    def tex(col: np.ndarray) -> np.ndarray:
        w = 2 * np.pi * np.asarray(col, float)[..., None] * k / n_az
        v = (amp * np.sin(w + ph)).sum(-1)
        return 128 + 60 * v / np.abs(v).max()

    return tex


@pytest.mark.parametrize("rotation, baseline", [(0.0, 1), (3.0, 1), (0.0, 5)])
def test_row_flow_recovers_a_known_parallax(rotation, baseline):
    # rows of a synthetic route: the pattern at column u of row 0 is at u + k p(u) + k rot in
    # row k (parallax p up to 2.5 samples per row, as near walls 10 cm apart; rot: the heading
    # change, found from 0 coarse to fine); stored as uint8
    tex = periodic_texture()
    cols = np.arange(360.0)
    par = 2.5 * np.sin(np.radians(cols)) / baseline  # per row, baseline rows = one "10 cm"
    rows = 12
    lines = np.empty((rows, 360))
    for k in range(rows):
        # invert u -> u + k (p(u) + rot) by fixed point iteration
        u = cols.copy()
        for _ in range(30):
            u = cols - k * (np.interp(u % 360, cols, par, period=360) + rotation)
        lines[k] = tex(u)
    lines = np.clip(np.rint(lines), 0, 255).astype(np.uint8)
    d = estimate_row_flow(lines, 2.0, 2.0, (4.0, 2.0, 1.0), 3, 5.0, 0.05, 20.0, None, baseline)
    assert d.shape == (rows - 1, 360)
    # truth of pair (k, k + 1) at column c: p(u) + rot, u the point seen at c at row k + 1/2
    truth = np.empty((rows - 1, 360))
    for k in range(rows - 1):
        u = cols.copy()
        for _ in range(30):
            u = cols - (k + 0.5) * (np.interp(u % 360, cols, par, period=360) + rotation)
        truth[k] = np.interp(u % 360, cols, par, period=360) + rotation
    err = np.abs(d - truth)
    assert np.median(err) < 0.05 and np.percentile(err, 90) < 0.15, (np.median(err), np.percentile(err, 90))
    # linear rows would need d = 0: the estimate is far closer
    assert err.mean() < 0.1 * np.abs(truth).mean()


def _synthesis_errors(orp: ORP, params: ORPParams, poses: np.ndarray) -> np.ndarray:
    loc = ORPLocalizer(orp, params)
    out = []
    for pose in poses:
        obs = prepare_lines(horizon_line(pose), 2.0, 1.0, 2.0)
        v, _, valid = loc.synthesize(pose, 2, 0.0, len(orp.lines) - 1.0)
        out.append(np.sqrt(np.mean((v - obs)[valid] ** 2)))
    return np.array(out)


def test_flow_synthesis_at_fractional_rows_beats_linear():
    # a 10 cm ORP; poses between rows (on the path and 10 cm beside it, headings off):
    # the motion-compensated synthesis is much closer to the true line than the linear blend
    poses = straight_route(n=301, step=0.02)
    lines = np.stack([horizon_line(p) for p in poses])
    orp = build_orp(lines, poses, 0.10, 1.0)
    rng = np.random.default_rng(3)
    x = 1.5 + 0.1 * rng.integers(0, 40, 24) + rng.uniform(0.03, 0.07, 24)  # mid-cell
    test = np.stack([x, 2.5 + rng.uniform(-0.1, 0.1, 24), rng.uniform(-0.2, 0.2, 24)], 1)
    e_flow = _synthesis_errors(orp, ORPParams(), test)
    e_lin = _synthesis_errors(orp, ORPParams(interp_flow=False), test)
    assert e_flow.mean() < 0.5 * e_lin.mean(), (e_flow.mean(), e_lin.mean())
    # at 2 cm (the frames' own spacing) it does no harm
    orp2 = build_orp(lines, poses, 0.02, 1.0)
    test[:, 0] = 1.5 + 0.02 * rng.integers(0, 200, 24) + 0.01
    e_flow = _synthesis_errors(orp2, ORPParams(), test)
    e_lin = _synthesis_errors(orp2, ORPParams(interp_flow=False), test)
    assert e_flow.mean() < 1.05 * e_lin.mean(), (e_flow.mean(), e_lin.mean())


def test_flow_synthesis_jacobian_matches_finite_differences():
    # the Jacobian's d/drow (d/dcolumn) is the rows' (columns') central derivative interpolated
    # between them (motion compensated), not the cell's own difference: close to finite
    # differences, not equal (smooth for Gauss-Newton; the linear mode's is further off)
    poses = straight_route(n=301, step=0.02)
    orp = build_orp(np.stack([horizon_line(p) for p in poses]), poses, 0.10, 1.0)
    loc = ORPLocalizer(orp, ORPParams())
    assert loc.flow is not None
    for pose in (np.array([3.437, 2.58, 0.07]), np.array([3.412, 2.45, -0.1])):
        v, jac, valid = loc.synthesize(pose, 1, 0.0, len(orp.lines) - 1.0)
        for k, (h, tol) in enumerate(((1e-4, 0.35), (1e-4, 0.35), (1e-5, 0.35))):
            dp = np.zeros(3)
            dp[k] = h
            vp, _, okp = loc.synthesize(pose + dp, 1, 0.0, len(orp.lines) - 1.0)
            vm, _, okm = loc.synthesize(pose - dp, 1, 0.0, len(orp.lines) - 1.0)
            num = (vp - vm) / (2 * h)
            use = valid & okp & okm
            rel = np.linalg.norm((num - jac[:, k])[use]) / np.linalg.norm(num[use])
            assert rel < tol, (pose, k, rel)


def test_localizer_at_10cm_spacing_with_flow():
    poses = straight_route(n=301, step=0.02)
    orp = build_orp(np.stack([horizon_line(p) for p in poses]), poses, 0.10, 1.0)
    loc = ORPLocalizer(orp, ORPParams(spacing_m=0.10))
    rng = np.random.default_rng(5)
    errs = []
    for _ in range(12):
        truth = np.array([1.6 + rng.uniform(0, 4), 2.5 + rng.uniform(-0.2, 0.2), rng.uniform(-0.3, 0.3)])
        fix = loc.localize(horizon_line(truth), se2_compose(truth, np.array([0.04, -0.03, math.radians(2.0)])))
        assert fix.ok
        errs.append(np.hypot(*(fix.pose[:2] - truth[:2])))
    assert np.mean(errs) < 0.002 and np.max(errs) < 0.004, errs


def test_configs_tracker_toml_equals_the_defaults():
    from pipeline.config import load_config

    cfg = load_config(None)["tracker"]["orp"]
    assert ORPParams.from_dict(cfg) == ORPParams()
    with pytest.raises(ValueError, match=r"\[tracker.orp\] spacing: unknown key"):
        ORPParams.from_dict({"spacing": 0.1})
    with pytest.raises(ValueError, match="odd"):
        ORPParams(oversample=2)
    with pytest.raises(ValueError, match="flow"):
        ORPParams(flow_iterations=0)
    with pytest.raises(ValueError, match="flow_regularization"):
        ORPParams(flow_regularization=0.0)


TINY = """
[simulate.omni]
room_m = [7.0, 5.0]
[simulate.omni.camera]
frame_size = [240, 240]
[simulate.omni.motion]
frame_spacing_m = 0.02
[simulate.omni.routes]
inset_m = 1.5
loop_corner_radius_m = 0.8
[simulate.omni.world]
objects = 3
object_size_m = [0.2, 0.5]
object_height_m = [1.2, 2.0]
texel_m = 0.02
"""


def test_simulated_run_builds_an_orp_and_localizes(tmp_path):
    from pipeline.cli import cli
    from pipeline.drivelog import read_drive_log, read_pose_csv

    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY)
    for name, extra in (("mem", []), ("run", ["--world", str(tmp_path / "mem"), "--seed", "3", "--offset", "0.05"])):
        r = CliRunner().invoke(cli, ["simulate", "omni", str(tmp_path / name), "--config", str(cfg), "--quiet", *extra])
        assert r.exit_code == 0, r.output

    def lines_of(name: str, idx):
        log = read_drive_log(tmp_path / name)
        hs = HorizonSampler(log.camera.omni, 1.0, 1.0, 3)
        truth = interpolate_trajectory(read_pose_csv(tmp_path / name / "ground_truth.csv"), log.frame_t)
        ims = [cv2.imread(str(log.image_path(i)), cv2.IMREAD_GRAYSCALE) for i in idx]
        return hs.lines(ims), truth[list(idx)]

    log = read_drive_log(tmp_path / "mem")
    idx = range(0, min(len(log.frame_images), 301))  # the first 6 m (a straight side and a corner)
    lines, poses = lines_of("mem", idx)
    assert lines.shape == (len(idx), 360) and np.isfinite(lines).all()
    orp = build_orp(lines, poses, 0.02, 1.0)
    loc = ORPLocalizer(orp)
    test_lines, truth = lines_of("run", range(40, 200, 20))
    errs = []
    for line, t in zip(test_lines, truth):
        fix = loc.localize(line, se2_compose(t, np.array([0.03, -0.02, 0.02])))
        errs.append(np.hypot(*(fix.pose[:2] - t[:2])))
    # small frames (240 x 240: a horizon ring of ~1 px per degree), 5 cm beside the route
    assert np.mean(errs) < 0.02, errs
