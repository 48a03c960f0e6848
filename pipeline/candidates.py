"""Candidate frame pairs for registration, from the prior trajectory.

A spatial hash over frame centres finds frames whose footprints may overlap; the predicted
overlap at the prior (a lattice of frame a's footprint mapped into frame b) ranks them.
Two kinds of pairs, in two rounds:

- *sequential*: frames of one log at most ``sequential_window`` apart in the log, predicted
  from odometry;
- *revisits*: everything else (other lanes, loop closures, other logs) whose path
  distance along the log exceeds ``revisit_min_path_m``, predicted from the *chain*: dead
  reckoning along the accepted sequential links, far tighter than odometry. The best
  ``max_revisits_per_frame`` per frame by predicted overlap are kept. Progressively
  (:func:`window_revisit_candidates`, :func:`revisit_windows`): window by window along the
  path, predicted from the poses solved so far and the chain since the last frame that
  revisit links hold, so that the search radius stays a few pixels on any path length.

Each pair carries its search radius from the prior's uncertainty, as in Kelly (2000): the
error accumulated since the last good link (odometry error gradient x distance where no
link holds a step), plus a floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapstore.grid import frame_centre, se2_between
from pipeline.odometry_model import default_model, is_stage, log_model, sigmas


@dataclass
class FrameTable:
    """All frames of a build, numbered globally (log by log).

    Attributes:
        prior: (N, 3) prior poses (metres, radians) in the site frame.
        log: (N,) log index of each frame.
        path_m: (N,) distance travelled since the log's first frame (metres, from the prior).
        shapes: rectified frame shape ``(H, W)`` per log.
        pixel_size: metres per pixel of the rectified frames.
        odometry_tables: per log, its drive.toml ``[odometry]`` fields (the prior's error
            model, :mod:`pipeline.odometry_model`); None or {} = the build's defaults.
        registrable: (N,) False for frames ingest placed by the prior (too little texture
            to register: they take part in no pair); None = all.
    """

    prior: np.ndarray
    log: np.ndarray
    path_m: np.ndarray
    shapes: list[tuple[int, int]]
    pixel_size: float
    odometry_tables: list[dict] | None = None
    registrable: np.ndarray | None = None

    @classmethod
    def from_priors(cls, priors: list[np.ndarray], shapes: list[tuple[int, int]], pixel_size: float,
                    odometry_tables: list[dict] | None = None,
                    registrable: list[np.ndarray] | None = None) -> "FrameTable":
        log = np.concatenate([np.full(len(p), k) for k, p in enumerate(priors)])
        path = []
        for p in priors:
            step = np.hypot(*np.diff(p[:, :2], axis=0).T) if len(p) > 1 else np.zeros(0)
            path.append(np.concatenate([[0.0], np.cumsum(step)]))
        reg = None if registrable is None else np.concatenate([np.asarray(r, bool) for r in registrable])
        return cls(np.vstack(priors), log, np.concatenate(path), list(shapes), pixel_size, odometry_tables, reg)

    def pairable(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(pairs,) both frames registrable."""
        if self.registrable is None:
            return np.ones(len(a), bool)
        return self.registrable[a] & self.registrable[b]

    def models(self, cfg_opt: dict) -> np.ndarray:
        """(N, 5) each frame's odometry error model (its log's, :mod:`pipeline.odometry_model`)."""
        tables = self.odometry_tables or [None] * (int(self.log.max()) + 1 if len(self.log) else 0)
        per_log = np.array([log_model(cfg_opt, t) for t in tables]).reshape(-1, 5)
        if not len(per_log):
            return np.zeros((0, 5))
        return per_log[self.log]

    def revisit(self, a: np.ndarray, b: np.ndarray, cfg_reg: dict) -> np.ndarray:
        """(pairs,) pairs that count as revisits: both frames registrable, from two logs, or
        from one log more than ``sequential_window`` frames apart and farther apart along
        its path than ``revisit_min_path_m`` or ``revisit_min_path_frames`` frame widths (the
        smaller; a 256-pixel tile at 1 mm per pixel is 0.26 m wide: the tile below it in a
        grid scanned row by row is three tiles back, 0.97 m of path)."""
        same_log = self.log[a] == self.log[b]
        path_gap = np.where(same_log, np.abs(self.path_m[a] - self.path_m[b]), np.inf)
        width_m = np.array([min(s) for s in self.shapes], float).reshape(-1) * self.pixel_size
        width_m = width_m[self.log[a]] if len(width_m) else np.zeros(len(a))
        min_gap = np.minimum(cfg_reg["revisit_min_path_m"], cfg_reg["revisit_min_path_frames"] * width_m)
        pos = self.index_in_log()
        near = same_log & (np.abs(pos[a] - pos[b]) <= cfg_reg["sequential_window"])
        return (path_gap > min_gap) & ~near & self.pairable(a, b)

    def index_in_log(self) -> np.ndarray:
        """(N,) position of each frame within its log."""
        starts = np.r_[0, np.flatnonzero(np.diff(self.log)) + 1]
        idx = np.arange(len(self.log))
        return idx - np.repeat(starts, np.diff(np.r_[starts, len(self.log)]))


@dataclass
class Candidates:
    """Pairs (a < b) with their predicted overlap and search parameters.

    ``heading_known``: both frames have an absolute prior (:mod:`pipeline.odometry_model`:
    a stage) whose heading ``heading_sigma`` is held to; registration may then keep the
    prior's rotation where the overlap measures it worse.
    """

    a: np.ndarray
    b: np.ndarray
    overlap: np.ndarray
    radius_px: np.ndarray
    heading_sigma: np.ndarray
    sequential: np.ndarray
    heading_known: np.ndarray | None = None

    def __post_init__(self):
        if self.heading_known is None:
            self.heading_known = np.zeros(len(self.a), bool)

    def subset(self, keep: np.ndarray) -> "Candidates":
        """The pairs where ``keep`` (bool, per pair) is True."""
        return Candidates(self.a[keep], self.b[keep], self.overlap[keep], self.radius_px[keep],
                          self.heading_sigma[keep], self.sequential[keep], self.heading_known[keep])

    def __len__(self) -> int:
        return len(self.a)


def predicted_overlap(frames: FrameTable, a: np.ndarray, b: np.ndarray, samples: int = 9,
                      margin_m: np.ndarray | float = 0.0) -> np.ndarray:
    """Fraction of frame a's footprint that frame b covers at the prior poses, b's footprint
    grown by ``margin_m`` metres on every side (per pair or one value): with the search
    radius, pairs that may overlap although the prior puts them apart count too."""
    margin = np.broadcast_to(np.asarray(margin_m, float), (len(a),))
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
            # in chunks of pairs: the lattice is samples^2 values per pair (one round of
            # revisits over a 40 x 40 m site has ~3 million pairs: 1.9 GB per array at once)
            idx = np.flatnonzero(sel)
            for k0 in range(0, len(idx), _OVERLAP_CHUNK):
                ix = idx[k0 : k0 + _OVERLAP_CHUNK]
                rel = se2_between(frames.prior[b[ix]], frames.prior[a[ix]])  # a in b's frame
                c, s = np.cos(rel[:, 2:3]), np.sin(rel[:, 2:3])
                xb = rel[:, 0:1] + c * xv - s * yv
                yb = rel[:, 1:2] + s * xv + c * yv
                mg = margin[ix][:, None]
                inside = ((np.abs(xb) <= (wb - 1) / 2 * frames.pixel_size + mg)
                          & (np.abs(yb) <= (hb - 1) / 2 * frames.pixel_size + mg))
                out[ix] = inside.mean(axis=1)
    return out


_OVERLAP_CHUNK = 65536  # pairs per chunk of predicted_overlap (~40 MB per lattice array)


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


def odometry_sigmas(distance_m: np.ndarray | float, cfg_opt: dict,
                    model: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Dead-reckoning sigmas over ``distance_m`` metres travelled (Kelly's (2000) error gradient):
    translation ``alpha d + floor`` (metres) and heading ``h d + floor`` (radians), with the
    ``[optimize]`` defaults or a log's ``model`` ((4,) or one per distance)."""
    return sigmas(distance_m, default_model(cfg_opt) if model is None else model)


@dataclass
class ChainUncertainty:
    """Dead-reckoning uncertainty along each log, as in Kelly (2000).

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
        m = frames.models(cfg_opt)
        var_t = (m[:, 0] * step) ** 2 + m[:, 1] ** 2
        var_h = (m[:, 2] * step) ** 2 + m[:, 3] ** 2
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
        return _absolute_cap(frames, a, b, np.hypot(sig_t, sig_h * lever), sig_h, cfg_opt)


def _heading_known(frames: FrameTable, a: np.ndarray, b: np.ndarray, cfg_opt: dict) -> np.ndarray:
    """(pairs,) both frames' priors are absolute (:class:`Candidates` ``heading_known``)."""
    m = frames.models(cfg_opt)
    return (m[a, 4] > 0.5) & (m[b, 4] > 0.5) if len(a) else np.zeros(0, bool)


def _absolute_cap(frames: FrameTable, a: np.ndarray, b: np.ndarray, sig_t: np.ndarray, sig_h: np.ndarray,
                  cfg_opt: dict) -> tuple[np.ndarray, np.ndarray]:
    """Relative sigmas of frames of one log whose prior is absolute
    (:mod:`pipeline.odometry_model`) never exceed those of two of its poses."""
    m = frames.models(cfg_opt)
    ab = (m[a, 4] > 0.5) & (frames.log[a] == frames.log[b])
    if not ab.any():
        return sig_t, sig_h
    return np.where(ab, np.minimum(sig_t, m[a, 1]), sig_t), np.where(ab, np.minimum(sig_h, m[a, 3]), sig_h)


def _radius(frames: FrameTable, a, b, unc: ChainUncertainty, cfg_reg: dict, cfg_opt: dict) -> np.ndarray:
    """Search radius (pixels) of pairs (a, b): search_sigmas x their relative sigma + floor."""
    sig_t, _ = unc.relative(frames, a, b, cfg_opt)
    return cfg_reg["search_sigmas"] * sig_t / frames.pixel_size + cfg_reg["search_floor_px"]


def _finish(frames: FrameTable, a, b, ov, sequential, unc: ChainUncertainty,
            cfg_reg: dict, cfg_opt: dict) -> Candidates:
    sig_t, sig_h = unc.relative(frames, a, b, cfg_opt)
    radius = cfg_reg["search_sigmas"] * sig_t / frames.pixel_size + cfg_reg["search_floor_px"]
    return Candidates(a, b, ov, radius, sig_h, sequential, _heading_known(frames, a, b, cfg_opt))


def sequential_candidates(frames: FrameTable, cfg_reg: dict, cfg_opt: dict) -> Candidates:
    """Pairs of frames of one log at most ``sequential_window`` apart that overlap at the prior."""
    pa, pb = [], []
    for k in range(1, cfg_reg["sequential_window"] + 1):
        a = np.arange(len(frames.log) - k)
        keep = frames.log[a] == frames.log[a + k]
        pa.append(a[keep])
        pb.append(a[keep] + k)
    a, b = np.concatenate(pa), np.concatenate(pb)
    keep = frames.pairable(a, b)
    a, b = a[keep], b[keep]
    unc = ChainUncertainty.odometry(frames, cfg_opt)
    radius = _radius(frames, a, b, unc, cfg_reg, cfg_opt)
    ov = predicted_overlap(frames, a, b, margin_m=radius * frames.pixel_size)
    keep = ov >= cfg_reg["min_predicted_overlap"]
    a, b, ov = a[keep], b[keep], ov[keep]
    order = np.lexsort((b, a))
    a, b, ov = a[order], b[order], ov[order]
    return _finish(frames, a, b, ov, np.ones(len(a), bool), unc, cfg_reg, cfg_opt)


def revisit_candidates(frames: FrameTable, chain: np.ndarray, unc: ChainUncertainty, cfg_reg: dict,
                       cfg_opt: dict) -> Candidates:
    """Revisit pairs (other lanes, loops, other logs) predicted from the ``chain`` poses.

    ``chain`` (N, 3) is the trajectory after the sequential links (dead reckoning along
    registrations), ``unc`` its uncertainty; the best ``max_revisits_per_frame`` pairs per
    frame by predicted overlap are kept.
    """
    n = len(chain)
    along = FrameTable(chain, frames.log, frames.path_m, frames.shapes, frames.pixel_size, frames.odometry_tables,
                       frames.registrable)
    a, b = _neighbour_pairs(along, chain)
    far = frames.revisit(a, b, cfg_reg)
    a, b = a[far], b[far]
    ov = predicted_overlap(along, a, b, margin_m=_radius(frames, a, b, unc, cfg_reg, cfg_opt) * frames.pixel_size)
    sel = _best_per_frame(a, b, ov, n, cfg_reg)
    return _finish(frames, a[sel], b[sel], ov[sel], np.zeros(len(sel), bool), unc, cfg_reg, cfg_opt)


def _best_per_frame(a: np.ndarray, b: np.ndarray, ov: np.ndarray, n: int, cfg_reg: dict) -> np.ndarray:
    """Indices of the pairs kept: overlap >= ``min_predicted_overlap`` and at least
    ``revisit_relative_overlap`` of the best revisit overlap of either frame (a frame that
    overlaps its neighbour lane by a third is not also paired across a corner), greedily by
    overlap, at most ``max_revisits_per_frame`` per frame; sorted by (a, b)."""
    best = np.zeros(n)
    if len(a):
        np.maximum.at(best, a, ov)
        np.maximum.at(best, b, ov)
    ok = np.flatnonzero((ov >= cfg_reg["min_predicted_overlap"])
                        & (ov >= cfg_reg["revisit_relative_overlap"] * np.maximum(best[a], best[b])))
    ok = ok[np.argsort(-ov[ok], kind="stable")]
    k = cfg_reg["max_revisits_per_frame"]
    count = np.zeros(n, int)
    kept = []
    for i in ok.tolist():
        if count[a[i]] < k and count[b[i]] < k:
            kept.append(i)
            count[a[i]] += 1
            count[b[i]] += 1
    return np.array(sorted(kept, key=lambda i: (a[i], b[i])), dtype=int)


def revisit_windows(frames: FrameTable, window_m: float, cfg_opt: dict | None = None) -> list[tuple[int, int]]:
    """Consecutive frame ranges ``[s, e)`` of about ``window_m`` metres of path each; a
    window never spans two logs (global frame order, log after log). With ``cfg_opt``, a
    stage's log (:func:`pipeline.odometry_model.is_stage`) is one window: every tile's
    prior is its own, nothing drifts along its path to be held window by window."""
    out = []
    models = frames.models(cfg_opt) if cfg_opt is not None else None
    for k in np.unique(frames.log):
        idx = np.flatnonzero(frames.log == k)
        if len(idx) == 0:
            continue
        if models is not None and is_stage(models[idx[0]]):
            out.append((int(idx[0]), int(idx[-1]) + 1))
            continue
        cut = np.floor((frames.path_m[idx] - frames.path_m[idx[0]]) / max(window_m, 1e-9)).astype(int)
        starts = np.r_[0, np.flatnonzero(np.diff(cut)) + 1]
        ends = np.r_[starts[1:], len(idx)]
        out += [(int(idx[i]), int(idx[j - 1]) + 1) for i, j in zip(starts, ends)]
    return out


def _pairs_into_window(frames: FrameTable, poses: np.ndarray, s: int, e: int) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (a < b) with b in ``[s, e)``, a < e, whose centres (at ``poses``) are closer
    than one frame diagonal (metres), ordered by b, then a.

    Frames ``[0, e)`` are binned into squares of the diagonal's side, and each window frame
    is measured against the frames of its own and the 8 neighbouring squares only (two
    centres closer than a side are at most one square apart in each axis): a window costs
    a sort of the ``e`` frames' bins, not ``e`` distances per window frame (at 40 x 40 m,
    38,000 frames, the dense distances were 7 % of register and grew with the site)."""
    cell = max(np.hypot(h, w) for h, w in frames.shapes) * frames.pixel_size
    if e <= s:
        return np.zeros(0, int), np.zeros(0, int)
    xy = poses[:e, :2]
    ij = np.floor(xy / cell).astype(np.int64)
    ij -= ij.min(axis=0) - 1  # >= 1: a neighbour's bin index stays >= 0
    cols = int(ij[:, 1].max()) + 2
    key = ij[:, 0] * cols + ij[:, 1]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    bs = np.arange(s, e)
    pa, pb = [], []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            k = key[s:e] + di * cols + dj
            lo = np.searchsorted(sorted_key, k, side="left")
            n = np.searchsorted(sorted_key, k, side="right") - lo
            if not n.any():
                continue
            # every (b, a) of the bin: a = order[lo[b] + 0 .. n[b] - 1]
            starts = np.repeat(lo - np.cumsum(n) + n, n)
            a = order[np.arange(int(n.sum())) + starts]
            pa.append(a)
            pb.append(np.repeat(bs, n))
    if not pa:
        return np.zeros(0, int), np.zeros(0, int)
    a, b = np.concatenate(pa), np.concatenate(pb)
    keep = a < b
    a, b = a[keep], b[keep]
    d2 = ((poses[b, :2] - xy[a]) ** 2).sum(axis=1)
    keep = d2 < cell * cell
    a, b = a[keep], b[keep]
    o = np.lexsort((a, b))
    return a[o].astype(int), b[o].astype(int)


@dataclass
class ChainCovariance:
    """First-order uncertainty of poses dead-reckoned along the chain from a known pose.

    Per step k (frame k - 1 -> k): translation variance ``var_t[k]`` (m^2) and heading
    variance ``var_h[k]`` (rad^2). A heading error in step k swings every later frame b
    about frame k by ``|p_b - p_k|``, so the position variance of b predicted from frame
    ``r`` is ``sum_{r<k<=b} var_t[k] + var_h[k] |p_b - p_k|^2``: with running sums of
    ``var_h``, ``var_h p`` and ``var_h |p|^2`` any (r, b) costs O(1). Unlike
    :class:`ChainUncertainty`'s half-path lever, this is right when the heading error sits
    in a few odometry steps (a turn that no link holds) far from b.
    """

    cum_t: np.ndarray
    cum_h: np.ndarray
    cum_hp: np.ndarray
    cum_hpp: np.ndarray
    xy: np.ndarray
    first: np.ndarray

    @classmethod
    def from_steps(cls, frames: FrameTable, positions: np.ndarray, var_t: np.ndarray,
                   var_h: np.ndarray) -> "ChainCovariance":
        """``positions`` (N, 2) metres (the chain's); ``var_*`` (N,): step k-1 -> k (0 at log starts)."""
        start = np.r_[True, np.diff(frames.log) != 0]
        vt = np.where(start, 0.0, var_t)
        vh = np.where(start, 0.0, var_h)
        xy = positions - positions.mean(axis=0)  # small numbers: no cancellation in the sums
        starts = np.flatnonzero(start)
        return cls(np.cumsum(vt), np.cumsum(vh), np.cumsum(vh[:, None] * xy, axis=0),
                   np.cumsum(vh * (xy**2).sum(axis=1)), xy, starts[frames.log])

    def since(self, frames: FrameTable, ref: np.ndarray, b: np.ndarray, cfg_opt: dict) -> tuple[np.ndarray, np.ndarray]:
        """Sigmas (metres, radians) of frame b's pose predicted along the chain from frame
        ``ref`` (same log, ``ref <= b``), whose pose is known; ``ref = -1``: from the start
        of b's log, itself known only to the log-start sigmas (exactly for log 0: the gauge)."""
        ref = np.asarray(ref)
        b = np.asarray(b)
        r = np.where(ref < 0, self.first[b], ref)
        h0 = self.cum_h[b] - self.cum_h[r]
        h1 = self.cum_hp[b] - self.cum_hp[r]
        h2 = self.cum_hpp[b] - self.cum_hpp[r]
        pb = self.xy[b]
        var_p = (self.cum_t[b] - self.cum_t[r]) + np.maximum(
            (pb**2).sum(axis=1) * h0 - 2.0 * (pb * h1).sum(axis=1) + h2, 0.0)
        loose = (ref < 0) & (frames.log[b] != frames.log[0])
        lever = np.hypot(*(self.xy[r] - pb).T)
        sh = np.sqrt(h0) + np.where(loose, cfg_opt["log_start_sigma_rad"], 0.0)
        st = np.hypot(np.sqrt(var_p) + np.where(loose, cfg_opt["log_start_sigma_m"], 0.0),
                      np.where(loose, cfg_opt["log_start_sigma_rad"], 0.0) * lever)
        return _absolute_cap(frames, r, b, st, sh, cfg_opt)


def window_revisit_candidates(frames: FrameTable, poses: np.ndarray, s: int, e: int, held: np.ndarray,
                              cc: ChainCovariance, cfg_reg: dict, cfg_opt: dict,
                              component: np.ndarray | None = None) -> Candidates:
    """Revisit pairs whose later frame b lies in the window ``[s, e)`` (one log), predicted
    from ``poses``: frames before ``s`` as solved so far, the window's frames along the chain
    from the last solved frame.

    The search radius is the uncertainty accumulated *since the last revisit link*:
    ``held[k]`` is the last frame of log k (before ``s``) whose pose revisit links hold
    (-1: none yet, the log start's uncertainty applies). For a pair inside the window it is
    at most the chain's between the two frames. ``max_revisits_per_frame`` applies per
    window, so that a frame keeps pairs for its next lane too.

    ``component`` (N,): labels of the frames' components under the links so far
    (:func:`pipeline.links.components`). Frames of a log with an absolute prior need not be
    connected at all (a stage's tiles placed by their positions between blank tiles): a pair
    across two components is as uncertain as two prior poses, however well each is held
    (a stage's errors are systematic, shear and drift: a component placed by many tiles'
    positions is no better placed than one).
    """
    a, b = _pairs_into_window(frames, poses, s, e)
    far = frames.revisit(a, b, cfg_reg)
    a, b = a[far], b[far]
    along = FrameTable(poses, frames.log, frames.path_m, frames.shapes, frames.pixel_size, frames.odometry_tables,
                       frames.registrable)
    ref = np.full(len(b), int(held[frames.log[s]]))
    sig_t, sig_h = cc.since(frames, ref, b, cfg_opt)
    inside = a >= s
    if inside.any():
        it, ih = cc.since(frames, a[inside], b[inside], cfg_opt)
        sig_t[inside] = np.minimum(sig_t[inside], it)
        sig_h[inside] = np.minimum(sig_h[inside], ih)
    if component is not None:
        m = frames.models(cfg_opt)
        apart = (m[a, 4] > 0.5) & (frames.log[a] == frames.log[b]) & (component[a] != component[b])
        sig_t = np.where(apart, np.maximum(sig_t, m[a, 1]), sig_t)
        sig_h = np.where(apart, np.maximum(sig_h, m[a, 3]), sig_h)
    radius = cfg_reg["search_sigmas"] * sig_t / frames.pixel_size + cfg_reg["search_floor_px"]
    ov = predicted_overlap(along, a, b, margin_m=radius * frames.pixel_size)
    sel = _best_per_frame(a, b, ov, len(poses), cfg_reg)
    a, b, ov, radius, sig_h = a[sel], b[sel], ov[sel], radius[sel], sig_h[sel]
    return Candidates(a, b, ov, radius, sig_h, np.zeros(len(a), bool), _heading_known(frames, a, b, cfg_opt))
