"""The significance a registration's correlation peak needs, from the log's own null pairs.

How high does the phase correlation peak of a pair that does *not* overlap come out? It
depends on the images: noise, texture, shading, sensor patterns. So, as ASHLAR does with its
permutation test, the register stage asks the data: it takes real candidate pairs (a, b)
with their prior relative pose and search radius, replaces b by a frame c far from a (at
least ``far_diagonals`` frame diagonals apart at the prior, so that it cannot overlap),
and runs the coarse stage (:func:`pipeline.coarse.coarse_shift`) on (a, c). The peak
significances ``peak_z`` (peak height over the surface's standard deviation) of these null
pairs describe what "no match" looks like for this log; a link must stand clearly above
them: ``max(min_peak_z, median + k x 1.4826 MAD)`` (a normal tail at k sigma that a few
true matches among the null pairs, e.g. an unexpected revisit, cannot move).

Where the coarse stage had to tell comparable peaks apart by their band-passed NCC (a narrow
strip searched in a wide box, :data:`pipeline.coarse.NCC_PEAK_FRACTION`), the null pairs'
best NCCs give a second threshold the same way (at least ``min_peak_ncc``): a link whose
peak is not significant by its height is still accepted when its NCC clears that one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapstore.grid import frame_to_frame_affine
from pipeline.coarse import CoarseParams, coarse_shift

__all__ = ["NullFigures", "null_pairs", "null_threshold", "null_peak_z"]


@dataclass(frozen=True)
class NullFigures:
    """The null distribution and the threshold taken from it (report section
    ``registration.peak_null``)."""

    pairs: int
    median_z: float
    mad_z: float
    max_z: float
    threshold_z: float
    median_ncc: float = float("nan")
    max_ncc: float = float("nan")
    threshold_ncc: float = 1.0

    def to_dict(self) -> dict:
        return {"pairs": self.pairs, "median_z": round(self.median_z, 2), "mad_z": round(self.mad_z, 2),
                "max_z": round(self.max_z, 2), "threshold_z": round(self.threshold_z, 2),
                "median_ncc": round(self.median_ncc, 3), "max_ncc": round(self.max_ncc, 3),
                "threshold_ncc": round(self.threshold_ncc, 3)}

    def accepts(self, peak_z: float, ncc: float) -> bool:
        """A coarse answer is significant: its peak clears ``threshold_z``, or its
        band-passed NCC (NaN when it was not needed) clears ``threshold_ncc``."""
        return peak_z >= self.threshold_z or (np.isfinite(ncc) and ncc >= self.threshold_ncc)


def _tail(x: np.ndarray, floor: float, k: float) -> tuple[float, float, float, int]:
    """(median, MAD, threshold max(floor, median + k 1.4826 MAD), count) of the finite
    ``x``; the threshold is ``floor`` alone with fewer than 8 values."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) < 8:
        return float("nan"), float("nan"), float(floor), len(x)
    med = float(np.median(x))
    mad = float(np.median(np.abs(x - med)))
    return med, mad, max(float(floor), med + k * 1.4826 * mad), len(x)


def null_threshold(z: np.ndarray, floor: float, k: float, ncc: np.ndarray | None = None,
                   ncc_floor: float = 1.0) -> NullFigures:
    """``max(floor, median + k x 1.4826 MAD)`` of the null pairs' peak significances ``z``
    (``floor`` alone when there are fewer than 8); the same of their band-passed NCCs
    ``ncc`` (NaN where the coarse stage did not need one) with ``ncc_floor``."""
    z = np.asarray(z, float)
    med, mad, thr, n = _tail(z, floor, k)
    zmax = float(np.nanmax(z)) if np.isfinite(z).any() else float("nan")
    q = np.full(0, np.nan) if ncc is None else np.asarray(ncc, float)
    qmed, _, qthr, _ = _tail(q, ncc_floor, k)
    qmax = float(np.nanmax(q)) if np.isfinite(q).any() else float("nan")
    return NullFigures(n, med, mad, zmax, thr, qmed, qmax, min(qthr, 1.0))


def null_pairs(prior: np.ndarray, shapes: np.ndarray, pixel_size: float, a: np.ndarray, count: int,
               far_diagonals: float, seed: int = 0, eligible: np.ndarray | None = None) -> list[tuple[int, int]]:
    """Up to ``count`` null pairs ``(i, c)``: ``i`` indexes the candidates' first frames
    ``a``, ``c`` is a frame at least ``far_diagonals`` frame diagonals from ``a[i]`` at the
    ``prior`` poses (N, 3), metres. ``shapes`` (N, 2): each frame's (H, W); ``eligible``
    (N,): the frames ``c`` may be (default all). Deterministic for a seed."""
    rng = np.random.default_rng(seed)
    if len(a) == 0 or len(prior) < 2:
        return []
    diag = np.hypot(shapes[:, 0], shapes[:, 1]) * pixel_size
    out = []
    for i in rng.permutation(len(a))[: 4 * count]:
        ai = int(a[i])
        d = np.hypot(*(prior[:, :2] - prior[ai, :2]).T)
        far = d > far_diagonals * np.maximum(diag, diag[ai])
        if eligible is not None:
            far &= eligible
        far = np.flatnonzero(far)
        if len(far):
            out.append((int(i), int(far[rng.integers(len(far))])))
        if len(out) >= count:
            break
    return out


def null_peak_z(frame, pairs: list[tuple[int, int]], rel: np.ndarray, radius_px: np.ndarray,
                pixel_size: float, p: CoarseParams) -> tuple[np.ndarray, np.ndarray]:
    """Peak significances and band-passed NCCs (:class:`pipeline.coarse.CoarseResult`) of
    the coarse stage on the null ``pairs`` (a, c), each searched with a real candidate's
    relative pose ``rel[i]`` (3,) of c in a (metres, radians) and ``radius_px[i]``;
    ``frame(g)`` returns ``(image, valid)``. NaN where nothing was searched (or, for the
    NCC, not needed)."""
    out = np.full(len(pairs), np.nan)
    q = np.full(len(pairs), np.nan)
    for i, (a, c) in enumerate(pairs):
        ia, va = frame(a)
        ic, vc = frame(c)
        b_to_a = frame_to_frame_affine(rel[i], ic.shape, ia.shape, pixel_size)
        a_to_b = np.linalg.inv(np.vstack([b_to_a, [0.0, 0.0, 1.0]]))[:2]
        r = coarse_shift(np.asarray(ia, np.float32), va, np.asarray(ic, np.float32), vc, a_to_b, float(radius_px[i]), p)
        if not isinstance(r, str):
            out[i], q[i] = r.peak_z, r.ncc
    return out, q
