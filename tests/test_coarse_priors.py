"""Unit tests for the coarse stage and the prior helpers around registration.

- :mod:`pipeline.coarse`: phase-correlation shift of b against a near a prior warp, on
  crops of one band-limited random texture at known integer offsets (convention
  ``a(x) ~ bw(x + shift)``: with ``a = T[y, x]``, ``b = T[y + oy, x + ox]`` and a prior
  ``a_to_b`` translating by ``t``, the answer is ``shift = -o - t``, i.e. the corrected warp
  ``x -> x + t + shift`` is the true ``x -> x - o``).
- :mod:`pipeline.peak_null`: the null-pair threshold and the choice of null pairs, checked
  exactly against hand-computed values.
- :mod:`pipeline.prior_bias`: a straight log whose prior heading is flipped by pi over a run
  of frames (positions right), and a log whose prior positions are 5 % too long, with links
  carrying the true relative poses.
- :mod:`pipeline.odometry_model`: the (5,) error models of absolute and odometry priors.

All images are at most 512 x 1024 px; the whole file runs in well under 10 s.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from conftest import smooth_texture
from mapstore.grid import se2_between, wrap_angle
from pipeline.coarse import CoarseParams, CoarseResult, coarse_shift
from pipeline.links import Link
from pipeline.odometry_model import (STAGE_MAX_HEADING_SIGMA_RAD, absolute_sigmas, default_model, inflated_table,
                                     is_stage, log_model)
from pipeline.peak_null import NullFigures, null_pairs, null_threshold
from pipeline.prior_bias import BiasParams, estimate_prior_correction
from pipeline.registration import RegistrationParams

REPO = Path(__file__).resolve().parents[1]
with open(REPO / "configs" / "floor.toml", "rb") as _f:
    FLOOR = tomllib.load(_f)
REGISTER = FLOOR["register"]
OPTIMIZE = FLOOR["optimize"]


def _translation(tx: float, ty: float) -> np.ndarray:
    """2 x 3 affine ``x -> x + (tx, ty)`` (a's pixel -> b's pixel)."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty]])


def _ones(shape: tuple[int, int]) -> np.ndarray:
    return np.ones(shape, bool)


# --------------------------------------------------------------------------- coarse


def test_coarse_params_from_floor_config_match_dataclass_defaults():
    # The tests below use the dataclass defaults; they are the configured values.
    assert RegistrationParams.from_config(REGISTER).coarse == CoarseParams()


@pytest.mark.parametrize("prior_t", [(0.0, 0.0), (3.0, -2.0), (-6.0, 4.0)])
def test_coarse_recovers_known_integer_offset_with_sign_convention(prior_t):
    rng = np.random.default_rng(1)
    tex = smooth_texture(rng, (320, 320))
    ox, oy = 7, -5  # b(x) = a(x + o): the true warp a -> b is x -> x - o
    a = tex[40:296, 40:296] + rng.normal(0, 2, (256, 256)).astype(np.float32)
    b = tex[40 + oy:296 + oy, 40 + ox:296 + ox] + rng.normal(0, 2, (256, 256)).astype(np.float32)
    prior = _translation(*prior_t)

    r = coarse_shift(a, _ones(a.shape), b, _ones(b.shape), prior, 20, CoarseParams())

    assert isinstance(r, CoarseResult), r
    expected = np.array([-ox - prior_t[0], -oy - prior_t[1]])
    np.testing.assert_allclose(r.shift, expected, atol=0.5)
    # the corrected warp (prior composed with a translation by the shift) is the true one
    np.testing.assert_allclose(prior[:, 2] + r.shift, [-ox, -oy], atol=0.5)
    assert r.scale == 1
    assert r.peak_z > 50
    assert r.uniqueness > 0.5
    assert 0 < r.peak <= 1.0
    assert r.overlap_px >= CoarseParams().min_overlap_px


@pytest.mark.parametrize("prior_error_px", [24, -24])
def test_coarse_narrow_strip_with_wrong_prior_finds_true_shift(prior_error_px):
    # Two 512 x 512 crops side by side overlapping by 15 px; the prior puts b 24 px off.
    rng = np.random.default_rng(3)
    tex = smooth_texture(rng, (512, 1024))
    overlap = 15
    off = 512 - overlap  # b(x) = a(x + off): true warp x -> x - off
    a = tex[:, :512] + rng.normal(0, 2, (512, 512)).astype(np.float32)
    b = tex[:, off:off + 512] + rng.normal(0, 2, (512, 512)).astype(np.float32)
    prior = _translation(-off + prior_error_px, 0.0)

    r = coarse_shift(a, _ones(a.shape), b, _ones(b.shape), prior, 60, CoarseParams())

    assert isinstance(r, CoarseResult), r
    truth = np.array([-prior_error_px, 0.0])
    assert np.hypot(*(r.shift - truth)) < 1.0, r.shift
    assert np.isnan(r.ncc) or r.ncc > 0.5
    # (on this seed the peaks are told apart by their NCC, and it is decisive)
    assert np.isfinite(r.ncc)
    assert r.uniqueness > 0.5


def test_coarse_flat_pair_returns_reason():
    flat = np.full((128, 128), 100.0, np.float32)
    r = coarse_shift(flat, _ones(flat.shape), flat.copy(), _ones(flat.shape), _translation(0, 0), 10,
                     CoarseParams())
    assert isinstance(r, str)
    assert "flat" in r


def test_coarse_frames_out_of_reach_return_reason():
    rng = np.random.default_rng(4)
    a = smooth_texture(rng, (128, 128))
    b = smooth_texture(rng, (128, 128))
    # the prior puts b 1000 px to the right of a, the radius is 20 px
    r = coarse_shift(a, _ones(a.shape), b, _ones(b.shape), _translation(-1000, 0), 20, CoarseParams())
    assert isinstance(r, str)
    assert "overlap" in r


@pytest.mark.parametrize("noise", [0.0, 2.0])
def test_coarse_periodic_texture_has_low_uniqueness(noise):
    # A random 12 x 12 tile repeated: shifts one period apart match equally well.
    rng = np.random.default_rng(0)
    period = 12
    tex = np.tile(smooth_texture(rng, (period, period)), (25, 25)).astype(np.float32)
    ox, oy = 5, 3
    a = tex[20:276, 20:276] + rng.normal(0, noise, (256, 256)).astype(np.float32)
    b = tex[20 + oy:276 + oy, 20 + ox:276 + ox] + rng.normal(0, noise, (256, 256)).astype(np.float32)

    r = coarse_shift(a, _ones(a.shape), b, _ones(b.shape), _translation(0, 0), 20, CoarseParams())

    assert isinstance(r, CoarseResult), r
    assert r.uniqueness < 0.2
    # whichever period it picked, the shift is the true one modulo the period
    residual = (r.shift - np.array([-ox, -oy]) + period / 2) % period - period / 2
    np.testing.assert_allclose(residual, 0.0, atol=0.5)


# --------------------------------------------------------------------------- peak_null

Z10 = np.array([1, 2, 3, 4, 5, 6, 7, 8, 9, 100], float)
# median 5.5; |z - 5.5| = 4.5 3.5 2.5 1.5 .5 .5 1.5 2.5 3.5 94.5 -> MAD 2.5
Z10_MED, Z10_MAD = 5.5, 2.5


def test_null_threshold_median_plus_k_mad():
    f = null_threshold(Z10, floor=4.0, k=3.0)
    assert f.pairs == 10
    assert f.median_z == pytest.approx(Z10_MED)
    assert f.mad_z == pytest.approx(Z10_MAD)
    assert f.max_z == pytest.approx(100.0)
    assert f.threshold_z == pytest.approx(Z10_MED + 3.0 * 1.4826 * Z10_MAD)  # 16.6195
    # no NCCs: the NCC threshold is the floor (1.0 by default), medians NaN
    assert f.threshold_ncc == 1.0
    assert np.isnan(f.median_ncc) and np.isnan(f.max_ncc)


def test_null_threshold_floor_wins_when_higher():
    f = null_threshold(Z10, floor=20.0, k=3.0)
    assert f.threshold_z == 20.0
    assert f.median_z == pytest.approx(Z10_MED)


def test_null_threshold_ignores_nans():
    with_nan = np.concatenate([Z10, [np.nan, np.nan, np.nan]])
    f = null_threshold(with_nan, floor=4.0, k=3.0)
    g = null_threshold(Z10, floor=4.0, k=3.0)
    assert f.pairs == 10
    assert f.threshold_z == pytest.approx(g.threshold_z)
    assert f.max_z == pytest.approx(100.0)


def test_null_threshold_fewer_than_eight_finite_values_gives_floor():
    z = np.array([1, 2, 3, 50, 60, 70, 80, np.nan, np.nan, np.nan])  # 7 finite
    f = null_threshold(z, floor=6.0, k=3.0)
    assert f.pairs == 7
    assert f.threshold_z == 6.0
    assert np.isnan(f.median_z) and np.isnan(f.mad_z)
    assert f.max_z == 80.0
    empty = null_threshold(np.zeros(0), floor=6.0, k=3.0)
    assert empty.pairs == 0 and empty.threshold_z == 6.0 and np.isnan(empty.max_z)


def test_null_threshold_ncc_likewise_with_floor_and_cap_at_one():
    ncc = np.array([0.1, 0.2, 0.2, 0.3, 0.3, 0.3, 0.4, 0.5, np.nan, np.nan])  # 8 finite
    # median 0.3; |ncc - 0.3| = .2 .1 .1 0 0 0 .1 .2 -> MAD 0.1
    f = null_threshold(Z10, floor=4.0, k=3.0, ncc=ncc, ncc_floor=0.2)
    assert f.median_ncc == pytest.approx(0.3)
    assert f.max_ncc == pytest.approx(0.5)
    assert f.threshold_ncc == pytest.approx(0.3 + 3.0 * 1.4826 * 0.1)  # 0.7448
    # the floor wins when higher
    assert null_threshold(Z10, 4.0, 3.0, ncc=ncc, ncc_floor=0.9).threshold_ncc == pytest.approx(0.9)
    # capped at 1: a wide spread, or a floor above 1
    assert null_threshold(Z10, 4.0, 10.0, ncc=ncc, ncc_floor=0.2).threshold_ncc == 1.0
    assert null_threshold(Z10, 4.0, 3.0, ncc=ncc, ncc_floor=1.5).threshold_ncc == 1.0
    # fewer than 8 finite NCCs: the floor alone
    assert null_threshold(Z10, 4.0, 3.0, ncc=ncc[:7], ncc_floor=0.6).threshold_ncc == 0.6


def test_null_figures_accepts_by_peak_or_by_ncc():
    f = NullFigures(pairs=10, median_z=5.0, mad_z=1.0, max_z=9.0, threshold_z=8.0, threshold_ncc=0.7)
    assert f.accepts(8.0, float("nan"))  # at the threshold
    assert f.accepts(12.0, 0.1)
    assert not f.accepts(7.9, float("nan"))  # NaN NCC never accepts
    assert not f.accepts(7.9, 0.69)
    assert f.accepts(3.0, 0.7)  # by the NCC alone
    assert f.to_dict()["threshold_ncc"] == 0.7


def _line_log(n: int = 40, step: float = 0.1) -> np.ndarray:
    """Poses along x, ``step`` metres apart."""
    return np.stack([step * np.arange(n), np.zeros(n), np.zeros(n)], axis=1)


def test_null_pairs_are_far_apart():
    prior = _line_log(40)
    shapes = np.full((40, 2), 100)
    shapes[7] = (400, 300)  # one large frame: its diagonal counts for pairs it takes part in
    px = 0.001
    diag = np.hypot(shapes[:, 0], shapes[:, 1]) * px
    a = np.arange(0, 40, 2)
    pairs = null_pairs(prior, shapes, px, a, count=15, far_diagonals=3.0, seed=5)
    assert 0 < len(pairs) <= 15
    for i, c in pairs:
        ai = a[i]
        d = np.hypot(*(prior[c, :2] - prior[ai, :2]))
        assert d > 3.0 * max(diag[c], diag[ai]), (ai, c, d)
    # frame 7 is 0.5 m across: 3 diagonals = 1.5 m, i.e. 15 or more frames away (0.1 m apart)
    from7 = null_pairs(prior, shapes, px, np.array([7]), count=10, far_diagonals=3.0, seed=5)
    assert from7
    assert all(c >= 7 + 15 for _, c in from7)
    # ... and no partner for frame 0, 0.7 m away: far from a small frame (3 diagonals are
    # 0.42 m), but not from itself
    only = np.zeros(40, bool)
    only[[6, 7, 8]] = True
    from0 = null_pairs(prior, shapes, px, np.zeros(20, int), count=20, far_diagonals=3.0, seed=5, eligible=only)
    assert len(from0) == 20
    assert {c for _, c in from0} == {6, 8}


def test_null_pairs_deterministic_for_a_seed():
    prior = _line_log(40)
    shapes = np.full((40, 2), 100)
    a = np.arange(40)
    p1 = null_pairs(prior, shapes, 0.001, a, 10, 3.0, seed=11)
    p2 = null_pairs(prior, shapes, 0.001, a, 10, 3.0, seed=11)
    p3 = null_pairs(prior, shapes, 0.001, a, 10, 3.0, seed=12)
    assert p1 == p2
    assert len(p1) == 10
    assert p1 != p3
    assert all(isinstance(i, int) and isinstance(c, int) for i, c in p1)


def test_null_pairs_respect_eligible():
    prior = _line_log(40)
    shapes = np.full((40, 2), 100)
    a = np.arange(40)
    eligible = np.zeros(40, bool)
    eligible[[0, 1, 38, 39]] = True
    pairs = null_pairs(prior, shapes, 0.001, a, 20, 3.0, seed=0, eligible=eligible)
    assert pairs
    assert all(eligible[c] for _, c in pairs)
    # no eligible frame far enough from any first frame: no pairs
    near = np.zeros(40, bool)
    near[20] = True
    assert null_pairs(prior, shapes, 0.001, np.array([19, 20, 21]), 5, 3.0, eligible=near) == []


def test_null_pairs_empty_inputs():
    prior = _line_log(40)
    shapes = np.full((40, 2), 100)
    assert null_pairs(prior, shapes, 0.001, np.zeros(0, int), 5, 3.0) == []
    assert null_pairs(prior[:1], shapes[:1], 0.001, np.array([0]), 5, 3.0) == []
    # a log shorter than the separation: nothing is far enough
    assert null_pairs(prior, shapes, 0.01, np.arange(40), 5, 3.0) == []


# --------------------------------------------------------------------------- prior_bias

PX_BIAS = 0.001  # metres per pixel: a 0.05 m step is 50 px, well above prior_min_step_px


def _true_line(n: int = 30, step: float = 0.05) -> np.ndarray:
    return np.stack([step * np.arange(n), np.zeros(n), np.zeros(n)], axis=1)


def _sequential_links(true: np.ndarray, rng: np.random.Generator | None = None) -> list[Link]:
    """Accepted links between consecutive frames carrying the true relative poses (plus a
    little measurement noise when ``rng`` is given)."""
    links = []
    for i in range(len(true) - 1):
        rel = se2_between(true[i], true[i + 1])
        if rng is not None:
            rel = rel + rng.normal(0, [3e-4, 3e-4, 2e-3])
        links.append(Link(i, i + 1, rel, np.diag([1e-8, 1e-8, 1e-6]), 0.9, 0.8, 0.5, 1000, "correlation"))
    return links


def test_bias_params_from_floor_config():
    p = BiasParams.from_config(REGISTER)
    assert p == BiasParams(float(REGISTER["prior_min_step_px"]), float(REGISTER["prior_heading_threshold_rad"]),
                           int(REGISTER["prior_min_run_frames"]), int(REGISTER["prior_smoothing_links"]),
                           float(REGISTER["prior_scale_threshold"]), int(REGISTER["prior_min_scale_links"]))
    assert p.min_run_frames <= 11  # the flipped run below is long enough


def test_prior_heading_flipped_run_is_corrected():
    n = 30
    true = _true_line(n)
    prior = true.copy()
    flipped = np.arange(10, 21)  # frames 10..20
    prior[flipped, 2] = wrap_angle(prior[flipped, 2] + np.pi)
    links = _sequential_links(true, np.random.default_rng(0))
    p = BiasParams.from_config(REGISTER)

    c = estimate_prior_correction(prior, np.zeros(n, int), np.zeros(n, bool), links, PX_BIAS, p)

    assert c.any
    assert len(c.heading_segments) == 1
    seg = c.heading_segments[0]
    assert (seg["log"], seg["first_frame"], seg["last_frame"]) == (0, 10, 20)
    assert abs(seg["offset_rad_median"]) == pytest.approx(np.pi, abs=0.05)
    np.testing.assert_array_equal(np.flatnonzero(c.changed), flipped)
    # the flipped frames get their true heading back, up to the links' noise
    err = wrap_angle(c.prior[flipped, 2] - true[flipped, 2])
    assert np.abs(err).max() < 0.05
    # positions are kept everywhere; the other frames are untouched
    np.testing.assert_array_equal(c.prior[:, :2], prior[:, :2])
    others = np.setdiff1d(np.arange(n), flipped)
    np.testing.assert_array_equal(c.prior[others], prior[others])
    assert c.scales == []  # positions were right: no scale
    assert c.to_dict()["frames_corrected"] == len(flipped)


def test_prior_heading_run_shorter_than_min_run_is_left_alone():
    n = 30
    true = _true_line(n)
    prior = true.copy()
    prior[10:13, 2] = np.pi  # three frames only
    p = BiasParams.from_config(REGISTER)
    assert p.min_run_frames > 3
    c = estimate_prior_correction(prior, np.zeros(n, int), np.zeros(n, bool), _sequential_links(true), PX_BIAS, p)
    assert not c.any
    np.testing.assert_array_equal(c.prior, prior)
    assert not c.changed.any()


def test_prior_consistent_with_links_is_unchanged():
    n = 30
    true = _true_line(n)
    p = BiasParams.from_config(REGISTER)
    links = _sequential_links(true, np.random.default_rng(1))
    c = estimate_prior_correction(true, np.zeros(n, int), np.zeros(n, bool), links, PX_BIAS, p)
    assert not c.any
    np.testing.assert_array_equal(c.prior, true)


def test_prior_odometry_scale_error_is_corrected():
    n = 30
    true = _true_line(n)
    true[:, 1] = 0.2  # not through the origin: scaling is about the first frame
    prior = true.copy()
    prior[:, :2] = true[0, :2] + 1.05 * (true[:, :2] - true[0, :2])  # odometry 5 % long
    p = BiasParams.from_config(REGISTER)
    links = _sequential_links(true)
    assert len(links) >= p.min_scale_links

    c = estimate_prior_correction(prior, np.zeros(n, int), np.zeros(n, bool), links, PX_BIAS, p)

    assert c.heading_segments == []
    assert len(c.scales) == 1
    # the scale is the median |link| / |odo|, applied to the prior: 1 / 1.05
    assert c.scales[0]["scale"] == pytest.approx(1 / 1.05, abs=1e-4)
    assert c.scales[0]["links"] == n - 1
    np.testing.assert_allclose(c.prior[:, :2], true[:, :2], atol=1e-9)
    np.testing.assert_array_equal(c.prior[:, 2], prior[:, 2])
    assert c.changed.all()


def test_prior_scale_not_applied_to_absolute_priors():
    n = 30
    true = _true_line(n)
    prior = true.copy()
    prior[:, :2] *= 1.05
    p = BiasParams.from_config(REGISTER)
    c = estimate_prior_correction(prior, np.zeros(n, int), np.ones(n, bool), _sequential_links(true), PX_BIAS, p)
    assert c.scales == []
    np.testing.assert_array_equal(c.prior, prior)


def test_prior_correction_is_per_log():
    # two logs of 30 frames; only log 1 has a flipped run; a link across logs is ignored
    n = 30
    true = np.vstack([_true_line(n), _true_line(n) + [0.0, 1.0, 0.0]])
    prior = true.copy()
    prior[n + 5:n + 17, 2] = np.pi  # frames 35..46
    links = _sequential_links(true[:n]) + [
        Link(n + lk.a, n + lk.b, lk.rel, lk.cov, 0.9, 0.8, 0.5, 1000, "correlation")
        for lk in _sequential_links(true[n:])
    ]
    links.append(Link(n - 1, n, np.array([-0.05, 0.0, 0.0]), np.eye(3) * 1e-8, 0.9, 0.8, 0.5, 1000, "correlation"))
    log = np.repeat([0, 1], n)
    p = BiasParams.from_config(REGISTER)
    c = estimate_prior_correction(prior, log, np.zeros(2 * n, bool), links, PX_BIAS, p)
    assert [(s["log"], s["first_frame"], s["last_frame"]) for s in c.heading_segments] == [(1, n + 5, n + 16)]
    np.testing.assert_array_equal(np.flatnonzero(c.changed), np.arange(n + 5, n + 17))


# --------------------------------------------------------------------------- odometry_model


def test_log_model_absolute_table():
    m = log_model(OPTIMIZE, {"kind": "absolute", "sigma_m": 0.5, "heading_sigma_rad": 0.1})
    np.testing.assert_allclose(m, [0.0, np.sqrt(2) * 0.5, 0.0, np.sqrt(2) * 0.1, 1.0])
    # the per-pose sigmas come back out
    assert absolute_sigmas(m) == pytest.approx((0.5, 0.1))


def test_log_model_default_uses_optimize_odometry_keys():
    expected = [OPTIMIZE["odometry_error_gradient"], OPTIMIZE["odometry_sigma_floor_m"],
                OPTIMIZE["odometry_heading_sigma_per_m"], OPTIMIZE["odometry_heading_sigma_floor_rad"], 0.0]
    np.testing.assert_array_equal(log_model(OPTIMIZE, None), expected)
    np.testing.assert_array_equal(log_model(OPTIMIZE, {}), expected)
    np.testing.assert_array_equal(default_model(OPTIMIZE), expected)
    assert absolute_sigmas(log_model(OPTIMIZE, None)) is None


def test_log_model_odometry_table_overrides_only_its_fields():
    m = log_model(OPTIMIZE, {"error_gradient": 0.03, "heading_sigma_floor_rad": 0.002})
    base = default_model(OPTIMIZE)
    np.testing.assert_array_equal(m, [0.03, base[1], base[2], 0.002, 0.0])


def test_is_stage():
    stage = log_model(OPTIMIZE, {"kind": "absolute", "sigma_m": 1e-5, "heading_sigma_rad": 0.002})
    gps = log_model(OPTIMIZE, {"kind": "absolute", "sigma_m": 2.0, "heading_sigma_rad": 0.1})
    odometry = log_model(OPTIMIZE, None)
    assert is_stage(stage)
    assert not is_stage(gps)
    assert not is_stage(odometry)
    # even an odometry model with a tiny heading sigma is no stage (not absolute)
    assert not is_stage(log_model(OPTIMIZE, {"heading_sigma_floor_rad": 0.0, "heading_sigma_per_m": 0.0}))
    # the limit applies to the stored (two-pose, sqrt 2 larger) heading sigma
    per_pose_limit = STAGE_MAX_HEADING_SIGMA_RAD / np.sqrt(2)

    def absolute(heading: float) -> np.ndarray:
        return log_model(OPTIMIZE, {"kind": "absolute", "sigma_m": 1e-5, "heading_sigma_rad": heading})

    assert is_stage(absolute(0.99 * per_pose_limit))
    assert not is_stage(absolute(1.01 * per_pose_limit))


def test_inflated_table_absolute_multiplies_sigmas():
    table = {"kind": "absolute", "sigma_m": 0.5, "heading_sigma_rad": 0.1}
    out = inflated_table(OPTIMIZE, table, 3.0, 2.0)
    assert out == {"kind": "absolute", "sigma_m": pytest.approx(1.5), "heading_sigma_rad": pytest.approx(0.2)}
    assert table == {"kind": "absolute", "sigma_m": 0.5, "heading_sigma_rad": 0.1}  # input not modified
    np.testing.assert_allclose(log_model(OPTIMIZE, out), log_model(OPTIMIZE, table) * [1, 3, 1, 2, 1])


@pytest.mark.parametrize("table", [None, {"error_gradient": 0.03}])
def test_inflated_table_odometry_multiplies_model(table):
    out = inflated_table(OPTIMIZE, table, 3.0, 2.0)
    assert set(out) == {"error_gradient", "sigma_floor_m", "heading_sigma_per_m", "heading_sigma_floor_rad"}
    np.testing.assert_allclose(log_model(OPTIMIZE, out), log_model(OPTIMIZE, table) * [3, 3, 2, 2, 1])


def test_coarse_radius_far_beyond_the_frames_keeps_the_search_small(monkeypatch):
    """A prior far less certain than the frames are large (a GPS prior's revisits: radii of
    1500-2500 px around 682 x 511 frames) still finds the shift, and the correlation surface
    stays within a few frame sides instead of growing with the radius (6000 x 6000 px, 4 GB
    at peak for a 60-frame drone log before)."""
    import pipeline.coarse as coarse

    rng = np.random.default_rng(5)
    tex = smooth_texture(rng, (360, 520))
    ox, oy = 120, 30  # b(x) = a(x + o)
    a = tex[40:296, 40:296] + rng.normal(0, 2, (256, 256)).astype(np.float32)
    b = tex[40 + oy:296 + oy, 40 + ox:296 + ox] + rng.normal(0, 2, (256, 256)).astype(np.float32)
    shapes = []
    surface = coarse._phase_surface

    def spy(pa, pb, *args, **kw):
        shapes.append(pa.shape)
        return surface(pa, pb, *args, **kw)

    monkeypatch.setattr(coarse, "_phase_surface", spy)
    prior = _translation(0.0, 0.0)  # 124 px off the truth, with a radius of 2000 px
    r = coarse_shift(a, _ones(a.shape), b, _ones(b.shape), prior, 2000, CoarseParams())
    assert isinstance(r, CoarseResult), r
    np.testing.assert_allclose(r.shift, [-ox, -oy], atol=0.5)
    assert shapes and max(h * w for h, w in shapes) <= 4 * 512 * 512, shapes
