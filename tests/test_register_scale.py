"""Registration at scale: progressive revisits (pipeline.stages.register.progressive_revisits).

On long paths the chain of sequential links drifts (its heading errors pile up, above all
where no link holds a step, e.g. at lane ends), so revisits predicted along the whole chain
get search windows too wide for correlation or miss their partners. These tests check the
pieces that keep predictions tight: the chain's covariance with true lever arms, the
windows, the candidates predicted from the poses solved so far, the incremental solve,
and the whole loop on a synthetic lawnmower with registration replaced by ground truth
(so no images are needed).
"""

from __future__ import annotations

import numpy as np
import pytest

from mapstore.grid import se2_between, se2_compose, wrap_angle
from pipeline.candidates import ChainCovariance, ChainUncertainty, FrameTable, revisit_windows, window_revisit_candidates
from pipeline.config import load_config
from pipeline.links import Link
from pipeline.optimize import IncrementalPoses
import pipeline.stages.register as register

PX = 0.0025
SHAPE = (240, 320)  # 0.6 x 0.8 m footprints
CFG = load_config()
LANE_DY = 0.396  # the simulator's lawnmower spacing at 320 x 240, 2.5 mm


def lawnmower(lanes: int, length_m: float, step_m: float = 0.1) -> np.ndarray:
    """Ground-truth poses (x, y, theta) of a lawnmower: lanes along x, alternating direction."""
    n = int(round(length_m / step_m)) + 1
    rows = []
    for k in range(lanes):
        xs = np.linspace(0.0, length_m, n)
        if k % 2:
            xs = xs[::-1]
        rows += [(x, k * LANE_DY, 0.0 if k % 2 == 0 else np.pi) for x in xs]
    return np.array(rows)


def drifting_chain(truth: np.ndarray, rng: np.random.Generator, heading_sigma: float, xy_sigma: float,
                   turn_heading_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps of truth with noise; the step into each lane's first frame (the turn) is an
    odometry step with a large heading error. Returns (steps, covs, linked)."""
    true_steps = se2_between(truth[:-1], truth[1:])
    n = len(true_steps)
    turn = np.abs(wrap_angle(truth[1:, 2] - truth[:-1, 2])) > 1.0
    sig_h = np.where(turn, turn_heading_sigma, heading_sigma)
    noise = np.c_[rng.normal(0, xy_sigma, (n, 2)), rng.normal(0, 1, n) * sig_h]
    steps = true_steps + noise
    cov = np.zeros((n, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = xy_sigma**2
    cov[:, 2, 2] = sig_h**2
    return steps, cov, ~turn


def compose(start: np.ndarray, steps: np.ndarray) -> np.ndarray:
    out = [start]
    for s in steps:
        out.append(se2_compose(out[-1], s))
    return np.array(out)


def test_chain_covariance_uses_the_lever_from_each_step():
    # A straight 10 m chain: one step (frame 10 -> 11) with heading variance, others exact.
    n = 101
    prior = np.c_[np.arange(n) * 0.1, np.zeros(n), np.zeros(n)]
    frames = FrameTable.from_priors([prior], [SHAPE], PX)
    var_t = np.zeros(n)
    var_h = np.zeros(n)
    var_h[11] = 0.002**2
    var_t[50] = 0.001**2
    cc = ChainCovariance.from_steps(frames, prior[:, :2], var_t, var_h)
    opt = CFG["optimize"]
    st, sh = cc.since(frames, np.array([0, 0, 20]), np.array([100, 11, 100]), opt)
    # From frame 0 to 100: the heading error at frame 11 swings frame 100 by 0.002 x 8.9 m,
    # plus the 1 mm translation step.
    assert st[0] == pytest.approx(np.hypot(0.002 * 8.9, 0.001), rel=1e-6)
    assert sh[0] == pytest.approx(0.002)
    assert st[1] == pytest.approx(0.0, abs=1e-9)  # frame 11 itself does not move
    assert st[2] == pytest.approx(0.001) and sh[2] == 0.0  # from 20 on, only the translation step
    # The half-path lever of ChainUncertainty underestimates it (4.95 m instead of 8.9 m).
    half, _ = ChainUncertainty.from_steps(frames, var_t, var_h).relative(frames, np.array([0]), np.array([100]), opt)
    assert half[0] < 0.7 * st[0]
    # ref = -1: from the log start (log 0: the gauge, exact).
    st0, _ = cc.since(frames, np.array([-1]), np.array([100]), opt)
    assert st0[0] == pytest.approx(st[0])


def test_revisit_windows_partition_each_log():
    p1 = lawnmower(2, 4.0)
    p2 = lawnmower(1, 2.0) + np.array([0.0, 3.0, 0.0])
    frames = FrameTable.from_priors([p1, p2], [SHAPE, SHAPE], PX)
    wins = revisit_windows(frames, 1.5)
    assert wins[0][0] == 0 and wins[-1][1] == len(frames.prior)
    assert all(e0 == s1 for (_, e0), (s1, _) in zip(wins[:-1], wins[1:]))
    for s, e in wins:
        assert frames.log[s] == frames.log[e - 1]
        assert frames.path_m[e - 1] - frames.path_m[s] < 1.5 + 1e-9
    assert sum(1 for s, e in wins if s == len(p1)) == 1  # the second log starts a window


def test_window_candidates_radius_counts_from_the_last_held_frame():
    truth = lawnmower(3, 4.0)
    frames = FrameTable.from_priors([truth], [SHAPE], PX)
    reg, opt = CFG["register"], CFG["optimize"]
    n = len(truth)
    var_h = np.full(n, (4e-5) ** 2)
    var_h[41] = 0.002**2  # the turn into lane 1: an odometry step
    var_t = np.full(n, (0.01 * PX) ** 2)
    cc = ChainCovariance.from_steps(frames, truth[:, :2], var_t, var_h)
    s, e = 41 + 10, 41 + 30  # the middle of lane 1
    near = window_revisit_candidates(frames, truth, s, e, np.array([s - 1]), cc, reg, opt)
    far = window_revisit_candidates(frames, truth, s, e, np.array([-1]), cc, reg, opt)
    assert len(near) > 0 and pairs(near) == pairs(far)
    assert np.all((near.b >= s) & (near.b < e) & (near.a < near.b))
    assert np.all(np.abs(truth[near.a, 1] - truth[near.b, 1]) == pytest.approx(LANE_DY))
    assert np.all(near.radius_px <= far.radius_px + 1e-9)
    assert np.all(near.radius_px < reg["search_floor_px"] + 1.0)
    assert far.radius_px.min() > near.radius_px.max() + 2.0  # the turn's heading error
    # The cap applies within the window.
    counts = np.bincount(np.r_[near.a, near.b], minlength=n)
    assert counts.max() <= reg["max_revisits_per_frame"]


def pairs(c) -> list[tuple[int, int]]:
    return list(zip(c.a.tolist(), c.b.tolist()))


def truth_link(truth: np.ndarray, a: int, b: int, rng: np.random.Generator) -> Link:
    sig = 0.01 * PX
    rel = se2_between(truth[a], truth[b]) + np.r_[rng.normal(0, sig, 2), rng.normal(0, 3e-5)]
    return Link(a, b, rel, np.diag([sig**2, sig**2, (3e-5) ** 2]), 0.95, 0.5, 0.3, 10000, "correlation")


def test_incremental_poses_follow_the_links_and_drop_a_wrong_one():
    rng = np.random.default_rng(5)
    truth = lawnmower(4, 6.0)
    steps, cov, _ = drifting_chain(truth, rng, 4e-5, 0.01 * PX, 0.004)
    chain = compose(truth[0], steps)
    solver = IncrementalPoses(CFG["optimize"]["outlier_chi2"])
    est = chain.copy()
    lane = 61
    gauge = np.array([1e-6, 1e-6, 1e-7])
    dropped_links = []
    for k in range(4):
        s, e = k * lane, (k + 1) * lane
        if k:
            est[s:e] = se2_compose(est[s - 1], se2_between(chain[s - 1], chain[s:e]))
        links = [truth_link(truth, a, a + 2 * (lane - 1 - (a - (k - 1) * lane)) + 1, rng)
                 for a in range((k - 1) * lane, k * lane, 3)] if k else []
        if k == 2:
            links[5].rel = links[5].rel + np.array([0.03, 0.0, 0.0])  # a 12 px error
        est, drop = solver.add_window(est, s, e, steps, cov, links, s - 1 if k else None, gauge)
        dropped_links += [(k, i) for i in drop]
    assert dropped_links == [(2, 5)]
    err = np.hypot(*(est[:, :2] - truth[:, :2]).T) / PX
    assert np.abs(est[0] - truth[0]).max() < 1e-6
    # The chain alone is tens of pixels off after the first turn; the solved lanes are not.
    assert np.hypot(*(chain[-1, :2] - truth[-1, :2])) / PX > 10
    assert err.max() < 3.0


def test_progressive_revisits_keep_predictions_inside_the_search_window(monkeypatch):
    """A 6-lane, 8 m lawnmower whose chain drifts (heading errors at every turn); the
    registration is replaced by the ground truth, accepted only when the true relative pose
    lies within the pair's search radius of the prediction, as correlation requires."""
    rng = np.random.default_rng(1)
    truth = lawnmower(6, 8.0)
    frames = FrameTable.from_priors([truth], [SHAPE], PX)
    steps, cov, linked = drifting_chain(truth, rng, 4e-5, 0.01 * PX, 0.004)
    chain = compose(truth[0], steps)
    frames.prior = chain.copy()
    seen = []

    def fake_register(store_path, prior, pixel_size, cands, cfg, *, quiet=False, label="", run=None, significance=None):
        out = []
        for a, b, r in zip(cands.a.tolist(), cands.b.tolist(), cands.radius_px.tolist()):
            pred, true = se2_between(prior[a], prior[b]), se2_between(truth[a], truth[b])
            miss = (np.hypot(*(pred[:2] - true[:2])) + abs(wrap_angle(pred[2] - true[2])) * 0.4) / PX
            seen.append((miss, r))
            lk = truth_link(truth, a, b, rng)
            if miss > r:
                lk.status, lk.reason = "rejected", "ambiguous: outside the search window"
            out.append(lk)
        return out

    monkeypatch.setattr(register, "register_candidates", fake_register)
    cfg = {"register": dict(CFG["register"], revisit_window_m=3.0), "optimize": CFG["optimize"]}
    links, est, figures = register.progressive_revisits(None, frames, chain, steps, cov, linked, cfg, None, quiet=True)
    miss, radius = np.array(seen).T
    assert len(links) == len(seen) > 6 * 40
    assert np.all(miss < radius), (miss / radius).max()
    # Tight search windows (measured: median 4.3, p90 9.8, max 18.4 px; predictions off by
    # at most 4 px).
    assert np.median(radius) < 6.0 and np.percentile(radius, 90) < 12.0
    assert radius.max() < 40.0
    assert figures["passes"] == len(revisit_windows(frames, 3.0))
    assert figures["window_fit_dropped"] == 0
    # Every lane is linked to its neighbour and the solved poses follow the truth.
    lane = np.round(truth[:, 1] / LANE_DY).astype(int)
    got = {(min(lane[lk.a], lane[lk.b]), max(lane[lk.a], lane[lk.b])) for lk in links if lk.status == "accepted"}
    assert {(k, k + 1) for k in range(5)} <= got
    assert np.hypot(*(chain[:, :2] - truth[:, :2]).T).max() / PX > 10
    assert np.hypot(*(est[:, :2] - truth[:, :2]).T).max() / PX < 2.0


def test_isam_factorization_follows_the_chain():
    from pipeline.optimize import isam_factorization

    odometry = np.array([np.diag([1e-6, 1e-6, 1e-6])] * 3)  # steps held by odometry: millimetres
    gps = np.array([np.diag([13.0, 13.0, 0.025]), np.diag([1e-4, 1e-4, 3e-8])])  # geotagged: metres
    assert isam_factorization(odometry) == "CHOLESKY"
    assert isam_factorization(gps) == "QR"
    assert isam_factorization(np.zeros((0, 3, 3))) == "CHOLESKY"


def test_register_plan_processes_for_many_small_frames_threads_for_large(monkeypatch):
    """scheduler auto (the default), workers 0: large frames on a thread per core; small
    frames on a worker process per core when there are processes_min_frames of them, else
    one thread (two threads sharing the interpreter were slower than one); threads with
    workers 0: one thread for small frames; an explicit count, or another scheduler, as
    configured."""
    monkeypatch.setattr(register.os, "cpu_count", lambda: 2)
    reg = dict(load_config()["register"])
    assert reg["workers"] == 0 and reg["scheduler"] == "auto" and reg["threads_min_frame_px"] == 200000
    many = reg["processes_min_frames"]
    small = FrameTable.from_priors([np.zeros((5, 3))], [(240, 320)], 0.0025)
    small_many = FrameTable.from_priors([np.zeros((many, 3))], [(240, 320)], 0.0025)
    large = FrameTable.from_priors([np.zeros((many, 3))], [(1024, 1024)], 0.001)
    mixed = FrameTable.from_priors([np.zeros((many, 3)), np.zeros((2, 3))], [(240, 320), (1024, 1024)], 0.001)
    plan = register.register_plan
    assert plan(reg, small) == ("threads", 1)
    assert plan(reg, small_many) == ("processes", 2)
    assert plan(reg, large) == ("threads", 2)
    assert plan(reg, mixed) == ("processes", 2)  # the median frame is small
    assert plan(dict(reg, workers=1), small_many) == ("threads", 1)
    assert plan(dict(reg, workers=2), small) == ("threads", 2)
    assert plan(dict(reg, scheduler="threads"), small_many) == ("threads", 1)
    assert plan(dict(reg, scheduler="threads", workers=2), small_many) == ("threads", 2)
    assert plan(dict(reg, scheduler="processes"), small) == ("processes", 2)
    assert plan(dict(reg, threads_min_frame_px=0), small_many) == ("threads", 2)
    monkeypatch.setattr(register.os, "cpu_count", lambda: 1)
    assert plan(reg, small_many) == ("threads", 1)


def test_pairs_into_a_window_are_every_close_pair_by_binning_as_by_all_distances():
    """The binned search finds exactly the pairs (and their order) that measuring every
    distance finds: random centres with duplicates, pairs near the diagonal's length, windows
    at the start, middle and end."""
    from pipeline.candidates import _pairs_into_window

    rng = np.random.default_rng(3)
    n = 1500
    poses = np.c_[rng.uniform(-6.0, 6.0, (n, 2)), rng.uniform(-3.0, 3.0, n)]
    poses[700:703] = poses[5]  # frames at one place
    frames = FrameTable(poses, np.zeros(n, int), np.zeros(n), [(480, 640)], 0.0025)
    cell = np.hypot(480, 640) * 0.0025
    poses[900, :2] = poses[10, :2] + [cell * (1 - 1e-12), 0.0]  # just inside
    poses[901, :2] = poses[11, :2] + [cell, 0.0]  # exactly one diagonal: not a pair
    for s, e in ((0, n), (400, 950), (n - 50, n), (7, 7)):
        a, b = _pairs_into_window(frames, poses, s, e)
        d2 = ((poses[s:e, None, :2] - poses[None, :e, :2]) ** 2).sum(axis=2)
        bi, ai = np.nonzero(d2 < cell * cell)
        keep = ai < bi + s
        np.testing.assert_array_equal(a, ai[keep])
        np.testing.assert_array_equal(b, bi[keep] + s)
        if s <= 900 < e:
            assert (10, 900) in set(zip(a.tolist(), b.tolist()))
        if s <= 901 < e:
            assert (11, 901) not in set(zip(a.tolist(), b.tolist()))


def test_predicted_overlap_in_chunks_is_the_same_as_in_one_go(monkeypatch):
    """predicted_overlap works through its pairs in chunks (bounded memory for millions of
    pairs): chunk boundaries change nothing, for two logs of different frame shapes."""
    import pipeline.candidates as cand

    rng = np.random.default_rng(5)
    n = 400
    poses = np.c_[rng.uniform(0.0, 4.0, (n, 2)), rng.uniform(-3.0, 3.0, n)]
    log = (np.arange(n) >= n // 2).astype(int)
    frames = FrameTable(poses, log, np.zeros(n), [(480, 640), (240, 320)], 0.0025)
    a, b = cand._neighbour_pairs(frames, poses)
    margin = rng.uniform(0.0, 0.05, len(a))
    whole = cand.predicted_overlap(frames, a, b, margin_m=margin)
    monkeypatch.setattr(cand, "_OVERLAP_CHUNK", 7)
    np.testing.assert_array_equal(cand.predicted_overlap(frames, a, b, margin_m=margin), whole)
    assert len(a) > 100 and 0.0 < whole.mean() < 1.0
