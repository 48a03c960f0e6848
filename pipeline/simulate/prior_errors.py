"""A simulated log's odometry made wrong on purpose: the priors real drives bring.

Used by ``bench/bench_loose_prior.py`` and the tests: a copy of a simulated log (images
linked, not copied) whose ``odometry.csv`` is rewritten with one kind of error, the ground
truth kept for evaluation.

- ``tight``: unchanged (the simulator's 1 % drift);
- ``loose``: positions scaled by 1.05 about the start (a wheel radius 5 % off);
- ``flipped``: one lane's heading turned by pi, its positions kept (gimbal vs body yaw);
- ``heading``: a smooth heading error of sigma 0.2 rad added to theta (a wandering compass).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["VARIANTS", "lanes", "rewrite_prior"]

VARIANTS = ("tight", "loose", "flipped", "heading")


def lanes(gt: np.ndarray, *, min_samples: int = 8) -> list[tuple[int, int]]:
    """Index ranges ``[i, j)`` of the straight runs (lanes) of a pose table ``gt`` (rows t,
    x, y, theta): heading within 0.1 rad of the run's first sample, at least
    ``min_samples`` samples."""
    out, i = [], 0
    th = gt[:, 3]
    while i < len(th):
        j = i + 1
        while j < len(th) and abs(np.angle(np.exp(1j * (th[j] - th[i])))) < 0.1:
            j += 1
        if j - i >= min_samples:
            out.append((i, j))
        i = j
    return out


def rewrite_prior(log: Path, out: Path, variant: str, seed: int = 1, *, lane: int = 2) -> None:
    """Write ``out``: a copy of the simulated ``log`` with its odometry.csv rewritten as
    ``variant`` (see the module docstring); ``lane``: which lane ``flipped`` turns."""
    from pipeline.drivelog import read_pose_csv, write_pose_csv

    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    from pipeline.fsutil import link_tree

    link_tree(log, out)  # hard links: a log's files must not lead outside it ([ingest] follow_symlinks)
    odo = read_pose_csv(log / "odometry.csv")
    (out / "odometry.csv").unlink()
    rng = np.random.default_rng(seed)
    if variant == "loose":
        odo[:, 1:3] = odo[0, 1:3] + 1.05 * (odo[:, 1:3] - odo[0, 1:3])
    elif variant == "heading":
        walk = np.cumsum(rng.normal(0.0, 1.0, len(odo)))
        walk = np.convolve(walk - walk.mean(), np.ones(51) / 51, mode="same")
        odo[:, 3] += 0.2 * walk / max(walk.std(), 1e-9)
    elif variant == "flipped":
        gt = read_pose_csv(log / "ground_truth.csv")
        runs = lanes(gt)
        i, j = runs[min(lane, len(runs) - 1)]
        t0, t1 = gt[i, 0], gt[j - 1, 0]
        sel = (odo[:, 0] >= t0) & (odo[:, 0] <= t1)
        odo[sel, 3] = np.angle(np.exp(1j * (odo[sel, 3] + np.pi)))
    write_pose_csv(out / "odometry.csv", odo)
