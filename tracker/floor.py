"""The floor tracker (Kelly (2000), absolute mode): a pose fix of a live frame against the map.

Given a rectified live frame, a prior pose (world frame: x, y metres, theta radians) and
its 1-sigma uncertainty, :meth:`FloorTracker.fix`

1. selects up to ``n_templates`` templates (``template_px`` squares) spread over the frame,
   best texture score of their weakest gradient direction first (Kelly (2000): prequalify by
   texture; a straight edge scores 0), the score computed on the frame reduced 2x, and
   only where the map holds data around the prior (:mod:`tracker.coverage`: the edge of a
   region or corridor bundle, of a previous frame in relative mode);
2. predicts each template's place in the map from the prior (:mod:`mapstore.grid`
   conventions), cuts the map window around it, resampled into the frame's orientation and
   pixel size (one cv2.warpAffine per window from one map box), with a search radius from
   the prior's uncertainty (``search_sigmas`` sigmas of the template's predicted position,
   plus 1, clamped to [``min_radius_px``, ``max_radius_px``]);
3. finds the normalized cross-correlation peak with subpixel precision, its NCC (C1) and
   uniqueness (C1 - C2). A radius up to ``coarse_min_radius_px`` is searched at full
   resolution. A larger one (a loose prior: +-2 cm is ~36 px) is searched coarse to fine:
   the template and the map window reduced 2x (area average) give the coarse peak and the
   uniqueness (C2 at least ``exclusion_px`` / 2 reduced pixels away), then the full
   template is searched within ``fine_radius_px`` of the coarse peak for C1 and the
   subpixel position: ~0.4x the correlation time of a full-resolution search of that
   radius (bench/bench_tracker_speed.py), the same accuracy;
4. fits the rigid pose that carries the templates onto their matches (weighted least
   squares in closed form), dropping the worst template while its residual exceeds
   ``max_residual_px``; with ``refine_radius_px`` > 0 it then refines once more with the map
   windows cut at the fitted pose (this removes the bias of peak interpolation at large
   offsets);
5. returns the pose, its covariance (from the fit's residuals and geometry), quality
   figures and a status:

   - ``ok``: at least ``min_templates`` consistent templates (rigid-fit residual RMS under
     ``max_rms_px``) with NCC >= ``min_ncc`` and uniqueness >= ``min_uniqueness``;
   - ``low_texture``: fewer than ``min_templates`` templates reach ``min_texture``;
   - ``ambiguous``: the matches would be enough, but too many are not unique;
   - ``lost``: the matches disagree, fall outside the map or correlate poorly.

   Anything but ``ok`` returns the prior as the pose, never a guess.

Units: frame and map pixels as named; poses in the world (map) frame.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from mapstore.grid import MapGrid, affine_box, frame_centre, frame_pixels_to_vehicle, wrap_angle
from mapstore.knobs import knob
from tracker.correlate import match_stack, noise_sigma, peaks_of, weakest_direction_score
from tracker.coverage import coverage_mask
from tracker.params import params_from_dict
from tracker.tiles import TileCache

__all__ = ["FloorTrackerParams", "Fix", "FloorTracker", "select_templates", "template_exclusion", "half_frame",
           "fit_rigid"]

OK, LOW_TEXTURE, AMBIGUOUS, LOST = "ok", "low_texture", "ambiguous", "lost"


@dataclass(frozen=True)
class FloorTrackerParams:
    """Tracker settings (``[tracker.floor]`` in ``configs/tracker.toml`` documents each)."""

    template_px: int = knob(ge=1, default=17)
    n_templates: int = knob(ge=1, default=8)
    grid_cells: tuple[int, int] = knob(ge=1, default=(3, 4))
    min_texture: float = knob(ge=0.0, default=20.0)
    search_sigmas: float = knob(gt=0.0, default=3.0)
    min_radius_px: int = knob(ge=0, default=3)
    max_radius_px: int = knob(ge=1, default=48)
    exclusion_px: int = knob(ge=0, default=3)
    min_ncc: float = knob(ge=-1.0, le=1.0, default=0.6)
    min_uniqueness: float = knob(ge=0.0, le=2.0, default=0.2)
    min_templates: int = knob(ge=1, default=4)
    max_residual_px: float = knob(gt=0.0, default=0.75)
    max_rms_px: float = knob(gt=0.0, default=0.4)
    refine_radius_px: int = knob(ge=0, default=0)
    coarse_min_radius_px: int = knob(ge=0, default=8)
    fine_radius_px: int = knob(ge=0, default=3)
    measurement_floor_px: float = knob(gt=0.0, default=0.05)
    max_sigma_px: float = knob(gt=0.0, default=0.25)
    prefilter_noise: float = knob(ge=0.0, default=15.0)
    prefilter_sigma_px: float = knob(ge=0.0, default=1.0)

    @classmethod
    def from_dict(cls, d: dict) -> "FloorTrackerParams":
        return params_from_dict(cls, d, "tracker.floor")


@dataclass
class Fix:
    """The result of one :meth:`FloorTracker.fix`.

    ``pose``: (x, y, theta) world frame (the prior unless ``status == "ok"``); ``cov``: 3x3
    covariance of the pose (m^2, rad^2); ``status``; ``templates``: templates searched;
    ``inliers``: used in the final fit; ``rms_px``: fit residual RMS (frame pixels);
    ``ncc``, ``uniqueness``: medians over the inliers; ``correction_px``: distance from the
    prior to the fix (frame pixels); ``coverage``: the fraction of the frame's valid pixels
    where a template can search map data under the prior (1 when the map covers the whole
    footprint; a low value means the frame is mostly off the map).
    """

    pose: np.ndarray
    cov: np.ndarray
    status: str
    templates: int = 0
    inliers: int = 0
    rms_px: float = float("nan")
    ncc: float = float("nan")
    uniqueness: float = float("nan")
    correction_px: float = float("nan")
    reasons: dict = field(default_factory=dict)
    coverage: float = 1.0

    @property
    def ok(self) -> bool:
        return self.status == OK

    def to_dict(self) -> dict:
        d = asdict(self)
        d["pose"], d["cov"] = self.pose.tolist(), self.cov.tolist()
        return d


def half_frame(frame: np.ndarray) -> np.ndarray:
    """The frame reduced 2x by area averaging (odd last row / column dropped): pixel (j, i)
    averages frame pixels (2j..2j+1, 2i..2i+1), its centre at frame (2j + 0.5, 2i + 0.5)."""
    h, w = frame.shape
    return cv2.resize(frame[: h - h % 2, : w - w % 2], (w // 2, h // 2), interpolation=cv2.INTER_AREA)


def template_exclusion(valid: np.ndarray, p: FloorTrackerParams) -> np.ndarray:
    """Where a template centre may not go, on the frame reduced 2x (bool, ``(H // 2, W // 2)``):
    its ``template_px`` square would reach a pixel that ``valid`` (frame shape) marks unusable."""
    bad = cv2.dilate((~valid).astype(np.uint8), np.ones((p.template_px, p.template_px), np.uint8))
    h, w = valid.shape
    return bad[1::2, 1::2][: h // 2, : w // 2] > 0


def select_templates(frame: np.ndarray, valid: np.ndarray | None, p: FloorTrackerParams,
                     small: np.ndarray | None = None,
                     exclusion: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Template centres (N, 2) as frame (col, row) integers, their texture scores, and how
    many cells held a template over ``min_texture``. One candidate per cell of a
    ``grid_cells`` (rows, cols) partition of the frame's interior, best ``n_templates`` kept.

    The score is Kelly's (2000) texture score of the template's weakest gradient direction
    (:func:`tracker.correlate.weakest_direction_score`, full-resolution (grey levels /
    px)^2): on an isotropic texture the texture score itself, near 0 on the straight edge of
    a painted line, whose matches slide along it and are never unique. It is computed on
    the frame reduced 2x (:func:`half_frame`, passed as ``small`` when already made), a
    quarter of the work: it only ranks candidates. The cells are equal (the interior's last rows /
    columns that do not fill a cell are left out), their maxima found at once. ``exclusion``:
    :func:`template_exclusion` of ``valid`` when already made (a camera's mask is the same
    frame after frame; ``valid`` is then not read).
    """
    h, w = frame.shape
    half = p.template_px // 2
    if small is None:
        small = half_frame(frame)
    score = weakest_direction_score(small, half | 1) * np.float32(0.25)  # half-res gradients are 2x steeper
    if exclusion is None and valid is not None:
        exclusion = template_exclusion(valid, p)
    if exclusion is not None:  # a template must lie wholly on valid pixels
        score[exclusion[: score.shape[0], : score.shape[1]]] = 0.0
    nr, nc = p.grid_cells
    r0, c0, ch, cw, corner = _cells(h, w, half, nr, nc)
    cells = score[r0 : r0 + nr * ch, c0 : c0 + nc * cw].reshape(nr, ch, nc, cw).transpose(0, 2, 1, 3)
    cells = cells.reshape(nr * nc, ch * cw)
    k = cells.argmax(axis=1)
    scores_a = cells[np.arange(nr * nc), k].astype(np.float64)
    r, c = np.divmod(k, cw)
    centres_a = corner + 2.0 * np.stack([c, r], axis=1)
    good = scores_a >= p.min_texture
    order = np.argsort(-scores_a[good], kind="stable")[: p.n_templates]
    return centres_a[good][order], scores_a[good][order], int(good.sum())


@functools.lru_cache(maxsize=16)
def _cells(h: int, w: int, half: int, nr: int, nc: int) -> tuple[int, int, int, int, np.ndarray]:
    """The template cells of a frame (H, W) on the frame reduced 2x: the first cell's origin
    (r0, c0) and the cells' size (ch, cw), reduced pixels, chosen so that a template centred
    anywhere in a cell lies inside the frame (the interior's last rows / columns that do
    not fill a cell are left out); and each cell's origin in full-frame pixels (nr nc, 2)
    as (col, row), row-major over the cells (read-only: shared by every frame)."""
    r0 = c0 = (half + 1) // 2
    ch, cw = ((h - half - 1) // 2 - r0) // nr, ((w - half - 1) // 2 - c0) // nc
    ij = np.arange(nr * nc)
    corner = np.stack([2 * (c0 + (ij % nc) * cw), 2 * (r0 + (ij // nc) * ch)], axis=1).astype(float)
    corner.flags.writeable = False
    return r0, c0, ch, cw, corner


def _prefilter_reach(sigma: float) -> int:
    """Half-width (pixels) of :func:`prefilter`'s kernel for ``sigma`` (0 when no smoothing)."""
    return int(math.ceil(2.0 * sigma)) if sigma > 0 else 0


def prefilter(img: np.ndarray, sigma: float) -> np.ndarray:
    """``img`` (uint8) smoothed by a Gaussian of ``sigma`` pixels, its kernel cut at 2 sigma
    (5 taps for sigma 1: half the work of OpenCV's default 3-sigma kernel, and OpenCV's
    fixed-point path for 8-bit images); borders replicated. The frame of a noisy fix and
    the map windows it is correlated with go through this same filter."""
    k = 2 * _prefilter_reach(sigma) + 1
    return cv2.GaussianBlur(img, (k, k), sigma, borderType=cv2.BORDER_REPLICATE)


def fit_rigid(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """The rotation angle and translation (theta, t) minimizing sum w |R src + t - dst|^2
    (2-D points, closed form)."""
    if weights is None:
        theta, tx, ty = _fit_rigid_points(np.asarray(src, float).tolist(), np.asarray(dst, float).tolist())
        return theta, np.array([tx, ty])
    w = np.asarray(weights, float)
    ws = w / w.sum()
    ms, md = ws @ src, ws @ dst
    a, b = src - ms, dst - md
    (sxx, sxy), (syx, syy) = ((a * w[:, None]).T @ b).tolist()
    theta = math.atan2(sxy - syx, sxx + syy)  # sum w (a x b), sum w (a . b)
    c, s = math.cos(theta), math.sin(theta)
    m0, m1 = float(ms[0]), float(ms[1])
    t = np.array([float(md[0]) - (c * m0 - s * m1), float(md[1]) - (s * m0 + c * m1)])
    return theta, t


def _fit_rigid_points(src: list, dst: list) -> tuple[float, float, float]:
    """:func:`fit_rigid` (unweighted) of short lists of (x, y) points in plain floats:
    (theta, tx, ty)."""
    n = len(src)
    msx, msy = sum(p[0] for p in src) / n, sum(p[1] for p in src) / n
    mdx, mdy = sum(p[0] for p in dst) / n, sum(p[1] for p in dst) / n
    sxx = sxy = syx = syy = 0.0
    for (ax, ay), (bx, by) in zip(src, dst):
        ax, ay, bx, by = ax - msx, ay - msy, bx - mdx, by - mdy
        sxx += ax * bx
        sxy += ax * by
        syx += ay * bx
        syy += ay * by
    theta = math.atan2(sxy - syx, sxx + syy)
    c, s = math.cos(theta), math.sin(theta)
    return theta, mdx - (c * msx - s * msy), mdy - (s * msx + c * msy)


def _cut(img: np.ndarray, cols: np.ndarray, rows: np.ndarray, half: int) -> np.ndarray:
    """The (2 half + 1)^2 squares of ``img`` centred on integer pixels (cols, rows): (N, S, S)
    float32, one fancy-indexing gather."""
    off = np.arange(-half, half + 1)
    return img[(rows[:, None] + off)[:, :, None], (cols[:, None] + off)[:, None, :]].astype(np.float32)


def _largest_eigenvalue_2x2(a: float, b: float, d: float) -> float:
    """The larger eigenvalue of the symmetric matrix [[a, b], [b, d]] (closed form)."""
    return 0.5 * (a + d) + float(np.hypot(0.5 * (a - d), b))


def _median(x: np.ndarray) -> float:
    """The median of a small 1-D array (cheaper than np.median at this size)."""
    s = np.sort(x)
    n = len(s)
    return float("nan") if n == 0 else float(0.5 * (s[(n - 1) // 2] + s[n // 2]))


class FloorTracker:
    """Pose fixes of rectified frames against one map raster (level 0 of a bundle).

    Args:
        tiles: the map's level-0 intensity (uint8, 0 = no data) as a :class:`TileCache`.
        grid: its :class:`mapstore.grid.MapGrid`.
        frame_pixel_size: metres per pixel of the rectified live frames.
        params: :class:`FloorTrackerParams`.
    """

    def __init__(self, tiles: TileCache, grid: MapGrid, frame_pixel_size: float,
                 params: FloorTrackerParams | None = None):
        self.tiles = tiles
        self.grid = grid
        self.frame_pixel_size = float(frame_pixel_size)
        self.p = params or FloorTrackerParams()
        self._excl: tuple[np.ndarray, np.ndarray] | None = None  # (valid mask, its template_exclusion)
        self._corner_lever: dict[tuple[int, int], float] = {}  # frame shape -> largest lever (m)

    def _exclusion(self, valid: np.ndarray) -> np.ndarray:
        """:func:`template_exclusion` of ``valid``, kept while the mask stays the same (a
        camera's valid mask: one comparison, ~8 us, instead of a dilation, ~40 us)."""
        c = self._excl
        if c is None or c[0].shape != valid.shape or not np.array_equal(c[0], valid):
            c = self._excl = (valid.copy(), template_exclusion(valid, self.p))
        return c[1]

    def search_radius_px(self, sigma: np.ndarray, shape: tuple[int, int]) -> int:
        """The search radius (frame pixels) a prior 1-sigma ``sigma`` (m, m, rad) gives a
        template at the corner of a frame of ``shape`` (the worst lever), clamped to
        [``min_radius_px``, ``max_radius_px``]: the reach :meth:`fix` reads the map with."""
        lever = self._corner_lever.get(shape)
        if lever is None:  # the frame corner farthest from the centre (metres)
            h, w = shape
            xv, yv = frame_pixels_to_vehicle(np.array([0.0, w - 1.0]), np.array([0.0, h - 1.0]), shape,
                                             self.frame_pixel_size)
            lever = self._corner_lever[shape] = float(np.hypot(np.abs(xv).max(), np.abs(yv).max()))
        return self._radius(sigma, lever)

    def _radius(self, sigma: np.ndarray, lever: float) -> int:
        """The search radius (frame pixels) for the largest template lever ``lever`` (metres)
        under a prior 1-sigma ``sigma`` (m, m, rad): ``search_sigmas`` predicted 1-sigmas + 1,
        rounded up, clamped to [``min_radius_px``, ``max_radius_px``]."""
        p = self.p
        s = math.hypot(math.hypot(float(sigma[0]), float(sigma[1])), float(sigma[2]) * lever) / self.frame_pixel_size
        return int(min(max(math.ceil(p.search_sigmas * s) + 1, p.min_radius_px), p.max_radius_px))

    def prefetch(self, pose: np.ndarray, shape: tuple[int, int], margin_px: int) -> int:
        """Read into the tile cache every map tile within ``margin_px`` map pixels of the
        footprint of a frame of ``shape`` at ``pose`` (world frame); returns how many tiles
        were read (0 when all were cached: a few dictionary lookups)."""
        h, w = shape
        a = self.grid.frame_to_grid_affine(pose, shape, self.frame_pixel_size)
        u0, v0, u1, v1 = affine_box(a, 0.0, 0.0, w - 1.0, h - 1.0)
        m = int(margin_px)
        c0, r0 = math.floor(u0) - m, math.floor(v0) - m
        c1, r1 = math.ceil(u1) + m + 1, math.ceil(v1) + m + 1
        return self.tiles.warm(r0, r1, c0, c1)

    # --- map windows and the search --------------------------------------------------------

    def _map_patch(self, affine: np.ndarray, centres: np.ndarray, reach: float,
                   with_half: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, bool]:
        """The map box (uint8 grid pixels, even sides) holding every frame point within
        ``reach`` frame pixels (Chebyshev) of a template centre under ``affine`` (frame ->
        grid pixels), its 2x area reduction when ``with_half`` (a reduced pixel is 0, no
        data, when any of its four is), the box's origin (grid column, row), and whether
        the box has pixels without data (0)."""
        box = np.array([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]]) * reach
        pts = (centres[:, None, :] + box[None]).reshape(-1, 2)
        g = pts @ affine[:, :2].T + affine[:, 2]
        c0, r0 = int(np.floor(g[:, 0].min())) - 2, int(np.floor(g[:, 1].min())) - 2
        c1, r1 = int(np.ceil(g[:, 0].max())) + 3, int(np.ceil(g[:, 1].max())) + 3
        c1 += (c1 - c0) % 2
        r1 += (r1 - r0) % 2
        patch = self.tiles.window(r0, r1, c0, c1)
        small = None
        gaps = not self.tiles.full(r0, r1, c0, c1)  # (decided per tile and remembered: no scan of the box)
        if with_half:
            small = cv2.resize(patch, ((c1 - c0) // 2, (r1 - r0) // 2), interpolation=cv2.INTER_AREA)
            if gaps:
                small[np.minimum.reduce([patch[0::2, 0::2], patch[1::2, 0::2], patch[0::2, 1::2],
                                         patch[1::2, 1::2]]) == 0] = 0
        return patch, small, np.array([c0, r0], float), gaps

    def _map_windows(self, src: np.ndarray, origin: np.ndarray, affine: np.ndarray, starts: np.ndarray,
                     size: int, level: int = 0, todo: np.ndarray | None = None,
                     gaps: bool = True, blur: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The map resampled onto frame points: window i's pixel (u, v) is the frame point
        ``starts[i] + 2**level (u, v)`` (frame pixels) under ``affine`` (frame -> grid
        pixels), read from ``src``, the map box at ``origin`` (:meth:`_map_patch`) at level 0
        or its 2x reduction at level 1. (N, size, size) float32 windows (bilinear, one
        cv2.warpAffine each, the ``todo`` ones; 0 outside the map) and a mask of the windows
        holding map data everywhere (checked only when ``gaps``: ``src`` may hold 0s).

        ``blur`` > 0: each window smoothed by :func:`prefilter` of ``blur`` window pixels, as
        the frame is (a window is resampled with its margin, smoothed, cut back; a window
        with no data within the margin does not hold data everywhere). The map's own pixels
        are never smoothed: only the few thousand pixels correlated, in the frame's axes."""
        n = len(starts)
        m = _prefilter_reach(blur)
        big = size + 2 * m
        out = np.zeros((n, big, big), np.uint8)
        lin = affine[:, :2]
        t = (starts - m * 2**level) @ lin.T + affine[:, 2] - origin
        if level == 1:  # reduced pixel (a, b) has its centre at box pixel (2b + 0.5, 2a + 0.5)
            t = (t - 0.5) / 2.0
        mat = np.empty((2, 3))
        mat[:, :2] = lin
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        for i in range(n) if todo is None else np.flatnonzero(todo):
            mat[:, 2] = t[i]
            cv2.warpAffine(src, mat, (big, big), dst=out[i], flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        has_data = out.reshape(n, -1).min(axis=1) > 0 if gaps else np.ones(n, bool)
        if m:  # the windows side by side in one row (few long rows filter fastest); each keeps its own columns
            row = prefilter(np.ascontiguousarray(out.transpose(1, 0, 2)).reshape(big, n * big), blur)
            out = row.reshape(big, n, big).transpose(1, 0, 2)[:, m:m + size, m:m + size]
        if todo is not None:
            has_data &= todo
        return out.astype(np.float32), has_data

    def _search(self, frame: np.ndarray, small: np.ndarray, centres: np.ndarray, pose: np.ndarray, radius: int,
                blur: float = 0.0):
        """Match every template within ``radius`` frame pixels of its place under ``pose``.

        ``frame`` is the live frame (uint8), ``small`` its :func:`half_frame`. A radius up
        to ``coarse_min_radius_px`` is searched at full resolution; a larger one coarse to
        fine: the 2x reduced template (2 ((template_px // 2 + 1) // 2) + 1 reduced pixels,
        9 for 17) over the 2x reduced map window (radius ``radius`` / 2, rounded up), then
        the full template within ``fine_radius_px`` of the coarse peak. Returns (matched
        frame positions (N, 2), NaN without map data; NCC C1 of the full-resolution peak;
        uniqueness C1 - C2 of the search (the coarse one when coarse to fine, its exclusion
        ``exclusion_px`` halved, rounded up); usable mask: map data everywhere and the peaks
        inside their searches). ``blur``: the frame's :func:`prefilter` sigma (frame pixels;
        0: none), applied to the map windows alike (half of it at the 2x reduced level)."""
        p = self.p
        affine = self.grid.frame_to_grid_affine(pose, frame.shape, self.frame_pixel_size)
        half = p.template_px // 2
        ci, ri = centres[:, 0].astype(int), centres[:, 1].astype(int)
        full_t = _cut(frame, ci, ri, half)
        if radius <= p.coarse_min_radius_px:
            reach = half + radius
            patch, _, origin, gaps = self._map_patch(affine, centres, reach + 1 + _prefilter_reach(blur), False)
            wins, has = self._map_windows(patch, origin, affine, centres - reach, 2 * reach + 1, gaps=gaps, blur=blur)
            pk = peaks_of(match_stack(wins, full_t, has), p.exclusion_px, has)
            pos = centres + np.stack([pk.dx, pk.dy], axis=1)
            uniq, usable = pk.c1 - pk.c2, has & pk.interior
            ncc = pk.c1
        else:
            hc, rc, rf = (half + 1) // 2, -(-radius // 2), p.fine_radius_px
            reach_c = 2 * (hc + rc) + 1
            margin = max(_prefilter_reach(blur), 2 * _prefilter_reach(blur / 2))
            patch, patch2, origin, gaps = self._map_patch(affine, centres, max(reach_c, half + rf + 2 * rc) + 2 + margin,
                                                          True)
            jc, ic = ci // 2, ri // 2
            # the coarse window's pixel (u, v) is the frame point 2 (jc - hc - rc + u, ...) + 0.5
            starts_c = 2.0 * np.stack([jc, ic], axis=1) + 0.5 - 2 * (hc + rc)
            wins, has = self._map_windows(patch2, origin, affine, starts_c, 2 * (hc + rc) + 1, level=1, gaps=gaps,
                                          blur=blur / 2)
            pc = peaks_of(match_stack(wins, _cut(small, jc, ic, hc), has), -(-p.exclusion_px // 2), has)
            step = np.rint(2.0 * np.stack([pc.dx, pc.dy], axis=1))
            go = has & pc.interior
            wins_f, has_f = self._map_windows(patch, origin, affine, centres + step - (half + rf),
                                              2 * (half + rf) + 1, todo=go, gaps=gaps, blur=blur)
            pf = peaks_of(match_stack(wins_f, full_t, has_f), None, has_f)
            pos = centres + step + np.stack([pf.dx, pf.dy], axis=1)
            uniq, usable = pc.c1 - pc.c2, has_f & pf.interior
            ncc = np.where(has_f, pf.c1, -1.0)
            has = has & (has_f | ~go)
        pos[~has] = np.nan
        return pos, ncc, uniq, usable

    def _pose_from(self, centres: np.ndarray, matched: np.ndarray, pose: np.ndarray, shape: tuple[int, int],
                   keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rigid pose carrying template centres onto matches (robust: the worst residual over
        ``max_residual_px`` dropped, refitted, while more than ``min_templates`` remain);
        returns (pose, kept mask, residuals in frame pixels). Plain floats: a handful of
        points, where numpy's per-call cost would dominate."""
        fs = self.frame_pixel_size
        cx, cy = frame_centre(shape)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        px, py = float(pose[0]), float(pose[1])
        src, dst = [], []  # template centres (vehicle frame, m); matches (world frame under the prior pose)
        for (u, v), (mu, mv) in zip(centres.tolist(), matched.tolist()):
            src.append(((u - cx) * fs, (cy - v) * fs))
            mx, my = (mu - cx) * fs, (cy - mv) * fs
            dst.append((px + c * mx - s * my, py + s * mx + c * my))
        kept = keep.tolist()
        max_res, floor_n = self.p.max_residual_px, self.p.min_templates
        while True:
            theta, tx, ty = _fit_rigid_points([a for a, k in zip(src, kept) if k], [b for b, k in zip(dst, kept) if k])
            c, s = math.cos(theta), math.sin(theta)
            res = [math.hypot(c * x - s * y + tx - dx, s * x + c * y + ty - dy) / fs for (x, y), (dx, dy) in zip(src, dst)]
            worst = max((r, i) for i, (r, k) in enumerate(zip(res, kept)) if k)
            if worst[0] <= max_res or sum(kept) <= floor_n:
                break
            kept[worst[1]] = False
        return np.array([tx, ty, wrap_angle(theta)]), np.array(kept), np.array(res)

    def fix(self, frame: np.ndarray, prior: np.ndarray, prior_sigma: np.ndarray,
            valid: np.ndarray | None = None) -> Fix:
        """A pose fix of ``frame`` (uint8 rectified, (H, W)) from ``prior`` (x, y, theta)
        with 1-sigma ``prior_sigma`` (m, m, rad); ``valid`` marks usable frame pixels."""
        p = self.p
        prior = np.asarray(prior, float)
        sigma = np.asarray(prior_sigma, float)
        prior_cov = np.diag(sigma**2)
        noise = noise_sigma(frame)
        blur = 0.0
        if p.prefilter_noise > 0 and noise >= p.prefilter_noise:  # a noisy frame: average the noise down
            blur = p.prefilter_sigma_px
            frame = prefilter(frame, blur)
        small = half_frame(frame)
        # templates only where the map holds data around the prior (tracker.coverage)
        reach = self.search_radius_px(sigma, frame.shape)
        mask, covered = coverage_mask(self.tiles, self.grid, prior, frame.shape, self.frame_pixel_size,
                                      p.template_px // 2 + reach + p.fine_radius_px, valid)
        excl = self._exclusion(valid) if mask is None and valid is not None else None
        centres, _, n_textured = select_templates(frame, valid if mask is None else mask, p, small=small,
                                                  exclusion=excl)
        if len(centres) < p.min_templates:
            status, reasons = LOW_TEXTURE, {"textured": n_textured}
            if mask is not None:  # textured, but where the map has no data: off the map
                n_all = len(select_templates(frame, valid, p, small=small)[0])
                if n_all >= p.min_templates:
                    status, reasons = LOST, {"textured": n_textured, "no_map": n_all - len(centres)}
            return Fix(prior, prior_cov, status, templates=len(centres), reasons=reasons, coverage=covered)
        xv, yv = frame_pixels_to_vehicle(centres[:, 0], centres[:, 1], frame.shape, self.frame_pixel_size)
        radius = self._radius(sigma, float(np.sqrt((xv * xv + yv * yv).max())))
        matched, ncc, uniq, usable = self._search(frame, small, centres, prior, radius, blur)
        strong = usable & (ncc >= p.min_ncc)
        unique = strong & (uniq >= p.min_uniqueness)
        reasons = {"noise_grey": noise, "no_map": int(np.isnan(matched[:, 0]).sum()), "weak": int((~strong).sum()),
                   "not_unique": int((strong & ~unique).sum())}
        if unique.sum() < p.min_templates:
            status = AMBIGUOUS if strong.sum() >= p.min_templates else LOST
            return Fix(prior, prior_cov, status, templates=len(centres), reasons=reasons, coverage=covered)
        pose, keep, res = self._pose_from(centres, matched, prior, frame.shape, unique)
        # refine: windows cut at the fitted pose, small radius, same templates
        if p.refine_radius_px > 0:
            matched2, ncc2, uniq2, usable2 = self._search(frame, small, centres, pose, p.refine_radius_px, blur)
            keep2 = keep & usable2 & (ncc2 >= p.min_ncc)
        if p.refine_radius_px > 0 and keep2.sum() >= p.min_templates:
            pose, keep, res = self._pose_from(centres, matched2, pose, frame.shape, keep2)
            ncc, uniq = ncc2, uniq2
        n_in = int(keep.sum())
        rk = res[keep]
        rms = math.sqrt(float(rk @ rk) / n_in)
        reasons["outliers"] = int(unique.sum()) - n_in
        corr = float(np.hypot(*(pose[:2] - prior[:2])) / self.frame_pixel_size)
        fix = Fix(prior, prior_cov, LOST, templates=len(centres), inliers=n_in, rms_px=rms,
                  ncc=_median(ncc[keep]), uniqueness=_median(uniq[keep]),
                  correction_px=corr, reasons=reasons, coverage=covered)
        if n_in < p.min_templates or rms > p.max_rms_px:
            return fix
        cov = self._covariance(centres[keep], frame.shape, pose, rms)
        spread_px = float(np.sqrt(_largest_eigenvalue_2x2(cov[0, 0], cov[0, 1], cov[1, 1]))) / self.frame_pixel_size
        fix.reasons["sigma_px"] = spread_px
        if spread_px > p.max_sigma_px:  # templates bunched: the heading and the centre are loose
            fix.status = AMBIGUOUS
            return fix
        fix.pose, fix.status, fix.cov = pose, OK, cov
        return fix

    def _covariance(self, centres: np.ndarray, shape: tuple[int, int], pose: np.ndarray, rms_px: float) -> np.ndarray:
        """Pose covariance (m^2, rad^2) of the rigid fit: per-axis measurement variance from
        the residuals (at least ``measurement_floor_px``) through the fit's Jacobian."""
        n = len(centres)
        dof = max(2 * n - 3, 1)
        s2 = max(rms_px**2 * 2 * n / dof, self.p.measurement_floor_px**2) / 2.0 * self.frame_pixel_size**2
        xv, yv = frame_pixels_to_vehicle(centres[:, 0], centres[:, 1], shape, self.frame_pixel_size)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        # J^T J of the Jacobian rows [1, 0, a_i], [0, 1, b_i] (d position / d theta), summed in closed form
        a, b = -s * xv - c * yv, c * xv - s * yv
        sa, sb = float(a.sum()), float(b.sum())
        saa = float(a @ a + b @ b)
        # the inverse of [[n, 0, sa], [0, n, sb], [sa, sb, saa]] by its adjugate
        det = n * (n * saa - sb * sb) - sa * sa * n
        return (s2 / det) * np.array([[n * saa - sb * sb, sa * sb, -n * sa],
                                      [sa * sb, n * saa - sa * sa, -n * sb],
                                      [-n * sa, -n * sb, n * n]])
