"""Real 2-D spectra in OpenCV's packed CCS layout, worked on without unpacking.

``cv2.dft`` of a real image with ``DFT_COMPLEX_OUTPUT`` returns the full (h, w, 2)
spectrum, half of it the conjugate of the other half; without it the spectrum comes packed
(CCS: the non-redundant half in an (h, w) real array), six times faster on the coarse
stage's boxes (1.8 ms instead of 11.6 ms for a cross-correlation of two 180 x 1200 boxes on
one core), and ``cv2.mulSpectrums`` and ``cv2.idft(..., DFT_REAL_OUTPUT)`` work on it as
they are. What the coarse stage also needs per frequency (the cross-power spectrum's
magnitude, to whiten it, and a Gaussian low-pass) is done here on the packed array through
index arrays of its layout (:func:`ccs_layout`), cached per shape.

The CCS layout (OpenCV's ``dft`` documentation), for an h x w image: columns ``2k - 1, 2k``
(``1 <= k <= (w - 1) // 2``) hold the real and imaginary parts of ``Y[y, k]`` for every row
y; column 0 (and, for an even w, column w - 1: frequency w / 2) holds that column's own
packed 1-D spectrum down the rows: ``Y[0, c]`` real in row 0, ``Y[j, c]`` in rows
``2j - 1, 2j`` (``1 <= j <= (h - 1) // 2``), and for an even h ``Y[h / 2, c]`` real in row
h - 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ["CCSLayout", "ccs_layout", "ccs_lowpass", "ccs_magnitudes", "ccs_scale", "clear_caches",
           "full_magnitude_sample"]


@dataclass(frozen=True)
class CCSLayout:
    """Index arrays into a flattened (h, w) CCS array.

    Attributes:
        re, im: (K,) flat positions of the real and imaginary parts of its complex entries.
        real: (R,) flat positions of its purely real entries (``2 K + R = h w``).
        fy, fx: (K + R,) the frequencies (cycles per pixel, signed as ``np.fft.fftfreq``)
            of the complex entries, then of the real ones.
    """

    shape: tuple[int, int]
    re: np.ndarray
    im: np.ndarray
    real: np.ndarray
    fy: np.ndarray
    fx: np.ndarray

    def half_position(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Where the full spectrum's entries (y, x) (integer arrays) are found: indices into
        the (K + R,) concatenation of complex then real entries (an entry and its conjugate
        map to the same place)."""
        h, w = self.shape
        y, x = np.asarray(y) % h, np.asarray(x) % w
        mirror = x > w // 2
        y = np.where(mirror, (-y) % h, y)
        x = np.where(mirror, w - x, x)
        n_int = (w - 1) // 2
        special = (x == 0) | ((w % 2 == 0) & (x == w // 2))
        out = np.empty(y.shape, np.int64)
        # interior columns: entry (y, x) is the (y * n_int + x - 1)-th complex entry
        out[~special] = y[~special] * n_int + x[~special] - 1
        # special columns: rows j and h - j are conjugates; 0 and h / 2 are real
        ys, xs = y[special], x[special]
        col = np.where(xs == 0, 0, 1)
        j = np.where(ys > h // 2, h - ys, ys)
        n_pairs = (h - 1) // 2
        is_real = (j == 0) | ((h % 2 == 0) & (j == h // 2))
        k_base = n_int * h
        r_per_col = 2 if h % 2 == 0 else 1
        out_s = np.where(is_real,
                         k_base + self._n_special * n_pairs + col * r_per_col + (j != 0),
                         k_base + col * n_pairs + (j - 1))
        out[special] = out_s
        return out

    @property
    def _n_special(self) -> int:
        return 2 if self.shape[1] % 2 == 0 else 1


@lru_cache(maxsize=64)
def ccs_layout(h: int, w: int) -> CCSLayout:
    """The index arrays of an (h, w) CCS spectrum (cached per shape)."""
    n_int = (w - 1) // 2
    rows = np.arange(h)
    ks = np.arange(1, n_int + 1)
    # interior columns: complex entry (y, k) ordered row by row (as a view of the array's
    # columns 1 .. 2 n_int reshaped to (h, n_int, 2) holds them)
    re = (rows[:, None] * w + (2 * ks - 1)[None, :]).ravel()
    im = re + 1
    fy = np.repeat(np.fft.fftfreq(h), n_int)
    fx = np.tile(ks / w, h)
    specials = [0] + ([w - 1] if w % 2 == 0 else [])
    spec_fx = [0.0] + ([-0.5] if w % 2 == 0 else [])
    n_pairs = (h - 1) // 2
    js = np.arange(1, n_pairs + 1)
    re_s, im_s, fy_s, fx_s = [], [], [], []
    for c, f in zip(specials, spec_fx):
        re_s.append((2 * js - 1) * w + c)
        im_s.append(2 * js * w + c)
        fy_s.append(js / h)
        fx_s.append(np.full(n_pairs, f))
    real, fy_r, fx_r = [], [], []
    for c, f in zip(specials, spec_fx):
        real.append(c)
        fy_r.append(0.0)
        fx_r.append(f)
        if h % 2 == 0:
            real.append((h - 1) * w + c)
            fy_r.append(-0.5)
            fx_r.append(f)
    return CCSLayout(
        (h, w),
        np.concatenate([re, *re_s]).astype(np.intp),
        np.concatenate([im, *im_s]).astype(np.intp),
        np.array(real, np.intp),
        np.concatenate([fy, *fy_s, fy_r]),
        np.concatenate([fx, *fx_s, fx_r]),
    )


def _interior(spec: np.ndarray, layout: CCSLayout) -> np.ndarray:
    """The interior columns' complex entries as an (h, n_int, 2) view of ``spec``."""
    h, w = layout.shape
    n_int = (w - 1) // 2
    return spec[:, 1 : 1 + 2 * n_int].reshape(h, n_int, 2)


def ccs_magnitudes(spec: np.ndarray, layout: CCSLayout) -> np.ndarray:
    """(K + R,) magnitudes of a CCS spectrum's complex entries, then of its real ones."""
    inner = _interior(spec, layout)
    n = inner.shape[0] * inner.shape[1]
    flat = spec.reshape(-1)
    re, im = layout.re[n:], layout.im[n:]
    return np.concatenate([np.hypot(inner[..., 0], inner[..., 1]).ravel(), np.hypot(flat[re], flat[im]),
                           np.abs(flat[layout.real])])


def ccs_scale(spec: np.ndarray, layout: CCSLayout, gain: np.ndarray) -> None:
    """Multiply each entry of a CCS spectrum (in place; C-contiguous float32) by its
    (K + R,) real ``gain`` (complex entries first, as :func:`ccs_magnitudes`)."""
    inner = _interior(spec, layout)
    n = inner.shape[0] * inner.shape[1]
    k = len(layout.re)
    inner *= gain[:n].reshape(inner.shape[0], inner.shape[1], 1)
    flat = spec.reshape(-1)
    flat[layout.re[n:]] *= gain[n:k]
    flat[layout.im[n:]] *= gain[n:k]
    flat[layout.real] *= gain[k:]


@lru_cache(maxsize=64)
def ccs_lowpass(h: int, w: int, sigma: float) -> np.ndarray:
    """A Gaussian of ``sigma`` pixels as the (K + R,) response at the layout's entries."""
    lay = ccs_layout(h, w)
    return np.exp(-2.0 * np.pi**2 * sigma**2 * (lay.fx**2 + lay.fy**2)).astype(np.float32)


@lru_cache(maxsize=64)
def full_magnitude_sample(h: int, w: int, samples: int) -> np.ndarray:
    """Indices into :func:`ccs_magnitudes` of the full (h, w) spectrum's entries at every
    ``max(h w // samples, 1)``-th flat position: the magnitudes an even subsample of the
    unpacked spectrum would give."""
    step = max(h * w // samples, 1)
    flat = np.arange(0, h * w, step)
    return ccs_layout(h, w).half_position(flat // w, flat % w)


def clear_caches() -> None:
    """Forget the layouts and samples cached per spectrum shape (:func:`ccs_layout`,
    :func:`ccs_lowpass`, :func:`full_magnitude_sample`): for a stage done with its
    correlations. Register's pairs search windows of many sizes: a 10 x 10 m floor's
    register left 46 shapes cached, 19 MB of index arrays, then kept under optimize."""
    for f in (ccs_layout, ccs_lowpass, full_magnitude_sample):
        f.cache_clear()
