"""Candidate frame pairs for registration, from the prior trajectory.

A spatial hash over frame centres finds frames whose footprints may overlap; the predicted
overlap at the prior (a lattice of frame a's footprint mapped into frame b) ranks them.
Two kinds of pairs, in two rounds:

- *sequential*: frames of one log at most ``sequential_window`` apart in the log, predicted
  from odometry;
- *revisits*: everything else (other lanes, loop closures, other logs) whose path
  distance along the log exceeds ``revisit_min_path_m``, predicted from the *chain*: dead
  reckoning along the accepted sequential links, far tighter than odometry. The best
  ``max_revisits_per_frame`` per frame by predicted overlap are kept.

Each pair carries its search radius from the prior's uncertainty, as in seed 000: the
error accumulated since the last good link (odometry error gradient x distance where no
link holds a step), plus a floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapstore.grid import frame_centre, se2_between


@dataclass
class FrameTable:
    """All frames of a build, numbered globally (log by log).

    Attributes:
        prior: (N, 3) prior poses (metres, radians) in the site frame.
        log: (N,) log index of each frame.
        path_m: (N,) distance travelled since the log's first frame (metres, from the prior).
        shapes: rectified frame shape ``(H, W)`` per log.
        pixel_size: metres per pixel of the rectified frames.
    """

    prior: np.ndarray
    log: np.ndarray
    path_m: np.ndarray
    shapes: list[tuple[int, int]]
    pixel_size: float

    @classmethod
    def from_priors(cls, priors: list[np.ndarray], shapes: list[tuple[int, int]], pixel_size: float) -> "FrameTable":
        log = np.concatenate([np.full(len(p), k) for k, p in enumerate(priors)])
        path = []
        for p in priors:
            step = np.hypot(*np.diff(p[:, :2], axis=0).T) if len(p) > 1 else np.zeros(0)
            path.append(np.concatenate([[0.0], np.cumsum(step)]))
        return cls(np.vstack(priors), log, np.concatenate(path), list(shapes), pixel_size)

    def index_in_log(self) -> np.ndarray:
        """(N,) position of each frame within its log."""
        starts = np.r_[0, np.flatnonzero(np.diff(self.log)) + 1]
        idx = np.arange(len(self.log))
        return idx - np.repeat(starts, np.diff(np.r_[starts, len(self.log)]))


@dataclass
class Candidates:
    """Pairs (a < b) with their predicted overlap and search parameters."""

    a: np.ndarray
    b: np.ndarray
    overlap: np.ndarray
    radius_px: np.ndarray
    heading_sigma: np.ndarray
    sequential: np.ndarray

    def __len__(self) -> int:
        return len(self.a)


def predicted_overlap(frames: FrameTable, a: np.ndarray, b: np.ndarray, samples: int = 9) -> np.ndarray:
    """Fraction of frame a's footprint that frame b covers at the prior poses."""
    out = np.zeros(len(a))
    for la in np.unique(frames.log[a]):
        for lb in np.unique(frames.log[b]):
            sel = (frames.log[a] == la) & (frames.log[b] == lb)
            if not sel.any():
                continue
            ha, wa = frames.shapes[la]
            hb, wb = frames.shapes[lb]
            cxa, cya = frame_centre((ha, wa))
            cxb, cyb = frame_centre((hb, wb))
            gy, gx = np.meshgrid(np.linspace(0, ha - 1, samples), np.linspace(0, wa - 1, samples), indexing="ij")
            # Lattice in a's vehicle frame (metres), then into b's vehicle frame.
            xv = (gx.ravel() - cxa) * frames.pixel_size
            yv = -(gy.ravel() - cya) * frames.pixel_size
            rel = se2_between(frames.prior[b[sel]], frames.prior[a[sel]])  # a in b's frame
            c, s = np.cos(rel[:, 2:3]), np.sin(rel[:, 2:3])
            xb = rel[:, 0:1] + c * xv - s * yv
            yb = rel[:, 1:2] + s * xv + c * yv
            inside = (np.abs(xb) <= (wb - 1) / 2 * frames.pixel_size) & (np.abs(yb) <= (hb - 1) / 2 * frames.pixel_size)
            out[sel] = inside.mean(axis=1)
    return out


def _neighbour_pairs(frames: FrameTable, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (a < b) whose centres are closer than one frame diagonal (spatial hash)."""
    n = len(prior)
    cell = max(np.hypot(h, w) for h, w in frames.shapes) * frames.pixel_size
    keys = np.floor(prior[:, :2] / cell).astype(np.int64)
    order = np.lexsort((keys[:, 1], keys[:, 0]))
    sk = keys[order]
    bounds = np.r_[0, np.flatnonzero(np.any(np.diff(sk, axis=0) != 0, axis=1)) + 1, n]
    buckets = {(int(sk[i0, 0]), int(sk[i0, 1])): order[i0:i1] for i0, i1 in zip(bounds[:-1], bounds[1:])}
    pa, pb = [np.zeros(0, int)], [np.zeros(0, int)]
    for (kx, ky), members in buckets.items():
        near = [buckets.get((kx + dx, ky + dy)) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
        others = np.concatenate([m for m in near if m is not None])
        aa = np.repeat(members, len(others))
        bb = np.tile(others, len(members))
        keep = aa < bb
        pa.append(aa[keep])
        pb.append(bb[keep])
    a, b = np.concatenate(pa), np.concatenate(pb)
    close = np.hypot(*(prior[a, :2] - prior[b, :2]).T) < cell
    return a[close], b[close]


def odometry_sigmas(distance_m: np.ndarray | float, cfg_opt: dict) -> tuple[np.ndarray, np.ndarray]:
    """Dead-reckoning sigmas over ``distance_m`` metres travelled (seed 000's error gradient):
    translation ``alpha d + floor`` (metres) and heading ``h d + floor`` (radians)."""
    d = np.asarray(distance_m, dtype=float)
    return (
        cfg_opt["odometry_error_gradient"] * d + cfg_opt["odometry_sigma_floor_m"],
        cfg_opt["odometry_heading_sigma_per_m"] * d + cfg_opt["odometry_heading_sigma_floor_rad"],
    )


@dataclass
class ChainUncertainty:
    """Dead-reckoning uncertainty along each log, as in seed 000.

    Per step between consecutive frames: the variance of the step (``step_var_t`` in m^2,
    ``step_var_h`` in rad^2): tiny where a registration link holds the step, the odometry's
    (error gradient x step length)^2 elsewhere. The uncertainty of the relative pose of
    two frames of one log is what accumulates between them; across logs the logs' start
    uncertainty is added.
    """

    cum_var_t: np.ndarray
    cum_var_h: np.ndarray

    @classmethod
    def from_steps(cls, frames: FrameTable, step_var_t: np.ndarray, step_var_h: np.ndarray) -> "ChainUncertainty":
        """``step_*`` (N,): variance of the step from frame k-1 to frame k (0 at a log's start)."""
        vt = np.where(np.r_[True, np.diff(frames.log) != 0], 0.0, step_var_t)
        vh = np.where(np.r_[True, np.diff(frames.log) != 0], 0.0, step_var_h)
        return cls(np.cumsum(vt), np.cumsum(vh))

    @classmethod
    def odometry(cls, frames: FrameTable, cfg_opt: dict) -> "ChainUncertainty":
        step = np.r_[0.0, np.abs(np.diff(frames.path_m))]
        var_t = (cfg_opt["odometry_error_gradient"] * step) ** 2 + cfg_opt["odometry_sigma_floor_m"] ** 2
        var_h = (cfg_opt["odometry_heading_sigma_per_m"] * step) ** 2 + cfg_opt["odometry_heading_sigma_floor_rad"] ** 2
        return cls.from_steps(frames, var_t, var_h)

    def relative(self, frames: FrameTable, a: np.ndarray, b: np.ndarray, cfg_opt: dict) -> tuple[np.ndarray, np.ndarray]:
        """Sigmas (metres, radians) of the relative pose of frames a and b."""
        same = frames.log[a] == frames.log[b]
        var_t = np.where(same, np.abs(self.cum_var_t[b] - self.cum_var_t[a]), self.cum_var_t[a] + self.cum_var_t[b])
        var_h = np.where(same, np.abs(self.cum_var_h[b] - self.cum_var_h[a]), self.cum_var_h[a] + self.cum_var_h[b])
        sig_h = np.sqrt(var_h) + np.where(same, 0.0, cfg_opt["log_start_sigma_rad"])
        sig_t = np.sqrt(var_t) + np.where(same, 0.0, cfg_opt["log_start_sigma_m"])
        # A heading error also moves the far frame: lever arm = half the path between them
        # (the heading error of a random walk accumulates along it).
        lever = np.where(same, np.abs(frames.path_m[a] - frames.path_m[b]) / 2.0,
                         np.hypot(*(frames.prior[a, :2] - frames.prior[b, :2]).T))
        return np.hypot(sig_t, sig_h * lever), sig_h


def _finish(frames: FrameTable, a, b, ov, sequential, unc: ChainUncertainty,
            cfg_reg: dict, cfg_opt: dict) -> Candidates:
    sig_t, sig_h = unc.relative(frames, a, b, cfg_opt)
    radius = cfg_reg["search_sigmas"] * sig_t / frames.pixel_size + cfg_reg["search_floor_px"]
    return Candidates(a, b, ov, radius, sig_h, sequential)


def sequential_candidates(frames: FrameTable, cfg_reg: dict, cfg_opt: dict) -> Candidates:
    """Pairs of frames of one log at most ``sequential_window`` apart that overlap at the prior."""
    pa, pb = [], []
    for k in range(1, cfg_reg["sequential_window"] + 1):
        a = np.arange(len(frames.log) - k)
        keep = frames.log[a] == frames.log[a + k]
        pa.append(a[keep])
        pb.append(a[keep] + k)
    a, b = np.concatenate(pa), np.concatenate(pb)
    ov = predicted_overlap(frames, a, b)
    keep = ov >= cfg_reg["min_predicted_overlap"]
    a, b, ov = a[keep], b[keep], ov[keep]
    order = np.lexsort((b, a))
    a, b, ov = a[order], b[order], ov[order]
    return _finish(frames, a, b, ov, np.ones(len(a), bool), ChainUncertainty.odometry(frames, cfg_opt),
                   cfg_reg, cfg_opt)


def revisit_candidates(frames: FrameTable, chain: np.ndarray, unc: ChainUncertainty, cfg_reg: dict,
                       cfg_opt: dict) -> Candidates:
    """Revisit pairs (other lanes, loops, other logs) predicted from the ``chain`` poses.

    ``chain`` (N, 3) is the trajectory after the sequential links (dead reckoning along
    registrations), ``unc`` its uncertainty; the best ``max_revisits_per_frame`` pairs per
    frame by predicted overlap are kept.
    """
    n = len(chain)
    along = FrameTable(chain, frames.log, frames.path_m, frames.shapes, frames.pixel_size)
    a, b = _neighbour_pairs(along, chain)
    same_log = frames.log[a] == frames.log[b]
    path_gap = np.where(same_log, np.abs(frames.path_m[a] - frames.path_m[b]), np.inf)
    pos = frames.index_in_log()
    far = (path_gap > cfg_reg["revisit_min_path_m"]) & ~(same_log & (np.abs(pos[a] - pos[b]) <= cfg_reg["sequential_window"]))
    a, b = a[far], b[far]
    ov = predicted_overlap(along, a, b)
    ok = np.flatnonzero(ov >= cfg_reg["min_predicted_overlap"])
    ok = ok[np.argsort(-ov[ok], kind="stable")]
    k = cfg_reg["max_revisits_per_frame"]
    count = np.zeros(n, int)
    kept = []
    for i in ok.tolist():
        if count[a[i]] < k and count[b[i]] < k:
            kept.append(i)
            count[a[i]] += 1
            count[b[i]] += 1
    sel = np.array(sorted(kept, key=lambda i: (a[i], b[i])), dtype=int)
    return _finish(frames, a[sel], b[sel], ov[sel], np.zeros(len(sel), bool), unc, cfg_reg, cfg_opt)
