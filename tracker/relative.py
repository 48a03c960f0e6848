"""Relative mode: frame-to-frame motion where the map has no data (Kelly's (2000) unmapped areas).

The previous frame is treated as a small map: a :class:`mapstore.grid.MapGrid` whose pixel
``(r, c)`` is the previous frame's pixel ``(r, c)``, so that "world" coordinates are the
previous vehicle frame (metres; the frame centre at the origin, +x along the columns, +y
against the rows, as :mod:`mapstore.grid`'s frame convention). The floor tracker's fix of
the current frame against it, from the odometry's motion as prior, is then the motion
between the two frames: the same templates, correlation, robust rigid fit and statuses as
an absolute fix, with the same guarantee (never ``ok`` on disagreement).

Errors accumulate: each step's covariance (from the fit) is composed into the pose's, so a
stretch of relative steps reports how far it may have drifted (:func:`compose_covariance`);
the session (:mod:`tracker.session`) reports the measured growth against ground truth.
"""

from __future__ import annotations

import numpy as np

from mapstore.grid import MapGrid, frame_centre, se2_compose
from tracker.floor import Fix, FloorTracker, FloorTrackerParams
from tracker.tiles import ArrayTiles

__all__ = ["frame_grid", "frame_as_map", "RelativeTracker", "compose_covariance", "chain"]


def frame_grid(shape: tuple[int, int], pixel_size: float) -> MapGrid:
    """The grid of a frame of ``shape`` (H, W) in its own vehicle frame: pixel (r, c) of
    the grid is pixel (r, c) of the frame (:mod:`mapstore.grid` frame convention)."""
    cx, cy = frame_centre(shape)
    return MapGrid(-cx * pixel_size, cy * pixel_size, float(pixel_size), int(shape[1]), int(shape[0]))


def frame_as_map(frame: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    """A frame (uint8) as map pixels: 0 = no data where ``valid`` is False, covered pixels 1..255."""
    out = np.maximum(frame, 1).astype(np.uint8)
    if valid is not None:
        out[~valid] = 0
    return out


def compose_covariance(pose_a: np.ndarray, cov_a: np.ndarray, delta: np.ndarray, cov_d: np.ndarray) -> np.ndarray:
    """Covariance (m^2, rad^2) of ``pose_a ⊕ delta`` to first order, for independent errors:
    ``J_a cov_a J_a^T + J_d cov_d J_d^T`` (``delta`` in ``pose_a``'s frame)."""
    c, s = np.cos(pose_a[2]), np.sin(pose_a[2])
    dx, dy = float(delta[0]), float(delta[1])
    ja = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
    jd = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ja @ cov_a @ ja.T + jd @ cov_d @ jd.T


class RelativeTracker:
    """Frame-to-frame fixes of rectified frames of one size and pixel size.

    Args:
        frame_pixel_size: metres per pixel of the rectified frames.
        params: :class:`FloorTrackerParams` (the absolute tracker's).
    """

    def __init__(self, frame_pixel_size: float, params: FloorTrackerParams | None = None):
        self.frame_pixel_size = float(frame_pixel_size)
        self.params = params or FloorTrackerParams()

    def step(self, previous: np.ndarray, previous_valid: np.ndarray | None, frame: np.ndarray,
             valid: np.ndarray | None, motion_prior: np.ndarray, motion_sigma: np.ndarray) -> Fix:
        """The motion from ``previous`` to ``frame``: a :class:`Fix` whose ``pose`` is the
        current frame's pose in the previous vehicle frame (x, y metres, theta radians) and
        ``cov`` its covariance. ``motion_prior``: the odometry's motion, same frame;
        ``motion_sigma``: its 1-sigma (m, m, rad)."""
        grid = frame_grid(previous.shape, self.frame_pixel_size)
        tiles = ArrayTiles(frame_as_map(previous, previous_valid), tile_px=max(previous.shape))
        # (the fix takes templates only where the previous frame overlaps this one)
        return FloorTracker(tiles, grid, self.frame_pixel_size, self.params).fix(frame, motion_prior, motion_sigma,
                                                                                 valid)


def chain(pose: np.ndarray, cov: np.ndarray, step: Fix) -> tuple[np.ndarray, np.ndarray]:
    """Pose and covariance after one relative step (``step.pose`` in ``pose``'s frame)."""
    return se2_compose(pose, step.pose), compose_covariance(pose, cov, step.pose, step.cov)
