"""Coarse translation of one frame against another: phase correlation over the predicted overlap.

The coarse stage of pairwise registration (:mod:`pipeline.registration`): it finds the
integer-pixel neighbourhood of the answer, which Gauss-Newton then refines to a small
fraction of a pixel. Its cost is that of one FFT of the predicted overlap padded by the
search radius, whatever the prior's error, and it works on strips as narrow as ~12 px.

Method (as MIST and ASHLAR do for tile grids):

1. The *search box*: frame a's part that frame b overlaps at the prior (b warped into a's
   pixel frame with the prior), grown by the search radius on every side and clipped to a.
2. Both images over the box (b resampled there with the prior), reduced by a power of two
   when the box holds more than ``max_pixels`` pixels, mean-free over their valid pixels
   and tapered to 0 over ``taper_px`` at their valid edges (no spectral leakage from the
   edges of a strip or of b's footprint).
3. The phase correlation surface (normalized cross-power spectrum, Gaussian low-pass of
   ``smoothing_px``); its ``peaks`` highest local maxima are the candidates. A circular
   surface cannot tell a shift ``d`` from ``d - size``: both aliases of each peak are kept.
4. The highest peak whose shift leaves at least ``min_overlap_px`` overlapping pixels is the
   answer (of its aliases, the one whose actual overlap matches best: band-passed NCC);
   its height C1 against the highest competing peak C2 (farther than ``exclusion_px``)
   gives the uniqueness ``1 - C2 / C1``, Kelly's (2000) C1 - C2 on a scale-free surface:
   repeating texture, or no match at all, drives it towards 0. When other peaks reach
   ``NCC_PEAK_FRACTION`` of the highest (a narrow strip in a wide search box: the match is
   one peak among noise peaks of its height), the band-passed NCC over each one's actual
   overlap decides between them, and that NCC is the answer's significance too
   (``ncc``; the register stage accepts a match by it where the peak alone is not
   significant).

Conventions: pixel frames (column x, row y) as in :mod:`mapstore.grid`. The result ``d``
(full-resolution pixels, float) satisfies ``a(x) ~ bw(x + d)`` with ``bw`` b warped into
a's frame by the prior: the corrected warp is ``a_to_b`` composed with a translation by d.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.resample import masked_blur
from pipeline.spectrum import ccs_layout, ccs_lowpass, ccs_magnitudes, ccs_scale, full_magnitude_sample

__all__ = ["CoarseParams", "CoarseResult", "coarse_shift", "mapped_box", "reach_fraction"]

# C2 / C1 on the surface from which the NCC check of the uniqueness runs (see coarse_shift).
NCC_CHECK = 0.1
# A ridge: the band-passed NCC falls along it (to C2 and twice as far) by less than this
# share of its fall across at C2's distance (stripes: ~0; fibres of tissue: 0.3 and more).
RIDGE_FALL = 0.25
# Peaks at least this share of the highest one are told apart by the band-passed NCC over
# their actual overlap (as MIST does): a strip a tenth of the search box wide puts the match
# among noise peaks of its own height.
NCC_PEAK_FRACTION = 0.5
# ... and a lower peak must beat a higher one's band-passed NCC by this much (on a tissue
# section a peak 11 px off the match reached 0.91 on its own overlap).
NCC_PEAK_MARGIN = 0.1
# The answer's NCC is its significance (CoarseResult.ncc) only when the other peaks' NCCs
# stay below 1 - this of it (3 % strips: the match 0.85, noise peaks 0.05-0.1; a tissue
# section's smooth structure: 0.9 against 0.57-0.77, no answer).
NCC_DECISIVE = 0.5


@dataclass(frozen=True)
class CoarseParams:
    """Knobs of the coarse stage (``[register]`` ``coarse_*``; see configs/floor.toml).

    Attributes:
        max_pixels: boxes with more pixels are reduced by powers of two to at most this.
        window_px: an overlap whose shorter side exceeds this is searched in a window of
            ``max(window_px, 4 radius + 32)`` pixels about its middle (0: never).
        min_side_px: ... but never so far that the box's shorter side falls below this.
        peaks: correlation peaks checked by NCC.
        smoothing_px: Gaussian low-pass of the correlation surface (reduced pixels).
        whitening_floor: the cross-power spectrum's magnitudes m are normalized by
            ``m + whitening_floor x median(m)`` (0: pure phase correlation).
        taper_px: width of the cosine taper at valid edges (reduced pixels; at most a
            quarter of the box's shorter side).
        exclusion_px: C2 is the best candidate at least this far from C1 (full-res pixels).
        min_overlap_px: fewest overlapping valid pixels (full resolution) for a candidate.
    """

    max_pixels: int = 65536
    window_px: int = 64
    min_side_px: int = 16
    peaks: int = 6
    smoothing_px: float = 0.0
    whitening_floor: float = 3.0
    taper_px: float = 6.0
    exclusion_px: float = 4.0
    min_overlap_px: int = 2000


@dataclass(frozen=True)
class CoarseResult:
    """The coarse answer.

    Attributes:
        shift: (2,) float, full-resolution pixels (x, y): ``a(x) ~ bw(x + shift)``.
        peak: C1, the best candidate's height on the phase correlation surface (1 for
            identical images; noise peaks of a w x h box reach about sqrt(2 ln(w h) / (w h))).
        uniqueness: 1 - C2 / C1 in [0, 1] with C2 the highest competing peak (more than
            ``exclusion_px`` away, with a shift that leaves enough overlap; 0 without any):
            Kelly's (2000) C1 - C2 made independent of the surface's scale. Repeating texture,
            or no match at all, drives it towards 0.
        overlap_px: overlapping valid pixels of the best candidate (full resolution).
        scale: reduction factor used (1, 2, 4, ...).
        candidates: candidates scored.
        peak_z: C1's height over the surface's robust standard deviation.
        ncc: the band-passed NCC over the answer's actual overlap when peaks of comparable
            height were told apart by it and it sets the answer apart (the others' at most
            ``1 - NCC_DECISIVE`` of it); NaN otherwise (one peak stood out alone, or the
            NCC does not decide).
    """

    shift: np.ndarray
    peak: float
    uniqueness: float
    overlap_px: int
    scale: int
    candidates: int
    peak_z: float = 0.0
    ncc: float = float("nan")


def mapped_box(m: np.ndarray, x0: float, y0: float, x1: float, y1: float,
               grow: float = 0.0) -> tuple[int, int, int, int]:
    """Integer box ``(x0, y0, x1, y1)`` (end exclusive) holding the box ``[x0, x1] x [y0,
    y1]`` mapped by the 2 x 3 (or 3 x 3) affine ``m``, grown by ``grow`` pixels; not clipped."""
    corners = np.array([[x0, y0, 1.0], [x1, y0, 1.0], [x0, y1, 1.0], [x1, y1, 1.0]]) @ np.asarray(m, float)[:2].T
    lo, hi = corners.min(axis=0) - grow, corners.max(axis=0) + grow
    return int(np.floor(lo[0])), int(np.floor(lo[1])), int(np.ceil(hi[0])) + 1, int(np.ceil(hi[1])) + 1


def _search_box(a_valid: np.ndarray, b_valid: np.ndarray, a_to_b: np.ndarray,
                radius: int, window: int = 0
                ) -> tuple[tuple[int, int, int, int], int, tuple[int, int, int, int]] | None:
    """``((x0, y0, x1, y1), narrow, footprint)``: where b may overlap a, the bounding box of
    b's valid pixels mapped into a's frame by the prior (``footprint``, end exclusive, not
    clipped), grown by ``radius``, clipped to a's valid bounding box; and the shorter side
    of the overlap the prior predicts (0 when it predicts none). None when the box is empty."""
    bx, by, bw, bh = cv2.boundingRect(b_valid.view(np.uint8))
    ax, ay, aw, ah = cv2.boundingRect(a_valid.view(np.uint8))
    if bw == 0 or aw == 0:
        return None
    footprint = mapped_box(cv2.invertAffineTransform(a_to_b), bx, by, bx + bw - 1, by + bh - 1)
    px0, py0, px1, py1 = footprint
    narrow = max(min(min(px1, ax + aw) - max(px0, ax), min(py1, ay + ah) - max(py0, ay)), 0)
    x0, y0 = max(px0 - radius, ax), max(py0 - radius, ay)
    x1, y1 = min(px1 + radius, ax + aw), min(py1 + radius, ay + ah)
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None
    if window > 0 and narrow > window:
        # A wide overlap: a window about its middle is plenty, and smaller than the whole
        # overlap it smears less under a scale or rotation the prior does not know.
        half = max(window, 4 * radius + 32) // 2
        cx = (max(px0, ax) + min(px1, ax + aw)) // 2
        cy = (max(py0, ay) + min(py1, ay + ah)) // 2
        wx0, wy0, wx1, wy1 = max(x0, cx - half), max(y0, cy - half), min(x1, cx + half), min(y1, cy + half)
        # (only where a is valid all over it: the middle of a mirror camera's ring of
        # valid floor pixels is its hole)
        if wx1 - wx0 >= 2 and wy1 - wy0 >= 2 and a_valid[wy0:wy1, wx0:wx1].mean() >= 0.9:
            x0, y0, x1, y1 = wx0, wy0, wx1, wy1
    return (x0, y0, x1, y1), narrow, footprint


def reach_fraction(a_valid: np.ndarray, b_valid: np.ndarray, a_to_b: np.ndarray, radius_px: float) -> float:
    """Share of a's valid pixels within the search radius of b's footprint at the prior
    (bounding boxes: b's footprint may lie wholly outside a at the prior)."""
    found = _search_box(a_valid, b_valid, a_to_b, max(int(np.ceil(radius_px)), 1))
    if found is None:
        return 0.0
    x0, y0, x1, y1 = found[0]
    return float(np.count_nonzero(a_valid[y0:y1, x0:x1])) / max(float(np.count_nonzero(a_valid)), 1.0)


def _grown(mask: np.ndarray, radius: int) -> np.ndarray:
    """uint8 0/1 ``mask`` dilated by a square of half-side ``radius`` (pixels). (A chessboard
    distance transform, linear in the pixels: OpenCV's dilation costs the kernel's side per
    pixel, minutes for a wide search over a large frame.)"""
    if radius <= 8:
        return cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * radius + 1, 2 * radius + 1)))
    dist = cv2.distanceTransform((mask == 0).view(np.uint8), cv2.DIST_C, 3)
    return (dist <= radius).view(np.uint8)


def _crop(img: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """``img[y0:y1, x0:x1]`` with zeros where the box leaves the image."""
    h, w = img.shape
    if x0 >= 0 and y0 >= 0 and x1 <= w and y1 <= h:
        return img[y0:y1, x0:x1]
    out = np.zeros((y1 - y0, x1 - x0), img.dtype)
    sx0, sy0, sx1, sy1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - y0 : sy1 - y0, sx0 - x0 : sx1 - x0] = img[sy0:sy1, sx0:sx1]
    return out


def _reduction(w: int, h: int, narrow: int, p: CoarseParams) -> int:
    """Power-of-two reduction bringing a w x h box to at most ``max_pixels`` pixels, unless
    its shorter side, or the predicted overlap's (``narrow``, when > 0), would fall below
    ``min_side_px``."""
    side = min(w, h) if narrow <= 0 else min(w, h, narrow)
    f = 1
    while (w // f) * (h // f) > p.max_pixels and side // (2 * f) >= p.min_side_px:
        f *= 2
    return f


def _taper(mask: np.ndarray, taper: float) -> np.ndarray:
    """Weights rising smoothly from 0 at the edge of ``mask`` (and of the array) to 1 about
    ``taper`` pixels inside: a box mean of the mask over 2 x taper + 1 pixels is 1/2 on a
    straight edge and 1 deep inside; float32."""
    m = mask.astype(np.float32)
    k = 2 * max(int(round(taper)), 1) + 1
    t = cv2.blur(m, (k, k), borderType=cv2.BORDER_CONSTANT)
    u = np.clip(2.0 * t - 1.0, 0.0, 1.0)
    return m * u * u * (3.0 - 2.0 * u)


def _prepared(img: np.ndarray, mask: np.ndarray, taper: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean-free over ``mask``, 0 outside, tapered to 0 over ``taper`` px at the mask's
    edge; and the taper weights."""
    w = _taper(mask, taper)
    n = float(w.sum())
    mean = float((img * w).sum(dtype=np.float64) / n) if n > 0 else 0.0
    return (img - np.float32(mean)) * w, w


# Values a median for a threshold is taken from (an even subsample).
MEDIAN_SAMPLES = 1024


def _median(x: np.ndarray, samples: int = MEDIAN_SAMPLES) -> float:
    """Median of an array, from an even subsample of at most ``samples`` values (a scale
    for a threshold needs no more)."""
    flat = x.ravel()
    step = max(len(flat) // samples, 1)
    return float(np.median(flat[::step]))


def _overlap_weight(wa: np.ndarray, wb: np.ndarray) -> np.ndarray:
    """The whole surface of :func:`_weight_at` at once (three real FFTs, circular)."""
    cross = cv2.mulSpectrums(cv2.dft(wa), cv2.dft(wb), 0, conjB=True)
    return cv2.idft(cross, flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)


# Local maxima whose overlap weight is evaluated one by one for C2; beyond that many (a
# flat surface of many similar maxima) the whole weight surface is computed by FFT.
WEIGHT_EVALUATIONS = 4


def _weight_at(wa: np.ndarray, wb: np.ndarray, py: int, px: int) -> float:
    """``W(d) = sum_x wa(x + d) wb(x)`` at the surface position (py, px) (the convention of
    :func:`_phase_surface`; the images are zero-padded beyond every reachable shift, so the
    position's nearer alias is its shift): how much of the two images' weight the shift
    brings together. Evaluated directly at the few peaks that need it (a whole surface of
    it by FFT was a fifth of the coarse stage)."""
    h, w = wa.shape
    dy = py if py <= h // 2 else py - h
    dx = px if px <= w // 2 else px - w
    ya0, ya1 = max(0, -dy), min(h, h - dy)
    xa0, xa1 = max(0, -dx), min(w, w - dx)
    if ya1 <= ya0 or xa1 <= xa0:
        return 0.0
    return float(np.einsum("ij,ij->", wa[ya0 + dy:ya1 + dy, xa0 + dx:xa1 + dx], wb[ya0:ya1, xa0:xa1],
                           dtype=np.float64))


def _phase_surface(a: np.ndarray, b: np.ndarray, sigma: float, floor: float) -> np.ndarray:
    """``r(d) = sum_x a(x + d) b(x)``, phase-normalized and low-passed, shape of a. The
    cross-power spectrum's magnitudes m are divided by ``m + floor x median(m)``:
    components well above the median (the texture) come out level, as in pure phase
    correlation (``floor`` = 0), while the many weak ones, mostly noise, are not raised to
    their level. (Real transforms, the spectra packed: :mod:`pipeline.spectrum`.)"""
    h, w = a.shape
    cross = cv2.mulSpectrums(cv2.dft(a), cv2.dft(b), 0, conjB=True)
    lay = ccs_layout(h, w)
    mag = ccs_magnitudes(cross, lay)
    k = len(lay.re)
    # (the full spectrum's mean and median: every complex entry stands for itself and its
    # conjugate)
    mean = (2.0 * float(mag[:k].sum(dtype=np.float64)) + float(mag[k:].sum(dtype=np.float64))) / (h * w)
    med = float(np.median(mag[full_magnitude_sample(h, w, MEDIAN_SAMPLES)]))
    gain = np.float32(1.0) / (mag + np.float32(floor * med + 1e-6 * mean + 1e-20))
    if sigma > 0:
        gain *= ccs_lowpass(h, w, float(sigma))
    ccs_scale(cross, lay, gain)
    return cv2.idft(cross, flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)


def _peaks(r: np.ndarray, k: int, suppress: int = 2) -> list[tuple[int, int]]:
    """The ``k`` highest peaks (row, col) of a surface, each at least ``suppress`` + 1 px
    from the others (the maximum, then the maximum outside its neighbourhood, ...)."""
    r = r.copy()
    h, w = r.shape
    out = []
    low = float(r.min()) - 1.0
    for _ in range(k):
        _, _, _, (x, y) = cv2.minMaxLoc(r)
        out.append((y, x))
        r[max(y - suppress, 0) : y + suppress + 1, max(x - suppress, 0) : x + suppress + 1] = low
        # (a peak on the border: its wrapped neighbourhood too)
        if y < suppress:
            r[h - (suppress - y) :, max(x - suppress, 0) : x + suppress + 1] = low
        if x < suppress:
            r[max(y - suppress, 0) : y + suppress + 1, w - (suppress - x) :] = low
        if y >= h - suppress:
            r[: y + suppress + 1 - h, max(x - suppress, 0) : x + suppress + 1] = low
        if x >= w - suppress:
            r[max(y - suppress, 0) : y + suppress + 1, : x + suppress + 1 - w] = low
    return out


def _subpixel(r: np.ndarray, y: int, x: int) -> tuple[float, float]:
    """Parabolic vertex offsets (dy, dx) in (-0.5, 0.5) around the circular peak (y, x)."""
    h, w = r.shape

    def vertex(m: float, c: float, p: float) -> float:
        den = m - 2.0 * c + p
        return float(np.clip(0.5 * (m - p) / den, -0.5, 0.5)) if den < 0 else 0.0

    c = float(r[y, x])
    return (vertex(float(r[(y - 1) % h, x]), c, float(r[(y + 1) % h, x])),
            vertex(float(r[y, (x - 1) % w]), c, float(r[y, (x + 1) % w])))


def _band_pass(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Difference of Gaussians (1 and 8 px) over the valid pixels (float32 0/1 ``mask``;
    normalized convolution, so that the frame's edge is no structure): the texture,
    without shading or noise; 0 outside the mask.

    Candidates are compared on it: on the raw images the NCC of slowly varying content
    (vignetting, large structures) stays high several pixels off the match, which made
    every neighbour of the peak a "competitor" (C1 - C2 ~ 0.02 on pairs that match well).
    """
    return (masked_blur(img, mask, 1.0) - masked_blur(img, mask, 8.0)) * mask


def _overlap_count(ma: np.ndarray, mb: np.ndarray, dx: int, dy: int, min_n: int) -> int:
    """Pixels valid in both ``ma(x)`` and ``mb(x + d)`` (float32 0/1 masks); 0 when their
    rectangle of overlap is already smaller than ``min_n``."""
    h, w = ma.shape
    ya0, ya1 = max(0, -dy), min(h, h - dy)
    xa0, xa1 = max(0, -dx), min(w, w - dx)
    if ya1 <= ya0 or xa1 <= xa0 or (ya1 - ya0) * (xa1 - xa0) < min_n:  # (a shift beyond the box: none)
        return 0
    return int(np.einsum("ij,ij->", ma[ya0:ya1, xa0:xa1], mb[ya0 + dy:ya1 + dy, xa0 + dx:xa1 + dx],
                         dtype=np.float64))


def _shifted(m: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``m(x + d)`` on ``m``'s grid, 0 where ``x + d`` falls outside."""
    h, w = m.shape
    out = np.zeros_like(m)
    ya0, ya1 = max(0, -dy), min(h, h - dy)
    xa0, xa1 = max(0, -dx), min(w, w - dx)
    if ya1 > ya0 and xa1 > xa0:
        out[ya0:ya1, xa0:xa1] = m[ya0 + dy:ya1 + dy, xa0 + dx:xa1 + dx]
    return out


def _ncc_at(a: np.ndarray, ma: np.ndarray, b: np.ndarray, mb: np.ndarray, dx: int, dy: int,
            min_n: int) -> tuple[float, int]:
    """NCC of ``a(x)`` and ``b(x + d)`` over the pixels valid in both; (ncc, pixels).

    ``a``, ``b`` are 0 outside their valid masks ``ma``, ``mb`` (float32 0/1). Pairs whose
    rectangle of overlap holds fewer than ``min_n`` pixels are not evaluated (ncc -1).
    """
    h, w = a.shape
    ya0, ya1 = max(0, -dy), min(h, h - dy)
    xa0, xa1 = max(0, -dx), min(w, w - dx)
    if ya1 <= ya0 or xa1 <= xa0 or (ya1 - ya0) * (xa1 - xa0) < min_n:  # (a shift beyond the box: none)
        return -1.0, 0
    sa = (slice(ya0, ya1), slice(xa0, xa1))
    sb = (slice(ya0 + dy, ya1 + dy), slice(xa0 + dx, xa1 + dx))
    m = ma[sa] * mb[sb]
    n = float(m.sum(dtype=np.float64))
    if n < min_n:
        return -1.0, int(n)
    va, vb = a[sa] * m, b[sb] * m
    sa1, sb1 = float(va.sum(dtype=np.float64)), float(vb.sum(dtype=np.float64))
    saa = float(np.einsum("ij,ij->", va, va, dtype=np.float64)) - sa1 * sa1 / n
    sbb = float(np.einsum("ij,ij->", vb, vb, dtype=np.float64)) - sb1 * sb1 / n
    sab = float(np.einsum("ij,ij->", va, vb, dtype=np.float64)) - sa1 * sb1 / n
    den = np.sqrt(max(saa, 0.0) * max(sbb, 0.0))
    return (sab / den if den > 0 else -1.0), int(n)


def coarse_shift(
    a: np.ndarray,
    a_valid: np.ndarray,
    b: np.ndarray,
    b_valid: np.ndarray,
    a_to_b: np.ndarray,
    radius_px: float,
    p: CoarseParams,
) -> CoarseResult | str:
    """Coarse shift of b against a near the prior ``a_to_b`` (2 x 3, a's pixels -> b's).

    Args:
        a, b: float32 frames (grey levels) and their boolean valid masks.
        a_to_b: the prior warp, a's pixel (x, y) -> b's pixel.
        radius_px: the prior's uncertainty (pixels): the box grows by it on every side and
            candidate shifts lie within it (plus one reduced pixel).

    Returns:
        :class:`CoarseResult`, or a reason string when the pair cannot be searched.
    """
    radius = max(int(np.ceil(radius_px)), 1)
    flags = cv2.WARP_INVERSE_MAP
    found = _search_box(a_valid, b_valid, a_to_b, radius, p.window_px)
    if found is None:
        return "small overlap: frames do not overlap within the search radius of the prior"
    box, narrow, (fx0, fy0, fx1, fy1) = found
    # The part of a that b may overlap, grown once more by the radius (beyond a's edge, a is
    # invalid there): b's pixels that a shift within the radius brings into a are in it.
    x0, y0, x1, y1 = box[0] - radius, box[1] - radius, box[2] + radius, box[3] + radius
    # ... but no further than b's footprint at the prior reaches (beyond both a's box and b's
    # footprint neither frame has a pixel): a radius larger than the frames (a GPS prior's
    # revisits, 1500-2500 px around 682 x 511 frames) grew the box, and every array of this
    # search, to 6000 x 6000 px, 4 GB at peak for a 60-frame drone log.
    # (Only where the radius exceeds the box: with the smaller radii of floors and tile
    # grids the box is left as it was.)
    if 2 * radius > max(box[2] - box[0], box[3] - box[1]):
        x0, y0 = max(x0, min(box[0], fx0 - 2)), max(y0, min(box[1], fy0 - 2))
        x1, y1 = min(x1, max(box[2], fx1 + 2)), min(y1, max(box[3], fy1 + 2))
    bw_, bh_ = x1 - x0, y1 - y0
    f = _reduction(bw_, bh_, narrow, p)
    offset = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    m = np.vstack([a_to_b, [0.0, 0.0, 1.0]]) @ offset
    bw = cv2.warpAffine(b, m[:2], (bw_, bh_), flags=cv2.INTER_LINEAR | flags, borderMode=cv2.BORDER_CONSTANT)
    mb = cv2.warpAffine(b_valid.view(np.uint8), m[:2], (bw_, bh_), flags=cv2.INTER_NEAREST | flags,
                        borderMode=cv2.BORDER_CONSTANT)
    ab, ma = _crop(a, x0, y0, x1, y1), _crop(a_valid.view(np.uint8), x0, y0, x1, y1)
    # Only pixels that a shift within the radius can bring over the other frame take part:
    # the rest of the box would only add noise to the surface (a thin strip's peak drowned).
    ma, mb = ma & _grown(mb, radius), mb & _grown(ma, radius)
    if f > 1:
        size = (bw_ // f, bh_ // f)
        ab = cv2.resize(ab[: size[1] * f, : size[0] * f], size, interpolation=cv2.INTER_AREA)
        bw = cv2.resize(bw[: size[1] * f, : size[0] * f], size, interpolation=cv2.INTER_AREA)
        # A reduced pixel is valid when its whole footprint is.
        ma = cv2.resize(ma[: size[1] * f, : size[0] * f].astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999
        mb = cv2.resize(mb[: size[1] * f, : size[0] * f].astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999
    else:
        ma, mb = ma > 0, mb > 0
    min_n = max(p.min_overlap_px // (f * f), 16)
    if np.count_nonzero(ma) < min_n or np.count_nonzero(mb) < min_n:
        return "small overlap: too few valid pixels in the search box"
    # (the taper never eats more than a quarter of the box or of the predicted overlap)
    taper = min(p.taper_px, min(ab.shape) / 4.0, (narrow / f) / 4.0 if narrow > 0 else np.inf)
    h, w = ab.shape
    # Zero padding by the radius: a shift within it never wraps content around (a wrapped
    # correlation would lower every peak but the prior's, and hide a repeating texture).
    # At most by the box's side: two images within the box correlate over fewer than twice
    # its side of shifts, so a box padded by its side never wraps whatever the radius.
    pad = int(np.ceil(radius / f)) + 1
    hp, wp = cv2.getOptimalDFTSize(h + min(pad, h)), cv2.getOptimalDFTSize(w + min(pad, w))
    pa, pb, wa, wb = (np.zeros((hp, wp), np.float32) for _ in range(4))
    pa[:h, :w], wa[:h, :w] = _prepared(ab.astype(np.float32, copy=False), ma, taper)
    pb[:h, :w], wb[:h, :w] = _prepared(bw.astype(np.float32, copy=False), mb, taper)
    if not pa.any() or not pb.any():
        return "no texture: the search box is flat"
    r = _phase_surface(pa, pb, p.smoothing_px, p.whitening_floor)
    # Candidates: shifts within the search radius. The peak of r is at s with
    # a(x) = bw(x - s), so our shift is d = -s; a circular surface cannot tell s from
    # s - size, so each position stands for up to four shifts (aliases): the reachable
    # positions are those with an alias within the radius. Of the highest peaks there, the
    # first whose alias leaves enough overlap is the answer (among several aliases, the
    # band-passed NCC over the actual overlap decides).
    reach = radius / f + 1.0
    wy = np.minimum(np.arange(hp), hp - np.arange(hp)).astype(np.float32)
    wx = np.minimum(np.arange(wp), wp - np.arange(wp)).astype(np.float32)
    reachable = wy[:, None] ** 2 + wx[None, :] ** 2 <= reach * reach
    # For the uniqueness, peaks are compared as correlations: each divided by the overlap
    # weight its shift brings together (the surface is lower where less overlaps: a
    # periodic texture's peaks one period apart are then equal; by at most 2: below half the
    # largest weight that would raise noise as much as a match).
    # (Within a radius under a tenth of the box's shorter side the weight varies by less
    # than a fifth: it is left out, saving three transforms.)
    # (The weights are relative to the prior's shift, where the two boxes, built about the
    # predicted overlap, bring the most together; or, where they do not meet there (a
    # corner just out of reach of the prior), to the highest peak's.)
    w0 = 0.0
    if reach >= 0.1 * min(h, w):
        w0 = _weight_at(wa, wb, 0, 0)
        if w0 <= 0:
            top = np.unravel_index(int(np.argmax(np.where(reachable, r, -np.inf))), r.shape)
            w0 = _weight_at(wa, wb, int(top[0]), int(top[1]))
        if w0 <= 0:
            return "small overlap: the frames' valid parts never meet within the search radius"

    def as_correlation(y: int, x: int) -> float:
        v = float(r[y, x])
        return v if w0 <= 0 else v / max(_weight_at(wa, wb, y, x) / w0, 0.5)

    # The peaks are ranked on the surface itself (their significance: dividing by a small
    # overlap weight would raise noise as much as a match); only the uniqueness compares
    # them as correlations.
    rr = np.where(reachable, r, np.float32(-np.inf)).astype(np.float32)
    fa, fb = ma.astype(np.float32), mb.astype(np.float32)
    band: list[np.ndarray] = []

    def aliases(py: int, px: int) -> list[tuple[int, int, int]]:
        out = []
        for sy in {py, py - hp}:
            for sx in {px, px - wp}:
                dx, dy = -sx, -sy
                if np.hypot(dx, dy) <= reach:
                    n = _overlap_count(fa, fb, dx, dy, min_n)
                    if n >= min_n:
                        out.append((dx, dy, n))
        return out

    excl = max(p.exclusion_px / f, 1.5)
    # The highest peak with enough overlap, and those that reach NCC_PEAK_FRACTION of it.
    scored: list[tuple[int, int, list[tuple[int, int, int]]]] = []
    for py, px in _peaks(rr, p.peaks, int(np.ceil(excl))):
        if not np.isfinite(rr[py, px]):
            break
        if scored and rr[py, px] < NCC_PEAK_FRACTION * rr[scored[0][0], scored[0][1]]:
            break
        found = aliases(py, px)
        if found:
            scored.append((py, px, found))
    if not scored:
        return "small overlap: no shift within the search radius leaves enough overlap"
    ncc = float("nan")
    ncc_uniq = 1.0
    if len(scored) > 1 or len(scored[0][2]) > 1:
        band += [_band_pass(ab, fa), _band_pass(bw, fb)]
        # every alias of every peak by its band-passed NCC over its own overlap; then, from
        # the highest peak down, a lower one wins only by NCC_PEAK_MARGIN, compared over the
        # pixels of a both shifts cover where there are enough (an NCC over another overlap
        # is another statistic: a wrong shift whose overlap holds more of the tissue and
        # less of the background would win on its own), else over their own overlaps
        q = [[(_ncc_at(band[0], fa, band[1], fb, c[0], c[1], min_n)[0], c) for c in found] for _, _, found in scored]
        per_peak = [max(qs, key=lambda t: t[0]) for qs in q]
        k = 0
        for i in range(1, len(per_peak)):
            (qi, ci), (qk, ck) = per_peak[i], per_peak[k]
            common = fa * _shifted(fb, ci[0], ci[1]) * _shifted(fb, ck[0], ck[1])
            if float(common.sum()) >= min_n:
                qi = _ncc_at(band[0], common, band[1], fb, ci[0], ci[1], min_n)[0]
                qk = _ncc_at(band[0], common, band[1], fb, ck[0], ck[1], min_n)[0]
            if qi > qk + NCC_PEAK_MARGIN:
                k = i
        others = [t[0] for i, t in enumerate(per_peak) if i != k]
        if per_peak[k][0] <= 0:
            ncc_uniq = 0.0  # (no NCC speaks for an answer that does not correlate)
        elif others:
            ncc_uniq = float(np.clip(1.0 - max(max(others), 0.0) / per_peak[k][0], 0.0, 1.0))
        # (the NCC speaks for the answer only when it sets it apart from the other peaks:
        # on smooth structure, tissue or a blurred edge, shifts a few pixels apart all
        # reach 0.6-0.9)
        if ncc_uniq >= NCC_DECISIVE:
            ncc = per_peak[k][0]
        py, px = scored[k][:2]
        choice = per_peak[k][1]
    else:
        k = 0
        py, px = scored[0][:2]
        choice = scored[0][2][0]
    sub_yx = _subpixel(r, py, px)
    c1, (bx, by, n1), sub = as_correlation(py, px), choice, (-sub_yx[1], -sub_yx[0])
    # C2: the highest local maximum of the reachable surface outside the exclusion disc
    # around C1 (a slope rising out of the radius included; a broad peak's own shoulder is
    # no competitor), both as correlations (divided by their overlap weight); uniqueness
    # 1 - C2 / C1. Phase correlation weighs every frequency alike, and the many weak ones
    # (edge leakage) align best where the two boxes coincide, i.e. at the prior's shift:
    # that would hide a repeating texture's twin peak or a ridge (stripes). So where the
    # NCC of the two band-passed images (shading out; over the same pixels of a for both)
    # has a dip between C1 and C2 (C2 is a peak of its own) or falls along C1 -> C2 much
    # slower than across (a ridge: RIDGE_FALL), the two are compared by that NCC as well,
    # and the lower uniqueness counts (only when C2 reaches NCC_CHECK x C1: a twin or a
    # ridge is never far below the main peak).
    dy_ = np.minimum(np.abs(np.arange(hp) - py), hp - np.abs(np.arange(hp) - py)).astype(np.float32)
    dx_ = np.minimum(np.abs(np.arange(wp) - px), wp - np.abs(np.arange(wp) - px)).astype(np.float32)
    near = dy_[:, None] ** 2 + dx_[None, :] ** 2 <= excl * excl
    # (local maxima: a 3 x 3 dilation; -inf outside the radius, so only positions within it
    # can be maxima; when the radius is small only the surface's four corners hold them)
    ry, rx = min(int(reach) + 2, hp // 2), min(int(reach) + 2, wp // 2)
    rc = np.roll(rr, (ry, rx), axis=(0, 1))[: 2 * ry + 1, : 2 * rx + 1]
    lc = rc >= cv2.dilate(rc, np.ones((3, 3), np.uint8), borderValue=float(-np.inf))
    local = np.zeros(rr.shape, bool)
    local[: 2 * ry + 1, : 2 * rx + 1] = lc
    local = np.roll(local, (-ry, -rx), axis=(0, 1))
    # C2: the local maxima outside the exclusion disc, highest first, as correlations (a
    # maximum's correlation is at most twice its height: the search stops there)
    cand = np.flatnonzero((local & ~near).ravel() & np.isfinite(rr).ravel())
    cand = cand[np.argsort(-rr.ravel()[cand], kind="stable")]
    c2, second_at = 0.0, None
    for n, j in enumerate(cand.tolist()):
        v = float(rr.flat[j])
        if second_at is not None and ((2.0 if w0 > 0 else 1.0) * v if v > 0 else v) <= c2:
            break
        if n == WEIGHT_EVALUATIONS and w0 > 0:
            # (many maxima of similar height: all of them at once)
            rest = cand[n:]
            ws = _overlap_weight(wa, wb).ravel()[rest]
            qs = rr.ravel()[rest] / np.maximum(ws / w0, 0.5)
            i = int(np.argmax(qs))
            if float(qs[i]) > c2:
                c2, second_at = float(qs[i]), divmod(int(rest[i]), wp)
            break
        y, x = divmod(j, wp)
        q = as_correlation(y, x)
        if second_at is None or q > c2:
            c2, second_at = q, (y, x)
    uniq = float(np.clip(1.0 - max(c2, 0.0) / c1, 0.0, 1.0)) if c1 > 0 else 0.0
    if k > 0:
        # (a lower peak that the NCC chose over the highest: the surface's own C1 - C2 says
        # nothing there; the NCCs of the peaks compared say how unique it is)
        uniq = ncc_uniq
    if second_at is not None and c2 > NCC_CHECK * c1:
        second = aliases(*second_at)
        if second:
            if not band:
                band += [_band_pass(ab, fa), _band_pass(bw, fb)]
            ua, ub = band
            sx, sy = max(second, key=lambda c: c[2])[:2]
            mx, my = int(round((bx + sx) / 2)), int(round((by + sy) / 2))
            # (over the same pixels of a: an NCC over another overlap is another statistic;
            # a wrong shift whose overlap holds more of a strong edge and less of the blank
            # background would beat the match on its own overlap)
            common = fa * _shifted(fb, bx, by) * _shifted(fb, sx, sy) * _shifted(fb, mx, my)
            q1 = _ncc_at(ua, common, ub, fb, bx, by, min_n)[0]
            q2 = _ncc_at(ua, common, ub, fb, sx, sy, min_n)[0]
            mid = _ncc_at(ua, common, ub, fb, mx, my, min_n)[0]
            ex, ey = float(sx - bx), float(sy - by)
            across = _ncc_at(ua, fa, ub, fb, int(round(bx - ey)), int(round(by + ex)), min_n)[0]
            # (a ridge stays high twice as far along: a shoulder of the match's own lobe in
            # an anisotropic texture does not)
            far = _ncc_at(ua, fa, ub, fb, int(round(bx + 2 * ex)), int(round(by + 2 * ey)), min_n)[0]
            ridge = max(q1 - q2, q1 - far) < RIDGE_FALL * (q1 - across)
            if q1 > 0 and q2 > -1.0 and (mid < q2 or ridge):
                uniq = min(uniq, float(np.clip(1.0 - max(q2, 0.0) / q1, 0.0, 1.0)))
    shift = (np.array([bx, by], float) + np.array(sub)) * f
    # Significance against the surface's robust spread (a broad peak of smooth texture
    # would inflate a plain standard deviation).
    med = _median(r)
    sd = 1.4826 * _median(np.abs(r - med))
    z = (float(r[py, px]) - med) / sd if sd > 0 else 0.0
    return CoarseResult(shift, c1, uniq, int(n1 * f * f), f, int(np.count_nonzero(reachable)), z, ncc)
