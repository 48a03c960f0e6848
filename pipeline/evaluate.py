"""Ground-truth evaluation of poses and links (simulated logs, or logs with ground_truth.csv).

Pure functions; the build never reads ground truth, only reports these figures.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapstore.grid import interpolate_trajectory, se2_between, se2_compose, se2_inverse

__all__ = ["align_se2", "absolute_trajectory_error", "link_errors", "ground_truth_at"]


def align_se2(est_xy: np.ndarray, gt_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid 2D alignment (Kabsch/Umeyama without scale).

    Returns ``(R, t)`` (2x2 rotation, (2,) translation) minimising
    ``sum || R est_i + t - gt_i ||^2``.
    """
    est = np.asarray(est_xy, dtype=float).reshape(-1, 2)
    gt = np.asarray(gt_xy, dtype=float).reshape(-1, 2)
    if len(est) != len(gt) or len(est) == 0:
        raise ValueError(f"align_se2: need equal, non-zero numbers of points ({len(est)} vs {len(gt)})")
    me, mg = est.mean(axis=0), gt.mean(axis=0)
    h = (est - me).T @ (gt - mg)  # 2x2 cross-covariance
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, d]) @ u.T
    return r, mg - r @ me


def absolute_trajectory_error(est_poses: np.ndarray, gt_poses: np.ndarray, pixel_size: float) -> dict:
    """Position error after the best rigid SE(2) alignment of ``est`` onto ``gt``, in pixels.

    Returns ``{"rms_px", "max_px", "per_frame_px"}`` (per_frame_px: (N,) array).
    """
    est = np.asarray(est_poses, dtype=float)
    gt = np.asarray(gt_poses, dtype=float)
    r, t = align_se2(est[:, :2], gt[:, :2])
    err = np.linalg.norm(est[:, :2] @ r.T + t - gt[:, :2], axis=1) / pixel_size
    return {"rms_px": float(np.sqrt(np.mean(err**2))), "max_px": float(err.max()), "per_frame_px": err}


def link_errors(links, gt_poses: np.ndarray, pixel_size: float, frame_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Per link, the displacement error (pixels) of ``link.rel`` vs the ground-truth relative pose.

    The error is ``|| T_est(q) - T_gt(q) || / pixel_size`` for the point ``q`` (in frame b)
    that the ground truth puts at the centre of the overlap, approximated by the midpoint of
    the two frame centres (frame centres are the poses, so that midpoint is
    ``rel_gt.t / 2`` in frame a). ``frame_shape`` is accepted for interface stability; the
    midpoint approximation does not need it.
    """
    if not links:
        return np.zeros(0)
    gt = np.asarray(gt_poses, dtype=float)
    a = np.array([lk.a for lk in links])
    b = np.array([lk.b for lk in links])
    rel_est = np.array([lk.rel for lk in links], dtype=float)
    rel_gt = se2_between(gt[a], gt[b])
    p = np.zeros_like(rel_gt)
    p[:, :2] = rel_gt[:, :2] / 2.0  # midpoint in frame a
    q = se2_compose(se2_inverse(rel_gt), p)  # the same point in frame b (ground truth)
    pe = se2_compose(rel_est, q)  # where the link puts it in frame a
    return np.linalg.norm(pe[:, :2] - p[:, :2], axis=1) / pixel_size


def ground_truth_at(frames_t: np.ndarray, gt_csv_path: str | Path) -> np.ndarray:
    """Ground-truth poses (N, 3) at the frame times, SE(2)-interpolated from ``ground_truth.csv``."""
    from pipeline.drivelog import read_pose_csv

    samples = read_pose_csv(gt_csv_path, min_rows=2)
    return interpolate_trajectory(samples, np.asarray(frames_t, dtype=float))
