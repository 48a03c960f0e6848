"""Pairwise rigid registration of rectified frames, to a small fraction of a pixel.

Why this design (measured in ``bench/bench_register.py``):

1. **Prior warp.** Frame b is resampled into frame a's pixel frame with the prior relative
   pose, so that what is left is a small correction.
2. **Coarse search: normalized cross-correlation** (``cv2.matchTemplate``) of a template
   from a over the prior's uncertainty window in b, on an image pyramid when that window
   is wide. The NCC surface also gives Kelly's (2000) *uniqueness* C1 - C2 (highest peak minus
   the highest competing peak: a local maximum outside the main one, or a slope rising out
   of the window; -1 when there is none, so values run up to 2), the figure that tells a
   real match from texture that repeats. Taking C2 as the surface's maximum outside the
   main peak instead read the main peak's own shoulder on smooth texture (C1 - C2 ~ 0.04 on
   pairs that registered to 0.03 px) and left such frames without any link.
   Phase correlation would be as fast but gives no such figure.
3. **Fine: inverse-compositional Gauss-Newton** on the whole overlap, rigid (x, y, theta)
   about the overlap's centroid (with ``estimate_scale``, for ``[optimize] pose_model =
   "similarity2"``: plus the log of the relative scale, a similarity about the centroid), with a per-pair gain/offset (exposure differs between
   frames) and bicubic resampling. The Jacobian and Hessian come from frame a once, so each
   iteration costs one warp. OpenCV's ECC does the same job but resamples bilinearly,
   which biases sub-pixel shifts by a few hundredths of a pixel on floor texture.
4. **Covariance from the data**: ``sigma^2 H^-1`` with H the Gauss-Newton Hessian and
   sigma^2 the residual variance, carried to the link's pose frame; not a constant.
5. **Feature path** (SIFT + pycolmap's LO-RANSAC) when the prior is too loose for
   correlation (large search radius or heading uncertainty); its estimate seeds steps 2-3.

Pixel frames follow :mod:`mapstore.grid`: (column, row), pose of b in a's frame ``rel``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from mapstore.grid import frame_affine_to_rel, frame_centre, frame_to_frame_affine
from pipeline.coarse import CoarseParams, coarse_shift, mapped_box, reach_fraction
from pipeline.resample import POSITION_STEPS, gradients, masked_blur



@dataclass(frozen=True)
class RegistrationParams:
    """The ``[register]`` knobs used per pair (see configs/floor.toml for meanings)."""

    max_iterations: int = 30
    tolerance_px: float = 1e-3
    mask_margin_px: int = 2
    fine_stride_px: int = 3
    min_overlap_fraction: float = 0.15
    min_overlap_px: int = 2000
    fine_smoothing_px: float = 0.7
    fine_background_px: float = 8.0
    fine_ramp: bool = True
    fine_max_step_px: float = 1.0
    # Acceptance tests that end a pair early (the register stage applies them again with
    # the log's own threshold): the coarse peak's significance and its uniqueness.
    min_peak_z: float = 8.0
    # (or the band-passed NCC of an answer told apart from peaks of its height: a narrow strip)
    min_peak_ncc: float = 0.5
    min_uniqueness: float = 0.2
    min_ncc: float = 0.2
    covariance_inflation: float = 1.0
    feature_rotation_rad: float = 0.05
    feature_ratio: float = 0.8
    feature_max_error_px: float = 2.0
    feature_min_inliers: int = 12
    # Estimate the relative scale of b to a too (a 4th Gauss-Newton parameter, its log);
    # set from ``[optimize] pose_model = "similarity2"``, not from ``[register]``.
    estimate_scale: bool = False
    coarse: CoarseParams = CoarseParams()

    @classmethod
    def from_config(cls, table: dict) -> "RegistrationParams":
        """From the ``[register]`` table, read through its schema (:mod:`pipeline.schema`: every
        key known, typed and in range); the ``coarse_*`` knobs make :class:`CoarseParams`."""
        from pipeline.schema import settings
        from pipeline.schema_floor import RegisterConfig

        r = settings(RegisterConfig, table)
        coarse = CoarseParams(max_pixels=r.coarse_max_pixels, window_px=r.coarse_window_px,
                              min_side_px=r.coarse_min_side_px, peaks=r.coarse_peaks,
                              smoothing_px=r.coarse_smoothing_px, whitening_floor=r.coarse_whitening_floor,
                              taper_px=r.coarse_taper_px, exclusion_px=r.coarse_exclusion_px,
                              min_overlap_px=r.min_overlap_px)
        return cls(max_iterations=r.max_iterations, tolerance_px=r.tolerance_px, mask_margin_px=r.mask_margin_px,
                   fine_stride_px=r.fine_stride_px, min_overlap_fraction=r.min_overlap_fraction,
                   min_overlap_px=r.min_overlap_px, fine_smoothing_px=r.fine_smoothing_px,
                   fine_background_px=r.fine_background_px, fine_ramp=r.fine_ramp, fine_max_step_px=r.fine_max_step_px,
                   min_peak_z=r.min_peak_z, min_peak_ncc=r.min_peak_ncc, min_uniqueness=r.min_uniqueness,
                   min_ncc=r.min_ncc, covariance_inflation=r.covariance_inflation,
                   feature_rotation_rad=r.feature_rotation_rad, feature_ratio=r.feature_ratio,
                   feature_max_error_px=r.feature_max_error_px, feature_min_inliers=r.feature_min_inliers,
                   coarse=coarse)


@dataclass
class PairResult:
    """Outcome of registering frame b to frame a.

    Attributes:
        ok: False when the pair could not be registered; ``reason`` says why.
        rel: (3,) pose of b in a's frame (metres, radians).
        cov: (3, 3) covariance of ``rel`` (m^2, m rad, rad^2).
        ncc: NCC of the aligned overlap after gain/offset correction.
        uniqueness: C1 - C2 of the coarse NCC surface (Kelly (2000); < 0.2 is poor; C2 is the
            highest competing peak, -1 without one).
        overlap: overlap pixels / frame a's valid pixels.
        pixels: pixels used by the fine alignment.
        iterations: Gauss-Newton iterations.
        method: "correlation" or "features"; ``inliers`` for the feature path.
        gain: mean of b over the aligned overlap divided by a's (exposure ratio b/a).
        log_scale: with ``estimate_scale``, the log of b's ground pixel size over a's
            (one pixel of b spans ``exp(log_scale)`` pixels of a); None for a rigid result.
        cov4: with ``estimate_scale``, (4, 4) covariance of ``(rel, log_scale)`` (``cov``
            is its upper-left 3 x 3 block); None otherwise.
    """

    ok: bool
    reason: str = ""
    rel: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    cov: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    ncc: float = float("nan")
    uniqueness: float = float("nan")
    overlap: float = 0.0
    pixels: int = 0
    iterations: int = 0
    method: str = "correlation"
    inliers: int = 0
    gain: float = 1.0
    log_scale: float | None = None
    cov4: np.ndarray | None = None
    peak_z: float = 0.0
    rotation: str = "measured"
    peak_ncc: float = float("nan")


def _affine3(m: np.ndarray) -> np.ndarray:
    return np.vstack([m, [0.0, 0.0, 1.0]])


def _invert(m: np.ndarray) -> np.ndarray:
    return cv2.invertAffineTransform(m)


def _rigid_about(d: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """2x3 affine of a rotation by d[2] (and, with a 4th element, a scaling by exp(d[3]))
    about ``centre`` followed by translation d[:2] (pixels)."""
    c, s = np.cos(d[2]), np.sin(d[2])
    if len(d) > 3:
        k = np.exp(d[3])
        c, s = k * c, k * s
    r = np.array([[c, -s], [s, c]])
    t = centre + d[:2] - r @ centre
    return np.hstack([r, t[:, None]])


# Below this step (pixels), warps switch from OpenCV's 1/32-pixel positions to exact ones.
QUANTIZED_STEP_PX = 0.05


def _warp(img: np.ndarray, a_to_b: np.ndarray, shape: tuple[int, int], flags: int) -> np.ndarray:
    """``out(x) = img(a_to_b x)`` for x over ``shape``."""
    return cv2.warpAffine(img, a_to_b, (shape[1], shape[0]), flags=flags | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT)


def smooth(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian of ``sigma`` pixels (0: the image itself)."""
    return cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0 else img


class PreparedFrame:
    """A frame ready to register: the raw image (coarse search), its smoothed copy and the
    smoothed copy's gradients (fine alignment).

    Prepared once per frame and shared by every pair the frame takes part in: as frame a
    (template side: image and gradients) or as frame b (sampled side).

    Five-tap central differences give the gradients: the 3x3 Sobel attenuates the fine
    texture's gradient, which turns Gauss-Newton's quadratic convergence into a slow
    linear one (16 iterations instead of 4 on simulated concrete).
    """

    # Side of the blocks in which the smoothed frame and its gradients are computed when a
    # pair first needs them: a pair of tiles overlapping by a 30 px strip needs a tenth of
    # each frame (whole frames were half of the fine stage on 10 x 10 tiles of 1024 px).
    BLOCK_PX = 128

    def __init__(self, img: np.ndarray, valid: np.ndarray, sigma: float, *, features: tuple | None = None):
        self.raw = img.astype(np.float32, copy=False)
        self.valid = valid
        self._sigma = sigma
        self._sift: tuple | None = features
        self._smooth: np.ndarray | None = None
        self._gx: np.ndarray | None = None
        self._gy: np.ndarray | None = None
        self._done: np.ndarray | None = None
        self._lock = threading.Lock()

    @cached_property
    def valid_count(self) -> int:
        """Valid pixels of the frame."""
        return int(np.count_nonzero(self.valid))

    def _margin(self) -> int:
        # rows and columns beyond a block that its smoothing (OpenCV's kernel for a float
        # image: 8 sigma + 1 taps) and five-tap gradients reach
        return (int(round(self._sigma * 8 + 1)) | 1) // 2 + 2 if self._sigma > 0 else 2

    def ensure(self, x0: int, y0: int, x1: int, y1: int) -> None:
        """Compute the smoothed frame and its gradients over the blocks that the box
        ``[x0, x1) x [y0, y1)`` (pixels, clipped to the frame) touches and that are not done
        yet (elsewhere the arrays hold anything: read only what was ensured). Each block
        from its own crop of the raw frame grown by the filters' reach, so its values never
        depend on which pair asked first (they differ from a whole-frame filtering by float
        rounding, ~1e-7 relative)."""
        h, w = self.raw.shape
        bs = self.BLOCK_PX
        with self._lock:
            self._allocate()
            by0, by1 = max(y0, 0) // bs, -(-min(y1, h) // bs)
            bx0, bx1 = max(x0, 0) // bs, -(-min(x1, w) // bs)
            m = self._margin()
            for r, c in zip(*np.nonzero(~self._done[by0:by1, bx0:bx1])):
                by, bx = by0 + int(r), bx0 + int(c)
                ry0, ry1, rx0, rx1 = by * bs, min((by + 1) * bs, h), bx * bs, min((bx + 1) * bs, w)
                cy0, cy1, cx0, cx1 = max(ry0 - m, 0), min(ry1 + m, h), max(rx0 - m, 0), min(rx1 + m, w)
                sm = smooth(self.raw[cy0:cy1, cx0:cx1], self._sigma)
                gx, gy = gradients(sm)
                inner = (slice(ry0 - cy0, ry1 - cy0), slice(rx0 - cx0, rx1 - cx0))
                self._smooth[ry0:ry1, rx0:rx1] = sm[inner]
                self._gx[ry0:ry1, rx0:rx1] = gx[inner]
                self._gy[ry0:ry1, rx0:rx1] = gy[inner]
                self._done[by, bx] = True

    def _whole(self) -> None:
        self.ensure(0, 0, self.raw.shape[1], self.raw.shape[0])

    @property
    def a(self) -> np.ndarray:
        """The smoothed frame (float32, grey levels); only the blocks :meth:`ensure` was
        asked for hold it until the whole is read here."""
        self._whole()
        return self._smooth

    @property
    def gx(self) -> np.ndarray:
        self._whole()
        return self._gx

    @property
    def gy(self) -> np.ndarray:
        self._whole()
        return self._gy

    def _allocate(self) -> None:
        if self._done is None:
            h, w = self.raw.shape
            # (not zeroed: only the blocks done are ever read; zeroing three whole frames
            # per prepared frame was half the register stage's page faults)
            self._smooth = np.empty((h, w), np.float32)
            self._gx = np.empty((h, w), np.float32)
            self._gy = np.empty((h, w), np.float32)
            self._done = np.zeros((-(-h // self.BLOCK_PX), -(-w // self.BLOCK_PX)), bool)

    def partial(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(smoothed, gx, gy), frame-sized, valid only where :meth:`ensure` was asked."""
        with self._lock:
            self._allocate()
        return self._smooth, self._gx, self._gy

    @property
    def shape(self) -> tuple[int, int]:
        return self.raw.shape

    @property
    def has_sift(self) -> bool:
        return self._sift is not None

    def sift(self) -> tuple:
        """SIFT keypoints and descriptors of the raw frame over its valid pixels (the
        feature path), computed once per frame (detection was 60 % of a drone log's
        register stage when every pair detected both its frames again)."""
        if self._sift is None:
            u8 = cv2.normalize(self.raw, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
            self._sift = cv2.SIFT_create().detectAndCompute(u8, self.valid.astype(np.uint8) * 255)
        return self._sift


def _translation(x: float, y: float) -> np.ndarray:
    return np.array([[1.0, 0.0, x], [0.0, 1.0, y]])


def _footprint_box(b_shape: tuple[int, int], a_to_b: np.ndarray, a_shape: tuple[int, int],
                   grow: int) -> tuple[int, int, int, int] | None:
    """The box ``(x0, y0, x1, y1)`` of a's pixels (clipped to a) that b's frame covers at
    the warp ``a_to_b`` (2 x 3, a's pixels -> b's), grown by ``grow`` pixels; None when
    empty."""
    hb, wb = b_shape
    x0, y0, x1, y1 = mapped_box(_invert(a_to_b), -1.0, -1.0, float(wb), float(hb), grow + 1)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, a_shape[1]), min(y1, a_shape[0])
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _refine(tpl: PreparedFrame, fb: PreparedFrame, a_to_b: np.ndarray, p: RegistrationParams,
            fix_rotation: float | None = None):
    """Inverse-compositional Gauss-Newton: returns (a_to_b, cov_pixel, centre, ncc, n, iters, gain) or a reason.

    ``cov_pixel`` is 3 x 3 over (dx, dy, dtheta) in a's pixels and radians, or with
    ``p.estimate_scale`` 4 x 4 with the log-scale last. With ``fix_rotation`` (a variance,
    rad^2) the rotation stays where ``a_to_b`` has it (translation, and scale, only) and
    ``cov_pixel`` gives it that variance, uncorrelated: the prior's, restated.
    """
    shape = tpl.shape
    # (everything about the overlap is done in the box of a that b's footprint covers,
    # grown by the erosion's reach: outside it the mask is empty anyway)
    box = _footprint_box(fb.shape, a_to_b, shape, p.mask_margin_px + 2)
    if box is None:
        return f"small overlap: 0 px for fine alignment (min {p.min_overlap_px})"
    bx0, by0, bx1, by1 = box
    vb = _warp(fb.valid.view(np.uint8), a_to_b @ _affine3(_translation(bx0, by0)), (by1 - by0, bx1 - bx0),
               cv2.INTER_NEAREST) > 0
    mask = vb & tpl.valid[by0:by1, bx0:bx1]
    if p.mask_margin_px > 0:
        k = 2 * p.mask_margin_px + 1
        mask = cv2.erode(mask.view(np.uint8), np.ones((k, k), np.uint8), borderValue=0) > 0
    n_full = int(np.count_nonzero(mask))
    if n_full < p.min_overlap_px:
        return f"small overlap: {n_full} px for fine alignment (min {p.min_overlap_px})"
    # Gauss-Newton on a lattice of every `stride`-th pixel: warps cost stride^2 less, and
    # the estimate's noise grows only by about `stride` (measured in bench_register).
    st = max(int(p.fine_stride_px), 1)
    c0, r0, bw_, bh_ = cv2.boundingRect(mask.view(np.uint8))
    msub = mask[r0 : r0 + bh_ : st, c0 : c0 + bw_ : st]
    c0, r0 = c0 + bx0, r0 + by0  # (a's pixels from here on)
    lat = (slice(r0, r0 + bh_, st), slice(c0, c0 + bw_, st))
    lat_shape = msub.shape
    n = int(msub.sum())
    lr, lc = np.nonzero(msub)
    ys, xs = (r0 + st * lr).astype(np.float32), (c0 + st * lc).astype(np.float32)
    # (the smoothed frames and gradients only where this pair reads them: a over the
    # lattice; b where each iteration's lattice lands, grown by the interpolation's reach)
    tpl.ensure(c0, r0, c0 + bw_, r0 + bh_)
    ta, tgx, tgy = tpl.partial()

    def b_at(m: np.ndarray) -> np.ndarray:
        """b's smoothed frame, ensured where the lattice lands at the warp ``m`` (a -> b),
        grown by the interpolation's reach (Lanczos-4: 4 px)."""
        fb.ensure(*mapped_box(m, c0, r0, c0 + bw_, r0 + bh_, 5.0))
        return fb.partial()[0]

    b = b_at(a_to_b)
    av = ta[lat][msub]
    gx = gx_raw = tgx[lat][msub]
    gy = gy_raw = tgy[lat][msub]
    a_mean = float(av.mean(dtype=np.float64))  # (levels, for the exposure ratio)
    # The background (a Gaussian of fine_background_px over the overlap) comes out of both
    # frames' samples, computed alike on the lattice over the same overlap, when that
    # correlates the two better than the raw samples (less a ramp) do: the shading across a
    # microscope tile's overlap strip (tens of grey levels, different in each tile)
    # outweighs its texture (cells: a few grey levels); on brain tiles the raw overlap's
    # NCC at the right shift was 0.08, 0.93 without the background. Where the raw samples
    # correlate better (smooth texture, whose energy the background would take: blobs of
    # 6 px lost 3x in rotation accuracy) they are kept. (Each frame's own background, from
    # its own pixels, differs near the frame's edge, where overlaps are: that biased
    # simulated links by 0.01 px and the poses 3x.)
    bg_sigma = p.fine_background_px / st
    lat_mask = msub.astype(np.float32)

    def background(samples: np.ndarray) -> np.ndarray:
        img = np.zeros(lat_shape, np.float32)
        img[msub] = samples
        return masked_blur(img, lat_mask, bg_sigma)

    if bg_sigma > 0:
        bg = background(av)
        b0 = _warp(b, (_affine3(a_to_b) @ np.array([[st, 0.0, c0], [0.0, st, r0], [0.0, 0.0, 1.0]]))[:2],
                   lat_shape, cv2.INTER_LINEAR)[msub]
        ramp = np.stack([np.ones(n, np.float32), xs - xs.mean(), ys - ys.mean()], axis=1)
        q_ramp = np.linalg.qr(ramp.astype(np.float64))[0]  # (one factorization for both)
        raw_ncc = _ncc_less(av, b0, q_ramp)
        fg_ncc = _ncc_less(av - bg[msub], b0 - background(b0)[msub], q_ramp)
        if not fg_ncc > raw_ncc:
            bg_sigma = 0.0
    if bg_sigma > 0:
        bgx, bgy = gradients(bg)
        av = av - bg[msub]
        gx = gx - bgx[msub] / np.float32(st)
        gy = gy - bgy[msub] / np.float32(st)

    def foreground(samples: np.ndarray) -> np.ndarray:
        return samples - background(samples)[msub] if bg_sigma > 0 else samples

    centre = np.array([xs.mean(dtype=np.float64), ys.mean(dtype=np.float64)])
    dxs, dys = xs - np.float32(centre[0]), ys - np.float32(centre[1])
    nfull = 4 if p.estimate_scale else 3
    free = [0, 1] + ([] if fix_rotation is not None else [2]) + ([3] if p.estimate_scale else [])
    cols = [gx, gy, gy * dxs - gx * dys]
    if p.estimate_scale:  # d/d(log scale) of a similarity about the centre
        cols.append(gx * dxs + gy * dys)
    jac = np.stack([cols[i] for i in free], axis=1)
    npar = jac.shape[1]

    def full(d: np.ndarray) -> np.ndarray:
        out = np.zeros(nfull)
        out[free] = d
        return out

    a_c = av - np.float32(av.mean(dtype=np.float64))
    # Photometric model b_w = alpha a_c + beta (+ a linear ramp across the overlap with
    # ``fine_ramp``: shading, vignetting and illumination gradients differ between frames).
    # One product per iteration gives everything: [J | P]^T b_w with P the photometric
    # basis; its coefficients c = (P^T P)^-1 P^T b_w, and J^T e = J^T b_w - (J^T P) c.
    scale_r = np.float32(max(float(np.abs(dxs).max()), float(np.abs(dys).max()), 1.0))
    phot = [a_c, np.ones(n, np.float32)] + ([dxs / scale_r, dys / scale_r] if p.fine_ramp else [])
    design = np.concatenate([jac, np.stack(phot, axis=1)], axis=1)
    pbasis = design[:, npar:]
    nphot = pbasis.shape[1]
    # One Gram matrix holds the Hessian J^T J, J^T P and P^T P. The design is copied to
    # float64 once: every product below is then a BLAS one, 5x faster than einsum's
    # float64 accumulation of float32 (a 100k x 7 design: 0.23 vs 1.1 ms per iteration)
    # at the same precision; BLAS runs one thread under the workers
    # (:func:`pipeline.parallel.opencv_threads`), else its threads fought them.
    design64 = design.astype(np.float64)
    gram_all = design64.T @ design64
    hess, jt_p, gram = gram_all[:npar, :npar], gram_all[:npar, npar:], gram_all[npar:, npar:]
    a_var = float(gram[0, 0])
    if a_var <= 0:
        return "no texture: the overlap is flat"
    try:
        hinv = np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        return "no texture: the overlap does not constrain the pose (singular Hessian)"
    try:
        gram_inv = np.linalg.inv(gram)
    except np.linalg.LinAlgError:
        return "no texture: the overlap is flat"

    def solve(bw: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, float]:
        """(gain alpha, Gauss-Newton step, photometric coefficients, squared residual) for
        the samples b_w."""
        b64 = bw.astype(np.float64)
        v = b64 @ design64
        c = gram_inv @ v[npar:]
        alpha = float(c[0])
        jt_e = v[:npar] - jt_p @ c
        cost = float(b64 @ b64) - float(v[npar:] @ c)
        return alpha, hinv @ jt_e / alpha if alpha > 1e-6 else np.zeros(npar), c, cost

    # Lattice pixel (i, j) -> a pixel (c0 + st j, r0 + st i).
    lattice = np.array([[st, 0.0, c0], [0.0, st, r0], [0.0, 0.0, 1.0]])
    r_max = float(np.hypot(max(c0 + bw_ - centre[0], centre[0] - c0), max(r0 + bh_ - centre[1], centre[1] - r0)))
    m = _affine3(a_to_b)
    it = 0

    def warped(exact: bool, alpha: float) -> np.ndarray:
        b = b_at(m)
        if not exact:
            return _warp(b, (m @ lattice)[:2], lat_shape, cv2.INTER_CUBIC)[msub]
        # Exact positions (as pipeline.resample.ExactSampler): Lanczos at the 1/32 grid
        # point plus the remainder times b's gradient, which near convergence is
        # alpha R grad a (b(W(x)) = alpha a(x) + beta): no remap of b's gradients needed.
        x = m[0, 0] * gx64 + m[0, 1] * gy64 + m[0, 2]
        y = m[1, 0] * gx64 + m[1, 1] * gy64 + m[1, 2]
        q = POSITION_STEPS
        xq, yq = np.rint(x * q) / q, np.rint(y * q) / q
        v = cv2.remap(b, xq.astype(np.float32), yq.astype(np.float32), cv2.INTER_LANCZOS4,
                      borderMode=cv2.BORDER_REPLICATE)[msub]
        rx = (x - xq)[msub].astype(np.float32)
        ry = (y - yq)[msub].astype(np.float32)
        # (b's gradient is alpha A^-T grad a for the linear part A of the warp: A itself for
        # a rotation, A / det A for a similarity.)
        ga = alpha if not p.estimate_scale else alpha / float(m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0])
        gbx = np.float32(ga) * (np.float32(m[0, 0]) * gx_raw + np.float32(m[0, 1]) * gy_raw)
        gby = np.float32(ga) * (np.float32(m[1, 0]) * gx_raw + np.float32(m[1, 1]) * gy_raw)
        return v + gbx * rx + gby * ry

    # OpenCV's fast (1/32-pixel quantized) warp until the steps are that small, then exact
    # sampling for the last iterations.
    gy64, gx64 = np.mgrid[r0 : r0 + st * lat_shape[0] : st, c0 : c0 + st * lat_shape[1] : st].astype(np.float64)
    exact = switched = False
    halvings = 0
    alpha = 1.0
    best_cost, base, trial = np.inf, m, None

    units = np.array([1.0, 1.0, r_max, r_max][:nfull])  # (pixels at the overlap's far end)

    def length(d: np.ndarray) -> float:
        """A step's largest displacement over the overlap (pixels)."""
        out = max(np.hypot(d[0], d[1]), abs(d[2]) * r_max)
        return max(out, abs(d[3]) * r_max) if nfull > 3 else out

    for it in range(1, p.max_iterations + 1):
        raw_bw = warped(exact, alpha)
        bw = foreground(raw_bw)
        last_exact = exact
        a_new, delta, _, cost = solve(bw)
        delta = full(delta)
        if trial is not None and cost > best_cost and not switched and float(np.dot(delta * units, trial * units)) < 0:
            # The last step made the fit worse and Gauss-Newton now points back: it
            # overshot (the two frames' texture differs in contrast or focus, so the
            # template's Hessian misjudges the curvature). Go back and take half of it.
            # (A worse fit with Gauss-Newton still pointing onwards is not an overshoot:
            # under a scale change pixels near the overlap's edge leave it, and the cost
            # of the fixed lattice rises on the way to the answer.)
            trial = trial * 0.5
            halvings += 1
            step = length(trial)
            m = base @ _affine3(_invert(_rigid_about(trial, centre)))
            if step < p.tolerance_px:
                break
            continue
        alpha = a_new
        if alpha <= 1e-6:
            return "no correlation: negative or zero gain between the frames"
        best_cost, base = cost, m
        step = length(delta)
        if step > p.fine_max_step_px:
            # A trust region: the coarse stage put us within about a pixel, so a longer step
            # comes from a poorly conditioned first estimate (weak texture, thin strips) and
            # would throw the alignment out of its basin.
            delta = delta * (p.fine_max_step_px / step)
            step = p.fine_max_step_px
        trial = delta
        m = base @ _affine3(_invert(_rigid_about(delta, centre)))
        if exact and step < p.tolerance_px:
            break
        switched = not exact and step < QUANTIZED_STEP_PX
        exact = exact or switched
    if not (last_exact and step < p.tolerance_px):
        # Not converged on exact samples: sample the final estimate for the statistics.
        raw_bw = warped(True, alpha)
        bw = foreground(raw_bw)
    alpha, _, c, _ = solve(bw)
    e = bw - pbasis @ c.astype(np.float32)
    sigma2 = float(np.einsum("i,i->", e, e, dtype=np.float64)) / max(n - npar - nphot, 1)
    # Residuals correlated between neighbouring samples (the smoothing above, interpolation
    # at rectification) carry less information than sigma^2 H^-1 assumes: inflate by the
    # AR(1) variance factor of their lag-1 correlation along rows and columns (without it
    # the links' chi-square came out 1.7x too large).
    cov_free = p.covariance_inflation * _correlation_inflation(e, msub) * sigma2 * hinv / (alpha * alpha)
    cov_px = np.zeros((nfull, nfull))
    cov_px[np.ix_(free, free)] = cov_free
    if fix_rotation is not None:
        cov_px[2, 2] = fix_rotation
    # NCC of a and b_w with the offset (and ramp) taken out of both (their projections on
    # the rest of the photometric basis Q), from dot products already at hand.
    v = np.einsum("ij,i->j", design, bw, dtype=np.float64)[npar:]
    qq_inv = np.linalg.inv(gram[1:, 1:])
    qa, qb = gram[1:, 0], v[1:]
    bb = float(np.einsum("i,i->", bw, bw, dtype=np.float64)) - float(qb @ qq_inv @ qb)
    aa = a_var - float(qa @ qq_inv @ qa)
    ab = float(v[0]) - float(qa @ qq_inv @ qb)
    ncc = ab / np.sqrt(aa * bb) if aa > 0 and bb > 0 else 0.0
    gain = float(raw_bw.mean(dtype=np.float64)) / a_mean if a_mean > 0 else 1.0
    return m[:2], cov_px, centre, ncc, n_full, it, gain


def _ncc_less(x: np.ndarray, y: np.ndarray, q: np.ndarray) -> float:
    """NCC of samples ``x`` and ``y`` (n,) after taking their least-squares fit on a basis
    out of both (e.g. offset and a linear ramp); ``q`` (n, k): the basis orthonormalized
    (``np.linalg.qr(basis)[0]``, float64); -1 when either is flat."""
    rx = x - q @ (q.T @ x)
    ry = y - q @ (q.T @ y)
    den = float(np.sqrt(np.dot(rx, rx) * np.dot(ry, ry)))
    return float(np.dot(rx, ry)) / den if den > 0 else -1.0


def _correlation_inflation(e: np.ndarray, mask: np.ndarray) -> float:
    """``prod (1 + rho) / (1 - rho)`` over the lag-1 correlations rho of residuals ``e``
    (given at the True pixels of ``mask``) along rows and columns."""
    img = np.zeros(mask.shape, np.float32)
    img[mask] = e
    flat = img.ravel()
    energy = float(np.einsum("i,i->", flat, flat, dtype=np.float64))
    if energy <= 0:
        return 1.0
    factor = 1.0
    for lag in (1, mask.shape[1]):  # along rows, along columns (row-end wraps are negligible)
        rho = float(np.einsum("i,i->", flat[:-lag], flat[lag:], dtype=np.float64)) / energy
        rho = min(max(rho, 0.0), 0.9)
        factor *= (1.0 + rho) / (1.0 - rho)
    return factor


def _features(fa: "PreparedFrame", fb: "PreparedFrame", p: RegistrationParams):
    """SIFT matches + pycolmap LO-RANSAC: a 2x3 a->b rigid estimate and its inlier count, or a reason."""
    import pycolmap

    ka, da = fa.sift()
    kb, db = fb.sift()
    if da is None or db is None or len(ka) < p.feature_min_inliers or len(kb) < p.feature_min_inliers:
        return "feature path: too few features"
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < p.feature_ratio * m[1].distance]
    if len(good) < p.feature_min_inliers:
        return f"feature path: too few matches ({len(good)}, need {p.feature_min_inliers})"
    pa = np.array([ka[m.queryIdx].pt for m in good], dtype=np.float64)
    pb = np.array([kb[m.trainIdx].pt for m in good], dtype=np.float64)
    opts = pycolmap.RANSACOptions()
    opts.max_error = p.feature_max_error_px
    opts.random_seed = 0
    res = pycolmap.estimate_affine2d_robust(pa, pb, opts)
    if res is None or res["num_inliers"] < p.feature_min_inliers:
        n_in = 0 if res is None else res["num_inliers"]
        return f"feature path: no consistent motion ({n_in} inliers, need {p.feature_min_inliers})"
    inl = np.asarray(res["inlier_mask"], bool)
    # Rigid (Kabsch) fit on the inliers: the affine's scale/shear are not physical here.
    qa, qb = pa[inl], pb[inl]
    ma, mb = qa.mean(0), qb.mean(0)
    u, _, vt = np.linalg.svd((qa - ma).T @ (qb - mb))
    r = (u @ vt).T
    if np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = (u @ vt).T
    t = mb - r @ ma
    return np.hstack([r, t[:, None]]), int(inl.sum())


def register_pair(
    a: np.ndarray | PreparedFrame,
    a_valid: np.ndarray | None,
    b: np.ndarray | PreparedFrame,
    b_valid: np.ndarray | None,
    prior_rel: np.ndarray,
    pixel_size: float,
    radius_px: float,
    heading_sigma_rad: float,
    p: RegistrationParams,
    *,
    heading_known: bool = False,
) -> PairResult:
    """Register frame b to frame a (rectified, same pixel size) near ``prior_rel``.

    Args:
        a, b: frames in grey levels (float32) with their masks a_valid, b_valid; or
            :class:`PreparedFrame` objects (masks then None), to prepare each frame once
            when it takes part in many pairs.
        prior_rel: prior pose of b in a's frame (metres, radians).
        radius_px: search radius for the translation (the prior's uncertainty), pixels.
        heading_sigma_rad: the prior's heading uncertainty (radians); beyond
            ``feature_rotation_rad``, when correlation at the prior's rotation finds no
            good match, the feature path seeds the alignment.
        heading_known: the prior's heading is an absolute one (a stage that does not
            rotate): where the overlap measures the rotation worse than
            ``heading_sigma_rad``, the translation is aligned at the prior's rotation.
    """
    fa = a if isinstance(a, PreparedFrame) else PreparedFrame(a, a_valid, p.fine_smoothing_px)
    fb = b if isinstance(b, PreparedFrame) else PreparedFrame(b, b_valid, p.fine_smoothing_px)
    b_to_a = frame_to_frame_affine(prior_rel, fb.shape, fa.shape, pixel_size)
    a_to_b = _invert(b_to_a)
    if heading_sigma_rad <= p.feature_rotation_rad:
        return _align(fa, fb, a_to_b, pixel_size, radius_px, heading_sigma_rad, p, heading_known)
    # A loose heading: correlation at the prior's rotation first (its peak survives a few
    # degrees, and the prior is usually better than its sigma says); the feature path, which
    # any rotation leaves alike, only when that finds nothing good.
    first = _align(fa, fb, a_to_b, pixel_size, radius_px, heading_sigma_rad, p, heading_known)
    if first.ok and first.ncc >= p.min_ncc:
        return first
    res = _features(fa, fb, p)
    if isinstance(res, str):
        return PairResult(False, res, method="features")
    a_to_b, inliers = res
    # The feature estimate must agree with the prior within its uncertainty.
    jump = np.hypot(*(_invert(a_to_b) @ [*frame_centre(fb.shape), 1.0] - b_to_a @ [*frame_centre(fb.shape), 1.0]))
    if jump > 3.0 * radius_px + 5.0:
        return PairResult(False, f"feature path: match {jump:.0f} px from the prior (radius {radius_px:.0f} px)",
                          method="features")
    return _align(fa, fb, a_to_b, pixel_size, 3.0, heading_sigma_rad, p, heading_known, "features", inliers)


def _align(fa: PreparedFrame, fb: PreparedFrame, a_to_b: np.ndarray, pixel_size: float, radius_px: float,
           heading_sigma_rad: float, p: RegistrationParams, heading_known: bool, method: str = "correlation",
           inliers: int = 0) -> PairResult:
    """The coarse and fine stages from the warp ``a_to_b`` (the prior's, or the feature
    path's estimate); see :func:`register_pair`."""
    a, a_valid, b, b_valid = fa.raw, fa.valid, fb.raw, fb.valid
    box = _footprint_box(b.shape, a_to_b, a.shape, 0)
    overlap = 0.0
    if box is not None:
        x0, y0, x1, y1 = box
        bvw = _warp(b_valid.view(np.uint8), a_to_b @ _affine3(_translation(x0, y0)), (y1 - y0, x1 - x0),
                    cv2.INTER_NEAREST)
        overlap = float(np.count_nonzero((bvw > 0) & a_valid[y0:y1, x0:x1])) / max(float(fa.valid_count), 1.0)
    if overlap < p.min_overlap_fraction:
        # The prior may be off by the search radius: the pair is searched when b's
        # footprint, grown by it, covers enough of a.
        reach = reach_fraction(a_valid, b_valid, a_to_b, radius_px)
        if reach < p.min_overlap_fraction:
            return PairResult(False, f"small overlap: {reach:.0%} within the search radius of the prior "
                                     f"(min {p.min_overlap_fraction:.0%})", overlap=overlap, method=method)
    coarse = coarse_shift(a, a_valid, b, b_valid, a_to_b, radius_px, p.coarse)
    if isinstance(coarse, str):
        return PairResult(False, coarse, overlap=overlap, method=method)
    uniq, z, q = coarse.uniqueness, coarse.peak_z, coarse.ncc
    # (a feature path's seed has its inliers for significance: its coarse search, a few
    # pixels about the seed, only refines it)
    if method != "features" and z < p.min_peak_z and not (np.isfinite(q) and q >= p.min_peak_ncc):
        return PairResult(False, f"no match: correlation peak {z:.1f} sigma (min {p.min_peak_z:g})"
                                 + (f", NCC {q:.2f} (min {p.min_peak_ncc:.2f})" if np.isfinite(q) else ""),
                          overlap=overlap, uniqueness=uniq, method=method, peak_z=z, peak_ncc=q)
    if method != "features" and uniq < p.min_uniqueness:
        return PairResult(False, f"ambiguous: uniqueness {uniq:.3f} (min {p.min_uniqueness:g})",
                          overlap=overlap, uniqueness=uniq, method=method, peak_z=z, peak_ncc=q)
    a_to_b = a_to_b @ _affine3(_rigid_about(np.array([*coarse.shift, 0.0]), np.zeros(2)))
    fine = _refine(fa, fb, a_to_b, p)
    rotation = "measured"
    if heading_known and not isinstance(fine, str) and method != "features" and fine[1][2, 2] > heading_sigma_rad**2:
        # The overlap measures the rotation worse than the prior knows it (thin strips of a
        # stage that does not rotate): align the translation only, at the prior's rotation,
        # and leave the heading to the prior (a noisy rotation would swing b's centre).
        fixed = _refine(fa, fb, a_to_b, p, fix_rotation=max(heading_sigma_rad, 1e-6) ** 2)
        if not isinstance(fixed, str):
            fine, rotation = fixed, "prior"
    if isinstance(fine, str):
        return PairResult(False, fine, overlap=overlap, uniqueness=uniq, method=method, peak_z=z, peak_ncc=q)
    a_to_b, cov_px, centre, ncc, n, iters, gain = fine
    b_to_a = _invert(a_to_b)
    rel = frame_affine_to_rel(b_to_a, b.shape, a.shape, pixel_size)
    # Covariance: the error is a rigid perturbation about `centre` in a's pixel frame;
    # carry it to b's centre and to metres/radians (rows point to -y, angles flip).
    pc = b_to_a @ np.array([*frame_centre(b.shape), 1.0])
    g = np.array([[1.0, 0.0, -(pc[1] - centre[1])], [0.0, 1.0, pc[0] - centre[0]], [0.0, 0.0, 1.0]])
    dmat = np.diag([pixel_size, -pixel_size, -1.0])
    if not p.estimate_scale:
        jm = dmat @ g
        cov = jm @ cov_px @ jm.T
        return PairResult(True, "", rel, cov, ncc, uniq, overlap, n, iters, method, inliers, gain, peak_z=z,
                          rotation=rotation, peak_ncc=q)
    # Similarity: a log-scale perturbation about `centre` also moves b's centre radially.
    g4 = np.zeros((4, 4))
    g4[:3, :3] = g
    g4[:2, 3] = pc[:2] - centre
    g4[3, 3] = 1.0
    jm = np.diag([pixel_size, -pixel_size, -1.0, 1.0]) @ g4
    cov4 = jm @ cov_px @ jm.T
    log_scale = 0.5 * float(np.log(abs(np.linalg.det(b_to_a[:, :2]))))
    return PairResult(True, "", rel, cov4[:3, :3].copy(), ncc, uniq, overlap, n, iters, method, inliers, gain,
                      log_scale, cov4, peak_z=z, rotation=rotation, peak_ncc=q)
