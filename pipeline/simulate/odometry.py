"""Wheel-odometry simulation with an error gradient (Kelly): position error ~ alpha x distance.

The true motion between consecutive odometry samples is the SE(2) increment
``(dx, dy, dtheta) = ⊖P_k ⊕ P_{k+1}`` of the ground-truth poses (vehicle frame, metres and
radians). The measured increment is

    dx', dy' = (dx, dy) x (1 + e_s) x (1 + n_d)         e_s ~ N(0, (scale_share alpha)^2), once
                                                         n_d ~ N(0, distance_noise^2), per sample
    dtheta'  = dtheta + w_k sqrt(ds) + n_theta          w_k ~ N(0, sigma_w^2) per sample (random walk)
                                                         n_theta ~ N(0, heading_noise_rad^2)

with ``ds = |(dx, dy)|``. A systematic scale error gives a position error e_s x d along the
track; the heading random walk (variance sigma_w^2 per metre) gives a lateral error of std
sigma_w d^1.5 / sqrt(3), and sigma_w is chosen so that this equals
``heading_walk_share x alpha x reference_distance_m`` at the reference distance. So the
position error after distance d is on the order of alpha x d over routes of that length.
``alpha = 0`` switches every error term off (the odometry is then the ground truth
expressed in the odometry frame).

Odometry frame: "origin" starts at (0, 0, 0) at the first sample; "world" at the first
sample's ground-truth pose.
"""

from __future__ import annotations

import numpy as np

from mapstore.grid import se2_between, se2_inverse, se2_compose, wrap_angle

__all__ = ["odometry_times", "simulate_odometry", "integrate_increments", "odometry_error"]


def odometry_times(t_first: float, t_last: float, rate_hz: float) -> np.ndarray:
    """Sample times (seconds) on the ``k / rate_hz`` lattice covering ``[t_first, t_last]``.

    The first sample is at or before ``t_first``, the last at or after ``t_last``.
    """
    k0 = int(np.floor(t_first * rate_hz + 1e-9))
    k1 = int(np.ceil(t_last * rate_hz - 1e-9))
    # (the tolerance keeps exact lattice times from adding a sample; the checks below keep
    # rounding, e.g. 5.6000000000000005 s, from leaving a frame outside the span)
    if k0 / rate_hz > t_first:
        k0 -= 1
    if k1 / rate_hz < t_last:
        k1 += 1
    k1 = max(k1, k0 + 1)
    return np.arange(k0, k1 + 1) / rate_hz


def integrate_increments(start: np.ndarray, inc: np.ndarray) -> np.ndarray:
    """Compose SE(2) increments ``inc`` (K, 3) from ``start`` (3,) -> (K + 1, 3) poses.

    Vectorised: headings by cumulative sum, positions by summing rotated increments.
    """
    th = start[2] + np.concatenate([[0.0], np.cumsum(inc[:, 2])])
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    dx = c * inc[:, 0] - s * inc[:, 1]
    dy = s * inc[:, 0] + c * inc[:, 1]
    x = start[0] + np.concatenate([[0.0], np.cumsum(dx)])
    y = start[1] + np.concatenate([[0.0], np.cumsum(dy)])
    return np.stack([x, y, wrap_angle(th)], axis=1)


def simulate_odometry(
    gt: np.ndarray,
    alpha: float,
    rng: np.random.Generator,
    cfg: dict,
) -> np.ndarray:
    """Dead-reckoning poses (K, 3) in the odometry frame from ground-truth poses ``gt`` (K, 3).

    Args:
        gt: world-frame poses (x, y, theta) at the odometry sample times.
        alpha: error gradient (position error per distance travelled, dimensionless).
        rng: the odometry's random stream.
        cfg: the ``[simulate.floor.odometry]`` table (shares, noise, frame).
    """
    gt = np.asarray(gt, dtype=float)
    inc = se2_between(gt[:-1], gt[1:])
    if alpha > 0:
        k = len(inc)
        ds = np.hypot(inc[:, 0], inc[:, 1])
        scale = 1.0 + rng.normal(0.0, cfg["scale_share"] * alpha)
        dist_noise = 1.0 + rng.normal(0.0, cfg["distance_noise"], k)
        sigma_w = cfg["heading_walk_share"] * alpha * np.sqrt(3.0) / np.sqrt(cfg["reference_distance_m"])
        walk = rng.normal(0.0, sigma_w, k) * np.sqrt(ds)
        white = rng.normal(0.0, cfg["heading_noise_rad"], k)
        inc = inc.copy()
        inc[:, :2] *= (scale * dist_noise)[:, None]
        inc[:, 2] = inc[:, 2] + walk + white
    start = gt[0] if cfg["frame"] == "world" else np.zeros(3)
    return integrate_increments(start, inc)


def odometry_error(odo: np.ndarray, gt: np.ndarray, frame: str) -> np.ndarray:
    """Position error (K,) metres of odometry vs ground truth, aligned at the first sample."""
    ref = gt[0] if frame == "world" else np.zeros(3)
    aligned = se2_compose(gt[0], se2_compose(se2_inverse(ref), odo))
    return np.hypot(aligned[:, 0] - gt[:, 0], aligned[:, 1] - gt[:, 1])
