"""Global pose optimization, ground-truth evaluation and plots on synthetic pose graphs.

Pure numpy graphs (pipeline.testing.synthgraph): lawnmower ground truth, drifting odometry (1 %),
links from the ground-truth relative poses plus noise drawn from their covariances.
"""

from __future__ import annotations

import numpy as np
import pytest

from mapstore.grid import se2_between, se2_compose
from pipeline.config import default_config
from pipeline.evaluate import absolute_trajectory_error, align_se2, ground_truth_at, link_errors
from pipeline.links import Link
from pipeline.optimize import optimize_poses
from pipeline.testing.synthgraph import synthetic_graph

PX = 0.0025


@pytest.fixture(scope="module")
def cfg() -> dict:
    return dict(default_config()["optimize"])


@pytest.fixture(scope="module")
def clean(cfg):
    g = synthetic_graph((5.0, 5.0), seed=1, pixel_size=PX)
    return g, optimize_poses(g.priors, g.links, cfg, pixel_size=PX)


def test_optimized_far_better_than_odometry(clean):
    g, r = clean
    odo = absolute_trajectory_error(np.concatenate(g.priors), g.gt, PX)
    ate = absolute_trajectory_error(r.poses, g.gt, PX)
    assert odo["rms_px"] > 1.0
    # Link noise is 0.005-0.02 px per axis: the poses must land near that level.
    assert ate["rms_px"] < 0.05 and ate["max_px"] < 0.15, ate
    assert ate["rms_px"] < odo["rms_px"] / 20
    assert r.poses.shape == (len(g.gt), 3)
    assert r.residual_rms_px < 0.05
    # chi2(3) at p = 0.999: about 0.1 % of good links may be flagged.
    assert r.rejected <= 5
    for lk in g.links:
        assert "residual_px" in lk.extra and "mahalanobis" in lk.extra
    assert r.marginal_cov is not None and r.marginal_cov.shape == (len(g.gt), 3, 3)
    assert np.all(np.linalg.eigvalsh(r.marginal_cov) > 0)
    assert r.seconds > 0 and r.iterations > 0


def test_corrupted_links_rejected_poses_unchanged(cfg, clean):
    g0, r0 = clean
    g = synthetic_graph((5.0, 5.0), seed=1, pixel_size=PX, corrupt_fraction=0.05)
    r = optimize_poses(g.priors, g.links, cfg, pixel_size=PX)
    rej = np.array([lk.status == "rejected" for lk in g.links])
    assert g.corrupted.sum() >= 50
    assert np.all(rej[g.corrupted]), "every corrupted link must be rejected"
    assert (rej & ~g.corrupted).sum() <= 5, "no more than a handful of good links rejected"
    assert r.rejected == rej.sum()
    for i in np.flatnonzero(g.corrupted):
        reason = g.links[i].reason
        assert reason.startswith("outlier: ")
        # Rejected by the chi-square test after optimization, or before it by the
        # odometry gate (corrupted links between nearby frames of one log).
        assert "> 16.27" in reason or "disagrees with odometry" in reason
    # The map hangs off frame 0's heading (the gauge), which the links at frame 0 set:
    # compare the poses after a rigid alignment.
    rot, t = align_se2(r.poses[:, :2], r0.poses[:, :2])
    d = np.linalg.norm(r.poses[:, :2] @ rot.T + t - r0.poses[:, :2], axis=1) / PX
    assert np.sqrt(np.mean(d**2)) <= 0.05
    assert absolute_trajectory_error(r.poses, g.gt, PX)["rms_px"] < 0.05


def test_two_logs_loose_prior_on_second(cfg):
    g = synthetic_graph((3.0, 3.0), seed=3, pixel_size=PX, n_logs=2)
    # The second log's odometry starts off its true pose by centimetres (a loose dock).
    g.priors[1] = se2_compose(np.array([0.03, -0.02, 0.01]), g.priors[1])
    r = optimize_poses(g.priors, g.links, cfg, pixel_size=PX)
    assert len(r.poses) == sum(len(p) for p in g.priors)
    ate = absolute_trajectory_error(r.poses, g.gt, PX)
    assert ate["rms_px"] < 0.05, ate
    # The first log stays in the site frame: its first frame at its odometry pose.
    np.testing.assert_allclose(r.poses[0], g.priors[0][0], atol=1e-5)


def test_without_links_odometry_is_kept(cfg):
    g = synthetic_graph((2.0, 2.0), seed=4, pixel_size=PX)
    r = optimize_poses(g.priors, [], cfg, pixel_size=PX)
    np.testing.assert_allclose(r.poses, g.priors[0], atol=1e-6)
    assert r.rejected == 0 and r.residual_rms_px == 0.0


def test_bad_links_raise(cfg):
    prior = np.zeros((3, 3))
    prior[:, 0] = [0.0, 0.1, 0.2]
    bad = Link(0, 5, np.zeros(3), np.eye(3), 1, 1, 1, 1, "correlation")
    with pytest.raises(ValueError, match="invalid for 3 frames"):
        optimize_poses([prior], [bad], cfg)
    bad = Link(0, 1, np.zeros(3), -np.eye(3), 1, 1, 1, 1, "correlation")
    with pytest.raises(ValueError, match="positive definite"):
        optimize_poses([prior], [bad], cfg)


def test_align_se2_recovers_rigid_transform():
    rng = np.random.default_rng(0)
    p = rng.uniform(-5, 5, (50, 2))
    a = 0.7
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    t = np.array([1.5, -2.0])
    q = p @ rot.T + t
    r_est, t_est = align_se2(p, q)
    np.testing.assert_allclose(r_est, rot, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-12)
    est = np.column_stack([p, np.zeros(50)])
    gt = np.column_stack([q, np.full(50, a)])
    assert absolute_trajectory_error(est, gt, PX)["rms_px"] < 1e-9


def test_link_errors_zero_for_exact_and_measure_offsets():
    rng = np.random.default_rng(1)
    gt = np.column_stack([rng.uniform(0, 2, 20), rng.uniform(0, 2, 20), rng.uniform(-3, 3, 20)])
    links = [Link(i, i + 1, se2_between(gt[i], gt[i + 1]), np.eye(3) * 1e-8, 1, 1, 1, 1, "correlation")
             for i in range(19)]
    assert np.all(link_errors(links, gt, PX, (240, 320)) < 1e-9)
    links[3].rel = links[3].rel + np.array([2 * PX, 0.0, 0.0])  # 2 px shift in frame a
    e = link_errors(links, gt, PX, (240, 320))
    assert e[3] == pytest.approx(2.0, rel=1e-9)
    assert np.all(np.delete(e, 3) < 1e-9)


def test_ground_truth_at(tmp_path):
    path = tmp_path / "ground_truth.csv"
    path.write_text("t,x,y,theta\n0,0,0,0\n1,1,0,0\n2,1,1,1.5707963267948966\n")
    p = ground_truth_at(np.array([0.0, 0.5, 1.0]), path)
    np.testing.assert_allclose(p, [[0, 0, 0], [0.5, 0, 0], [1, 0, 0]], atol=1e-12)


def test_plots_write_pngs(tmp_path, clean):
    from pipeline.plots import plot_link_residuals, plot_trajectories

    g, r = clean
    links = [Link(lk.a, lk.b, lk.rel, lk.cov, 1, 1, 1, 1, "correlation", lk.status, lk.reason, dict(lk.extra))
             for lk in g.links]
    links[0].status, links[0].extra["residual_px"] = "rejected", 20.0
    traj = tmp_path / "traj.png"
    res = tmp_path / "res.png"
    plot_trajectories(traj, np.concatenate(g.priors), r.poses, g.gt, links)
    plot_link_residuals(res, links)
    for p in (traj, res):
        assert p.stat().st_size > 5000 and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    plot_trajectories(tmp_path / "bare.png", r.poses, r.poses, None, None)
    assert (tmp_path / "bare.png").stat().st_size > 1000


def test_a_loose_link_many_pixels_off_is_an_outlier_by_its_residual(cfg):
    """A link whose own covariance is loose (sigma 5 px) but which disagrees by 8 px passes
    the chi-square test (Mahalanobis^2 ~2.6 < 16.27); the residual test
    (``outlier_max_residual_px``, the publish gate's 3 px) rejects it, naming the residual,
    and no accepted link is left above either threshold."""
    def run(max_px: float):
        g = synthetic_graph((3.0, 3.0), seed=4, pixel_size=PX)
        revisits = [i for i, lk in enumerate(g.links) if abs(lk.b - lk.a) > 5]
        lk = g.links[revisits[len(revisits) // 2]]
        lk.rel = lk.rel + np.array([8 * PX, 0.0, 0.0])
        lk.cov = np.diag([(5 * PX) ** 2, (5 * PX) ** 2, 1e-4])
        r = optimize_poses(g.priors, g.links, dict(cfg, outlier_max_residual_px=max_px), pixel_size=PX)
        return lk, r, g

    lk, r, g = run(3.0)
    assert lk.status == "rejected" and lk.reason.startswith("outlier: residual") and "> 3 px" in lk.reason, lk.reason
    acc = [x for x in g.links if x.status == "accepted"]
    assert max(x.extra["residual_px"] for x in acc) <= 3.0 and max(x.extra["mahalanobis"] for x in acc) <= 16.27
    lk, r, _ = run(0.0)  # off: the chi-square test alone keeps it
    assert lk.status == "accepted" and lk.extra["residual_px"] > 3.0 and lk.extra["mahalanobis"] < 16.27


def test_on_cycles_matches_removing_each_edge():
    """A link lies on a loop exactly when removing it leaves its two frames connected."""
    from pipeline.links import components, on_cycles

    rng = np.random.default_rng(3)
    for _ in range(40):
        n = int(rng.integers(2, 12))
        m = int(rng.integers(0, 16))
        a, b = rng.integers(0, n, m), rng.integers(0, n, m)
        keep = a != b
        a, b = a[keep], b[keep]
        got = on_cycles(n, a, b)
        for e in range(len(a)):
            rest = np.arange(len(a)) != e
            lab = components(n, a[rest], b[rest])
            assert got[e] == (lab[a[e]] == lab[b[e]]), (n, a.tolist(), b.tolist(), e)


def test_covariance_calibration_ignores_bridges():
    """Links that are bridges fit exactly whatever their noise: a graph of many of them
    (strips joined by a few links) must not read as noiseless links (the median at zero
    once shrank every covariance a million times)."""
    from pipeline.optimize import calibration_scale

    # Eight triangles (24 loop links, 8 loops) joined in a chain by 30 bridges.
    links, m = [], []
    for t in range(8):
        base = 3 * t
        for a, b in ((base, base + 1), (base + 1, base + 2), (base, base + 2)):
            links.append(Link(a, b, np.zeros(3), np.eye(3), 0.9, 0.5, 0.3, 100, "correlation"))
            m.append(3.0)  # loop links: each carries its share of its loop's chi-square
    node = 24
    for k in range(30):
        links.append(Link(0 if k == 0 else node - 1, node, np.zeros(3), np.eye(3), 0.9, 0.5, 0.3, 100, "correlation"))
        m.append(0.0)
        node += 1
    # 8 loops over 24 loop links: a share of 1/3 of chi-square(3)'s median 2.37 each, ~0.79;
    # the loop links' 3.0 read ~3.8x too optimistic covariances. (Over all 54 links, the
    # bridges' zeros put the median at 0 and the scale at the floor of 1e-6.)
    k = calibration_scale(np.array(m), links, tolerance=2.0, min_loops=4)
    assert 3.0 < k < 4.5, k


def test_covariance_calibration_by_group():
    """Links to the published map (group 1) are calibrated apart from the night's links
    (group 0): each group's loop links set its own factor, a group within the tolerance
    keeps 1, and one group scaled leaves the other as it was."""
    from pipeline.optimize import calibration_scale, calibration_scales

    # a chain of 20 frames, each also linked to a hub (the map, frame 100): 19 + 20 links,
    # 19 loops, every link on one
    links = [Link(i, i + 1, np.zeros(3), np.eye(3), 0.9, 0.5, 0.3, 100, "correlation") for i in range(19)]
    links += [Link(100, i, np.zeros(3), np.eye(3), 0.9, 0.5, 0.3, 100, "correlation") for i in range(20)]
    group = np.array([0] * 19 + [1] * 20)
    share = 19 / 39
    m = np.array([2.37 * share] * 19 + [10 * 2.37 * share] * 20)  # the map links 10x too optimistic
    k = calibration_scales(m, links, group, tolerance=2.0, min_loops=4)
    assert k[0] == 1.0 and 9.0 < k[1] < 11.0, k
    # one group: the median of all, as calibration_scale (here the map links' majority)
    assert calibration_scale(m, links, tolerance=2.0, min_loops=4) == calibration_scales(
        m, links, np.zeros(len(m), int), tolerance=2.0, min_loops=4)[0]
    # too few loop links in a group: it keeps 1
    k = calibration_scales(m, links, np.array([0] * 36 + [1] * 3), tolerance=2.0, min_loops=4)
    assert k[1] == 1.0


def test_added_variance_finds_the_maps_own_error():
    """Links whose translation residuals hold an error of their own besides their
    covariance (the published map's): the variance added per axis is found, whatever the
    links' own precision; none when the residuals are within their covariance."""
    from pipeline.optimize import added_variance

    rng = np.random.default_rng(5)
    n, share = 4000, 0.6
    c = rng.uniform(0.5e-10, 4e-10, n)  # each link's own variance per axis (m^2)
    v0 = 4e-10  # the map's (m^2 per axis: 20 µm)
    cov = np.zeros((n, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = c
    cov[:, 2, 2] = 1e-8
    r = np.zeros((n, 3))
    r[:, :2] = rng.normal(size=(n, 2)) * np.sqrt(share * (c + v0))[:, None]
    v = added_variance(r, cov, share)
    assert 0.85 * v0 < v < 1.15 * v0, v
    r[:, :2] = rng.normal(size=(n, 2)) * np.sqrt(share * c)[:, None] * 0.9  # within their covariance
    assert added_variance(r, cov, share) == 0.0
    assert added_variance(np.zeros((0, 3)), np.zeros((0, 3, 3)), share) == 0.0
