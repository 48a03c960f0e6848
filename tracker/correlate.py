"""Template search by normalized cross-correlation, with a subpixel peak and uniqueness.

Seed 000: the *disparity* is the position of the NCC peak minus the predicted position;
*uniqueness* is C1 - C2, the highest minus the second-highest correlation peak in the search
neighbourhood (< 0.2 is poor); the *texture score* prequalifies templates. Units: pixels of
the image the template was cut from.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Peak", "texture_score", "ncc_peak", "peak_of", "subpixel_offset"]


@dataclass(frozen=True)
class Peak:
    """One template's search result.

    ``dx, dy``: subpixel offset (columns, rows) of the best match from the window's centre
    (pixels); ``c1``: its NCC; ``c2``: the best NCC outside ``exclusion`` pixels of it
    (-1 when there is no other position); ``interior``: the peak is not on the search
    border (a border peak may be the flank of a peak outside the window).
    """

    dx: float
    dy: float
    c1: float
    c2: float
    interior: bool

    @property
    def uniqueness(self) -> float:
        return self.c1 - self.c2


def texture_score(img: np.ndarray, window_px: int) -> np.ndarray:
    """Seed 000's texture score: the mean squared gradient magnitude ((grey levels / px)^2,
    Sobel 3x3 / 8) over a ``window_px`` square around each pixel; float32, same shape."""
    gx, gy = cv2.spatialGradient(img if img.dtype == np.uint8 else np.clip(img, 0, 255).astype(np.uint8))
    g = gx.astype(np.float32)
    energy = cv2.multiply(g, g, scale=1.0 / 64.0)
    g = gy.astype(np.float32)
    energy = cv2.add(energy, cv2.multiply(g, g, scale=1.0 / 64.0))
    return cv2.boxFilter(energy, -1, (window_px, window_px), normalize=True, borderType=cv2.BORDER_REFLECT)


def subpixel_offset(m1: float, c0: float, p1: float) -> float:
    """Vertex of the parabola through (-1, m1), (0, c0), (1, p1), clamped to [-0.5, 0.5]."""
    den = m1 - 2.0 * c0 + p1
    if den >= 0.0:
        return 0.0
    return float(min(0.5, max(-0.5, 0.5 * (m1 - p1) / den)))


def ncc_peak(window: np.ndarray, template: np.ndarray, exclusion: int) -> Peak:
    """Search ``template`` (h, w) over ``window`` (h + 2R, w + 2R), float32 both.

    The window's centre position (offset R, R) is the prediction; the returned offsets are
    relative to it.
    """
    return peak_of(cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED), exclusion)


def peak_of(res: np.ndarray, exclusion: int) -> Peak:
    """The :class:`Peak` of one NCC surface (offsets from its centre; ``res`` is modified)."""
    py, px = np.unravel_index(int(np.argmax(res)), res.shape)
    c1 = float(res[py, px])
    rh, rw = res.shape
    interior = 0 < px < rw - 1 and 0 < py < rh - 1
    if interior:
        sx = subpixel_offset(res[py, px - 1], c1, res[py, px + 1])
        sy = subpixel_offset(res[py - 1, px], c1, res[py + 1, px])
    else:
        sx = sy = 0.0
    y0, y1 = max(0, py - exclusion), min(rh, py + exclusion + 1)
    x0, x1 = max(0, px - exclusion), min(rw, px + exclusion + 1)
    if (y1 - y0) * (x1 - x0) == res.size:
        c2 = -1.0
    else:
        res[y0:y1, x0:x1] = -1.0
        c2 = float(res.max())
    return Peak(px - (rw - 1) / 2.0 + sx, py - (rh - 1) / 2.0 + sy, float(c1), c2, interior)
