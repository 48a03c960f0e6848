"""Overlaps no link verifies: where a mosaic can be ghosted without any residual showing it.

Accepted links tie frames into groups (connected components of the link graph). Inside a
group every overlap's alignment is checked by the links; between two groups the relative
placement rests on the prior alone (odometry, GPS), and where their frames overlap in the
map, a prior a few metres off draws the same road twice. No link residual sees that: on the
drone flight of examples/README.md such a map published with every gate passed (93 % of its
registrable frames overlapped a frame of another group).

:func:`unverified_overlaps` finds, at the optimized poses, the registrable frames whose
footprint overlaps a registrable frame of another group by at least ``min_overlap`` of the
smaller footprint (frames as rotated rectangles of their log's frame size, ``cv2``'s exact
intersection). The optimize stage reports them (``links.unverified_overlap_frames``, the
groups involved, examples) and warns in one line; ``[publish]
max_unverified_overlap_fraction`` gates their share of the registrable frames.

Units: poses ``(x, y, theta)`` in metres and radians (:mod:`mapstore.grid`); frame sizes in
metres.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["lone_frames", "unverified_overlaps"]


def unverified_overlaps(poses: np.ndarray, sizes_m: np.ndarray, groups: np.ndarray, candidates: np.ndarray,
                        min_overlap: float) -> tuple[np.ndarray, int]:
    """Frames overlapping a frame of another group: ``(mask (N,) bool, pairs)``.

    Args:
        poses: ``(N, 3)`` frame poses (centre x, y in metres; heading in radians).
        sizes_m: ``(N, 2)`` each frame's footprint (width, height) in metres.
        groups: ``(N,)`` link-group label per frame (:func:`pipeline.links.components`).
        candidates: ``(N,)`` bool, the frames that count (registrable, not dropped).
        min_overlap: the overlap's share of the smaller footprint that counts (0-1).
    """
    poses = np.asarray(poses, np.float64)
    sizes = np.asarray(sizes_m, np.float64)
    idx = np.flatnonzero(candidates)
    mask = np.zeros(len(poses), bool)
    pairs = 0
    if len(idx) < 2:
        return mask, 0
    reach = np.hypot(sizes[idx, 0], sizes[idx, 1]) / 2.0  # half diagonals
    order = np.argsort(poses[idx, 0])  # sweep along x: only frames within reach are tested
    xs = poses[idx[order], 0]
    rmax = float(reach.max())
    for k, oi in enumerate(order):
        i = idx[oi]
        stop = np.searchsorted(xs, xs[k] + reach[oi] + rmax, side="right")
        for ol in order[k + 1 : stop]:
            j = idx[ol]
            if groups[i] == groups[j]:
                continue
            if np.hypot(*(poses[i, :2] - poses[j, :2])) > reach[oi] + reach[ol]:
                continue
            ri = ((poses[i, 0], poses[i, 1]), (sizes[i, 0], sizes[i, 1]), float(np.degrees(poses[i, 2])))
            rj = ((poses[j, 0], poses[j, 1]), (sizes[j, 0], sizes[j, 1]), float(np.degrees(poses[j, 2])))
            kind, pts = cv2.rotatedRectangleIntersection(ri, rj)
            if kind == cv2.INTERSECT_NONE or pts is None or len(pts) < 3:
                continue
            area = cv2.contourArea(cv2.convexHull(pts.astype(np.float32)))
            if area >= min_overlap * min(sizes[i].prod(), sizes[j].prod()):
                mask[i] = mask[j] = True
                pairs += 1
    return mask, pairs


def lone_frames(frames: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Those of ``frames`` (indices) that form a group of their own (``groups``: a label per
    node, :func:`pipeline.links.components`): frames without any accepted link. Each one
    overlapping its neighbours makes every one of them an unverified overlap too; the
    report counts them apart so that one unlinked frame does not read as a ghosted strip."""
    groups = np.asarray(groups)
    frames = np.asarray(frames, np.int64)
    size_of = np.bincount(groups, minlength=int(groups.max()) + 1 if len(groups) else 0)
    return frames[size_of[groups[frames]] == 1] if len(frames) else frames
