"""Levenberg-Marquardt with its linear systems solved by blocks of the floor (pipeline.blocked_lm):
the split, and the solution against GTSAM's own optimizer and against optimize_poses's whole solve."""

from __future__ import annotations

import copy

import gtsam
import numpy as np
import pytest

from mapstore.grid import se2_between
from pipeline.blocked_lm import BlockSystem, blocks_per_side, floor_blocks, levenberg_marquardt
from pipeline.config import default_config, load_config
from pipeline.links import Link
from pipeline.optimize import optimize_poses, sim_between
from pipeline.testing.synthgraph import synthetic_graph

PX = 0.0025
X = gtsam.symbol_shorthand.X


def _lawnmower(side: int, seed: int = 0):
    """A ``side`` x ``side`` floor one metre apart, rows driven in turn: (N, 2) positions and
    (F, 2) the frames of each link (its row's next two frames, three of the next row)."""
    order = np.arange(side * side).reshape(side, side)
    order[1::2] = order[1::2, ::-1]
    xy = np.zeros((side * side, 2))
    xy[order.ravel(), 0] = np.tile(np.arange(side), side)
    xy[order.ravel(), 1] = np.repeat(np.arange(side), side)
    ends = [(order[r, c], order[r + dr, c + dc]) for r in range(side) for c in range(side)
            for dr, dc in ((0, 1), (0, 2), (1, -1), (1, 0), (1, 1))
            if 0 <= r + dr < side and 0 <= c + dc < side]
    return xy, np.array(ends)


def test_blocks_per_side():
    assert blocks_per_side(40_000, 8000) == 2
    assert blocks_per_side(31_999, 8000) == 1
    assert blocks_per_side(100_000, 8000) == 3
    assert blocks_per_side(10**6, 0) == 1


def test_floor_blocks_leave_no_factor_between_two_blocks():
    xy, ends = _lawnmower(30)
    hub = len(xy)  # a frame linked to every 7th frame, all over the floor (as the published map's)
    xy = np.vstack([xy, [[3.0, 3.0]]])
    ends = np.vstack([ends, [(hub, k) for k in range(0, hub, 7)]])
    group = floor_blocks(xy, ends[:, 0], ends[:, 1], 3)
    ga, gb = group[ends[:, 0]], group[ends[:, 1]]
    assert not np.any((ga >= 0) & (gb >= 0) & (ga != gb))
    assert group[hub] == -1
    sizes = np.bincount(group[group >= 0], minlength=9)
    assert sizes.min() > 0.6 * sizes.max(), sizes
    assert (group < 0).sum() < 0.25 * len(xy)  # (4 cuts of 30 frames, links reaching 2 across)


def _noisy_graph(side: int, seed: int = 3):
    """A lawnmower pose graph with noisy links under a Cauchy kernel, a prior on frame 0, and
    starting poses off by 5 cm and 0.01 rad: (graph, initial values, positions)."""
    rng = np.random.default_rng(seed)
    xy, ends = _lawnmower(side)
    truth = np.column_stack([xy, 0.02 * rng.standard_normal(len(xy))])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*truth[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    cov = np.diag([1e-4, 1e-4, 1e-6])
    kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(3.0)
    for (i, j), rel in zip(ends, se2_between(truth[ends[:, 0]], truth[ends[:, 1]])):
        rel = rel + rng.multivariate_normal(np.zeros(3), cov)
        noise = gtsam.noiseModel.Robust.Create(kernel, gtsam.noiseModel.Gaussian.Covariance(cov))
        graph.add(gtsam.BetweenFactorPose2(X(int(i)), X(int(j)), gtsam.Pose2(*rel), noise))
    values = gtsam.Values()
    for i, p in enumerate(truth):
        values.insert(X(i), gtsam.Pose2(p[0] + rng.normal(0, 0.05), p[1] + rng.normal(0, 0.05), p[2] + rng.normal(0, 0.01)))
    return graph, values, xy


@pytest.mark.parametrize("per_side", [2, 3])
def test_blocked_levenberg_marquardt_is_gtsams(per_side):
    graph, values, xy = _noisy_graph(24)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    whole = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    a = gtsam.utilities.extractPose2(whole.optimize())
    system = BlockSystem.split(gtsam, graph, xy, per_side, 3)
    assert system is not None and len(system.interior) == per_side**2 and system.separator
    out, steps = levenberg_marquardt(system, values, params)
    b = gtsam.utilities.extractPose2(out)
    assert steps == whole.iterations()
    assert np.abs(a - b).max() < 1e-6  # (metres, radians: the solves' rounding over the last steps)
    # a factor taken out of the split is out of its solve: the same as GTSAM without it
    i = graph.size() - 1
    system.remove(i)
    graph.remove(i)
    c = gtsam.utilities.extractPose2(levenberg_marquardt(system, values, params)[0])
    d = gtsam.utilities.extractPose2(gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize())
    assert np.abs(c - d).max() < 1e-6


def test_split_refuses_factors_of_three_frames_and_empty_graphs():
    three = gtsam.NonlinearFactorGraph()
    three.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), [X(0), X(1), X(2)], lambda f, v, h: np.zeros(1)))
    assert BlockSystem.split(gtsam, three, np.zeros((3, 2)), 2, 3) is None
    assert BlockSystem.split(gtsam, gtsam.NonlinearFactorGraph(), np.zeros((2, 2)), 2, 3) is None


def test_optimize_poses_by_blocks_is_the_whole_solve():
    cfg = dict(default_config()["optimize"])
    runs = {}
    for block_frames in (0, 40):
        g = synthetic_graph((5.0, 5.0), seed=1, pixel_size=PX, corrupt_fraction=0.05)
        links = copy.deepcopy(g.links)
        runs[block_frames] = (optimize_poses(g.priors, links, {**cfg, "block_frames": block_frames}, pixel_size=PX),
                              links)
    (whole, lw), (blocked, lb) = runs[0], runs[40]
    assert blocks_per_side(len(whole.poses), 40) >= 2
    assert [lk.status for lk in lw] == [lk.status for lk in lb]
    assert whole.rejected == blocked.rejected and whole.rejected >= 50
    assert np.abs(whole.poses - blocked.poses).max() < 1e-6
    assert abs(whole.residual_rms_px - blocked.residual_rms_px) < 1e-6


def test_similarity_poses_by_blocks():
    rng = np.random.default_rng(4)
    n = 60
    x = 0.1 * np.arange(n)
    truth = np.column_stack([x, 0.01 * np.sin(x), 0.02 * np.cos(x), np.exp(0.02 * np.sin(2.0 * x))])
    truth[:, 3] /= np.exp(np.mean(np.log(truth[:, 3])))
    odo = truth[:, :3] + np.column_stack([0.002 * rng.standard_normal((n, 2)), np.zeros(n)])
    odo[0] = truth[0, :3]
    cov4 = np.diag([(0.01 * PX) ** 2, (0.01 * PX) ** 2, 1e-8, 1e-8])

    def links():
        out = []
        for i in range(n):
            for j in (i + 1, i + 2):
                if j < n:
                    rel = sim_between(truth[i], truth[j])
                    out.append(Link(i, j, rel[:3], cov4[:3, :3].copy(), 0.99, 0.8, 0.6, 1000, "correlation",
                                    log_scale=float(rel[3]), cov4=cov4.copy()))
        return out

    cfg = {**load_config(None)["optimize"], "pose_model": "similarity2"}
    whole = optimize_poses([odo], links(), {**cfg, "block_frames": 0}, PX)
    blocked = optimize_poses([odo], links(), {**cfg, "block_frames": 7}, PX)
    assert blocks_per_side(n, 7) == 2
    assert np.abs(whole.scales - blocked.scales).max() < 1e-8
    assert np.abs(whole.poses - blocked.poses).max() < 1e-8


def test_split_refuses_keys_other_than_the_frames():
    L = gtsam.symbol_shorthand.L
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.BetweenFactorPose2(X(0), L(1), gtsam.Pose2(), gtsam.noiseModel.Unit.Create(3)))
    assert BlockSystem.split(gtsam, graph, np.zeros((2, 2)), 2, 3) is None
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.BetweenFactorPose2(X(0), X(5), gtsam.Pose2(), gtsam.noiseModel.Unit.Create(3)))
    assert BlockSystem.split(gtsam, graph, np.zeros((2, 2)), 2, 3) is None
    assert BlockSystem.split(gtsam, graph, np.zeros((6, 2)), 2, 3) is not None
