"""Priors that are wrong for a whole run: a heading off by a constant, an odometry scale error.

Sequential registrations measure each step of a log in frame a's pixels; the prior gives the
same step from its positions and its heading. Where many consecutive links agree with each
other but not with the prior, the prior is biased, not the links:

- heading: the step's direction in a's frame from the prior, ``atan2(odo)``, against the
  link's, ``atan2(link)``: their difference is minus the prior heading's error at frame a
  (the prior's frame is turned by the error, so the step looks turned back by it; a
  drone's gimbal vs body yaw, a compass off by a constant, a lane driven with the heading
  flipped by pi while the positions, from GPS, are right). A run of at least
  ``min_run_frames`` frames whose (robustly smoothed) differences stand more than
  ``heading_threshold_rad`` (and four times their own scatter) from zero is corrected, frame
  by frame, by the smoothed difference; the positions are kept. (With wheel odometry the
  step is measured in the vehicle's frame, so a drifting heading shows no difference here
  and nothing is corrected: the drift is the optimizer's to remove.)
- scale: ``|link| / |odo|`` over a log's steps, its median against 1 (wheel odometry with
  a wrong wheel radius): when it is off by more than ``scale_threshold``, the log's prior
  positions are scaled about its first frame (not for absolute priors: GPS or a stage).

Only steps longer than ``min_step_px`` count (a short step's direction is noise). Pure
functions of the frames' priors and the links; :func:`pipeline.stages.register.run_register`
retries failed sequential pairs with a wide search first (:func:`far_candidates`), so
that a flipped lane has links to show its bias.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mapstore.grid import se2_between, wrap_angle

__all__ = ["BiasParams", "PriorCorrection", "estimate_prior_correction"]


@dataclass(frozen=True)
class BiasParams:
    """``[register]`` ``prior_*`` knobs (configs/floor.toml)."""

    min_step_px: float = 8.0
    heading_threshold_rad: float = 0.05
    min_run_frames: int = 5
    smoothing_links: int = 5
    scale_threshold: float = 0.02
    min_scale_links: int = 20

    @classmethod
    def from_config(cls, reg: dict) -> "BiasParams":
        """From the ``[register]`` table (read through its schema, :mod:`pipeline.schema`)."""
        from pipeline.schema import settings
        from pipeline.schema_floor import RegisterConfig

        r = settings(RegisterConfig, reg)
        return cls(r.prior_min_step_px, r.prior_heading_threshold_rad, r.prior_min_run_frames, r.prior_smoothing_links,
                   r.prior_scale_threshold, r.prior_min_scale_links)


@dataclass
class PriorCorrection:
    """Corrected prior poses (N, 3) and what was changed (report ``registration.prior``)."""

    prior: np.ndarray
    heading_segments: list[dict] = field(default_factory=list)
    scales: list[dict] = field(default_factory=list)
    changed: np.ndarray | None = None  # (N,) frames whose prior changed

    @property
    def any(self) -> bool:
        return bool(self.heading_segments or self.scales)

    def to_dict(self) -> dict:
        return {"heading_segments": self.heading_segments, "scales": self.scales,
                "frames_corrected": int(self.changed.sum()) if self.changed is not None else 0}


def _circular_median(x: np.ndarray) -> float:
    """Median of angles: about their circular mean, wrapped (radians)."""
    m = float(np.arctan2(np.sin(x).mean(), np.cos(x).mean()))
    return float(wrap_angle(m + np.median(wrap_angle(x - m))))


def step_evidence(prior: np.ndarray, links: list, pixel_size: float, min_step_px: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per accepted link between frames of one log: ``(a, b, heading difference (rad),
    length ratio |link| / |odo|)``, for steps longer than ``min_step_px``."""
    rows = []
    for lk in links:
        if lk.status != "accepted" or not np.isfinite(lk.rel).all():
            continue
        odo = se2_between(prior[lk.a], prior[lk.b])
        lo, ll = np.hypot(odo[0], odo[1]), np.hypot(lk.rel[0], lk.rel[1])
        if min(lo, ll) < min_step_px * pixel_size:
            continue
        d = wrap_angle(np.arctan2(odo[1], odo[0]) - np.arctan2(lk.rel[1], lk.rel[0]))
        rows.append((lk.a, lk.b, float(d), float(ll / lo)))
    if not rows:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0)
    a, b, d, r = (np.array(c) for c in zip(*rows))
    return a.astype(int), b.astype(int), d, r


def estimate_prior_correction(prior: np.ndarray, log: np.ndarray, absolute: np.ndarray, links: list,
                              pixel_size: float, p: BiasParams) -> PriorCorrection:
    """The corrected prior (see the module docstring).

    Args:
        prior: (N, 3) prior poses (metres, radians), frames numbered globally, log after log.
        log: (N,) log index of each frame; ``absolute``: (N,) frames whose prior is absolute.
        links: registration links (global frame indices): only accepted links within one
            log count.
    """
    out = prior.copy()
    changed = np.zeros(len(prior), bool)
    a, b, d, ratio = step_evidence(prior, links, pixel_size, p.min_step_px)
    same = log[a] == log[b] if len(a) else np.zeros(0, bool)
    a, b, d, ratio = a[same], b[same], d[same], ratio[same]
    segments, scales = [], []
    for k in np.unique(log):
        frames_k = np.flatnonzero(log == k)
        sel = log[a] == k
        if not sel.any():
            continue
        # Heading: the frame's difference (median of its links'), smoothed over neighbours;
        # significant where it stands above the threshold and four times its own scatter.
        per: dict[int, list[float]] = {}
        for ai, bi, di in zip(a[sel], b[sel], d[sel]):
            per.setdefault(int(ai), []).append(di)
        idx = np.array(sorted(per))
        dif = np.array([_circular_median(np.array(per[i])) for i in idx])
        half = p.smoothing_links // 2
        smooth = np.zeros(len(idx))
        noise = np.zeros(len(idx))
        for j in range(len(idx)):
            w = dif[max(0, j - half) : j + half + 1]
            smooth[j] = _circular_median(w)
            noise[j] = 1.4826 * float(np.median(np.abs(wrap_angle(w - smooth[j])))) / np.sqrt(len(w))
        sig = np.abs(smooth) > np.maximum(p.heading_threshold_rad, 4.0 * noise)
        # Runs of significant frames of one sign and about one offset (a run ends where the
        # offset jumps by more than the threshold), at least min_run_frames long.
        keep = np.zeros(len(idx), bool)
        def same_offset(e: int, smooth=smooth) -> bool:
            return abs(wrap_angle(smooth[e + 1] - smooth[e])) < max(p.heading_threshold_rad, 0.25 * abs(smooth[e]))

        for j, e in _runs(sig, same_offset):
            if int(idx[e]) - int(idx[j]) + 1 >= p.min_run_frames:
                keep[j : e + 1] = True
                segments.append({"log": int(k), "first_frame": int(idx[j]), "last_frame": int(idx[e]),
                                 "offset_rad_median": round(_circular_median(smooth[j : e + 1]), 4),
                                 "offset_rad_max": round(float(np.abs(smooth[j : e + 1]).max()), 4),
                                 "links": int(e - j + 1)})
        if keep.any():
            # Every frame takes the correction of the nearest frame with evidence (0 where
            # that one is not in a kept run): a step function, so a lane's correction does
            # not leak into the turn before it.
            corr = np.where(keep, smooth, 0.0)
            near = np.clip(np.searchsorted(idx, frames_k), 0, len(idx) - 1)
            prev = np.clip(near - 1, 0, len(idx) - 1)
            pick = np.where(np.abs(idx[prev] - frames_k) <= np.abs(idx[near] - frames_k), prev, near)
            c = corr[pick]
            out[frames_k, 2] = wrap_angle(prior[frames_k, 2] + c)
            changed[frames_k] |= c != 0.0
        # Scale (odometry priors only: a wheel radius, not GPS or a stage).
        if not absolute[frames_k].any() and sel.sum() >= p.min_scale_links:
            r = ratio[sel]
            med = float(np.median(r))
            mad = float(np.median(np.abs(r - med))) * 1.4826 / np.sqrt(len(r))
            if abs(med - 1.0) > max(p.scale_threshold, 5 * mad):
                p0 = out[frames_k[0], :2].copy()
                out[frames_k, :2] = p0 + med * (out[frames_k, :2] - p0)
                changed[frames_k] = True
                scales.append({"log": int(k), "scale": round(med, 5), "links": int(sel.sum())})
    return PriorCorrection(out, segments, scales, changed)


def _runs(flag: np.ndarray, joins) -> list[tuple[int, int]]:
    """Inclusive index ranges ``(j, e)`` of consecutive True ``flag`` entries, a range going
    on from ``e`` to ``e + 1`` only where ``joins(e)``."""
    out = []
    j = 0
    while j < len(flag):
        if not flag[j]:
            j += 1
            continue
        e = j
        while e + 1 < len(flag) and flag[e + 1] and joins(e):
            e += 1
        out.append((j, e))
        j = e + 1
    return out


def failed_runs(a: np.ndarray, b: np.ndarray, ok: np.ndarray, log: np.ndarray, min_run: int) -> np.ndarray:
    """(pairs,) True for sequential pairs (a, b) that failed (``ok`` False) inside a run of at
    least ``min_run`` consecutive frames of one log whose pairs all failed: where a wide
    search is worth a try (an isolated failure is a bad frame, not a biased prior)."""
    fail_frames = np.zeros(int(max(b.max(initial=-1), a.max(initial=-1))) + 1, int)
    good = np.zeros_like(fail_frames)
    np.add.at(good, a[ok], 1)
    np.add.at(good, b[ok], 1)
    np.add.at(fail_frames, a[~ok], 1)
    bad = (fail_frames > 0) & (good == 0)
    run = np.zeros(len(bad), bool)
    for j, e in _runs(bad, lambda e: log[e + 1] == log[e]):
        if e - j + 1 >= min_run:
            run[j : e + 1] = True
    return ~ok & (run[a] | run[b])


def calibrate_models(prior: np.ndarray, log: np.ndarray, models: np.ndarray, links: list, tolerance: float,
                     min_links: int) -> list[dict]:
    """Per log, how much noisier the prior's steps are than its error model says, from the
    accepted links between its frames: ``{"log", "translation", "heading", "links"}`` with
    the factors (>= 1) by which its translation and heading sigmas must grow so that the
    links' disagreement with the prior's steps is what the model expects at its 90th
    percentile (Rayleigh 2.146 sigma for the translation, half-normal 1.645 sigma for the
    heading: the tail is what the odometry gate meets; 10 % wrong links do not move it);
    factors within ``tolerance`` count as 1. Logs with fewer than ``min_links`` links are
    left out. ``models``: (N, 5) each frame's model (:mod:`pipeline.odometry_model`)."""
    from pipeline.odometry_model import sigmas

    rows = []
    for lk in links:
        if lk.status != "accepted" or log[lk.a] != log[lk.b] or not np.isfinite(lk.rel).all():
            continue
        odo = se2_between(prior[lk.a], prior[lk.b])
        d = float(np.hypot(odo[0], odo[1]))
        st, sh = sigmas(d, models[lk.a])
        rows.append((int(log[lk.a]), float(np.hypot(*(np.asarray(lk.rel[:2]) - odo[:2]))) / max(float(st), 1e-12),
                     abs(float(wrap_angle(lk.rel[2] - odo[2]))) / max(float(sh), 1e-12)))
    out = []
    if not rows:
        return out
    k_, ut, uh = (np.array(c) for c in zip(*rows))
    for k in np.unique(k_):
        sel = k_ == k
        if sel.sum() < min_links:
            continue
        s_t = float(np.percentile(ut[sel], 90)) / 2.1460
        s_h = float(np.percentile(uh[sel], 90)) / 1.6449
        s_t = s_t if s_t > tolerance else 1.0
        s_h = s_h if s_h > tolerance else 1.0
        if s_t > 1.0 or s_h > 1.0:
            out.append({"log": int(k), "translation": round(s_t, 3), "heading": round(s_h, 3), "links": int(sel.sum())})
    return out
