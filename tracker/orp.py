"""Omnidirectional route panoramas (ORP, Yagi et al. (2005)) and the ORP localizer (view synthesis, eq. 5).

Vehicle side: numpy and OpenCV only (plus :mod:`mapstore.grid` and :mod:`tracker.omnicam`).

Frames and units
    World frame of :mod:`mapstore.grid`: x, y metres, theta radians counter-clockwise from +x.
    *Azimuth* (radians) as in :mod:`tracker.omnicam`: camera azimuth 0 = vehicle +x, counter-
    clockwise; a *horizon line* has ``360 * samples_per_degree`` samples, sample ``j`` at camera
    azimuth ``j / samples_per_degree`` degrees; values are grey levels (0..255).
    *Path length* ``s`` (metres) along the memorized route.

ORP (Yagi et al. (2005), section 2.2)
    Each frame of a memorized run is unwarped to its horizon line (the panorama at elevation 0,
    rows within ``horizon_band_deg`` averaged, azimuths box-filtered from an ``oversample``-times
    finer remap so that 1 sample/degree does not alias) and the lines are stacked along the
    route, resampled to a fixed spacing ``spacing_m`` along the path: an ``(M, A)`` uint8 image
    plus the route pose ``(x, y, theta)`` of every row. The route poses are, for now, the
    memorized run's ground truth (the build will supply the optimized poses).

Localization by synthesis (Yagi et al. (2005), section 3, eq. 5)
    A scene point seen from a candidate pose ``P`` at world bearing ``beta`` lies on the line
    through ``P`` of direction ``beta``; any route point ``R(s)`` on that line saw it at the same
    world bearing, i.e. at camera azimuth ``beta - theta(s)`` (at the horizon, elevation 0, the
    same point whatever the distance along the line). The synthesized line at ``P`` takes, for
    every azimuth, the ORP at the route's crossing ``s`` of that line (Newton on
    ``(R(s) - P) . n(beta) = 0`` from ``P``'s projection, within ``window_m`` of it; azimuths
    whose line runs within ``min_crossing_deg`` of the route tangent, or crosses outside the
    window, are left out). The pose maximizing the normalized correlation between the observed
    and the synthesized line is found by Gauss-Newton over ``(x, y, theta)`` plus a gain and
    offset (maximizing NCC), coarse to fine over Gaussian-smoothed lines, with an analytic
    Jacobian (the ORP's gradients along ``s`` and azimuth chained through the crossing
    geometry). This replaces the seed's dual active contours (a deformable search for the same
    tangent curve): measured in ``bench/bench_orp.py``.

Motion-compensated row interpolation (``interp_flow``)
    Between two rows the scene moves along azimuth (parallax of near walls and objects, the
    heading change), so at 10 cm spacing a linear blend of the rows ghosts. When it loads the
    ORP, the localizer estimates from the stored rows alone (:func:`estimate_row_flow`, 1-D
    Lucas-Kanade coarse to fine, over ``flow_baseline_m``) the displacement ``d(i, c)`` of each
    column from row ``i`` to ``i + 1``, and synthesizes a fractional row ``i + f`` from row
    ``i`` at ``c - f d`` and row ``i + 1`` at ``c + (1 - f) d``, blended; its row derivative
    (for the Jacobian) is the rows' motion-compensated central derivative, interpolated.

Masking (Yagi et al. (2005), section 5.4)
    Before each coarse-to-fine level and once after the last fit, the lines are compared per
    azimuth sector (``mask_sector_deg``) at the current pose: sectors whose NCC falls below
    ``mask_min_ncc`` (moved objects, occlusions, windows dark at night) are dropped (at most
    ``mask_max_fraction`` of them, the worst), and the pose is (re)fitted from the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import cv2
import numpy as np

from mapstore.grid import se2_interpolate, wrap_angle
from mapstore.knobs import knob
from tracker.omnicam import OmniCamera, panorama_unwarp
from tracker.params import params_from_dict

__all__ = [
    "ORPParams",
    "HorizonSampler",
    "ORP",
    "path_length",
    "build_orp",
    "orp_from_frames",
    "prepare_lines",
    "estimate_row_flow",
    "ORPFix",
    "ORPLocalizer",
]

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class ORPParams:
    """ORP construction and localizer settings (``[tracker.orp]`` of configs/tracker.toml)."""

    # -- construction --
    samples_per_degree: float = knob(gt=0.0, default=1.0)
    horizon_band_deg: float = knob(ge=0.0, default=1.0)
    oversample: int = knob(ge=1, default=3)
    spacing_m: float = knob(gt=0.0, default=0.02)
    # -- localizer --
    window_m: float = knob(gt=0.0, default=1.0)
    min_crossing_deg: float = knob(ge=0.0, le=90.0, default=10.0)
    highpass_deg: float = knob(ge=0.0, default=2.0)
    normalize_deg: float = knob(ge=0.0, default=2.0)
    smoothing_deg: tuple[float, ...] = knob(ge=0.0, default=(4.0, 2.0, 1.0))
    iterations: tuple[int, ...] = knob(ge=0, default=(6, 4, 4))
    min_valid_fraction: float = knob(ge=0.0, le=1.0, default=0.3)
    min_ncc: float = knob(ge=-1.0, le=1.0, default=0.5)
    # -- masking --
    masking: bool = knob(default=True)
    mask_sector_deg: float = knob(gt=0.0, le=360.0, default=15.0)
    mask_min_ncc: float = knob(ge=-1.0, le=1.0, default=0.8)
    mask_max_fraction: float = knob(ge=0.0, le=1.0, default=0.5)
    mask_margin: float = knob(ge=0.0, default=0.15)
    # -- motion-compensated row interpolation --
    interp_flow: bool = knob(default=True)
    flow_smoothing_deg: tuple[float, ...] = knob(ge=0.0, default=(4.0, 2.0, 1.0))
    flow_iterations: int = knob(ge=1, default=3)
    flow_window_deg: float = knob(gt=0.0, default=5.0)
    flow_regularization: float = knob(gt=0.0, default=0.05)
    flow_max_deg: float = knob(gt=0.0, default=20.0)
    flow_baseline_m: float = knob(gt=0.0, default=0.10)

    @classmethod
    def from_dict(cls, d: dict) -> "ORPParams":
        """From a ``[tracker.orp]`` table; an unknown key, a wrong type or a value out of range
        raises ValueError (:class:`mapstore.knobs.ConfigError`)."""
        return params_from_dict(cls, d, "tracker.orp")

    def __post_init__(self) -> None:
        if self.samples_per_degree <= 0 or self.spacing_m <= 0 or self.window_m <= 0:
            raise ValueError("samples_per_degree, spacing_m and window_m must be positive")
        if int(self.oversample) < 1 or int(self.oversample) % 2 == 0:
            raise ValueError(f"oversample must be an odd integer >= 1, got {self.oversample}")
        if len(self.smoothing_deg) != len(self.iterations) or not self.smoothing_deg:
            raise ValueError("smoothing_deg and iterations must have the same (non-zero) length")
        if not self.flow_smoothing_deg or int(self.flow_iterations) < 1 or self.flow_window_deg <= 0:
            raise ValueError("flow_smoothing_deg must be non-empty, flow_iterations >= 1, flow_window_deg > 0")
        if not (self.flow_regularization > 0 and self.flow_max_deg > 0 and self.flow_baseline_m > 0):
            # a zero regularization divides 0 by 0 on a flat window (a NaN flow)
            raise ValueError("flow_regularization, flow_max_deg and flow_baseline_m must be positive")


# --- horizon lines ---------------------------------------------------------------------------


class HorizonSampler:
    """Unwarps omni frames to horizon lines (Yagi et al.'s (2005) horizontal line, Fig. 3a).

    A panorama remap (:func:`tracker.omnicam.panorama_unwarp`) at ``samples_per_degree x
    oversample`` samples per degree over elevations ``[-horizon_band_deg, +horizon_band_deg]``;
    :meth:`line` averages the valid rows and box-filters ``oversample`` neighbouring azimuths
    (centred on each output azimuth) into one sample: an anti-aliased ``(A,)`` float32 line,
    ``A = 360 x samples_per_degree``, grey levels.
    """

    def __init__(self, camera: OmniCamera, samples_per_degree: float = 1.0, horizon_band_deg: float = 1.0,
                 oversample: int = 3):
        self.samples_per_degree = float(samples_per_degree)
        self.oversample = int(oversample)
        fine = self.samples_per_degree * self.oversample
        band = max(float(horizon_band_deg), 0.0)
        self.panorama = panorama_unwarp(camera, samples_per_degree=fine, elevation_range_deg=(-band, band))
        self.n_azimuths = int(round(360.0 * self.samples_per_degree))
        if self.panorama.unwarp.shape[1] != self.n_azimuths * self.oversample:
            raise ValueError("samples_per_degree x 360 must be an integer")
        valid = self.panorama.unwarp.valid.astype(np.float32)
        self._row_w = valid / np.maximum(valid.sum(0, keepdims=True), 1.0)
        self.valid = self._pool(valid.max(0)) > 0.999

    def _pool(self, fine: np.ndarray) -> np.ndarray:
        half = self.oversample // 2
        return np.roll(fine, half, axis=-1).reshape(*fine.shape[:-1], self.n_azimuths, self.oversample).mean(-1)

    def line(self, image: np.ndarray) -> np.ndarray:
        """The horizon line ``(A,)`` float32 (grey levels) of one omni frame (any dtype)."""
        strip = self.panorama.apply(image).astype(np.float32)
        return self._pool((strip * self._row_w).sum(0)).astype(np.float32)

    def lines(self, images: Iterable[np.ndarray]) -> np.ndarray:
        """Horizon lines ``(N, A)`` float32 of a sequence of frames."""
        return np.stack([self.line(im) for im in images])


# --- the ORP -------------------------------------------------------------------------------


@dataclass
class ORP:
    """An omnidirectional route panorama.

    Attributes:
        lines: ``(M, A)`` uint8 horizon lines (grey levels), row ``i`` at path length
            ``s0 + i * spacing_m``; column ``j`` at camera azimuth ``j / samples_per_degree`` deg.
        poses: ``(M, 3)`` float32 route poses ``x, y, theta`` (metres, radians, world frame).
        s0: path length of row 0 (metres); spacing_m: row spacing along the path (metres).
        samples_per_degree: azimuth samples per degree.
        horizon_band_deg: elevation band (degrees) averaged into each line (what the live
            frames' :class:`HorizonSampler` must use).
    """

    lines: np.ndarray
    poses: np.ndarray
    s0: float
    spacing_m: float
    samples_per_degree: float
    meta: dict = field(default_factory=dict)
    horizon_band_deg: float = 1.0

    @classmethod
    def from_record(cls, record) -> "ORP":
        """The ORP of a stored route (a :class:`mapstore.routes.RouteRecord`: uint8 lines
        ``(M, A)``, float32 poses ``(M, 3)`` world frame, ``s0_m``, ``spacing_m`` metres,
        ``samples_per_degree``, ``horizon_band_deg``). ``meta`` keeps the record's meta plus
        its ``version`` and ``sources``."""
        lines = np.ascontiguousarray(record.lines, np.uint8)
        poses = np.asarray(record.poses, np.float32).reshape(-1, 3)
        if lines.ndim != 2 or len(lines) != len(poses) or len(lines) < 2:
            raise ValueError(f"a route needs at least 2 rows of lines (M, A) and poses (M, 3), got "
                             f"{lines.shape} and {poses.shape}")
        meta = dict(record.meta)
        meta.update({"version": int(record.version), "sources": list(record.sources)})
        return cls(lines, poses, float(record.s0_m), float(record.spacing_m), float(record.samples_per_degree),
                   meta, float(record.horizon_band_deg))

    @property
    def s(self) -> np.ndarray:
        """``(M,)`` path length of each row (metres)."""
        return self.s0 + self.spacing_m * np.arange(len(self.lines))

    @property
    def length_m(self) -> float:
        return self.spacing_m * max(len(self.lines) - 1, 0)

    @property
    def nbytes(self) -> int:
        """Stored bytes (uncompressed): the uint8 lines plus float32 poses."""
        return int(self.lines.nbytes + self.poses.astype(np.float32).nbytes)

    def bytes_per_km(self) -> float:
        """Storage per kilometre of route (bytes): ``nbytes / length``."""
        return self.nbytes / max(self.length_m, 1e-9) * 1000.0


def path_length(poses: np.ndarray) -> np.ndarray:
    """Cumulative path length (metres) of poses ``(N, 3)`` (or positions ``(N, 2)``), 0 first."""
    xy = np.asarray(poses, float)[:, :2]
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])


def build_orp(lines: np.ndarray, poses: np.ndarray, spacing_m: float, samples_per_degree: float) -> ORP:
    """Stack horizon lines ``(N, A)`` taken at route poses ``(N, 3)`` into an ORP.

    Rows are resampled at a fixed ``spacing_m`` (metres) along the cumulative path length:
    lines linearly between the two frames around each row, poses by SE(2) geodesic
    interpolation (:func:`mapstore.grid.se2_interpolate`). Frames that did not move are merged
    (their lines averaged).
    """
    lines = np.asarray(lines, np.float32)
    poses = np.asarray(poses, float)
    if lines.ndim != 2 or len(lines) != len(poses) or len(lines) < 2:
        raise ValueError("need at least 2 lines (N, A) with N poses (N, 3)")
    s = path_length(poses)
    keep = np.concatenate([[True], np.diff(s) > 1e-6])
    if not keep.all():  # stationary frames: average their lines into the first of each run
        grp = np.cumsum(keep) - 1
        cnt = np.bincount(grp).astype(np.float32)
        acc = np.zeros((int(grp[-1]) + 1, lines.shape[1]), np.float32)
        np.add.at(acc, grp, lines)
        lines, poses, s = acc / cnt[:, None], poses[keep], s[keep]
    m = int(math.floor(s[-1] / spacing_m + 1e-9)) + 1
    sg = np.arange(m) * spacing_m
    i = np.clip(np.searchsorted(s, sg, side="right") - 1, 0, len(s) - 2)
    f = np.clip((sg - s[i]) / (s[i + 1] - s[i]), 0.0, 1.0)
    out = lines[i] * (1.0 - f[:, None]).astype(np.float32) + lines[i + 1] * f[:, None].astype(np.float32)
    p = se2_interpolate(poses[i], poses[i + 1], f)
    return ORP(np.clip(np.rint(out), 0, 255).astype(np.uint8), p.astype(np.float32), 0.0, float(spacing_m),
               float(samples_per_degree))


def orp_from_frames(images: Iterable[np.ndarray], poses: np.ndarray, camera: OmniCamera,
                    params: ORPParams = ORPParams()) -> ORP:
    """An ORP from a memorized run's omni frames and their route poses ``(N, 3)`` (world frame)."""
    hs = HorizonSampler(camera, params.samples_per_degree, params.horizon_band_deg, params.oversample)
    orp = build_orp(hs.lines(images), poses, params.spacing_m, params.samples_per_degree)
    orp.horizon_band_deg = float(params.horizon_band_deg)
    return orp


# --- line preprocessing --------------------------------------------------------------------


def _gauss_circular(a: np.ndarray, sigma_samples: float) -> np.ndarray:
    """Gaussian smoothing along the last axis (circular), float32."""
    a = np.ascontiguousarray(a, np.float32)
    if sigma_samples <= 0.05:
        return a
    r = int(math.ceil(3.0 * sigma_samples))
    k = cv2.getGaussianKernel(2 * r + 1, sigma_samples).astype(np.float32)
    a2 = np.atleast_2d(a)
    pad = np.concatenate([a2[:, -r:], a2, a2[:, :r]], axis=1) if r <= a2.shape[1] else np.pad(a2, ((0, 0), (r, r)), mode="wrap")
    out = cv2.sepFilter2D(pad, cv2.CV_32F, k, np.ones((1, 1), np.float32), borderType=cv2.BORDER_REFLECT)[:, r:-r]
    return out.reshape(a.shape)


def prepare_lines(lines: np.ndarray, highpass_samples: float, smooth_samples: float,
                  normalize_samples: float = 0.0) -> np.ndarray:
    """What the localizer correlates (float32, same shape): log intensity (illumination is
    multiplicative), minus its Gaussian of ``highpass`` samples, divided by its local RMS over
    a Gaussian of ``normalize`` samples (local contrast; 0 = not), smoothed by ``smooth``."""
    a = np.log1p(np.asarray(lines, np.float32))
    if highpass_samples > 0:
        a = a - _gauss_circular(a, highpass_samples)
    if normalize_samples > 0:
        a = a / np.sqrt(_gauss_circular(a * a, normalize_samples) + np.float32(1e-4))
    return _gauss_circular(a, smooth_samples)


def _sample_rows(padded: np.ndarray, rows: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Rows ``rows (K,)`` of an image ``(M, A, C)`` float32 sampled at fractional columns
    ``pos (K, A)`` (samples, circular), linear in the column (OpenCV remap: positions to 1/32
    sample). ``padded``: the image with its last column before column 0 and its first two
    after column ``A - 1`` (``(M, A + 3, C)``).

    Returns ``(K, A, C)`` float32."""
    a, ch = padded.shape[1] - 3, padded.shape[2]
    mx = np.mod(pos, np.float32(a)).astype(np.float32)
    mx += np.float32(1.0)
    my = np.broadcast_to(np.asarray(rows, np.float32)[:, None], mx.shape)
    out = np.empty((len(rows), a, ch), np.float32)
    step = 16384  # remap's maps and source stay below SHRT_MAX rows
    for k0 in range(0, len(rows), step):
        k1 = min(k0 + step, len(rows))
        r_lo = int(rows[k0:k1].min())
        r_hi = int(rows[k0:k1].max()) + 1
        res = cv2.remap(padded[r_lo:r_hi], mx[k0:k1], np.ascontiguousarray(my[k0:k1] - np.float32(r_lo)),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out[k0:k1] = res.reshape(k1 - k0, a, ch)
    return out


def estimate_row_flow(lines: np.ndarray, highpass_samples: float, normalize_samples: float,
                      smoothing_samples: Iterable[float], iterations: int = 3, window_samples: float = 3.0,
                      regularization: float = 0.05, max_flow: float = 20.0,
                      initial: np.ndarray | None = None, baseline_rows: int = 1) -> np.ndarray:
    """Azimuthal displacement between adjacent rows of a route panorama (motion compensation).

    For each row pair ``(i, i + 1)`` of ``lines (M, A)`` (grey levels) and each column ``c``
    (samples), ``d[i, c]`` (samples of azimuth) such that the scene seen at column
    ``c - d / 2`` in row ``i`` is seen at ``c + d / 2`` in row ``i + 1`` (the pattern moves by
    ``d`` from one row to the next: parallax, which depends on each column's depth, plus the
    heading change). Symmetric 1-D Lucas-Kanade, vectorized over all pairs: on the prepared
    lines (:func:`prepare_lines` with ``highpass`` / ``normalize`` samples) smoothed by each of
    ``smoothing_samples`` in turn (coarse to fine), ``iterations`` updates per scale, each
    ``d -= G(g e) / (G(g g) + lambda)`` with ``e`` the difference of the two warped rows, ``g``
    their mean azimuthal gradient, ``G`` a Gaussian of ``window_samples`` (circular) and
    ``lambda = regularization x mean(G(g g))`` (textureless columns keep their start);
    ``|d - initial|`` is clipped to ``max_flow``. ``initial``: ``(M - 1,)`` or ``(M - 1, A)``
    starting displacement (e.g. minus the heading change, in samples), default 0.

    ``baseline_rows`` ``K > 1`` (rows closer than the parallax the uint8 rows resolve): the
    displacement is estimated between rows ``i`` and ``i + K`` (starting from the sum of the
    ``K`` initial steps), and each adjacent pair gets the mean over the ``K``-row windows that
    contain it of (window displacement - its initial) / K, plus its own initial step (parallax
    grows linearly with the distance driven; the wide baseline averages the noise down).
    Last, per pair and column, the displacement is replaced by ``initial`` or by 0 (a linear
    blend) where one of those leaves a smaller Gaussian-windowed squared difference between
    the two warped rows (walls a few centimetres away, occlusions: parallax no shift models).

    Returns ``(M - 1, A)`` float32 (samples).
    """
    lines = np.asarray(lines)
    m, a = lines.shape
    if m < 2:
        return np.zeros((0, a), np.float32)
    step0 = np.zeros((m - 1, a), np.float32)
    if initial is not None:
        ini = np.asarray(initial, np.float32)
        step0 += ini[:, None] if ini.ndim == 1 else ini
    k = int(min(max(int(baseline_rows), 1), m - 1))
    cum = np.concatenate([np.zeros((1, a), np.float64), np.cumsum(step0, 0, dtype=np.float64)])
    d0 = (cum[k:] - cum[:-k]).astype(np.float32)  # (M - K, A): initial over K rows
    d = d0.copy()
    cols = np.arange(a, dtype=np.float32)[None, :]
    rows0 = np.arange(m - k)
    for sg in smoothing_samples:
        img = prepare_lines(lines, highpass_samples, float(sg), normalize_samples)
        grad = (np.roll(img, -1, 1) - np.roll(img, 1, 1)) * np.float32(0.5)
        both = np.stack([img, grad], axis=-1)  # (M, A, 2): value, slope; padded for _sample_rows
        both = np.ascontiguousarray(np.concatenate([both[:, -1:], both, both[:, :2]], axis=1))
        lam = None
        for _ in range(int(iterations)):
            s0 = _sample_rows(both, rows0, cols - 0.5 * d)
            s1 = _sample_rows(both, rows0 + k, cols + 0.5 * d)
            e = s1[..., 0] - s0[..., 0]
            g = np.float32(0.5) * (s0[..., 1] + s1[..., 1])
            den = _gauss_circular(g * g, window_samples)
            if lam is None:
                lam = np.float32(regularization * max(float(den.mean()), 1e-12))
            d = d - _gauss_circular(g * e, window_samples) / (den + lam)
            d = np.clip(d, d0 - max_flow * k, d0 + max_flow * k).astype(np.float32)
    if k > 1:  # pair i lies in the windows j = i - K + 1 .. i (those that exist)
        res = np.concatenate([np.zeros((1, a), np.float64), np.cumsum(d - d0, 0, dtype=np.float64)])
        i = np.arange(m - 1)
        lo, hi = np.maximum(i - k + 1, 0), np.minimum(i, m - 1 - k) + 1
        d = (step0 + (res[hi] - res[lo]) / (hi - lo)[:, None] / k).astype(np.float32)
    # unreliable where it does not beat the simpler models: per pair and column the
    # displacement, the initial step or 0 (the linear blend), whichever leaves the smallest
    # windowed difference between the two warped rows (at the finest scale)
    rows = np.arange(m - 1)
    err = []
    for cand in (d, step0, np.zeros_like(d)):
        e = (_sample_rows(both, rows + 1, cols + 0.5 * cand)[..., 0] - _sample_rows(both, rows, cols - 0.5 * cand)[..., 0])
        err.append(_gauss_circular(e * e, window_samples))
    best = np.argmin(np.stack(err), axis=0)
    return np.where(best == 0, d, np.where(best == 1, step0, np.float32(0.0))).astype(np.float32)


def _sample_columns(tab: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """A table ``(M, A + 1, C)`` (the first column repeated at the end) at ``rows`` (int) and
    fractional ``cols`` in ``[0, A)`` (samples), linear in the column: ``(K, C)``. (Cubic,
    Catmull-Rom sampling synthesized the analytic room's lines closer but localized the
    simulated runs worse: 0.13 / 0.52 cm on the path / moved objects at 10 cm, against
    0.10 / 0.38.)"""
    j = np.minimum(cols.astype(np.intp), tab.shape[1] - 2)
    t = (cols - j)[:, None]
    p0 = tab[rows, j]
    return p0 + t * (tab[rows, j + 1] - p0)


def _flow_row_derivative(img: np.ndarray, slope: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """d/drow of the motion-compensated interpolation at the rows themselves, ``(M, A)``: the
    mean of the derivatives of the cells on either side (one-sided at the ends). ``img``,
    ``slope`` ``(M, A)``: a level's values and d/dcolumn; ``flow`` ``(M - 1, A)`` (samples).
    Leaving row ``i`` forward: ``L[i+1](c + d) - L[i](c) - d L'[i](c)``; arriving from row
    ``i - 1``: ``L[i](c) - L[i-1](c - d) - d L'[i](c)`` (with that cell's ``d``). Interpolated
    between rows, it gives Gauss-Newton a slope without the jump a cell's own difference has
    at every row (which biased fits from an offset prior by ~0.7 mm at 2 cm spacing)."""
    m, a = img.shape
    padded = np.concatenate([img[:, -1:], img, img[:, :2]], axis=1)[..., None].astype(np.float32)
    cols = np.arange(a, dtype=np.float32)[None, :]
    rows = np.arange(m - 1)
    ahead = _sample_rows(padded, rows + 1, cols + flow)[..., 0]
    behind = _sample_rows(padded, rows, cols - flow)[..., 0]
    fwd = ahead - img[:-1] - flow * slope[:-1]
    bwd = img[1:] - behind - flow * slope[1:]
    out = np.zeros((m, a), np.float32)
    out[:-1] += fwd
    out[1:] += bwd
    out[1:-1] *= np.float32(0.5)
    return out


# --- the localizer -------------------------------------------------------------------------


@dataclass
class ORPFix:
    """One localization result.

    Attributes:
        pose: ``(3,)`` estimated ``x, y, theta`` (metres, radians, world frame).
        ok: the fit converged with enough valid azimuths.
        ncc: correlation of the observed and the synthesized line at the pose (finest level).
        valid_fraction: share of azimuths used in the last fit.
        masked_fraction: share of azimuths dropped by masking.
        s: path length (metres) of the pose's projection on the route.
        iterations: Gauss-Newton iterations run.
        mask: ``(A,)`` bool, True for the azimuths masking dropped.
    """

    pose: np.ndarray
    ok: bool
    ncc: float
    valid_fraction: float
    masked_fraction: float
    s: float
    iterations: int
    mask: np.ndarray


class ORPLocalizer:
    """Pose from one horizon line and a prior near the memorized route (see the module docstring)."""

    def __init__(self, orp: ORP, params: ORPParams = ORPParams()):
        self.orp, self.params = orp, params
        self.n_az = orp.lines.shape[1]
        self.spd = orp.samples_per_degree
        self.az = np.arange(self.n_az) * (TWO_PI / self.n_az)  # camera azimuth of each sample
        self.col_per_rad = self.n_az / TWO_PI
        p = orp.poses.astype(np.float64)
        self.xy = p[:, :2]
        self.theta = np.unwrap(p[:, 2])
        d = np.gradient(self.xy, axis=0)
        self.tangent = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        self.dtheta_ds = np.gradient(self.theta) / orp.spacing_m if len(p) > 1 else np.zeros(len(p))
        # route table per row (x, y, tangent x, y, heading, dtheta/ds) and its row-to-row steps:
        # linear interpolation at fractional row r = i + f is geo[i] + f * dgeo[i]
        geo = np.column_stack([self.xy, self.tangent, self.theta, self.dtheta_ds])
        self._geo = np.ascontiguousarray(geo[:-1])
        self._dgeo = np.ascontiguousarray(np.diff(geo, axis=0))
        self._pos = np.ascontiguousarray(geo[:-1, :4])
        self._dpos = np.ascontiguousarray(self._dgeo[:, :4])
        hp = params.highpass_deg * self.spd
        self.levels = []
        for sg in params.smoothing_deg:
            img = prepare_lines(orp.lines, hp, sg * self.spd, params.normalize_deg * self.spd)
            # wrap one column so bilinear sampling at column A-1 + f reaches column 0
            g_c = (np.roll(img, -1, 1) - np.roll(img, 1, 1)) * 0.5
            g_r = np.gradient(img, axis=0) if len(img) > 1 else np.zeros_like(img)
            # (M, A + 1, 3): value, d/drow, d/dcolumn, the first column repeated at the end
            stack = np.stack([img, g_r, g_c], axis=-1)
            self.levels.append(np.ascontiguousarray(np.concatenate([stack, stack[:, :1]], 1)))
        self.min_cross = math.sin(math.radians(params.min_crossing_deg))
        # motion-compensated interpolation between rows: per row pair and column, the azimuthal
        # displacement (samples) of the scene from row i to row i + 1 (started from the heading
        # change); None = linear blend of the rows
        self.flow = None
        if params.interp_flow and len(orp.lines) >= 2:
            d0 = -np.diff(self.theta) * self.col_per_rad
            fl = estimate_row_flow(orp.lines, hp, params.normalize_deg * self.spd,
                                   [sg * self.spd for sg in params.flow_smoothing_deg], params.flow_iterations,
                                   params.flow_window_deg * self.spd, params.flow_regularization,
                                   params.flow_max_deg * self.spd, d0,
                                   max(1, int(round(params.flow_baseline_m / orp.spacing_m))))
            fl = np.concatenate([fl, fl[:, :1]], 1).astype(np.float64)
            # (M - 1, A, 2): displacement at each column, its step to the next column
            self.flow = np.ascontiguousarray(np.stack([fl[:, :-1], np.diff(fl, axis=1)], -1), np.float32)
            # per level (M, A + 1, 3): value, d/dcolumn, d/drow (motion compensated at the rows)
            self.levels_vc = []
            for t in self.levels:
                dr = _flow_row_derivative(t[:, :-1, 0], t[:, :-1, 2], fl[:, :-1].astype(np.float32))
                tv = np.stack([t[:, :-1, 0], t[:, :-1, 2], dr], axis=-1)
                self.levels_vc.append(np.ascontiguousarray(np.concatenate([tv, tv[:, :1]], 1)))

    # -- route geometry ---------------------------------------------------------------------
    def project(self, xy: np.ndarray, r_lo: float = 0.0, r_hi: float | None = None) -> float:
        """Path length (metres) of the route point nearest to ``xy`` (metres), among rows
        ``[r_lo, r_hi]`` (default: all)."""
        lo = max(0, int(math.floor(r_lo)))
        hi = len(self.xy) if r_hi is None else min(len(self.xy), int(math.ceil(r_hi)) + 1)
        q = np.asarray(xy, float)[:2]
        i = lo + int(np.argmin(np.sum((self.xy[lo:hi] - q) ** 2, axis=1)))
        ds = float(np.dot(q - self.xy[i], self.tangent[i]))
        return self.orp.s0 + float(np.clip(i * self.orp.spacing_m + ds, 0.0, self.orp.length_m))

    def _lerp(self, r: np.ndarray, tab: np.ndarray, dtab: np.ndarray) -> np.ndarray:
        """Rows of ``tab`` linearly interpolated at fractional rows ``r`` (clamped to the route)."""
        i = np.minimum(np.maximum(r.astype(np.intp), 0), len(tab) - 1)
        f = (r - i)[:, None]
        return tab[i] + f * dtab[i]

    def crossings(self, pose: np.ndarray, r_lo: float, r_hi: float, newton: int = 3):
        """For each azimuth, the route row where the line through ``pose`` at that world bearing
        crosses the route (eq. 5), within rows ``[r_lo, r_hi]``.

        Returns ``(r, valid, dr_dpose (A, 3) rows per unit, theta(s), dtheta/ds, beta)``.
        """
        x, y, th = float(pose[0]), float(pose[1]), float(pose[2])
        beta = th + self.az
        cb, sb = np.cos(beta), np.sin(beta)
        nx, ny = -sb, cb
        h = self.orp.spacing_m
        r = np.full(self.n_az, (self.project((x, y), r_lo, r_hi) - self.orp.s0) / h)
        lo, hi = r_lo - 1.0, r_hi + 1.0
        for _ in range(newton):  # Newton on g(s) = (R(s) - P) . n(beta) = 0
            q = self._lerp(r, self._pos, self._dpos)
            g = (q[:, 0] - x) * nx + (q[:, 1] - y) * ny
            gs = q[:, 2] * nx + q[:, 3] * ny
            gs = np.where(np.abs(gs) < 1e-6, 1e-6, gs)
            r = np.minimum(np.maximum(r - g / (gs * h), lo), hi)
        q = self._lerp(r, self._geo, self._dgeo)
        gs = q[:, 2] * nx + q[:, 3] * ny
        g = (q[:, 0] - x) * nx + (q[:, 1] - y) * ny
        valid = (np.abs(gs) >= self.min_cross) & (r >= r_lo) & (r <= r_hi) & (np.abs(g) < 0.25 * h)
        gs = np.where(np.abs(gs) < 1e-6, 1e-6, gs) * h
        # ds/dx = n_x / gs, ds/dy = n_y / gs, ds/dtheta = ((R - P) . u) / gs   (rows per unit)
        dr = np.empty((self.n_az, 3))
        dr[:, 0] = nx / gs
        dr[:, 1] = ny / gs
        dr[:, 2] = ((q[:, 0] - x) * cb + (q[:, 1] - y) * sb) / gs
        return r, valid, dr, q[:, 4], q[:, 5], beta

    def synthesize(self, pose: np.ndarray, level: int, r_lo: float, r_hi: float):
        """The synthesized (prepared) line at ``pose`` and its Jacobian ``(A, 3)`` w.r.t. the pose."""
        tab = self.levels[level]
        r, valid, dr, th_r, k, beta = self.crossings(pose, r_lo, r_hi)
        c = np.mod((beta - th_r) * self.col_per_rad, self.n_az)
        if self.flow is not None:
            v, vr, vc = self._sample_flow(level, r, c)
        else:
            v, vr, vc = self._sample_linear(tab, r, c)
        # d v = vr dr + vc dc, dc = (dbeta - theta'(s) ds) col_per_rad, dbeta = dtheta_pose
        along = vr - vc * k * self.orp.spacing_m * self.col_per_rad  # per row of dr
        jac = along[:, None] * dr
        jac[:, 2] += vc * self.col_per_rad
        return v, jac, valid

    def _sample_linear(self, tab: np.ndarray, r: np.ndarray, c: np.ndarray):
        """Value, d/drow, d/dcolumn of a level at rows ``r``, columns ``c`` (samples): bilinear
        (rows blended linearly: the interpolation without motion compensation)."""
        m = len(tab)
        rr = np.minimum(np.maximum(r, 0.0), m - 1.000001)
        i0 = rr.astype(np.intp)
        j0 = np.minimum(c.astype(np.intp), self.n_az - 1)
        fr, fc = (rr - i0)[:, None], (c - j0)[:, None]
        i1 = np.minimum(i0 + 1, m - 1)
        top = tab[i0, j0] * (1 - fc) + tab[i0, j0 + 1] * fc
        bot = tab[i1, j0] * (1 - fc) + tab[i1, j0 + 1] * fc
        smp = top + (bot - top) * fr
        return smp[:, 0], smp[:, 1], smp[:, 2]

    def _sample_flow(self, level: int, r: np.ndarray, c: np.ndarray):
        """Value, d/drow, d/dcolumn of a level at rows ``r``, columns ``c`` (samples), motion
        compensated: in the cell ``r = i + f``, with ``d`` the row pair's displacement at ``c``,
        row ``i`` is sampled at ``c - f d``, row ``i + 1`` at ``c + (1 - f) d``, blended
        ``(1 - f) a + f b``; d/drow interpolated likewise between the rows' own (motion
        compensated, central: :func:`_flow_row_derivative`); d/dcolumn ``(1 - f) a' + f b'``
        plus the flow's slope term."""
        m, n = len(self.levels_vc[level]), self.n_az
        rr = np.minimum(np.maximum(r, 0.0), m - 1.000001)
        i0 = rr.astype(np.intp)
        f = rr - i0
        jc = np.minimum(c.astype(np.intp), n - 1)
        fl = self.flow[i0, jc]  # (A, 2): displacement at column jc, its step to jc + 1
        dd = fl[:, 1]  # d(flow)/dcolumn
        d = fl[:, 0] + dd * (c - jc)
        fd = f * d
        pos = np.concatenate([c - fd, c - fd + d])
        np.mod(pos, n, out=pos)
        smp = _sample_columns(self.levels_vc[level], np.concatenate([i0, i0 + 1]), pos)
        a, b, ga, gb = smp[:n, 0], smp[n:, 0], smp[:n, 1], smp[n:, 1]
        tab_r = smp[:, 2]
        g1 = (1.0 - f) * ga
        g2 = f * gb
        v = a + f * (b - a)
        vc = g1 + g2 + dd * (g2 * (1.0 - f) - g1 * f)  # the flow's slope stretches each row
        vr = tab_r[:n] * (1.0 - f) + tab_r[n:] * f
        return v, vr, vc

    # -- fitting ----------------------------------------------------------------------------
    def _fit_level(self, obs: np.ndarray, pose: np.ndarray, level: int, weights: np.ndarray, r_lo: float,
                   r_hi: float, iters: int) -> tuple[np.ndarray, int]:
        """Gauss-Newton on ``obs ~ a syn(pose) + b`` over (x, y, theta, a, b)."""
        pose = pose.astype(np.float64).copy()
        n = 0
        for n in range(1, iters + 1):
            v, jac, valid = self.synthesize(pose, level, r_lo, r_hi)
            w = weights * valid
            sw = w.sum()
            if sw < self.params.min_valid_fraction * self.n_az:
                break
            mv = (w * v).sum() / sw
            mo = (w * obs).sum() / sw
            cov = (w * (v - mv) * (obs - mo)).sum()
            var = max((w * (v - mv) ** 2).sum(), 1e-12)
            a = cov / var
            b = mo - a * mv
            res = obs - (a * v + b)
            J = np.empty((self.n_az, 5))
            J[:, :3] = a * jac
            J[:, 3] = v
            J[:, 4] = 1.0
            Jw = J * w[:, None]
            H = Jw.T @ J
            H[np.diag_indices(3)] *= 1.0 + 1e-6
            try:
                delta = np.linalg.solve(H, Jw.T @ res)
            except np.linalg.LinAlgError:
                break
            step = delta[:3]
            # trust region: at most 5 cm and 3 degrees per iteration
            scale = min(1.0, 0.05 / max(math.hypot(step[0], step[1]), 1e-12), math.radians(3.0) / max(abs(step[2]), 1e-12))
            pose += scale * step
            if math.hypot(step[0], step[1]) < 1e-5 and abs(step[2]) < 1e-5:
                break
        return pose, n

    def _ncc(self, obs: np.ndarray, v: np.ndarray, w: np.ndarray) -> float:
        sw = w.sum()
        if sw < 3:
            return 0.0
        a = obs - (w * obs).sum() / sw
        b = v - (w * v).sum() / sw
        den = math.sqrt(max((w * a * a).sum() * (w * b * b).sum(), 1e-20))
        return float((w * a * b).sum() / den)

    def sector_ncc(self, obs: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Per sector of ``mask_sector_deg`` (sectors ``(K,)``, the last one takes the remainder):
        NCC of observed vs synthesized (NaN where fewer than half its azimuths are usable)."""
        n = max(1, int(round(self.params.mask_sector_deg * self.spd)))
        k = max(1, self.n_az // n)
        edges = np.minimum(np.arange(k + 1) * n, self.n_az)
        edges[-1] = self.n_az
        sec = np.repeat(np.arange(k), np.diff(edges))

        def ssum(a: np.ndarray) -> np.ndarray:
            return np.bincount(sec, a, minlength=k)

        sw = ssum(w)
        with np.errstate(invalid="ignore", divide="ignore"):
            mo, mv = ssum(w * obs) / sw, ssum(w * v) / sw
            a, b = obs - mo[sec], v - mv[sec]
            out = ssum(w * a * b) / np.sqrt(np.maximum(ssum(w * a * a) * ssum(w * b * b), 1e-20))
        out[sw < 0.5 * np.diff(edges)] = np.nan
        return out

    def sector_mask(self, obs: np.ndarray, pose: np.ndarray, level: int, r_lo: float, r_hi: float,
                    relative: bool = True) -> np.ndarray:
        """Per-azimuth weights (0 or 1): sectors whose NCC at ``pose`` is below ``mask_min_ncc``
        (``relative``: below ``min(mask_min_ncc, median - mask_margin)``) are 0; at most
        ``mask_max_fraction`` of the scored sectors (the worst) are dropped."""
        p = self.params
        v, _, valid = self.synthesize(pose, level, r_lo, r_hi)
        sec = self.sector_ncc(obs, v, valid.astype(np.float64))
        n = max(1, int(round(p.mask_sector_deg * self.spd)))
        scored = np.flatnonzero(np.isfinite(sec))
        # relative to the typical sector: far from the answer every sector correlates poorly,
        # and only the clear outliers go
        thr = p.mask_min_ncc
        if relative and len(scored):
            thr = min(thr, float(np.median(sec[scored])) - p.mask_margin)
        bad = scored[sec[scored] < thr]
        cap = int(math.floor(p.mask_max_fraction * len(scored)))
        if len(bad) > cap:
            bad = bad[np.argsort(sec[bad])[:cap]]
        w = np.ones(self.n_az)
        for i in bad:
            w[i * n : (i + 1) * n if i < len(sec) - 1 else self.n_az] = 0.0
        return w

    def localize(self, line: np.ndarray, prior: np.ndarray, *, masking: bool | None = None) -> ORPFix:
        """Estimate the pose (x, y, theta; metres, radians, world frame) of a horizon line.

        ``line``: ``(A,)`` grey levels (:class:`HorizonSampler`, same samples per degree as the
        ORP); ``prior``: ``(3,)`` pose near the route (a few centimetres, a few degrees).
        """
        p = self.params
        masking = p.masking if masking is None else masking
        if len(line) != self.n_az:
            raise ValueError(f"line has {len(line)} samples, the ORP {self.n_az}")
        hp = p.highpass_deg * self.spd
        obs_levels = [prepare_lines(line, hp, sg * self.spd, p.normalize_deg * self.spd).astype(np.float64)
                      for sg in p.smoothing_deg]
        s_prior = self.project(prior)
        win = p.window_m / self.orp.spacing_m
        r_c = (s_prior - self.orp.s0) / self.orp.spacing_m
        r_lo, r_hi = max(0.0, r_c - win), min(len(self.xy) - 1.0, r_c + win)
        weights = np.ones(self.n_az)
        pose = np.asarray(prior, np.float64).copy()
        total = 0
        last = len(p.iterations) - 1
        # masking at every level: sectors that disagree at the current pose are left out
        # (moved objects, lights switched, windows dark at night); re-decided per level, and
        # once more after the last fit (refit when the mask changed).
        for lev, it in enumerate(p.iterations):
            if masking:
                weights = self.sector_mask(obs_levels[lev], pose, lev, r_lo, r_hi)
            pose, n = self._fit_level(obs_levels[lev], pose, lev, weights, r_lo, r_hi, int(it))
            total += n
        for _ in range(2 if masking else 0):  # at the answer: the absolute threshold
            w2 = self.sector_mask(obs_levels[last], pose, last, r_lo, r_hi, relative=False)
            if np.array_equal(w2, weights):
                break
            weights = w2
            pose, n = self._fit_level(obs_levels[last], pose, last, weights, r_lo, r_hi, int(p.iterations[last]))
            total += n
        masked = float(1.0 - weights.mean())
        v, _, valid = self.synthesize(pose, last, r_lo, r_hi)
        w = weights * valid
        ncc = self._ncc(obs_levels[last], v, w)
        frac = float(w.mean())
        pose[2] = float(wrap_angle(pose[2]))
        ok = frac >= p.min_valid_fraction and ncc >= p.min_ncc
        return ORPFix(pose, bool(ok), ncc, frac, masked, self.project(pose, r_lo, r_hi), total, weights == 0)

