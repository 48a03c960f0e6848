"""Pairwise registration (pipeline.registration) and candidate pairs (pipeline.candidates).

Frames are cut from a band-limited random texture at known poses (bicubic, as ingest's
rectified frames are), with sensor noise sigma 5 grey levels.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import smooth_texture
from mapstore.grid import MapGrid, se2_between, wrap_angle
from pipeline.candidates import ChainUncertainty, FrameTable, revisit_candidates, sequential_candidates
from pipeline.config import load_config
from pipeline.links import Link
from pipeline.stages.register import chain_from_links
from pipeline.resample import ExactSampler
from pipeline.registration import RegistrationParams, register_pair

PX = 0.0025
SHAPE = (240, 320)  # rows, columns: 0.8 x 0.6 m
NOISE = 5.0
CFG = load_config()
PARAMS = RegistrationParams.from_config(CFG["register"])
MIN_NCC, MIN_UNIQ = CFG["register"]["min_ncc"], CFG["register"]["min_uniqueness"]
# Ingest's valid masks exclude a border (valid_mask_erode_px = 2, eroded with a zero border).
VALID = np.zeros(SHAPE, bool)
VALID[2:-2, 2:-2] = True


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(11)
    grid = MapGrid.covering(-0.9, -0.9, 0.9, 0.9, PX)
    return smooth_texture(rng, grid.shape), grid


def cut(tex: np.ndarray, grid: MapGrid, pose, rng: np.random.Generator, noise: float = NOISE) -> np.ndarray:
    """The frame seen at ``pose`` (resampled exactly from the world texture), plus Gaussian noise."""
    a = grid.frame_to_grid_affine(np.asarray(pose, float), SHAPE, PX)
    rows, cols = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    img = ExactSampler(tex, border=cv2.BORDER_REFLECT)(a[0, 0] * cols + a[0, 1] * rows + a[0, 2],
                                                       a[1, 0] * cols + a[1, 1] * rows + a[1, 2])
    return (img + noise * rng.standard_normal(SHAPE)).astype(np.float32)


def errors(rel: np.ndarray, rel_true: np.ndarray) -> tuple[float, float]:
    """(translation error in px, heading error x the frame's half diagonal in px)."""
    t = float(np.hypot(*(rel[:2] - rel_true[:2]))) / PX
    r = abs(float(wrap_angle(rel[2] - rel_true[2]))) * np.hypot(*SHAPE) / 2
    return t, r


def accepted(r) -> bool:
    """The register stage's acceptance rule for a pair result."""
    return bool(r.ok and r.ncc >= MIN_NCC and r.uniqueness >= MIN_UNIQ)


def mahalanobis2(r, rel_true) -> float:
    e = np.r_[r.rel[:2] - rel_true[:2], wrap_angle(r.rel[2] - rel_true[2])]
    return float(e @ np.linalg.solve(r.cov, e))


@pytest.mark.parametrize(
    "pose_a, pose_b",
    [
        ((0.0, 0.0, 0.1), (0.0513, 0.0127, 0.1261)),  # forward step with a small turn
        ((0.05, -0.02, -0.4), (0.1312, 0.0231, -0.38)),
        ((-0.1, 0.05, 2.0), (-0.1411, 0.1337, 1.9852)),
    ],
)
def test_translation_and_small_rotation_recovered(world, pose_a, pose_b):
    tex, grid = world
    rng = np.random.default_rng(int(abs(pose_a[2]) * 100))
    a, b = cut(tex, grid, pose_a, rng), cut(tex, grid, pose_b, rng)
    rel_true = se2_between(np.array(pose_a), np.array(pose_b))
    # Prior off by ~1.5 px and 3 mrad, as odometry over one frame step would be.
    prior = rel_true + np.array([0.0030, -0.0021, 0.003])
    r = register_pair(a, VALID, b, VALID, prior, PX, 8.0, 0.005, PARAMS)
    assert r.ok, r.reason
    assert accepted(r), (r.ncc, r.uniqueness)
    t_err, r_err = errors(r.rel, rel_true)
    assert t_err < 0.05, f"translation error {t_err:.4f} px"
    assert r_err < 0.05, f"rotation error {r_err:.4f} px at the frame corner"
    # Data-derived covariance: symmetric, positive definite, and consistent with the error.
    assert np.allclose(r.cov, r.cov.T, rtol=1e-9, atol=0)
    assert np.all(np.linalg.eigvalsh(r.cov) > 0)
    assert np.sqrt(r.cov[0, 0] + r.cov[1, 1]) / PX < 0.05  # sub-0.05 px sigma on this texture
    assert mahalanobis2(r, rel_true) < 30.0
    assert r.overlap > 0.7 and r.uniqueness > 0.3 and r.ncc > 0.8


def test_opposite_headings_adjacent_lanes(world):
    """Cross-lane pair of a lawnmower: headings differ by pi, lanes 0.4 m apart (1/3 overlap).

    Headings 0 and pi and offsets in multiples of 1/32 px make the cut frames exact: OpenCV's
    warps round sample positions to 1/32 px, and for slightly rotated frames that rounding
    error is coherent enough to bias a narrow-strip registration by ~0.05 px (measured:
    dtheta = pi - 0.006 -> mean x error -0.058 px, sigma 0.005; the same pair with exact
    frames -> -0.003 px). The simulator renders with cv2.remap, so its cross-lane links
    carry the same rendering error.
    """
    tex, grid = world
    rng = np.random.default_rng(5)
    pose_a = np.array([0.0, -0.2, 0.0])
    pose_b = np.array([12.5 * PX, 0.2, np.pi])
    a, b = cut(tex, grid, pose_a, rng), cut(tex, grid, pose_b, rng)
    rel_true = se2_between(pose_a, pose_b)
    prior = rel_true + np.array([-0.004, 0.0025, -0.002])  # ~2 px, 2 mrad off
    r = register_pair(a, VALID, b, VALID, prior, PX, 10.0, 0.005, PARAMS)
    assert r.ok, r.reason
    assert accepted(r), (r.ncc, r.uniqueness)
    assert abs(abs(r.rel[2]) - np.pi) < 0.02
    t_err, r_err = errors(r.rel, rel_true)
    assert t_err < 0.05, f"translation error {t_err:.4f} px"
    assert r_err < 0.05
    assert np.all(np.linalg.eigvalsh(r.cov) > 0)
    assert mahalanobis2(r, rel_true) < 30.0
    assert 0.2 < r.overlap < 0.5


def test_valid_mask_reaching_the_image_edge(world):
    tex, grid = world
    rng = np.random.default_rng(5)
    pose_a = np.array([0.0, -0.2, 0.002])
    pose_b = np.array([0.031, 0.2, np.pi - 0.004])
    a, b = cut(tex, grid, pose_a, rng), cut(tex, grid, pose_b, rng)
    rel_true = se2_between(pose_a, pose_b)
    full = np.ones(SHAPE, bool)
    r = register_pair(a, full, b, full, rel_true + np.array([-0.004, 0.0025, -0.002]), PX, 10.0, 0.005, PARAMS)
    assert r.ok, r.reason
    assert errors(r.rel, rel_true)[0] < 0.05


def test_no_overlap_is_refused_with_a_reason(world):
    tex, grid = world
    rng = np.random.default_rng(1)
    a = cut(tex, grid, (-0.45, 0.0, 0.0), rng)
    b = cut(tex, grid, (0.45, 0.0, 0.0), rng)
    prior = np.array([0.9, 0.0, 0.0])  # 0.9 m apart, frames are 0.8 m wide
    r = register_pair(a, VALID, b, VALID, prior, PX, 8.0, 0.005, PARAMS)
    assert not r.ok
    assert r.reason and "overlap" in r.reason


def test_constant_frame_is_rejected(world):
    tex, grid = world
    rng = np.random.default_rng(2)
    textured = cut(tex, grid, (0.0, 0.0, 0.0), rng)
    flat = np.full(SHAPE, 128.0, np.float32)
    flat_noisy = (flat + NOISE * rng.standard_normal(SHAPE)).astype(np.float32)
    prior = np.array([0.04, 0.0, 0.0])
    for a, b in ((textured, flat), (flat, textured), (flat, flat), (textured, flat_noisy), (flat_noisy, textured)):
        r = register_pair(a, VALID, b, VALID, prior, PX, 8.0, 0.005, PARAMS)
        assert not accepted(r), (r.ok, r.reason, r.ncc, r.uniqueness)
        if not r.ok:
            assert r.reason


def test_periodic_texture_has_low_uniqueness():
    """A repeated pattern (period below the search window) correlates as well one period away."""
    rng = np.random.default_rng(3)
    period = 10
    tile = cv2.GaussianBlur(rng.standard_normal((period, period)).astype(np.float32), (0, 0), 1.0)
    big = np.tile(tile, (SHAPE[0] // period + 4, SHAPE[1] // period + 4))
    big = 128 + 30 * big / big.std()
    a = (big[:SHAPE[0], :SHAPE[1]] + NOISE * rng.standard_normal(SHAPE)).astype(np.float32)
    b = (big[:SHAPE[0], 3 : 3 + SHAPE[1]] + NOISE * rng.standard_normal(SHAPE)).astype(np.float32)
    prior = np.array([3 * PX, 0.0, 0.0])  # b is a shifted 3 px along +x
    r = register_pair(a, VALID, b, VALID, prior, PX, 12.0, 0.005, PARAMS)
    assert r.uniqueness < MIN_UNIQ, r.uniqueness
    assert not accepted(r)


def test_stripes_have_low_uniqueness():
    """One-directional texture (brushed floor): the match slides along the stripes."""
    rng = np.random.default_rng(4)
    x = np.arange(SHAPE[1] + 40, dtype=np.float32)
    profile = cv2.GaussianBlur(rng.standard_normal((1, len(x))).astype(np.float32), (0, 0), 1.5)[0]
    big = np.tile(128 + 30 * profile / profile.std(), (SHAPE[0] + 40, 1))
    a = (big[:SHAPE[0], :SHAPE[1]] + NOISE * rng.standard_normal(SHAPE)).astype(np.float32)
    b = (big[5 : 5 + SHAPE[0], 2 : 2 + SHAPE[1]] + NOISE * rng.standard_normal(SHAPE)).astype(np.float32)
    prior = np.array([2 * PX, -5 * PX, 0.0])
    r = register_pair(a, VALID, b, VALID, prior, PX, 8.0, 0.005, PARAMS)
    assert not accepted(r), (r.ok, r.reason, r.ncc, r.uniqueness)


def test_smooth_texture_is_not_ambiguous():
    """Coarse, smooth texture (blobs of ~6 px): the NCC peak is broad, so 5 px from it the
    surface is still high; that shoulder is no competing peak. C2 counts local maxima only
    (measured: C1 - C2 was 0.10 with the shoulder counted, rejecting a pair that registers
    to 0.004 px; the periodic and striped textures above stay rejected)."""
    rng = np.random.default_rng(21)
    grid = MapGrid.covering(-0.9, -0.9, 0.9, 0.9, PX)
    blobs = cv2.GaussianBlur(rng.standard_normal(grid.shape).astype(np.float32), (0, 0), 6.0)
    tex = 128 + 20 * blobs / blobs.std()
    pa, pb = np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.02, 0.01])
    a, b = cut(tex, grid, pa, rng), cut(tex, grid, pb, rng)
    true = se2_between(pa, pb)
    r = register_pair(a, VALID, b, VALID, true + np.array([2 * PX, -PX, 0.0]), PX, 5.0, 0.001, PARAMS)
    assert accepted(r), (r.ok, r.reason, r.ncc, r.uniqueness)
    t, rot = errors(r.rel, true)
    assert t < 0.05 and rot < 0.05, (t, rot)


# --- candidates -------------------------------------------------------------------------

LANES = 3
LANE_FRAMES = 21  # 2 m lanes, a frame every 0.1 m
LANE_DY = 0.4  # 2/3 of the 0.6 m footprint height: 1/3 side overlap


def lawnmower_priors() -> np.ndarray:
    rows = []
    for k in range(LANES):
        xs = np.linspace(0.0, 2.0, LANE_FRAMES)
        if k % 2:
            xs = xs[::-1]
        for x in xs:
            rows.append((x, k * LANE_DY, 0.0 if k % 2 == 0 else np.pi))
    return np.array(rows)


def lane_of(i: np.ndarray) -> np.ndarray:
    return np.asarray(i) // LANE_FRAMES


@pytest.fixture
def table() -> FrameTable:
    return FrameTable.from_priors([lawnmower_priors()], [SHAPE], PX)


def test_sequential_candidates(table):
    reg, opt = CFG["register"], CFG["optimize"]
    c = sequential_candidates(table, reg, opt)
    pairs = set(zip(c.a.tolist(), c.b.tolist()))
    n = len(table.prior)
    assert all(1 <= b - a <= reg["sequential_window"] for a, b in pairs)
    # Every consecutive pair and every pair two apart inside a lane (overlaps 7/8 and 3/4).
    for i in range(n - 1):
        assert (i, i + 1) in pairs
    for i in range(n - 2):
        if lane_of(i) == lane_of(i + 2):
            assert (i, i + 2) in pairs
    assert np.all(c.sequential)
    assert np.all(c.overlap >= reg["min_predicted_overlap"])
    # Search radius from the odometry's uncertainty: more path between the frames, wider.
    r = dict(zip(pairs_list(c), c.radius_px.tolist()))
    for i in range(n - 2):
        if lane_of(i) == lane_of(i + 2):
            assert r[(i, i + 2)] > r[(i, i + 1)]
    assert np.all(c.radius_px >= reg["search_floor_px"])


def pairs_list(c) -> list[tuple[int, int]]:
    return list(zip(c.a.tolist(), c.b.tolist()))


def test_revisit_candidates_cross_lanes(table):
    reg, opt = CFG["register"], CFG["optimize"]
    unc = ChainUncertainty.odometry(table, opt)
    c = revisit_candidates(table, table.prior, unc, reg, opt)
    assert len(c) > 0
    assert not np.any(c.sequential)
    la, lb = lane_of(c.a), lane_of(c.b)
    # Only adjacent lanes overlap (0.4 m apart; 0.8 m apart do not), with footprints (0.8 m
    # long) that meet.
    assert np.all(np.abs(la - lb) == 1)
    assert np.all(np.abs(table.prior[c.a, 0] - table.prior[c.b, 0]) < 0.8)
    assert np.all(c.overlap >= reg["min_predicted_overlap"])
    # No more than max_revisits_per_frame per frame; every middle-lane frame away from the
    # lane ends has partners in both neighbouring lanes.
    counts = np.bincount(np.r_[c.a, c.b], minlength=len(table.prior))
    assert counts.max() <= reg["max_revisits_per_frame"]
    # Frames near the lane ends are less than revisit_min_path_m of path from their cross-lane
    # neighbours (through the turn): they are neither sequential nor revisit pairs. Away
    # from the ends (x in [0.6, 1.4] m: >= 1.6 m of path), every frame has a partner.
    mid_x = np.abs(table.prior[:, 0] - 1.0) <= 0.4 + 1e-9
    for i in np.flatnonzero(mid_x):
        partners = np.r_[c.b[c.a == i], c.a[c.b == i]]
        assert len(partners) >= 1, i
    # The middle lane pairs with both neighbours.
    mid = (la == 1) | (lb == 1)
    assert set(np.r_[la[mid], lb[mid]].tolist()) == {0, 1, 2}
    # The pair at the same x in lanes 0 and 1 is there (lane 1 runs backwards).
    assert (5, 2 * LANE_FRAMES - 1 - 5) in set(pairs_list(c))
    # Radius grows with the path travelled between the two frames.
    gap = np.abs(table.path_m[c.b] - table.path_m[c.a])
    order = np.argsort(gap, kind="stable")
    assert np.all(np.diff(c.radius_px[order]) >= -1e-9)
    assert c.radius_px[order[-1]] > c.radius_px[order[0]] + 1.0


def test_chain_uncertainty_shrinks_where_links_hold(table):
    reg, opt = CFG["register"], CFG["optimize"]
    n = len(table.prior)
    odo = ChainUncertainty.odometry(table, opt)
    tight = ChainUncertainty.from_steps(table, np.full(n, (0.01 * PX) ** 2), np.full(n, 1e-10))
    c_odo = revisit_candidates(table, table.prior, odo, reg, opt)
    c_tight = revisit_candidates(table, table.prior, tight, reg, opt)
    # (footprints are grown by the search radius when predicting overlaps, so the pairs at
    # the edge of overlapping may differ; the common ones search much less)
    common = set(pairs_list(c_odo)) & set(pairs_list(c_tight))
    assert len(common) >= 0.9 * len(c_tight)
    r_odo = dict(zip(pairs_list(c_odo), c_odo.radius_px))
    r_tight = dict(zip(pairs_list(c_tight), c_tight.radius_px))
    assert all(r_tight[p] < r_odo[p] for p in common)
    assert np.allclose(c_tight.radius_px, reg["search_floor_px"], atol=0.5)


def _step_links(prior: np.ndarray, sigma_m: float = 0.05 * PX) -> list[Link]:
    cov = np.diag([sigma_m**2, sigma_m**2, 1e-8])
    return [Link(i, i + 1, se2_between(prior[i], prior[i + 1]), cov.copy(), 0.95, 0.6, 0.9, 50000, "correlation")
            for i in range(len(prior) - 1)]


def test_chain_from_links_gates_a_link_that_disagrees_with_odometry(table):
    reg, opt = CFG["register"], CFG["optimize"]
    prior = table.prior
    links = _step_links(prior)
    # A small, plausible correction (1 mm, < 1 odometry sigma over 0.1 m) is taken ...
    links[3].rel = links[3].rel + np.array([0.001, 0.0, 0.0])
    # ... a wrong link (5 cm off, ~33 sigmas) is not; nor is a rejected one.
    links[10].rel = links[10].rel + np.array([0.0, 0.05, 0.0])
    links[30].rel = links[30].rel + np.array([0.0005, 0.0, 0.0])
    links[30].status = "rejected"
    chain, unc = chain_from_links(table, links, opt, reg["chain_gate_sigmas"])
    # A held step is the link fused with the odometry step (inverse-covariance weights):
    # the link, 12x sharper, pulls it to within (1 / (1 + 144)) of itself.
    odo_sig = opt["odometry_error_gradient"] * 0.1 + opt["odometry_sigma_floor_m"]
    w_link = odo_sig**2 / (odo_sig**2 + (0.05 * PX) ** 2)
    # Frames 0..3 follow odometry; from frame 4 on, the 1 mm correction carries through.
    assert np.allclose(chain[:4], prior[:4])
    d = np.hypot(*(chain[4:, :2] - prior[4:, :2]).T)
    assert np.allclose(d, 0.001 * w_link, atol=1e-9)
    assert not np.any(d > 0.002), "the 5 cm link must not enter the chain"
    # Uncertainty: tiny steps where links hold, the odometry's where the link was gated or rejected.
    step_var = np.diff(unc.cum_var_t)
    link_var = 2 * (0.05 * PX) ** 2 * w_link
    assert np.isclose(step_var[0], link_var)
    assert np.isclose(step_var[10], odo_sig**2)
    assert np.isclose(step_var[30], odo_sig**2)
    assert np.isclose(step_var[3], link_var)
