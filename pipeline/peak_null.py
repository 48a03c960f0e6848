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

    def to_dict(self) -> dict:
        return {"pairs": self.pairs, "median_z": round(self.median_z, 2), "mad_z": round(self.mad_z, 2),
                "max_z": round(self.max_z, 2), "threshold_z": round(self.threshold_z, 2)}


def null_threshold(z: np.ndarray, floor: float, k: float) -> NullFigures:
    """``max(floor, median + k x 1.4826 MAD)`` of the null pairs' peak significances ``z``
    (``floor`` alone when there are fewer than 8)."""
    z = np.asarray(z, float)
    z = z[np.isfinite(z)]
    if len(z) < 8:
        return NullFigures(len(z), float("nan"), float("nan"), float(z.max()) if len(z) else float("nan"), float(floor))
    med = float(np.median(z))
    mad = float(np.median(np.abs(z - med)))
    return NullFigures(len(z), med, mad, float(z.max()), max(float(floor), med + k * 1.4826 * mad))


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
                pixel_size: float, p: CoarseParams) -> np.ndarray:
    """Peak significances of the coarse stage on the null ``pairs`` (a, c), each searched
    with a real candidate's relative pose ``rel[i]`` (3,) of c in a (metres, radians) and
    ``radius_px[i]``; ``frame(g)`` returns ``(image, valid)``. NaN where nothing was searched."""
    out = np.full(len(pairs), np.nan)
    for i, (a, c) in enumerate(pairs):
        ia, va = frame(a)
        ic, vc = frame(c)
        b_to_a = frame_to_frame_affine(rel[i], ic.shape, ia.shape, pixel_size)
        a_to_b = np.linalg.inv(np.vstack([b_to_a, [0.0, 0.0, 1.0]]))[:2]
        r = coarse_shift(np.asarray(ia, np.float32), va, np.asarray(ic, np.float32), vc, a_to_b, float(radius_px[i]), p)
        if not isinstance(r, str):
            out[i] = r.peak_z
    return out
