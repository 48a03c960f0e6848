"""Ground-truth evaluation of poses and links (simulated logs, or logs with ground_truth.csv).

Pure functions; the build never reads ground truth, only reports these figures.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapstore.grid import interpolate_trajectory, se2_between, se2_compose, se2_inverse

__all__ = ["align_se2", "absolute_trajectory_error", "link_errors", "ground_truth_at", "mosaic_vs_world", "seam_ratio"]


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


def mosaic_vs_world(
    mosaic: np.ndarray,
    grid,
    texture: np.ndarray,
    texture_grid,
    rot: np.ndarray | None = None,
    trans: np.ndarray | None = None,
    erode_px: int = 4,
) -> dict:
    """A rendered mosaic against the simulator's ground-truth world texture.

    Every covered map pixel (``mosaic > 0``, eroded by ``erode_px`` to leave out the map's
    ragged edge) is placed in the world by ``grid`` and by the rigid alignment ``(rot,
    trans)`` of the estimated poses onto the ground truth (:func:`align_se2`; identity when
    None), and the world texture is sampled there (cubic). Returns ``{"ncc", "psnr_db",
    "rmse", "pixels", "gain", "offset"}``: NCC, and PSNR (peak 255) and RMSE in grey levels
    after the best global linear fit ``world ≈ gain * mosaic + offset`` (the mosaic's
    exposure scale is arbitrary: gains are normalized over the frames, not to the world).
    """
    import cv2

    covered = (mosaic > 0).astype(np.uint8)
    if erode_px > 0:
        covered = cv2.erode(covered, np.ones((2 * erode_px + 1,) * 2, np.uint8), borderValue=0)
    rows, cols = np.nonzero(covered)
    if len(rows) == 0:
        raise ValueError("mosaic_vs_world: the mosaic covers no pixel")
    x, y = grid.pixel_to_world(cols.astype(float), rows.astype(float))
    if rot is not None:
        xy = np.column_stack([x, y]) @ np.asarray(rot).T + np.asarray(trans)
        x, y = xy[:, 0], xy[:, 1]
    tc, tr = texture_grid.world_to_pixel(x, y)
    # cv2.remap wants maps under 32767 rows: lay the samples out in rows of 4096
    n = len(tc)
    width = 4096
    pad = -n % width
    mx = np.r_[tc, np.zeros(pad)].astype(np.float32).reshape(-1, width)
    my = np.r_[tr, np.zeros(pad)].astype(np.float32).reshape(-1, width)
    ref = cv2.remap(texture.astype(np.float32), mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT).ravel()[:n]
    m = mosaic[rows, cols].astype(float)
    ref = ref.astype(float)
    mc, rc = m - m.mean(), ref - ref.mean()
    ncc = float((mc @ rc) / np.sqrt((mc @ mc) * (rc @ rc)))
    gain = float((mc @ rc) / (mc @ mc))
    offset = float(ref.mean() - gain * m.mean())
    rmse = float(np.sqrt(np.mean((gain * m + offset - ref) ** 2)))
    return {"ncc": ncc, "psnr_db": float(20 * np.log10(255.0 / max(rmse, 1e-9))), "rmse": rmse,
            "pixels": int(len(rows)), "gain": gain, "offset": offset}


def seam_ratio(mosaic: np.ndarray, border_mask: np.ndarray, erode_px: int = 4) -> float:
    """Seam metric: mean squared gradient magnitude on frame borders / elsewhere.

    ``border_mask``: bool, True within a few pixels of any frame's footprint edge (inside the
    covered area). Seams that show raise the ratio above 1; invisible seams give about 1.
    """
    import cv2

    img = mosaic.astype(np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    energy = gx * gx + gy * gy
    covered = cv2.erode((mosaic > 0).astype(np.uint8), np.ones((2 * erode_px + 1,) * 2, np.uint8), borderValue=0) > 0
    on = covered & border_mask
    off = covered & ~border_mask
    if not on.any() or not off.any():
        return float("nan")
    return float(energy[on].mean() / energy[off].mean())
