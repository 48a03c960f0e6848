"""Per-frame quality figures: texture (Kelly (2000)), isotropy (motion blur), exposure, noise.

Pure functions over frames in 8-bit grey levels (0..255) with a validity mask. Exposure is
judged on the raw frame against the clip levels of the log's own data (:class:`ExposureLevels`:
the format's bottom and top codes, or the levels where the log's pixels pile up when it clips
inside them), texture on the rectified frame in working grey levels (after the log's
:class:`pipeline.images.IntensityMap`) against a floor and the frame's own noise
(:func:`noise_sigma`); isolated hot pixels are replaced first (:func:`remove_hot_pixels`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from pipeline.images import IntensityMap


def smoothed_gradients(image: np.ndarray, sigma: float = 1.0, *,
                       work: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Image gradients ``(dI/dx, dI/dy)`` in grey levels per pixel, after a Gaussian of
    ``sigma`` pixels (0 = none) that keeps sensor noise from counting as texture.

    ``work``: three float32 arrays of the image's shape written instead of new ones (the
    smoothed image, then gx and gy in the second and third), e.g. buffers reused across calls."""
    img = image.astype(np.float32, copy=False)
    if sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigma, dst=None if work is None else work[0])
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0, dst=None if work is None else work[1])
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0, dst=None if work is None else work[2])
    return gx, gy


def texture_score_map(image: np.ndarray, window: int = 17, sigma: float = 1.0, *,
                      work: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Kelly's (2000) texture score: local mean of squared gradient magnitude.

    ``I''(p) = 1/w^2 * sum over the w x w window of (dI/dx)^2 + (dI/dy)^2``, in
    (grey levels / pixel)^2, on gradients from :func:`smoothed_gradients`.

    Returns float32 of the image's shape (``work``'s first array when given: see
    :func:`smoothed_gradients`; all three are overwritten).
    """
    gx, gy = smoothed_gradients(image, sigma, work=work)
    return texture_from_gradients(gx, gy, window, out=None if work is None else work[0], in_place=work is not None)


def texture_from_gradients(gx: np.ndarray, gy: np.ndarray, window: int, *, out: np.ndarray | None = None,
                           in_place: bool = False) -> np.ndarray:
    """Kelly's (2000) texture score from gradients: mean of gx^2 + gy^2 over ``window`` x ``window``
    (into ``out`` when given; ``in_place``: ``gx`` may be overwritten)."""
    g2 = cv2.multiply(gx, gx, dst=gx if in_place else None)
    cv2.accumulateSquare(gy, g2)  # OpenCV in place: no temporaries
    return cv2.boxFilter(g2, cv2.CV_32F, (window, window), dst=g2 if out is None else out, normalize=True)


def isotropy_from_gradients(gx: np.ndarray, gy: np.ndarray, weight: np.ndarray) -> float:
    """Isotropy (see :func:`isotropy`) from gradients and a 0/1 float32 pixel weight."""
    gxw = gx * weight
    gyw = gy * weight
    jxx = float(cv2.sumElems(gxw * gx)[0])
    jyy = float(cv2.sumElems(gyw * gy)[0])
    jxy = float(cv2.sumElems(gxw * gy)[0])
    half_trace = 0.5 * (jxx + jyy)
    if half_trace <= 0:
        return 0.0
    root = np.sqrt(0.25 * (jxx - jyy) ** 2 + jxy**2)
    return float((half_trace - root) / (half_trace + root))


def _block_sums(a: np.ndarray, block: int) -> np.ndarray:
    """Sums of ``a`` over ``block`` x ``block`` tiles (the last row and column of tiles may be smaller)."""
    h, w = a.shape
    nh, nw = -(-h // block), -(-w // block)
    if nh * block != h or nw * block != w:
        a = np.pad(a, ((0, nh * block - h), (0, nw * block - w)))
    # (OpenCV's area average times the block's pixels: 0.5 ms per 1024 x 1024 float32
    # frame, relative error 1e-6; numpy's ufunc.reduceat took 2.3 ms)
    return cv2.resize(np.ascontiguousarray(a, np.float32), (nw, nh), interpolation=cv2.INTER_AREA).astype(np.float64) \
        * float(block * block)


def _eigen_ratio(sxx: float, syy: float, sxy: float) -> float:
    """Smaller / larger eigenvalue of the 2 x 2 tensor ``[[sxx, sxy], [sxy, syy]]`` (0 when empty)."""
    half_trace = 0.5 * (sxx + syy)
    if half_trace <= 0:
        return 0.0
    root = np.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)
    return float((half_trace - root) / (half_trace + root))


def _isotropies(gxx: np.ndarray, gyy: np.ndarray, gxy: np.ndarray, weight: np.ndarray | None, textured: np.ndarray,
                block: int, sharp: float = 0.6) -> tuple[float, float, float]:
    """``(frame, block, sharp fraction)`` isotropy from the gradient products (see
    :func:`block_isotropy`); the sharp fraction is the share of the textured pixels that lie
    in blocks whose own isotropy reaches ``sharp`` (1.0 when no block is textured).
    ``weight`` None: the products are weighted already."""
    if weight is not None:
        pxx, pyy, pxy = gxx * weight, gyy * weight, gxy * weight
    else:
        pxx, pyy, pxy = gxx, gyy, gxy
    frame = _eigen_ratio(float(cv2.sumElems(pxx)[0]), float(cv2.sumElems(pyy)[0]), float(cv2.sumElems(pxy)[0]))
    jxx, jyy, jxy = _block_sums(pxx, block), _block_sums(pyy, block), _block_sums(pxy, block)
    nt = _block_sums(textured, block)
    tr = jxx + jyy
    ok = (tr > 0) & (nt > 0)
    if not ok.any():
        return frame, frame, 1.0
    f = nt[ok] / tr[ok]
    blocks = _eigen_ratio(float((jxx[ok] * f).sum()), float((jyy[ok] * f).sum()), float((jxy[ok] * f).sum()))
    half_trace = 0.5 * tr[ok]
    root = np.sqrt(0.25 * (jxx[ok] - jyy[ok]) ** 2 + jxy[ok] ** 2)
    each = (half_trace - root) / (half_trace + root)
    return frame, blocks, float(nt[ok][each >= sharp].sum() / nt[ok].sum())


def block_isotropy(gx: np.ndarray, gy: np.ndarray, weight: np.ndarray, textured: np.ndarray, block: int) -> float:
    """Isotropy (see :func:`isotropy`) of the frame's blocks, each block counted by its texture,
    not its contrast.

    The structure tensor of every ``block`` x ``block`` tile (pixels weighted by ``weight``,
    0/1 float32) is divided by its trace and weighted by the tile's number of ``textured``
    pixels (0/1 float32); the isotropy is that of their sum. Motion blur makes every tile
    anisotropic the same way, so a uniformly textured frame reads as with :func:`isotropy`
    (a 9-pixel blur 0.33-0.37, 5 pixels 0.55-0.59, a sharp floor 0.9-1.0); a strong edge of
    the scene (the border of a tissue section, a painted line) no longer outweighs the rest
    of the frame, only its own tiles. No textured tile: :func:`isotropy_from_gradients`.
    """
    return _isotropies(gx * gx, gy * gy, gx * gy, weight, textured, block)[1]


def isotropy(image: np.ndarray, valid: np.ndarray, sigma: float = 1.0) -> float:
    """How evenly a frame's texture is spread over directions, in [0, 1].

    The ratio of the smaller to the larger eigenvalue of the frame's mean structure tensor
    (gradients from :func:`smoothed_gradients` over the valid pixels). Motion blur removes
    gradient energy along the motion and drives it towards 0; so does one-directional
    texture (brushed or striped floors), which constrains a match in one direction only.
    Robust to sensor noise (noise sigma 5 grey levels moves it by < 0.01), unlike
    reference-free blur measures that read noise as detail.
    """
    gx, gy = smoothed_gradients(image, sigma)
    weight = (cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0).astype(np.float32)
    return isotropy_from_gradients(gx, gy, weight)


# Immerkaer's noise operator: the difference of two Laplacians, blind to planes and to most
# of an image's smooth structure; white noise of sigma s gives responses of sigma 6 s.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_MAD_TO_SIGMA = 1.4826
# Pure white noise of sigma s has a texture score (window 17, smoothing sigma 1) of about
# 0.041 s^2 on average, at most ~0.07 s^2 over a 512 x 512 frame (measured).
NOISE_TEXTURE_PER_SIGMA2 = 0.041


def noise_sigma(image: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Robust sensor noise sigma of one frame, in the image's units (grey levels).

    1.4826 x the median absolute response of Immerkaer's 3 x 3 noise operator, / 6 (its
    gain on white noise), over the pixels whose 3 x 3 neighbourhood lies inside ``mask``
    (bool, image shape; None = the whole frame but its border). Texture raises it little
    (the median ignores edges and fine structure covering less than half the frame); a
    resampled (smoothed) frame reads lower than its raw frame's noise.
    """
    img = np.ascontiguousarray(image, np.float32)
    r = cv2.filter2D(img, cv2.CV_32F, _NOISE_KERNEL, borderType=cv2.BORDER_REFLECT_101)
    # The median over a regular lattice of at most ~2^15 pixels: plenty for one figure.
    step = max(1, int(np.ceil(np.sqrt(img.size / 2**15))))
    if mask is None:
        sel = r[1:-1:step, 1:-1:step]
    else:
        inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0) > 0
        sel = r[::step, ::step][inner[::step, ::step]]
    if sel.size == 0:
        return 0.0
    return float(_MAD_TO_SIGMA * np.median(np.abs(sel)) / 6.0)


_RING = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]


def _reflect(i: np.ndarray, n: int) -> np.ndarray:
    """Indices reflected into ``0..n-1`` as ``cv2.BORDER_REFLECT_101`` does (one pixel beyond)."""
    return np.abs(np.where(i >= n, 2 * (n - 1) - i, i))


def remove_hot_pixels(image: np.ndarray, sigmas: float, floor: float) -> tuple[np.ndarray, int]:
    """Replace isolated hot (or dead) pixels by their 3 x 3 median.

    A pixel is one when it differs from its 3 x 3 median, and from the most extreme of its 8
    neighbours on that side, by more than ``sigmas`` x the neighbours' spread (1.4826 x their
    median absolute deviation, at least ``floor`` grey levels: e.g. the frame's noise sigma or
    one code); an adjacent pair of such pixels (each beyond all its other neighbours) counts
    too. So: single pixels and pairs far outside their surroundings (a stuck pixel, a cosmic
    ray, a pixel at 65535 in a 16-bit frame near 1000 counts), never an edge, a corner, a line
    (or its end) or a blob of real signal, whose pixels have like neighbours, nor a bright
    speck in busy texture (its neighbours spread).

    Returns the cleaned image (``image`` itself when nothing was found) and the count.
    """
    img = np.ascontiguousarray(image, np.float32)
    med = cv2.medianBlur(img, 3)
    # (OpenCV's absdiff and compare: 1.5 ms a 1024 x 1024 frame where numpy's abs, compare
    # and flatnonzero took 5.4; most frames have no candidate at all)
    over = cv2.compare(cv2.absdiff(img, med), float(sigmas * floor), cv2.CMP_GT)
    if cv2.countNonZero(over) == 0:
        return image, 0
    cand = np.flatnonzero(over)
    h, w = img.shape
    pad = cv2.copyMakeBorder(img, 1, 1, 1, 1, cv2.BORDER_REFLECT_101)
    ys, xs = np.divmod(cand, w)
    nb = np.stack([pad[ys + 1 + dy, xs + 1 + dx] for dy, dx in _RING], axis=1)
    srt = np.sort(nb, axis=1)
    centre = 0.5 * (srt[:, 3] + srt[:, 4])
    spread = _MAD_TO_SIGMA * np.median(np.abs(srt - centre[:, None]), axis=1)
    t = sigmas * np.maximum(spread, floor)
    v = img.ravel()[cand]
    bad = np.zeros(cand.size, bool)
    for sign, first, second, arg in ((1.0, srt[:, -1], srt[:, -2], np.argmax), (-1.0, srt[:, 0], srt[:, 1], np.argmin)):
        single = sign * (v - first) > t
        pair = ~single & (sign * (v - second) > t)
        if pair.any():  # a pair only when the partner (the most extreme neighbour) is a pair pixel too
            k = arg(nb[pair], axis=1)
            dy = np.array([d[0] for d in _RING])[k]
            dx = np.array([d[1] for d in _RING])[k]
            partner = _reflect(ys[pair] + dy, h) * w + _reflect(xs[pair] + dx, w)
            pair[pair] = np.isin(partner, cand[pair])
        bad |= single | pair
    bad = cand[bad]
    if bad.size == 0:
        return image, 0
    out = img.copy()
    out.ravel()[bad] = med.ravel()[bad]
    return out, int(bad.size)


# A log's extreme value counts as a clip level ("pile-up") when at least [ingest.quality]
# pileup_min_fraction of its sampled pixels sit on it and it holds this many times more
# pixels than the mean code of the 8 codes next to it.
PILEUP_RATIO = 4.0
_PILEUP_WINDOW = 8


def _pileup(values: np.ndarray, top: bool, code_step: float, min_fraction: float) -> float | None:
    """The extreme value of ``values`` when the data pile up on it (see :data:`PILEUP_RATIO`), else None."""
    ext = float(values.max() if top else values.min())
    half = 0.5 * code_step
    d = (ext - values) if top else (values - ext)
    at = int(np.count_nonzero(d <= half))
    near = int(np.count_nonzero((d > half) & (d <= (_PILEUP_WINDOW + 0.5) * code_step))) / _PILEUP_WINDOW
    if at >= min_fraction * values.size and at >= PILEUP_RATIO * max(near, 1.0):
        return ext
    return None


@dataclass(frozen=True)
class ExposureLevels:
    """Where a log's raw pixels clip, in grey levels of full scale (0..255).

    ``dark``: the format's bottom code (0), or the level the log's pixels pile up at when it
    clips above it (a camera's black clip, video-range data); ``saturated``: the top code
    (255), or the pile-up level when the data clip below it (12-bit data in 16-bit files).
    A raw pixel within ``margin_codes`` codes (of ``code_step`` grey levels) of a level counts
    as clipped there. ``*_source``: "bottom code" / "top code" or "pile-up".
    """

    dark: float = 0.0
    saturated: float = 255.0
    code_step: float = 1.0
    margin_codes: float = 2.0
    dark_source: str = "bottom code"
    saturated_source: str = "top code"

    def fractions(self, raw: np.ndarray) -> tuple[float, float]:
        """``(saturated, dark)`` fractions of the raw pixels ``raw`` (any shape)."""
        n = max(raw.size, 1)
        m = (self.margin_codes + 0.5) * self.code_step
        sat = float(np.count_nonzero(raw >= self.saturated - m)) / n
        dark = float(np.count_nonzero(raw <= self.dark + m)) / n
        return sat, dark

    def describe(self) -> dict:
        """For the manifest: levels in grey levels and in codes, and where they come from."""
        return {"dark_level": self.dark, "dark_counts": self.dark / self.code_step, "dark_source": self.dark_source,
                "saturated_level": self.saturated, "saturated_counts": self.saturated / self.code_step,
                "saturated_source": self.saturated_source, "code_step": self.code_step,
                "margin_codes": self.margin_codes}


def exposure_levels(values: np.ndarray, code_step: float, q: dict) -> ExposureLevels:
    """A log's :class:`ExposureLevels` from a sample of its raw pixels (grey levels of full
    scale, hot pixels removed), ``q`` the ``[ingest.quality]`` table."""
    values = np.asarray(values, np.float32).ravel()
    kw: dict = {"code_step": float(code_step), "margin_codes": float(q["clip_margin_codes"])}
    # Data spanning only a few codes (a uniform scene) have no clip level of their own.
    if values.size and float(values.max() - values.min()) > 2 * (_PILEUP_WINDOW + 1) * code_step:
        hi = _pileup(values, True, code_step, q["pileup_min_fraction"])
        lo = _pileup(values, False, code_step, q["pileup_min_fraction"])
        m = (q["clip_margin_codes"] + 0.5) * code_step
        if hi is not None and hi < 255.0 - m:
            kw.update(saturated=hi, saturated_source="pile-up")
        if lo is not None and lo > m:
            kw.update(dark=lo, dark_source="pile-up")
    return ExposureLevels(**kw)


@dataclass(frozen=True)
class CleanedRaw:
    """A raw frame with its hot pixels replaced (:func:`clean_raw`): the pixels (grey levels
    of full scale), the frame's noise sigma (grey levels of full scale, measured before the
    replacement) and the count of pixels replaced."""

    pixels: np.ndarray
    noise_sigma: float
    hot_pixels: int


def clean_raw(raw: np.ndarray, hot_pixel_sigmas: float, code_step: float,
              mask: np.ndarray | None = None) -> CleanedRaw:
    """A raw frame's noise (:func:`noise_sigma` over ``mask``) and its hot pixels replaced
    (:func:`remove_hot_pixels` at ``hot_pixel_sigmas`` x the noise, at least one code of
    ``code_step`` grey levels; ``hot_pixel_sigmas`` 0: none)."""
    sigma = noise_sigma(raw, mask)
    pixels, hot = raw, 0
    if hot_pixel_sigmas > 0:
        pixels, hot = remove_hot_pixels(raw, hot_pixel_sigmas, max(sigma, code_step))
    return CleanedRaw(pixels, sigma, hot)


@dataclass(frozen=True)
class RawFigures:
    """A raw frame after :meth:`FrameAssessor.clean`: the cleaned pixels (grey levels of full
    scale), its noise sigma (grey levels of full scale), the hot pixels replaced (count), and
    its exposure figures over the assessed raw pixels (fractions; mean in grey levels)."""

    pixels: np.ndarray
    noise_sigma: float
    hot_pixels: int
    saturated_fraction: float
    dark_fraction: float
    mean_level: float


@dataclass(frozen=True)
class FrameQuality:
    """Quality figures of one frame, the reason it was rejected, and why it is not registrable.

    Attributes:
        texture_median: median texture score over valid pixels, (working grey levels / pixel)^2.
        textured_fraction: fraction of valid pixels whose texture score reaches the threshold.
        isotropy: in [0, 1], the larger of :func:`isotropy_from_gradients` (the frame's) and
            :func:`block_isotropy`; low for motion blur or one-directional texture.
        mean_level: mean raw grey level (0..255 of the file's full scale, hot pixels removed).
        saturated_fraction, dark_fraction: raw pixels clipped at the log's levels (:class:`ExposureLevels`).
        reason: why the frame is rejected (not stored), None if it is stored.
        noise_sigma: the raw frame's noise sigma in working grey levels (:func:`noise_sigma`).
        hot_pixels: hot (or dead) pixels replaced (count, :func:`remove_hot_pixels`).
        prior_reason: why a stored frame is not registrable (too little texture, or a partly
            textured frame whose texture runs one way: it is placed by its prior pose), None if
            it is registrable.
    """

    texture_median: float
    textured_fraction: float
    isotropy: float
    mean_level: float
    saturated_fraction: float
    dark_fraction: float
    reason: str | None
    noise_sigma: float = 0.0
    hot_pixels: int = 0
    prior_reason: str | None = None

    @property
    def registrable(self) -> bool:
        """Stored and registrable (no :attr:`reason`, no :attr:`prior_reason`)."""
        return self.reason is None and self.prior_reason is None

    @property
    def gate(self) -> str | None:
        """The gate that rejected or flagged the frame ("overexposed", "underexposed",
        "low texture", "one-directional texture", "blurred or one-directional texture"),
        None if it passed them all."""
        r = self.reason or self.prior_reason
        return None if r is None else r.split(":")[0]


# Gates that keep a frame, flagged not registrable (the others reject it).
PRIOR_GATES = ("low texture", "one-directional texture")
# [ingest.quality] knobs to change when a gate rejects or flags most of a log.
GATE_KNOBS = {
    "overexposed": "max_saturated_fraction (or clip_margin_codes)",
    "underexposed": "max_dark_fraction (or clip_margin_codes)",
    "low texture": "min_textured_fraction, min_local_texture or noise_texture_factor",
    "one-directional texture": "min_isotropy",
    "blurred or one-directional texture": "min_isotropy (or isotropy_min_textured_fraction, blur_max_sharp_fraction)",
}


class FrameAssessor:
    """Quality of frames sharing one valid mask; ``q`` is the ``[ingest.quality]`` table.

    ``levels``: the log's clip levels (:func:`exposure_levels`); ``intensity``: the log's
    normalization (rectified frames are assessed after it; noise is converted to working grey
    levels with it); ``raw_mask``: the raw pixels assessed for exposure and noise (bool raw
    ``(H, W)``, e.g. an omni camera's floor annulus; None = all).

    Per frame, :meth:`clean` (raw: noise, hot pixels, exposure) and then ``self(raw, rectified)``
    (rectified, in working grey levels: texture, isotropy, and the verdict), gates in order:

    1. exposure (``max_saturated_fraction``, ``max_dark_fraction``): rejected;
    2. texture (fewer than ``min_textured_fraction`` of the pixels reach
       :meth:`texture_threshold`): kept, not registrable (placed by its prior);
    3. isotropy below ``min_isotropy``: rejected as blurred when at least
       ``isotropy_min_textured_fraction`` of the frame is textured (motion blur leaves a floor
       textured) and less than ``blur_max_sharp_fraction`` of its texture lies in blocks of
       isotropy ``isotropy_sharp_block`` or more (blur leaves no block sharp; a band of
       striped floor leaves the rest sharp: such a frame is registrable); a partly textured
       frame whose texture runs one way is an edge or a band of the scene (a tissue
       section's border), not blur: kept, not registrable.

    Texture and isotropy use the rectified frame's valid pixels (the masks are prepared once).
    """

    def __init__(self, valid: np.ndarray, q: dict, *, levels: ExposureLevels | None = None,
                 intensity: IntensityMap | None = None, raw_mask: np.ndarray | None = None):
        self.q = q
        self.levels = levels if levels is not None else ExposureLevels(margin_codes=float(q["clip_margin_codes"]))
        # Noise in working grey levels = |gain| x raw noise (the map is linear).
        self.noise_gain = 1.0 if intensity is None else abs(float(intensity.gain))
        self.raw_mask = raw_mask
        v8 = valid.astype(np.uint8)
        # The isotropy's pixels: as calibrated (min_isotropy, and the example configs' values),
        # they include the gradients of the frame's own edge (0 outside ``valid``).
        self.iso_weight = (cv2.erode(v8, np.ones((3, 3), np.uint8)) > 0).astype(np.float32)
        # Texture is scored only where the whole window lies on gradients out of reach of an
        # invalid pixel (the Gaussian's 4 sigma, Sobel's 1): the frame's edge is not texture.
        reach = int(np.ceil(4.0 * q["texture_smoothing_sigma_px"])) + 1
        w = q["texture_window_px"]
        inner = cv2.erode(v8, np.ones((w + 2 * reach, w + 2 * reach), np.uint8), borderValue=0) > 0
        self.texture_mask = inner if inner.any() else valid.astype(bool)
        # Precomputed for each frame: the flat indices of the pixels the isotropy weighs 0
        # (the products are zeroed there in place, not multiplied by the weight: 7 ms a
        # 1024 x 1024 frame), the texture pixels' count, and the flat indices of every 7th
        # of them (the texture median's sample), so that no frame pays a boolean selection.
        self._iso_zero = np.flatnonzero(self.iso_weight.ravel() == 0)
        self._texture_count = int(np.count_nonzero(self.texture_mask))
        self._median_sample = np.flatnonzero(self.texture_mask.ravel())[::7]

    def clean(self, raw: np.ndarray) -> RawFigures:
        """Noise, hot pixel removal and exposure of a raw frame (grey levels of full scale)."""
        c = clean_raw(raw, float(self.q["hot_pixel_sigmas"]), self.levels.code_step, self.raw_mask)
        pixels, sigma, hot = c.pixels, c.noise_sigma, c.hot_pixels
        sel = pixels if self.raw_mask is None else pixels[self.raw_mask]
        sat, dark = self.levels.fractions(sel)
        return RawFigures(pixels, sigma, hot, sat, dark, float(sel.mean()) if sel.size else 0.0)

    def texture_threshold(self, noise_working: float) -> float:
        """Texture score a pixel needs to count as textured, (working grey levels / pixel)^2:
        ``max(min_local_texture, noise_texture_factor x noise^2)``."""
        return max(float(self.q["min_local_texture"]), float(self.q["noise_texture_factor"]) * noise_working**2)

    def __call__(self, raw: RawFigures | np.ndarray, rectified: np.ndarray) -> FrameQuality:
        """The verdict on a frame: ``raw`` from :meth:`clean` (or a raw frame, cleaned here),
        ``rectified`` in working grey levels."""
        q = self.q
        fig = raw if isinstance(raw, RawFigures) else self.clean(raw)
        saturated, dark = fig.saturated_fraction, fig.dark_fraction
        noise = self.noise_gain * fig.noise_sigma
        thr = self.texture_threshold(noise)
        gx, gy = smoothed_gradients(rectified, q["texture_smoothing_sigma_px"])
        gxx, gyy, gxy = gx * gx, gy * gy, gx * gy
        w = q["texture_window_px"]
        score = cv2.boxFilter(gxx + gyy, cv2.CV_32F, (w, w), normalize=True)  # texture_from_gradients
        tex_px = cv2.bitwise_and((score >= thr).view(np.uint8), self.texture_mask.view(np.uint8))
        textured = float(cv2.countNonZero(tex_px)) / max(self._texture_count, 1)
        for p in (gxx, gyy, gxy):  # weighted by iso_weight (0 or 1) in place: the score has them
            p.ravel()[self._iso_zero] = 0.0
        # Motion blur lowers both; one strong edge of the scene only the frame's, a field of
        # weak one-directional texture around a few strong isotropic features only the blocks'.
        iso_frame, iso_blocks, sharp = _isotropies(gxx, gyy, gxy, None, tex_px.astype(np.float32),
                                                   int(q["isotropy_block_px"]), float(q["isotropy_sharp_block"]))
        iso = max(iso_frame, iso_blocks)
        # Motion blur makes every block anisotropic; a band of one-directional texture of the
        # scene (stripes, a brushed panel) leaves the rest of a textured frame sharp.
        blurred = sharp < q["blur_max_sharp_fraction"]
        reason = prior_reason = None
        lv = self.levels
        if saturated > q["max_saturated_fraction"]:
            reason = (f"overexposed: {saturated:.1%} of pixels saturated (within {lv.margin_codes:g} codes of "
                      f"{lv.saturated / lv.code_step:.0f}, the {lv.saturated_source}; "
                      f"max {q['max_saturated_fraction']:.1%})")
        elif dark > q["max_dark_fraction"]:
            reason = (f"underexposed: {dark:.1%} of pixels black (within {lv.margin_codes:g} codes of "
                      f"{lv.dark / lv.code_step:.0f}, the {lv.dark_source}; max {q['max_dark_fraction']:.1%})")
        elif textured < q["min_textured_fraction"]:
            prior_reason = (
                f"low texture: {textured:.1%} of pixels textured (min {q['min_textured_fraction']:.1%} with score "
                f">= {thr:.3g}: min_local_texture {q['min_local_texture']:g}, noise {noise:.2f} grey levels)"
            )
        elif iso < q["min_isotropy"] and textured >= q["isotropy_min_textured_fraction"] and blurred:
            reason = (f"blurred or one-directional texture: isotropy {iso:.2f} (min {q['min_isotropy']}), "
                      f"{sharp:.0%} of the texture in sharp blocks (min {q['blur_max_sharp_fraction']:.0%})")
        elif iso < q["min_isotropy"] and textured < q["isotropy_min_textured_fraction"]:
            prior_reason = (f"one-directional texture: isotropy {iso:.2f} (min {q['min_isotropy']}) over "
                            f"{textured:.1%} textured pixels (judged as blur from "
                            f"{q['isotropy_min_textured_fraction']:.0%})")
        return FrameQuality(
            # Median over a sparse sample of pixels: plenty for a per-frame figure.
            texture_median=float(np.median(score.ravel()[self._median_sample])) if self._texture_count else 0.0,
            textured_fraction=textured,
            isotropy=iso,
            mean_level=fig.mean_level,
            saturated_fraction=saturated,
            dark_fraction=dark,
            reason=reason,
            noise_sigma=noise,
            hot_pixels=fig.hot_pixels,
            prior_reason=prior_reason,
        )
