"""The floor tracker (seed 000, absolute mode): a pose fix of a live frame against the map.

Given a rectified live frame, a prior pose (world frame: x, y metres, theta radians) and
its 1-sigma uncertainty, :meth:`FloorTracker.fix`

1. selects up to ``n_templates`` templates (``template_px`` squares) spread over the frame,
   best texture score first (seed 000: prequalify by texture);
2. predicts each template's place in the map from the prior (:mod:`mapstore.grid`
   conventions), cuts the map window around it, resampled into the frame's orientation and
   pixel size, with a search radius from the prior's uncertainty (``search_sigmas`` sigmas
   of the template's predicted position, at least ``min_radius_px``);
3. finds the normalized cross-correlation peak with subpixel precision, its NCC (C1) and
   uniqueness (C1 - C2);
4. fits the rigid pose that carries the templates onto their matches (weighted least
   squares in closed form), dropping the worst template while its residual exceeds
   ``max_residual_px``, then refines once more with the map windows cut at the fitted pose
   (this removes the bias of peak interpolation at large offsets);
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

from dataclasses import asdict, dataclass, field, fields

import cv2
import numpy as np

from mapstore.grid import MapGrid, frame_pixels_to_vehicle, se2_compose, wrap_angle
from tracker.correlate import ncc_peak, texture_score
from tracker.tiles import TileCache

__all__ = ["FloorTrackerParams", "Fix", "FloorTracker", "select_templates", "fit_rigid"]

OK, LOW_TEXTURE, AMBIGUOUS, LOST = "ok", "low_texture", "ambiguous", "lost"


@dataclass(frozen=True)
class FloorTrackerParams:
    """Tracker settings (``[tracker.floor]`` in ``configs/tracker.toml`` documents each)."""

    template_px: int = 17
    n_templates: int = 8
    grid_cells: tuple[int, int] = (3, 4)
    min_texture: float = 20.0
    search_sigmas: float = 3.0
    min_radius_px: int = 3
    max_radius_px: int = 48
    exclusion_px: int = 3
    min_ncc: float = 0.6
    min_uniqueness: float = 0.2
    min_templates: int = 4
    max_residual_px: float = 0.75
    max_rms_px: float = 0.4
    refine_radius_px: int = 0
    measurement_floor_px: float = 0.05

    @classmethod
    def from_dict(cls, d: dict) -> "FloorTrackerParams":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown tracker parameter(s): {', '.join(sorted(unknown))}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


@dataclass
class Fix:
    """The result of one :meth:`FloorTracker.fix`.

    ``pose``: (x, y, theta) world frame (the prior unless ``status == "ok"``); ``cov``: 3x3
    covariance of the pose (m^2, rad^2); ``status``; ``templates``: templates searched;
    ``inliers``: used in the final fit; ``rms_px``: fit residual RMS (frame pixels);
    ``ncc``, ``uniqueness``: medians over the inliers; ``correction_px``: distance from the
    prior to the fix (frame pixels).
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

    @property
    def ok(self) -> bool:
        return self.status == OK

    def to_dict(self) -> dict:
        d = asdict(self)
        d["pose"], d["cov"] = self.pose.tolist(), self.cov.tolist()
        return d


def select_templates(frame: np.ndarray, valid: np.ndarray | None, p: FloorTrackerParams) -> tuple[np.ndarray, np.ndarray, int]:
    """Template centres (N, 2) as frame (col, row) integers, their texture scores, and how
    many cells held a template over ``min_texture``. One candidate per cell of a
    ``grid_cells`` (rows, cols) partition of the frame's interior, best ``n_templates`` kept.

    The texture score (seed 000, in full-resolution (grey levels / px)^2) is computed on the
    frame reduced 2x (area average), a quarter of the work: it only ranks candidates.
    """
    h, w = frame.shape
    half = p.template_px // 2
    small = cv2.resize(frame, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    score = texture_score(small, half | 1) * np.float32(0.25)  # half-res gradients are 2x steeper
    if valid is not None:
        # a template must lie wholly on valid pixels
        bad = cv2.dilate((~valid).astype(np.uint8), np.ones((p.template_px, p.template_px), np.uint8))
        score[bad[1::2, 1::2][: score.shape[0], : score.shape[1]] > 0] = 0.0
    nr, nc = p.grid_cells
    # cells of the reduced frame whose centres keep the full template inside the frame
    rows = np.linspace((half + 1) // 2, (h - half - 1) // 2, nr + 1).astype(int)
    cols = np.linspace((half + 1) // 2, (w - half - 1) // 2, nc + 1).astype(int)
    centres, scores = [], []
    for i in range(nr):
        for j in range(nc):
            cell = score[rows[i] : rows[i + 1], cols[j] : cols[j + 1]]
            k = int(np.argmax(cell))
            r, c = divmod(k, cell.shape[1])
            centres.append((2 * (cols[j] + c), 2 * (rows[i] + r)))
            scores.append(float(cell[r, c]))
    centres_a, scores_a = np.array(centres, float), np.array(scores)
    good = scores_a >= p.min_texture
    order = np.argsort(-scores_a[good])[: p.n_templates]
    return centres_a[good][order], scores_a[good][order], int(good.sum())


def fit_rigid(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """The rotation angle and translation (theta, t) minimizing sum w |R src + t - dst|^2
    (2-D points, closed form)."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    ws = w / w.sum()
    ms, md = ws @ src, ws @ dst
    a, b = src - ms, dst - md
    dot = np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    cross = np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    theta = float(np.arctan2(cross, dot))
    c, s = np.cos(theta), np.sin(theta)
    t = md - np.array([c * ms[0] - s * ms[1], s * ms[0] + c * ms[1]])
    return theta, t


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

    # --- map windows and the search --------------------------------------------------------

    def _map_windows(self, affine: np.ndarray, centres: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
        """The map resampled onto the frame pixels around every template centre: (N, S, S)
        float32 windows, S = template_px + 2 ``radius``, under ``affine`` (frame -> grid
        pixels; bilinear, one cv2.remap for all), and a mask of the windows that hold map
        data everywhere."""
        h = self.p.template_px // 2 + radius
        size = 2 * h + 1
        n = len(centres)
        off = np.arange(-h, h + 1, dtype=np.float64)
        fc = centres[:, 0, None, None] + off[None, None, :]  # (N, 1, S) frame columns
        fr = centres[:, 1, None, None] + off[None, :, None]  # (N, S, 1) frame rows
        gx = affine[0, 0] * fc + affine[0, 1] * fr + affine[0, 2]
        gy = affine[1, 0] * fc + affine[1, 1] * fr + affine[1, 2]
        c0, r0 = int(np.floor(gx.min())) - 1, int(np.floor(gy.min())) - 1
        c1, r1 = int(np.ceil(gx.max())) + 2, int(np.ceil(gy.max())) + 2
        patch = self.tiles.window(r0, r1, c0, c1)
        mx = (gx - c0).astype(np.float32).reshape(n * size, size)
        my = (gy - r0).astype(np.float32).reshape(n * size, size)
        out = cv2.remap(patch, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out = out.reshape(n, size, size)
        has_data = out.reshape(n, -1).min(axis=1) > 0 if patch.min() == 0 else np.ones(n, bool)
        return out.astype(np.float32), has_data

    def _search(self, frame_f: np.ndarray, centres: np.ndarray, pose: np.ndarray, radius: int):
        """Match every template within ``radius`` pixels of its place under ``pose``;
        returns (matched frame positions (N, 2), c1, c2, usable mask)."""
        affine = self.grid.frame_to_grid_affine(pose, frame_f.shape, self.frame_pixel_size)
        half = self.p.template_px // 2
        n = len(centres)
        pos, c1, c2 = np.full((n, 2), np.nan), np.full(n, -1.0), np.full(n, -1.0)
        usable = np.zeros(n, bool)
        wins, has_data = self._map_windows(affine, centres, radius)
        for i in np.flatnonzero(has_data):
            ci, ri = int(centres[i, 0]), int(centres[i, 1])
            pk = ncc_peak(wins[i], frame_f[ri - half : ri + half + 1, ci - half : ci + half + 1], self.p.exclusion_px)
            c1[i], c2[i] = pk.c1, pk.c2
            # the template at frame (col, row) matches the map where frame pixel
            # (col + dx, row + dy) lands under the pose: the template is there in the map
            pos[i] = (ci + pk.dx, ri + pk.dy)
            usable[i] = pk.interior
        return pos, c1, c2, usable

    def _sigma_px(self, sigma: np.ndarray, centres: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """1-sigma predicted position error of each template (frame pixels)."""
        xv, yv = frame_pixels_to_vehicle(centres[:, 0], centres[:, 1], shape, self.frame_pixel_size)
        lever = np.hypot(xv, yv)
        return np.hypot(np.hypot(sigma[0], sigma[1]), sigma[2] * lever) / self.frame_pixel_size

    def _pose_from(self, centres: np.ndarray, matched: np.ndarray, pose: np.ndarray, shape: tuple[int, int],
                   keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rigid pose carrying template centres onto matches (robust); returns (pose, kept
        mask, residuals in frame pixels)."""
        affine = self.grid.frame_to_grid_affine(pose, shape, self.frame_pixel_size)
        g = matched @ affine[:, :2].T + affine[:, 2]
        wx, wy = self.grid.pixel_to_world(g[:, 0], g[:, 1])
        dst = np.column_stack([wx, wy])
        vx, vy = frame_pixels_to_vehicle(centres[:, 0], centres[:, 1], shape, self.frame_pixel_size)
        src = np.column_stack([vx, vy])
        keep = keep.copy()
        while True:
            theta, t = fit_rigid(src[keep], dst[keep])
            c, s = np.cos(theta), np.sin(theta)
            pred = src @ np.array([[c, s], [-s, c]]) + t
            res = np.hypot(*(pred - dst).T) / self.frame_pixel_size
            worst = np.argmax(np.where(keep, res, -1.0))
            if res[worst] <= self.p.max_residual_px or keep.sum() <= self.p.min_templates:
                break
            keep[worst] = False
        return np.array([t[0], t[1], wrap_angle(theta)]), keep, res

    def fix(self, frame: np.ndarray, prior: np.ndarray, prior_sigma: np.ndarray,
            valid: np.ndarray | None = None) -> Fix:
        """A pose fix of ``frame`` (uint8 rectified, (H, W)) from ``prior`` (x, y, theta)
        with 1-sigma ``prior_sigma`` (m, m, rad); ``valid`` marks usable frame pixels."""
        p = self.p
        prior = np.asarray(prior, float)
        sigma = np.asarray(prior_sigma, float)
        prior_cov = np.diag(sigma**2)
        centres, _, n_textured = select_templates(frame, valid, p)
        if len(centres) < p.min_templates:
            return Fix(prior, prior_cov, LOW_TEXTURE, templates=len(centres), reasons={"textured": n_textured})
        frame_f = frame.astype(np.float32)
        radius = int(np.clip(np.ceil(p.search_sigmas * self._sigma_px(sigma, centres, frame.shape).max()) + 1,
                             p.min_radius_px, p.max_radius_px))
        matched, c1, c2, usable = self._search(frame_f, centres, prior, radius)
        strong = usable & (c1 >= p.min_ncc)
        unique = strong & (c1 - c2 >= p.min_uniqueness)
        reasons = {"no_map": int(np.isnan(matched[:, 0]).sum()), "weak": int((~strong).sum()),
                   "not_unique": int((strong & ~unique).sum())}
        if unique.sum() < p.min_templates:
            status = AMBIGUOUS if strong.sum() >= p.min_templates else LOST
            return Fix(prior, prior_cov, status, templates=len(centres), reasons=reasons)
        pose, keep, res = self._pose_from(centres, matched, prior, frame.shape, unique)
        # refine: windows cut at the fitted pose, small radius, same templates
        if p.refine_radius_px > 0:
            matched2, c1b, c2b, usable2 = self._search(frame_f, centres, pose, p.refine_radius_px)
            keep2 = keep & usable2 & (c1b >= p.min_ncc)
        if p.refine_radius_px > 0 and keep2.sum() >= p.min_templates:
            pose, keep, res = self._pose_from(centres, matched2, pose, frame.shape, keep2)
            c1, c2 = c1b, c2b
        n_in = int(keep.sum())
        rms = float(np.sqrt(np.mean(res[keep] ** 2)))
        reasons["outliers"] = int(unique.sum()) - n_in
        corr = float(np.hypot(*(pose[:2] - prior[:2])) / self.frame_pixel_size)
        fix = Fix(prior, prior_cov, LOST, templates=len(centres), inliers=n_in, rms_px=rms,
                  ncc=float(np.median(c1[keep])), uniqueness=float(np.median((c1 - c2)[keep])),
                  correction_px=corr, reasons=reasons)
        if n_in < p.min_templates or rms > p.max_rms_px:
            return fix
        fix.pose, fix.status = pose, OK
        fix.cov = self._covariance(centres[keep], frame.shape, pose, rms)
        return fix

    def _covariance(self, centres: np.ndarray, shape: tuple[int, int], pose: np.ndarray, rms_px: float) -> np.ndarray:
        """Pose covariance (m^2, rad^2) of the rigid fit: per-axis measurement variance from
        the residuals (at least ``measurement_floor_px``) through the fit's Jacobian."""
        n = len(centres)
        dof = max(2 * n - 3, 1)
        s2 = max(rms_px**2 * 2 * n / dof, self.p.measurement_floor_px**2) / 2.0 * self.frame_pixel_size**2
        xv, yv = frame_pixels_to_vehicle(centres[:, 0], centres[:, 1], shape, self.frame_pixel_size)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        j = np.zeros((2 * n, 3))
        j[0::2, 0] = 1.0
        j[1::2, 1] = 1.0
        j[0::2, 2] = -s * xv - c * yv
        j[1::2, 2] = c * xv - s * yv
        return s2 * np.linalg.inv(j.T @ j)

    def predict(self, pose: np.ndarray, sigma: np.ndarray, odometry_delta: np.ndarray,
                error_gradient: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """Dead reckoning between fixes: ``pose ⊕ odometry_delta`` (delta in the vehicle
        frame, metres/radians) and the 1-sigma grown by ``error_gradient`` x distance
        (seed 000's error gradient) in position and heading."""
        d = float(np.hypot(odometry_delta[0], odometry_delta[1]))
        grow = np.array([error_gradient * d, error_gradient * d, error_gradient * d])
        return se2_compose(pose, odometry_delta), np.hypot(np.asarray(sigma, float), grow)
