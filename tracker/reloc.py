"""Global relocalization: where on the map is this frame, with no prior (or a wrong one)?

Feature voting, as in ground-texture localization work: an *index* of ORB features (world
position, binary descriptor) over the map, built once (at export time); a live frame's ORB
features are matched against it (Hamming distance, ratio test), a RANSAC rigid fit over the
matches proposes a pose, and the floor tracker (:class:`tracker.floor.FloorTracker`)
verifies it by template correlation before it is called ``ok``. A proposal that does not
verify is never returned as a fix.

Why features rather than seed 004's eigenspace of patches: the vehicle's heading is
arbitrary at start-up, and an eigenspace of floor patches is not rotation invariant (one
would need every heading in the index, or rotation-invariant spectra that discard the
phase a floor texture is recognised by); ORB keypoints carry their own orientation, so one
index serves every heading, and the fit gives the full pose (x, y, theta), not only a
place. Measured in ``bench/bench_tracker.py``.

Units: frame pixels, world metres and radians (:mod:`mapstore.grid` conventions).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields

import cv2
import numpy as np

from mapstore.grid import MapGrid, frame_pixels_to_vehicle
from tracker.floor import LOST, Fix, FloorTracker
from tracker.tiles import TileCache

__all__ = ["RelocParams", "FeatureIndex", "build_index", "Relocalizer"]


@dataclass(frozen=True)
class RelocParams:
    """Relocalization settings (``[tracker.reloc]`` in ``configs/tracker.toml``)."""

    features_per_tile: int = 48
    tile_px: int = 256
    fast_threshold: int = 12
    query_features: int = 400
    ratio: float = 0.85
    ransac_m: float = 0.004
    min_inliers: int = 10
    max_scale_error: float = 0.03
    candidates: int = 3
    verify_sigma_m: float = 0.005
    verify_sigma_rad: float = 0.01

    @classmethod
    def from_dict(cls, d: dict) -> "RelocParams":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown relocalization parameter(s): {', '.join(sorted(unknown))}")
        return cls(**d)


@dataclass
class FeatureIndex:
    """ORB features of a map: ``xy`` (N, 2) float64 world metres, ``descriptors`` (N, 32)
    uint8, ``angle`` (N,) float32 keypoint orientation (degrees, map image frame)."""

    xy: np.ndarray
    descriptors: np.ndarray
    angle: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)


def _orb(n: int, fast_threshold: int) -> cv2.ORB:
    # one pyramid level: the camera height is fixed, so is the scale
    return cv2.ORB_create(nfeatures=n, scaleFactor=1.2, nlevels=1, edgeThreshold=31, patchSize=31,
                          fastThreshold=fast_threshold)


def build_index(tiles: TileCache, grid: MapGrid, params: RelocParams | None = None) -> FeatureIndex:
    """ORB features over every ``params.tile_px`` tile of the map raster (level 0 of
    ``grid``), each tile read with a 32-pixel margin of context so features near tile edges
    are found once, by the tile holding them. Tiles with no data are skipped; a feature is
    kept only where the descriptor's 31-pixel patch is wholly covered."""
    p = params or RelocParams()
    orb = _orb(p.features_per_tile, p.fast_threshold)
    margin = 32
    xy, desc, ang = [], [], []
    h, w = grid.shape
    t = p.tile_px
    for r0 in range(0, h, t):
        for c0 in range(0, w, t):
            win = tiles.window(r0 - margin, r0 + t + margin, c0 - margin, c0 + t + margin)
            if not win.any():
                continue
            covered = (win > 0).astype(np.uint8)
            mask = cv2.erode(covered, np.ones((33, 33), np.uint8), borderValue=0)
            mask[:margin] = 0
            mask[margin + t :] = 0
            mask[:, :margin] = 0
            mask[:, margin + t :] = 0
            if not mask.any():
                continue
            kps, d = orb.detectAndCompute(win, mask)
            if d is None:
                continue
            pts = np.array([k.pt for k in kps], float)
            gx, gy = grid.pixel_to_world(pts[:, 0] + c0 - margin, pts[:, 1] + r0 - margin)
            xy.append(np.column_stack([gx, gy]))
            desc.append(d)
            ang.append(np.array([k.angle for k in kps], np.float32))
    if not xy:
        return FeatureIndex(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, np.float32))
    return FeatureIndex(np.vstack(xy), np.vstack(desc), np.concatenate(ang))


class Relocalizer:
    """Pose proposals from a :class:`FeatureIndex`, verified by a :class:`FloorTracker`."""

    def __init__(self, index: FeatureIndex, tracker: FloorTracker, params: RelocParams | None = None):
        self.index = index
        self.tracker = tracker
        self.p = params or RelocParams()
        self._orb = _orb(self.p.query_features, self.p.fast_threshold)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.last_seconds = 0.0

    def proposals(self, frame: np.ndarray, valid: np.ndarray | None = None) -> list[tuple[np.ndarray, int]]:
        """Up to ``candidates`` poses (x, y, theta) with their RANSAC inlier counts, best first."""
        p = self.p
        if len(self.index) < p.min_inliers:
            return []
        mask = None if valid is None else cv2.erode(valid.astype(np.uint8), np.ones((33, 33), np.uint8))
        kps, d = self._orb.detectAndCompute(frame, mask)
        if d is None or len(kps) < p.min_inliers:
            return []
        pairs = self._matcher.knnMatch(d, self.index.descriptors, k=2)
        good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < p.ratio * m[1].distance]
        if len(good) < p.min_inliers:
            return []
        q = np.array([kps[m.queryIdx].pt for m in good], float)
        vx, vy = frame_pixels_to_vehicle(q[:, 0], q[:, 1], frame.shape, self.tracker.frame_pixel_size)
        src = np.column_stack([vx, vy])
        dst = self.index.xy[[m.trainIdx for m in good]]
        out: list[tuple[np.ndarray, int]] = []
        remaining = np.ones(len(good), bool)
        for _ in range(p.candidates):
            if remaining.sum() < p.min_inliers:
                break
            # RANSAC in metres, around a local origin (float32 inside OpenCV)
            o = dst[remaining].mean(axis=0)
            m, inl = cv2.estimateAffinePartial2D(src[remaining].astype(np.float32),
                                                 (dst[remaining] - o).astype(np.float32),
                                                 method=cv2.RANSAC, ransacReprojThreshold=p.ransac_m,
                                                 maxIters=2000, confidence=0.999)
            if m is None:
                break
            inl = inl.ravel().astype(bool)
            scale = float(np.hypot(m[0, 0], m[1, 0]))
            n_in = int(inl.sum())
            if n_in < p.min_inliers:
                break
            idx = np.flatnonzero(remaining)
            if abs(scale - 1.0) <= p.max_scale_error:
                out.append((np.array([m[0, 2] + o[0], m[1, 2] + o[1], float(np.arctan2(m[1, 0], m[0, 0]))]), n_in))
            remaining[idx[inl]] = False
        return out

    def locate(self, frame: np.ndarray, valid: np.ndarray | None = None) -> Fix:
        """A verified fix with no prior: the first proposal the tracker confirms (``ok``),
        else a ``lost`` fix (pose NaN). ``last_seconds`` holds the time it took."""
        t0 = time.perf_counter()
        sigma = np.array([self.p.verify_sigma_m, self.p.verify_sigma_m, self.p.verify_sigma_rad])
        tried = 0
        try:
            for pose, n_in in self.proposals(frame, valid):
                tried += 1
                fix = self.tracker.fix(frame, pose, sigma, valid)
                if fix.ok:
                    fix.reasons["reloc_inliers"] = n_in
                    return fix
            return Fix(np.full(3, np.nan), np.full((3, 3), np.nan), LOST, reasons={"reloc_proposals": tried})
        finally:
            self.last_seconds = time.perf_counter() - t0
