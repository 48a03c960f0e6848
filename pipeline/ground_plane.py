"""Aerial frames' tilt and height, measured from the images: each camera against the ground plane.

An aircraft's camera is rarely nadir, and its recorded height is not exact. On the senseFly
flight ``seneca_drone`` the frames are tilted by 7.2 degrees (median) and up to 21 degrees,
and a tilted view of flat ground is a perspective (keystone) image that no rigid 2-D motion
fits: consecutive frames of that flight disagree by 8.4 px (median, native pixels) under the
best similarity, 1.4 px once each frame is turned to a nadir view with the tilt measured
here (the autopilot's recorded roll and pitch, ``attitude.csv``, left 7.2 px: they are the
aircraft's attitude, not the camera's at the exposure). The recorded heights (barometric /
GPS) then disagree with the images' relative scale by 1.3 % (median absolute deviation; 3 %
at the 90th percentile), which is 4-10 px at the edge of a 680 px frame: the relative
heights are measured here too.

Tilt. Two views of a plane are related by the homography ``H = K (R + t n^T / d) K^-1``
(Hartley and Zisserman, *Multiple View Geometry in Computer Vision*, 2nd ed. 2004, section
13.1), whose decomposition (Malis and Vargas, *Deeper understanding of the homography
decomposition for vision-based control*, INRIA RR-6303, 2007; ``cv2.decomposeHomographyMat``)
gives the plane's normal ``n`` in the first camera's frame, and with ``R`` in the second's.
Each frame is matched (SIFT, ratio test, RANSAC homography) with the next ``pair_span``
frames and its nearest neighbours by prior position; each pair leaves two physically
possible normals per frame (points in front of both cameras); a frame's normal is the mode
of its candidates (the one most others agree with within ``agree_rad``), averaged over
those that agree; a frame with one pair takes the decomposition that agrees with its
partner's normal. Frames with no normal are rectified as if nadir, counted in the report.

Height. Turned to nadir views, two frames of flat ground differ by a similarity whose scale
is the ratio of their heights. Each pair's log scale (weighted by its uncertainty from the
fit) and each frame's recorded height (``height_sigma``, relative) are combined by least
squares (conjugate gradients on the graph Laplacian; Cauchy-reweighted against pairs that
disagree): the relative heights follow the images. The overall scale comes from the prior
positions where they are GPS (the same similarity gives each pair's camera step in units of
height; the median ratio of the GPS steps to those): on ``seneca_drone`` the recorded
heights made the images' metres 13 % longer than the GPS's, a map off its georeference by
13 %. Where the positions are dead reckoning, from the records.

Frames: camera coordinates are OpenCV's (x right, y down, z along the optical axis);
:func:`nadir_rotation` gives the rotation ``R`` taking the frame's camera coordinates to a
nadir camera's (``R n = (0, 0, 1)``), the smallest such rotation, which keeps the image's
heading. Heights in metres.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.progress import Counter

__all__ = ["GroundPlaneParams", "GroundPlaneEstimate", "estimate_ground_plane", "frame_pairs", "pair_normals",
           "combine_normals", "nadir_rotation", "tilt_angle", "nadir_scale", "solve_heights", "positions_scale"]


# Homography inliers kept per pair for its height ratio.
MAX_KEPT_POINTS = 500


@dataclass(frozen=True)
class GroundPlaneParams:
    """``[ingest.ground_plane]`` (configs/floor.toml documents each knob)."""

    mode: str = "auto"
    max_side_px: int = 800
    features: int = 2000
    pair_span: int = 2
    neighbours: int = 6
    neighbour_distance: float = 0.5
    ratio: float = 0.75
    ransac_px: float = 2.0
    min_inliers: int = 40
    agree_rad: float = 0.03
    max_tilt_rad: float = 0.6
    height_sigma: float = 0.05
    scale_sigma_floor: float = 0.002
    height_scale: str = "auto"
    min_step_fraction: float = 0.2

    @classmethod
    def from_config(cls, table: dict) -> "GroundPlaneParams":
        """From the ``[ingest.ground_plane]`` table, read through its schema (every key known, typed
        and in range: :mod:`pipeline.schema`)."""
        from pipeline.schema import settings
        from pipeline.schema_floor import GroundPlaneConfig

        t = settings(GroundPlaneConfig, table)
        return cls(**{k: getattr(t, k) for k in cls.__dataclass_fields__})

    def applies(self, *, has_intrinsics: bool, has_heights: bool) -> bool:
        """Whether a log is measured: ``images`` for any camera with intrinsics,
        ``auto`` only where the frames also carry their own heights (an aircraft)."""
        if not has_intrinsics or self.mode == "none":
            return False
        return self.mode == "images" or has_heights

    def scale_from_positions(self, *, has_heights: bool) -> bool:
        """Whether the heights' overall scale comes from the prior positions (``positions``;
        ``auto``: for frames with their own heights, an aircraft whose positions are GPS)
        rather than from the recorded heights (``records``)."""
        return self.height_scale == "positions" or (self.height_scale == "auto" and has_heights)


@dataclass(frozen=True)
class GroundPlaneEstimate:
    """Per-frame tilt and height of a log.

    Attributes:
        rotations: ``(N, 3, 3)`` float64, camera -> nadir camera coordinates (identity where
            ``estimated`` is False).
        normals: ``(N, 3)`` float64, the ground's unit normal in camera coordinates
            (``(0, 0, 1)`` where not estimated).
        estimated: ``(N,)`` bool, the tilt was measured.
        support: ``(N,)`` int, candidate normals that agreed with the frame's normal.
        heights: ``(N,)`` float64 metres: the recorded heights, adjusted to the images'
            relative scale where ``heights_estimated``.
        recorded_heights: ``(N,)`` float64 metres, as given.
        heights_estimated: ``(N,)`` bool, the frame's height was measured (a pair with both
            tilts measured).
        pairs_matched: frame pairs whose homography had ``min_inliers`` inliers.
        pairs_tried: frame pairs matched.
        height_scale: the factor the positions applied to the heights (1.0 without them).
        height_scale_pairs: the pairs it is the median of (0: not applied).
    """

    rotations: np.ndarray
    normals: np.ndarray
    estimated: np.ndarray
    support: np.ndarray
    heights: np.ndarray
    recorded_heights: np.ndarray
    heights_estimated: np.ndarray
    pairs_matched: int
    pairs_tried: int
    height_scale: float = 1.0
    height_scale_pairs: int = 0

    def describe(self) -> dict:
        """Summary for the ingest report: counts, tilt angles (degrees) and the heights'
        change from the records (per cent of the height)."""
        deg = np.degrees(tilt_angle(self.normals[self.estimated]))
        he = self.heights_estimated
        change = 100.0 * np.abs(self.heights[he] / self.recorded_heights[he] - 1.0)
        return {
            "frames_estimated": int(self.estimated.sum()),
            "frames": int(self.estimated.size),
            "pairs_matched": self.pairs_matched,
            "pairs_tried": self.pairs_tried,
            "tilt_median_deg": round(float(np.median(deg)), 2) if deg.size else None,
            "tilt_max_deg": round(float(deg.max()), 2) if deg.size else None,
            "heights_estimated": int(he.sum()),
            "height_change_median_pct": round(float(np.median(change)), 2) if change.size else None,
            "height_change_max_pct": round(float(change.max()), 2) if change.size else None,
            "height_scale_from_positions": round(self.height_scale, 4) if self.height_scale_pairs else None,
            "height_scale_pairs": self.height_scale_pairs,
        }


def tilt_angle(normals: np.ndarray) -> np.ndarray:
    """Angle (radians) between each unit normal ``(..., 3)`` and the optical axis."""
    return np.arccos(np.clip(np.asarray(normals)[..., 2], -1.0, 1.0))


def nadir_rotation(normal: np.ndarray) -> np.ndarray:
    """The smallest rotation ``R`` (3 x 3) with ``R @ normal = (0, 0, 1)`` (Rodrigues)."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    v = np.cross(n, (0.0, 0.0, 1.0))
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx * ((1.0 - n[2]) / s**2)


def pair_normals(pts_a: np.ndarray, pts_b: np.ndarray, K: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The plane normals (in camera a's and camera b's coordinates) a homography allows.

    Args:
        pts_a, pts_b: ``(M, 2)`` undistorted pixel positions of the homography's inliers.
        K: ``(3, 3)`` camera matrix of both views.

    Returns:
        ``[(n_a, n_b), ...]``: the decompositions of the a -> b homography whose plane lies in
        front of both cameras for at least 90 % of the points (usually two).
    """
    H, _ = cv2.findHomography(pts_a, pts_b, 0)
    if H is None:
        return []
    _, rots, _, norms = cv2.decomposeHomographyMat(H, K)
    kinv = np.linalg.inv(K)
    ra = np.c_[pts_a, np.ones(len(pts_a))] @ kinv.T
    rb = np.c_[pts_b, np.ones(len(pts_b))] @ kinv.T
    out = []
    for r, n in zip(rots, norms):
        n_a = np.asarray(n, np.float64).ravel()
        n_a = n_a / np.linalg.norm(n_a)
        n_b = r @ n_a
        if n_a[2] <= 0 or n_b[2] <= 0:
            continue
        if np.mean(ra @ n_a > 0) < 0.9 or np.mean(rb @ n_b > 0) < 0.9:
            continue
        out.append((n_a, n_b))
    return out


def combine_normals(candidates: np.ndarray, agree_rad: float) -> tuple[np.ndarray, int]:
    """One frame's normal from its candidates ``(k, 3)``: the mode, then the mean of those
    within ``agree_rad`` of it. Returns ``(unit normal, support)``; support 0 for no candidate.
    """
    c = np.asarray(candidates, np.float64).reshape(-1, 3)
    if len(c) == 0:
        return np.array([0.0, 0.0, 1.0]), 0
    cosang = np.clip(c @ c.T, -1.0, 1.0)
    close = cosang >= np.cos(agree_rad)
    counts = close.sum(axis=1)
    best = counts.max()
    # among the candidates of largest support, the one nearest the optical axis (a tie
    # between a pair's two decompositions is broken towards the smaller tilt)
    pick = int(np.flatnonzero(counts == best)[np.argmax(c[counts == best, 2])])
    n = c[close[pick]].mean(axis=0)
    return n / np.linalg.norm(n), int(best)


def _features(img: np.ndarray, K: np.ndarray, dist: np.ndarray | None, p: GroundPlaneParams):
    """SIFT keypoints (undistorted pixel positions at full resolution) and descriptors."""
    h, w = img.shape
    s = min(1.0, p.max_side_px / max(h, w))
    small = img if s == 1.0 else cv2.resize(img, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    u8 = cv2.normalize(small, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    kp, desc = cv2.SIFT_create(p.features).detectAndCompute(u8, None)
    if desc is None or len(kp) < 4:
        return np.zeros((0, 2)), None
    pts = np.array([k.pt for k in kp], np.float64) / s
    if dist is not None and np.any(dist):
        pts = cv2.undistortPoints(pts.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
    return pts, desc


def _match(fa, fb, K: np.ndarray, p: GroundPlaneParams) -> list:
    """``[(normal candidates, inliers of a, inliers of b)]`` of a pair, or ``[]``."""
    (pa, da), (pb, db) = fa, fb
    if da is None or db is None or len(pa) < p.min_inliers or len(pb) < p.min_inliers:
        return []
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < p.ratio * m[1].distance]
    if len(good) < p.min_inliers:
        return []
    a = pa[[g.queryIdx for g in good]]
    b = pb[[g.trainIdx for g in good]]
    _, inl = cv2.findHomography(a, b, cv2.RANSAC, p.ransac_px, maxIters=2000, confidence=0.999)
    if inl is None or int(inl.sum()) < p.min_inliers:
        return []
    keep = inl.ravel().astype(bool)
    a, b = a[keep], b[keep]
    sols = pair_normals(a, b, K)
    if len(a) > MAX_KEPT_POINTS:  # enough for the pair's scale; bounded memory per pair
        pick = np.linspace(0, len(a) - 1, MAX_KEPT_POINTS).astype(np.int64)
        a, b = a[pick], b[pick]
    return [(sols, a, b)] if sols else []


def frame_pairs(positions: np.ndarray | None, n_frames: int, params: GroundPlaneParams,
                footprint_m: float | None = None) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, to match: each frame with the next ``pair_span`` frames,
    and with its ``neighbours`` nearest frames by prior position (``(N, 2)`` metres) closer
    than ``neighbour_distance`` x ``footprint_m`` (the frame's shorter ground side), which
    brings in the neighbouring flight lines."""
    pairs = {(i, j) for i in range(n_frames) for j in range(i + 1, min(n_frames, i + 1 + params.pair_span))}
    if positions is not None and footprint_m and params.neighbours > 0 and n_frames > 1:
        xy = np.asarray(positions, np.float64)[:, :2]
        k = min(params.neighbours, n_frames - 1)
        for r0 in range(0, n_frames, 512):  # blocks of rows: memory 512 x N, not N x N
            rows = np.arange(r0, min(n_frames, r0 + 512))
            d = np.hypot(xy[rows, None, 0] - xy[None, :, 0], xy[rows, None, 1] - xy[None, :, 1])
            d[np.arange(len(rows)), rows] = np.inf
            near = np.argpartition(d, k - 1, axis=1)[:, :k]
            for r, i in enumerate(rows):
                for j in near[r]:
                    if d[r, j] < params.neighbour_distance * footprint_m:
                        pairs.add((min(int(i), int(j)), max(int(i), int(j))))
    return sorted(pairs)


def _resolve(n_frames: int, pairs: list[tuple[int, int]], sols: list, agree_rad: float,
             max_tilt_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's normal from its pairs' decompositions: ``(normals (N, 3), support (N,))``,
    support 0 where none. First the frames whose candidates agree among themselves (two
    pairs, or both sides of one); then, repeatedly, a frame whose pair partner is resolved
    takes the decomposition that agrees with the partner's normal."""
    cands: list[list[np.ndarray]] = [[] for _ in range(n_frames)]
    for (i, j), ss in zip(pairs, sols):
        for n_a, n_b in ss:
            cands[i].append(n_a)
            cands[j].append(n_b)
    normals = np.tile([0.0, 0.0, 1.0], (n_frames, 1))
    support = np.zeros(n_frames, np.int64)
    for i, c in enumerate(cands):
        n, s = combine_normals(np.array(c), agree_rad)
        if s >= 2 and tilt_angle(n) <= max_tilt_rad:
            normals[i], support[i] = n, s
    cos_ok = np.cos(agree_rad)
    changed = True
    while changed:
        changed = False
        confirmed: dict[int, list[np.ndarray]] = {}
        for (i, j), ss in zip(pairs, sols):
            for me, other, mine, theirs in ((i, j, 0, 1), (j, i, 1, 0)):
                if support[me] or not support[other]:
                    continue
                for sol in ss:
                    if sol[theirs] @ normals[other] >= cos_ok:
                        confirmed.setdefault(me, []).append(sol[mine])
        for i, c in confirmed.items():
            n = np.mean(c, axis=0)
            n /= np.linalg.norm(n)
            if tilt_angle(n) <= max_tilt_rad:
                normals[i], support[i], changed = n, len(c), True
    return normals, support


def estimate_ground_plane(
    read: Callable[[int], np.ndarray | None],
    n_frames: int,
    K: np.ndarray,
    dist: np.ndarray | None,
    params: GroundPlaneParams,
    *,
    pairs: list[tuple[int, int]] | None = None,
    heights: np.ndarray | None = None,
    positions: np.ndarray | None = None,
    min_step_m: float = 0.0,
    workers: int = 1,
    quiet: bool = True,
    label: str = "tilt",
) -> GroundPlaneEstimate:
    """Each frame's tilt and height from its homographies with other frames of the log.

    Args:
        read: frame index -> raw grey image ``(H, W)`` (any float or integer scale), or None
            for a frame that cannot be used.
        n_frames: frames of the log, in capture order.
        K: ``(3, 3)`` camera matrix (raw pixels); ``dist`` OpenCV's distortion coefficients.
        pairs: the frame pairs to match (:func:`frame_pairs`); default each frame with the
            next ``pair_span``.
        heights: ``(N,)`` recorded heights (metres); default 1 (then the returned heights
            are relative).
        positions: ``(N, 2)`` the cameras' positions over the ground (metres, e.g. GPS):
            when given, the heights' overall scale comes from them (:func:`positions_scale`,
            pairs at least ``min_step_m`` apart) instead of from the records.
        workers: threads (OpenCV releases the GIL in SIFT, matching and RANSAC).
    """
    if pairs is None:
        pairs = frame_pairs(None, n_frames, params)
    # Pairs in the order of their later frame, in chunks: a frame's features (~0.25 MB) are
    # kept only until its last pair is matched, so memory follows the flight lines' length,
    # not the log's.
    order = sorted(range(len(pairs)), key=lambda k: (max(pairs[k]), min(pairs[k])))
    last_use = {}
    for pos, k in enumerate(order):
        for f in pairs[k]:
            last_use[f] = pos
    results: list = [[] for _ in pairs]
    cache: dict[int, tuple] = {}

    def feats(i: int):
        img = read(i)
        return (np.zeros((0, 2)), None) if img is None else _features(np.asarray(img, np.float32), K, dist, params)

    chunk = max(16, 8 * max(1, workers))
    with ThreadPoolExecutor(max(1, workers)) as pool, Counter(len(order), label=label, unit="pairs",
                                                              quiet=quiet) as bar:
        for start in range(0, len(order), chunk):
            ks = order[start : start + chunk]
            need = sorted({f for k in ks for f in pairs[k]} - cache.keys())
            cache.update(zip(need, pool.map(feats, need)))
            for k, r in zip(ks, pool.map(lambda k: _match(cache[pairs[k][0]], cache[pairs[k][1]], K, params), ks)):
                results[k] = r
            end = start + len(ks) - 1
            for f in [f for f in cache if last_use[f] <= end]:
                del cache[f]
            bar.advance(len(ks))
    sols = [r[0][0] if r else [] for r in results]
    normals, support = _resolve(n_frames, pairs, sols, params.agree_rad, params.max_tilt_rad)
    estimated = support > 0
    rotations = np.stack([nadir_rotation(n) for n in normals]) if n_frames else np.zeros((0, 3, 3))
    recorded = np.full(n_frames, 1.0) if heights is None else np.asarray(heights, np.float64)
    kinv = np.linalg.inv(K)
    scales, steps = [], []
    for (i, j), r in zip(pairs, results):
        if r and estimated[i] and estimated[j]:
            _, a, b = r[0]
            log_ratio, sigma, step = nadir_scale(a, b, kinv, rotations[i], rotations[j])
            scales.append((i, j, log_ratio, sigma))
            steps.append((i, j, step))
    new_h, measured = solve_heights(recorded, scales, params.height_sigma, params.scale_sigma_floor)
    factor, used = 1.0, 0
    if positions is not None:
        factor, used = positions_scale(new_h, steps, np.asarray(positions, np.float64)[:, :2], min_step_m)
        new_h = new_h * factor
    return GroundPlaneEstimate(rotations, normals, estimated, support, new_h, recorded, measured,
                               sum(bool(r) for r in results), len(pairs), factor, used)


def nadir_scale(pts_a: np.ndarray, pts_b: np.ndarray, kinv: np.ndarray, rot_a: np.ndarray,
                rot_b: np.ndarray) -> tuple[float, float, float]:
    """Two frames' nadir views compared through their matched points (pixels, undistorted):
    ``(log(h_a / h_b), its standard deviation, |C_a - C_b| / h_b)``.

    A ground point seen at nadir coordinates ``x_a = R_a^T (X - C_a) / h_a`` (``C`` the
    camera's position over the ground, ``h`` its height, ``R`` its heading) is seen at
    ``x_b = s x_a + c`` with ``|s| = h_a / h_b`` and ``|c| = |C_a - C_b| / h_b``: the
    least-squares similarity gives both; the deviation of ``log |s|`` is
    ``residual / (spread x sqrt(points))``.
    """
    def nadir(p: np.ndarray, r: np.ndarray) -> np.ndarray:
        x = np.c_[p, np.ones(len(p))] @ kinv.T @ r.T
        return x[:, 0] / x[:, 2] + 1j * x[:, 1] / x[:, 2]

    za, zb = nadir(pts_a, rot_a), nadir(pts_b, rot_b)
    ma, mb = za.mean(), zb.mean()
    za, zb = za - ma, zb - mb
    s = np.vdot(za, zb) / np.vdot(za, za).real
    spread = float(np.sqrt(np.mean(np.abs(za) ** 2)))
    resid = float(np.sqrt(np.mean(np.abs(s * za - zb) ** 2))) / abs(s)
    return float(np.log(abs(s))), resid / (spread * np.sqrt(len(za))), float(abs(mb - s * ma))


def positions_scale(heights: np.ndarray, steps: list[tuple[int, int, float]], positions: np.ndarray,
                    min_step_m: float) -> tuple[float, int]:
    """The factor that brings relative heights ``(N,)`` to the positions' metres: the median over
    pairs of ``|P_a - P_b| / (|C_a - C_b| / h_b x h_b)``, pairs ``(a, b, |C_a - C_b| / h_b)``
    whose positions ``(N, 2)`` (metres; e.g. GPS) lie at least ``min_step_m`` apart (a step
    much longer than the positions' noise). ``(1.0, 0)`` without such a pair."""
    ratios = []
    for a, b, step in steps:
        d = float(np.hypot(*(positions[a] - positions[b])))
        if d >= min_step_m and step > 0:
            ratios.append(d / (step * heights[b]))
    return (float(np.median(ratios)), len(ratios)) if ratios else (1.0, 0)


def solve_heights(recorded: np.ndarray, scales: list[tuple[int, int, float, float]], height_sigma: float,
                  scale_sigma_floor: float, *, cauchy: float = 3.0, rounds: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Heights ``(N,)`` (metres) that fit the pairs' log height ratios and the records.

    Minimizes ``sum_pairs w (y_i - y_j - m_ij)^2 + sum_frames (y_i - log h_i)^2 / height_sigma^2``
    over ``y = log(height)``, with ``w = 1 / max(sigma_ij, scale_sigma_floor)^2``
    reweighted by Cauchy's ``1 / (1 + (r / cauchy)^2)`` of the residual ``r`` in sigmas
    (a pair far off its neighbours stops pulling), by conjugate gradients (the system is the link
    graph's weighted Laplacian plus a diagonal: sparse, symmetric, positive definite).

    Args:
        recorded: ``(N,)`` recorded heights (metres, positive).
        scales: ``(i, j, log(h_i / h_j), sigma)`` per measured pair.

    Returns:
        ``(heights, measured)``: measured is True for frames in at least one pair; the
        others keep their records.
    """
    n = len(recorded)
    prior = np.log(np.asarray(recorded, np.float64))
    measured = np.zeros(n, bool)
    if not scales:
        return np.exp(prior), measured
    s = np.array(scales, np.float64)
    i, j = s[:, 0].astype(np.int64), s[:, 1].astype(np.int64)
    m = s[:, 2]
    sig = np.maximum(s[:, 3], scale_sigma_floor)
    measured[i] = measured[j] = True
    lam = 1.0 / height_sigma**2
    y = prior.copy()
    w = 1.0 / sig**2
    for _ in range(rounds):
        def apply(v: np.ndarray) -> np.ndarray:
            d = w * (v[i] - v[j])
            out = lam * v
            np.add.at(out, i, d)
            np.add.at(out, j, -d)
            return out

        rhs = lam * prior
        np.add.at(rhs, i, w * m)
        np.add.at(rhs, j, -w * m)
        y = _conjugate_gradients(apply, rhs, y)
        r = np.abs(y[i] - y[j] - m) / sig
        w = 1.0 / (1.0 + (r / cauchy) ** 2) / sig**2
    return np.exp(y), measured


def _conjugate_gradients(apply: Callable[[np.ndarray], np.ndarray], b: np.ndarray, x: np.ndarray,
                         *, tol: float = 1e-12, max_iter: int = 2000) -> np.ndarray:
    """Solve ``A x = b`` for symmetric positive definite ``A`` given as ``apply``."""
    r = b - apply(x)
    p = r.copy()
    rr = float(r @ r)
    stop = tol * float(b @ b)
    for _ in range(max_iter):
        if rr <= stop:
            break
        ap = apply(p)
        alpha = rr / float(p @ ap)
        x = x + alpha * p
        r = r - alpha * ap
        rr_new = float(r @ r)
        p = r + (rr_new / rr) * p
        rr = rr_new
    return x
