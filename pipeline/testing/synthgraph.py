"""Synthetic pose graphs (no images) for testing and benchmarking ``pipeline.optimize``.

A lawnmower route of frames (ground truth), drifting odometry in the style of
``pipeline.simulate.odometry`` (systematic scale error plus a heading random walk), and
registration links computed from the ground-truth relative poses plus noise drawn from each
link's own covariance: consecutive frames, frames two apart, and the nearest frame of the
previous lane (the overlaps a real lawnmower log produces). Optionally a fraction of the
links is corrupted by a translation offset, to exercise outlier rejection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapstore.grid import se2_between, se2_compose, se2_exp, wrap_angle
from pipeline.links import Link

__all__ = ["SyntheticGraph", "lawnmower_poses", "drifting_odometry", "make_links", "synthetic_graph", "corrupt_links"]


@dataclass
class SyntheticGraph:
    gt: np.ndarray  # (N, 3) ground-truth poses
    lane: np.ndarray  # (N,) lane index, -1 on U-turns
    priors: list[np.ndarray]  # per log (N_k, 3) odometry poses
    links: list[Link]
    corrupted: np.ndarray  # (L,) bool: link i was corrupted


def lawnmower_poses(area: tuple[float, float], *, inset: float = 0.3, lane_spacing: float = 0.4,
                    step: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Frames every ``step`` metres along lanes in x joined by semicircular U-turns.

    Returns (N, 3) poses and (N,) lane index (-1 for frames on a U-turn).
    """
    x0, x1 = inset, area[0] - inset
    y0, y1 = inset, area[1] - inset
    n_lanes = max(1, int(np.ceil((y1 - y0) / lane_spacing - 1e-9)) + 1)
    gap = (y1 - y0) / (n_lanes - 1) if n_lanes > 1 else 0.0
    poses, lanes = [], []
    for j in range(n_lanes):
        y = y0 + j * gap
        n = int(np.floor((x1 - x0) / step + 1e-9)) + 1
        xs = x0 + np.arange(n) * step
        fwd = j % 2 == 0
        if not fwd:
            xs = xs[::-1]
        th = 0.0 if fwd else np.pi
        poses.append(np.stack([xs, np.full(n, y), np.full(n, th)], axis=1))
        lanes.append(np.full(n, j))
        if j + 1 < n_lanes:
            r = gap / 2.0
            m = max(1, int(round(np.pi * r / step)))
            a = np.arange(1, m) / m * np.pi  # interior points of the half circle
            xe = xs[-1]
            cx, cy = xe, y + r
            if fwd:  # turn left, counter-clockwise around (xe, y + r)
                px, py = cx + r * np.sin(a), cy - r * np.cos(a)
                ph = a
            else:  # turn right, clockwise
                px, py = cx - r * np.sin(a), cy - r * np.cos(a)
                ph = np.pi - a
            poses.append(np.stack([px, py, wrap_angle(ph)], axis=1))
            lanes.append(np.full(len(a), -1))
    return np.concatenate(poses), np.concatenate(lanes)


def drifting_odometry(gt: np.ndarray, alpha: float, rng: np.random.Generator, *,
                      scale_share: float = 0.7, heading_walk_share: float = 0.7,
                      reference_distance_m: float = 50.0, start: np.ndarray | None = None) -> np.ndarray:
    """Dead reckoning from ground truth with a scale error and a heading random walk.

    Starts at ``start`` (default (0, 0, 0): the log's own odometry frame).
    """
    inc = se2_between(gt[:-1], gt[1:])
    ds = np.hypot(inc[:, 0], inc[:, 1])
    scale = 1.0 + rng.normal(0.0, scale_share * alpha)
    sigma_w = heading_walk_share * alpha * np.sqrt(3.0) / np.sqrt(reference_distance_m)
    inc = inc.copy()
    inc[:, :2] *= scale * (1.0 + rng.normal(0.0, 0.002, len(inc)))[:, None]
    inc[:, 2] += rng.normal(0.0, sigma_w, len(inc)) * np.sqrt(ds)
    out = [np.zeros(3) if start is None else np.asarray(start, float)]
    th = out[0][2] + np.concatenate([[0.0], np.cumsum(inc[:, 2])])
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    x = out[0][0] + np.concatenate([[0.0], np.cumsum(c * inc[:, 0] - s * inc[:, 1])])
    y = out[0][1] + np.concatenate([[0.0], np.cumsum(s * inc[:, 0] + c * inc[:, 1])])
    return np.stack([x, y, wrap_angle(th)], axis=1)


def _random_cov(rng: np.random.Generator, pixel_size: float, sigma_px: tuple[float, float],
                lever_m: float) -> np.ndarray:
    """A data-like link covariance: anisotropic translation, heading sigma ~ sigma_xy / lever."""
    sx, sy = rng.uniform(*sigma_px, 2) * pixel_size
    phi = rng.uniform(0, np.pi)
    r = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    st = np.sqrt(sx * sy) / lever_m
    rho = rng.uniform(-0.3, 0.3, 2)
    m = np.zeros((3, 3))
    m[:2, :2] = r @ np.diag([sx, sy])
    m[2] = st * np.array([rho[0], rho[1], np.sqrt(1.0 - rho @ rho)])
    cov = m @ m.T
    return cov


def make_links(gt: np.ndarray, lane: np.ndarray, rng: np.random.Generator, *, pixel_size: float = 0.0025,
               sigma_px: tuple[float, float] = (0.005, 0.02), lever_m: float = 0.25,
               skip2_fraction: float = 0.5, offset: int = 0) -> list[Link]:
    """Links between overlapping frames (global indices start at ``offset``).

    Consecutive frames; frames two apart (all on U-turns, ``skip2_fraction`` of them on
    lanes); each lane frame to the nearest frame of the previous lane.
    """
    n = len(gt)
    pairs = [(i, i + 1) for i in range(n - 1)]
    # Frames two apart: a fraction of them on the lanes (cross-lane links add redundancy
    # there), all of them on the U-turns (which have no other lane to link to).
    pairs += [(i, i + 2) for i in range(0, n - 2) if lane[i] < 0 or lane[i + 2] < 0 or rng.random() < skip2_fraction]
    lanes = np.unique(lane[lane >= 0])
    for j in lanes[1:]:
        prev = np.flatnonzero(lane == j - 1)
        cur = np.flatnonzero(lane == j)
        order = np.argsort(gt[prev, 0])
        xs = gt[prev[order], 0]
        for i in cur:
            k = int(np.clip(np.searchsorted(xs, gt[i, 0]), 1, len(xs) - 1))
            k = k if abs(xs[k] - gt[i, 0]) < abs(xs[k - 1] - gt[i, 0]) else k - 1
            pairs.append((int(prev[order][k]), int(i)))
    pa = np.array([p[0] for p in pairs])
    pb = np.array([p[1] for p in pairs])
    covs = np.stack([_random_cov(rng, pixel_size, sigma_px, lever_m) for _ in pairs])
    noise = (np.linalg.cholesky(covs) @ rng.standard_normal((len(pairs), 3, 1)))[..., 0]
    rel = se2_compose(se2_between(gt[pa], gt[pb]), se2_exp(noise))
    return [
        Link(int(a) + offset, int(b) + offset, rel[i], covs[i], 0.95, 0.5, 0.8, 10000, "correlation")
        for i, (a, b) in enumerate(zip(pa, pb))
    ]


def corrupt_links(links: list[Link], fraction: float, rng: np.random.Generator, *, pixel_size: float = 0.0025,
                  offset_px: tuple[float, float] = (5.0, 50.0)) -> np.ndarray:
    """Add a random translation offset (pixels, random direction) to ``fraction`` of the links."""
    k = int(round(fraction * len(links)))
    idx = rng.choice(len(links), size=k, replace=False)
    bad = np.zeros(len(links), bool)
    bad[idx] = True
    for i in idx:
        mag = rng.uniform(*offset_px) * pixel_size
        ang = rng.uniform(0, 2 * np.pi)
        lk = links[i]
        lk.rel = lk.rel + np.array([mag * np.cos(ang), mag * np.sin(ang), 0.0])
    return bad


def synthetic_graph(area: tuple[float, float] = (5.0, 5.0), *, alpha: float = 0.01, seed: int = 0,
                    pixel_size: float = 0.0025, corrupt_fraction: float = 0.0, n_logs: int = 1,
                    **link_kw) -> SyntheticGraph:
    """A lawnmower graph; ``n_logs`` > 1 splits the route into consecutive logs.

    Every log's odometry starts at its first frame's ground-truth pose (the logs share the
    site frame, as the optimizer's gauge assumes) and drifts independently.
    """
    rng = np.random.default_rng(seed)
    gt, lane = lawnmower_poses(area)
    bounds = np.linspace(0, len(gt), n_logs + 1).astype(int)
    priors = []
    for k in range(n_logs):
        seg = gt[bounds[k]:bounds[k + 1]]
        priors.append(drifting_odometry(seg, alpha, rng, start=seg[0]))
    links = make_links(gt, lane, rng, pixel_size=pixel_size, **link_kw)
    bad = corrupt_links(links, corrupt_fraction, rng, pixel_size=pixel_size) if corrupt_fraction > 0 else np.zeros(len(links), bool)
    return SyntheticGraph(gt, lane, priors, links, bad)
