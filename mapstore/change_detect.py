"""Pixel-level change detection between two co-registered floor images (pure numerics).

Two versions of the same map window, FROM ``a`` and TO ``b`` (uint8 grey levels, 0 = no
data, same grid), are compared so that what a re-render of an unchanged floor brings does
not count as change:

1. **Illumination / exposure** (a smooth gain field). ``b ~ g(x, y) a`` with ``log g`` the
   median of ``log b - log a`` per block of ``gain_block_px``, median-filtered over
   ``gain_window_px`` (larger than the largest change, so that a change cannot pull the
   field: a 1 m^2 repaint is 400 x 400 px at 2.5 mm), lightly smoothed and interpolated
   to the pixels. Everything is compared in FROM's grey-level scale times ``g``.
2. **Sub-pixel misalignment**. Both images are smoothed (Gaussian ``blur_sigma_px``); a
   pixel of TO counts as different only where it lies outside FROM's local envelope: the
   3 x 3 minimum and maximum pulled towards the pixel's own value by ``max_shift_px``
   (a shift by d pixels moves a value by about d times the gradient, and the 3 x 3
   extremes lie one gradient step away), and symmetrically FROM against TO's envelope.
   The residual is the smaller of the two excesses (0 when their signs differ), with the
   sign of TO - FROM.
3. **Threshold** ``max(threshold_sigma x min(noise, max_noise), min_contrast)`` grey
   levels. The noise is the ``noise_block_quantile`` of 1.4826 x MAD of ``TO - g FROM`` per
   gain block, over the pixels the TO version rewrote whose residual averaged over
   ``mean_window_px`` stays under ``min_contrast`` (the changes left out; the low quantile
   and ``max_noise`` guard against what remains of them).
4. **Candidates**: pixels whose residual, or its mean over ``mean_window_px`` (a repainted
   texture fills in), passes the threshold; closed (``close_px``); the band of
   ``edge_band_px`` at each candidate's edge trimmed to the pixels holding at least half
   their neighbourhood's peak (the half-contrast contour, where a soft-edged change's blend
   weight is 0.5); holes up to ``max_hole_px`` filled.
5. **Sharp edges** tell a change from what is left of an exposure difference: the render
   blends frames over tens of pixels, so a gain error fades in over that width, whereas a
   stain, a marking or a repainted patch starts within a few pixels. A candidate is kept
   only when the mean absolute residual on the ring of ``edge_ring_px`` just inside its
   edge exceeds the one just outside (valid pixels) by ``min_edge_step`` x the threshold.
   An exposure difference touching a change joins its candidate. When the change passes
   (its sharp edge dominates), the exposure difference is cut off again as a *part*
   (connected pixels of one sign of the window-mean residual) whose own stretch of edge
   is soft (:func:`_soft_parts`); when the merged candidate fails, its pixels are
   examined again at ``rethreshold_factor`` times the level (up to ``rethreshold_steps``
   times; same bar), where the stronger change stands alone with its sharp edge.
6. Regions smaller than ``min_area_px`` are dropped.

Units: pixels of the map grid (level 0), grey levels of the 0..255 scale, natural-log
gains. No I/O, no pipeline imports: numpy and OpenCV only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

__all__ = [
    "DetectParams",
    "Detection",
    "log_gain_field",
    "envelope_residual",
    "noise_sigma",
    "observed_mask",
    "segment_changes",
    "detect_changes",
]

MAD_TO_SIGMA = 1.4826  # sigma of a normal distribution = 1.4826 x its median absolute deviation


@dataclass(frozen=True)
class DetectParams:
    """Knobs of the detection (``configs/diff.toml`` ``[diff]``, documented there).

    Pixels are level-0 map pixels, contrasts grey levels (0..255 scale).
    """

    valid_erode_px: int = 3
    blur_sigma_px: float = 2.0
    max_shift_px: float = 0.5
    gain_block_px: int = 64
    gain_window_px: int = 1088
    gain_min_valid_fraction: float = 0.25
    gain_smooth_blocks: float = 1.0
    threshold_sigma: float = 5.0
    noise_block_quantile: float = 0.25
    max_noise: float = 3.0
    min_contrast: float = 6.0
    mean_window_px: int = 9
    close_px: int = 4
    edge_band_px: int = 4
    max_hole_px: int = 2000
    edge_ring_px: int = 4
    min_edge_step: float = 1.5
    min_area_px: int = 160
    observed_close_px: int = 2
    part_min_edge_step: float = 1.0
    rethreshold_factor: float = 2.0
    rethreshold_steps: int = 2

    def __post_init__(self) -> None:
        for name in ("gain_block_px", "gain_window_px", "edge_ring_px"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"diff.{name} must be >= 1, got {getattr(self, name)!r}")
        for name in ("valid_erode_px", "mean_window_px", "close_px", "edge_band_px", "max_hole_px", "min_area_px",
                     "observed_close_px", "rethreshold_steps"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"diff.{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("blur_sigma_px", "max_shift_px", "threshold_sigma", "max_noise", "min_contrast", "min_edge_step",
                     "part_min_edge_step", "gain_smooth_blocks"):
            if not float(getattr(self, name)) >= 0.0:
                raise ValueError(f"diff.{name} must be >= 0, got {getattr(self, name)!r}")
        if not float(self.rethreshold_factor) >= 1.0:
            raise ValueError(f"diff.rethreshold_factor must be >= 1, got {self.rethreshold_factor!r}")
        if not 0.0 <= float(self.noise_block_quantile) <= 1.0:
            raise ValueError(f"diff.noise_block_quantile must be in [0, 1], got {self.noise_block_quantile!r}")
        if not 0.0 < float(self.gain_min_valid_fraction) <= 1.0:
            raise ValueError(f"diff.gain_min_valid_fraction must be in (0, 1], got {self.gain_min_valid_fraction!r}")

    @property
    def halo_px(self) -> int:
        """Context a window needs around the pixels it judges (px): half the gain window."""
        return int(self.gain_window_px) // 2


@dataclass
class Detection:
    """What :func:`detect_changes` finds in a window.

    Attributes:
        mask: bool, the changed pixels (after every test).
        residual: float32, TO - g FROM outside the misalignment envelopes (grey levels,
            FROM's scale times the gain; 0 where invalid).
        log_gain: float32, the natural log of the gain field g (TO / FROM).
        valid: bool, both versions have data (eroded by ``valid_erode_px``).
        observed: bool, the judged pixels the TO version rewrote (:func:`observed_mask`).
        noise: robust sigma of ``TO - g FROM`` (grey levels; 0 when nothing qualified; see
            step 3 of the module docstring and :func:`noise_sigma`).
        threshold: the detection threshold used (grey levels).
        candidates: the candidate regions and the edge test's verdict, and the parts cut
            off kept ones (see :func:`segment_changes`); those not kept are smooth
            differences (exposure or illumination left-overs), ignored.
    """

    mask: np.ndarray
    residual: np.ndarray
    log_gain: np.ndarray
    valid: np.ndarray
    observed: np.ndarray
    noise: float
    threshold: float
    candidates: list[dict] = field(default_factory=list)


def _disk(radius: int) -> np.ndarray:
    r = max(int(radius), 0)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _block_nanmedian(x: np.ndarray, valid: np.ndarray, block: int, min_fraction: float) -> np.ndarray:
    """Median of the valid values of each ``block`` x ``block`` block (partial blocks at the
    bottom/right included); NaN for blocks with fewer than ``min_fraction`` valid pixels.
    Every second pixel in each direction is sampled (a median needs no more)."""
    h, w = x.shape
    step = 2 if block >= 8 else 1
    sub = np.where(valid, x, np.float32(np.nan))[::step, ::step]
    bs = block // step
    nr, nc = -(-h // block), -(-w // block)
    pad = np.full((nr * bs, nc * bs), np.nan, np.float32)
    pad[: sub.shape[0], : sub.shape[1]] = sub[: nr * bs, : nc * bs]
    v = np.sort(pad.reshape(nr, bs, nc, bs).swapaxes(1, 2).reshape(nr, nc, bs * bs), axis=-1)  # NaN last
    n = np.count_nonzero(~np.isnan(v), axis=-1)
    lo = np.take_along_axis(v, np.maximum(n - 1, 0)[..., None] // 2, axis=-1)[..., 0]
    hi = np.take_along_axis(v, (n // 2)[..., None], axis=-1)[..., 0]
    out = (0.5 * (lo + hi)).astype(np.float32)
    out[n < min_fraction * bs * bs] = np.nan
    return out


def _nan_median_filter(m: np.ndarray, radius: int) -> np.ndarray:
    """Median of the non-NaN values in each (2r+1)^2 window (NaN where none)."""
    if radius <= 0:
        return m.copy()
    p = np.pad(m, radius, constant_values=np.nan)
    win = sliding_window_view(p, (2 * radius + 1, 2 * radius + 1)).reshape(m.shape[0], m.shape[1], -1)
    v = np.sort(win, axis=-1)
    n = np.count_nonzero(~np.isnan(v), axis=-1)
    lo = np.take_along_axis(v, np.maximum(n - 1, 0)[..., None] // 2, axis=-1)[..., 0]
    hi = np.take_along_axis(v, (n // 2)[..., None], axis=-1)[..., 0]
    return (0.5 * (lo + hi)).astype(np.float32)


def _fill_nan(m: np.ndarray) -> np.ndarray:
    """NaN cells filled from their nearest valid neighbours (repeated 3 x 3 averaging);
    all zeros when nothing is valid."""
    out = m.astype(np.float32, copy=True)
    ok = ~np.isnan(out)
    if not ok.any():
        return np.zeros_like(out)
    while not ok.all():
        num = cv2.blur(np.where(ok, out, 0.0).astype(np.float32), (3, 3), borderType=cv2.BORDER_REPLICATE)
        den = cv2.blur(ok.astype(np.float32), (3, 3), borderType=cv2.BORDER_REPLICATE)
        grow = ~ok & (den > 0)
        out[grow] = num[grow] / den[grow]
        ok = ok | grow
    return out


def log_gain_field(a: np.ndarray, b: np.ndarray, valid: np.ndarray, p: DetectParams) -> np.ndarray:
    """The smooth gain field ``log g = log(TO / FROM)`` per pixel (float32, natural log).

    Args:
        a, b: FROM and TO intensities (grey levels, any float or integer type), same shape.
        valid: bool, pixels where both hold data.
    """
    la = np.log(np.maximum(a.astype(np.float32), 1.0))
    lb = np.log(np.maximum(b.astype(np.float32), 1.0))
    blk = int(p.gain_block_px)
    blocks = _block_nanmedian(lb - la, valid, blk, float(p.gain_min_valid_fraction))
    radius = max(0, int(round(p.gain_window_px / (2.0 * blk))))
    field_ = _fill_nan(_nan_median_filter(blocks, radius))
    if p.gain_smooth_blocks > 0:
        field_ = cv2.GaussianBlur(field_, (0, 0), float(p.gain_smooth_blocks), borderType=cv2.BORDER_REPLICATE)
    h, w = a.shape
    nr, nc = field_.shape
    # cv2.resize by an integer factor puts source cell centres at (i + 0.5) * blk - 0.5: the block centres
    up = cv2.resize(field_, (nc * blk, nr * blk), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(up[:h, :w])


def _envelope(x: np.ndarray, shift: float) -> tuple[np.ndarray, np.ndarray]:
    k = np.ones((3, 3), np.uint8)
    lo = cv2.erode(x, k, borderType=cv2.BORDER_REPLICATE)
    hi = cv2.dilate(x, k, borderType=cv2.BORDER_REPLICATE)
    s = np.float32(min(max(shift, 0.0), 1.0))
    return x + s * (lo - x), x + s * (hi - x)


def envelope_residual(a_f: np.ndarray, b_f: np.ndarray, log_gain: np.ndarray, valid: np.ndarray,
                      max_shift_px: float) -> np.ndarray:
    """TO minus gain-corrected FROM where each lies outside the other's misalignment envelope.

    Args:
        a_f, b_f: smoothed FROM and TO (float32 grey levels).
        log_gain: natural log of the gain field TO / FROM (per pixel).
        valid: bool, where both hold data (0 elsewhere in the result).
        max_shift_px: tolerated misalignment (pixels, 0..1).

    Returns float32 grey levels (FROM's scale times the gain), signed like TO - FROM.
    """
    ag = a_f * np.exp(log_gain).astype(np.float32)
    lo, hi = _envelope(ag, max_shift_px)
    d1 = b_f - np.clip(b_f, lo, hi)
    lo, hi = _envelope(b_f, max_shift_px)
    d2 = np.clip(ag, lo, hi) - ag
    agree = (np.sign(d1) == np.sign(d2)) & valid
    return np.where(agree, np.sign(d1) * np.minimum(np.abs(d1), np.abs(d2)), np.float32(0.0)).astype(np.float32)


def noise_sigma(a_f: np.ndarray, b_f: np.ndarray, log_gain: np.ndarray, where: np.ndarray, block: int,
                quantile: float, min_fraction: float) -> float:
    """Robust noise sigma of ``TO - g FROM`` (grey levels) over the pixels ``where``.

    Per block of ``block`` x ``block`` pixels with at least ``min_fraction`` of them in
    ``where``: 1.4826 x the median absolute deviation; the result is the ``quantile`` of
    these block figures, so that changes covering most of the window (a repainted square
    metre on a small map) cannot inflate it. 0 when no block qualifies.
    """
    if not where.any():
        return 0.0
    d = (b_f - a_f * np.exp(log_gain)).astype(np.float32)
    med = _block_nanmedian(d, where, block, min_fraction)
    h, w = d.shape
    up = np.repeat(np.repeat(np.nan_to_num(med), block, axis=0), block, axis=1)[:h, :w]
    mad = _block_nanmedian(np.abs(d - up), where, block, min_fraction)
    mad = mad[np.isfinite(mad)]
    if not len(mad):
        return 0.0
    return float(MAD_TO_SIGMA * np.quantile(mad, quantile))


def observed_mask(a: np.ndarray, b: np.ndarray, close_px: int) -> np.ndarray:
    """Pixels the TO version rewrote: both hold data and the values differ, closed by
    ``close_px`` (a re-rendered pixel equals the old one by chance now and then; a pixel no
    new frame saw keeps its old value bit for bit)."""
    m = ((a != b) & (a > 0) & (b > 0)).astype(np.uint8)
    if close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(close_px))
    return (m > 0) & (a > 0) & (b > 0)


def _fill_small_holes(mask: np.ndarray, max_hole_px: int) -> np.ndarray:
    """``mask`` with the holes (background components not touching the border, 4-connected)
    of at most ``max_hole_px`` pixels filled."""
    if max_hole_px <= 0 or not mask.any():
        return mask
    inv = (~mask).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
    if n <= 1:
        return mask
    h, w = mask.shape
    x, y, bw, bh, area = stats[:, 0], stats[:, 1], stats[:, 2], stats[:, 3], stats[:, 4]
    inner = (x > 0) & (y > 0) & (x + bw < w) & (y + bh < h) & (area <= max_hole_px)
    inner[0] = False
    return mask | inner[lab]


def _edge_steps(labels: np.ndarray, n: int, absres: np.ndarray, valid: np.ndarray, ring_px: int) -> np.ndarray:
    """Per label 1..n-1: mean |residual| on the ring just inside its edge minus the mean on
    the ring just outside (grey levels), the outer ring counting valid pixels only (an edge
    along the end of the data says nothing about sharpness). Index 0 unused."""
    k = _disk(ring_px)
    inside = labels > 0
    eroded = cv2.erode(inside.astype(np.uint8), k, borderValue=0) > 0
    inner = inside & ~eroded
    grown = cv2.dilate(labels.astype(np.float32), k).astype(np.int32)  # the nearest (largest) label around
    outer = ~inside & (grown > 0) & valid
    s_in = np.bincount(labels[inner], weights=absres[inner], minlength=n)
    c_in = np.bincount(labels[inner], minlength=n)
    s_out = np.bincount(grown[outer], weights=absres[outer], minlength=n)
    c_out = np.bincount(grown[outer], minlength=n)
    m_in = s_in / np.maximum(c_in, 1)
    m_out = np.where(c_out > 0, s_out / np.maximum(c_out, 1), 0.0)
    return m_in, m_out


def _soft_parts(m: np.ndarray, signed: np.ndarray, absres: np.ndarray, valid: np.ndarray, threshold: float,
                p: DetectParams) -> np.ndarray:
    """The parts of the kept candidates ``m`` that reach their edge only through soft edges.

    A part is a connected set of candidate pixels of one sign of ``signed`` (the residual
    averaged over ``mean_window_px``): an exposure difference touching a real change joins
    its candidate, but it has its own sign and its own, soft, edge. Parts holding at least
    ``4 x edge_ring_px`` pixels of the candidate's inner edge ring get the edge test of
    :func:`_edge_steps` on their stretch of the edge; below ``part_min_edge_step`` x the
    threshold (a lower bar than the candidates': the fragments of a repainted texture have
    ragged edges) they are cut off. Parts inside a candidate (the mixed signs of a
    repainted texture) stay.
    """
    pos = m & (signed >= 0)
    n_pos, lab_pos = cv2.connectedComponents(pos.astype(np.uint8), connectivity=8)
    n_neg, lab_neg = cv2.connectedComponents((m & ~pos).astype(np.uint8), connectivity=8)
    parts = np.where(lab_pos > 0, lab_pos, np.where(lab_neg > 0, lab_neg + n_pos - 1, 0)).astype(np.int32)
    n = n_pos + n_neg - 1
    if n <= 2:
        return np.zeros(m.shape, bool)
    k = _disk(p.edge_ring_px)
    inner = m & ~(cv2.erode(m.astype(np.uint8), k, borderValue=0) > 0)
    outer = ~m & valid & (cv2.dilate(m.astype(np.uint8), k) > 0)
    grown = cv2.dilate(parts.astype(np.float32), k).astype(np.int32)
    c_in = np.bincount(parts[inner], minlength=n)
    s_in = np.bincount(parts[inner], weights=absres[inner], minlength=n)
    c_out = np.bincount(grown[outer], minlength=n)
    s_out = np.bincount(grown[outer], weights=absres[outer], minlength=n)
    step = s_in / np.maximum(c_in, 1) - np.where(c_out > 0, s_out / np.maximum(c_out, 1), 0.0)
    soft = (c_in >= 4 * int(p.edge_ring_px)) & (step < float(p.part_min_edge_step) * threshold)
    soft[0] = False
    return soft[parts]


def _bbox(m: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """Slices of the bounding box of ``m``'s True pixels grown by ``margin`` (clipped)."""
    rows = np.flatnonzero(m.any(axis=1))
    if not len(rows):
        return None
    cols = np.flatnonzero(m.any(axis=0))
    h, w = m.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + 1 + margin, h)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + 1 + margin, w)))


def _level_candidates(ar: np.ndarray, arm: np.ndarray, judge: np.ndarray, valid: np.ndarray, level: float,
                      min_step: float, p: DetectParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Candidates at one threshold ``level`` (grey levels): step 4 and the edge test of
    step 5 of the module docstring with the bar ``min_step`` (grey levels). Returns
    ``(labels, stats, step, keep)``: the candidate label image, cv2's component stats, the
    edge steps and the verdicts (per label)."""
    m = (((ar > level) | (arm > level)) & judge).astype(np.uint8)
    if p.close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(p.close_px))
    m = m.astype(bool) & judge
    if p.edge_band_px > 0 and m.any():
        core = cv2.erode(m.astype(np.uint8), _disk(p.edge_band_px), borderValue=0) > 0
        peak = cv2.dilate(arm, _disk(2 * p.edge_band_px + 1))
        m &= core | (arm >= 0.5 * peak)
    m = _fill_small_holes(m, int(p.max_hole_px)) & judge
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m.astype(np.uint8), connectivity=8)
    e_in, e_out = _edge_steps(labels, n, ar, valid, int(p.edge_ring_px))
    step = e_in - e_out
    keep = (stats[:, cv2.CC_STAT_AREA] >= int(p.min_area_px)) & (step >= min_step)
    keep[0] = False
    return labels, stats, step, keep


def segment_changes(residual: np.ndarray, judge: np.ndarray, valid: np.ndarray, threshold: float,
                    p: DetectParams) -> tuple[np.ndarray, list[dict]]:
    """The changed pixels from a residual (steps 4 to 6 of the module docstring).

    Candidates failing the edge test are examined again inside their own pixels at
    ``rethreshold_factor`` times the level, up to ``rethreshold_steps`` times, with the
    same bar for the edge step (sharpness is a step in grey levels whatever the level): a
    stain touching an exposure difference merges with it at the threshold and stands out,
    with its sharp edge, at a higher level.

    Args:
        residual: float32 grey levels (see :func:`envelope_residual`).
        judge: bool, pixels that may be declared changed.
        valid: bool, pixels where both versions hold data (the edge test's context).
        threshold: grey levels.

    Returns ``(mask, candidates)``: the bool mask, and every first-level candidate of at
    least ``min_area_px``: ``{"area_px", "edge_step", "mean_abs", "box", "kept"}`` (grey
    levels: the edge step = mean |residual| inside minus outside; box = (row0, row1, col0,
    col1) in the window; kept = some of it is in the mask; the others are smooth
    differences), then the soft parts cut off kept ones (``{"area_px", "part": True,
    "box", "kept": False}``).
    """
    ar = np.abs(residual).astype(np.float32)
    w = max(int(p.mean_window_px), 1)
    arm = cv2.blur(ar, (w, w), borderType=cv2.BORDER_REFLECT) if w > 1 else ar
    out = np.zeros(ar.shape, bool)
    box = _bbox(((ar > threshold) | (arm > threshold)) & judge,
                int(p.close_px) + 4 * int(p.edge_band_px) + int(p.edge_ring_px) + 4)
    if box is None:
        return out, []
    ar, arm, jd, vd = ar[box], arm[box], judge[box], valid[box]
    signed = cv2.blur(residual[box], (w, w), borderType=cv2.BORDER_REFLECT) if w > 1 else residual[box]
    final = np.zeros(ar.shape, bool)
    first = None
    todo, level = jd, float(threshold)
    for _ in range(int(p.rethreshold_steps) + 1):
        labels, stats, step, keep = _level_candidates(ar, arm, todo, vd, level, float(p.min_edge_step) * threshold, p)
        kept = keep[labels]
        if kept.any():
            final |= kept & ~_soft_parts(kept, signed, ar, vd, threshold, p)
        if first is None:
            first = (labels, stats, step)
        failed = (labels > 0) & ~kept & (stats[:, cv2.CC_STAT_AREA] >= int(p.min_area_px))[labels]
        if not failed.any():
            break
        todo, level = failed, level * float(p.rethreshold_factor)
    final = _fill_small_holes(final, int(p.max_hole_px)) & jd
    labels, stats, step = first
    r0, c0 = int(box[0].start), int(box[1].start)
    area = stats[:, cv2.CC_STAT_AREA]
    level_mean = np.bincount(labels.ravel(), weights=ar.ravel(), minlength=len(area)) / np.maximum(area, 1)
    any_kept = np.bincount(labels[final], minlength=len(area)) > 0
    candidates: list[dict] = []
    for i in np.nonzero(area[1:] >= int(p.min_area_px))[0] + 1:
        x, y, bw, bh = (int(v) for v in stats[i, :4])
        candidates.append({"area_px": int(area[i]), "edge_step": float(step[i]), "mean_abs": float(level_mean[i]),
                           "box": (r0 + y, r0 + y + bh, c0 + x, c0 + x + bw), "kept": bool(any_kept[i])})
    dropped = any_kept[labels] & (labels > 0) & ~final  # cut off candidates that kept something
    if dropped.any():
        _, _, sst, _ = cv2.connectedComponentsWithStats(dropped.astype(np.uint8), connectivity=8)
        for x, y, bw, bh, a in sst[1:]:
            if a >= int(p.min_area_px):
                candidates.append({"area_px": int(a), "part": True, "kept": False,
                                   "box": (r0 + int(y), r0 + int(y + bh), c0 + int(x), c0 + int(x + bw))})
    out[box] = final
    return out, candidates


def detect_changes(a: np.ndarray, b: np.ndarray, p: DetectParams, judge: np.ndarray | None = None) -> Detection:
    """Changed pixels between FROM ``a`` and TO ``b`` (uint8 windows of one grid, 0 = no data).

    Args:
        judge: bool, the pixels whose change is decided (e.g. the changed tiles; the rest of
            the window is context for the gain field). Default: all.

    The whole pipeline of the module docstring; see :class:`Detection`.
    """
    if a.shape != b.shape:
        raise ValueError(f"detect_changes: shapes differ ({a.shape} vs {b.shape})")
    both = ((a > 0) & (b > 0)).astype(np.uint8)
    valid = (cv2.erode(both, _disk(p.valid_erode_px), borderValue=0) if p.valid_erode_px > 0 else both) > 0
    judge = valid if judge is None else (judge & valid)
    a_f = a.astype(np.float32)
    b_f = b.astype(np.float32)
    if p.blur_sigma_px > 0:
        a_f = cv2.GaussianBlur(a_f, (0, 0), float(p.blur_sigma_px))
        b_f = cv2.GaussianBlur(b_f, (0, 0), float(p.blur_sigma_px))
    log_gain = log_gain_field(a_f, b_f, valid, p)
    residual = envelope_residual(a_f, b_f, log_gain, valid, float(p.max_shift_px))
    rewritten = observed_mask(a, b, int(p.observed_close_px)) & judge
    # noise: over rewritten pixels that are no candidate change at the lowest contrast
    w = max(int(p.mean_window_px), 1)
    quiet = cv2.blur(np.abs(residual), (w, w), borderType=cv2.BORDER_REFLECT) <= float(p.min_contrast)
    noise = noise_sigma(a_f, b_f, log_gain, rewritten & quiet, int(p.gain_block_px), float(p.noise_block_quantile),
                        float(p.gain_min_valid_fraction))
    threshold = max(float(p.threshold_sigma) * min(noise, float(p.max_noise)), float(p.min_contrast))
    mask, candidates = segment_changes(residual, judge, valid, threshold, p)
    return Detection(mask, residual, log_gain, valid, rewritten, noise, threshold, candidates)
