"""Pairwise rigid registration of rectified frames, to a small fraction of a pixel.

Why this design (measured in ``bench/bench_register.py``):

1. **Prior warp.** Frame b is resampled into frame a's pixel frame with the prior relative
   pose, so that what is left is a small correction.
2. **Coarse search: normalized cross-correlation** (``cv2.matchTemplate``) of a template
   from a over the prior's uncertainty window in b, on an image pyramid when that window
   is wide. The NCC surface also gives seed 000's *uniqueness* C1 - C2 (highest peak minus
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

from dataclasses import dataclass, field

import cv2
import numpy as np

from mapstore.grid import frame_affine_to_rel, frame_centre, frame_to_frame_affine
from pipeline.resample import POSITION_STEPS, gradients


@dataclass(frozen=True)
class RegistrationParams:
    """The ``[register]`` knobs used per pair (see configs/floor.toml for meanings)."""

    template_px: int = 64
    peak_exclusion_px: int = 4
    uniqueness_margin_px: int = 4
    coarse_max_radius_px: int = 12
    max_iterations: int = 30
    tolerance_px: float = 1e-3
    mask_margin_px: int = 2
    fine_stride_px: int = 3
    min_overlap_fraction: float = 0.15
    min_overlap_px: int = 2000
    fine_smoothing_px: float = 0.7
    covariance_inflation: float = 1.0
    feature_radius_px: float = 40.0
    feature_rotation_rad: float = 0.05
    feature_ratio: float = 0.8
    feature_max_error_px: float = 2.0
    feature_min_inliers: int = 12
    # Estimate the relative scale of b to a too (a 4th Gauss-Newton parameter, its log);
    # set from ``[optimize] pose_model = "similarity2"``, not from ``[register]``.
    estimate_scale: bool = False

    @classmethod
    def from_config(cls, table: dict) -> "RegistrationParams":
        names = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in table.items() if k in names})


@dataclass
class PairResult:
    """Outcome of registering frame b to frame a.

    Attributes:
        ok: False when the pair could not be registered; ``reason`` says why.
        rel: (3,) pose of b in a's frame (metres, radians).
        cov: (3, 3) covariance of ``rel`` (m^2, m rad, rad^2).
        ncc: NCC of the aligned overlap after gain/offset correction.
        uniqueness: C1 - C2 of the coarse NCC surface (seed 000; < 0.2 is poor; C2 is the
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


def _ncc_search(
    a: np.ndarray, region_of, mask: np.ndarray, radius: int, p: RegistrationParams
) -> tuple[np.ndarray, float, float] | None:
    """Integer shift d with a(x) ~ bw(x + d) over a template of a inside ``mask``.

    ``region_of(y0, y1, x0, x1)`` returns rows y0:y1, columns x0:x1 of b warped into a's
    frame (bw), so that only the searched region is ever resampled.
    Returns (d, C1, C1 - C2) or None when no template fits.
    """
    span = radius + p.uniqueness_margin_px
    inner = cv2.erode(mask.astype(np.uint8), np.ones((2 * span + 1, 2 * span + 1), np.uint8), borderValue=0) > 0
    if not inner.any():
        return None
    # The template: the largest square (at most template_px) inside the eroded overlap,
    # from its chessboard distance transform; among the places where it fits, the one
    # nearest the middle of those places (at the ends of a long strip lens distortion
    # misaligns most).
    depth = cv2.distanceTransform(inner.view(np.uint8), cv2.DIST_C, 3)
    deepest = int(cv2.minMaxLoc(depth)[1])
    h = min(p.template_px // 2, deepest - 1)  # every pixel within h of the centre is inside
    if h < 4:
        return None
    fits = (depth >= h + 1).view(np.uint8)
    x0, y0, w0, h0 = cv2.boundingRect(fits)
    cx, cy = x0 + w0 // 2, y0 + h0 // 2
    if not fits[cy, cx]:  # a non-convex region: its point nearest the box centre
        ys, xs = np.nonzero(fits)
        k = int(np.argmin((xs - cx) ** 2 + (ys - cy) ** 2))
        cx, cy = int(xs[k]), int(ys[k])
    r0, r1, c0, c1 = cy - h, cy + h, cx - h, cx + h
    tmpl = a[r0:r1, c0:c1]
    if r0 - span < 0 or c0 - span < 0 or r1 + span > a.shape[0] or c1 + span > a.shape[1]:
        return None
    if tmpl.std() < 1e-3:
        return None
    region = region_of(r0 - span, r1 + span, c0 - span, c1 + span)
    surf = cv2.matchTemplate(region, tmpl, cv2.TM_CCOEFF_NORMED)
    # Only shifts within the search radius count as candidates; the margin beyond them
    # is used for the uniqueness test only.
    core = surf[p.uniqueness_margin_px : surf.shape[0] - p.uniqueness_margin_px,
                p.uniqueness_margin_px : surf.shape[1] - p.uniqueness_margin_px]
    _, c1v, _, loc = cv2.minMaxLoc(core)
    py, px = loc[1] + p.uniqueness_margin_px, loc[0] + p.uniqueness_margin_px
    yy, xx = np.mgrid[0 : surf.shape[0], 0 : surf.shape[1]]
    away = (yy - py) ** 2 + (xx - px) ** 2 > p.peak_exclusion_px**2
    # C2: the highest competing *peak* (a local maximum of the surface, its edge included:
    # a slope rising out of the window counts), not the main peak's own shoulder, which on
    # smooth texture is still high 5 px out though nothing competes with the match.
    peaks = away & (surf >= cv2.dilate(surf, np.ones((3, 3), np.uint8)))
    c2v = float(surf[peaks].max()) if peaks.any() else -1.0
    d = np.array([px - span, py - span], dtype=float)
    return d, float(c1v), float(c1v - c2v)


def _coarse(
    a: np.ndarray, b: np.ndarray, a_to_b: np.ndarray, mask: np.ndarray, radius: float, p: RegistrationParams
) -> tuple[np.ndarray, float, float] | None:
    """Refine ``a_to_b`` by an integer-pixel NCC search (pyramid when the radius is wide)."""
    radius = max(int(np.ceil(radius)), 1)
    level = 0
    while (radius >> level) > p.coarse_max_radius_px:
        level += 1
    shift = np.zeros(2)
    if level > 0:
        f = 2**level
        bw = _warp(b, a_to_b, a.shape, cv2.INTER_LINEAR)
        small = (max(a.shape[0] // f, 1), max(a.shape[1] // f, 1))
        a_s = cv2.resize(a, small[::-1], interpolation=cv2.INTER_AREA)
        bw_s = cv2.resize(bw, small[::-1], interpolation=cv2.INTER_AREA)
        m_s = cv2.resize(mask.astype(np.uint8), small[::-1], interpolation=cv2.INTER_NEAREST) > 0
        res = _ncc_search(a_s, lambda y0, y1, x0, x1: bw_s[y0:y1, x0:x1], m_s, int(np.ceil(radius / f)), p)
        if res is None:
            return None
        shift = res[0] * f
        radius = f + 1
    m = _affine3(a_to_b) @ _affine3(_rigid_about(np.array([*shift, 0.0]), np.zeros(2)))

    def region_of(y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        offset = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
        return _warp(b, (m @ offset)[:2], (y1 - y0, x1 - x0), cv2.INTER_LINEAR)

    res = _ncc_search(a, region_of, mask, radius, p)
    if res is None:
        return None
    d, c1, uniq = res
    shift = shift + d
    return a_to_b @ _affine3(_rigid_about(np.array([*shift, 0.0]), np.zeros(2))), c1, uniq


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

    def __init__(self, img: np.ndarray, valid: np.ndarray, sigma: float):
        self.raw = img.astype(np.float32, copy=False)
        self.valid = valid
        self.a = smooth(self.raw, sigma)
        self.gx, self.gy = gradients(self.a)

    @property
    def shape(self) -> tuple[int, int]:
        return self.raw.shape


def _refine(tpl: PreparedFrame, fb: PreparedFrame, a_to_b: np.ndarray, p: RegistrationParams):
    """Inverse-compositional Gauss-Newton: returns (a_to_b, cov_pixel, centre, ncc, n, iters, gain) or a reason.

    ``cov_pixel`` is 3 x 3 over (dx, dy, dtheta) in a's pixels and radians, or with
    ``p.estimate_scale`` 4 x 4 with the log-scale last.
    """
    shape = tpl.a.shape
    b = fb.a
    vb = _warp(fb.valid.astype(np.uint8), a_to_b, shape, cv2.INTER_NEAREST) > 0
    mask = vb & tpl.valid
    if p.mask_margin_px > 0:
        k = 2 * p.mask_margin_px + 1
        mask = cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8), borderValue=0) > 0
    n_full = int(mask.sum())
    if n_full < p.min_overlap_px:
        return f"small overlap: {n_full} px for fine alignment (min {p.min_overlap_px})"
    # Gauss-Newton on a lattice of every `stride`-th pixel: warps cost stride^2 less, and
    # the estimate's noise grows only by about `stride` (measured in bench_register).
    st = max(int(p.fine_stride_px), 1)
    c0, r0, bw_, bh_ = cv2.boundingRect(mask.astype(np.uint8))
    lat = (slice(r0, r0 + bh_, st), slice(c0, c0 + bw_, st))
    msub = mask[lat]
    lat_shape = msub.shape
    n = int(msub.sum())
    lr, lc = np.nonzero(msub)
    ys, xs = (r0 + st * lr).astype(np.float32), (c0 + st * lc).astype(np.float32)
    av = tpl.a[lat][msub]
    gx = tpl.gx[lat][msub]
    gy = tpl.gy[lat][msub]
    centre = np.array([xs.mean(dtype=np.float64), ys.mean(dtype=np.float64)])
    dxs, dys = xs - np.float32(centre[0]), ys - np.float32(centre[1])
    cols = [gx, gy, gy * dxs - gx * dys]
    if p.estimate_scale:  # d/d(log scale) of a similarity about the centre
        cols.append(gx * dxs + gy * dys)
    jac = np.stack(cols, axis=1)
    npar = jac.shape[1]
    # einsum, not BLAS: with float64 copies and `@` one thread was 5 % faster, but on the
    # threads scheduler OpenBLAS's own threads fought the workers (145 -> 95-120 pairs/s).
    hess = np.einsum("ij,ik->jk", jac, jac, dtype=np.float64)
    try:
        hinv = np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        return "no texture: the overlap does not constrain the pose (singular Hessian)"
    a_c = av - av.mean(dtype=np.float64).astype(np.float32)
    a_var = float(np.einsum("i,i->", a_c, a_c, dtype=np.float64))
    if a_var <= 0:
        return "no texture: the overlap is flat"
    # One product per iteration gives everything: [J | a_c | 1]^T b_w. With b_w's mean m,
    # J^T (b_w - m) = J^T b_w - m J^T 1, and a_c . (b_w - m) = a_c . b_w (a_c sums to 0).
    design = np.concatenate([jac, a_c[:, None], np.ones((n, 1), np.float32)], axis=1)
    jt_one = jac.sum(axis=0, dtype=np.float64)
    jt_a = np.einsum("ij,i->j", jac, a_c, dtype=np.float64)

    def solve(bw: np.ndarray) -> tuple[float, np.ndarray, float]:
        """(gain alpha, Gauss-Newton step, mean of b_w) for the samples b_w."""
        v = np.einsum("ij,i->j", design, bw, dtype=np.float64)
        mean = v[npar + 1] / n
        alpha = v[npar] / a_var
        jt_e = v[:npar] - mean * jt_one - alpha * jt_a
        return alpha, hinv @ jt_e / alpha if alpha > 1e-6 else np.zeros(npar), mean

    # Lattice pixel (i, j) -> a pixel (c0 + st j, r0 + st i).
    lattice = np.array([[st, 0.0, c0], [0.0, st, r0], [0.0, 0.0, 1.0]])
    r_max = float(np.hypot(max(c0 + bw_ - centre[0], centre[0] - c0), max(r0 + bh_ - centre[1], centre[1] - r0)))
    m = _affine3(a_to_b)
    it = 0

    def warped(exact: bool, alpha: float) -> np.ndarray:
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
        ga = alpha if npar == 3 else alpha / float(m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0])
        gbx = np.float32(ga) * (np.float32(m[0, 0]) * gx + np.float32(m[0, 1]) * gy)
        gby = np.float32(ga) * (np.float32(m[1, 0]) * gx + np.float32(m[1, 1]) * gy)
        return v + gbx * rx + gby * ry

    # OpenCV's fast (1/32-pixel quantized) warp until the steps are that small, then exact
    # sampling for the last iterations.
    gy64, gx64 = np.mgrid[r0 : r0 + st * lat_shape[0] : st, c0 : c0 + st * lat_shape[1] : st].astype(np.float64)
    exact = False
    alpha = 1.0
    for it in range(1, p.max_iterations + 1):
        bw = warped(exact, alpha)
        last_exact = exact
        alpha, delta, _ = solve(bw)
        if alpha <= 1e-6:
            return "no correlation: negative or zero gain between the frames"
        m = m @ _affine3(_invert(_rigid_about(delta, centre)))
        step = max(np.hypot(delta[0], delta[1]), abs(delta[2]) * r_max)
        if npar > 3:
            step = max(step, abs(delta[3]) * r_max)
        if exact and step < p.tolerance_px:
            break
        exact = exact or step < QUANTIZED_STEP_PX
    if not (last_exact and step < p.tolerance_px):
        # Not converged on exact samples: sample the final estimate for the statistics.
        bw = warped(True, alpha)
    alpha, _, mean = solve(bw)
    bc = bw - np.float32(mean)
    e = bc - np.float32(alpha) * a_c
    sigma2 = float(np.einsum("i,i->", e, e, dtype=np.float64)) / max(n - npar - 2, 1)
    # Residuals correlated between neighbouring samples (the smoothing above, interpolation
    # at rectification) carry less information than sigma^2 H^-1 assumes: inflate by the
    # AR(1) variance factor of their lag-1 correlation along rows and columns (without it
    # the links' chi-square came out 1.7x too large).
    cov_px = p.covariance_inflation * _correlation_inflation(e, msub) * sigma2 * hinv / (alpha * alpha)
    ncc = alpha * a_var / np.sqrt(a_var * float(np.einsum("i,i->", bc, bc, dtype=np.float64)))
    a_mean = float(av.mean(dtype=np.float64))
    gain = mean / a_mean if a_mean > 0 else 1.0
    return m[:2], cov_px, centre, ncc, n_full, it, gain


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


def _features(a, a_valid, b, b_valid, p: RegistrationParams):
    """SIFT matches + pycolmap LO-RANSAC: a 2x3 a->b rigid estimate and its inlier count, or a reason."""
    import pycolmap

    sift = cv2.SIFT_create()

    def detect(img, valid):
        u8 = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
        return sift.detectAndCompute(u8, valid.astype(np.uint8) * 255)

    ka, da = detect(a, a_valid)
    kb, db = detect(b, b_valid)
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
) -> PairResult:
    """Register frame b to frame a (rectified, same pixel size) near ``prior_rel``.

    Args:
        a, b: frames in grey levels (float32) with their masks a_valid, b_valid; or
            :class:`PreparedFrame` objects (masks then None), to prepare each frame once
            when it takes part in many pairs.
        prior_rel: prior pose of b in a's frame (metres, radians).
        radius_px: search radius for the translation (the prior's uncertainty), pixels.
        heading_sigma_rad: the prior's heading uncertainty (radians); with ``radius_px``
            it selects the feature path when correlation would not converge.
    """
    fa = a if isinstance(a, PreparedFrame) else PreparedFrame(a, a_valid, p.fine_smoothing_px)
    fb = b if isinstance(b, PreparedFrame) else PreparedFrame(b, b_valid, p.fine_smoothing_px)
    a, a_valid, b, b_valid = fa.raw, fa.valid, fb.raw, fb.valid
    b_to_a = frame_to_frame_affine(prior_rel, b.shape, a.shape, pixel_size)
    a_to_b = _invert(b_to_a)
    method, inliers = "correlation", 0
    if radius_px > p.feature_radius_px or heading_sigma_rad > p.feature_rotation_rad:
        res = _features(a, a_valid, b, b_valid, p)
        if isinstance(res, str):
            return PairResult(False, res, method="features")
        a_to_b, inliers = res
        # The feature estimate must agree with the prior within its uncertainty.
        jump = np.hypot(*(_invert(a_to_b) @ [*frame_centre(b.shape), 1.0] - b_to_a @ [*frame_centre(b.shape), 1.0]))
        if jump > 3.0 * radius_px + 5.0:
            return PairResult(False, f"feature path: match {jump:.0f} px from the prior (radius {radius_px:.0f} px)", method="features")
        method, radius_px = "features", 3.0
    bvw = _warp(b_valid.astype(np.uint8), a_to_b, a.shape, cv2.INTER_NEAREST) > 0
    overlap_mask = bvw & a_valid
    overlap = float(overlap_mask.sum()) / max(float(a_valid.sum()), 1.0)
    if overlap < p.min_overlap_fraction:
        return PairResult(False, f"small overlap: {overlap:.0%} at the prior (min {p.min_overlap_fraction:.0%})", overlap=overlap, method=method)
    coarse = _coarse(a, b, a_to_b, overlap_mask, radius_px, p)
    if coarse is None:
        return PairResult(False, "overlap too narrow: no template fits with the search window", overlap=overlap, method=method)
    a_to_b, c1, uniq = coarse
    fine = _refine(fa, fb, a_to_b, p)
    if isinstance(fine, str):
        return PairResult(False, fine, overlap=overlap, uniqueness=uniq, method=method)
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
        return PairResult(True, "", rel, cov, ncc, uniq, overlap, n, iters, method, inliers, gain)
    # Similarity: a log-scale perturbation about `centre` also moves b's centre radially.
    g4 = np.zeros((4, 4))
    g4[:3, :3] = g
    g4[:2, 3] = pc[:2] - centre
    g4[3, 3] = 1.0
    jm = np.diag([pixel_size, -pixel_size, -1.0, 1.0]) @ g4
    cov4 = jm @ cov_px @ jm.T
    log_scale = 0.5 * float(np.log(abs(np.linalg.det(b_to_a[:, :2]))))
    return PairResult(True, "", rel, cov4[:3, :3].copy(), ncc, uniq, overlap, n, iters, method, inliers, gain,
                      log_scale, cov4)
