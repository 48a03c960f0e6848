"""Benchmark of the global pose optimization (pipeline.optimize) on synthetic pose graphs.

Prints, for a 10,000-frame lawnmower graph (~2.5 links per frame, 1 % odometry drift):
graph size, optimization seconds, LM iterations, residual RMS, ATE of odometry and of the
optimized poses vs ground truth; for a 600-frame graph with 5 % of the links corrupted
(offsets 5-50 px): rejected / missed corrupted links, good links rejected, and how much the
poses move vs the clean run (raw and after a rigid alignment, which removes the gauge:
the map hangs off frame 0's heading, which the links touching frame 0 set).

    python bench/bench_optimize.py [--area-large 20] [--seeds 3] [--marginals-area 10]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pipeline.config import default_config
from pipeline.evaluate import absolute_trajectory_error, align_se2
from pipeline.optimize import optimize_poses
from pipeline.testing.synthgraph import synthetic_graph

PX = 0.0025


def _large(cfg: dict, area: float, seed: int) -> None:
    t = time.perf_counter()
    g = synthetic_graph((area, area), seed=seed, pixel_size=PX)
    tg = time.perf_counter() - t
    c = dict(cfg, marginals_max_frames=0)
    r = optimize_poses(g.priors, g.links, c, pixel_size=PX)
    odo = absolute_trajectory_error(np.concatenate(g.priors), g.gt, PX)
    ate = absolute_trajectory_error(r.poses, g.gt, PX)
    print(
        f"large  seed {seed}: {len(g.gt)} frames, {len(g.links)} links ({len(g.links) / len(g.gt):.2f}/frame), "
        f"generated in {tg:.1f} s\n"
        f"       optimization {r.seconds:.2f} s, {r.iterations} LM iterations in {r.passes} solves, "
        f"rejected {r.rejected}, residual RMS {r.residual_rms_px:.4f} px\n"
        f"       ATE odometry {odo['rms_px']:.1f} px RMS / {odo['max_px']:.1f} max; "
        f"optimized {ate['rms_px']:.4f} px RMS / {ate['max_px']:.4f} max"
    )


def _marginals(cfg: dict, area: float) -> None:
    g = synthetic_graph((area, area), seed=0, pixel_size=PX)
    r = optimize_poses(g.priors, g.links, dict(cfg, marginals_max_frames=10**9), pixel_size=PX)
    sig = np.sqrt(r.marginal_cov[:, 0, 0] + r.marginal_cov[:, 1, 1]) / PX
    print(
        f"marginals: {len(g.gt)} frames in {r.marginals_seconds:.2f} s (optimization {r.seconds:.2f} s); "
        f"position sigma median {np.median(sig):.3f} px, max {sig.max():.3f} px"
    )


def _corrupt(cfg: dict, seed: int) -> dict:
    g0 = synthetic_graph((5.0, 5.0), seed=seed, pixel_size=PX)
    r0 = optimize_poses(g0.priors, g0.links, cfg, pixel_size=PX)
    g = synthetic_graph((5.0, 5.0), seed=seed, pixel_size=PX, corrupt_fraction=0.05)
    r = optimize_poses(g.priors, g.links, cfg, pixel_size=PX)
    rej = np.array([lk.status == "rejected" for lk in g.links])
    d = np.linalg.norm(r.poses[:, :2] - r0.poses[:, :2], axis=1) / PX
    rot, tr = align_se2(r.poses[:, :2], r0.poses[:, :2])
    da = np.linalg.norm(r.poses[:, :2] @ rot.T + tr - r0.poses[:, :2], axis=1) / PX
    out = {
        "frames": len(g.gt),
        "links": len(g.links),
        "corrupted": int(g.corrupted.sum()),
        "corrupted_rejected": int((g.corrupted & rej).sum()),
        "good_rejected": int((~g.corrupted & rej).sum()),
        "good_rejected_clean_run": r0.rejected,
        "pose_change_rms_px": float(np.sqrt(np.mean(d**2))),
        "pose_change_aligned_rms_px": float(np.sqrt(np.mean(da**2))),
        "ate_clean_px": absolute_trajectory_error(r0.poses, g0.gt, PX)["rms_px"],
        "ate_corrupt_px": absolute_trajectory_error(r.poses, g.gt, PX)["rms_px"],
        "seconds": r.seconds,
        "passes": r.passes,
    }
    print(
        f"corrupt seed {seed}: {out['frames']} frames, {out['links']} links, corrupted {out['corrupted']}: "
        f"rejected {out['corrupted_rejected']}, good rejected {out['good_rejected']} "
        f"(clean run {out['good_rejected_clean_run']}); pose change vs clean {out['pose_change_rms_px']:.4f} px RMS "
        f"raw, {out['pose_change_aligned_rms_px']:.4f} aligned; ATE clean {out['ate_clean_px']:.4f} / "
        f"corrupt {out['ate_corrupt_px']:.4f} px; {out['seconds']:.2f} s, {out['passes']} solves"
    )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--area-large", type=float, default=20.0, help="side (m) of the large lawnmower (20 -> ~10,000 frames)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--marginals-area", type=float, default=10.0, help="side (m) of the graph timed with marginals (0 = skip)")
    ap.add_argument("--policy", default=None, help="override [optimize] outlier_policy")
    args = ap.parse_args()
    cfg = dict(default_config()["optimize"])
    if args.policy:
        cfg["outlier_policy"] = args.policy
    _large(cfg, args.area_large, 0)
    if args.marginals_area > 0:
        _marginals(cfg, args.marginals_area)
    for seed in range(args.seeds):
        _corrupt(cfg, seed)


if __name__ == "__main__":
    main()
