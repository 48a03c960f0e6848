"""Template search by normalized cross-correlation, with a subpixel peak and uniqueness.

Kelly (2000): the *disparity* is the position of the NCC peak minus the predicted position;
*uniqueness* is C1 - C2, the highest minus the second-highest correlation peak in the search
neighbourhood (< 0.2 is poor); the *texture score* prequalifies templates. Units: pixels of
the image the template was cut from.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Peak", "Peaks", "weakest_direction_score", "noise_sigma", "ncc_peak", "peak_of", "subpixel_offset", "match_stack", "peaks_of"]


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


@dataclass(frozen=True)
class Peaks:
    """The :class:`Peak` fields of a stack of N searches, as (N,) arrays (float64, ``interior``
    bool); a search not done has c1 = c2 = -1 and ``interior`` False."""

    dx: np.ndarray
    dy: np.ndarray
    c1: np.ndarray
    c2: np.ndarray
    interior: np.ndarray


def weakest_direction_score(img: np.ndarray, window_px: int) -> np.ndarray:
    """Texture score of the weakest gradient direction over a ``window_px`` square around
    each pixel ((grey levels / px)^2, Sobel 3x3 / 8; float32, same shape): twice the smaller
    eigenvalue of the window's mean structure tensor. Equal to Kelly's (2000) texture score
    (mean squared gradient magnitude; :func:`pipeline.quality.texture_score_map` on the batch
    side, which the vehicle side may not import) on an isotropic texture, near 0 on a
    straight edge or line (a painted marking), where a template's match slides along the
    line and is not unique (Kelly's (2000) C1 - C2 would reject it after the search; this
    rejects it before).

    One ``cv2.cornerMinEigenVal`` (Shi and Tomasi's minimum eigenvalue: Sobel 3x3 gradients
    scaled by 1 / (4 window 255) for uint8, summed over the window) times 255^2 / 2: a
    fifth of the calls of the same arithmetic spelled out (borders reflected without
    repeating the edge pixel)."""
    src = img if img.dtype == np.uint8 else np.clip(img, 0, 255).astype(np.uint8)
    return cv2.cornerMinEigenVal(src, int(window_px), 3, borderType=cv2.BORDER_REFLECT_101) * _MIN_EIGEN_TO_SCORE


_MIN_EIGEN_TO_SCORE = np.float32(255.0 * 255.0 / 2.0)
"""cornerMinEigenVal of uint8 (gradients / (4 w 255), summed over w^2 pixels) -> twice the
smaller eigenvalue of the mean of (gradient / 8)^2: 2 (4 w 255)^2 / (64 w^2) = 255^2 / 2."""


_LAPLACE = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def noise_sigma(img: np.ndarray, crop: int = 64) -> float:
    """Sensor noise 1-sigma of an image (grey levels), Immerkaer's estimator (1996: the mean
    absolute response to a kernel that cancels smooth image structure) over a central crop
    of at most ``crop`` pixels a side (64: ~4000 responses, a few per cent of precision, and
    a third of the time of 128: it only decides whether a frame is prefiltered). A floor
    texture adds a little; rectified frames of the simulator read ~7 at noise sigma 10 and
    ~28-40 at sigma 40 (rectification smooths)."""
    h, w = img.shape
    r0, c0 = max((h - crop) // 2, 0), max((w - crop) // 2, 0)
    c = img[r0 : r0 + crop, c0 : c0 + crop]
    if c.dtype != np.uint8 and c.dtype != np.float32:
        c = c.astype(np.float32)
    r = cv2.filter2D(c, cv2.CV_32F, _LAPLACE, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2.0) * cv2.norm(r, cv2.NORM_L1) / max(r.size, 1) / 6.0)


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


def match_stack(windows: np.ndarray, templates: np.ndarray, todo: np.ndarray) -> np.ndarray:
    """NCC surfaces (cv2.TM_CCOEFF_NORMED) of ``templates[i]`` (N, t, t) over ``windows[i]``
    (N, t + 2R, t + 2R), float32 both, for the ``todo`` ones: (N, 2R + 1, 2R + 1) float32,
    -1 where not done.

    One cv2.matchTemplate per search. Windows and templates are offset by the templates'
    mean grey level first (the NCC does not change): the rounding error of OpenCV's DFT
    correlation falls from ~1e-4 to ~1e-6 of NCC."""
    n, s = windows.shape[:2]
    k = s - templates.shape[1] + 1
    level = np.float32(cv2.mean(templates.reshape(-1, templates.shape[-1]))[0]) if len(templates) else np.float32(0)
    windows, templates = windows - level, templates - level
    res = np.full((n, k, k), -1.0, np.float32)
    for i in np.flatnonzero(todo):
        res[i] = cv2.matchTemplate(windows[i], templates[i], cv2.TM_CCOEFF_NORMED)
    return res


def peaks_of(res: np.ndarray, exclusion: int | None, todo: np.ndarray | None = None) -> Peaks:
    """:func:`peak_of` of every surface of a stack ``res`` (N, K, K) (``res`` is modified
    when C2 is computed): offsets from the surfaces' centres (pixels), subpixel by the
    parabola through the peak's neighbours (clamped to +-0.5, 0 on the border), C1, and C2
    the best value farther than ``exclusion`` (Chebyshev) from the peak (-1 when none, or
    when ``exclusion`` is None: not computed). Surfaces not in ``todo`` get offsets 0 and
    c1 = c2 = -1. One cv2.minMaxLoc per surface (two with C2), plain floats otherwise."""
    n, kh, kw = res.shape
    dx, dy = np.zeros(n), np.zeros(n)
    c1, c2 = np.full(n, -1.0), np.full(n, -1.0)
    interior = np.zeros(n, bool)
    cx, cy = (kw - 1) / 2.0, (kh - 1) / 2.0
    for i in range(n) if todo is None else np.flatnonzero(todo).tolist():
        r = res[i]
        _, v, _, (px, py) = cv2.minMaxLoc(r)
        c1[i] = v
        if 0 < px < kw - 1 and 0 < py < kh - 1:
            interior[i] = True
            a = r[py - 1 : py + 2, px - 1 : px + 2].tolist()
            dx[i] = px - cx + subpixel_offset(a[1][0], v, a[1][2])
            dy[i] = py - cy + subpixel_offset(a[0][1], v, a[2][1])
        else:
            dx[i], dy[i] = px - cx, py - cy
        if exclusion is not None:
            y0, x0 = max(0, py - exclusion), max(0, px - exclusion)
            if (min(kh, py + exclusion + 1) - y0) * (min(kw, px + exclusion + 1) - x0) < kh * kw:
                r[y0 : py + exclusion + 1, x0 : px + exclusion + 1] = -1.0
                c2[i] = cv2.minMaxLoc(r)[1]
    return Peaks(dx, dy, c1, c2, interior)
