"""pipeline.spectrum: OpenCV's packed (CCS) real spectra read through their layout, and
the coarse stage's surfaces computed on them (against the unpacked complex spectra)."""

import cv2
import numpy as np
import pytest

from pipeline.coarse import _overlap_weight, _phase_surface
from pipeline.registration import PreparedFrame
from pipeline.resample import gradients
from pipeline.spectrum import ccs_layout, ccs_lowpass, ccs_magnitudes, clear_caches, full_magnitude_sample

SHAPES = [(8, 10), (9, 10), (8, 9), (9, 15), (1, 6), (2, 2), (135, 225), (180, 300)]


@pytest.mark.parametrize("h,w", SHAPES)
def test_layout_reads_every_entry_of_the_spectrum(h, w):
    a = np.random.default_rng(h * 100 + w).standard_normal((h, w)).astype(np.float32)
    full = np.fft.fft2(a.astype(np.float64))
    lay = ccs_layout(h, w)
    flat = cv2.dft(a).ravel()
    assert 2 * len(lay.re) + len(lay.real) == h * w
    vals = np.concatenate([flat[lay.re] + 1j * flat[lay.im], flat[lay.real] + 0j])
    ref = full[np.rint(lay.fy * h).astype(int) % h, np.rint(lay.fx * w).astype(int) % w]
    assert np.abs(vals - ref).max() <= 1e-6 * np.abs(full).max()
    # every position of the full spectrum (and its conjugate) maps to its magnitude
    yy, xx = np.mgrid[0:h, 0:w]
    mags = ccs_magnitudes(cv2.dft(a), lay)
    pos = lay.half_position(yy.ravel(), xx.ravel())
    assert np.abs(mags[pos] - np.abs(full).ravel()).max() <= 1e-6 * np.abs(full).max()


def test_lowpass_and_median_sample_match_the_unpacked_spectrum():
    h, w = 45, 64
    lp = ccs_lowpass(h, w, 1.5)
    lay = ccs_layout(h, w)
    g = np.exp(-2 * np.pi**2 * 1.5**2 * (np.fft.fftfreq(h)[:, None] ** 2 + np.fft.fftfreq(w)[None, :] ** 2))
    ys, xs = np.rint(lay.fy * h).astype(int) % h, np.rint(lay.fx * w).astype(int) % w
    assert np.allclose(lp, g[ys, xs], atol=1e-6)
    a = np.random.default_rng(3).standard_normal((h, w)).astype(np.float32)
    full = np.abs(np.fft.fft2(a)).ravel()
    step = max(h * w // 100, 1)
    mags = ccs_magnitudes(cv2.dft(a), lay)
    assert np.allclose(mags[full_magnitude_sample(h, w, 100)], full[::step], rtol=1e-5)


def _reference_phase_surface(a, b, sigma, floor):
    fa = np.fft.fft2(a.astype(np.float64))
    fb = np.fft.fft2(b.astype(np.float64))
    cross = fa * np.conj(fb)
    mag = np.abs(cross)
    flat = mag.ravel()
    med = np.median(flat[:: max(len(flat) // 1024, 1)])
    cross /= mag + floor * med + 1e-6 * mag.mean() + 1e-20
    if sigma > 0:
        fy, fx = np.fft.fftfreq(a.shape[0])[:, None], np.fft.fftfreq(a.shape[1])[None, :]
        cross *= np.exp(-2 * np.pi**2 * sigma**2 * (fx**2 + fy**2))
    return np.fft.ifft2(cross).real


@pytest.mark.parametrize("shape", [(96, 400), (75, 81)])
def test_phase_surface_and_overlap_weight_match_complex_spectra(shape):
    rng = np.random.default_rng(7)
    a = rng.standard_normal(shape).astype(np.float32)
    b = np.roll(a, (3, -5), axis=(0, 1)) + 0.3 * rng.standard_normal(shape).astype(np.float32)
    for sigma, floor in ((1.0, 0.1), (0.0, 0.0)):
        r = _phase_surface(a, b, sigma, floor)
        ref = _reference_phase_surface(a, b, sigma, floor)
        assert np.abs(r - ref).max() <= 1e-5 * np.abs(ref).max()
        py, px = np.unravel_index(np.argmax(r), r.shape)
        assert (py, px) == (shape[0] - 3, 5)  # r(d) = sum a(x + d) b(x), b = a moved by (3, -5)
    wa, wb = np.abs(a), np.abs(b)
    ref = np.fft.ifft2(np.fft.fft2(wa.astype(np.float64)) * np.conj(np.fft.fft2(wb.astype(np.float64)))).real
    assert np.abs(_overlap_weight(wa, wb) - ref).max() <= 1e-5 * np.abs(ref).max()


def test_prepared_frame_blocks_match_whole_frame_filtering():
    rng = np.random.default_rng(11)
    img = cv2.GaussianBlur((rng.random((300, 430)) * 255).astype(np.float32), (0, 0), 1.2)
    valid = np.ones(img.shape, bool)
    ref_a = cv2.GaussianBlur(img, (0, 0), 0.7)
    ref_gx, ref_gy = gradients(ref_a)
    f = PreparedFrame(img, valid, 0.7)
    f.ensure(250, 20, 300, 290)  # a strip: only the blocks it touches are computed
    sm, gx, gy = f.partial()
    assert f._done.sum() == 3 * 2  # 3 block rows x 2 block columns (128 px blocks)
    sl = (slice(20, 290), slice(250, 300))
    for got, ref in ((sm, ref_a), (gx, ref_gx), (gy, ref_gy)):
        assert np.abs(got[sl] - ref[sl]).max() <= 1e-3
    assert not f._done[:, 0].any() and not f._done[:, 3].any()  # untouched blocks are not computed
    whole = f.a  # reading the whole computes the rest
    assert f._done.all()
    assert np.abs(whole - ref_a).max() <= 1e-3 and np.abs(f.gx - ref_gx).max() <= 1e-3
    assert np.abs(f.gy - ref_gy).max() <= 1e-3
    assert f.valid_count == img.size


def test_clear_caches_forgets_every_shape_and_the_layouts_come_back_the_same():
    before = ccs_layout(24, 30)
    sample = full_magnitude_sample(24, 30, 100)
    ccs_lowpass(24, 30, 1.5)
    clear_caches()
    assert all(f.cache_info().currsize == 0 for f in (ccs_layout, ccs_lowpass, full_magnitude_sample))
    again = ccs_layout(24, 30)
    assert again is not before
    np.testing.assert_array_equal(again.re, before.re)
    np.testing.assert_array_equal(full_magnitude_sample(24, 30, 100), sample)
